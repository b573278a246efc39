"""The Dirichlet-process Gaussian mixture (IGMM) over y = [θ, w] and its Gibbs samplers.

* ``DPSampler`` — one sampler object: Neal's (2000) Algorithm 8 (the paper's Algorithm 1)
  with fresh or re-used auxiliary components, or the slice sampler; eq. 6's reward weighting.
* ``DPMixtureState`` — one state of the chain (labels, component parameters, H).
* ``labels`` — eq. 5/6's label logits; ``neal8``,
  ``reuse``, ``slice`` — the label passes;
  ``conditionals`` — the μ and Σ conditionals and the point estimate;
  ``reward_weights`` — r_c of eq. 6.

All DP mathematics runs in float64 (``dipole_torch.gaussian.DTYPE``).
"""

from dipole_torch.dp.conditionals import posterior_point_estimate, resample_parameters
from dipole_torch.dp.reward_weights import RewardRegression, reward_weights
from dipole_torch.dp.sampler import DPNumericalError, DPSampler
from dipole_torch.dp.slice import SliceChain
from dipole_torch.dp.state import DPMixtureState, sequential_labels

__all__ = [
    "DPMixtureState",
    "DPNumericalError",
    "DPSampler",
    "RewardRegression",
    "SliceChain",
    "posterior_point_estimate",
    "resample_parameters",
    "reward_weights",
    "sequential_labels",
]

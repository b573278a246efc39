"""dipole-torch: DIPOLE (Dirichlet-process policy learning) in PyTorch and Pyro."""

from dipole_torch.dp_mixture import (
    DPMixture,
    DPMixtureState,
    fit_dp_mixture,
    neal8_sweep,
    reward_weights,
)
from dipole_torch.gaussian_mixture import GaussianMixture
from dipole_torch.mcmc import Neal8Kernel
from dipole_torch.optimizer import Dipole, PolicySearch, Power
from dipole_torch.power import importance_sets, power_update
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.pyro_model import InverseWishart, dp_log_joint, dp_mixture_model
from dipole_torch.reward import RewardScale
from dipole_torch.sampling import draw

__all__ = [
    "DPMixture",
    "DPMixtureState",
    "Dipole",
    "GaussianMixture",
    "InverseWishart",
    "Neal8Kernel",
    "NormalInverseWishartPrior",
    "PolicySearch",
    "Power",
    "RewardScale",
    "dp_log_joint",
    "dp_mixture_model",
    "draw",
    "fit_dp_mixture",
    "importance_sets",
    "neal8_sweep",
    "power_update",
    "reward_weights",
]
__version__ = "0.1.0"

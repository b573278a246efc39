"""dipole-torch: DIPOLE (Dirichlet-process policy learning) in PyTorch and Pyro."""

from pathlib import Path

from dipole_torch.dp_mixture import (
    DPMixture,
    DPMixtureState,
    fit_dp_mixture,
    neal8_sweep,
    reward_weights,
)
from dipole_torch.gaussian_mixture import GaussianMixture
from dipole_torch.mcmc import Neal8Kernel, SliceKernel
from dipole_torch.optimizer import Dipole, PolicySearch, Power
from dipole_torch.power import importance_sets, power_update
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.pyro_model import InverseWishart, dp_log_joint, dp_mixture_model
from dipole_torch.reward import RewardScale
from dipole_torch.sampling import draw
from dipole_torch.slice_sampler import SliceChain, slice_sweep

# The application around the library is dipole_torch.models, dipole_torch.tasks,
# dipole_torch.configs and dipole_torch.train. A wheel installs them inside this package
# (pyproject.toml maps the repository's top-level models/, tasks/, configs/ and train.py
# there). In the source tree they stay at the top, next to this folder: searching the
# repository root too makes the same names resolve there, whether or not (or how) the
# project is installed in editable mode. Only there: an installed package holds tasks/.
_root = Path(__file__).resolve().parent.parent
if not (Path(__file__).parent / "tasks").is_dir() and (_root / "tasks" / "__init__.py").is_file():
    __path__.append(str(_root))
del _root

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
    "SliceChain",
    "SliceKernel",
    "dp_log_joint",
    "dp_mixture_model",
    "draw",
    "fit_dp_mixture",
    "importance_sets",
    "neal8_sweep",
    "power_update",
    "reward_weights",
    "slice_sweep",
]
__version__ = "0.1.0"

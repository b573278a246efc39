"""dipole-torch: DIPOLE (Dirichlet-process policy learning) in PyTorch and Pyro.

The optimizers (``Dipole``, ``Power``), the DP mixture and its samplers
(``DPSampler``, ``DPMixtureState``), the Gaussian mixture of the policies
(``GaussianMixture``, a Pyro distribution) and the Pyro side (``DPMixtureKernel``,
``dp_mixture_model``, ``InverseWishart``). Those four are imported on first use, so
that ``import dipole_torch`` and an optimizer's iterations do not import Pyro.
"""

from importlib import import_module
from pathlib import Path

from dipole_torch.dipole import Dipole
from dipole_torch.dp import (
    DPMixtureState,
    DPNumericalError,
    DPSampler,
    SliceChain,
    reward_weights,
)
from dipole_torch.options import DipoleOptions
from dipole_torch.power import importance_sets, power_update
from dipole_torch.power_optimizer import Power
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.result import SearchResult
from dipole_torch.reward import RewardScale
from dipole_torch.sampling import draw
from dipole_torch.search import PolicySearch

# The Pyro side, imported when first used (benchmarks/bench_startup.py measures the import).
_LAZY = {
    "GaussianMixture": "dipole_torch.gaussian_mixture",
    "DPMixtureKernel": "dipole_torch.mcmc",
    "InverseWishart": "dipole_torch.pyro_model",
    "dp_log_joint": "dipole_torch.pyro_model",
    "dp_mixture_model": "dipole_torch.pyro_model",
}


def __getattr__(name: str):
    if name in _LAZY:
        value = getattr(import_module(_LAZY[name]), name)
        globals()[name] = value
        return value
    raise AttributeError(f"module 'dipole_torch' has no attribute {name!r}")


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
    "DPMixtureKernel",
    "DPMixtureState",
    "DPNumericalError",
    "DPSampler",
    "Dipole",
    "DipoleOptions",
    "GaussianMixture",
    "InverseWishart",
    "NormalInverseWishartPrior",
    "PolicySearch",
    "Power",
    "RewardScale",
    "SearchResult",
    "SliceChain",
    "dp_log_joint",
    "dp_mixture_model",
    "draw",
    "importance_sets",
    "power_update",
    "reward_weights",
]
__version__ = "0.2.0"

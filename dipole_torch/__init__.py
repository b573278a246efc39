"""dipole-torch: DIPOLE (Dirichlet-process policy learning) in PyTorch and Pyro."""

from dipole_torch.gaussian_mixture import GaussianMixture
from dipole_torch.random import draw

__all__ = ["GaussianMixture", "draw"]
__version__ = "0.1.0"

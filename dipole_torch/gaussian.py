"""Gaussian helpers shared by the DP mixture, its prior and the optimizers: log densities from
Cholesky factors, symmetric positive-definite inverses, and draws given a precision.

No distribution objects: at DIPOLE's sizes (a few points, D ≈ 10) their construction
(broadcasting, validation) costs more than the arithmetic. All DP mathematics runs in float64
(``DTYPE``): with D ≈ 10 and a few points per component, float32 Cholesky factors of the
sampled covariances lose positive definiteness.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dipole_torch.sampling import _expand

DTYPE = torch.float64
LOG_2PI = math.log(2.0 * math.pi)

__all__ = [
    "DTYPE",
    "LOG_2PI",
    "gaussian_log_prob",
    "log_prob_tril",
    "mahalanobis",
    "symmetric",
]


def symmetric(matrix: Tensor) -> Tensor:
    """``[..., D, D]`` ½ (A + Aᵀ): removes the rounding asymmetry of products and inverses."""
    return 0.5 * (matrix + matrix.transpose(-1, -2))


def mahalanobis(tril: Tensor, diff: Tensor) -> Tensor:
    """``[K, P]`` the lengths of ``diff: [K, P, D]`` under L_k L_kᵀ, ``tril: [K, D, D]``
    (row k under factor k; one triangular solve per factor)."""
    z = torch.linalg.solve_triangular(tril, diff.transpose(-1, -2), upper=False)
    return z.square().sum(-2).sqrt()


def log_prob_tril(value: Tensor, mean: Tensor | float, tril: Tensor) -> Tensor:
    """``[*lead, *batch]`` log N(value; mean, L Lᵀ) from the Cholesky factors
    ``tril: [*batch, D, D]``, for ``value - mean: [*lead, *batch, D]`` (broadcast).

    The leading dims go into the columns of one triangular solve per factor, so the factors
    are never copied per point (an expanded ``[N, K, D, D]`` would take gigabytes).
    ``mean = 0.0`` takes ``value`` as already centred.
    """
    # (x − 0.0 is x, bit for bit: centred queries skip the subtraction.)
    diff = value if isinstance(mean, float) and mean == 0.0 else value - mean
    d = diff.shape[-1]
    nb = tril.dim() - 2
    if diff.dim() - 1 < nb:
        diff = diff.expand(*tril.shape[:-2], d)
    lead = diff.shape[: diff.dim() - 1 - nb]
    inner = tuple(
        b if a == 1 else a for a, b in zip(diff.shape[len(lead) : -1], tril.shape[:-2], strict=True)
    )
    tril = _expand(tril, (*inner, d, d))
    size = math.prod(lead)
    diff = _expand(diff, (*lead, *inner, d))
    rhs = diff.reshape(size, *inner, d).movedim(0, -1)
    z = torch.linalg.solve_triangular(tril, rhs, upper=False)  # [*inner, D, size]
    mahalanobis = z.square().sum(-2).movedim(-1, 0).reshape(*lead, *inner)
    log_det = tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    return -0.5 * (mahalanobis + d * LOG_2PI) - log_det


def gaussian_log_prob(value: Tensor, means: Tensor, covariances: Tensor) -> Tensor:
    """``[...]`` log N(value; means, covariances), broadcast as ``log_prob_tril``."""
    return log_prob_tril(value, means, torch.linalg.cholesky(covariances))

"""Input checks shared by the library: each error names the argument and what is wrong."""

from __future__ import annotations

import torch
from torch import Tensor


def check_positive_definite(matrix: Tensor, name: str) -> None:
    """Raise ``ValueError`` unless ``matrix: [..., D, D]`` is symmetric positive definite."""
    if matrix.dim() < 2 or matrix.shape[-1] != matrix.shape[-2]:
        raise ValueError(f"{name} must be square matrices [..., D, D], got {list(matrix.shape)}")
    if not torch.isfinite(matrix).all():
        raise ValueError(f"{name} contains non-finite values")
    scale = matrix.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1e-300)[..., None, None]
    asym = (matrix - matrix.transpose(-1, -2)).abs() / scale
    if (asym > 1e-6).any():
        raise ValueError(f"{name} is not symmetric")
    _, info = torch.linalg.cholesky_ex(matrix)
    if (info != 0).any():
        raise ValueError(f"{name} is not positive definite (Cholesky failed)")


def check_matrix_shape(tensor: Tensor, shape: tuple[int, ...], name: str) -> None:
    """Raise ``ValueError`` unless ``tensor.shape == shape``; -1 in ``shape`` matches any size."""
    if not isinstance(tensor, Tensor):
        raise TypeError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
    ok = tensor.dim() == len(shape) and all(
        s in (-1, t) for s, t in zip(shape, tensor.shape, strict=False)
    )
    if not ok:
        want = ", ".join("N" if s == -1 else str(s) for s in shape)
        raise ValueError(f"{name} must have shape [{want}], got {list(tensor.shape)}")


def check_finite(tensor: Tensor, name: str) -> None:
    """Raise ``ValueError`` if ``tensor`` holds NaN or inf, naming the first bad index."""
    bad = ~torch.isfinite(tensor)
    if bad.any():
        first = tuple(int(i) for i in bad.nonzero()[0])
        raise ValueError(f"{name} contains non-finite values (first at index {first})")

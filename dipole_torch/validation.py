"""Input checks shared by the library: each error names the argument and what is wrong."""

from __future__ import annotations

import math

import numpy as np
import torch
from torch import Tensor


def _check_symmetric(matrix: Tensor, name: str) -> Tensor:
    """Raise ``ValueError`` unless ``matrix: [..., D, D]`` is square, finite and symmetric
    (to 1e-6 of its largest variance); returns that largest variance ``[...]``."""
    if matrix.dim() < 2 or matrix.shape[-1] != matrix.shape[-2]:
        raise ValueError(f"{name} must be square matrices [..., D, D], got {list(matrix.shape)}")
    if not torch.isfinite(matrix).all():
        raise ValueError(f"{name} contains non-finite values")
    scale = matrix.diagonal(dim1=-2, dim2=-1).abs().amax(-1).clamp_min(1e-300)
    asym = (matrix - matrix.transpose(-1, -2)).abs() / scale[..., None, None]
    if (asym > 1e-6).any():
        raise ValueError(f"{name} is not symmetric")
    return scale


def check_positive_definite(matrix: Tensor, name: str) -> None:
    """Raise ``ValueError`` unless ``matrix: [..., D, D]`` is symmetric positive definite."""
    _check_symmetric(matrix, name)
    _, info = torch.linalg.cholesky_ex(matrix)
    if (info != 0).any():
        raise ValueError(f"{name} is not positive definite (Cholesky failed)")


def check_positive_semidefinite(matrix: Tensor, name: str, tolerance: float = 1e-9) -> None:
    """Raise ``ValueError`` unless ``matrix: [..., D, D]`` is finite, symmetric and positive
    semi-definite: no eigenvalue below ``-tolerance`` times the matrix's largest variance.

    For covariances a run itself may leave singular: an exploration shrunk to rank one, or
    to zero, by rounding (the optimizer samples no policy whose covariance does not
    factorise), which a checkpoint must restore as it was."""
    scale = _check_symmetric(matrix, name)
    symmetric = (matrix + matrix.transpose(-1, -2)) / 2
    if (torch.linalg.eigvalsh(symmetric).amin(-1) < -tolerance * scale).any():
        raise ValueError(f"{name} is not positive semi-definite (a negative eigenvalue)")


# The smallest eigenvalue of a correlation matrix that float64 factorisations of matrices
# drawn around it still survive (a covariance this close to singular, once an inverse-Wishart
# draw adds its own spread, loses positive definiteness to rounding).
MIN_CORRELATION_EIGENVALUE = 1e-10


def check_well_conditioned(matrix: Tensor, name: str) -> None:
    """Raise ``ValueError`` unless the positive definite ``matrix: [D, D]`` is far enough from
    singular for float64: the eigenvalues of its correlation matrix (scale-free, so that
    coordinates in any units pass) at least ``MIN_CORRELATION_EIGENVALUE``."""
    std = matrix.diagonal().sqrt()
    smallest = float(torch.linalg.eigvalsh(matrix / std[:, None] / std[None, :]).amin())
    if not smallest >= MIN_CORRELATION_EIGENVALUE:
        raise ValueError(
            f"{name} is too close to singular for float64 (its correlation matrix's smallest "
            f"eigenvalue is {smallest:.3g}, below {MIN_CORRELATION_EIGENVALUE:g}): some "
            "coordinates are (nearly) linear combinations of the others; widen it or add a "
            "regularisation"
        )


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
    """Raise ``ValueError`` if ``tensor`` holds NaN or inf, naming the first bad index, is
    complex (casting to a real dtype would silently drop the imaginary part) or is a meta
    tensor (a shape without values)."""
    if tensor.device.type == "meta":
        raise ValueError(f"{name} is a meta tensor (no values): give it on a real device")
    if tensor.is_complex():
        raise ValueError(f"{name} must be real numbers, got dtype {tensor.dtype}")
    if not bool(torch.isfinite(tensor).all()):
        first = tuple(int(i) for i in (~torch.isfinite(tensor)).nonzero()[0])
        raise ValueError(f"{name} contains non-finite values (first at index {first})")


def check_real_tensor(tensor: Tensor, name: str) -> None:
    """Raise ``TypeError`` unless ``tensor`` is a floating-point ``torch.Tensor``.

    Integer and bool tensors are refused, not converted: an integer θ0 would make every
    asked θ an integer (truncated) and a bool one all ``True``, and a silent conversion
    hides a mistake in the caller. Pass ``theta0.double()`` (or ``.float()``) instead.
    """
    if not isinstance(tensor, Tensor) or not tensor.is_floating_point():
        raise TypeError(
            f"{name} must be a floating-point torch.Tensor (integer and bool tensors are "
            f"refused, not converted), got {getattr(tensor, 'dtype', type(tensor).__name__)}"
        )


def check_count(value, name: str, minimum: int = 1, optional: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is a whole number ``>= minimum`` (``None`` too
    when ``optional``); bools, strings, NaN and inf are refused."""
    if optional and value is None:
        return
    number = isinstance(value, int | float | np.integer | np.floating) and not isinstance(
        value, bool
    )
    if not (number and math.isfinite(value) and int(value) == value and value >= minimum):
        kind = "a positive integer" if minimum == 1 else f"an integer >= {minimum}"
        raise ValueError(f"{name} must be {kind}{' or None' if optional else ''}, got {value!r}")


def check_real(value, name: str, optional: bool = False) -> None:
    """Raise ``ValueError`` unless ``value`` is a real number (not a bool or a string);
    range checks are the caller's."""
    if optional and value is None:
        return
    if not isinstance(value, int | float | np.integer | np.floating) or isinstance(value, bool):
        raise ValueError(f"{name} must be a real number, got {value!r}")


def check_positive_finite(value, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is a real number (``check_real``) in (0, ∞),
    e.g. a DP concentration α: α = ∞ gives no valid CRP weights, α ≤ 0 a NaN log joint."""
    check_real(value, name)
    if not 0 < value < math.inf:
        raise ValueError(f"{name} must be a positive finite number, got {value!r}")


def check_generator(generator, name: str = "generator") -> None:
    """Raise ``TypeError`` unless ``generator`` is ``None`` or a ``torch.Generator`` (on any
    device: the library draws its seeds on the generator's own device)."""
    if generator is not None and not isinstance(generator, torch.Generator):
        raise TypeError(f"{name} must be a torch.Generator or None, got {type(generator).__name__}")


def check_choice(value, choices: tuple, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is one of ``choices`` (compared by equality, so
    a bool or a number never matches a string choice)."""
    if not any(type(value) is type(choice) and value == choice for choice in choices):
        listed = [repr(choice) for choice in choices]
        alternatives = (
            listed[0] if len(listed) == 1 else f"{', '.join(listed[:-1])} or {listed[-1]}"
        )
        raise ValueError(f"{name} must be {alternatives}, got {value!r}")


def check_flag(value, name: str) -> None:
    """Raise ``ValueError`` unless ``value`` is a bool (``"no"`` or ``0`` is refused, not
    taken as a truth value)."""
    if not isinstance(value, bool | np.bool_):
        raise ValueError(f"{name} must be True or False, got {value!r}")

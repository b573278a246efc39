"""What an optimizer accepts as θ0, Σ_start and bounds, turned into float64 tensors."""

from __future__ import annotations

import numbers

import numpy as np
import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE
from dipole_torch.validation import (
    check_finite,
    check_matrix_shape,
    check_positive_definite,
    check_real_tensor,
)

__all__ = [
    "Bounds",
    "SigmaStart",
    "Theta0",
    "as_covariance",
    "as_theta0",
    "check_asked",
    "check_in_box",
    "into_box",
    "make_box",
    "told_as_asked",
]

Bounds = tuple[float | list[float] | Tensor, float | list[float] | Tensor] | None
# θ0: a [D] tensor, list or numpy array.
Theta0 = Tensor | list[float] | np.ndarray
# Σ_start: one std (a number), [D] stds or a [D, D] covariance (tensor, list or numpy array).
SigmaStart = float | Tensor | list[float] | list[list[float]] | np.ndarray


def as_theta0(theta0) -> Tensor:
    """``theta0`` as a ``[D]`` floating tensor: a tensor as it is (its dtype and device are
    the optimizer's), a list or a numpy array of numbers as float64 on the CPU (a numpy
    float32 array stays float32). Integer and bool tensors are refused, not converted (a
    silent cast would hide a mistake: an integer θ0 truncated every ask)."""
    if isinstance(theta0, list | tuple):
        if not all(_is_number(v) for v in theta0):
            odd = next(v for v in theta0 if not _is_number(v))
            raise TypeError(
                f"theta0 as a list must be [D] real numbers, got an element {odd!r} "
                f"({type(odd).__name__})"
            )
        theta0 = torch.tensor([float(v) for v in theta0], dtype=DTYPE)
    elif isinstance(theta0, np.ndarray) and theta0.dtype.kind in "iuf":
        floating = theta0.dtype if theta0.dtype.kind == "f" else np.float64
        theta0 = torch.from_numpy(np.array(theta0, dtype=floating))
    elif not isinstance(theta0, Tensor):
        # A number too: Dipole(0.0, 1.0) reads as one parameter, but is more often a slip.
        one = f" (one parameter: [{theta0!r}])" if _is_number(theta0) else ""
        raise TypeError(
            f"theta0 must be [D] parameters (a list, a numpy array or a [D] tensor), got "
            f"{theta0!r} ({type(theta0).__name__}){one}"
        )
    check_real_tensor(theta0, "theta0")
    if theta0.dim() != 1:
        raise ValueError(f"theta0 must have shape [D] (D parameters), got {list(theta0.shape)}")
    check_finite(theta0, "theta0")
    if theta0.shape[0] < 1:
        raise ValueError("theta0 must have at least one parameter, got shape [0]")
    return theta0.detach()


def as_covariance(sigma_start, theta0: Tensor) -> Tensor:
    """Σ_start ``[D, D]`` in float64 on ``theta0``'s device, from one std σ (a number or a
    0-d tensor: σ² I), ``[D]`` per-coordinate stds (diag(σ²)), or a ``[D, D]`` covariance,
    each a tensor, a list or a numpy array (as pycma's ``sigma0`` and its per-coordinate
    stds)."""
    d = theta0.shape[0]
    if _is_number(sigma_start):
        sigma_start = torch.tensor(float(sigma_start), dtype=DTYPE)
    elif isinstance(sigma_start, list | tuple | np.ndarray):
        try:
            sigma_start = torch.as_tensor(np.asarray(sigma_start, dtype=np.float64))
        except (TypeError, ValueError):
            raise TypeError(
                f"sigma_start must be a number, [D] stds or a [D, D] covariance, got "
                f"{sigma_start!r}"
            ) from None
    check_real_tensor(sigma_start, "sigma_start")
    check_finite(sigma_start, "sigma_start")
    # A copy: the caller editing its tensor afterwards leaves Σ_start be.
    sigma = sigma_start.detach().to(device=theta0.device, dtype=DTYPE, copy=True)
    if sigma.dim() < 2:
        if sigma.dim() == 1 and sigma.shape[0] != d:
            raise ValueError(
                f"sigma_start must have shape [{d}, {d}] (a covariance), [{d}] (stds) or [] "
                f"(one std), got {list(sigma.shape)}"
            )
        if bool((sigma <= 0).any()):
            raise ValueError(f"sigma_start's stds must be positive, got {sigma.tolist()}")
        return _in_range(torch.diag_embed(sigma.square().expand(d)))
    if sigma.shape != (d, d):
        raise ValueError(
            f"sigma_start must have shape [{d}, {d}] (a covariance), [{d}] (stds) or [] "
            f"(one std), got {list(sigma.shape)}"
        )
    check_positive_definite(sigma, "sigma_start")
    return _in_range(sigma)


# Σ_start's variances: within float64's range with room for the products the DP prior and
# the factorisations form (a std of 1e154 squares to 1e308, and its prior overflows; one of
# 1e-155 to a subnormal that no Cholesky survives).
VARIANCE_RANGE = (1e-300, 1e300)


def _in_range(covariance: Tensor) -> Tensor:
    """``covariance`` if its variances lie in ``VARIANCE_RANGE``."""
    variances = covariance.diagonal()
    low, high = VARIANCE_RANGE
    if not bool(((variances >= low) & (variances <= high)).all()):
        raise ValueError(
            f"sigma_start's variances must lie between {low:g} and {high:g} (stds between "
            f"{low**0.5:g} and {high**0.5:g}), got {float(variances.min()):.3g} to "
            f"{float(variances.max()):.3g}: express θ in units closer to 1"
        )
    return covariance


def make_box(bounds: Bounds, theta0: Tensor) -> tuple[Tensor, Tensor] | None:
    """``(lower [D], upper [D])`` in float64 on ``theta0``'s device from ``bounds`` =
    ``(lower, upper)``, each a number, a list of D numbers, a numpy array or a ``[D]``
    tensor (±inf: that side is open), or ``None`` (no box). Raises ``ValueError`` unless
    lower < upper on every axis and θ0 lies inside."""
    if bounds is None:
        return None
    try:
        low, high = bounds
    except (TypeError, ValueError):
        raise ValueError(f"bounds must be None or (lower, upper), got {bounds!r}") from None
    d = theta0.shape[0]
    box = []
    for name, value in (("lower", low), ("upper", high)):
        if isinstance(value, np.ndarray) and value.dtype.kind in "iuf":  # as θ0 takes them
            value = torch.as_tensor(value.astype(np.float64))
        numbers_ = isinstance(value, list | tuple) and all(_is_number(v) for v in value)
        if isinstance(value, bool) or not (isinstance(value, int | float | Tensor) or numbers_):
            raise TypeError(
                f"bounds' {name} must be a number, a list of D numbers, a numpy array or a [D] "
                f"tensor, got {value!r}"
            )
        edge = torch.as_tensor(value, dtype=DTYPE, device=theta0.device)
        if edge.dim() == 0:
            edge = edge.expand(d)
        check_matrix_shape(edge, (d,), f"bounds' {name}")
        if bool(edge.isnan().any()):
            raise ValueError(f"bounds' {name} contains NaN")
        box.append(edge.clone())
    lower, upper = box
    if not bool((lower < upper).all()):
        axis = int((lower >= upper).nonzero()[0])
        raise ValueError(
            f"bounds must have lower < upper on every axis; axis {axis} has "
            f"[{float(lower[axis])}, {float(upper[axis])}]"
        )
    theta = theta0.to(DTYPE)
    outside = (theta < lower) | (theta > upper)
    if bool(outside.any()):
        axis = int(outside.nonzero()[0])
        raise ValueError(
            f"theta0 must lie inside bounds; axis {axis}: {float(theta[axis])} is outside "
            f"[{float(lower[axis])}, {float(upper[axis])}]"
        )
    return lower, upper


def into_box(box: tuple[Tensor, Tensor] | None, theta: Tensor) -> Tensor:
    """``theta [..., D]`` projected onto ``box`` (``(lower [D], upper [D])``); unchanged
    without one."""
    if box is None:
        return theta
    return torch.minimum(torch.maximum(theta, box[0]), box[1])


def check_in_box(box: tuple[Tensor, Tensor] | None, theta: Tensor) -> None:
    """Raise ``ValueError`` naming the first row of ``theta [B, D]`` outside ``box``
    (compared in the told dtype, so an asked row rounded to float32 still counts as inside)."""
    if box is None:
        return
    lower, upper = (edge.to(device=theta.device, dtype=theta.dtype) for edge in box)
    outside = (theta < lower) | (theta > upper)
    if bool(outside.any()):
        row, axis = (int(i) for i in outside.nonzero()[0])
        raise ValueError(
            f"theta row {row} lies outside bounds on axis {axis}: "
            f"{float(theta[row, axis])} not in [{float(lower[axis])}, {float(upper[axis])}]"
        )


def _compared(asked: Tensor, theta: Tensor, dtype: torch.dtype) -> tuple[Tensor, Tensor]:
    """The first B rows of ``asked`` and ``theta [B, D]`` in the narrower of the told dtype
    and the dtype the rows were handed out in, ``dtype``: a float32 row told back as float64,
    or a float64 row told as float32, is the row asked."""
    narrower = theta.dtype if torch.finfo(theta.dtype).eps >= torch.finfo(dtype).eps else dtype
    theta = theta.detach()
    asked = asked[: theta.shape[0]].to(device=theta.device, dtype=narrower)
    return asked, theta.to(narrower)


def told_as_asked(asked: Tensor, theta: Tensor, dtype: torch.dtype | None = None) -> bool:
    """Whether ``theta [B, D]`` is exactly the first B rows of ``asked [B', D]``, handed out
    in ``dtype`` (default: the told dtype), compared in the narrower dtype of the two (an
    asked row cast to float32 is the same row). Rows told as asked lie in the box as the
    asked ones do (rounding keeps the order of the box's edges), so ``check_in_box`` need not
    look at them."""
    return torch.equal(*_compared(asked, theta, theta.dtype if dtype is None else dtype))


def check_asked(asked: Tensor, theta: Tensor, dtype: torch.dtype | None = None) -> None:
    """Raise ``ValueError`` naming the first told row of ``theta [B, D]`` that is not the
    asked one, ``asked [B', D]``, B ≤ B', handed out in ``dtype`` (compared as in
    ``told_as_asked``: an asked row cast to float32 and back is the same row)."""
    if told_as_asked(asked, theta, dtype):  # the usual case, in one comparison
        return
    asked, theta = _compared(asked, theta, theta.dtype if dtype is None else dtype)
    different = (asked != theta).any(-1)
    if bool(different.any()):
        row = int(different.nonzero()[0])
        gap = float((asked[row] - theta[row]).abs().max())
        raise ValueError(
            f"theta row {row} is not the row asked (it differs by up to {gap:g}): tell() "
            "takes the rows of the last ask as asked (a new point is asked, not told; to keep "
            "θ in a box, clipped or within limits, give the optimizer bounds=(lower, upper): "
            "it asks inside them)"
        )


def _is_number(value) -> bool:
    return isinstance(value, numbers.Real) and not isinstance(value, bool | np.bool_)

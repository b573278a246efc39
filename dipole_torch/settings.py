"""What an optimizer was built with, compared: ``load_state_dict`` refuses a state saved by
an optimizer built with other settings (``PolicySearch._settings``) and names them."""

from __future__ import annotations

import math

import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE

__all__ = ["SETTINGS_RTOL", "setting_differences"]

# Settings saved as tensors may differ in their last bits between devices and engines (a
# task's θ0 computed by forward kinematics on another device): they match to this relative
# tolerance. Any other setting must be equal.
SETTINGS_RTOL = 1e-6


# Settings kept in another form than given: Σ_start is given as one std, stds or a covariance.
LABELS = {"sigma_start": "sigma_start (as a covariance)"}


def setting_differences(saved: dict, own: dict) -> list[str]:
    """``"name: <saved> saved, <own> here"`` for each setting of both whose values differ
    (tensors: in shape, or beyond ``SETTINGS_RTOL`` of their largest magnitude). A setting
    that one of them lacks is not compared: the state is from a version before that option
    existed or after it was removed (``train.py``'s resume checks the config's keys)."""

    def same(a, b) -> bool:
        if not (isinstance(a, Tensor) or isinstance(b, Tensor)):
            return a == b
        if not (isinstance(a, Tensor) and isinstance(b, Tensor)) or a.shape != b.shape:
            return False
        a, b = a.detach().cpu().to(DTYPE), b.detach().cpu().to(DTYPE)
        finite = a.isfinite()
        if not torch.equal(finite, b.isfinite()) or not torch.equal(a[~finite], b[~finite]):
            return False  # (±inf sides of a box must be equal)
        if not bool(finite.any()):
            return True
        scale = float(torch.cat((a[finite], b[finite])).abs().amax())
        return bool(((a[finite] - b[finite]).abs() <= SETTINGS_RTOL * scale).all())

    def shown(value) -> str:
        if isinstance(value, Tensor):
            small = value.numel() <= 4
            return str(value.tolist()) if small else f"a tensor of shape {list(value.shape)}"
        return repr(value)

    def difference(key: str, a, b) -> str:
        key = LABELS.get(key, key)
        large = isinstance(a, Tensor) and isinstance(b, Tensor) and a.numel() > 4
        if not (large and a.shape == b.shape):
            return f"{key}: {shown(a)} saved, {shown(b)} here"
        # Too large to show whole: where the two differ most (a non-finite gap first).
        a, b = a.detach().cpu().to(DTYPE), b.detach().cpu().to(DTYPE)
        gap = (a - b).abs().nan_to_num(nan=math.inf)
        gap[(a == b) | (a.isnan() & b.isnan())] = 0.0  # (equal infinities do not differ)
        at = tuple(int(i) for i in torch.unravel_index(gap.argmax(), gap.shape))
        return (
            f"{key}: [{', '.join(map(str, a.shape))}] tensors that differ most at "
            f"{list(at)}: {float(a[at]):g} saved, {float(b[at]):g} here"
        )

    return [
        difference(key, saved[key], own[key])
        for key in saved
        if key in own and not same(saved[key], own[key])
    ]

"""Mapping returns to the positive weights that PoWER (eq. 7) and eq. 6 need."""

from __future__ import annotations

import torch
from torch import Tensor

from dipole_torch.validation import check_finite


class RewardScale:
    """Affine map of returns in ``[low, high]`` onto weights in ``[floor, 1]``.

    PoWER averages samples weighted by their returns and eq. 6 multiplies component
    probabilities by r_c, so both need positive numbers. The paper's returns are not all
    positive (cart-pole's lie in [−1000, 1000]) and it does not say how it made them so; we use
    w = max((r − low) / (high − low), floor), the transform that keeps PoWER's update
    (a weighted average) invariant to the units of the return. ``floor`` keeps a return at the
    bottom of the range from zeroing a component's weight in eq. 6.

    With ``low = high = None`` returns are used as they are and must be positive.

    Args:
        low: lowest possible return, or ``None``.
        high: highest possible return (> low), or ``None``.
        floor: smallest weight, in (0, 1).
    """

    def __init__(self, low: float | None = None, high: float | None = None, floor: float = 1e-3):
        if (low is None) != (high is None):
            raise ValueError("reward_range needs both low and high, or neither")
        if low is not None and not float(high) > float(low):
            raise ValueError(f"reward_range must have high > low, got ({low}, {high})")
        if not 0.0 < floor < 1.0:
            raise ValueError(f"floor must lie in (0, 1), got {floor}")
        self.low = None if low is None else float(low)
        self.high = None if high is None else float(high)
        self.floor = float(floor)

    def __call__(self, rewards: Tensor) -> Tensor:
        """``[...]`` weights of ``rewards: [...]``; raises on values outside the range."""
        self.validate(rewards)
        return self.weights(rewards)

    def validate(self, rewards: Tensor) -> None:
        """Raise ``ValueError`` on non-finite rewards, or rewards this scale cannot map."""
        check_finite(rewards, "rewards")
        if self.low is None:
            if (rewards <= 0).any():
                raise ValueError(
                    "rewards must be positive when no reward_range is given (PoWER and eq. 6 "
                    f"weight by them); got min {float(rewards.min()):g}. Pass reward_range="
                    "(low, high) to map them to [floor, 1]."
                )
            return
        slack = 1e-9 * (self.high - self.low)
        if (rewards < self.low - slack).any() or (rewards > self.high + slack).any():
            raise ValueError(
                f"rewards outside reward_range ({self.low:g}, {self.high:g}): "
                f"min {float(rewards.min()):g}, max {float(rewards.max()):g}"
            )

    def weights(self, rewards: Tensor) -> Tensor:
        """The map itself, for rewards already validated (e.g. the ones an optimizer kept)."""
        if self.low is None:
            return rewards
        return ((rewards - self.low) / (self.high - self.low)).clamp(self.floor, 1.0)

    def inverse(self, weights: Tensor) -> Tensor:
        """Returns corresponding to ``weights`` (the floor is not undone)."""
        if self.low is None:
            return weights
        return self.low + weights * (self.high - self.low)

    @property
    def slope(self) -> float:
        """d(return)/d(weight)."""
        return 1.0 if self.low is None else self.high - self.low


def check_rewards(rewards: Tensor, batch: int) -> Tensor:
    """Validate ``rewards: [B]`` against the batch size; return them as float64."""
    if not isinstance(rewards, Tensor):
        rewards = torch.as_tensor(rewards)
    if rewards.shape != (batch,):
        raise ValueError(
            f"rewards must have shape [{batch}] (one per asked θ), got {list(rewards.shape)}"
        )
    check_finite(rewards, "rewards")
    return rewards.to(torch.float64)

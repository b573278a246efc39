"""Mapping returns to the positive weights that PoWER (eq. 7) and eq. 6 need."""

from __future__ import annotations

import math
from collections.abc import Sequence

import torch
from torch import Tensor

from dipole_torch.validation import check_finite

RewardRange = tuple[float, float] | str | None
_LARGEST_WEIGHT = 1e150  # a positive return used as a weight: its square stays finite
_SMALLEST_FIRST_WEIGHT = 1e-150  # the first batch's largest weight: its square is not 0


class RewardScale:
    """Affine map of returns onto weights in ``[floor, 1]``.

    PoWER averages samples weighted by their returns and eq. 6 multiplies component
    probabilities by r_c, so both need positive numbers. The paper's returns are not all
    positive (cart-pole's lie in [−1000, 1000]) and it does not say how it made them so; we use
    w = max((r − low) / (high − low), floor), the transform that keeps PoWER's update (a
    weighted average) invariant to the units of the return. ``floor`` keeps a return at the
    bottom of the range from zeroing a component's weight in eq. 6.

    Three modes:

    * ``RewardScale()`` (adaptive, the default of the optimizers): ``low`` and ``high`` are
      the smallest and largest of the returns the optimizer currently keeps (its
      ``reference``), recomputed at every use. No range is needed in advance; any finite
      returns work (negative, of order 1e-9 or 1e9, a range that grows during the run), and
      the weights are invariant to any positive affine change of the return's units.
    * ``RewardScale(low, high)``: a fixed range known in advance (the paper's setting);
      returns outside it are refused.
    * ``RewardScale(positive=True)``: returns are used as they are and must be positive.

    Args:
        low: lowest possible return, or ``None``.
        high: highest possible return (> low), or ``None``.
        floor: smallest weight, in (0, 1).
        positive: use positive returns as weights unchanged (no range).
    """

    def __init__(
        self,
        low: float | None = None,
        high: float | None = None,
        floor: float = 1e-3,
        positive: bool = False,
    ):
        if (low is None) != (high is None):
            raise ValueError("reward_range needs both low and high, or neither")
        if low is not None:
            low, high = float(low), float(high)
            if not (math.isfinite(low) and math.isfinite(high) and high > low):
                raise ValueError(
                    f"reward_range must be finite with high > low, got ({low}, {high})"
                )
            if positive:
                raise ValueError("positive=True takes no reward_range")
        if not 0.0 < floor < 1.0:
            raise ValueError(f"floor must lie in (0, 1), got {floor}")
        self.low = low
        self.high = high
        self.floor = float(floor)
        self.positive = bool(positive)

    @property
    def adaptive(self) -> bool:
        """Whether the range follows the kept returns."""
        return self.low is None and not self.positive

    def __call__(self, rewards: Tensor, reference: Tensor | None = None) -> Tensor:
        """``[...]`` weights of ``rewards: [...]``; raises on values this scale cannot map."""
        self.validate(rewards)
        return self.weights(rewards, reference)

    def validate(self, rewards: Tensor, first: bool = False, name: str = "rewards") -> None:
        """Raise ``ValueError`` on non-finite rewards, or rewards this scale cannot map;
        ``first``: they are the run's first batch; ``name``: the argument to name."""
        check_finite(rewards, name)
        self.check_range(rewards, first, name)

    def check_range(self, rewards: Tensor, first: bool = False, name: str = "rewards") -> None:
        """``validate`` for rewards already checked finite (``check_rewards``): raise
        ``ValueError`` on rewards this scale cannot map."""
        if self.positive:
            if (rewards <= 0).any():
                raise ValueError(
                    f"{name} must be positive with reward_range='positive' (Dipole.paper's "
                    "default: PoWER and eq. 6 weight by them as they are); got min "
                    f"{float(rewards.min()):g}. Pass reward_range=None to map any returns to "
                    "[floor, 1] by their min-max, or a fixed (low, high)."
                )
            if (rewards > _LARGEST_WEIGHT).any():
                raise ValueError(
                    f"{name} used as weights (reward_range='positive') must be at most "
                    f"{_LARGEST_WEIGHT:g}, whose squares the DP mixture's variances hold; got "
                    f"max {float(rewards.max()):g}. Rescale them, or pass reward_range=None."
                )
            if first and float(rewards.max()) < _SMALLEST_FIRST_WEIGHT:
                # The prior's reward variance is set by the first batch's scale.
                raise ValueError(
                    f"the first batch's {name} used as weights (reward_range='positive') "
                    f"must reach {_SMALLEST_FIRST_WEIGHT:g}, whose square the DP mixture's "
                    f"variances hold; got max {float(rewards.max()):g}. Rescale them, or pass "
                    "reward_range=None."
                )
            return
        if self.low is None:
            return
        slack = 1e-9 * self.high - 1e-9 * self.low  # (high - low overflows beyond ±9e307)
        if (rewards < self.low - slack).any() or (rewards > self.high + slack).any():
            raise ValueError(
                f"{name} outside reward_range ({self.low:g}, {self.high:g}): "
                f"min {float(rewards.min()):g}, max {float(rewards.max()):g}"
            )

    def range(self, reference: Tensor | None = None) -> tuple[Tensor, Tensor]:
        """``(low, high)`` of the map as 0-d tensors; adaptive: the min and max of
        ``reference: [N]`` (``high`` > ``low`` always: a flat reference maps to weight 1)."""
        if self.positive:
            raise RuntimeError("RewardScale(positive=True) has no range")
        if self.low is not None:
            return torch.tensor(self.low, dtype=torch.float64), torch.tensor(
                self.high, dtype=torch.float64
            )
        if reference is None or reference.numel() == 0:
            raise ValueError("an adaptive RewardScale needs the reference returns")
        low, high = reference.min(), reference.max()
        # A flat reference: every return is the best one (weight 1), with a width relative to
        # the returns' size, so that high - width is below high at any magnitude.
        width = high - low
        flat = (high.abs() * 2.0**-40).clamp_min(torch.finfo(reference.dtype).tiny)
        width = torch.where(width > 0, width, flat)
        # (A range too wide for a float, ±1.8e308 returns: its own ends; weights() halves.)
        return torch.where(torch.isfinite(width), high - width, low), high

    def weights(self, rewards: Tensor, reference: Tensor | None = None) -> Tensor:
        """The map itself, for rewards already validated.

        Args:
            rewards: ``[...]`` returns.
            reference: ``[N]`` the returns that define an adaptive range (e.g. the ones an
                optimizer keeps); ignored with a fixed range. Defaults to ``rewards``.
        """
        if self.positive:
            return rewards
        low, high = self.range(rewards.reshape(-1) if reference is None else reference)
        if low.dtype != rewards.dtype or low.device != rewards.device:
            low, high = low.to(rewards), high.to(rewards)
        weights = (rewards - low) / (high - low)
        # Returns near ±1.8e308 are finite, their range not: the same map on halves (exact).
        halves = (0.5 * rewards - 0.5 * low) / (0.5 * high - 0.5 * low)
        weights = torch.where(torch.isfinite(high - low), weights, halves)
        return weights.clamp(self.floor, 1.0)

    def inverse(self, weights: Tensor, reference: Tensor | None = None) -> Tensor:
        """Returns corresponding to ``weights`` (the floor is not undone)."""
        if self.positive:
            return weights
        low, high = self.range(reference)
        return low.to(weights) + weights * (high - low).to(weights)

    def slope(self, reference: Tensor | None = None) -> float:
        """d(return)/d(weight)."""
        if self.positive:
            return 1.0
        low, high = self.range(reference)
        return float(high - low)


def check_rewards(rewards, batch: int, each: str = "asked θ", name: str = "rewards") -> Tensor:
    """Validate ``rewards: [B]`` (a tensor, an array or a list of numbers) against the batch
    size (one per ``each``); return them as float64, detached from any autograd graph.
    ``name`` is the argument the messages name."""
    if not isinstance(rewards, Tensor):
        try:
            rewards = torch.as_tensor(rewards)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(
                f"{name} must be a tensor, an array or a list of numbers, got {rewards!r}"
            ) from None
    if rewards.shape != (batch,):
        raise ValueError(
            f"{name} must have shape [{batch}] (one per {each}), got {list(rewards.shape)}"
        )
    dtype = rewards.dtype
    if dtype == torch.bool or not (dtype.is_floating_point or dtype.is_signed):
        raise ValueError(f"{name} must be real numbers, got dtype {dtype}")
    if rewards.device.type == "meta":
        raise ValueError(f"{name} is a meta tensor (no values)")
    check_finite(rewards, name)
    return rewards.detach().to(torch.float64)


def check_reward_range(reward_range, name: str = "reward_range") -> None:
    """Raise ``ValueError`` unless ``reward_range`` is ``None``, ``"positive"`` or a pair
    ``(low, high)`` of finite numbers with high > low."""
    if reward_range is None or (isinstance(reward_range, str) and reward_range == "positive"):
        return
    message = f"{name} must be None, (low, high) or 'positive', got {reward_range!r}"
    if isinstance(reward_range, str) or not isinstance(reward_range, Sequence):
        raise ValueError(message)
    if len(reward_range) != 2 or not all(
        isinstance(v, int | float) and not isinstance(v, bool) for v in reward_range
    ):
        raise ValueError(message)
    low, high = (float(v) for v in reward_range)
    if not (math.isfinite(low) and math.isfinite(high) and high > low):
        raise ValueError(f"{name} must be finite with high > low, got ({low}, {high})")


def make_reward_scale(reward_range: RewardRange, floor: float) -> RewardScale:
    """The ``RewardScale`` of ``reward_range``: ``None``, adaptive (the kept returns'
    min–max); ``(low, high)``, fixed; ``"positive"``, positive returns used as they are."""
    check_reward_range(reward_range)
    if reward_range is None:
        return RewardScale(floor=floor)
    if reward_range == "positive":
        return RewardScale(floor=floor, positive=True)
    low, high = reward_range
    return RewardScale(low, high, floor)

"""The range of the returns told: the scale at which retirement judges a policy's kept
returns flat, and at which a wake judges a gain visible or a return near the best
(``dipole_torch.mechanisms.retirement``).

A few returns far below all others (crashed rollouts) or far above them (a glitch: a
simulation that blew up) are left out of it.
"""

from __future__ import annotations

import bisect
import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

if TYPE_CHECKING:
    from dipole_torch.archive import SampleArchive

__all__ = ["OUTLIER_COUNT", "OUTLIER_GAP", "OUTLIER_SHARE", "ReturnRange"]

# A few returns far below or far above all others are left out of the returns' range: the
# lowest (highest) returns told, at most OUTLIER_SHARE of them (more are part of the task)
# and OUTLIER_COUNT in all (what is kept to judge them), when a gap wider than OUTLIER_GAP
# times the range of the returns left lies between them and the rest. (One return of -1e6
# among Vincent 2-D's returns in [-1, 1] made the spread rule retire every policy at once,
# 1e-4 of a range of 1e6: of 51 optima converged to 1e-4 in 2000 trials, 7 were; one of
# +1e6, 2.)
OUTLIER_SHARE = 0.05
OUTLIER_COUNT = 1024
OUTLIER_GAP = 10.0
_ROUNDS = 4  # each side's cut is judged against the other's: alternations at most


def _cut(tail: list[float], other: float, allowed: int, sign: float) -> float:
    """The most extreme of ``tail`` (the returns from one end inward: ascending for the low
    end, ``sign = 1``; descending for the high end, ``sign = -1``) that is not an outlier:
    the return after the innermost gap among the first ``allowed + 1`` wider than
    ``OUTLIER_GAP`` times that return's distance to ``other`` (the range's other end), that
    distance not zero; ``tail[0]`` where there is none."""
    n = min(allowed, len(tail) - 1)
    # A gap that wide puts tail[0] over 1 + OUTLIER_GAP times as far from ``other`` as the
    # return after it, itself at least as far as tail[n]: where tail[0] is not even
    # OUTLIER_GAP times as far as tail[n] (most calls), there is none.
    if n <= 0 or sign * (other - tail[0]) <= OUTLIER_GAP * sign * (other - tail[n]):
        return tail[0]
    signed = np.asarray(tail[: n + 1]) * sign  # (negation is exact: the same comparisons)
    inward = sign * other - signed[1:]
    gaps = np.flatnonzero((inward > 0) & (signed[1:] - signed[:-1] > OUTLIER_GAP * inward))
    return tail[int(gaps[-1]) + 1] if gaps.size else tail[0]


def _insert(tail: list[float], returns: list[float], kept: int, sign: float) -> bool:
    """Insert ``returns`` into ``tail`` (ordered as in ``_cut``), keeping its first
    ``kept``; whether it changed."""
    key = None if sign > 0 else _negated
    changed = False
    for value in returns:
        if len(tail) < kept or sign * value < sign * tail[-1]:
            bisect.insort(tail, value, key=key)
            del tail[kept:]
            changed = True
    return changed


def _negated(value: float) -> float:
    return -value


class ReturnRange:
    """The range of every return told since the world last changed, less outliers far below
    or far above the rest (``OUTLIER_GAP``): the scale of the retirement by spread, of a
    wake's visible gain and of its gate.

    Attributes:
        low, high: the range (``inf, -inf`` before any return).
    """

    def __init__(self):
        self.low, self.high = math.inf, -math.inf
        self.told = 0  # returns told
        self.lowest: list[float] = []  # the lowest OUTLIER_COUNT + 1 returns told, ascending
        self.highest: list[float] = []  # the highest OUTLIER_COUNT + 1, descending
        self.judges_high = True  # False: resumed without the highest returns (none left out)

    def observe(self, rewards: Tensor) -> None:
        """Widen the range by a told batch's ``rewards [B]``."""
        returns = rewards.tolist()
        allowed = self._allowed()
        self.told += len(returns)
        kept = OUTLIER_COUNT + 1
        changed = self._allowed() != allowed
        changed |= _insert(self.lowest, returns, kept, 1.0)
        changed |= _insert(self.highest, returns, kept, -1.0)
        if changed:  # (else the range stands: most tells)
            self.low, self.high = self._bounds()

    def _allowed(self) -> int:
        """How many returns at each end may be left out."""
        return min(int(OUTLIER_SHARE * self.told), OUTLIER_COUNT)

    def _bounds(self) -> tuple[float, float]:
        """The lowest and the highest return that are not outliers (``_cut``), each judged
        against the range the other leaves: alternated from the highest return that may not
        be left out (the narrowest range), a few times at most, to a pair where each end is
        the other's cut."""
        allowed, lowest, highest = self._allowed(), self.lowest, self.highest
        if not self.judges_high:
            return _cut(lowest, highest[0], allowed, 1.0), highest[0]
        high = highest[min(allowed, len(highest) - 1)]
        for _ in range(_ROUNDS):
            low = _cut(lowest, high, allowed, 1.0)
            high, last = _cut(highest, low, allowed, -1.0), high
            if high == last:
                break
        return low, high

    @property
    def outliers_above(self) -> bool:
        """Whether returns far above the rest are left out (``high`` below the highest
        told)."""
        return bool(self.highest) and self.high < self.highest[0]

    @property
    def leaves_out(self) -> bool:
        """Whether returns far below or far above the rest are left out."""
        return self.outliers_above or (bool(self.lowest) and self.low > self.lowest[0])

    def kept_spreads(self, archive: SampleArchive, num_policies: int) -> Tensor:
        """``[K]`` the spread (max − min) of each policy's kept returns in ``archive``;
        where they straddle an end of the range beyond which outliers are left out, the
        outliers count as that end.

        A policy holding a glitch among returns in the range then spreads no wider than the
        range (not a million ranges). A policy whose kept returns all lie beyond the range (it
        found a success far above the rest, left out of the range while such returns are
        rare) is judged on its own returns, finer than the range: clamped, they would be
        flat, and it would retire on the success it had just found, never to be woken."""
        high = archive.per_policy("amax", num_policies)
        low = archive.per_policy("amin", num_policies)
        if self.leaves_out:
            top, bottom = self.high, self.low
            high, low = (
                torch.where(low <= top, high.clamp(max=top), high),
                torch.where(high >= bottom, low.clamp(min=bottom), low),
            )
        return high - low

    def fraction(self, fraction: Tensor | float) -> Tensor | float:
        """``fraction`` (at most 1) of the range's width; 0 before any return, or while
        every return was equal."""
        if not self.high > self.low:
            return 0.0 * fraction
        width = self.high - self.low
        if math.isfinite(width):
            return fraction * width
        return fraction * self.high - fraction * self.low  # (the width overflowed: ±9e307)

    def forget(self) -> None:
        """The world changed (``reevaluate``): measured again from the next tell (the old
        world's range would judge the new returns' spread)."""
        self.low, self.high = math.inf, -math.inf
        self.told, self.lowest, self.highest, self.judges_high = 0, [], [], True

    # (The range is saved under the names of the waking's fields, which held it before it
    # moved here: a checkpoint from then resumes with its range, and no outlier left out.)
    def state_dict(self) -> dict:
        return {
            "waking_low": self.low,
            "waking_high": self.high,
            "returns_told": self.told,
            "lowest_returns": list(self.lowest),
            "highest_returns": list(self.highest),
        }

    def load_state_dict(self, state: dict) -> None:
        self.low = float(state.get("waking_low", math.inf))
        self.high = float(state.get("waking_high", -math.inf))
        if "lowest_returns" in state:
            self.lowest = [float(value) for value in state["lowest_returns"]]
            self.told = int(state["returns_told"])
        else:
            self.lowest = [self.low] if math.isfinite(self.low) else []
            self.told = len(self.lowest)
        # A checkpoint from before returns far above were left out keeps its high end: the
        # returns below it that would judge it were not saved.
        self.judges_high = "highest_returns" in state
        if self.judges_high:
            self.highest = [float(value) for value in state["highest_returns"]]
        else:
            self.highest = [self.high] if math.isfinite(self.high) else []

"""The range of the returns told: the scale at which retirement judges a policy's kept
returns flat, and at which a wake judges a gain visible or a return near the best
(``dipole_torch.mechanisms.retirement``).

A few returns far below all others (crashed rollouts) are left out of it.
"""

from __future__ import annotations

import math

from torch import Tensor

__all__ = ["OUTLIER_COUNT", "OUTLIER_GAP", "OUTLIER_SHARE", "ReturnRange"]

# A few returns far below all others (crashed rollouts) are left out of the returns' range:
# the lowest returns told, at most OUTLIER_SHARE of them (more are part of the task) and
# OUTLIER_COUNT in all (what is kept to judge them), when a gap wider than OUTLIER_GAP times
# the range of the returns above it lies between them and the rest. (One return of -1e6 among
# Vincent 2-D's returns in [-1, 1] made the spread rule retire every policy at once, 1e-4 of
# a range of 1e6: of 51 optima converged to 1e-4 in 2000 trials, 7 were.)
OUTLIER_SHARE = 0.05
OUTLIER_COUNT = 1024
OUTLIER_GAP = 10.0


class ReturnRange:
    """The range of every return told since the world last changed, less outliers far below
    the rest (``OUTLIER_GAP``): the scale of the retirement by spread, of a wake's visible
    gain and of its gate.

    Attributes:
        low, high: the range (``inf, -inf`` before any return).
    """

    def __init__(self):
        self.low, self.high = math.inf, -math.inf
        self.told = 0  # returns told
        self.lowest: list[float] = []  # the lowest OUTLIER_COUNT + 1 returns told, ascending

    def observe(self, rewards: Tensor) -> None:
        """Widen the range by a told batch's ``rewards [B]``."""
        returns = rewards.tolist()
        allowed = self._allowed()
        self.told += len(returns)
        high = max(self.high, max(returns))
        kept = OUTLIER_COUNT + 1
        changed = high != self.high or self._allowed() != allowed
        if len(self.lowest) < kept or min(returns) < self.lowest[-1]:
            self.lowest = sorted(self.lowest + returns)[:kept]
            changed = True
        self.high = high
        if changed:  # (else the range stands: most tells)
            self.low = self._low()

    def _allowed(self) -> int:
        """How many of the lowest returns may be left out."""
        return min(int(OUTLIER_SHARE * self.told), OUTLIER_COUNT)

    def _low(self) -> float:
        """The lowest return that is not an outlier: above the highest gap among the lowest
        (at most ``OUTLIER_SHARE`` of the returns told) wider than ``OUTLIER_GAP`` times
        the range above it, that range not empty; the lowest told where there is none."""
        lowest, high = self.lowest, self.high
        for i in range(self._allowed(), 0, -1):
            if high > lowest[i] and lowest[i] - lowest[i - 1] > OUTLIER_GAP * (high - lowest[i]):
                return lowest[i]
        return lowest[0]

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
        self.told, self.lowest = 0, []

    # (The range is saved under the names of the waking's fields, which held it before it
    # moved here: a checkpoint from then resumes with its range, and no outlier left out.)
    def state_dict(self) -> dict:
        return {
            "waking_low": self.low,
            "waking_high": self.high,
            "returns_told": self.told,
            "lowest_returns": list(self.lowest),
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

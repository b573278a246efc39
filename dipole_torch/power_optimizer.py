"""PoWER, the paper's baseline (Algorithm 3), as an ask/tell optimizer."""

from __future__ import annotations

import math
from typing import Any

import torch

from dipole_torch.inputs import Bounds, SigmaStart, Theta0
from dipole_torch.power import GlobalImportance, importance_sets
from dipole_torch.reward import RewardRange
from dipole_torch.search import PolicySearch
from dipole_torch.validation import check_count, check_real

__all__ = ["Power"]


class Power(PolicySearch):
    """PoWER, the paper's baseline: one policy with exploration covariance Σ_start.

    Algorithm 3: ``n0`` initial samples (default M) from N(θ0, Σ_start), then one sample
    per iteration; after each, θ moves by eq. 7 towards the reward-weighted average of the
    best M samples so far.

    The paper "manually reduced" PoWER's exploration covariance once cart-pole converged;
    ``exploration_decay`` < 1 is a reproducible stand-in: after iteration t the covariance is
    Σ_start · max(decay^t, min_exploration). The default 1.0 keeps Σ_start fixed.

    >>> opt = Power([0.0, 0.0], 0.5, generator=torch.Generator().manual_seed(0))
    >>> while not opt.stop(max_trials=200):
    ...     theta = opt.ask()
    ...     opt.tell(theta, -(theta - 1.0).pow(2).sum(-1))
    >>> bool(opt.best()[1] > -0.05)
    True

    Args:
        theta0: ``[D]`` initial policy θ^(0) (a tensor, a list or a numpy array).
        sigma_start: exploration: one std, ``[D]`` stds or a ``[D, D]`` covariance Σ.
        M: importance-set size (paper: 5).
        n0: initial samples (default M).
        reward_range: ``None`` (default): returns mapped to weights in [floor, 1] by the
            min–max of the kept returns; ``(low, high)``: a fixed map; ``"positive"``:
            positive returns used as weights (see ``dipole_torch.RewardScale``).
        reward_floor: smallest reward weight, in (0, 1).
        exploration_decay: per-iteration factor on the covariance, in (0, 1].
        min_exploration: floor of that factor, in (0, 1].
        best_evaluations: evaluations the best kept sample gets, one more at each ask, before
            its return (the mean of them) is trusted (1: every return as told); for noisy
            returns, as ``DipoleOptions.best_evaluations`` (deterministic returns detected
            the same way).
        generator: ``torch.Generator`` for every draw (default: seeded from torch's global
            generator).
        bounds: ``(lower, upper)`` box of the parameters (numbers, lists of D numbers or
            ``[D]`` tensors; ±inf leaves a side open), or ``None``; see
            ``PolicySearch``.
    """

    def __init__(
        self,
        theta0: Theta0,
        sigma_start: SigmaStart,
        M: int = 5,
        n0: int | None = None,
        reward_range: RewardRange = None,
        reward_floor: float = 1e-3,
        exploration_decay: float = 1.0,
        min_exploration: float = 1e-2,
        generator: torch.Generator | None = None,
        bounds: Bounds = None,
        best_evaluations: int = 1,
    ):
        check_count(M, "M (importance-set size)")
        check_count(best_evaluations, "best_evaluations")
        check_count(n0, "n0 (initial samples)", optional=True)
        for name, value in (
            ("reward_floor", reward_floor),
            ("exploration_decay", exploration_decay),
            ("min_exploration", min_exploration),
        ):
            check_real(value, name)
        if not (math.isfinite(exploration_decay) and 0.0 < exploration_decay <= 1.0):
            raise ValueError(f"exploration_decay must lie in (0, 1], got {exploration_decay}")
        if not (math.isfinite(min_exploration) and 0.0 < min_exploration <= 1.0):
            raise ValueError(f"min_exploration must lie in (0, 1], got {min_exploration}")
        super().__init__(
            theta0, sigma_start, M, M if n0 is None else n0, reward_range, reward_floor,
            generator, bounds,
        )  # fmt: skip
        self.importance = GlobalImportance()
        self.exploration_decay = float(exploration_decay)
        self.min_exploration = float(min_exploration)
        self.repeats.evaluations = int(best_evaluations)

    def _settings(self) -> dict[str, Any]:
        return {
            **super()._settings(),
            "exploration_decay": self.exploration_decay,
            "min_exploration": self.min_exploration,
            "best_evaluations": self.repeats.evaluations,
        }

    def _after_initial_batch(self) -> None:
        keep, _, _ = importance_sets(self.archive.owner, self.archive.rewards, 1, self.M)
        self.archive.keep(keep)

    def _iterate(self) -> None:
        self.importance.power_step(self)
        if self.exploration_decay < 1.0:
            factor = max(self.exploration_decay**self.iteration, self.min_exploration)
            self.policy_set.covariances = factor * self.sigma_start[None]

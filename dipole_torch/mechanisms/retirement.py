"""A policy's life after it was found: retirement once converged, merging of duplicates, and
the restart of a policy whose samples straddle two hills.

* Retirement (``retire_std``): a policy whose exploration std has shrunk below
  ``retire_std`` times Σ_start's stops being sampled; it stays among the policies, and its
  trials go to the others.
* Merging (``merge_radius``): an active policy closer than ``merge_radius`` exploration stds
  to another (both ways) or to a retired one, and to no third policy, is a duplicate and is
  dropped (one whose exploration covers two or more is left to the hill-valley probes).
* Restarts: a policy whose best kept sample lies far outside its exploration, while its
  latest sample was worse than all its kept ones, restarts from that best sample. Only a
  policy that keeps its exploration between clusterings (the success rule) can end up so.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE

if TYPE_CHECKING:
    from dipole_torch.search import PolicySearch, TellBatch

__all__ = ["Retirement", "exploration_distance"]


def exploration_distance(search: PolicySearch, diff: Tensor) -> Tensor:
    """``[K, P]`` the Mahalanobis lengths of ``diff: [K, P, D]`` under each policy's
    exploration covariance (row k under policy k's); inf in the rows whose covariance has
    lost definiteness in float64."""
    chol, info = torch.linalg.cholesky_ex(search.policy_covariances)
    ok = info == 0
    eye = torch.eye(search.dim, dtype=DTYPE, device=search.device)
    chol = torch.where(ok[:, None, None], chol, eye)
    z = torch.linalg.solve_triangular(chol, diff.transpose(-1, -2), upper=False)
    return torch.where(ok[:, None], z.square().sum(-2).sqrt(), math.inf)


class Retirement:
    """Retirement, merging and straddler restarts.

    Args:
        retire_std: relative exploration std below which a policy is retired (0: never).
        merge_radius: duplicate distance in exploration stds (0: never merge).
        restart_straddlers: restart policies whose samples straddle two hills (for
            exploration that is kept between clusterings).
    """

    def __init__(self, retire_std: float, merge_radius: float, restart_straddlers: bool):
        self.retire_std = float(retire_std)
        self.merge_radius = float(merge_radius)
        self.restarts = bool(restart_straddlers)
        self._in_valley: Tensor | None = None  # within one tell: see observe

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        """Which policies' latest sample was worse than every one they keep (``[K]``),
        judged before the samples are archived."""
        self._in_valley = None
        if not (self.restarts and search.started):
            return
        rows = batch.owner >= 0
        policy = batch.owner[rows]
        worst = search.archive.per_policy("amin", search.num_policies)
        self._in_valley = torch.zeros(search.num_policies, dtype=torch.bool, device=search.device)
        self._in_valley[policy] = batch.rewards[rows] < worst[policy]

    def forget(self) -> None:
        self._in_valley = None

    def converged(self, search: PolicySearch) -> Tensor:
        """``[K]`` whether each policy's exploration std is below ``retire_std`` times
        Σ_start's (never with ``retire_std = 0``, but for a covariance lost to rounding, NaN,
        which must not be sampled)."""
        return ~(search.relative_std() >= self.retire_std)

    # ------------------------------------------------------------------ restarts
    def restart_straddlers(self, search: PolicySearch) -> None:
        """Restart a policy from its best kept sample when that sample lies more than
        3 + √D exploration stds (Mahalanobis, under the policy's covariance) from its mean
        and the policy's latest sample was worse than all its kept ones.

        Its kept samples then straddle two or more hills (the clustering gave it samples
        from both): eq. 7 puts the mean between them, in a valley, where no new sample beats
        the kept ones, and the success rule shrinks the exploration until the policy retires
        short of any top. The policy keeps its best sample only, as a new policy would, and
        explores with Σ_start's shape at its old samples' spread around it. The second
        condition spares a policy on a plateau: its exploration shrinks below its kept
        samples' spread too, but its samples tie with the kept ones."""
        in_valley, self._in_valley = self._in_valley, None
        if in_valley is None or not bool((in_valley & search.active).any()):
            return  # the usual case: no factorisation needed
        archive, policies = search.archive, search.policy_set
        best = archive.best_samples(policies.means)
        distance = exploration_distance(search, (best - policies.means)[:, None, :])[:, 0]
        limit = 3.0 + math.sqrt(search.dim)
        # (A covariance that lost definiteness, distance inf, restarts nothing.)
        straddling = policies.active & in_valley & distance.isfinite() & (distance > limit)
        if not bool(straddling.any()):
            return
        for j in straddling.nonzero().squeeze(-1).tolist():
            own = (archive.owner == j).nonzero().squeeze(-1)
            centre = best[j]
            diff = archive.thetas[own] - centre
            scatter = diff.T @ diff / max(own.numel() - 1, 1)
            policies.means[j] = centre
            policies.covariances[j] = search.exploration.starting_covariance(search, scatter)
            restarted = torch.zeros(search.num_policies, dtype=torch.bool, device=search.device)
            restarted[j] = True
            policies.reset_fields(restarted)
            keep = torch.ones_like(archive.owner, dtype=torch.bool)
            keep[own] = False
            keep[own[archive.rewards[own].argmax()]] = True
            archive.keep(keep)

    # ------------------------------------------------------------------ retire and merge
    def retire_and_merge(self, search: PolicySearch) -> None:
        """Retire the converged policies, then drop duplicates (see the module docstring)."""
        policies = search.policy_set
        if self.retire_std > 0:
            policies.active = policies.active & ~self.converged(search)
        if self.merge_radius <= 0 or search.num_policies < 2:
            return
        # Mahalanobis distance of policy b's mean under policy a's exploration: [K, K]
        # (inf: a's covariance lost definiteness in float64 and judges no duplicates).
        diff = policies.means[None, :, :] - policies.means[:, None, :]
        near = exploration_distance(search, diff) < self.merge_radius
        near.fill_diagonal_(False)
        # A policy whose exploration covers two or more others is judged by none of them:
        # exploring that widely (a new policy), it may well be on a hill of its own, which
        # only a hill-valley probe can tell.
        judged = near.sum(-1) == 1
        best = search.policy_best_rewards
        active = policies.active
        drop = torch.zeros(search.num_policies, dtype=torch.bool, device=search.device)
        for a in (active & judged).nonzero().squeeze(-1).tolist():
            for b in range(search.num_policies):
                if a == b or drop[b] or drop[a]:
                    continue
                if not active[b]:
                    duplicate = bool(near[a, b])  # a explores a retired optimum...
                    if duplicate and best[a] > best[b]:
                        drop[b] = True  # ...which stopped short of the top: a goes on
                        continue
                else:
                    duplicate = bool(near[a, b] and near[b, a])
                    # Of two active duplicates the worse one goes.
                    if duplicate and best[a] > best[b]:
                        drop[b] = True
                        continue
                if duplicate:
                    drop[a] = True
        if drop.any():
            search.remove_policies(drop.nonzero().squeeze(-1))

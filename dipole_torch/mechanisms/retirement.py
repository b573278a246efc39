"""A policy's life after it was found: retirement once converged, waking to refine it further,
merging of duplicates, and the restart of a policy whose samples straddle two hills.

* Retirement (``retire_std``, ``retire_spread``): a policy stops being sampled once its
  exploration std has shrunk below its threshold, at first ``retire_std`` times Σ_start's,
  or once its M kept returns spread less than its other threshold, at first
  ``retire_spread`` times the range of every return told (``ReturnRange``: a few returns
  far below or far above all others, a crashed rollout or a glitch, left out; see
  ``ReturnRange.kept_spreads`` for a policy that holds one); it stays among the policies,
  and its trials go to the others.
* Waking (``refine``, ``refine_share``, ``refine_gate``, ``wake_while_active``;
  ``Waking``, ``dipole_torch.mechanisms.waking``): retired policies sampled again, each
  time with both thresholds times ``refine``, so that a converged policy is not frozen for
  good.
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

from dipole_torch.gaussian import mahalanobis
from dipole_torch.mechanisms.return_range import ReturnRange
from dipole_torch.mechanisms.waking import NoWaking, Waking

if TYPE_CHECKING:
    from dipole_torch.search import PolicySearch
    from dipole_torch.tell_batch import TellBatch

__all__ = ["Retirement", "exploration_distance"]

# The spread rule judges only a policy exploring below this fraction of Σ_start's std: one
# exploring wider has not converged, whatever its kept returns show (crawling along a ridge
# with a covariance stretched across it, its M best returns can agree to 1e-4 of the range
# while its largest std is still Σ_start's).
SPREAD_GATE = 0.1


def exploration_distance(search: PolicySearch, diff: Tensor, rows: Tensor | None = None) -> Tensor:
    """``[K, P]`` the Mahalanobis lengths of ``diff: [K, P, D]`` under each policy's
    exploration covariance (row k under policy k's, or under policy ``rows[k]``'s for
    ``rows: [K]``); inf in the rows whose covariance has lost definiteness in float64."""
    chol, ok = search.policy_set.exploration_factors()
    if rows is not None:
        chol, ok = chol[rows], ok[rows]
    return torch.where(ok[:, None], mahalanobis(chol, diff), math.inf)


def _per_policy(value: Tensor | float, k: int) -> list[float]:
    """``value`` (``[K]``, or one number for every policy) as K host numbers."""
    return value.tolist() if isinstance(value, Tensor) else [float(value)] * k


class Retirement:
    """Retirement, merging and straddler restarts.

    Args:
        retire_std: relative exploration std below which a policy is retired (0: no policy
            is ever retired).
        retire_spread: fraction of the returns' range below which the spread of a policy's
            M kept returns retires it too (0: the std alone).
        merge_radius: duplicate distance in exploration stds (0: never merge).
        restart_straddlers: restart policies whose samples straddle two hills (for
            exploration that is kept between clusterings).
        refine: the threshold's factor at each wake (0: retired policies stay retired).
        refine_share: the share of the trials after the first convergence within which
            a wake may start (``Waking``).
        refine_gate: the wakes' gate below the best return, a fraction of the returns'
            range (``Waking``).
        wake_while_active: a wake may start while other policies are active (``Waking``).
    """

    def __init__(
        self,
        retire_std: float,
        merge_radius: float,
        restart_straddlers: bool,
        refine: float,
        refine_share: float,
        retire_spread: float = 0.0,
        refine_gate: float = 1.0,
        wake_while_active: bool = False,
    ):
        self.retire_std = float(retire_std)
        self.retire_spread = float(retire_spread)
        self.merge_radius = float(merge_radius)
        self.restarts = bool(restart_straddlers)
        self.returns = ReturnRange()
        wakes = self.retire_std > 0 and refine > 0
        self.waking = (
            Waking(refine, refine_share, self.returns, refine_gate, wake_while_active)
            if wakes
            else NoWaking()
        )
        self._in_valley: tuple[bool, ...] | None = None  # within one tell: see observe

    def register(self, search: PolicySearch) -> None:
        self.waking.register(search)

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        """Which policies' latest sample was worse than every one they keep (K flags, on
        the host: ``restart_straddlers`` of this tell branches on them), judged before the
        samples are archived; the returns' range; the waking's trial counts."""
        self._in_valley = None
        if self.retire_std > 0:  # (else no rule reads the range)
            self.returns.observe(batch.rewards)
        self.waking.observe(search, batch)
        if not (self.restarts and search.started):
            return
        k, n = search.num_policies, batch.policy_rows
        worst = search.archive.per_policy("amin", k)
        if not batch.every_policy(k):  # (else one sample of each policy, in order)
            worst = worst[batch.owner[:n]]
        worse = (batch.rewards[:n] < worst).tolist()
        in_valley = [False] * k
        for policy, flag in zip(batch.policies, worse, strict=True):
            in_valley[policy] = flag
        self._in_valley = tuple(in_valley)

    def forget(self) -> None:
        """The world changed: nothing judged on the old world's returns is kept."""
        self._in_valley = None
        self.returns.forget()

    def converged(self, search: PolicySearch) -> Tensor:
        """``[K]`` whether each policy's exploration std is below its threshold times
        Σ_start's (``retire_std``), or its M kept returns spread less than its other
        threshold times the returns' range (``retire_spread``), both lowered by each wake;
        never with ``retire_std = 0``, but for a covariance lost to rounding, NaN, which must
        not be sampled."""
        return ~self._exploring(search)

    def _exploring(self, search: PolicySearch) -> Tensor:
        """``[K]`` not ``converged``: the std at or above its threshold (NaN is not), and the
        kept returns not flat at the returns' scale.

        The spread rule retires a policy whose returns have little left to show at the scale
        of the task's returns: on a broad optimum they agree to a small fraction of the
        range long before the exploration is small against Σ_start (its trials then go to
        finding other optima, and a wake refines it later); on a narrow one the std comes
        first. Only a policy with a full importance set (M kept samples) that explores below
        ``SPREAD_GATE`` of Σ_start's std is judged so."""
        flags = self._exploring_flags(search)
        return torch.tensor(flags, dtype=torch.bool, device=search.device)

    def _exploring_flags(self, search: PolicySearch) -> list[bool]:
        """``_exploring`` on the host: K flags from the per-policy numbers (K of each, a
        handful of calls where the same rule in tensor operations makes some twenty; the
        same comparisons of the same float64 numbers)."""
        k = search.num_policies
        relative = search.relative_std().tolist()
        std_limit = _per_policy(self.waking.thresholds(search, self.retire_std), k)
        exploring = [r >= t for r, t in zip(relative, std_limit, strict=True)]  # (NaN: False)
        if self.retire_spread <= 0 or self.retire_std <= 0:
            return exploring
        archive, full = search.archive, search.M
        counts = archive.counts(k).tolist()
        spreads = self.returns.kept_spreads(search.archive, k).tolist()
        thresholds = _per_policy(self.waking.thresholds(search, self.retire_spread), k)
        return [
            flag and not (n >= full and r < SPREAD_GATE and s < self.returns.fraction(t))
            for flag, n, r, s, t in zip(
                exploring, counts, relative, spreads, thresholds, strict=True
            )
        ]

    def refining(self, search: PolicySearch) -> Tensor:
        """``[K]`` the policies woken to refine: clusterings leave their samples out, as
        they leave the retired ones' (DP components over several converged policies' tight
        samples would merge them)."""
        return self.waking.refining(search)

    def final(self, search: PolicySearch) -> Tensor:
        """``[K]`` whether each policy has converged for good: below its threshold, and no
        wake could refine it further (``Waking.refinable``)."""
        return self.converged(search) & ~self.waking.refinable(search)

    def wake(self, search: PolicySearch) -> None:
        """At the end of an iteration: with no policy left active, wake retired ones
        (``Waking``)."""
        self.waking.wake(search)

    def state_dict(self) -> dict:
        kept = self.returns.state_dict() if self.retire_std > 0 else {}
        return {**kept, **self.waking.state_dict()}

    def load_state_dict(self, state: dict) -> None:
        self.returns.load_state_dict(state)
        self.waking.load_state_dict(state)

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
        if in_valley is None:
            return
        archive, policies = search.archive, search.policy_set
        active = policies.active_flags()
        candidates = [j for j, flag in enumerate(in_valley) if flag and active[j]]
        if not candidates:
            return  # the usual case: no factorisation needed
        best = archive.best_samples(policies.means)
        distance = exploration_distance(search, (best - policies.means)[:, None, :])[:, 0]
        distance = distance.tolist()
        limit = 3.0 + math.sqrt(search.dim)
        # (A covariance that lost definiteness, distance inf, restarts nothing.)
        straddling = [j for j in candidates if math.isfinite(distance[j]) and distance[j] > limit]
        if not straddling:
            return
        # Written row by row into copies: a tell's snapshot holds the tensors themselves.
        policies.means, policies.covariances = policies.means.clone(), policies.covariances.clone()
        for j in straddling:
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
            active = policies.active_flags()
            flags = [a and e for a, e in zip(active, self._exploring_flags(search), strict=True)]
            if tuple(flags) != active:  # (else the tensor stands, and what is memoised on it)
                policies.active = torch.tensor(flags, dtype=torch.bool, device=search.device)
        if self.merge_radius <= 0 or search.num_policies < 2:
            return
        # Only an active policy a judges duplicates (near[a][b], and near[b][a] for an active
        # b): the distances under the active policies' explorations alone, [A, K], where a
        # long run holds dozens of retired policies and a few active ones.
        active = policies.active_flags()
        judges = [a for a in range(len(active)) if active[a]]
        if not judges:
            return
        at = torch.tensor(judges, dtype=torch.long, device=search.device)
        # Mahalanobis distance of policy b's mean under policy a's exploration (inf: a's
        # covariance lost definiteness in float64 and judges no duplicates).
        diff = policies.means[None, :, :] - policies.means[at, None, :]
        # The pairwise decisions below run on the host: A and K are a handful of policies.
        rows = (exploration_distance(search, diff, at) < self.merge_radius).tolist()
        k = len(active)
        near: list[list[bool] | None] = [None] * k
        for a, row in zip(judges, rows, strict=True):
            row[a] = False
            near[a] = row
        best = search.policy_best_rewards.tolist()
        drop = [False] * k
        for a in judges:
            # A policy whose exploration covers two or more others is judged by none of
            # them: exploring that widely (a new policy), it may well be on a hill of its
            # own, which only a hill-valley probe can tell.
            if sum(near[a]) != 1:
                continue
            for b in range(k):
                if a == b or drop[b] or drop[a]:
                    continue
                if not active[b]:
                    duplicate = near[a][b]  # a explores a retired optimum...
                    if duplicate and best[a] > best[b]:
                        drop[b] = True  # ...which stopped short of the top: a goes on
                        continue
                else:
                    duplicate = near[a][b] and near[b][a]
                    # Of two active duplicates the worse one goes.
                    if duplicate and best[a] > best[b]:
                        drop[b] = True
                        continue
                if duplicate:
                    drop[a] = True
        if any(drop):
            dropped = [j for j in range(k) if drop[j]]
            search.remove_policies(torch.tensor(dropped, dtype=torch.long, device=search.device))

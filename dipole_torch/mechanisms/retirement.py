"""A policy's life after it was found: retirement once converged, waking to refine it further,
merging of duplicates, and the restart of a policy whose samples straddle two hills.

* Retirement (``retire_std``, ``retire_spread``): a policy stops being sampled once its
  exploration std has shrunk below its threshold, at first ``retire_std`` times Σ_start's,
  or once its M kept returns spread less than its other threshold, at first
  ``retire_spread`` times the range of every return told (``ReturnRange``: a few returns
  far below or far above all others, a crashed rollout or a glitch, left out; see
  ``_spread`` for a policy that holds one); it stays among the policies, and its trials go
  to the others.
* Waking (``refine``, ``refine_share``, ``refine_gate``, ``wake_while_active``;
  ``Waking``): once no policy is active (with ``wake_while_active``, also beside the
  policies found after every one had retired), the retired ones near the best return at the
  coarsest thresholds are sampled again, each with both thresholds times ``refine`` (one
  more decade with 0.1), when the trials they have taken are within ``refine_share`` of the
  trials after the first convergence; otherwise the run restarts (scouts). A converged
  policy is then not frozen for good: its precision keeps growing while trials remain.
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

from dipole_torch.gaussian import DTYPE, mahalanobis
from dipole_torch.mechanisms.return_range import ReturnRange
from dipole_torch.memo import Memo
from dipole_torch.policy_set import PolicyField

if TYPE_CHECKING:
    from dipole_torch.search import PolicySearch, TellBatch

__all__ = ["NoWaking", "Retirement", "Waking", "exploration_distance"]

# A policy whose exploration std is below this fraction of |θ| + Σ_start's std on every axis
# samples θ only to rounding (float64 resolves 2.2e-16 relative): it is never woken again.
# (Asked in float32, θ rounds at 6e-8 first: the returns then come out equal, and the rule
# for a plateau below stops the wakes.)
FINEST_STD = 1e-12
# A retired policy whose M kept returns spread at least this fraction of the told returns'
# range has a gain still to show (below it: 1e-9 of the range, finer than any accuracy
# asked of the benchmarks, 5e-8 of the range at the finest).
VISIBLE_GAIN = 1e-9
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


def _spread(search: PolicySearch, returns: ReturnRange) -> Tensor:
    """``[K]`` the spread (max − min) of each policy's kept returns; where they straddle an
    end of the range that ``returns`` leaves outliers beyond, the outliers count as that end.

    A policy holding a glitch among returns in the range then spreads no wider than the range
    (not a million ranges). A policy whose kept returns all lie beyond the range (it found a
    success far above the rest, left out of the range while such returns are rare) is judged
    on its own returns, finer than the range: clamped, they would be flat, and it would
    retire on the success it had just found, never to be woken."""
    archive, k = search.archive, search.num_policies
    high, low = archive.per_policy("amax", k), archive.per_policy("amin", k)
    if returns.leaves_out:
        top, bottom = returns.high, returns.low
        high, low = (
            torch.where(low <= top, high.clamp(max=top), high),
            torch.where(high >= bottom, low.clamp(min=bottom), low),
        )
    return high - low


class NoWaking:
    """Retired policies stay retired: every one's thresholds are ``retire_std`` and
    ``retire_spread``."""

    def register(self, search: PolicySearch) -> None:
        """Nothing to keep per policy."""

    def thresholds(self, search: PolicySearch, threshold: float) -> Tensor | float:
        return threshold

    def refining(self, search: PolicySearch) -> Tensor:
        """``[K]`` the policies that were woken (none)."""
        return torch.zeros(search.num_policies, dtype=torch.bool, device=search.device)

    def refinable(self, search: PolicySearch) -> Tensor:
        """``[K]`` the policies a wake could still refine (none)."""
        return torch.zeros(search.num_policies, dtype=torch.bool, device=search.device)

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        pass

    def wake(self, search: PolicySearch) -> None:
        pass

    def state_dict(self) -> dict:
        return {}

    def load_state_dict(self, state: dict) -> None:
        pass


class Waking(NoWaking):
    """Retired policies woken to converge one level further while trials remain.

    A policy retires once its exploration std is below ``retire_std · refine**n`` of
    Σ_start's, or its M kept returns spread less than ``retire_spread · refine**n`` of the
    range of every return told, n (field ``refinements``) the times it was woken. Once
    every policy has retired for the first time, and while no woken policy is active,
    retired policies are woken, n + 1 each, and sampled again with the exploration they
    retired with (the success rule goes on shrinking it):

    * **A gain to show**: the policies whose M kept returns spread at least
      ``VISIBLE_GAIN`` of the range of every return told, and whose best kept return is
      within ``gate`` of that range of the best such policy's, those with the fewest wakes
      (every optimum near the best one level further before any goes two), while the woken
      policies have taken less than ``share`` of the trials since every policy first
      retired. With ``while_active``, such a wake starts even while policies found since are
      active (they share the trials as ``max_sampled`` says); without it, only once none is.
      The gate orders the wakes, best optima first: a policy further below is woken once
      those near the best show no gain left.
    * **Barren restarts**: with no policy active, otherwise one retired policy, whatever
      its returns show: of those within ``gate`` of the best one's return, the least woken,
      and of those the best (highest kept return); while the woken policies have taken less
      than ``share`` of the trials of restarts and woken policies since the last new
      policy. A narrow peak on a broad hill shows no gain until the exploration reaches its
      scale; when the restarts find nothing, the solutions found are the ones to make
      better, each one level further before any goes two (the best one alone, woken level
      after level, was refined to rounding while the others stayed where they retired).

    Otherwise the run restarts as before (the next asks are scouts from the start
    distribution); the first time every policy has retired, it restarts first. The woken
    policies take turns as active ones do (``max_sampled``: the best kept returns first),
    and clusterings leave their samples out as they leave the retired ones'.

    A policy is not woken again once its std is below ``FINEST_STD`` of |θ| + Σ_start's
    std on every axis (θ resolved to rounding), nor while its kept returns are all equal
    (a plateau at its scale, or the returns' rounding: no sample can show a gain).

    Per-policy field: ``refinements`` (n, starting at 0).

    Args:
        refine: factor of the thresholds at each wake, in (0, 1).
        share: the share of the trials after the first convergence (and of those since the
            last new policy) that woken policies may have taken when a wake starts, in
            (0, 1); the restarts that look for new optima take the rest. A wake is not cut
            short: a woken policy runs until it retires at its new threshold, so the
            woken policies' share of the trials can end above ``share`` (on CEC 2013's
            Vincent 2-D and modified Rastrigin at 2000 trials, 0.3–0.8 of the trials after
            the first convergence). Holding it to ``share`` was measured and not kept: the
            docs' niching page says why.
        returns: the range of the returns told (the retirement's), the scale of a visible
            gain.
        gate: the fraction of that range below the best candidate's return within which
            a policy is woken for a gain to show, in [0, 1] (1: every one).
        while_active: wake policies with a gain to show while others are active.
    """

    def __init__(
        self,
        refine: float,
        share: float,
        returns: ReturnRange,
        gate: float = 1.0,
        while_active: bool = False,
    ):
        self.refine = float(refine)
        self.share = float(share)
        self.gate = float(gate)
        self.while_active = bool(while_active)
        self.converged_at = -1  # trials when every policy was first retired (-1: not yet)
        self.refine_trials = 0  # samples of woken policies since then
        # Since the last new policy: trials of restarts (asks with no policy active) and
        # samples of woken policies; the policy ids handed out by then.
        self.barren_restart_trials = 0
        self.barren_refine_trials = 0
        self.known_ids = 0
        self.returns = returns
        self._memo = Memo()

    def register(self, search: PolicySearch) -> None:
        search.policy_set.register("refinements", PolicyField(default=0, dtype=torch.long))

    def thresholds(self, search: PolicySearch, threshold: float) -> Tensor:
        """``[K]`` each policy's retirement threshold, ``threshold · refine**n`` (for
        ``retire_std`` or ``retire_spread``; memoised while the wake counts stand still: not
        to be written into)."""
        refinements = search.policy_set.refinements

        def compute() -> Tensor:
            n = refinements.to(DTYPE)
            return threshold * torch.pow(torch.tensor(self.refine, dtype=DTYPE), n)

        return self._memo.get(("thresholds", threshold), (refinements,), compute)

    def refining(self, search: PolicySearch) -> Tensor:
        """``[K]`` the policies that were woken (n > 0)."""
        return search.policy_set.refinements > 0

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        """The trials of restarts and of woken policies."""
        if not search.started or self.converged_at < 0:
            return
        if not search.policy_set.any_active():
            self.barren_restart_trials += batch.rewards.shape[0]
            return
        owner = batch.owner[: batch.policy_rows]
        woken = int((search.policy_set.refinements[owner] > 0).sum())
        self.refine_trials += woken
        self.barren_refine_trials += woken

    def refinable(self, search: PolicySearch) -> Tensor:
        """``[K]`` the policies a wake could still refine: θ not resolved to rounding, and
        kept returns not all equal."""
        policies = search.policy_set
        std = policies.covariances.diagonal(dim1=-2, dim2=-1).sqrt()
        scale = policies.means.abs() + search.sigma_start.diagonal().sqrt()
        resolved = (std <= FINEST_STD * scale).all(-1)
        counts = search.archive.counts(search.num_policies)
        flat = (_spread(search, self.returns) == 0) & (counts > 1)
        return ~resolved & ~flat

    def visible_gain(self, search: PolicySearch) -> Tensor:
        """``[K]`` whether each policy's M kept returns spread at least
        ``VISIBLE_GAIN`` of the told returns' range."""
        return _spread(search, self.returns) >= self.returns.fraction(VISIBLE_GAIN)

    def near_best(self, search: PolicySearch, candidates: Tensor) -> Tensor:
        """``[K]`` the ``candidates [K]`` (bool) whose best kept return is within ``gate`` of
        the told returns' range of the best candidate's (of the range's high end, where
        returns far above it were left out: a glitch held by one policy does not keep the
        others from their wakes)."""
        best = torch.where(candidates, search.policy_best_rewards, -math.inf)
        top = best.max()
        if self.returns.outliers_above:
            top = top.clamp(max=self.returns.high)
        return candidates & (best >= top - self.returns.fraction(self.gate))

    def least_woken_near_best(self, search: PolicySearch, candidates: Tensor) -> Tensor:
        """``[K]`` of the ``candidates [K]`` (bool, at least one) near the best
        (``near_best``), those woken the fewest times: every optimum near the best one level
        further before any goes two."""
        near = self.near_best(search, candidates)
        return near & (search.policy_set.refinements == search.policy_set.refinements[near].min())

    def wake(self, search: PolicySearch) -> None:
        """Wake retired policies as the class docstring says."""
        policies = search.policy_set
        if search.num_policies == 0:
            return
        busy = policies.any_active()
        if self.converged_at < 0:
            if not busy:
                self.converged_at = search.trials  # the first convergence: restart first
                self.known_ids = policies.next_id
            return
        if busy and (
            not self.while_active or bool((policies.active & self.refining(search)).any())
        ):
            return  # wakes wait for no policy to be active, or a wake is under way
        if not busy and policies.next_id > self.known_ids:  # a new policy: the restarts paid
            self.known_ids = policies.next_id
            self.barren_restart_trials = self.barren_refine_trials = 0
        wakeable = ~policies.active & self.refinable(search)
        since_new = self.barren_refine_trials + self.barren_restart_trials
        barren = self.barren_refine_trials < self.share * since_new
        shared = self.refine_trials < self.share * (search.trials - self.converged_at)
        visible = wakeable & self.visible_gain(search)
        if shared and bool(visible.any()):
            woken = self.least_woken_near_best(search, visible)
        elif not busy and barren and bool(wakeable.any()):
            # One policy: the restarts find nothing, the solutions found can be better; the
            # same order as above, the best of them.
            candidates = self.least_woken_near_best(search, wakeable)
            best = torch.where(candidates, search.policy_best_rewards, -math.inf)
            woken = torch.zeros_like(wakeable)
            woken[int(best.argmax())] = True
        else:
            return
        policies.refinements = torch.where(woken, policies.refinements + 1, policies.refinements)
        policies.active = policies.active | woken

    KEYS = ("converged_at", "refine_trials", "barren_restart_trials", "barren_refine_trials",
            "known_ids")  # fmt: skip

    def state_dict(self) -> dict:
        return {f"waking_{key}": getattr(self, key) for key in self.KEYS}

    def load_state_dict(self, state: dict) -> None:
        # (A checkpoint from before waking: fresh.)
        fresh = Waking(self.refine, self.share, self.returns, self.gate, self.while_active)
        for key in self.KEYS:
            value = state.get(f"waking_{key}", getattr(fresh, key))
            setattr(self, key, type(getattr(fresh, key))(value))


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
        spreads = _spread(search, self.returns).tolist()
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

"""Waking retired policies to converge them one level further while trials remain
(``refine``, ``refine_share``, ``refine_gate``, ``wake_while_active``): once no policy is
active (with ``wake_while_active``, also beside the policies found after every one had
retired), the retired ones near the best return at the coarsest thresholds are sampled
again, each with both thresholds times ``refine`` (one more decade with 0.1), when the
trials they have taken are within ``refine_share`` of the trials after the first
convergence; otherwise the run restarts (scouts). A converged policy is then not frozen for
good: its precision keeps growing while trials remain. ``Retirement``
(``dipole_torch.mechanisms.retirement``) holds the choice and applies the thresholds.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE
from dipole_torch.mechanisms.return_range import ReturnRange
from dipole_torch.memo import Memo
from dipole_torch.policy_set import PolicyField

if TYPE_CHECKING:
    from dipole_torch.search import PolicySearch
    from dipole_torch.tell_batch import TellBatch

__all__ = ["FINEST_STD", "VISIBLE_GAIN", "NoWaking", "Waking"]

# A policy whose exploration std is below this fraction of |θ| + Σ_start's std on every axis
# samples θ only to rounding (float64 resolves 2.2e-16 relative): it is never woken again.
# (Asked in float32, θ rounds at 6e-8 first: the returns then come out equal, and the rule
# for a plateau below stops the wakes.)
FINEST_STD = 1e-12
# A retired policy whose M kept returns spread at least this fraction of the told returns'
# range has a gain still to show (below it: 1e-9 of the range, finer than any accuracy
# asked of the benchmarks, 5e-8 of the range at the finest).
VISIBLE_GAIN = 1e-9


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
        spreads = self.returns.kept_spreads(search.archive, search.num_policies)
        flat = (spreads == 0) & (search.archive.counts(search.num_policies) > 1)
        return ~resolved & ~flat

    def visible_gain(self, search: PolicySearch) -> Tensor:
        """``[K]`` whether each policy's M kept returns spread at least
        ``VISIBLE_GAIN`` of the told returns' range."""
        spreads = self.returns.kept_spreads(search.archive, search.num_policies)
        return spreads >= self.returns.fraction(VISIBLE_GAIN)

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

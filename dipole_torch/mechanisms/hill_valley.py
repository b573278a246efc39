"""Hill-valley vetting (Ursem 1999; Maree et al. 2018): probes between two points tell
whether they lie on one hill or on two.

A probe worse than both ends shows a valley between them. Two uses:

* A candidate — a clustering's new component, or a scout alone in one — becomes a policy
  only if a probe halfway between its best sample and the nearest policy's best sample
  finds a valley (while fewer than ``Dipole.max_policies`` are active); with ``accept_unjudged``
  also when no valley shows but the two lie beyond each other's reach (``PAIR_REACH``). A
  candidate on the hill of a retired policy with a better sample than that policy's best
  replaces it: the retired policy stopped short of the top. A policy accepted that way
  alone is marked (the policy field ``unjudged``), for ``unjudged_share`` to cap its samples
  (``mechanisms.scouting``).
* Every fourth clustering, each active policy is probed against its nearest neighbour
  (``pair_points`` probes along the way) when one of the two explores within
  ``PAIR_REACH`` stds of the other's best sample; of two on one hill the worse goes.

Probes are evaluated at the next ask (owner ``PROBE``: they never
enter the archive) and judged at the tell after it. ``NoVetting`` is the "off" case.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE, mahalanobis
from dipole_torch.mechanisms.retirement import exploration_distance
from dipole_torch.policy_set import PolicyField

if TYPE_CHECKING:
    from dipole_torch.dipole import Dipole
    from dipole_torch.search import PolicySearch
    from dipole_torch.tell_batch import TellBatch

__all__ = ["HillValley", "NoVetting", "make_vetting"]

# Two policies are probed as a pair only when one explores within this many of its stds of
# the other's best sample. Between distant policies a probe that shows no valley is no
# evidence of one hill: a policy still far below its top sits under a ridge that joins its
# hill to the next one (as the viapoint task's routes are joined). Distant duplicates come
# within reach as they climb, or are merged (``merge_radius``). The value 3 is measured
# (docs: Precision and coverage).
PAIR_REACH = 3.0


class NoVetting:
    """Every new component becomes a policy; no probes."""

    vets_new_policies = False

    def register(self, search: PolicySearch) -> None:
        pass

    def probes(self) -> Tensor | None:
        return None

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        pass

    def judge(self, search: PolicySearch) -> None:
        pass

    def queue_probes(self, search: PolicySearch, clustered: bool) -> None:
        pass

    def forget(self) -> None:
        pass

    def state_dict(self, copy: bool = True) -> dict:
        return {}

    def load_state_dict(self, state: dict, device: torch.device) -> None:
        pass


class HillValley(NoVetting):
    """Candidates and neighbouring policies vetted by probes between them.

    Args:
        dim: D.
        device: where the queues live.
        pair_points: probes between two neighbouring policies, at i/(pair_points + 1) of the
            way (1: the midpoint; 3: Ursem's 1/4, 1/2, 3/4).
        cluster_every: iterations between clusterings (pairs are probed every fourth).
        accept_unjudged: a candidate whose probe shows no valley becomes a policy too when
            neither it (its starting covariance) nor the policy it was probed against
            explores within ``PAIR_REACH`` stds of the other's best sample.
        marks_unjudged: keep the policy field ``unjudged`` without ``accept_unjudged`` too,
            for acceptance switched on later in the run (it is kept with it).
    """

    vets_new_policies = True
    TENSORS = (
        "probe_rewards",
        "candidate_means",
        "candidate_covariances",
        "candidate_probes",
        "candidate_thresholds",
        "candidate_partners",
        "candidate_samples",
        "candidate_rewards",
        "candidate_unjudged",
        "pair_index",
        "pair_probes",
    )

    def __init__(
        self,
        dim: int,
        device: torch.device,
        pair_points: int,
        cluster_every: int,
        accept_unjudged: bool = False,
        marks_unjudged: bool = False,
    ):
        self.accept_unjudged = bool(accept_unjudged)
        # (The field is kept from the start when acceptance starts later: ``coverage_from``.)
        self.marks_unjudged = self.accept_unjudged or bool(marks_unjudged)
        self.pair_points = int(pair_points)
        self.cluster_every = int(cluster_every)
        vector = torch.empty(0, dim, dtype=DTYPE, device=device)
        scalar = torch.empty(0, dtype=DTYPE, device=device)
        # The last tell's probe returns (candidates' first, then the pairs').
        self.probe_rewards = scalar
        # Candidates: mean, starting covariance, best sample and its return; once probed,
        # the probe, the threshold a valley must go below and the partner policy.
        self.candidate_means = vector
        self.candidate_covariances = torch.empty(0, dim, dim, dtype=DTYPE, device=device)
        self.candidate_samples = vector
        self.candidate_rewards = scalar
        self.candidate_probes = vector
        self.candidate_thresholds = scalar
        self.candidate_partners = torch.empty(0, dtype=torch.long, device=device)
        # (accept_unjudged) which probed candidates lie beyond reach of their partner.
        self.candidate_unjudged = torch.empty(0, dtype=torch.bool, device=device)
        # Pairs of policies ([P, 2], by index) and their probes ([P·pair_points, D]).
        self.pair_index = torch.empty(0, 2, dtype=torch.long, device=device)
        self.pair_probes = vector

    def register(self, search: PolicySearch) -> None:
        """With ``marks_unjudged``, the policy field ``unjudged``: whether a policy was
        accepted with no valley shown (beyond reach of its partner)."""
        if self.marks_unjudged:
            search.policy_set.register("unjudged", PolicyField(default=False, dtype=torch.bool))

    # ------------------------------------------------------------------ ask and tell
    def probes(self) -> Tensor | None:
        """``[P, D]`` the probes of the next ask: the candidates', then the pairs'."""
        if self.candidate_probes.shape[0] == 0 and self.pair_probes.shape[0] == 0:
            return None  # (the usual case: no concatenation)
        return torch.cat((self.candidate_probes, self.pair_probes))

    def observe(self, search: PolicySearch, batch: TellBatch) -> None:
        """Keep the probes' returns; a cut ask left tests unjudgeable: forget them."""
        if batch.cut:
            self.forget()
        # The probes come last. (A copy: the told returns may be the caller's tensor.)
        self.probe_rewards = batch.rewards[batch.sample_rows : batch.probe_end].clone()

    def forget(self) -> None:
        """Empty the queues of tests (candidates and pairs) and their probes (a cut ask, or
        a changed world whose returns the queued thresholds no longer describe)."""
        for name in self.TENSORS:
            setattr(self, name, getattr(self, name)[:0])

    # ------------------------------------------------------------------ candidates
    def add_candidates(self, means: Tensor, covariances: Tensor, samples: Tensor,
                       rewards: Tensor) -> None:  # fmt: skip
        """Queue new components ``means [C, D]``, ``covariances [C, D, D]``, their best
        samples ``[C, D]`` and those samples' returns ``[C]`` for the test (their samples
        leave the data meanwhile)."""
        self.candidate_means = torch.cat((self.candidate_means, means))
        self.candidate_covariances = torch.cat((self.candidate_covariances, covariances))
        self.candidate_samples = torch.cat((self.candidate_samples, samples))
        self.candidate_rewards = torch.cat((self.candidate_rewards, rewards))

    def queue_probes(self, search: PolicySearch, clustered: bool) -> None:
        """Probe the queued candidates; after every fourth clustering, the pairs too."""
        self._probe_candidates(search)
        if clustered and (search.iteration // self.cluster_every) % 4 == 0:
            self._probe_pairs(search)

    def _probe_candidates(self, search: PolicySearch) -> None:
        """Each queued candidate against the policy nearest to it: the midpoint between the
        two best samples is evaluated at the next ask (with no policy left, every candidate
        becomes one)."""
        c = self.candidate_means.shape[0]
        if c == 0:
            return
        if search.num_policies == 0:
            self._accept(search, torch.ones(c, dtype=torch.bool, device=search.device))
            return
        partners = search.archive.best_samples(search.policy_means)
        distance = self._nearest(search, self.candidate_samples, partners)  # [C, K]
        nearest = distance.argmin(-1)
        self.candidate_probes = 0.5 * (self.candidate_samples + partners[nearest])
        self.candidate_thresholds = torch.minimum(
            self.candidate_rewards, search.policy_best_rewards[nearest]
        )
        self.candidate_partners = nearest
        if self.marks_unjudged:  # (also before acceptance starts: judged after it)
            # Beyond reach both ways: the partner's exploration to the candidate's best
            # sample, the candidate's starting covariance to the partner's.
            gap = (partners[nearest] - self.candidate_samples)[:, None, :]  # [C, 1, D]
            from_partner = exploration_distance(search, -gap, nearest)[:, 0]
            chol, info = torch.linalg.cholesky_ex(self.candidate_covariances)
            # (A covariance that does not factorise is no reason to accept: within reach.)
            from_candidate = torch.where(info == 0, mahalanobis(chol, gap)[:, 0], 0.0)
            reach = torch.minimum(from_partner, from_candidate)
            self.candidate_unjudged = reach >= PAIR_REACH

    def judge(self, search: PolicySearch) -> None:
        """Accept the candidates whose probe found a valley, and those on the hill of a
        retired policy with a better sample than its best (it is replaced); forget the
        others. Then judge the probed pairs of policies."""
        n = self.candidate_probes.shape[0]
        pair_rewards = self.probe_rewards[n:]
        if n:
            partners = self.candidate_partners
            valley = self.probe_rewards[:n] < self.candidate_thresholds
            refutes = (
                ~valley
                & ~search.active[partners]
                & (self.candidate_rewards > search.policy_best_rewards[partners])
            )
            accept = valley | refutes
            unjudged = None
            if self.accept_unjudged:
                unjudged = self.candidate_unjudged & ~accept
                accept = accept | unjudged
            self._place(search, refutes)
            accepted = self._accept(search, accept, unjudged)
            replaced = partners[accepted[refutes[accepted]]].unique()
            if replaced.numel():
                # Pair probes were chosen by index: they no longer apply.
                self._clear_pairs()
                pair_rewards = pair_rewards[:0]
                search.remove_policies(replaced)
        self._judge_pairs(search, pair_rewards)

    def _place(self, search: PolicySearch, refutes: Tensor) -> None:
        """Where the judged candidates would start (``refutes [C]``: the candidates that
        replace their retired partner, the others being new hills).

        * A replacement starts from its refuting sample, the best point known on that hill,
          not from its component's mean, which may lie on the next hill.
        * Each explores at most half the way to its partner, in Σ_start's per-axis stds:
          for a new hill a valley lies in between, so the hill is no wider, and a wider
          start spends its first samples on the neighbour's hill. A replacement explores at
          least as widely as the policy it replaces."""
        self.candidate_means = torch.where(
            refutes[:, None], self.candidate_samples, self.candidate_means
        )
        scale = search.sigma_start.diagonal().sqrt()
        half_gap = ((self.candidate_probes - self.candidate_samples) / scale).norm(dim=-1)
        partner = search.relative_std()[self.candidate_partners]
        half_gap = torch.where(refutes, torch.maximum(half_gap, partner), half_gap)
        relative = search.relative_std(self.candidate_covariances)
        factor = (half_gap / relative.clamp_min(1e-300)).clamp(max=1.0).square()
        self.candidate_covariances = factor[:, None, None] * self.candidate_covariances

    def _accept(self, search: Dipole, accept: Tensor, unjudged: Tensor | None = None) -> Tensor:
        """New policies from the ``accept``-ed candidates ``[C]`` (within the cap in force,
        ``Dipole.max_policies``, the best first), those accepted ``unjudged [C]`` marked so;
        the candidate queue is emptied. Returns the indices of the candidates that became
        policies."""
        index = accept.nonzero().squeeze(-1)
        if search.max_policies is not None:
            room = max(search.max_policies - sum(search.policy_set.active_flags()), 0)
            index = index[torch.argsort(self.candidate_rewards[index], descending=True)][:room]
        n = index.numel()
        if n:
            k = search.num_policies
            # (Not given: every new policy at the field's default, judged.)
            marks = {} if unjudged is None else {"unjudged": unjudged[index]}
            search.policy_set.extend(
                self.candidate_means[index], self.candidate_covariances[index], **marks
            )
            search.archive.append(
                self.candidate_samples[index],
                self.candidate_rewards[index],
                k + torch.arange(n, device=search.device),
            )
        for name in self.TENSORS:
            if name.startswith("candidate_"):
                setattr(self, name, getattr(self, name)[:0])
        return index

    # ------------------------------------------------------------------ pairs
    def _probe_pairs(self, search: PolicySearch) -> None:
        """Queue probes between every active policy and the policy nearest to it, when one
        of the two explores within ``PAIR_REACH`` stds of the other's best sample: two
        policies on one hill are one optimum.

        Each pair's ``pair_points`` probes lie at i/(pair_points + 1) of the way between the
        two best samples: between two policies still far below their tops the valley lies
        nearer the worse one, where a midpoint can miss it."""
        if search.num_policies < 2 or not search.policy_set.any_active():
            self._clear_pairs()
            return
        best = search.archive.best_samples(search.policy_means)
        distance = self._nearest(search, best, best)
        distance.fill_diagonal_(math.inf)
        a = search.active.nonzero().squeeze(-1)
        b = distance[a].argmin(-1)
        pairs = torch.stack((torch.minimum(a, b), torch.maximum(a, b)), -1).unique(dim=0)
        first, second = pairs[:, 0], pairs[:, 1]
        gap = (best[second] - best[first])[:, None, :]  # [P, 1, D]
        reach = torch.minimum(
            exploration_distance(search, gap, first)[:, 0],
            exploration_distance(search, -gap, second)[:, 0],
        )
        pairs = pairs[reach < PAIR_REACH]
        self.pair_index = pairs
        n = self.pair_points
        t = torch.arange(1, n + 1, dtype=DTYPE, device=search.device) / (n + 1)
        start, end = best[pairs[:, 0], None, :], best[pairs[:, 1], None, :]
        # (1 − t)·a + t·b: for t = ½ bit for bit the midpoint ½(a + b) of pair_points = 1.
        probes = (1 - t)[:, None] * start + t[:, None] * end
        self.pair_probes = probes.reshape(-1, search.dim)  # [P * pair_points, D], pair-major

    def _judge_pairs(self, search: PolicySearch, probe_rewards: Tensor) -> None:
        """Drop the worse policy of each probed pair that shows no valley between them (no
        probe worse than both ends; a retired policy goes only for a strictly better active
        one: it claimed the top of the hill, which the active one refutes)."""
        if self.pair_index.shape[0] == 0:
            return
        best = search.policy_best_rewards
        active = search.active
        a, b = self.pair_index[:, 0], self.pair_index[:, 1]
        lowest = probe_rewards.reshape(a.shape[0], -1).amin(-1)
        same_hill = lowest >= torch.minimum(best[a], best[b])
        # Ties go against the active one: the retired one's top stands.
        drop_b = torch.where(
            active[a] != active[b],
            torch.where(active[b], best[b] <= best[a], best[b] < best[a]),
            best[b] < best[a],
        )
        loser = torch.where(drop_b, b, a)[same_hill]
        self._clear_pairs()
        if loser.numel():
            search.remove_policies(loser.unique())

    def _clear_pairs(self) -> None:
        self.pair_index, self.pair_probes = self.pair_index[:0], self.pair_probes[:0]

    @staticmethod
    def _nearest(search: PolicySearch, points: Tensor, others: Tensor) -> Tensor:
        """``[P, Q]`` distances between ``points: [P, D]`` and ``others: [Q, D]`` in units of
        Σ_start's per-axis std (the scale the pairs are chosen in)."""
        scale = search.sigma_start.diagonal().sqrt()
        return torch.cdist(points / scale, others / scale)

    # ------------------------------------------------------------------ checkpoints
    def state_dict(self, copy: bool = True) -> dict[str, Tensor]:
        """The queues: copies, or (``copy=False``) the tensors themselves, which the
        queues replace and never write into."""
        return {
            name: getattr(self, name).clone() if copy else getattr(self, name)
            for name in self.TENSORS
        }

    def load_state_dict(self, state: dict, device: torch.device) -> None:
        for name in self.TENSORS:
            if name == "candidate_unjudged" and name not in state:  # (a checkpoint from before)
                value = torch.zeros(len(state["candidate_probes"]), dtype=torch.bool)
            else:
                value = state[name]
            if not isinstance(value, Tensor) or value.dim() != getattr(self, name).dim():
                raise ValueError(f"state_dict[{name!r}] does not fit the hill-valley queues")
            setattr(self, name, value.to(device))


def make_vetting(
    hill_valley: bool,
    dim: int,
    device: torch.device,
    pair_points: int,
    cluster_every: int,
    accept_unjudged: bool = False,
    marks_unjudged: bool = False,
) -> NoVetting:
    """``HillValley`` with ``hill_valley``, else ``NoVetting``."""
    if not hill_valley:
        return NoVetting()
    return HillValley(dim, device, pair_points, cluster_every, accept_unjudged, marks_unjudged)

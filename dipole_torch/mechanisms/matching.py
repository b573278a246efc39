"""What a clustering does to the policies: which samples it sees, where its chain starts, and
how its components become policies.

* ``ReplaceMatching`` — the paper: the IGMM's components *are* the policies. Every
  clustering sees all kept samples, starts from the last clustering's components (at the
  policies' current means) and its components replace the policies.
* ``OverlapMatching`` — the default: a policy lives on across clusterings (its
  exploration, its success rate, whether it retired). A clustering sees the active policies'
  samples and the scouts, starts with one component per active policy and one per scout, and
  a component continues the old policy that owns most of its samples (matched greedily,
  largest overlap first, ``match_by_overlap``); the other components become new
  policies, the best first, while fewer than ``max_policies`` are active — or candidates for
  the hill-valley test. Old policies left without a component were merged by the DP and are
  dropped.

The first clustering, of the n0 initial samples, makes its components the policies either way
(``adopt_components``).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import mahalanobis
from dipole_torch.mechanisms.exploration import MIN_RELATIVE_STD, start_spread
from dipole_torch.policy_set import PolicyField
from dipole_torch.power import importance_rows

if TYPE_CHECKING:
    from dipole_torch.dipole import Dipole

__all__ = [
    "OverlapMatching",
    "ReplaceMatching",
    "adopt_components",
    "capped_start",
    "match_by_overlap",
    "policy_and_scout_rows",
]


def adopt_components(search: Dipole, state: DPMixtureState) -> Tensor:
    """Make the components of ``state`` (a clustering of every kept sample) the policies:
    their θ-means, the exploration their posterior covariances give, their samples; then the
    ``max_policies`` best are kept and each keeps its best M samples.

    Returns:
        ``[K]`` the component of each policy.
    """
    d = search.dim
    search.dp_state = state
    search.policy_set.reset(
        state.means[:, :d].clone(),
        search.exploration.starting_covariance(search, state.covariances[:, :d, :d]),
    )
    search.archive.owner = state.labels.clone()
    kept = torch.ones(state.num_components, dtype=torch.bool, device=search.device)
    max_policies = search.max_policies
    if max_policies is not None:
        best = search.policy_best_rewards
        dropped = torch.argsort(best, descending=True, stable=True)[max_policies:]
        if dropped.numel():
            search.remove_policies(dropped)
            kept[dropped] = False
    keep_importance_sets(search)
    return kept.nonzero().squeeze(-1)


def keep_importance_sets(search: Dipole) -> None:
    """Keep each policy's best M samples (every sample has a policy here)."""
    archive = search.archive
    kept, _, _ = importance_rows(archive.owner, archive.rewards, search.num_policies, search.M)
    archive.keep(kept)


class ReplaceMatching:
    """The paper's: every clustering's components replace the policies.

    A policy remembers its component (field ``component``), so that the next clustering's
    chain starts from the last components even after policies were dropped in between."""

    def register(self, search: Dipole) -> None:
        search.policy_set.register("component", PolicyField(default=-1, dtype=torch.long))

    def clustered_rows(self, search: Dipole) -> Tensor:
        """``[N]`` every kept sample."""
        return torch.arange(len(search.archive), device=search.device)

    def warm_start(self, search: Dipole, y: Tensor, rows: Tensor) -> DPMixtureState:
        """The last clustering's components, at the policies' current means and with the
        policies' samples; with scouts (which belong to no component), the partition of
        the policies' samples and one singleton per scout instead."""
        owner = search.archive.owner[rows]
        component = search.policy_set.component
        if bool((owner < 0).any()) or bool((component < 0).any()):
            labels = _start_labels(owner, search.num_policies)
            return DPMixtureState.from_labels(y, labels, search.dp_state.prior)
        return DPMixtureState(
            labels=owner.clone(),
            means=torch.cat((search.policy_means, search.dp_state.means[component, -1:]), dim=1),
            covariances=search.dp_state.covariances[component],
            prior=search.dp_state.prior,
        )

    def apply(self, search: Dipole, rows: Tensor, y: Tensor, state: DPMixtureState) -> None:
        """The components replace the policies."""
        self.adopted(search, adopt_components(search, state))

    def adopted(self, search: Dipole, components: Tensor) -> None:
        """After ``adopt_components``: policy k is component ``components[k]``."""
        search.policy_set.component = components


class OverlapMatching:
    """The default: components matched to the policies they continue; the rest become new
    policies or hill-valley candidates, each starting no wider than ``start_cap`` times its
    distance to the nearest policy (``capped_start``).

    Args:
        start_cap: the cap's fraction of that distance (0: no cap).
    """

    def __init__(self, start_cap: float = 0.0):
        self.start_cap = float(start_cap)

    def register(self, search: Dipole) -> None:
        """Nothing to keep per policy."""

    def adopted(self, search: Dipole, components: Tensor) -> None:
        """Nothing to record after the first clustering."""

    def clustered_rows(self, search: Dipole) -> Tensor:
        """``[N']`` the samples of the clustered policies (``Dipole.clustered_policies``:
        the active ones but for those woken to refine) and the scouts (retired and refining
        policies keep theirs out of it); none when that is one policy's samples alone.

        One policy's kept samples and no scout (its importance set: M points) leave a
        clustering nothing to match but that policy, and almost never a new component; the
        clustering is skipped, for its cost in runs with one active policy (not in the paper,
        whose variant matches by ``"replace"``; docs: Speed)."""
        owner, clustered = search.archive.owner, search.clustered_policies
        if sum(clustered.tolist()) <= 1 and not bool((owner < 0).any()):
            return owner[:0]
        return policy_and_scout_rows(owner, clustered)

    def warm_start(self, search: Dipole, y: Tensor, rows: Tensor) -> DPMixtureState:
        """One component per clustered policy (its samples) and one per scout."""
        old = search.archive.owner[rows]
        active = search.clustered_policies.nonzero().squeeze(-1)
        compact = torch.full((search.num_policies,), -1, dtype=torch.long, device=search.device)
        compact[active] = torch.arange(active.numel(), device=search.device)
        labels = _start_labels(torch.where(old >= 0, compact[old.clamp_min(0)], old),
                               active.numel())  # fmt: skip
        return DPMixtureState.from_labels(y, labels, search.dp_state.prior)

    def apply(self, search: Dipole, rows: Tensor, y: Tensor, state: DPMixtureState) -> None:
        """Continue, create, vet or drop policies after a clustering ``state`` of ``y``
        (the augmented samples ``rows`` of the archive).

        Which component continues which policy, which become new ones and where every
        sample goes is bookkeeping over a handful of integers (policies, components, one
        clustering's samples): it runs on the host, each tensor read once (``tolist``);
        only the new policies' means and covariances are tensor maths."""
        d = search.dim
        archive, policies = search.archive, search.policy_set
        search.dp_state = state
        labels = state.labels
        k_new = state.num_components
        label_of = labels.tolist()  # [N'] the component of each clustered sample
        row_of = rows.tolist()  # [N'] its archive row
        owner_of = archive.owner.tolist()  # [N] every sample's policy
        returns = archive.rewards[rows].tolist()  # [N']
        clustered = search.clustered_policies.tolist()  # [K]
        k = len(clustered)
        active = [j for j in range(k) if clustered[j]]
        compact = [-1] * k  # a clustered policy's position among them
        for position, j in enumerate(active):
            compact[j] = position
        owned = [
            (label_of[i], compact[owner_of[r]]) for i, r in enumerate(row_of) if owner_of[r] >= 0
        ]
        continues = _match_by_overlap(owned, k_new, active)
        # New components, best sample first, while there is room.
        component_best = [-math.inf] * k_new
        for c, value in zip(label_of, returns, strict=True):
            component_best[c] = max(component_best[c], value)
        fresh = [c for c in range(k_new) if continues[c] < 0]
        fresh.sort(key=component_best.__getitem__, reverse=True)  # (stable: ties by index)
        continued = [c for c in range(k_new) if continues[c] >= 0]
        max_policies = search.max_policies
        flags = policies.active_flags()
        refining = sum(1 for j in range(k) if flags[j] and not clustered[j])
        room = (
            len(fresh) if max_policies is None else max(max_policies - refining - len(continued), 0)
        )
        fresh = fresh[:room]
        # The policies after it: those left out (retired, refining), continued ones, then new
        # ones.
        keep_old = [j for j in range(k) if not clustered[j]] + [continues[c] for c in continued]
        new_index = [-1] * k
        for position, j in enumerate(keep_old):
            new_index[j] = position
        component_policy = [-1] * k_new
        for c in continued:
            component_policy[c] = new_index[continues[c]]
        vet = search.vetting.vets_new_policies and len(keep_old) > 0
        weights = y[:, -1]
        new_means, new_covs, candidates = [], [], []
        for c in fresh:
            members = labels == c
            w = weights[members]
            mean = (w[:, None] * y[members, :d]).sum(0) / w.sum()  # eq. 7's average
            covariance = search.exploration.starting_covariance(
                search, state.covariances[c, :d, :d]
            )
            if self.start_cap > 0:
                covariance = capped_start(search, mean[None], covariance[None], self.start_cap)[0]
            if vet:
                # Its best sample (the first best, as argmax), to be compared with the
                # nearest policy's; its samples leave the data meanwhile.
                own = [i for i, label in enumerate(label_of) if label == c]
                best = max(own, key=returns.__getitem__)
                candidates.append((mean, covariance, y[best, :d], archive.rewards[row_of[best]]))
                continue
            component_policy[c] = len(keep_old) + len(new_means)
            new_means.append(mean)
            new_covs.append(covariance)
        if candidates:
            search.vetting.add_candidates(*(torch.stack(x) for x in zip(*candidates, strict=True)))
        policies.index(torch.tensor(keep_old, dtype=torch.long, device=search.device))
        if new_means:
            policies.extend(torch.stack(new_means), torch.stack(new_covs))
        # Re-own the samples: those left out keep theirs, clustered ones follow their component
        # (a component that became no policy loses its samples).
        owner = [new_index[o] if o >= 0 else -1 for o in owner_of]
        for r, c in zip(row_of, label_of, strict=True):
            owner[r] = component_policy[c]
        kept = [i for i, o in enumerate(owner) if o >= 0]
        archive.owner = torch.tensor(owner, dtype=torch.long, device=search.device)
        archive.keep(torch.tensor(kept, dtype=torch.long, device=search.device))
        keep_importance_sets(search)


def capped_start(search: Dipole, means: Tensor, covariances: Tensor, fraction: float) -> Tensor:
    """``[F, D, D]`` new policies' starting ``covariances`` (``[F, D, D]``, at ``means [F,
    D]``), each scaled down where wider to a spread tr(Σ_start⁻¹ Σ)/D of (fraction · d)²,
    d the Σ_start-whitened distance from its mean to the nearest policy mean: its std on
    Σ_start's axes at most ``fraction`` of the way to its neighbour.

    A component of a few scouts takes its spread from the scouts around it, up to Σ_start's;
    near another policy that spread reaches across the valley between them, so the new
    policy climbs the neighbour's hill and is later merged or dropped as its duplicate,
    having taken the trials a new optimum needed (docs: Niching). Unchanged without
    policies, or with ``fraction`` 0. A mean on a policy's own gets a spread of
    ``MIN_RELATIVE_STD``² (still positive definite): it retires at once.
    """
    others = search.policy_means
    if fraction <= 0 or others.shape[0] == 0:
        return covariances
    chol = torch.linalg.cholesky(search.sigma_start)
    diff = (others[None] - means[:, None]).to(chol.dtype)  # [F, K, D]
    distance = mahalanobis(chol, diff).amin(-1)  # [F]
    spread = start_spread(search, covariances.to(chol.dtype))  # [F]
    cap = (fraction * distance).square().clamp_min(MIN_RELATIVE_STD**2)
    scale = torch.where(spread > cap, cap / spread, 1.0)
    return covariances * scale[:, None, None].to(covariances.dtype)


def policy_and_scout_rows(owner: Tensor, clustered: Tensor) -> Tensor:
    """``[N']`` the rows of an archive's ``owner [N]`` that are samples of the ``clustered
    [K]`` (bool) policies or scouts (owner < 0)."""
    return ((owner < 0) | clustered[owner.clamp_min(0)]).nonzero().squeeze(-1)


def match_by_overlap(labels: Tensor, old: Tensor, num_components: int, policies: Tensor) -> Tensor:
    """``[C]`` the old policy each new component continues (−1: none), matched greedily,
    largest overlap first: a component continues the policy that owns most of its samples
    among those not yet matched.

    Args:
        labels: ``[N]`` new component of each sample that an old policy owned.
        old: ``[N]`` the old policy's position in ``policies`` of each such sample.
        num_components: C.
        policies: ``[P]`` the old policies' indices.
    """
    pairs = list(zip(labels.tolist(), old.tolist(), strict=True))
    continues = _match_by_overlap(pairs, num_components, policies.tolist())
    return torch.tensor(continues, dtype=torch.long, device=labels.device)


def _match_by_overlap(
    pairs: list[tuple[int, int]], num_components: int, policies: list[int]
) -> list[int]:
    """``match_by_overlap`` on the host: ``pairs`` lists (component, position in
    ``policies``) of each sample an old policy owned. Of equal overlaps the first in
    (component, policy) order is matched first, as ``argmax`` of the flattened counts."""
    # Greedy matching on the sparse counts, largest first (ties by (component, policy)):
    # O(N log N) in the samples, where rescanning a C × P table for each match grew as
    # C·P·min(C, P) with the number of policies (``max_policies=None``).
    overlap: dict[tuple[int, int], int] = {}
    for pair in pairs:
        overlap[pair] = overlap.get(pair, 0) + 1
    continues = [-1] * num_components
    taken = [False] * len(policies)
    for (c, j), _ in sorted(overlap.items(), key=lambda item: (-item[1], item[0])):
        if continues[c] < 0 and not taken[j]:
            continues[c] = policies[j]
            taken[j] = True
    return continues


def _start_labels(owner: Tensor, num_policies: int) -> Tensor:
    """``[N]`` warm-start labels: a policy's samples share its label, each scout (owner −1)
    gets one of its own after the policies'."""
    scouts = owner < 0
    labels = owner.clone()
    labels[scouts] = num_policies + torch.arange(int(scouts.sum()), device=owner.device)
    return labels

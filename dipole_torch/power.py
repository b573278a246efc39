"""PoWER's step (Kober & Peters 2011; the paper's Algorithm 3), batched over policies: eq. 7
(``power_update``) on each policy's importance set.

The importance sets ("select the best M points") come in two variants, one object each:

* ``GlobalImportance`` — the paper's DIPOLE and PoWER: "importance sampling is performed
  by keeping a fixed number of elements K·M at every iteration" — the best K·M samples
  overall; each policy then averages its own best M among them, weighted by the reward
  weights of all kept returns.
* ``PolicyImportance`` — the default of ``Dipole``: every policy keeps
  its own best M, weighted by the min–max of its own M returns, so a policy on an optimum as
  good as the others' is not lost when its latest samples are a little worse than theirs.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.archive import HOST_ROWS
from dipole_torch.gaussian import DTYPE

if TYPE_CHECKING:
    from dipole_torch.search import PolicySearch

__all__ = [
    "GlobalImportance",
    "PolicyImportance",
    "importance_sets",
    "make_importance",
    "power_update",
]


def power_update(
    mean: Tensor, samples: Tensor, weights: Tensor, *, validate: bool = True
) -> Tensor:
    """Eq. 7 for K policies at once.

    θ_k ← θ_k + Σ_m w_km (θ_km − θ_k) / Σ_m w_km.

    Args:
        mean: ``[K, D]`` current policy parameters θ^(n−1).
        samples: ``[K, M, D]`` each policy's importance set (its best M samples).
        weights: ``[K, M]`` non-negative reward weights; 0 marks padding. A policy whose
            weights are all 0 keeps its mean.
        validate: check the shapes and the weights' signs (``False``: weights built
            non-negative, as ``PolicyImportance.slot_weights`` makes them).

    Returns:
        ``[K, D]`` updated parameters θ^(n).
    """
    if validate and (
        mean.dim() != 2
        or samples.dim() != 3
        or samples.shape[:-1] != weights.shape
        or samples.shape[0] != mean.shape[0]
        or samples.shape[-1] != mean.shape[-1]
    ):
        raise ValueError(
            f"power_update: expected mean [K, D], samples [K, M, D], weights [K, M]; got "
            f"{list(mean.shape)}, {list(samples.shape)}, {list(weights.shape)}"
        )
    if validate and not bool((weights >= 0).all()):  # (a NaN is not >= 0 either)
        raise ValueError("power_update: weights must be non-negative numbers (no NaN)")
    total = weights.sum(-1, keepdim=True)  # [K, 1]
    step = (weights.unsqueeze(-1) * (samples - mean.unsqueeze(-2))).sum(-2)
    return torch.where(
        total > 0, mean + step / total.clamp_min(torch.finfo(total.dtype).tiny), mean
    )


def importance_sets(
    owner: Tensor, rewards: Tensor, num_policies: int, size: int
) -> tuple[Tensor, Tensor, Tensor]:
    """Each policy's best ``size`` samples (Algorithm 3's "select the best M points").

    Args:
        owner: ``[N]`` policy index of every sample.
        rewards: ``[N]`` rewards (higher is better).
        num_policies: K.
        size: M.

    Returns:
        keep ``[N]`` bool mask of the samples in some importance set (≤ K·M of them);
        index ``[K, M]`` sample index of each slot (−1 for an empty slot, best first);
        valid ``[K, M]`` bool mask of filled slots.

    Ties go to the earlier sample. On the CPU, up to ``HOST_ROWS`` samples, the sets are
    chosen in Python scalars (``_host_sets``); otherwise in tensor operations
    (``_tensor_sets``): the same sets.
    """
    if not _on_host(owner):
        return _tensor_sets(owner, rewards, num_policies, size)
    sets, chosen = _host_sets(owner.tolist(), rewards.tolist(), num_policies, size)
    index = torch.tensor(_padded(sets, size, -1), dtype=torch.long).reshape(num_policies, size)
    return torch.tensor(chosen, dtype=torch.bool), index, index >= 0


def importance_rows(
    owner: Tensor, rewards: Tensor, num_policies: int, size: int
) -> tuple[Tensor, Tensor, Tensor]:
    """``importance_sets`` of the samples that policies own, in an archive that holds
    samples of no policy too (owner < 0), as rows of that archive.

    Args:
        owner: ``[N]`` policy index of every sample (< 0: no policy).
        rewards: ``[N]`` rewards (higher is better).
        num_policies: K.
        size: M.

    Returns:
        kept ``[R]`` the rows to keep, in archive order: every sample of no policy and
        every sample in an importance set;
        index ``[K, M]`` the row of each slot (best first; in an empty slot the first owned
        row, or row 0 when no row is owned, to be weighted 0);
        valid ``[K, M]`` bool mask of filled slots.
    """
    if not _on_host(owner):
        return _tensor_rows(owner, rewards, num_policies, size)
    owners = owner.tolist()
    sets, kept = _host_rows(owners, rewards.tolist(), num_policies, size)
    # With no owned row (every kept sample a scout's), the empty slots point at row 0.
    empty = next((row for row, policy in enumerate(owners) if policy >= 0), 0)
    index = torch.tensor(_padded(sets, size, empty), dtype=torch.long).reshape(num_policies, size)
    filled = [[True] * len(rows) for rows in sets]
    valid = torch.tensor(_padded(filled, size, False), dtype=torch.bool)
    kept_rows = torch.tensor(kept, dtype=torch.long)
    return kept_rows, index, valid.reshape(num_policies, size)


# Up to HOST_ROWS samples (``dipole_torch.archive``) the importance sets are chosen in Python
# scalars on the CPU.
_TINY = torch.finfo(DTYPE).tiny


def _on_host(owner: Tensor) -> bool:
    """Whether the sets of ``owner [N]`` are chosen in Python scalars."""
    return owner.device.type == "cpu" and owner.shape[0] <= HOST_ROWS


def _host_sets(
    owner: Sequence[int], rewards: Sequence[float], num_policies: int, size: int
) -> tuple[list[list[int]], list[bool]]:
    """The rows of each policy's importance set, best first (ties: the earlier row first,
    Python's sort being stable), as K lists of at most ``size`` rows, and ``[N]`` whether each
    row is in one; rows of owner < 0 belong to none."""
    groups: list[list[int]] = [[] for _ in range(num_policies)]
    for row, policy in enumerate(owner):
        if policy >= 0:
            groups[policy].append(row)
    sets = [sorted(rows, key=lambda row: -rewards[row])[:size] for rows in groups]
    chosen = [False] * len(owner)
    for rows in sets:
        for row in rows:
            chosen[row] = True
    return sets, chosen


def _host_rows(
    owner: Sequence[int], rewards: Sequence[float], num_policies: int, size: int
) -> tuple[list[list[int]], list[int]]:
    """``_host_sets`` of an archive that holds samples of no policy too (owner < 0): the K
    sets, and the rows to keep in archive order (every sample of no policy and every sample
    in a set)."""
    sets, chosen = _host_sets(owner, rewards, num_policies, size)
    return sets, [row for row, policy in enumerate(owner) if policy < 0 or chosen[row]]


def _host_weights(returns: list[float], floor: float) -> list[float]:
    """``PolicyImportance.slot_weights`` of one policy's kept ``returns`` (best first), in
    Python scalars: each mapped onto [floor, 1] by their min–max, all 1 when they are equal."""
    low, high = min(returns), max(returns)
    spread = high - low
    if not spread > 0:
        return [1.0] * len(returns)
    scale = max(spread, _TINY)
    return [min(max((value - low) / scale, floor), 1.0) for value in returns]


def _padded(rows: list[list], size: int, fill) -> list:
    """``rows`` flattened, each row padded to ``size`` with ``fill``."""
    return [item for row in rows for item in (*row, *[fill] * (size - len(row)))]


def _tensor_sets(
    owner: Tensor, rewards: Tensor, num_policies: int, size: int
) -> tuple[Tensor, Tensor, Tensor]:
    """``importance_sets`` in tensor operations, on any device (no host sync)."""
    n = owner.shape[0]
    # Group by owner, best reward first inside each group (two stable sorts).
    by_reward = torch.sort(rewards, descending=True, stable=True).indices
    order = by_reward[torch.sort(owner[by_reward], stable=True).indices]
    counts = torch.bincount(owner, minlength=num_policies)
    starts = torch.cumsum(counts, 0) - counts
    rank = torch.arange(n, device=owner.device) - starts[owner[order]]
    in_set = rank < size
    keep = torch.zeros(n, dtype=torch.bool, device=owner.device)
    keep[order[in_set]] = True
    index = torch.full((num_policies, size), -1, dtype=torch.long, device=owner.device)
    index[owner[order[in_set]], rank[in_set]] = order[in_set]
    return keep, index, index >= 0


def _tensor_rows(
    owner: Tensor, rewards: Tensor, num_policies: int, size: int
) -> tuple[Tensor, Tensor, Tensor]:
    """``importance_rows`` in tensor operations, on any device."""
    owned = (owner >= 0).nonzero().squeeze(-1)
    keep, index, valid = _tensor_sets(owner[owned], rewards[owned], num_policies, size)
    kept = owner < 0
    kept[owned[keep]] = True
    # With no owned row (every kept sample a scout's), the empty slots point at row 0.
    rows = owned[index.clamp_min(0)] if owned.numel() else torch.zeros_like(index)
    return kept.nonzero().squeeze(-1), rows, valid


class PolicyImportance:
    """Each policy keeps its own best M samples; eq. 7 weighs them by the min–max map of its
    own M returns (best 1, worst ``reward_floor``)."""

    # Whether ``power_step`` takes ``_host_step`` on the CPU (at most ``HOST_ROWS`` samples).
    has_host_path = True

    def power_step(self, search: PolicySearch) -> None:
        """Eq. 7 for every active policy on its importance set; the other samples policies
        own are dropped (samples of no policy, the scouts, are kept)."""
        if self.has_host_path and _on_host(search.archive.owner):
            self._host_step(search)
        else:
            self._tensor_step(search)

    def _tensor_step(self, search: PolicySearch) -> None:
        """``power_step`` in tensor operations, on any device."""
        archive, policies = search.archive, search.policy_set
        kept, index, valid = importance_rows(
            archive.owner, archive.rewards, search.num_policies, search.M
        )
        weights = self.slot_weights(search, index, valid)
        means = power_update(
            policies.means, archive.thetas[index], weights, validate=not self.unit_weights(search)
        )
        if not all(policies.active_flags()):  # (else every policy takes its step)
            means = torch.where(policies.active[:, None], means, policies.means)
        policies.means = means
        archive.keep(kept)

    def _host_step(self, search: PolicySearch) -> None:
        """``power_step`` on the CPU at an archive's usual sizes: the sets and the weights in
        Python scalars, eq. 7 for the active policies alone (a dozen calls an iteration where
        the tensor path makes some thirty; the same numbers: each policy's step is its own
        row's, and the scalars are the tensor path's float64 operations)."""
        archive, policies = search.archive, search.policy_set
        owner, rewards = archive.host_lists()
        sets, kept = _host_rows(owner, rewards, search.num_policies, search.M)
        stepping = [k for k, flag in enumerate(policies.active_flags()) if flag and sets[k]]
        if stepping:
            size, floor = search.M, search.reward_scale.floor
            rows: list[int] = []
            weights: list[float] = []
            for k in stepping:
                slots = sets[k]
                returns = [rewards[row] for row in slots]
                weights += _host_weights(returns, floor) + [0.0] * (size - len(slots))
                rows += slots + [slots[0]] * (size - len(slots))  # (padding: weight 0)
            at = torch.tensor(stepping, dtype=torch.long)
            index = torch.tensor(rows, dtype=torch.long).view(len(stepping), size)
            means = power_update(
                policies.means[at],
                archive.thetas[index],
                torch.tensor(weights, dtype=DTYPE).view(len(stepping), size),
                validate=False,
            )
            policies.means = policies.means.index_put((at,), means)
        archive.keep(torch.tensor(kept, dtype=torch.long))

    def slot_weights(self, search: PolicySearch, index: Tensor, valid: Tensor) -> Tensor:
        """``[K, M]`` eq. 7's weights of the importance-set slots ``index`` (``valid`` marks
        filled ones): each policy's own M returns mapped onto [floor, 1]. A policy's step then
        depends on its own samples only, not on how bad a scout or another policy's samples
        were (with the kept returns' range, a policy near the top has M weights ≈ 1 and its
        mean is a plain average of its samples, which lags and can straddle two optima)."""
        returns = search.archive.rewards[index]
        low = torch.where(valid, returns, math.inf).amin(-1, keepdim=True)
        high = torch.where(valid, returns, -math.inf).amax(-1, keepdim=True)
        spread = high - low
        tiny = torch.finfo(DTYPE).tiny
        mapped = ((returns - low) / spread.clamp_min(tiny)).clamp(search.reward_scale.floor, 1.0)
        # One sample, or M equal returns: equal weights.
        weights = torch.where(spread > 0, mapped, torch.ones_like(mapped))
        return weights * valid

    def unit_weights(self, search: PolicySearch) -> bool:
        """Whether ``slot_weights`` lie in [0, 1] by construction (``power_update`` then
        need not check them)."""
        return True


class GlobalImportance(PolicyImportance):
    """The best K·M samples overall are kept; eq. 7 weighs each policy's best M among them by
    the reward scale over all kept returns. A policy whose samples all fall out of the best
    K·M owns no data at the next clustering and disappears."""

    def power_step(self, search: PolicySearch) -> None:
        archive = search.archive
        top = min(search.num_policies * search.M, len(archive))
        archive.keep(torch.topk(archive.rewards, top).indices.sort().values)  # archive order
        super().power_step(search)

    # No host path: the weights come from the reward scale over all kept returns.
    has_host_path = False

    def slot_weights(self, search: PolicySearch, index: Tensor, valid: Tensor) -> Tensor:
        rewards = search.archive.rewards
        return search.reward_scale.weights(rewards, reference=rewards)[index] * valid

    def unit_weights(self, search: PolicySearch) -> bool:
        """The reward scale's weights lie in [floor, 1], but for positive returns used as
        they are (a loaded state may hold any)."""
        return not search.reward_scale.positive


def make_importance(kind: str) -> PolicyImportance:
    """``"policy"`` → ``PolicyImportance``, ``"global"`` → ``GlobalImportance``."""
    return GlobalImportance() if kind == "global" else PolicyImportance()

"""PoWER (Kober & Peters 2011) as used by DIPOLE: eq. 7 and the importance sets, batched over
policies."""

from __future__ import annotations

import numpy as np
import torch
from torch import Tensor


def power_update(mean: Tensor, samples: Tensor, weights: Tensor) -> Tensor:
    """Eq. 7 for K policies at once.

    θ_k ← θ_k + Σ_m w_km (θ_km − θ_k) / Σ_m w_km.

    Args:
        mean: ``[K, D]`` current policy parameters θ^(n−1).
        samples: ``[K, M, D]`` each policy's importance set (its best M samples).
        weights: ``[K, M]`` non-negative reward weights; 0 marks padding. A policy whose
            weights are all 0 keeps its mean.

    Returns:
        ``[K, D]`` updated parameters θ^(n).
    """
    if samples.shape[:-1] != weights.shape or samples.shape[0] != mean.shape[0]:
        raise ValueError(
            f"power_update: expected mean [K, D], samples [K, M, D], weights [K, M]; got "
            f"{list(mean.shape)}, {list(samples.shape)}, {list(weights.shape)}"
        )
    if (weights < 0).any():
        raise ValueError("power_update: weights must be non-negative")
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
    """
    if owner.device.type == "cpu" and rewards.device.type == "cpu":
        sets = _importance_sets_numpy(owner, rewards, num_policies, size)
        if sets is not None:
            return sets
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


def _importance_sets_numpy(
    owner: Tensor, rewards: Tensor, num_policies: int, size: int
) -> tuple[Tensor, Tensor, Tensor] | None:
    """:func:`importance_sets` on CPU with numpy: the same two stable sorts and integer
    bookkeeping (exact), in a fraction of the ~20 small-tensor ops' overhead. ``None`` for
    inputs whose handling is left to the torch path (empty, NaN, owners outside
    ``[0, num_policies)``), so errors and NaN ordering stay torch's."""
    own = owner.numpy()
    returns = rewards.detach().numpy()
    n = own.shape[0]
    if n == 0 or np.isnan(returns).any() or own.min() < 0 or own.max() >= num_policies:
        return None
    # Descending stable sort = ascending stable sort of the negated returns (exact; ±0 tie).
    by_reward = np.argsort(-returns, kind="stable")
    order = by_reward[np.argsort(own[by_reward], kind="stable")]
    counts = np.bincount(own, minlength=num_policies)
    starts = np.cumsum(counts) - counts
    rank = np.arange(n) - starts[own[order]]
    in_set = rank < size
    chosen = order[in_set]
    keep = np.zeros(n, dtype=bool)
    keep[chosen] = True
    index = np.full((num_policies, size), -1, dtype=np.int64)
    index[own[chosen], rank[in_set]] = chosen
    return torch.from_numpy(keep), torch.from_numpy(index), torch.from_numpy(index >= 0)

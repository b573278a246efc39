"""The label pass with re-used auxiliary components (the "ReUse" sampler of Favaro & Teh
2013): exact like Algorithm 8, with m + (slots taken) draws from H a sweep instead of N·m.

m slots of draws from H serve the whole sweep. At point i: if i was alone in its component,
that component's parameters replace the slot chosen by a uniform; i then joins a component
∝ r_c n_{-i,c} N(y_i; θ_c) or a slot j ∝ r_j (α/m) N(y_i; φ_j); a slot taken becomes a
component and is refilled from H.

The refills are independent of the chain, so they are drawn ahead, with the m slots, as a
*pool* of components (blocks of at most ``POOL_BLOCK``; one block holds a small data set's
N refills, the most a sweep can take). Every point's score under every component the pass
can meet (the K starting ones and the pool's) is then one table, made in one batched call
before the pass: the pass itself is bookkeeping over its columns, without a tensor call per
point or per component opened. CPU only (the pass runs on the host).
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from dipole_torch.dp.labels import (
    LogRewards,
    component_scores,
    free_slot,
    label_logits,
    reward_logs,
    starting_counts,
)
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE, log_prob_tril
from dipole_torch.sampling import draw_categorical_numpy

__all__ = ["POOL_BLOCK", "ComponentPool", "label_pass_reuse"]

POOL_BLOCK = 256  # refills drawn at once beyond the m slots (a sweep of N points takes ≤ N)


@dataclass
class ComponentPool:
    """Components a ReUse pass can meet, as columns: the sweep's K starting components,
    then blocks of draws from H (the m slots, then refills in order).

    Attributes:
        means: ``[C, D]``, covs and their factors ``tril [C, D, D]``: torch, for the kept
            components' parameters at the end of the pass.
        scores: ``[N, C]`` numpy ``component_scores`` (log r_c + log N(y_i; μ_c, Σ_c)); the
            columns of a block drawn at point i are filled for the points after i only.
    """

    means: Tensor
    covs: Tensor
    tril: Tensor
    scores: np.ndarray

    def extend(self, y: Tensor, start: int, means: Tensor, covs: Tensor, tril: Tensor,
               log_r: Tensor) -> None:  # fmt: skip
        """Append components (``means [B, D]``, ..., ``log_r [B]``), scored at the points
        ``y[start:]``."""
        block = np.full((self.scores.shape[0], means.shape[0]), -math.inf)
        if start < y.shape[0]:
            log_lik = log_prob_tril(y[start:, None, :], means, tril)
            block[start:] = component_scores(log_lik, log_r).numpy()
        self.scores = np.concatenate((self.scores, block), axis=1)
        self.means = torch.cat((self.means, means))
        self.covs = torch.cat((self.covs, covs))
        self.tril = torch.cat((self.tril, tril))

    def parameters(self, columns: list[int]) -> tuple[Tensor, Tensor, Tensor]:
        """``[k, D]`` means, ``[k, D, D]`` covariances and factors of ``columns``."""
        index = torch.tensor(columns, device=self.means.device)
        return self.means[index], self.covs[index], self.tril[index]


Draw = Callable[[int], tuple[Tensor, Tensor, Tensor]]  # count -> means, covs, tril from H


def start_pool(
    y: Tensor,
    state: DPMixtureState,
    tril: Tensor,
    log_rewards: LogRewards | None,
    draw: Draw,
    count: int,
) -> ComponentPool:
    """The pool's first columns: the K starting components and ``count`` draws from H,
    scored at every point in one call, with log r_c of both from one regression call."""
    means, covs, factors = draw(count)
    all_means = torch.cat((state.means, means))
    all_tril = torch.cat((tril, factors))
    log_r = reward_logs(log_rewards, all_means)
    scores = component_scores(log_prob_tril(y[:, None, :], all_means, all_tril), log_r)
    return ComponentPool(all_means, torch.cat((state.covariances, covs)), all_tril, scores.numpy())


def label_pass_reuse(
    y: Tensor,
    state: DPMixtureState,
    tril: Tensor,
    log_rewards: LogRewards | None,
    draw: Draw,
    uniforms: Tensor,
    slot_uniforms: Tensor,
    log_aux_prior: float,
    m: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor, Tensor]:
    """Algorithm 8's step 1 with re-used auxiliary components.

    Args:
        y: ``[N, D]`` data (CPU, float64).
        state: the sweep's starting state (labels ``[N]``, K components).
        tril: ``[K, D, D]`` Cholesky factors of its covariances.
        log_rewards: eq. 6's log r_c of component means (``ComponentRewards``); ``None``:
            eq. 5.
        draw: ``count -> (means, covs, tril)``, ``count`` components from H.
        uniforms: ``[N]`` the label draws' uniforms.
        slot_uniforms: ``[N]`` the uniforms that choose the slot a singleton's parameters
            replace.
        log_aux_prior: log(α/m).
        m: auxiliary slots.

    Returns:
        ``[N]`` labels in ``[0, k)``, the k slots' ``[k, D]`` means, ``[k, D, D]``
        covariances and their Cholesky factors, and ``[k]`` counts (empty slots included).
    """
    n, k = y.shape[0], state.num_components
    refills = min(n, POOL_BLOCK)
    pool = start_pool(y, state, tril, log_rewards, draw, m + refills)
    labels, counts, log_counts = starting_counts(state, 2 * k)
    logits = np.empty(2 * k + m)
    column = list(range(k))  # component -> its pool column
    slot = list(range(k, k + m))  # auxiliary slot -> its pool column
    next_refill, end = k + m, k + m + refills
    u, slot_u = uniforms.tolist(), slot_uniforms.tolist()
    for i in range(n):
        c = labels[i]
        counts[c] -= 1
        singleton = counts[c] == 0
        log_counts[c] = math.log(counts[c]) if counts[c] else -math.inf
        own = -1
        if singleton:  # its parameters become an empty component: a uniform slot
            own = min(int(slot_u[i] * m), m - 1)
            slot[own] = column[c]
        row = pool.scores[i]
        logits[:k] = label_logits(log_counts[:k], row[column])
        logits[k : k + m] = label_logits(log_aux_prior, row[slot])
        choice = draw_categorical_numpy(logits[: k + m], u[i])
        if choice < k:
            new = choice
        else:
            j = choice - k
            if j == own:
                new = c  # re-formed with its own parameters
            else:
                new = c if singleton else free_slot(counts, k)
                if new == k:  # a new component
                    k += 1
                    counts.append(0)
                    column.append(slot[j])
                    if k > log_counts.shape[0]:
                        log_counts = np.concatenate((log_counts, np.full(k, -math.inf)))
                        logits = np.empty(2 * k + m)
                column[new] = slot[j]
            # The slot taken is refilled from H (the pool's next column).
            if next_refill == end:
                means, covs, factors = draw(refills)
                pool.extend(y, i + 1, means, covs, factors, reward_logs(log_rewards, means))
                end += refills
            slot[j] = next_refill
            next_refill += 1
        labels[i] = new
        counts[new] += 1
        log_counts[new] = math.log(counts[new])
    means, covs, trils = pool.parameters(column)
    return (
        torch.tensor(labels, dtype=torch.long),
        means,
        covs,
        trils,
        torch.tensor(counts, dtype=DTYPE),
    )

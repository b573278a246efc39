"""Eq. 5/6's label logits, and the bookkeeping every label pass shares.

A label pass is Algorithm 8's step 1: each c_i redrawn in turn, the component parameters
held fixed. Point i joins an occupied component c or one of m auxiliary components with

    log P(c_i = c) = log w_c + log r_c + log F(y_i; θ_c) + const,

w_c = n_{-i,c} for an occupied component and α/m for an auxiliary one (eq. 5; eq. 6 with
the reward weight r_c, log r_c = 0 without it); the common factor b/(n − 1 + α) cancels.
``component_scores`` is the reward-weighted likelihood, computed for many points at once
and cached; ``label_logits`` adds the weight. Every pass (Algorithm 8's fresh auxiliary
draws in ``dipole_torch.dp.neal8``, the re-used ones in ``dipole_torch.dp.reuse``)
builds its logits with these two functions.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np
import torch
from torch import Tensor

from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE, log_prob_tril
from dipole_torch.prior import NormalInverseWishartPrior

__all__ = ["AuxiliaryDraws", "component_scores", "label_logits"]


def component_scores(log_likelihood: Tensor, log_r: Tensor) -> Tensor:
    """log r_c + log F(y_i; θ_c): eq. 6's reward-weighted likelihood (eq. 5: ``log_r`` = 0).

    Args:
        log_likelihood: ``[..., C]`` log N(y_i; μ_c, Σ_c) of points under components.
        log_r: ``[C]`` (or broadcastable) log r_c of the components.
    """
    return log_likelihood + log_r


def label_logits(log_weight, scores):
    """Eq. 5/6's label logits: log w_c + ``scores`` (``component_scores``), with
    ``log_weight`` = log n_{-i,c} for occupied components and log(α/m) for auxiliary ones.
    Tensors, numpy arrays and floats alike (the per-point passes run in numpy)."""
    return log_weight + scores


LogRewards = Callable[[Tensor], Tensor]  # component means [..., D] -> log r_c [...] (eq. 6)


@dataclass
class AuxiliaryDraws:
    """Auxiliary components drawn from H for a chunk of C points: ``means [C, m, D]``,
    symmetric ``covs`` and their Cholesky factors ``tril [C, m, D, D]``, ``log_r [C, m]``
    (log r_c, 0 unweighted) and ``logits [C, m]``: the auxiliary slots' label logits at
    their points. ``starting_log_r [K]``: log r_c of the sweep's starting components, when
    they were asked for with the draws (one regression call for both)."""

    means: Tensor
    covs: Tensor
    tril: Tensor
    log_r: Tensor
    logits: Tensor
    starting_log_r: Tensor | None = None

    @classmethod
    def draw(
        cls,
        prior: NormalInverseWishartPrior,
        points: Tensor,
        count: int,
        log_aux_prior: float,
        log_rewards: LogRewards | None,
        generator: torch.Generator | None,
        starting: Tensor | None = None,
    ) -> AuxiliaryDraws:
        """Algorithm 8's fresh draws: ``count`` components from H for each of the C
        ``points: [C, D]`` (``means [C, count, D]``, ``logits [C, count]``).

        Args:
            log_rewards: eq. 6's log r_c of component means (``ComponentRewards``);
                ``None``: eq. 5.
            starting: ``[K, D]`` means of the sweep's starting components, whose log r_c
                are wanted too (``starting_log_r``).
        """
        size, d = points.shape[0], points.shape[-1]
        means, covs = prior.sample(size * count, generator)
        tril = torch.linalg.cholesky(covs)
        log_r, starting_log_r = _log_rewards(log_rewards, means, starting)
        means, covs = means.view(size, count, d), covs.view(size, count, d, d)
        tril, log_r = tril.view(size, count, d, d), log_r.view(size, count)
        logits = _auxiliary_logits(
            log_aux_prior, log_prob_tril(points[:, None, :], means, tril), log_r
        )
        return cls(means, covs, tril, log_r, logits, starting_log_r)


def reward_logs(log_rewards: LogRewards | None, means: Tensor) -> Tensor:
    """``[A]`` log r_c of ``means: [A, D]``: eq. 6's (``log_rewards``), or zeros (eq. 5)."""
    return means.new_zeros(means.shape[0]) if log_rewards is None else log_rewards(means)


def _log_rewards(
    log_rewards: LogRewards | None, means: Tensor, starting: Tensor | None
) -> tuple[Tensor, Tensor | None]:
    """``[A]`` log r_c of the auxiliary ``means: [A, D]`` and ``[K]`` those of ``starting``
    (``None`` when not asked for), from one call of ``reward_logs``."""
    if starting is None:
        return reward_logs(log_rewards, means), None
    log_r = reward_logs(log_rewards, torch.cat((starting, means)))
    k = starting.shape[0]
    return log_r[k:], log_r[:k]


def _auxiliary_logits(log_aux_prior: float, log_lik: Tensor, log_r: Tensor) -> Tensor:
    return label_logits(log_aux_prior, component_scores(log_lik, log_r))


Auxiliary = Callable[[int, int], AuxiliaryDraws]  # (start, stop) -> draws for those points


def starting_scores(y: Tensor, state: DPMixtureState, tril: Tensor, log_r: Tensor) -> Tensor:
    """``[N, K]`` ``component_scores`` of every point under the sweep's starting
    components (fixed during the pass, as in Algorithm 8: one batched call), from the
    Cholesky factors ``tril: [K, D, D]`` of their covariances."""
    return component_scores(log_prob_tril(y[:, None, :], state.means, tril), log_r)


def starting_counts(
    state: DPMixtureState, capacity: int
) -> tuple[list[int], list[int], np.ndarray]:
    """The sweep's starting ``labels`` and ``counts`` as lists, and ``log_counts [capacity]``
    (−inf for empty slots), the bookkeeping every numpy label pass starts from."""
    labels = state.labels.tolist()
    counts = [0] * state.num_components  # (counted in Python: a bincount and its read cost more)
    for label in labels:
        counts[label] += 1
    log_counts = np.full(capacity, -math.inf)
    with np.errstate(divide="ignore"):  # an empty component: log 0 = −inf, as intended
        log_counts[: len(counts)] = np.log(np.asarray(counts, dtype=float))
    return labels, counts, log_counts


def pass_start(
    y: Tensor, state: DPMixtureState, tril: Tensor, log_r: Tensor
) -> tuple[list[int], list[int], np.ndarray, np.ndarray]:
    """What the numpy label passes start from: ``starting_counts``, and ``score [N,
    capacity]`` (``component_scores``; columns of components opened in the sweep are filled
    only for the points still to come), with room for ``capacity`` components
    (``open_slot`` grows it)."""
    n, k = y.shape[0], state.num_components
    capacity = max(2 * k, 8)
    labels, counts, log_counts = starting_counts(state, capacity)
    score = np.full((n, capacity), -math.inf)
    score[:, :k] = starting_scores(y, state, tril, log_r).numpy()
    return labels, counts, score, log_counts


def free_slot(counts: list[int], k: int) -> int:
    """The first empty slot below k, else k."""
    try:
        return counts.index(0, 0, k)
    except ValueError:
        return k


def open_slot(
    counts: list[int], score: np.ndarray, log_counts: np.ndarray, logits: np.ndarray, m: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Component ``len(counts)`` opens, empty; the slot arrays (``score [N, capacity]``,
    ``log_counts [capacity]``, the ``capacity + m`` logits buffer) double when it does not
    fit. Returns them (new arrays when they grew)."""
    counts.append(0)
    capacity = score.shape[1]
    if len(counts) > capacity:
        grown = np.full((score.shape[0], 2 * capacity), -math.inf)
        grown[:, :capacity] = score
        score = grown
        log_counts = np.concatenate((log_counts, np.full(capacity, -math.inf)))
        logits = np.empty(2 * capacity + m)
    return score, log_counts, logits


Slot = tuple[Tensor, Tensor, Tensor, float]  # μ, Σ, L, log r of a component opened in a pass


def slot_parameters(
    state: DPMixtureState, tril: Tensor, opened: dict[int, Slot], k: int
) -> tuple[Tensor, Tensor, Tensor]:
    """``[k, D]`` means, ``[k, D, D]`` covariances and their Cholesky factors of all k
    slots: the sweep's starting ones (factors ``tril``), overwritten by the components
    opened during the sweep (each slot's latest)."""
    start = state.num_components
    if not opened and k == start:
        return state.means, state.covariances, tril  # nothing opened: the starting ones
    d = state.means.shape[-1]
    means = torch.empty(k, d, dtype=DTYPE, device=state.means.device)
    covs = torch.empty(k, d, d, dtype=DTYPE, device=means.device)
    trils = torch.empty(k, d, d, dtype=DTYPE, device=means.device)
    means[:start], covs[:start], trils[:start] = state.means, state.covariances, tril
    slots = list(opened)
    index = torch.tensor(slots, device=means.device)
    means[index] = torch.stack([opened[slot][0] for slot in slots])
    covs[index] = torch.stack([opened[slot][1] for slot in slots])
    trils[index] = torch.stack([opened[slot][2] for slot in slots])
    return means, covs, trils

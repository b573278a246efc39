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

from dipole_torch.dp.reward_weights import RewardRegression, reward_weights
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE, gaussian_log_prob, log_prob_tril
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


@dataclass
class AuxiliaryDraws:
    """Auxiliary components drawn from H for a chunk of C points: ``means [C, m, D]``,
    ``covs`` (symmetric up to rounding: only their lower triangles and factors are used),
    their Cholesky factors ``tril [C, m, D, D]``, ``log_r [C, m]`` (log r_c, 0 unweighted)
    and ``logits [C, m]``: the auxiliary slots' label logits at their points."""

    means: Tensor
    covs: Tensor
    tril: Tensor
    log_r: Tensor
    logits: Tensor

    @classmethod
    def draw(
        cls,
        prior: NormalInverseWishartPrior,
        points: Tensor,
        count: int,
        log_aux_prior: float,
        reward: tuple[RewardRegression, Tensor] | None,
        generator: torch.Generator | None,
    ) -> AuxiliaryDraws:
        """Algorithm 8's fresh draws: ``count`` components from H for each of the C
        ``points: [C, D]`` (``means [C, count, D]``, ``logits [C, count]``).

        Args:
            reward: eq. 6's ``(regression, weights [N])``, the sweep's reward regression and
                the data's reward weights; ``None``: eq. 5.
        """
        size, d = points.shape[0], points.shape[-1]
        # Unsymmetrised: only the lower triangles are read, until a component opens.
        means, covs = prior.sample(size * count, generator, symmetrize=False)
        means, covs = means.reshape(size, count, d), covs.reshape(size, count, d, d)
        tril = torch.linalg.cholesky(covs)
        log_lik = log_prob_tril(points[:, None, :], means, tril)
        log_r = torch.zeros_like(log_lik)
        if reward is not None:
            log_r = reward_weights(reward[0], means, weights=reward[1])
        return cls(means, covs, tril, log_r, _auxiliary_logits(log_aux_prior, log_lik, log_r))

    @classmethod
    def shared(
        cls,
        prior: NormalInverseWishartPrior,
        y: Tensor,
        count: int,
        log_aux_prior: float,
        reward: tuple[RewardRegression, Tensor] | None,
        generator: torch.Generator | None,
    ) -> AuxiliaryDraws:
        """``count`` components from H shared by every point of ``y: [N, D]`` (``means
        [count, D]``, ``logits [N, count]``): the re-used auxiliary components."""
        means, covs = prior.sample(count, generator)
        tril = torch.linalg.cholesky(covs)
        log_r = torch.zeros(count, dtype=DTYPE)
        if reward is not None:
            log_r = reward_weights(reward[0], means, weights=reward[1])
        log_lik = log_prob_tril(y[:, None, :], means, tril)
        return cls(means, covs, tril, log_r, _auxiliary_logits(log_aux_prior, log_lik, log_r))


def _auxiliary_logits(log_aux_prior: float, log_lik: Tensor, log_r: Tensor) -> Tensor:
    return label_logits(log_aux_prior, component_scores(log_lik, log_r))


Auxiliary = Callable[[int, int], AuxiliaryDraws]  # (start, stop) -> draws for those points


def starting_scores(y: Tensor, state: DPMixtureState, log_r: Tensor) -> Tensor:
    """``[N, K]`` ``component_scores`` of every point under the sweep's starting
    components (fixed during the pass, as in Algorithm 8: one batched call)."""
    return component_scores(gaussian_log_prob(y[:, None, :], state.means, state.covariances), log_r)


def pass_start(
    y: Tensor, state: DPMixtureState, log_r: Tensor
) -> tuple[list[int], list[int], np.ndarray, np.ndarray]:
    """What the numpy label passes start from: ``labels`` and ``counts`` as lists,
    ``score [N, capacity]`` (``component_scores``; columns of components opened in the
    sweep are filled only for the points still to come) and ``log_counts [capacity]`` (−inf
    for empty slots), with room for ``capacity`` components (``open_slot`` grows it)."""
    n, k = y.shape[0], state.num_components
    labels = state.labels.tolist()
    counts = [0] * k  # (counted in Python: a bincount and its read cost more at these sizes)
    for label in labels:
        counts[label] += 1
    capacity = max(2 * k, 8)
    score = np.full((n, capacity), -math.inf)
    score[:, :k] = starting_scores(y, state, log_r).numpy()
    log_counts = np.full(capacity, -math.inf)
    with np.errstate(divide="ignore"):  # an empty component: log 0 = −inf, as intended
        log_counts[:k] = np.log(np.asarray(counts, dtype=float))
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
    state: DPMixtureState, opened: dict[int, Slot], k: int
) -> tuple[Tensor, Tensor]:
    """``[k, D]`` means and ``[k, D, D]`` covariances of all k slots: the sweep's starting
    ones, overwritten by the components opened during the sweep (each slot's latest)."""
    start = state.num_components
    if not opened and k == start:
        return state.means, state.covariances  # nothing opened: the starting ones
    means = torch.empty(k, state.means.shape[-1], dtype=DTYPE, device=state.means.device)
    covs = torch.empty(k, *state.covariances.shape[-2:], dtype=DTYPE, device=means.device)
    means[:start], covs[:start] = state.means, state.covariances
    for slot, (mean, cov, _, _) in opened.items():
        means[slot], covs[slot] = mean, cov
    return means, covs

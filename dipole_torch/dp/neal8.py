"""A sweep of Neal's (2000) Algorithm 8, the paper's Algorithm 1 (eqs. 5 and 6).

``neal8_sweep``: the labels (m auxiliary components from H for every point, or re-used
ones, ``dipole_torch.dp.reuse``), then the components' parameters
(``resample_parameters``), then H. Its label pass with fresh
auxiliary draws has two implementations that make the same draws from the same uniforms:

* ``label_pass_numpy`` on the CPU: the per-point work in numpy and Python scalars (a
  handful of numpy calls a point; torch's per-op overhead was many times that);
* ``label_pass_sync_free`` on other devices: tensor ops that never wait for the device
  within a chunk of points (one sync a chunk).

The auxiliary draws and their likelihoods are made in chunks of points (at most
``AUX_CHUNK_BYTES`` of ``[chunk, m, D, D]`` covariances, so memory does not grow with
N·m), and a component opened at point i gets its likelihood column only for the points
after i.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from dipole_torch.dp.conditionals import resample_parameters
from dipole_torch.dp.labels import (
    Auxiliary,
    AuxiliaryDraws,
    Slot,
    component_scores,
    free_slot,
    label_logits,
    open_slot,
    pass_start,
    slot_parameters,
)
from dipole_torch.dp.reuse import label_pass_reuse
from dipole_torch.dp.reward_weights import ComponentRewards
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE, log_prob_tril
from dipole_torch.sampling import draw_categorical, draw_categorical_numpy, uniforms

if TYPE_CHECKING:
    from dipole_torch.dp.sampler import DPSampler

__all__ = [
    "AUX_CHUNK_BYTES",
    "chunk_size",
    "label_pass_numpy",
    "label_pass_sync_free",
    "neal8_sweep",
]

AUX_CHUNK_BYTES = 2**26  # auxiliary covariances and their factors held at once (64 MB)


def chunk_size(n: int, m: int, d: int) -> int:
    """Points whose ``[m, D, D]`` auxiliary covariances and factors fit AUX_CHUNK_BYTES."""
    return max(1, min(n, AUX_CHUNK_BYTES // (2 * 8 * m * d * d)))


def neal8_sweep(
    y: Tensor, state: DPMixtureState, sampler: DPSampler, generator: torch.Generator | None
) -> DPMixtureState:
    """One Gibbs sweep of Algorithm 8 with ``sampler``'s options.

    1. Every label c_i is redrawn with eq. 5's probabilities (eq. 6 when
       ``sampler.reward_weighted``): ∝ r_c n_{-i,c} N(y_i; μ_c, Σ_c) for occupied components
       and ∝ r_c (α/m) N(y_i; μ_c, Σ_c) for m auxiliary components (``labels``);
       a singleton's own parameters fill the first auxiliary slot. r_c comes from the mixture
       at the start of the sweep, clamped to the range of the data's reward weights
       ``y[:, -1]`` (``reward_weights``).
    2. Every occupied component's parameters are redrawn from their conditionals.
    3. With ``sampler.update_prior``, H's hyperparameters are redrawn given the components
       (``updated``, anchored on
       ``sampler.prior``); otherwise H stays fixed.

    Args:
        y: ``[N, D]`` data (for DIPOLE, ``[θ, w]`` with the positive reward weight last).
        state: the current chain state.
        generator: source of all randomness.

    Returns:
        The new state (contiguous labels, occupied components only).
    """
    y = y if y.dtype == DTYPE else y.to(DTYPE)
    n, d = y.shape
    m = sampler.m
    prior = state.prior
    log_rewards = ComponentRewards(state, y[:, -1]) if sampler.reward_weighted else None
    tril = torch.linalg.cholesky(state.covariances)  # the labels' likelihoods, then the μ step
    log_aux_prior = math.log(sampler.alpha / m)
    draws = uniforms(n, generator, y.device)
    # The starting components' log r_c come with the first auxiliary draws (one regression).
    if sampler.auxiliary == "reuse":
        if y.device.type != "cpu":
            raise ValueError("auxiliary='reuse' runs on the CPU only")
        slot_draws = uniforms(n, generator, y.device)

        def draw(count: int) -> tuple[Tensor, Tensor, Tensor]:
            means, covs = prior.sample(count, generator)
            return means, covs, torch.linalg.cholesky(covs)

        labels, means, covs, tril, counts = label_pass_reuse(
            y, state, tril, log_rewards, draw, draws, slot_draws, log_aux_prior, m
        )
    else:
        chunk = chunk_size(n, m, d)
        first = AuxiliaryDraws.draw(
            prior, y[:chunk], m, log_aux_prior, log_rewards, generator, state.means
        )

        def auxiliary(start: int, stop: int) -> AuxiliaryDraws:
            if start == 0:
                return first
            return AuxiliaryDraws.draw(
                prior, y[start:stop], m, log_aux_prior, log_rewards, generator
            )

        label_pass = label_pass_numpy if y.device.type == "cpu" else label_pass_sync_free
        labels, means, covs, tril, counts = label_pass(
            y, state, tril, first.starting_log_r, auxiliary, draws, log_aux_prior, chunk
        )
    occupied = counts > 0
    # On CPU (no sync to ask) the relabelling is skipped when no component emptied.
    if y.device.type != "cpu" or not bool(occupied.all()):
        remap = torch.cumsum(occupied.long(), 0) - 1
        labels = remap[labels]
        means, covs, tril, counts = (
            means[occupied],
            covs[occupied],
            tril[occupied],
            counts[occupied],
        )
    new_state = DPMixtureState(labels, means, covs, prior)
    new_state = resample_parameters(
        y, new_state, sampler.inner_steps, generator, sampler.exact_covariance, counts, tril
    )
    if sampler.update_prior:
        new_state.prior = prior.updated(
            new_state.means, new_state.covariances - prior.regularization, sampler.prior, generator
        )
    return new_state


def label_pass_numpy(
    y: Tensor,
    state: DPMixtureState,
    tril: Tensor,
    log_r: Tensor,
    auxiliary: Auxiliary,
    uniforms: Tensor,
    log_aux_prior: float,
    chunk: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Algorithm 8's step 1 on the CPU.

    Args:
        y: ``[N, D]`` data (CPU, float64).
        state: the sweep's starting state (labels ``[N]``, K components).
        tril: ``[K, D, D]`` Cholesky factors of its covariances.
        log_r: ``[K]`` log r_c of the starting components (zeros unweighted).
        auxiliary: ``(start, stop) -> AuxiliaryDraws`` fresh auxiliary draws for those points.
        uniforms: ``[N]`` the label draws' uniforms.
        log_aux_prior: log(α/m).
        chunk: points per auxiliary chunk.

    Returns:
        ``[N]`` labels in ``[0, k)``, the k slots' ``[k, D]`` means, ``[k, D, D]``
        covariances and their Cholesky factors, and ``[k]`` counts (empty slots included).
    """
    n, k = y.shape[0], state.num_components
    labels, counts, score, log_counts = pass_start(y, state, tril, log_r)
    logits = np.empty(0)  # reused buffer for one point's K + m logits
    u = uniforms.tolist()
    opened: dict[int, Slot] = {}  # slot -> μ, Σ, L, log r
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        aux = auxiliary(start, stop)
        aux_logits = aux.logits.numpy()
        m = aux_logits.shape[1]
        if logits.shape[0] < score.shape[1] + m:
            logits = np.empty(score.shape[1] + m)
        live = [slot for slot in opened if counts[slot] > 0]
        if live:  # components opened in earlier chunks: their columns for this chunk
            mean = torch.stack([opened[slot][0] for slot in live])
            factors = torch.stack([opened[slot][2] for slot in live])
            lr = torch.tensor([opened[slot][3] for slot in live], dtype=DTYPE)
            column = component_scores(log_prob_tril(y[start:stop, None, :], mean, factors), lr)
            score[start:stop, live] = column.numpy()
        for i in range(start, stop):
            c = labels[i]
            counts[c] -= 1
            singleton = counts[c] == 0
            log_counts[c] = math.log(counts[c]) if counts[c] else -math.inf
            row = score[i]
            logits[:k] = label_logits(log_counts[:k], row[:k])
            logits[k : k + m] = aux_logits[i - start]
            if singleton:  # Algorithm 8: a singleton's parameters fill the first aux slot
                logits[k] = label_logits(log_aux_prior, row[c])
            choice = draw_categorical_numpy(logits[: k + m], u[i])
            if choice < k:
                new = choice
            elif singleton and choice == k:
                new = c  # kept its own parameters
            else:
                j = choice - k
                new = c if singleton else free_slot(counts, k)
                if new == k:
                    k += 1
                    score, log_counts, logits = open_slot(counts, score, log_counts, logits, m)
                r = i - start
                mean, factor = aux.means[r, j], aux.tril[r, j]
                lr = float(aux.log_r[r, j])
                opened[new] = (mean, aux.covs[r, j], factor, lr)
                if i + 1 < stop:
                    score[i + 1 : stop, new] = component_scores(
                        log_prob_tril(y[i + 1 : stop], mean, factor), lr
                    ).numpy()
            labels[i] = new
            counts[new] += 1
            log_counts[new] = math.log(counts[new])
    means, covs, trils = slot_parameters(state, tril, opened, k)
    counts_t = torch.tensor(counts, dtype=DTYPE)
    return torch.tensor(labels, dtype=torch.long), means, covs, trils, counts_t


def label_pass_sync_free(
    y: Tensor,
    state: DPMixtureState,
    start_tril: Tensor,
    log_r: Tensor,
    auxiliary: Auxiliary,
    uniforms: Tensor,
    log_aux_prior: float,
    chunk: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Algorithm 8's step 1 with tensor ops only: the host never waits for the device
    inside a chunk of points (one sync a chunk, to grow the slot capacity).

    Same arguments, draws and returns as ``label_pass_numpy``. Every branch of the
    per-point step becomes a masked write: all components live in ``capacity`` slots (empty
    ones have count 0, hence probability 0), and the likelihood column of the chunk's points
    under the chosen auxiliary component is computed at every point and written only where a
    component opens.
    """
    n, d = y.shape
    k = state.num_components
    device = y.device
    capacity = k + chunk
    means = torch.zeros(capacity, d, dtype=DTYPE, device=device)
    covs = torch.eye(d, dtype=DTYPE, device=device).repeat(capacity, 1, 1)
    means[:k], covs[:k] = state.means, state.covariances
    tril = torch.eye(d, dtype=DTYPE, device=device).repeat(capacity, 1, 1)
    tril[:k] = start_tril
    slot_log_r = torch.zeros(capacity, dtype=DTYPE, device=device)
    slot_log_r[:k] = log_r
    counts = torch.zeros(capacity, dtype=DTYPE, device=device)
    counts[:k] = torch.bincount(state.labels, minlength=k).to(DTYPE)
    labels = state.labels.clone()
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        used = int(counts.nonzero().max()) + 1  # the chunk's one sync
        if capacity - used < stop - start:  # each point opens at most one slot
            extra = stop - start
            means = torch.cat((means, means.new_zeros(extra, d)))
            covs = torch.cat((covs, torch.eye(d, dtype=DTYPE, device=device).repeat(extra, 1, 1)))
            tril = torch.cat((tril, torch.eye(d, dtype=DTYPE, device=device).repeat(extra, 1, 1)))
            slot_log_r = torch.cat((slot_log_r, slot_log_r.new_zeros(extra)))
            counts = torch.cat((counts, counts.new_zeros(extra)))
            capacity += extra
        aux = auxiliary(start, stop)
        y_chunk = y[start:stop]
        score = component_scores(log_prob_tril(y_chunk[:, None, :], means, tril), slot_log_r)
        for i in range(start, stop):
            _sync_free_step(
                i, i - start, y_chunk, labels, counts, score, means, covs, tril, slot_log_r,
                aux, uniforms, log_aux_prior,
            )  # fmt: skip
    k = int(counts.nonzero().max()) + 1
    return labels, means[:k], covs[:k], tril[:k], counts[:k]


def _sync_free_step(
    i: int,
    r: int,
    y_chunk: Tensor,
    labels: Tensor,
    counts: Tensor,
    score: Tensor,
    means: Tensor,
    covs: Tensor,
    tril: Tensor,
    slot_log_r: Tensor,
    aux: AuxiliaryDraws,
    uniforms: Tensor,
    log_aux_prior: float,
) -> None:
    """Relabel point i (row r of its chunk) in place, branch-free; see
    ``label_pass_sync_free``. ``labels [N]``, ``counts [S]``, ``score [C, S]`` and the
    slots' ``means [S, D]``, ``covs``/``tril [S, D, D]``, ``slot_log_r [S]`` are updated."""
    capacity = counts.shape[0]
    c = labels[i : i + 1]  # [1]: a view, not a host int
    counts.index_add_(0, c, counts.new_full((1,), -1.0))
    singleton = counts.index_select(0, c) == 0
    row = score[r]
    own = label_logits(log_aux_prior, row.index_select(0, c))
    aux_row = aux.logits[r]
    first = torch.where(singleton, own, aux_row[:1])
    log_counts = torch.where(counts > 0, counts.log(), -math.inf)
    logits = torch.cat((label_logits(log_counts, row), first, aux_row[1:]))
    choice = draw_categorical(logits[None], uniforms[i : i + 1])  # [1]
    is_aux = choice >= capacity
    keep_own = singleton & (choice == capacity)
    j = (choice - capacity).clamp(0, aux_row.shape[0] - 1)
    free = (counts == 0).to(torch.uint8).argmax().reshape(1)  # the first empty slot
    opened = torch.where(singleton, c, free)
    new = torch.where(is_aux, torch.where(keep_own, c, opened), choice)
    opens = is_aux & ~keep_own
    labels[i : i + 1] = new
    counts.index_add_(0, new, counts.new_ones(1))
    mean_j = aux.means[r].index_select(0, j)  # [1, D]
    tril_j = aux.tril[r].index_select(0, j)
    means.index_copy_(0, new, torch.where(opens[:, None], mean_j, means.index_select(0, new)))
    wide = opens[:, None, None]
    cov_j = aux.covs[r].index_select(0, j)
    covs.index_copy_(0, new, torch.where(wide, cov_j, covs.index_select(0, new)))
    tril.index_copy_(0, new, torch.where(wide, tril_j, tril.index_select(0, new)))
    lr_j = aux.log_r[r].index_select(0, j)
    slot_log_r.index_copy_(0, new, torch.where(opens, lr_j, slot_log_r.index_select(0, new)))
    column = component_scores(log_prob_tril(y_chunk[:, None, :], mean_j, tril_j), lr_j)
    score.index_copy_(1, new, torch.where(opens, column, score.index_select(1, new)))

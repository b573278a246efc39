"""The label pass with re-used auxiliary components (the "ReUse" sampler of Favaro & Teh
2013): exact like Algorithm 8, with m + (slots taken) draws from H a sweep instead of N·m.

One set of m draws from H serves the whole sweep. At point i: if i was alone in its
component, that component's parameters replace the auxiliary slot chosen by a uniform; i then
joins a component ∝ r_c n_{-i,c} N(y_i; θ_c) or a slot j ∝ r_j (α/m) N(y_i; φ_j); a slot taken
becomes a component and is refilled from H. CPU only.
"""

from __future__ import annotations

import math
from collections.abc import Callable

import numpy as np
import torch
from torch import Tensor

from dipole_torch.dp.labels import (
    AuxiliaryDraws,
    Slot,
    component_scores,
    free_slot,
    label_logits,
    open_slot,
    pass_start,
    slot_parameters,
)
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE, log_prob_tril
from dipole_torch.sampling import draw_categorical_numpy

__all__ = ["label_pass_reuse"]


def label_pass_reuse(
    y: Tensor,
    state: DPMixtureState,
    log_r: Tensor,
    fresh: Callable[[int], AuxiliaryDraws],
    uniforms: Tensor,
    slot_uniforms: Tensor,
    log_aux_prior: float,
    m: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Algorithm 8's step 1 with re-used auxiliary components.

    Args:
        y: ``[N, D]`` data (CPU, float64).
        state: the sweep's starting state (labels ``[N]``, K components).
        log_r: ``[K]`` log r_c of the starting components (zeros unweighted).
        fresh: ``count -> AuxiliaryDraws`` with ``count`` draws from H and their logits
            ``[N, count]`` at every point (``AuxiliaryDraws.shared``).
        uniforms: ``[N]`` the label draws' uniforms.
        slot_uniforms: ``[N]`` the uniforms that choose the slot a singleton's parameters
            replace.
        log_aux_prior: log(α/m).
        m: auxiliary slots.

    Returns:
        ``[N]`` labels in ``[0, k)``, the k slots' ``[k, D]`` means, ``[k, D, D]``
        covariances and ``[k]`` counts (empty slots included).
    """
    n, k = y.shape[0], state.num_components
    labels, counts, score, log_counts = pass_start(y, state, log_r)
    logits = np.empty(score.shape[1] + m)
    u, slot_u = uniforms.tolist(), slot_uniforms.tolist()
    aux = fresh(m)
    slots = [(aux.means[j], aux.covs[j], aux.tril[j], float(aux.log_r[j])) for j in range(m)]
    aux_logits = aux.logits.numpy().copy()  # [N, m], rows > i kept current
    opened: dict[int, Slot] = {}

    def parameters(slot: int) -> Slot:
        if slot in opened:
            return opened[slot]
        cov = state.covariances[slot]
        return state.means[slot], cov, torch.linalg.cholesky(cov), float(log_r[slot])

    for i in range(n):
        c = labels[i]
        counts[c] -= 1
        singleton = counts[c] == 0
        log_counts[c] = math.log(counts[c]) if counts[c] else -math.inf
        own = -1
        if singleton:  # its parameters become an empty component: a uniform slot
            own = min(int(slot_u[i] * m), m - 1)
            slots[own] = parameters(c)
            aux_logits[i:, own] = label_logits(log_aux_prior, score[i:, c])
        logits[:k] = label_logits(log_counts[:k], score[i, :k])
        logits[k : k + m] = aux_logits[i]
        choice = draw_categorical_numpy(logits[: k + m], u[i])
        if choice < k:
            new = choice
        else:
            j = choice - k
            if j == own:
                new = c  # re-formed with its own parameters
            else:
                new = c if singleton else free_slot(counts, k)
                if new == k:
                    k += 1
                    score, log_counts, logits = open_slot(counts, score, log_counts, logits, m)
                mean, cov, tril, lr = opened[new] = slots[j]
                if i + 1 < n:
                    score[i + 1 :, new] = component_scores(
                        log_prob_tril(y[i + 1 :], mean, tril), lr
                    ).numpy()
            # The slot taken is refilled from H; its logits are needed at later points only.
            refill = fresh(1)
            slots[j] = (refill.means[0], refill.covs[0], refill.tril[0], float(refill.log_r[0]))
            aux_logits[i + 1 :, j] = refill.logits[i + 1 :, 0].numpy()
        labels[i] = new
        counts[new] += 1
        log_counts[new] = math.log(counts[new])
    means, covs = slot_parameters(state, opened, k)
    return (
        torch.tensor(labels, dtype=torch.long),
        means,
        covs,
        torch.tensor(counts, dtype=DTYPE),
    )

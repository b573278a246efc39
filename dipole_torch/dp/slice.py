"""An exact sampler of the DP Gaussian mixture that draws every label at once: the slice
sampler of Walker (2007) with the blocked updates of Kalli, Griffin & Walker (2011), "Slice
sampling mixture models", Statistics and Computing 21.

The model is the one Algorithm 8 (``DPSampler``) samples
without reward weighting: G ~ DP(α, H), (μ_i, Σ_i) ~ G, y_i ~ N(μ_i, Σ_i + R), with H the
(non-conjugate) ``NormalInverseWishartPrior``. Written with sticks,
G = Σ_j w_j δ_{θ_j}, w_j = v_j Π_{l<j} (1 − v_l), v_j ~ Beta(1, α), θ_j ~ H, and with one slice
variable per point, u_i | z_i ~ U(0, w_{z_i}), the joint density is

    Π_i 1(u_i < w_{z_i}) N(y_i; θ_{z_i}) · Π_j Beta(v_j; 1, α) H(θ_j),

and integrating u_i out gives back P(z_i = j) = w_j. Given the slices only the finitely many
sticks with w_j > min_i u_i can hold a point, so a sweep needs finitely many. A sweep:

1. the occupied atoms | their points: Algorithm 8's step 2
   (``dipole_torch.dp.conditionals.resample_parameters``, the Σ step with its
   Metropolis-Hastings correction for R), then H | the occupied atoms when H is updated;
2. the sticks | labels, u integrated out: v_j ~ Beta(1 + n_j, α + Σ_{l>j} n_l);
3. the slices | sticks, labels: u_i = w_{z_i} · U(0, 1];
4. more sticks from Beta(1, α) until the mass left, Π_j (1 − v_j), is below min_i u_i, and
   every empty stick's atom from H;
5. every label at once: P(z_i = j) ∝ 1(u_i ≤ w_j) N(y_i; μ_j, Σ_j + R), one ``[N, J]`` matrix
   of log densities and one batched inverse-CDF draw.

Each step draws from an exact conditional, so the chain samples the same posterior as
Algorithm 8 (checked against the enumerated posterior in ``tests/test_dp_exact.py``). It does
O(N·J) work per sweep in a few dozen batched tensor operations, with no loop over points: the
sampler for large data sets and for GPUs. Per sweep it mixes more slowly than Algorithm 8
(the labels see the sticks' weights, not the clusters' sizes), and the reward weighting of
eq. 6 is not defined for it: DIPOLE's own clusterings stay with Algorithm 8, the paper's
sampler. The labels are stick indices, whose order the sticks' conditionals depend on; a
``SliceChain`` keeps them between sweeps, and ``SliceChain.state`` makes them
contiguous.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.dp.conditionals import resample_parameters
from dipole_torch.dp.state import DPMixtureState
from dipole_torch.gaussian import DTYPE, log_prob_tril
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.sampling import _to, draw_categorical, uniforms

if TYPE_CHECKING:
    from dipole_torch.dp.sampler import DPSampler

__all__ = ["SliceChain", "slice_sweep"]

_STICK_BLOCK = 8  # sticks drawn at a time when the slices need more
_MAX_STICKS = 2**16  # about α·log(1 / min u) are needed: far more means α is huge


@dataclass
class SliceChain:
    """A state of the slice sampler.

    Attributes:
        labels: ``[N]`` the stick of every point (not contiguous: empty sticks keep their
            place).
        means: ``[J, D]`` the atoms' means of sticks ``0 … J − 1``, ``J > labels.max()``.
        covariances: ``[J, D, D]`` their covariances (regularisation included).
        prior: the base distribution H.
    """

    labels: Tensor
    means: Tensor
    covariances: Tensor
    prior: NormalInverseWishartPrior

    @classmethod
    def from_state(cls, state: DPMixtureState) -> SliceChain:
        """Start a chain from a ``DPMixtureState`` (its
        component c on stick c)."""
        return cls(state.labels, state.means, state.covariances, state.prior)

    def state(self) -> DPMixtureState:
        """The occupied sticks as a ``DPMixtureState`` (labels contiguous, in stick
        order)."""
        k = self.means.shape[0]
        occupied = torch.bincount(self.labels, minlength=k) > 0
        remap = torch.cumsum(occupied.long(), 0) - 1
        return DPMixtureState(
            remap[self.labels], self.means[occupied], self.covariances[occupied], self.prior
        )


def slice_sweep(
    y: Tensor, chain: SliceChain, sampler: DPSampler, generator: torch.Generator | None
) -> SliceChain:
    """One sweep of the slice sampler (module docstring: steps 1–5), with ``sampler``'s α,
    inner steps, H update and Σ step; its prior anchors the update of H.

    Args:
        y: ``[N, D]`` data (float64).
        chain: the current state.
        generator: source of all randomness (its device may differ from ``y``'s).

    Returns:
        The new state.
    """
    alpha = sampler.alpha
    y = y if y.dtype == DTYPE else y.to(DTYPE)
    n = y.shape[0]
    prior = chain.prior
    labels = chain.labels
    # Sticks after the last occupied one are redrawn below like any new stick.
    sticks = int(labels.max()) + 1
    counts = torch.bincount(labels, minlength=sticks).to(DTYPE)  # [J]
    occupied = counts > 0

    # 1. The occupied atoms, given their points; then H, given them.
    remap = torch.cumsum(occupied.long(), 0) - 1
    compact = DPMixtureState(
        remap[labels], chain.means[:sticks][occupied], chain.covariances[:sticks][occupied], prior
    )
    compact = resample_parameters(
        y, compact, sampler.inner_steps, generator, sampler.exact_covariance,
        counts=counts[occupied],
    )  # fmt: skip
    if sampler.update_prior:
        prior = prior.updated(
            compact.means, compact.covariances - prior.regularization, sampler.prior, generator
        )

    # 2. The sticks, given the labels: v_j ~ Beta(1 + n_j, α + Σ_{l>j} n_l), in log space
    # (log v and log(1 − v) stay finite where v itself would round to 1).
    later = counts.flip(0).cumsum(0).flip(0) - counts
    log_v, log_rest = _log_beta(1.0 + counts, alpha + later, generator)
    log_w = log_v + _exclusive_cumsum(log_rest)  # [J] log w_j

    # 3. The slices: log u_i = log w_{z_i} + log U(0, 1] (U = 1 − U[0, 1) is never 0).
    log_u = log_w[labels] + torch.log1p(-uniforms(n, generator, y.device))

    # 4. More sticks until the mass left is below every slice.
    lowest = float(log_u.min())
    left = float(log_rest.sum())
    while left >= lowest:
        if log_w.shape[0] >= _MAX_STICKS:
            raise ValueError(
                f"alpha={alpha} needs more than {_MAX_STICKS} sticks to cover these slices; "
                "the slice sampler suits a concentration of order 1 to 100"
            )
        ones = torch.ones(_STICK_BLOCK, dtype=DTYPE, device=y.device)
        more_v, more_rest = _log_beta(ones, alpha * ones, generator)
        log_w = torch.cat((log_w, left + more_v + _exclusive_cumsum(more_rest)))
        left += float(more_rest.sum())
    total, d = log_w.shape[0], y.shape[1]
    kept = torch.zeros(total, dtype=torch.bool, device=y.device)
    kept[:sticks] = occupied
    means = torch.empty(total, d, dtype=DTYPE, device=y.device)
    covs = torch.empty(total, d, d, dtype=DTYPE, device=y.device)
    means[kept], covs[kept] = compact.means, compact.covariances
    fresh_means, fresh_covs = prior.sample(total - compact.num_components, generator)
    means[~kept], covs[~kept] = fresh_means, fresh_covs

    # 5. Every label at once, among the sticks above its slice.
    log_lik = log_prob_tril(y[:, None, :], means, torch.linalg.cholesky(covs))  # [N, J]
    logits = torch.where(log_u[:, None] <= log_w, log_lik, -math.inf)
    new_labels = draw_categorical(logits, uniforms(n, generator, y.device))
    return SliceChain(new_labels, means, covs, prior)


def _log_beta(a: Tensor, b: Tensor, generator: torch.Generator | None) -> tuple[Tensor, Tensor]:
    """``(log v, log(1 − v))`` for v ~ Beta(a, b), elementwise, from two gamma draws
    (``torch._standard_gamma`` takes the generator; ``torch.distributions.Beta`` does
    not)."""
    where = generator.device if generator is not None else a.device
    x = torch._standard_gamma(_to(a, where), generator=generator)
    z = torch._standard_gamma(_to(b, where), generator=generator)
    log_x, log_z = _to(x.log(), a.device), _to(z.log(), a.device)
    log_sum = torch.logaddexp(log_x, log_z)
    return log_x - log_sum, log_z - log_sum


def _exclusive_cumsum(values: Tensor) -> Tensor:
    """``[J]`` Σ_{l<j} values_l."""
    return torch.cumsum(values, 0) - values

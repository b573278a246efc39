"""The component parameters' conditional posteriors of the DP mixture (Algorithm 8's step 2)
and the point estimate a clustering ends with.

The prior H is non-linked: μ ~ N(μ0, Σ0) and Σ ~ IW(ν0, Ψ0) independently, and the
likelihood uses Σ + R (R the regularisation, the paper's heuristic "to avoid degeneracies").
Hence μ | Σ, y is Normal (``mean_conditional``), Σ | μ, y has no closed form once
R ≠ 0 and is sampled by an independence Metropolis-Hastings step
(``covariance_step``).

Every sum over points is taken about a centre (the prior mean, the component mean) rather
than from raw sums: at offsets of 1e6 the raw sums carry no digits of a spread of 1e-2.
"""

from __future__ import annotations

import math
from dataclasses import replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE, draw_normal_precision, symmetric
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.sampling import _to

if TYPE_CHECKING:
    from dipole_torch.dp.state import DPMixtureState

__all__ = [
    "covariance_step",
    "data_mean",
    "mean_conditional",
    "posterior_point_estimate",
    "resample_parameters",
    "residual_sums",
    "scatter_matrices",
]


def data_mean(y: Tensor) -> Tensor:
    """``[D]`` mean of ``y: [N, D]``, refined by the mean residual (for large offsets)."""
    mean = y.mean(0)
    return mean + (y - mean).mean(0)


def residual_sums(y: Tensor, labels: Tensor, centres: Tensor, k: int) -> Tensor:
    """``[K, D]`` Σ_{i in c} (y_i − centre_c) for ``centres: [K, D]`` or one ``[D]``."""
    centred = y - (centres[labels] if centres.dim() == 2 else centres)
    return torch.zeros(k, y.shape[-1], dtype=y.dtype, device=y.device).index_add_(
        0, labels, centred
    )


def scatter_matrices(y: Tensor, labels: Tensor, means: Tensor) -> Tensor:
    """``[K, D, D]`` Σ_{i in c} (y_i − μ_c)(y_i − μ_c)ᵀ for ``means: [K, D]``, batched.

    From centred residuals: Σ y yᵀ − 2 (Σ y) μᵀ + n μ μᵀ from raw sums cancels
    catastrophically at large offsets (1e12 against a scatter of 1e-4 at θ ≈ 1e6) and can
    leave the inverse-Wishart scale indefinite.
    """
    d = y.shape[-1]
    centred = y - means[labels]
    scatter = torch.zeros(means.shape[0], d, d, dtype=y.dtype, device=y.device)
    scatter.index_add_(0, labels, centred[:, :, None] * centred[:, None, :])
    return symmetric(scatter)


def mean_conditional(
    prior: NormalInverseWishartPrior, covs: Tensor, counts: Tensor, residuals: Tensor
) -> tuple[Tensor, Tensor]:
    """μ | Σ, y ~ N(P⁻¹ (Σ0⁻¹ μ0 + Σ⁻¹ Σ y), P⁻¹), P = Σ0⁻¹ + n Σ⁻¹, batched over K.

    The location is computed as μ0 + P⁻¹ Σ⁻¹ Σ_i (y_i − μ0), the same quantity without the
    cancellation of μ0-sized terms at large offsets.

    Args:
        covs: ``[K, D, D]`` component covariances Σ (regularisation included).
        counts: ``[K]`` points per component.
        residuals: ``[K, D]`` Σ_{i in c} (y_i − μ0) (``residual_sums`` about μ0).

    Returns:
        ``[K, D]`` the location and ``[K, D, D]`` the Cholesky factor of the precision P.
    """
    prior_precision = prior._mean_precision()  # Σ0⁻¹, factorised once per prior
    precision_k = torch.cholesky_inverse(torch.linalg.cholesky(covs))
    precision = prior_precision + counts[:, None, None] * precision_k
    precision = symmetric(precision)
    rhs = (precision_k @ residuals[:, :, None]).squeeze(-1)
    chol = torch.linalg.cholesky(precision)
    loc = prior.mean_loc + torch.cholesky_solve(rhs[:, :, None], chol).squeeze(-1)
    return loc, chol


def covariance_step(
    prior: NormalInverseWishartPrior,
    covs: Tensor,
    counts: Tensor,
    scatter: Tensor,
    generator: torch.Generator | None,
    exact: bool = True,
) -> tuple[Tensor, Tensor]:
    """Σ | μ, y by independence Metropolis-Hastings, batched over K.

    The proposal is the unregularised conjugate draw Σ' ~ IW(ν0 + n, Ψ0 + S), S the scatter
    about μ; it is accepted with probability min(1, ρ(Σ') / ρ(Σ)), where
    ρ(Σ) = Π_i N(y_i; μ, Σ + R) / N(y_i; μ, Σ) is the target over the proposal density up to
    a constant. With R = 0, ρ ≡ 1 and every proposal is accepted: the plain Gibbs draw.

    Args:
        covs: ``[K, D, D]`` current Σ + R.
        counts: ``[K]`` points per component.
        scatter: ``[K, D, D]`` Σ_i (y_i − μ)(y_i − μ)ᵀ about the current means.
        exact: ``False`` accepts every proposal (the conjugate draw of the unregularised
            model, then + R: a different model, kept as an ablation).

    Returns:
        ``[K, D, D]`` the new Σ + R, and ``[K]`` whether each proposal was accepted.
    """
    reg = prior.regularization
    # The acceptance uniforms are drawn with or without the test, so the rest of the chain
    # is the same either way (identical for R = 0, where every proposal is accepted).
    proposal, uniforms = prior.sample_inverse_wishart(
        prior.df + counts, prior.scale + scatter, generator, num_uniforms=counts.shape[0]
    )
    uniforms = _to(uniforms, covs.device)
    if not exact:
        return proposal + reg, torch.ones_like(counts, dtype=torch.bool)
    k = counts.shape[0]
    # Proposal and current state in one batched call (half the small-tensor ops).
    both = _regularisation_log_weight(
        torch.cat((proposal, covs - reg)),
        reg,
        torch.cat((counts, counts)),
        torch.cat((scatter, scatter)),
    )
    log_ratio, log_current = both[:k], both[k:]
    # A current Σ outside the support (Σ + R given from outside, Σ not positive definite) has
    # target density 0: any proposal is accepted.
    accept = (log_current == -math.inf) | (uniforms.log() < log_ratio - log_current)
    return torch.where(accept[:, None, None], proposal + reg, covs), accept


def _regularisation_log_weight(
    covs: Tensor, regularization: Tensor, counts: Tensor, scatter: Tensor
) -> Tensor:
    """``[K]`` Σ_i log N(y_i; μ, Σ + R) − log N(y_i; μ, Σ) for ``covs: [K, D, D]`` Σ.

    From the scatter S about μ: −½ [n (log|Σ + R| − log|Σ|) + tr(((Σ + R)⁻¹ − Σ⁻¹) S)].
    Exactly 0 for R = 0 (both terms come from identical matrices); −inf where Σ is not
    positive definite.
    """
    chol, info = torch.linalg.cholesky_ex(covs)
    valid = info == 0
    # On CPU, where asking costs no sync, the masking is skipped when nothing needs it.
    all_valid = covs.device.type == "cpu" and not bool(info.any())
    if not all_valid:
        eye = torch.eye(covs.shape[-1], dtype=covs.dtype, device=covs.device)
        # Placeholders where Σ is not positive definite, masked out below.
        chol = torch.where(valid[:, None, None], chol, eye)
        covs = torch.where(valid[:, None, None], covs, eye)
    chol_reg = torch.linalg.cholesky(covs + regularization)

    def log_lik(factor: Tensor) -> Tensor:  # Σ_i log N(y_i; μ, L Lᵀ) up to −½ n D log 2π
        log_det = 2.0 * factor.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        trace = torch.cholesky_solve(scatter, factor).diagonal(dim1=-2, dim2=-1).sum(-1)
        return -0.5 * (counts * log_det + trace)

    weight = log_lik(chol_reg) - log_lik(chol)
    if all_valid:
        return weight
    return torch.where(valid, weight, torch.full_like(weight, -math.inf))


def resample_parameters(
    y: Tensor,
    state: DPMixtureState,
    steps: int,
    generator: torch.Generator | None,
    exact_covariance: bool = True,
    counts: Tensor | None = None,
) -> DPMixtureState:
    """Algorithm 8's step 2: every component's (μ, Σ) redrawn given its points, batched over
    K, by ``steps`` alternations of the exact μ | Σ, y draw (``mean_conditional``) and
    the Σ | μ, y Metropolis-Hastings step (``covariance_step``).

    Args:
        y: ``[N, D]`` data (float64).
        state: labels, current ``[K, D]`` means and ``[K, D, D]`` covariances Σ + R, and H.
        steps: alternations of the μ and Σ steps.
        generator: source of all randomness.
        exact_covariance: apply the Metropolis-Hastings correction.
        counts: ``[K]`` float64 points per component, when the caller has them already.

    Returns:
        The state with the new means and covariances (Σ + R).
    """
    prior = state.prior
    labels, k = state.labels, state.num_components
    if counts is None:
        counts = torch.bincount(labels, minlength=k).to(DTYPE)
    residuals = residual_sums(y, labels, prior.mean_loc, k)
    means, covs = state.means, state.covariances
    for _ in range(steps):
        loc, precision_tril = mean_conditional(prior, covs, counts, residuals)
        means = draw_normal_precision(loc, precision_tril, generator)
        scatter = scatter_matrices(y, labels, means)
        covs = covariance_step(prior, covs, counts, scatter, generator, exact_covariance)[0]
    return replace(state, means=means, covariances=covs)


def posterior_point_estimate(y: Tensor, state: DPMixtureState) -> DPMixtureState:
    """Replace the last draw by conditional posterior means: E[Σ | μ, y] then E[μ | Σ, y].

    DIPOLE explores with each component's covariance; a single inverse-Wishart draw from five
    points in ten dimensions is too erratic for that, its conditional mean is not. E[Σ | μ, y]
    is that of the conjugate, unregularised conditional IW(ν0 + n, Ψ0 + S), plus R (a point
    estimate; the chain's own Σ step is exact, see ``resample_parameters``).

    Args:
        y: ``[N, D]`` data.
        state: labels ``[N]``, means ``[K, D]`` (S is taken about them) and H.
    """
    y = y.to(DTYPE)
    prior = state.prior
    labels, k = state.labels, state.num_components
    counts = torch.bincount(labels, minlength=k).to(DTYPE)
    scatter = scatter_matrices(y, labels, state.means)
    dof = (prior.df + counts - prior.dim - 1)[:, None, None]
    covs = (prior.scale + scatter) / dof + prior.regularization
    residuals = residual_sums(y, labels, prior.mean_loc, k)
    means = mean_conditional(prior, covs, counts, residuals)[0]
    return replace(state, means=means, covariances=covs)

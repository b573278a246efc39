"""The component parameters' conditional posteriors of the DP mixture (Algorithm 8's step 2)
and the point estimate a clustering ends with.

The prior H is non-linked: μ ~ N(μ0, Σ0) and Σ ~ IW(ν0, Ψ0) independently, and the
likelihood uses Σ + R (R the regularisation, the paper's heuristic "to avoid degeneracies").
Hence μ | Σ, y is Normal (``mean_conditional``), Σ | μ, y has no closed form once
R ≠ 0 and is sampled by an independence Metropolis-Hastings step
(``covariance_step``).

A sweep makes a few such steps for a few components: the cost is the number of tensor
calls, not their arithmetic. So every random number of the step is drawn up front
(``ParameterDraws``), each component's covariance travels with its Cholesky factor (the μ
step, the Metropolis-Hastings weights and the next sweep's likelihoods all need it), and
the four log-likelihood terms of the Metropolis-Hastings ratio are one batched call.

Every sum over points is taken about a centre (the prior mean, the component mean) rather
than from raw sums: at offsets of 1e6 the raw sums carry no digits of a spread of 1e-2.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace
from typing import TYPE_CHECKING

import torch
from torch import Tensor

from dipole_torch.gaussian import DTYPE
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.sampling import _to, bartlett_factor, inverse_wishart_from_factor

if TYPE_CHECKING:
    from dipole_torch.dp.state import DPMixtureState

__all__ = [
    "Covariances",
    "ParameterDraws",
    "SINGULAR_PIVOT",
    "check_estimate",
    "covariance_step",
    "data_mean",
    "draw_mean",
    "log_likelihoods",
    "mean_conditional",
    "mean_location",
    "posterior_point_estimate",
    "resample_parameters",
    "residual_sums",
    "scatter_matrices",
    "singular_by_rounding",
]


# A Cholesky pivot below this fraction of its variance is rounding: the matrix is singular.
SINGULAR_PIVOT = 1e-10


def singular_by_rounding(tril: Tensor, matrix: Tensor) -> Tensor:
    """``[...]`` whether ``matrix: [..., D, D]``, factorised as ``tril``, is singular though
    its factorisation succeeded: a pivot below ``SINGULAR_PIVOT`` of its variance (the part
    of that coordinate's variance the ones before it leave unexplained) is rounding."""
    pivots = tril.diagonal(dim1=-2, dim2=-1).square() / matrix.diagonal(dim1=-2, dim2=-1)
    return ~(pivots.amin(-1) >= SINGULAR_PIVOT)  # (NaN counts as singular)


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
    leave the inverse-Wishart scale indefinite. (Exactly symmetric: each outer product is,
    and both triangles add the same numbers in the same order.)
    """
    centred = y - means[labels]
    scatter = torch.zeros(means.shape[0], y.shape[-1], y.shape[-1], dtype=y.dtype, device=y.device)
    return scatter.index_add_(0, labels, centred[:, :, None] * centred[:, None, :])


def mean_conditional(
    prior: NormalInverseWishartPrior, precisions: Tensor, counts: Tensor, residuals: Tensor
) -> tuple[Tensor, Tensor]:
    """μ | Σ, y ~ N(P⁻¹ (Σ0⁻¹ μ0 + Σ⁻¹ Σ y), P⁻¹), P = Σ0⁻¹ + n Σ⁻¹, batched over K.

    The location is computed as μ0 + P⁻¹ Σ⁻¹ Σ_i (y_i − μ0), the same quantity without the
    cancellation of μ0-sized terms at large offsets.

    Args:
        precisions: ``[K, D, D]`` Σ⁻¹ of the component covariances (regularisation included).
        counts: ``[K]`` points per component.
        residuals: ``[K, D]`` Σ_{i in c} (y_i − μ0) (``residual_sums`` about μ0).

    Returns:
        ``[K, D, 1]`` L⁻¹ Σ⁻¹ Σ_i (y_i − μ0) and ``[K, D, D]`` the Cholesky factor L of the
        precision P: the location is μ0 + L⁻ᵀ of the first (``draw_mean``, ``mean_location``).
    """
    # (Σ0⁻¹ and Σ⁻¹ from cholesky_inverse are exactly symmetric, and so is P: positive
    # definite by construction, hence factorised without the error check's cost.)
    precision = prior._mean_precision() + counts[:, None, None] * precisions
    chol = torch.linalg.cholesky_ex(precision)[0]
    half = torch.linalg.solve_triangular(chol, precisions @ residuals[:, :, None], upper=False)
    return half, chol


def mean_location(prior: NormalInverseWishartPrior, half: Tensor, chol: Tensor) -> Tensor:
    """``[K, D]`` E[μ | Σ, y] = μ0 + L⁻ᵀ ``half`` from ``mean_conditional``'s pair."""
    return prior.mean_loc + torch.linalg.solve_triangular(chol.mT, half, upper=True).squeeze(-1)


def draw_mean(
    prior: NormalInverseWishartPrior, half: Tensor, chol: Tensor, normals: Tensor
) -> Tensor:
    """``[K, D]`` μ ~ N(μ0 + L⁻ᵀ half, P⁻¹) from ``mean_conditional``'s pair and standard
    ``normals: [K, D]``: μ0 + L⁻ᵀ (half + z), whose covariance is L⁻ᵀ L⁻¹ = P⁻¹."""
    return mean_location(prior, half + normals[:, :, None], chol)


@dataclass
class ParameterDraws:
    """The random numbers of ``steps`` alternations of the μ and Σ steps for K components,
    drawn at once (three generator calls instead of four a step):

    * ``normals [steps, K, D]``: the μ draws' standard normals;
    * ``bartlett [steps, K, D, D]``: Bartlett factors of Wishart(ν0 + n_k, I) for the Σ
      proposals IW(ν0 + n_k, Ψ0 + S_k) (``dipole_torch.sampling.bartlett_factor``);
    * ``log_uniforms [steps, K]``: the Metropolis-Hastings acceptance draws, log U(0, 1).
    """

    normals: Tensor
    bartlett: Tensor
    log_uniforms: Tensor

    @classmethod
    def draw(
        cls,
        prior: NormalInverseWishartPrior,
        counts: Tensor,
        steps: int,
        generator: torch.Generator | None,
    ) -> ParameterDraws:
        """Draws for ``steps`` alternations of the components with ``counts: [K]`` points
        (on ``generator``'s device, moved to ``counts``')."""
        k, d = counts.shape[0], prior.dim
        device = counts.device
        where = generator.device if generator is not None else device
        normals = torch.randn(steps, k, d, generator=generator, dtype=DTYPE, device=where)
        bartlett = bartlett_factor((prior.df + counts).expand(steps, k), d, generator)
        uniforms = torch.rand(steps, k, generator=generator, dtype=DTYPE, device=where)
        return cls(_to(normals, device), bartlett, _to(uniforms, device).log())


@dataclass
class Covariances:
    """K component covariances Σ + R with their Cholesky factors and inverses, as the μ and
    Σ steps use them: ``covs``, ``tril``, ``precisions``, all ``[K, D, D]``."""

    covs: Tensor
    tril: Tensor
    precisions: Tensor

    @classmethod
    def of(cls, covs: Tensor, tril: Tensor | None = None) -> Covariances:
        """From ``covs`` (and their factors when known)."""
        tril = torch.linalg.cholesky(covs) if tril is None else tril
        return cls(covs, tril, torch.cholesky_inverse(tril))


def log_likelihoods(tril: Tensor, precisions: Tensor, counts: Tensor, scatter: Tensor) -> Tensor:
    """``[B]`` Σ_i log N(y_i; μ, Σ) of each component's points up to −½ n D log 2π, from the
    scatter S about μ: −½ (n log|Σ| + tr(Σ⁻¹ S)).

    Args:
        tril: ``[B, D, D]`` Cholesky factors of Σ; ``precisions``: ``[B, D, D]`` Σ⁻¹.
        counts: ``[B]`` points per component; ``scatter``: ``[B, D, D]`` S.
    """
    half_log_det = tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    trace = (precisions * scatter).sum((-2, -1))  # tr(Σ⁻¹ S), both symmetric
    return -(counts * half_log_det + 0.5 * trace)


def covariance_step(
    prior: NormalInverseWishartPrior,
    current: Covariances,
    counts: Tensor,
    scatter: Tensor,
    bartlett: Tensor,
    log_uniforms: Tensor,
    exact: bool = True,
    check_support: bool = True,
) -> tuple[Covariances, Tensor]:
    """Σ | μ, y by independence Metropolis-Hastings, batched over K.

    The proposal is the unregularised conjugate draw Σ' ~ IW(ν0 + n, Ψ0 + S), S the scatter
    about μ; it is accepted with probability min(1, ρ(Σ') / ρ(Σ)), where
    ρ(Σ) = Π_i N(y_i; μ, Σ + R) / N(y_i; μ, Σ) is the target over the proposal density up to
    a constant (``log_likelihoods`` of Σ + R less those of Σ). With R = 0, ρ ≡ 1 and every
    proposal is accepted: the plain Gibbs draw.

    Args:
        current: the current Σ + R (``Covariances``).
        counts: ``[K]`` points per component.
        scatter: ``[K, D, D]`` Σ_i (y_i − μ)(y_i − μ)ᵀ about the current means.
        bartlett: ``[K, D, D]`` Bartlett factors of Wishart(ν0 + n, I) (``ParameterDraws``).
        log_uniforms: ``[K]`` log U(0, 1) acceptance draws.
        exact: ``False`` accepts every proposal (the conjugate draw of the unregularised
            model, then + R: a different model, kept as an ablation).
        check_support: also count a current Σ that factorises on rounding alone as outside
            the support (``singular_by_rounding``). Only a chain's start can be one
            (Algorithm 1's covariance of fewer points than dimensions: DIPOLE at D = 10 has 10
            points in p = 11, and about one time in five it factorises); after a step the
            current Σ is a proposal taken or a Σ that passed, so ``resample_parameters``
            asks for the test at its first step only.

    Returns:
        The new Σ + R (``Covariances``), and ``[K]`` whether each proposal was accepted.
    """
    reg = prior.regularization
    k = counts.shape[0]
    scale_tril = torch.linalg.cholesky_ex(prior.scale + scatter)[0]  # positive definite
    proposal = inverse_wishart_from_factor(bartlett, scale_tril)
    candidate = proposal + reg
    if not exact:
        accept = torch.ones(k, dtype=torch.bool, device=candidate.device)
        return Covariances.of(candidate), accept
    # Σ', Σ' + R and the current Σ factorised in one call, then inverted in one: with the
    # current Σ + R's, the four terms of the ratio. (The state holds Σ + R; the current Σ is
    # its difference with R.)
    stacked = torch.cat((proposal, candidate, current.covs - reg))
    tril, info = torch.linalg.cholesky_ex(stacked)
    if check_support:
        # A current Σ that factorises on rounding alone is as far outside the support as one
        # that does not (``singular_by_rounding``).
        outside = singular_by_rounding(tril[2 * k :], stacked[2 * k :])
        info = torch.cat((info[: 2 * k], torch.where(outside, 1, info[2 * k :])))
    # On CPU, where asking costs no sync, the masking is skipped when nothing needs it.
    masked = current.covs.device.type != "cpu" or bool(info.any())
    if masked:  # placeholders where a matrix did not factorise, masked out below
        failed = info != 0
        eye = torch.eye(tril.shape[-1], dtype=tril.dtype, device=tril.device)
        tril = torch.where(failed[:, None, None], eye, tril)
    precisions = torch.cholesky_inverse(tril)
    log_lik = log_likelihoods(
        torch.cat((tril, current.tril)),
        torch.cat((precisions, current.precisions)),
        torch.cat((counts, counts, counts, counts)),
        torch.cat((scatter, scatter, scatter, scatter)),
    ).view(2, 2, k)  # [proposal, current] x [Σ, Σ + R]
    log_weight = log_lik[:, 1] - log_lik[:, 0]  # log ρ of the proposal and of the current
    if masked:
        # A Σ that did not factorise has target density 0: a current Σ outside the support
        # (Σ + R given from outside) takes any proposal, a failed proposal is refused.
        failed = failed.view(3, k)  # Σ', Σ' + R, current Σ
        refused = failed[0] | failed[1]
        log_weight = torch.where(torch.stack((refused, failed[2])), -math.inf, log_weight)
        accept = (log_weight[1] == -math.inf) | (log_uniforms < log_weight[0] - log_weight[1])
        accept = accept & ~refused
    else:
        accept = log_uniforms < log_weight[0] - log_weight[1]
    wide = accept[:, None, None]
    new = Covariances(
        torch.where(wide, candidate, current.covs),
        torch.where(wide, tril[k : 2 * k], current.tril),
        torch.where(wide, precisions[k : 2 * k], current.precisions),
    )
    return new, accept


def resample_parameters(
    y: Tensor,
    state: DPMixtureState,
    steps: int,
    generator: torch.Generator | None,
    exact_covariance: bool = True,
    counts: Tensor | None = None,
    tril: Tensor | None = None,
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
        tril: ``[K, D, D]`` Cholesky factors of the covariances, when the caller has them.

    Returns:
        The state with the new means and covariances (Σ + R).
    """
    prior = state.prior
    labels, k = state.labels, state.num_components
    if counts is None:
        counts = torch.bincount(labels, minlength=k).to(DTYPE)
    covariances = Covariances.of(state.covariances, tril)
    residuals = residual_sums(y, labels, prior.mean_loc, k)
    draws = ParameterDraws.draw(prior, counts, steps, generator)
    for step in range(steps):
        half, chol = mean_conditional(prior, covariances.precisions, counts, residuals)
        means = draw_mean(prior, half, chol, draws.normals[step])
        scatter = scatter_matrices(y, labels, means)
        covariances, _ = covariance_step(
            prior, covariances, counts, scatter, draws.bartlett[step], draws.log_uniforms[step],
            exact_covariance, check_support=step == 0,
        )  # fmt: skip
    return replace(state, means=means, covariances=covariances.covs)


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
    precisions = torch.cholesky_inverse(torch.linalg.cholesky(covs))
    means = mean_location(prior, *mean_conditional(prior, precisions, counts, residuals))
    return replace(state, means=means, covariances=covs)


# How far beyond the data (in multiples of its width plus a reference spread) a component's
# mean may lie, or how wide a covariance may be, before it is taken for rounding garbage. The
# exact posterior mean is a matrix-weighted average of the data and μ0, which H's update keeps
# near the data: legitimate values stay within a few widths.
ESTIMATE_REACH = 1e6


def check_estimate(y: Tensor, state: DPMixtureState, spread: Tensor) -> DPMixtureState:
    """``state`` if its parameters and H are sound for ``y``; else ``FloatingPointError``.

    Data whose coordinates differ in scale by a hundred orders of magnitude (a return of
    1e148 beside parameters of order one) make the covariances too ill-conditioned for
    float64: their factorisation then yields NaN, or values that are finite but absurd
    (H's mean covariance 1e247 and a component mean 1e124 for parameters in [-1, 1]).
    Converged samples without regularisation (``regularization=0``: a policy whose kept
    samples are one point) make a component's covariance singular to rounding, and H's
    update then draws a scale Ψ0 just as singular: the estimate's covariance has a
    correlation beyond 1 − 1e-16 between two coordinates (or a negative eigenvalue) and its
    mean lies far off the data along the lost direction: the exploration the paper's
    variant takes from it no longer factorises at the next ask. A covariance that does not
    factorise, or is singular by rounding (``singular_by_rounding``), is refused too. All
    are refused here, so that a caller can skip the clustering instead of adopting them.

    Args:
        y: ``[N, D]`` the data the state was fitted to.
        state: means ``[K, D]``, covariances ``[K, D, D]`` and H.
        spread: ``[D]`` a reference standard deviation per coordinate (the initial H's),
            which sets the reach where the data have no width.
    """
    y = y.to(state.means.dtype)
    prior = state.prior
    low, high = y.amin(0), y.amax(0)
    reach = ESTIMATE_REACH * (high - low + spread)
    locations = torch.cat((state.means, prior.mean_loc[None]))  # [K + 1, D]
    stds = torch.cat(
        (state.covariances.diagonal(dim1=-2, dim2=-1), prior.mean_covariance.diagonal()[None])
    ).sqrt()
    tril, info = torch.linalg.cholesky_ex(state.covariances)
    factorises = (info == 0) & ~singular_by_rounding(tril, state.covariances)
    # NaN fails every comparison: it counts as not inside. One host sync for all.
    inside = (locations >= low - reach) & (locations <= high + reach) & (stds <= reach)
    if not bool(inside.all() & factorises.all()):
        raise FloatingPointError(
            "the DP mixture's estimate is not sound (non-finite, far outside the data, or a "
            "covariance singular to float64): the data's coordinates differ in scale, or the "
            "samples are degenerate, beyond what float64 factorises"
        )
    return state

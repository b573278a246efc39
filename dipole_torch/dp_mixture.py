"""Dirichlet-process Gaussian mixture (IGMM) sampled with Neal's (2000) Algorithm 8, with
DIPOLE's reward weighting (eq. 6).

All DP mathematics runs in float64: with D ≈ 10 and a few points per component, float32
Cholesky factors of the sampled covariances lose positive definiteness.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, replace

import numpy as np
import torch
from torch import Tensor

from dipole_torch.gaussian_mixture import GaussianMixture
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.sampling import _expand, _to, draw_categorical, draw_categorical_numpy
from dipole_torch.validation import check_finite, check_matrix_shape

DTYPE = torch.float64


@dataclass
class DPMixtureState:
    """One state of the Gibbs chain.

    Attributes:
        labels: ``[N]`` component index of every point, contiguous in ``[0, K)``.
        means: ``[K, D]`` component means.
        covariances: ``[K, D, D]`` component covariances (regularisation included).
        prior: the base distribution H, updated after every sweep unless the chain runs with
            ``update_prior=False``.
    """

    labels: Tensor
    means: Tensor
    covariances: Tensor
    prior: NormalInverseWishartPrior

    @property
    def num_components(self) -> int:
        return int(self.means.shape[0])

    @property
    def counts(self) -> Tensor:
        """``[K]`` number of points per component."""
        return torch.bincount(self.labels, minlength=self.num_components)

    def mixture(self) -> GaussianMixture:
        """The fitted mixture, with weights proportional to the component sizes."""
        return GaussianMixture(
            self.counts.to(self.means.dtype), self.means, self.covariances, validate_args=False
        )

    @classmethod
    def single_component(cls, y: Tensor, prior: NormalInverseWishartPrior) -> DPMixtureState:
        """Algorithm 1's start: one component with the data's mean and covariance.

        Args:
            y: ``[N, D]`` data.
        """
        y = y.to(DTYPE)
        n = y.shape[0]
        mean = _mean(y)
        centred = y - mean  # the covariance from centred data: exact at any offset
        cov = centred.T @ centred / max(n - 1, 1) + prior.regularization
        if torch.linalg.cholesky_ex(cov)[1] != 0 or n < 2:
            cov = prior.expected_covariance + prior.regularization
        return cls(
            labels=torch.zeros(n, dtype=torch.long, device=y.device),
            means=mean[None],
            covariances=cov[None],
            prior=prior,
        )

    @classmethod
    def from_labels(
        cls, y: Tensor, labels: Tensor, prior: NormalInverseWishartPrior
    ) -> DPMixtureState:
        """A state with the given partition and each component at its conditional posterior
        mean (see :func:`posterior_point_estimate`), e.g. to warm-start a chain."""
        y = y.to(DTYPE)
        labels = torch.unique(labels, return_inverse=True)[1].to(y.device)
        k = int(labels.max()) + 1
        centre = _mean(y)
        counts = torch.bincount(labels, minlength=k).to(DTYPE)
        means = centre + _residual_sums(y, labels, centre, k) / counts[:, None]
        covs = (prior.expected_covariance + prior.regularization).expand(k, -1, -1).clone()
        return posterior_point_estimate(y, cls(labels, means, covs, prior))

    def state_dict(self) -> dict:
        return {
            "labels": self.labels,
            "means": self.means,
            "covariances": self.covariances,
            "prior": self.prior.state_dict(),
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> DPMixtureState:
        return cls(
            labels=state["labels"],
            means=state["means"],
            covariances=state["covariances"],
            prior=NormalInverseWishartPrior.from_state_dict(state["prior"]),
        )


class RewardRegression:
    """E[w | θ] under a Gaussian mixture over y = [θ, w] (GMR), prepared once for many queries.

    The same regression as ``GaussianMixture.condition(θ_dims, θ).mean`` without building
    distribution objects: a sweep queries it for K component means and N·m auxiliary ones,
    and the objects' construction (shape broadcasting, validation) cost more than the maths.

    Args:
        weights: ``[K]`` mixing weights (any positive scale; e.g. the component sizes).
        means: ``[K, D + 1]`` component means.
        covariances: ``[K, D + 1, D + 1]`` component covariances.
    """

    def __init__(self, weights: Tensor, means: Tensor, covariances: Tensor):
        d = means.shape[-1] - 1
        self.means = means
        self.log_weights = (weights / weights.sum()).log()
        self.mean_theta, self.mean_w = means[:, :d], means[:, d]
        self.tril = torch.linalg.cholesky(covariances[:, :d, :d])  # [K, D, D]
        # gain_k = Σ_θθ⁻¹ Σ_θw: E[w | θ, k] = μ_w + gain_kᵀ (θ − μ_θ).
        cross = covariances[:, :d, d:]
        self.gain = torch.cholesky_solve(cross, self.tril).squeeze(-1)  # [K, D]
        self._bounds: tuple | None = None  # reward_weights' clamp, memoised per weights

    def predict(self, theta: Tensor) -> Tensor:
        """``[...]`` E[w | θ] for ``theta: [..., D]``."""
        diff = theta.unsqueeze(-2) - self.mean_theta  # [..., K, D]
        log_resp = torch.log_softmax(
            self.log_weights + _log_prob_tril(diff, 0.0, self.tril), dim=-1
        )
        conditional = self.mean_w + (self.gain * diff).sum(-1)  # [..., K]
        return (log_resp.exp() * conditional).sum(-1)


def reward_weights(
    mixture: GaussianMixture | RewardRegression,
    query_means: Tensor,
    floor: float | None = None,
    weights: Tensor | None = None,
) -> Tensor:
    """r_c of eq. 6: the reward the mixture predicts at a component's parameter mean.

    The reward is the last coordinate of y = [θ, r]; r_c = E[r | θ = μ_c^θ] by Gaussian mixture
    regression on ``mixture`` (the IGMM). Rewards must already be positive weights (see
    :class:`dipole_torch.RewardScale`).

    The regression extrapolates linearly away from the data (at a mean drawn from H it can
    predict far above the best reward, or below zero), so the prediction is clamped:

    * with ``weights``, to the data's range [max(min w, 1e-12·max |w|), max w], so no component
      is favoured beyond the best observed reward and none is ruled out;
    * without, below at 1e-12 · the largest |reward mean| of the mixture's components.

    Both bounds are relative, so r_c scales with the rewards and eq. 6's label probabilities
    do not depend on their units (an absolute floor silently switches eq. 6 off for small
    rewards). ``floor``, when given, replaces the lower bound by an absolute one.

    Args:
        mixture: the IGMM over ``[θ, r]`` (event dim D + 1), or its prepared
            :class:`RewardRegression`.
        query_means: ``[..., D + 1]`` component means whose θ-part is queried.
        floor: optional absolute lower bound on r_c.
        weights: ``[N]`` the data's reward weights (the last column of y).

    Returns:
        ``[...]`` log r_c.
    """
    if not isinstance(mixture, RewardRegression):
        mixture = RewardRegression(mixture.weights, mixture.means, mixture.covariances)
    d = mixture.means.shape[-1] - 1
    predicted = mixture.predict(query_means[..., :d])
    low, high = _clamp_bounds(mixture, predicted, floor, weights)
    if high is None:
        return predicted.clamp_min(low).log()
    return predicted.clamp(low, high).log()


def _clamp_bounds(
    regression: RewardRegression, predicted: Tensor, floor: float | None, weights: Tensor | None
) -> tuple[Tensor, Tensor | None]:
    """The 0-d bounds of :func:`reward_weights`' clamp (``high`` None without ``weights``).

    They depend on the mixture and the data only, not on the queries: a sweep queries the
    same regression twice (its components, then the auxiliary draws), so they are memoised
    on ``regression`` for the same ``weights`` tensor (unmodified) and ``floor``.
    """
    # (Inference tensors have no version counter: their bounds are not memoised.)
    cacheable = weights is None or not weights.is_inference()
    key = (weights, weights._version if weights is not None and cacheable else None, floor)
    key += (predicted.dtype,)
    memo = regression._bounds
    if cacheable and memo is not None and memo[0][0] is key[0] and memo[0][1:] == key[1:]:
        return memo[1]
    reference = (weights if weights is not None else regression.means[..., -1]).to(predicted)
    # The smallest normal float only matters for all-zero rewards, where eq. 6 is void.
    low = (1e-12 * reference.abs().max()).clamp_min(torch.finfo(predicted.dtype).tiny)
    if weights is not None:
        low = torch.maximum(low, reference.min())
    if floor is not None:
        low = torch.full_like(low, floor)
    high = None if weights is None else torch.maximum(reference.max(), low)
    if cacheable:
        regression._bounds = (key, (low, high))
    return low, high


def neal8_sweep(
    y: Tensor,
    state: DPMixtureState,
    alpha: float = 1.0,
    m: int = 10,
    reward_weighted: bool = False,
    generator: torch.Generator | None = None,
    inner_steps: int = 2,
    initial_prior: NormalInverseWishartPrior | None = None,
    update_prior: bool = True,
    exact_covariance: bool = True,
    reuse_auxiliary: bool = False,
) -> DPMixtureState:
    """One Gibbs sweep of Neal's Algorithm 8 (the paper's Algorithm 1, eqs. 5 and 6).

    1. Every label c_i is redrawn with probabilities (eq. 5; eq. 6 when ``reward_weighted``)
       ∝ r_c n_{-i,c} N(y_i; μ_c, Σ_c) for occupied components and ∝ r_c (α/m) N(y_i; μ_c, Σ_c)
       for m auxiliary components drawn fresh from H for this point (a singleton's own
       parameters fill the first auxiliary slot). The common factor b/(n − 1 + α) cancels.
    2. Every occupied component's parameters are redrawn from their conditional posteriors,
       ``inner_steps`` alternations of μ | Σ, y (Normal) and Σ | μ, y (inverse-Wishart, with a
       Metropolis-Hastings correction for the regularisation; see :func:`resample_parameters`).
    3. If ``update_prior``, H's hyperparameters are redrawn given the components
       (:meth:`NormalInverseWishartPrior.updated`); otherwise H stays fixed and the chain
       samples the DP mixture posterior under that H.

    Component parameters are fixed during step 1 (as in Algorithm 8), so the likelihoods of
    all points under the sweep's starting components are computed in one batched call before
    the per-point loop; r_c likewise comes from the mixture at the start of the sweep, clamped
    to the range of the data's reward weights ``y[:, -1]`` (:func:`reward_weights`). The
    auxiliary draws and their likelihoods are made in chunks of points (at most ~64 MB of
    ``[chunk, m, D, D]`` covariances, so memory does not grow with N·m), and a component
    opened at point i gets its likelihood column only for the points after i. The loop itself
    does O(K + m) work per point: on CPU in numpy (:func:`_label_pass_numpy`), on other
    devices with tensor ops that never wait for the device within a chunk of points (one
    sync a chunk; :func:`_label_pass_sync_free`). Both make the same draws from the same
    uniforms.

    Args:
        y: ``[N, D]`` data (for DIPOLE, ``[θ, r]`` with the positive reward weight last).
        state: the current chain state.
        alpha: DP concentration α > 0.
        m: number of auxiliary components (≥ 1).
        reward_weighted: multiply each component's probability by r_c (eq. 6).
        generator: source of all randomness.
        inner_steps: alternations of the μ and Σ conditionals per sweep.
        initial_prior: the prior the chain started from (anchors the update of H);
            defaults to ``state.prior``.
        update_prior: redraw H's hyperparameters after the sweep (step 3).
        exact_covariance: correct the Σ step for the regularisation (see
            :func:`resample_parameters`).
        reuse_auxiliary: instead of Algorithm 8's m fresh auxiliary draws per point, keep
            one set of m for the sweep and redraw only the slot a point takes (the "ReUse"
            sampler of Favaro & Teh 2013, also exact; a removed singleton's parameters
            replace a uniformly chosen slot). m + (slots taken) draws a sweep instead of
            N·m. CPU only (:func:`_label_pass_reuse`).

    Returns:
        The new state (contiguous labels, occupied components only).
    """
    _check_concentration(alpha, m)
    y = y if y.dtype == DTYPE else y.to(DTYPE)
    n, d = y.shape
    prior = state.prior
    weights = y[:, -1]
    if reward_weighted:
        counts = torch.bincount(state.labels, minlength=state.num_components).to(DTYPE)
        current = RewardRegression(counts, state.means, state.covariances)
        log_r = reward_weights(current, state.means, weights=weights)
    else:
        log_r = torch.zeros(state.num_components, dtype=DTYPE, device=y.device)
    log_aux_prior = math.log(alpha / m)
    uniforms = _uniforms(n, generator, y.device)

    def auxiliary(start: int, stop: int) -> _Auxiliary:
        """m fresh draws from H for each point of ``y[start:stop]``, with their scores."""
        size = stop - start
        # Unsymmetrised: only the lower triangles are read, until a component opens.
        means, covs = prior.sample(size * m, generator, symmetrize=False)
        means, covs = means.reshape(size, m, d), covs.reshape(size, m, d, d)
        tril = torch.linalg.cholesky(covs)
        log_lik = _log_prob_tril(y[start:stop, None, :], means, tril)
        aux_log_r = torch.zeros_like(log_lik)
        if reward_weighted:
            aux_log_r = reward_weights(current, means, weights=weights)
        return _Auxiliary(means, covs, tril, aux_log_r, log_aux_prior + aux_log_r + log_lik)

    if reuse_auxiliary:
        if y.device.type != "cpu":
            raise ValueError("reuse_auxiliary=True runs on CPU only")
        slot_uniforms = _uniforms(n, generator, y.device)

        def fresh(count: int) -> _Auxiliary:
            """``count`` draws from H with their scores at every point: ``[N, count]``."""
            means, covs = prior.sample(count, generator)
            tril = torch.linalg.cholesky(covs)
            aux_log_r = torch.zeros(count, dtype=DTYPE)
            if reward_weighted:
                aux_log_r = reward_weights(current, means, weights=weights)
            log_lik = _log_prob_tril(y[:, None, :], means, tril)
            return _Auxiliary(means, covs, tril, aux_log_r, log_aux_prior + aux_log_r + log_lik)

        labels, all_means, all_covs, counts = _label_pass_reuse(
            y, state, log_r, fresh, uniforms, slot_uniforms, log_aux_prior, m
        )
    else:
        chunk = _chunk_size(n, m, d)
        label_pass = _label_pass_numpy if y.device.type == "cpu" else _label_pass_sync_free
        labels, all_means, all_covs, counts = label_pass(
            y, state, log_r, auxiliary, uniforms, log_aux_prior, chunk
        )
    occupied = counts > 0
    # On CPU (no sync to ask) the relabelling is skipped when no component emptied.
    if y.device.type != "cpu" or not bool(occupied.all()):
        remap = torch.cumsum(occupied.long(), 0) - 1
        labels = remap[labels]
        all_means, all_covs, counts = all_means[occupied], all_covs[occupied], counts[occupied]
    new_state = DPMixtureState(labels, all_means, all_covs, prior)
    new_state = resample_parameters(
        y, new_state, inner_steps, generator, exact_covariance, counts=counts
    )
    if update_prior:
        anchor = initial_prior if initial_prior is not None else prior
        new_state.prior = prior.updated(
            new_state.means, new_state.covariances - prior.regularization, anchor, generator
        )
    return new_state


def resample_parameters(
    y: Tensor,
    state: DPMixtureState,
    steps: int,
    generator: torch.Generator | None,
    exact_covariance: bool = True,
    counts: Tensor | None = None,
) -> DPMixtureState:
    """Redraw every component's (μ, Σ) given its points, batched over K, ``steps`` times.

    The model's likelihood uses Σ + R (R the regularisation, the paper's heuristic "to avoid
    degeneracies"), with Σ ~ IW(ν0, Ψ0) under H; ``state.covariances`` hold Σ + R.

    * μ | Σ, y ~ N(m, P⁻¹) with P = Σ0⁻¹ + n (Σ + R)⁻¹ and m = P⁻¹ (Σ0⁻¹ μ0 + (Σ + R)⁻¹ Σ_i y_i),
      an exact Gibbs step.
    * Σ | μ, y has no closed form once R ≠ 0. An independence Metropolis-Hastings step proposes
      the unregularised conjugate draw Σ' ~ IW(ν0 + n, Ψ0 + S), S = Σ_i (y_i − μ)(y_i − μ)ᵀ,
      and accepts it with probability min(1, ρ(Σ') / ρ(Σ)), where
      ρ(Σ) = Π_i N(y_i; μ, Σ + R) / N(y_i; μ, Σ) is the target over the proposal density up to
      a constant. With R = 0, ρ ≡ 1 and every proposal is accepted: the plain Gibbs draw.
      ``exact_covariance=False`` skips the test and always takes Σ' (the earlier heuristic:
      the conjugate draw of the unregularised model, then + R), which samples a different
      model: on 3 points in 1-D with R = 0.3 it put 0.16 on one cluster against an exact
      0.06 (20 000 sweeps; tests/test_dp_exact.py).

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
    residuals = _residual_sums(y, labels, prior.mean_loc, k)
    means, covs = state.means, state.covariances
    for _ in range(steps):
        loc, precision_tril = _mean_conditional(prior, covs, counts, residuals)
        means = _draw_normal_precision(loc, precision_tril, generator)
        scatter = _scatter(y, labels, means)
        covs = _covariance_step(prior, covs, counts, scatter, generator, exact_covariance)[0]
    return replace(state, means=means, covariances=covs)


def posterior_point_estimate(y: Tensor, state: DPMixtureState) -> DPMixtureState:
    """Replace the last draw by conditional posterior means: E[Σ | μ, y] then E[μ | Σ, y].

    DIPOLE explores with each component's covariance; a single inverse-Wishart draw from five
    points in ten dimensions is too erratic for that, its conditional mean is not. E[Σ | μ, y]
    is that of the conjugate, unregularised conditional IW(ν0 + n, Ψ0 + S), plus R (a point
    estimate; the chain's own Σ step is exact, see :func:`resample_parameters`). Scatters are
    computed from centred data, so the estimate holds at any offset of y.

    Args:
        y: ``[N, D]`` data.
        state: labels ``[N]``, means ``[K, D]`` (S is taken about them) and H.
    """
    y = y.to(DTYPE)
    prior = state.prior
    labels, k = state.labels, state.num_components
    counts = torch.bincount(labels, minlength=k).to(DTYPE)
    scatter = _scatter(y, labels, state.means)
    dof = (prior.df + counts - prior.dim - 1)[:, None, None]
    covs = (prior.scale + scatter) / dof + prior.regularization
    residuals = _residual_sums(y, labels, prior.mean_loc, k)
    means = _mean_conditional(prior, covs, counts, residuals)[0]
    return replace(state, means=means, covariances=covs)


def fit_dp_mixture(
    y: Tensor,
    prior: NormalInverseWishartPrior,
    num_sweeps: int = 50,
    alpha: float = 1.0,
    m: int = 10,
    reward_weighted: bool = False,
    generator: torch.Generator | None = None,
    state: DPMixtureState | None = None,
    init: str = "single",
    update_prior: bool = True,
    exact_covariance: bool = True,
    reuse_auxiliary: bool = False,
    sampler: str = "neal8",
) -> DPMixtureState:
    """Run ``num_sweeps`` Gibbs sweeps and return the last state.

    Args:
        y: ``[N, D]`` data, N ≥ 1, finite.
        prior: base distribution H (e.g. :meth:`NormalInverseWishartPrior.from_exploration`).
        state: where the chain starts; overrides ``init``.
        init: ``"single"`` -- Algorithm 1's start, one component with the data's mean and
            covariance; ``"sequential"`` -- labels from one pass of the Chinese restaurant
            process adding the points one at a time (:func:`sequential_labels`). Single-site
            Gibbs merges far more easily than it splits: from one component, a point opens a
            new cluster only if (α/m)·N(y_i; aux) beats (n − 1)·N(y_i; all data), which for
            clusters spread over a low-dimensional subspace of a 10-D space essentially never
            happens. Use ``"sequential"`` to fit a fresh, large data set; DIPOLE's own
            clusterings are small (n0 points, then ≤ K·M warm-started ones).
        update_prior: redraw H's hyperparameters after every sweep (Algorithm 1's "update
            priors"); ``False`` keeps H fixed at ``prior`` (or at ``state.prior``).
        exact_covariance: Metropolis-Hastings correction of the Σ step for the
            regularisation (:func:`resample_parameters`); ``False`` restores the heuristic
            "conjugate draw + R".
        reuse_auxiliary: Favaro & Teh's re-used auxiliary draws instead of Algorithm 8's
            fresh ones (:func:`neal8_sweep`); CPU only.
        sampler: ``"neal8"`` -- Algorithm 8 (:func:`neal8_sweep`), the paper's sampler;
            ``"slice"`` -- the slice sampler, every label drawn at once
            (:func:`dipole_torch.slice_sampler.slice_sweep`; exact too, for large N and
            GPUs; no reward weighting, ``m`` unused).
    """
    check_matrix_shape(y, (-1, prior.dim), "y")
    check_finite(y, "y")
    if y.shape[0] < 1:
        raise ValueError("y must contain at least one point")
    _check_concentration(alpha, m)
    if num_sweeps < 1:
        raise ValueError(f"num_sweeps must be >= 1, got {num_sweeps}")
    if sampler not in ("neal8", "slice"):
        raise ValueError(f"sampler must be 'neal8' or 'slice', got {sampler!r}")
    if sampler == "slice" and (reward_weighted or reuse_auxiliary):
        raise ValueError(
            "sampler='slice' samples the unweighted DP mixture with its own draws: "
            "reward_weighted and reuse_auxiliary must be False"
        )
    y = y.to(DTYPE)
    if state is None:
        if init == "single":
            state = DPMixtureState.single_component(y, prior)
        elif init == "sequential":
            labels = sequential_labels(y, prior, alpha, generator)
            state = DPMixtureState.from_labels(y, labels, prior)
        else:
            raise ValueError(f"init must be 'single' or 'sequential', got {init!r}")
    elif state.labels.shape != (y.shape[0],):
        raise ValueError(
            f"state.labels must have shape [{y.shape[0]}], got {list(state.labels.shape)}"
        )
    if sampler == "slice":
        from dipole_torch.slice_sampler import SliceChain, slice_sweep

        chain = SliceChain.from_state(state)
        for _ in range(num_sweeps):
            chain = slice_sweep(
                y,
                chain,
                alpha,
                generator,
                initial_prior=prior,
                update_prior=update_prior,
                exact_covariance=exact_covariance,
            )
        return chain.state()
    for _ in range(num_sweeps):
        state = neal8_sweep(
            y,
            state,
            alpha,
            int(m),
            reward_weighted,
            generator,
            initial_prior=prior,
            update_prior=update_prior,
            exact_covariance=exact_covariance,
            reuse_auxiliary=reuse_auxiliary,
        )
    return state


def sequential_labels(
    y: Tensor, prior: NormalInverseWishartPrior, alpha: float, generator: torch.Generator | None
) -> Tensor:
    """Initial labels from one sequential Chinese-restaurant pass (an initialisation only;
    the Gibbs sweeps that follow are exact).

    Points are added one at a time, in an order drawn from ``generator``; point i joins
    cluster c with probability ∝ n_c N(y_i; ȳ_c, (1 + 1/n_c) E_H[Σ]) (the predictive density
    with Σ fixed at its prior mean and a flat prior on the cluster mean) or opens a new one
    ∝ α N(y_i; μ0, Σ0 + E_H[Σ]), the marginal likelihood under H with Σ fixed at its prior mean.

    Returns:
        ``[N]`` labels in ``[0, K)``.
    """
    y = y.to(DTYPE)
    n, d = y.shape
    cov = prior.expected_covariance + prior.regularization
    chol = torch.linalg.cholesky(cov)
    new_log_lik = _gaussian_log_prob(y, prior.mean_loc, prior.mean_covariance + cov)  # [N]
    uniforms = _uniforms(n, generator, y.device).tolist()
    log_alpha = math.log(alpha)
    where = generator.device if generator is not None else y.device
    order = torch.randperm(n, generator=generator, device=where).tolist()
    # The per-point work in numpy, in coordinates whitened by chol (z = L⁻¹ (y − ȳ), centred
    # first so that large offsets cancel): log N(y; ȳ_c, s C) = −½ (‖z − z̄_c‖² / s
    # + D log s + log|2π C|) with s = 1 + 1/n_c.
    z = torch.linalg.solve_triangular(chol, (y - _mean(y)).T, upper=False).T.cpu().numpy()
    const = -0.5 * d * _LOG_2PI - float(chol.diagonal().log().sum())
    new_log_lik = new_log_lik.cpu().numpy()
    sums = np.zeros((n, d))
    counts = np.zeros(n)
    labels = np.empty(n, dtype=np.int64)
    logits = np.empty(n + 1)
    k = 0
    for i in order:
        if k > 0:
            inflation = 1.0 + 1.0 / counts[:k]
            distance = np.square(z[i] - sums[:k] / counts[:k, None]).sum(1)
            existing = const - 0.5 * (distance / inflation + d * np.log(inflation))
            np.add(np.log(counts[:k]), existing, out=logits[:k])
        logits[k] = log_alpha + new_log_lik[i]
        c = draw_categorical_numpy(logits[: k + 1], uniforms[i])
        k = max(k, c + 1)
        labels[i] = c
        sums[c] += z[i]
        counts[c] += 1
    return torch.as_tensor(labels, device=y.device)


class DPMixture:
    """Convenience wrapper: a DP Gaussian mixture with fixed hyperparameters.

    H stays at ``prior`` by default (``update_prior=False``): the chain samples the DP mixture
    posterior under that base distribution. ``update_prior=True`` redraws H's hyperparameters
    after every sweep, as DIPOLE does (:func:`fit_dp_mixture`'s default). ``sampler="slice"``
    samples it with the slice sampler (every label at once) instead of Algorithm 8.

    Example:
        >>> g = torch.Generator().manual_seed(2)
        >>> y = torch.randn(100, 2, generator=g, dtype=torch.float64)
        >>> y[:50] -= 4
        >>> y[50:] += 4
        >>> prior = NormalInverseWishartPrior(  # means spread like the data, E[Σ] = 2 I
        ...     mean_loc=y.mean(0), mean_covariance=torch.cov(y.T), df=8.0,
        ...     scale=10.0 * torch.eye(2, dtype=torch.float64),
        ...     regularization=1e-3 * torch.eye(2, dtype=torch.float64))
        >>> state = DPMixture(prior).fit(y, num_sweeps=20, generator=g, init="sequential")
        >>> state.counts[state.counts >= 10].tolist()  # (tiny clusters may hold tail points)
        [50, 50]
    """

    def __init__(
        self,
        prior: NormalInverseWishartPrior,
        alpha: float = 1.0,
        m: int = 10,
        reward_weighted: bool = False,
        update_prior: bool = False,
        exact_covariance: bool = True,
        sampler: str = "neal8",
    ):
        self.prior = prior
        self.alpha = alpha
        self.m = m
        self.reward_weighted = reward_weighted
        self.update_prior = update_prior
        self.exact_covariance = exact_covariance
        self.sampler = sampler

    def fit(
        self,
        y: Tensor,
        num_sweeps: int = 50,
        generator: torch.Generator | None = None,
        state: DPMixtureState | None = None,
        init: str = "single",
    ) -> DPMixtureState:
        return fit_dp_mixture(
            y,
            self.prior,
            num_sweeps,
            self.alpha,
            self.m,
            self.reward_weighted,
            generator,
            state,
            init,
            update_prior=self.update_prior,
            exact_covariance=self.exact_covariance,
            sampler=self.sampler,
        )


# --------------------------------------------------------------------------- helpers
def _check_concentration(alpha: float, m: int) -> None:
    if not alpha > 0:
        raise ValueError(f"alpha must be positive, got {alpha}")
    if int(m) != m or m < 1:
        raise ValueError(f"m must be a positive integer, got {m}")


def _uniforms(n: int, generator: torch.Generator | None, device: torch.device) -> Tensor:
    """``[n]`` U(0, 1) draws from ``generator`` (on its own device), moved to ``device``."""
    where = generator.device if generator is not None else device
    return _to(torch.rand(n, generator=generator, dtype=DTYPE, device=where), device)


def _gaussian_log_prob(value: Tensor, means: Tensor, covariances: Tensor) -> Tensor:
    """``[...]`` log N(value; means, covariances), broadcast (no distribution object: its
    construction cost more than the maths at DIPOLE's sizes)."""
    return _log_prob_tril(value, means, torch.linalg.cholesky(covariances))


def _log_prob_tril(value: Tensor, mean: Tensor, tril: Tensor) -> Tensor:
    """``[*lead, *batch]`` log N(value; mean, L Lᵀ) from the Cholesky factors
    ``tril: [*batch, D, D]``, for ``value - mean: [*lead, *batch, D]`` (broadcast).

    The leading dims go into the columns of one triangular solve per factor, so the factors
    are never copied per point (an expanded ``[N, K, D, D]`` would take gigabytes).
    """
    # (x − 0.0 is x, bit for bit: RewardRegression's queries come centred.)
    diff = value if isinstance(mean, float) and mean == 0.0 else value - mean
    d = diff.shape[-1]
    nb = tril.dim() - 2
    if diff.dim() - 1 < nb:
        diff = diff.expand(*tril.shape[:-2], d)
    lead = diff.shape[: diff.dim() - 1 - nb]
    inner = tuple(
        b if a == 1 else a for a, b in zip(diff.shape[len(lead) : -1], tril.shape[:-2], strict=True)
    )
    tril = _expand(tril, (*inner, d, d))
    size = math.prod(lead)
    diff = _expand(diff, (*lead, *inner, d))
    rhs = diff.reshape(size, *inner, d).movedim(0, -1)
    z = torch.linalg.solve_triangular(tril, rhs, upper=False)  # [*inner, D, size]
    mahalanobis = z.square().sum(-2).movedim(-1, 0).reshape(*lead, *inner)
    log_det = tril.diagonal(dim1=-2, dim2=-1).log().sum(-1)
    return -0.5 * (mahalanobis + d * _LOG_2PI) - log_det


_LOG_2PI = math.log(2.0 * math.pi)
_AUX_CHUNK_BYTES = 2**26  # auxiliary covariances and their factors held at once (64 MB)


def _chunk_size(n: int, m: int, d: int) -> int:
    """Points whose ``[m, D, D]`` auxiliary covariances and factors fit _AUX_CHUNK_BYTES."""
    return max(1, min(n, _AUX_CHUNK_BYTES // (2 * 8 * m * d * d)))


@dataclass
class _Auxiliary:
    """The auxiliary components of a chunk of C points: ``means [C, m, D]``, ``covs``
    (symmetric up to rounding: only their lower triangles and factors are used) and
    their Cholesky factors ``tril [C, m, D, D]``, ``log_r [C, m]`` (log r_c, 0 unweighted) and
    ``score [C, m]`` = log(α/m) + log r_c + log N(y_i; μ, Σ)."""

    means: Tensor
    covs: Tensor
    tril: Tensor
    log_r: Tensor
    score: Tensor


def _pass_start(
    y: Tensor, state: DPMixtureState, log_r: Tensor
) -> tuple[list[int], list[int], np.ndarray, np.ndarray]:
    """What both numpy label passes start from: ``labels`` and ``counts`` as lists,
    ``score [N, capacity]`` with score[i, c] = log r_c + log N(y_i; μ_c, Σ_c) (columns of
    components opened in the sweep are filled only for the points still to come) and
    ``log_counts [capacity]`` (−inf for empty slots), with room for ``capacity`` components
    (:func:`_open_slot` grows it)."""
    n, k = y.shape[0], state.num_components
    labels = state.labels.tolist()
    counts = [0] * k  # (counted in Python: a bincount and its read cost more at these sizes)
    for label in labels:
        counts[label] += 1
    capacity = max(2 * k, 8)
    score = np.full((n, capacity), -math.inf)
    starting = _gaussian_log_prob(y[:, None, :], state.means, state.covariances) + log_r
    score[:, :k] = starting.numpy()
    log_counts = np.full(capacity, -math.inf)
    with np.errstate(divide="ignore"):  # an empty component: log 0 = −inf, as intended
        log_counts[:k] = np.log(np.asarray(counts, dtype=float))
    return labels, counts, score, log_counts


def _label_pass_numpy(
    y: Tensor,
    state: DPMixtureState,
    log_r: Tensor,
    auxiliary,
    uniforms: Tensor,
    log_aux_prior: float,
    chunk: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Step 1 of :func:`neal8_sweep` on CPU: the per-point work in numpy and Python scalars
    (a handful of numpy calls a point; torch's per-op overhead was ~15× that).

    Args:
        y: ``[N, D]`` data (CPU, float64).
        state: the sweep's starting state (labels ``[N]``, K components).
        log_r: ``[K]`` log r_c of the starting components (zeros unweighted).
        auxiliary: ``(start, stop) -> _Auxiliary`` fresh auxiliary draws for those points.
        uniforms: ``[N]`` the label draws' uniforms.
        log_aux_prior: log(α/m).
        chunk: points per auxiliary chunk.

    Returns:
        ``[N]`` labels in ``[0, k)``, the k slots' ``[k, D]`` means, ``[k, D, D]``
        covariances and ``[k]`` counts (empty slots included).
    """
    n, k = y.shape[0], state.num_components
    labels, counts, score, log_counts = _pass_start(y, state, log_r)
    logits = np.empty(0)  # reused buffer for one point's K + m logits
    u = uniforms.tolist()
    opened: dict[int, tuple[Tensor, Tensor, Tensor, float]] = {}  # slot -> μ, Σ, L, log r
    for start in range(0, n, chunk):
        stop = min(n, start + chunk)
        aux = auxiliary(start, stop)
        aux_score = aux.score.numpy()
        m = aux_score.shape[1]
        if logits.shape[0] < score.shape[1] + m:
            logits = np.empty(score.shape[1] + m)
        live = [slot for slot in opened if counts[slot] > 0]
        if live:  # components opened in earlier chunks: their columns for this chunk
            mean = torch.stack([opened[slot][0] for slot in live])
            tril = torch.stack([opened[slot][2] for slot in live])
            lr = torch.tensor([opened[slot][3] for slot in live], dtype=DTYPE)
            column = _log_prob_tril(y[start:stop, None, :], mean, tril) + lr
            score[start:stop, live] = column.numpy()
        for i in range(start, stop):
            c = labels[i]
            counts[c] -= 1
            singleton = counts[c] == 0
            log_counts[c] = math.log(counts[c]) if counts[c] else -math.inf
            row = score[i]
            np.add(log_counts[:k], row[:k], out=logits[:k])
            logits[k : k + m] = aux_score[i - start]
            if singleton:  # Algorithm 8: a singleton's parameters fill the first aux slot
                logits[k] = log_aux_prior + row[c]
            choice = draw_categorical_numpy(logits[: k + m], u[i])
            if choice < k:
                new = choice
            elif singleton and choice == k:
                new = c  # kept its own parameters
            else:
                j = choice - k
                new = c if singleton else _free_slot(counts, k)
                if new == k:
                    k += 1
                    score, log_counts, logits = _open_slot(counts, score, log_counts, logits, m)
                r = i - start
                mean, cov, tril = aux.means[r, j], _symmetric(aux.covs[r, j]), aux.tril[r, j]
                lr = float(aux.log_r[r, j])
                opened[new] = (mean, cov, tril, lr)
                if i + 1 < stop:
                    score[i + 1 : stop, new] = (
                        _log_prob_tril(y[i + 1 : stop], mean, tril) + lr
                    ).numpy()
            labels[i] = new
            counts[new] += 1
            log_counts[new] = math.log(counts[new])
    means, covs = _slot_parameters(state, opened, k)
    counts_t = torch.tensor(counts, dtype=DTYPE)
    return torch.tensor(labels, dtype=torch.long), means, covs, counts_t


def _label_pass_reuse(
    y: Tensor,
    state: DPMixtureState,
    log_r: Tensor,
    fresh,
    uniforms: Tensor,
    slot_uniforms: Tensor,
    log_aux_prior: float,
    m: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Step 1 of :func:`neal8_sweep` with re-used auxiliary components (Favaro & Teh 2013).

    One set of m draws from H serves the whole sweep. At point i: if i was alone in its
    component, that component's parameters replace the auxiliary slot chosen by
    ``slot_uniforms[i]``; i then joins a component ∝ r_c n_{-i,c} N(y_i; θ_c) or a slot j
    ∝ r_j (α/m) N(y_i; φ_j); a slot taken becomes a component and is refilled from H. Same
    arguments and returns as :func:`_label_pass_numpy`, but ``fresh(count) -> _Auxiliary``
    gives ``[count]`` draws with ``score [N, count]`` at every point.
    """
    n, k = y.shape[0], state.num_components
    labels, counts, score, log_counts = _pass_start(y, state, log_r)
    logits = np.empty(score.shape[1] + m)
    u, slot_u = uniforms.tolist(), slot_uniforms.tolist()
    aux = fresh(m)
    slots = [(aux.means[j], aux.covs[j], aux.tril[j], float(aux.log_r[j])) for j in range(m)]
    aux_score = aux.score.numpy().copy()  # [N, m], rows > i kept current
    opened: dict[int, tuple[Tensor, Tensor, Tensor, float]] = {}

    def parameters(slot: int) -> tuple[Tensor, Tensor, Tensor, float]:
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
            aux_score[i:, own] = log_aux_prior + score[i:, c]
        np.add(log_counts[:k], score[i, :k], out=logits[:k])
        logits[k : k + m] = aux_score[i]
        choice = draw_categorical_numpy(logits[: k + m], u[i])
        if choice < k:
            new = choice
        else:
            j = choice - k
            if j == own:
                new = c  # re-formed with its own parameters
            else:
                new = c if singleton else _free_slot(counts, k)
                if new == k:
                    k += 1
                    score, log_counts, logits = _open_slot(counts, score, log_counts, logits, m)
                mean, cov, tril, lr = opened[new] = slots[j]
                if i + 1 < n:
                    score[i + 1 :, new] = (_log_prob_tril(y[i + 1 :], mean, tril) + lr).numpy()
            # The slot taken is refilled from H; its scores are needed at later points only.
            refill = fresh(1)
            slots[j] = (refill.means[0], refill.covs[0], refill.tril[0], float(refill.log_r[0]))
            aux_score[i + 1 :, j] = refill.score[i + 1 :, 0].numpy()
        labels[i] = new
        counts[new] += 1
        log_counts[new] = math.log(counts[new])
    means, covs = _slot_parameters(state, opened, k)
    return (
        torch.tensor(labels, dtype=torch.long),
        means,
        covs,
        torch.tensor(counts, dtype=DTYPE),
    )


def _label_pass_sync_free(
    y: Tensor,
    state: DPMixtureState,
    log_r: Tensor,
    auxiliary,
    uniforms: Tensor,
    log_aux_prior: float,
    chunk: int,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """Step 1 of :func:`neal8_sweep` with tensor ops only: the host never waits for the
    device inside a chunk (one sync a chunk, to grow the slot capacity).

    Same arguments, draws and returns as :func:`_label_pass_numpy`. Every branch of the
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
    tril = torch.linalg.cholesky(covs)
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
        score = _log_prob_tril(y_chunk[:, None, :], means, tril) + slot_log_r  # [C, capacity]
        for i in range(start, stop):
            _sync_free_step(
                i, i - start, y_chunk, labels, counts, score, means, covs, tril, slot_log_r,
                aux, uniforms, log_aux_prior,
            )  # fmt: skip
    k = int(counts.nonzero().max()) + 1
    return labels, means[:k], covs[:k], counts[:k]


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
    aux: _Auxiliary,
    uniforms: Tensor,
    log_aux_prior: float,
) -> None:
    """Relabel point i (row r of its chunk) in place, branch-free; see
    :func:`_label_pass_sync_free`. ``labels [N]``, ``counts [S]``, ``score [C, S]`` and the
    slots' ``means [S, D]``, ``covs``/``tril [S, D, D]``, ``slot_log_r [S]`` are updated."""
    capacity = counts.shape[0]
    c = labels[i : i + 1]  # [1]: a view, not a host int
    counts.index_add_(0, c, counts.new_full((1,), -1.0))
    singleton = counts.index_select(0, c) == 0
    row = score[r]
    own = log_aux_prior + row.index_select(0, c)
    aux_row = aux.score[r]
    first = torch.where(singleton, own, aux_row[:1])
    log_counts = torch.where(counts > 0, counts.log(), -math.inf)
    logits = torch.cat((log_counts + row, first, aux_row[1:]))
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
    cov_j = _symmetric(aux.covs[r].index_select(0, j))
    covs.index_copy_(0, new, torch.where(wide, cov_j, covs.index_select(0, new)))
    tril.index_copy_(0, new, torch.where(wide, tril_j, tril.index_select(0, new)))
    lr_j = aux.log_r[r].index_select(0, j)
    slot_log_r.index_copy_(0, new, torch.where(opens, lr_j, slot_log_r.index_select(0, new)))
    column = _log_prob_tril(y_chunk[:, None, :], mean_j, tril_j) + lr_j  # [C, 1]
    score.index_copy_(1, new, torch.where(opens, column, score.index_select(1, new)))


def _slot_parameters(
    state: DPMixtureState, opened: dict[int, tuple[Tensor, Tensor, Tensor, float]], k: int
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


def _symmetric(matrix: Tensor) -> Tensor:
    return 0.5 * (matrix + matrix.transpose(-1, -2))


def _free_slot(counts: list[int], k: int) -> int:
    """The first empty slot below k, else k."""
    try:
        return counts.index(0, 0, k)
    except ValueError:
        return k


def _grow(score: np.ndarray, capacity: int) -> np.ndarray:
    grown = np.full((score.shape[0], capacity), -math.inf)
    grown[:, : score.shape[1]] = score
    return grown


def _open_slot(
    counts: list[int], score: np.ndarray, log_counts: np.ndarray, logits: np.ndarray, m: int
) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Component ``len(counts)`` opens, empty, in both numpy label passes; the slot arrays
    (``score [N, capacity]``, ``log_counts [capacity]``, the ``capacity + m`` logits buffer)
    double when it does not fit. Returns them (new arrays when they grew)."""
    counts.append(0)
    capacity = score.shape[1]
    if len(counts) > capacity:
        score = _grow(score, 2 * capacity)
        log_counts = np.concatenate((log_counts, np.full(capacity, -math.inf)))
        logits = np.empty(2 * capacity + m)
    return score, log_counts, logits


def _mean(y: Tensor) -> Tensor:
    """``[D]`` mean of ``y: [N, D]``, refined by the mean residual (for large offsets)."""
    mean = y.mean(0)
    return mean + (y - mean).mean(0)


def _residual_sums(y: Tensor, labels: Tensor, centres: Tensor, k: int) -> Tensor:
    """``[K, D]`` Σ_{i in c} (y_i − centre_c) for ``centres: [K, D]`` or one ``[D]``.

    Sums of residuals rather than of raw data: Σ y at an offset of 1e6 carries no digits of
    a spread of 1e-2 once the offset is subtracted again.
    """
    centred = y - (centres[labels] if centres.dim() == 2 else centres)
    return torch.zeros(k, y.shape[-1], dtype=y.dtype, device=y.device).index_add_(
        0, labels, centred
    )


def _scatter(y: Tensor, labels: Tensor, means: Tensor) -> Tensor:
    """``[K, D, D]`` Σ_{i in c} (y_i − μ_c)(y_i − μ_c)ᵀ for ``means: [K, D]``, batched.

    Computed from centred residuals: Σ y yᵀ − 2 (Σ y) μᵀ + n μ μᵀ from raw sums cancels
    catastrophically at large offsets (1e12 against a scatter of 1e-4 at θ ≈ 1e6) and can
    leave the inverse-Wishart scale indefinite.
    """
    d = y.shape[-1]
    centred = y - means[labels]
    scatter = torch.zeros(means.shape[0], d, d, dtype=y.dtype, device=y.device)
    scatter.index_add_(0, labels, centred[:, :, None] * centred[:, None, :])
    return 0.5 * (scatter + scatter.transpose(-1, -2))


def _covariance_step(
    prior: NormalInverseWishartPrior,
    covs: Tensor,
    counts: Tensor,
    scatter: Tensor,
    generator: torch.Generator | None,
    exact: bool = True,
) -> tuple[Tensor, Tensor]:
    """The Metropolis-Hastings step on Σ of :func:`resample_parameters`, batched over K.

    Args:
        covs: ``[K, D, D]`` current Σ + R.
        counts: ``[K]`` points per component.
        scatter: ``[K, D, D]`` Σ_i (y_i − μ)(y_i − μ)ᵀ about the current means.
        exact: ``False`` accepts every proposal (no correction).

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
        torch.cat((counts, counts)),  # (cat: a tenth of repeat's overhead)
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


def _mean_conditional(
    prior: NormalInverseWishartPrior, covs: Tensor, counts: Tensor, residuals: Tensor
) -> tuple[Tensor, Tensor]:
    """μ | Σ, y ~ N(P⁻¹ (Σ0⁻¹ μ0 + Σ⁻¹ Σ y), P⁻¹), P = Σ0⁻¹ + n Σ⁻¹, batched over K.

    The location is computed as μ0 + P⁻¹ Σ⁻¹ Σ_i (y_i − μ0), the same quantity without the
    cancellation of μ0-sized terms at large offsets.

    Args:
        covs: ``[K, D, D]`` component covariances Σ (regularisation included).
        counts: ``[K]`` points per component.
        residuals: ``[K, D]`` Σ_{i in c} (y_i − μ0) (:func:`_residual_sums` about μ0).

    Returns:
        ``[K, D]`` the location and ``[K, D, D]`` the Cholesky factor of the precision P.
    """
    prior_precision = prior._mean_precision()  # Σ0⁻¹, factorised once per prior
    precision_k = torch.cholesky_inverse(torch.linalg.cholesky(covs))
    precision = prior_precision + counts[:, None, None] * precision_k
    precision = 0.5 * (precision + precision.transpose(-1, -2))
    rhs = (precision_k @ residuals[:, :, None]).squeeze(-1)
    chol = torch.linalg.cholesky(precision)
    loc = prior.mean_loc + torch.cholesky_solve(rhs[:, :, None], chol).squeeze(-1)
    return loc, chol


def _draw_normal_precision(
    loc: Tensor, precision_tril: Tensor, generator: torch.Generator | None
) -> Tensor:
    """``[..., D]`` draws of N(loc, P⁻¹) with P = L Lᵀ: loc + L⁻ᵀ z, z ~ N(0, I) drawn from
    ``generator`` (on its device). Cov(L⁻ᵀ z) = L⁻ᵀ L⁻¹ = P⁻¹."""
    where = generator.device if generator is not None else loc.device
    z = torch.randn(loc.shape, generator=generator, dtype=loc.dtype, device=where)
    upper = precision_tril.transpose(-1, -2)
    step = torch.linalg.solve_triangular(upper, _to(z, loc.device).unsqueeze(-1), upper=True)
    return loc + step.squeeze(-1)

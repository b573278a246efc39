"""The generative model behind the DP mixture, written as a Pyro model.

Neal's Algorithm 8 (``dipole_torch.DPSampler`` with ``reward_weighted=False`` and
``update_prior=False``) is a Gibbs sampler for the posterior of this model:

* labels c_1..c_N from the Chinese restaurant process with concentration α: c_1 = 0 and
  c_i | c_<i takes an existing table k with probability n_k / (i − 1 + α) or opens table K
  with probability α / (i − 1 + α) (labels in order of first appearance);
* for each of the K tables, independently, μ_k ~ N(μ0, Σ0) and Σ_k ~ IW(ν0, Ψ0) (the
  non-linked base distribution H, ``NormalInverseWishartPrior``);
* y_i ~ N(μ_{c_i}, Σ_{c_i} + R), R the prior's regularisation.

``dp_mixture_model`` is that model for ``pyro.poutine`` (trace, condition, replay);
``dp_log_joint`` is its log joint density written out in closed form (the CRP's
exchangeable partition probability and H's densities), which is what the sampler's
conditionals are derived from. ``tests/test_pyro_model.py`` checks that the two agree, that
the sampler's μ and Σ conditionals are ratios of this joint, and runs a Geweke
joint-distribution test of the whole sweep against forward draws of this model.

DIPOLE's reward weighting (eq. 6) multiplies the label probabilities by r_c: that chain has
no generative model of this form, so only the unweighted sampler is checked against it.
"""

from __future__ import annotations

import math
import warnings
from contextlib import nullcontext

import pyro
import pyro.poutine as poutine
import torch
from pyro.distributions import Categorical, MultivariateNormal, TorchDistribution
from torch import Tensor
from torch.distributions import Wishart, constraints

from dipole_torch.dp.state import DPMixtureState
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.sampling import draw
from dipole_torch.validation import (
    check_count,
    check_finite,
    check_matrix_shape,
    check_positive_finite,
    check_real_tensor,
)

__all__ = [
    "InverseWishart",
    "canonical_state",
    "dp_log_joint",
    "dp_mixture_model",
    "state_from_trace",
    "state_sites",
]


class InverseWishart(TorchDistribution):
    """Σ ~ IW(ν, Ψ) over D × D symmetric positive-definite matrices.

    Density (Ψ the scale, E[Σ] = Ψ / (ν − D − 1) for ν > D + 1)::

        log p(Σ) = ν/2 log|Ψ| − νD/2 log 2 − log Γ_D(ν/2) − (ν + D + 1)/2 log|Σ|
                   − ½ tr(Ψ Σ⁻¹)

    Draws are Σ = W⁻¹ with ``W ~ torch.distributions.Wishart(df=ν, precision_matrix=Ψ)``,
    the convention of ``NormalInverseWishartPrior``.

    Args:
        df: scalar or ``[...]`` degrees of freedom ν > D − 1.
        scale: ``[..., D, D]`` symmetric positive-definite scale Ψ.
        validate_args: as for ``torch.distributions``.
    """

    arg_constraints = {"df": constraints.positive, "scale": constraints.positive_definite}
    support = constraints.positive_definite
    has_rsample = False

    def __init__(self, df: Tensor | float, scale: Tensor, validate_args: bool | None = None):
        if scale.dim() < 2 or scale.shape[-1] != scale.shape[-2]:
            raise ValueError(f"scale must have shape [..., D, D], got {list(scale.shape)}")
        d = scale.shape[-1]
        df = torch.as_tensor(df, dtype=scale.dtype, device=scale.device)
        if not bool((df > d - 1).all()):
            raise ValueError(f"df must exceed D - 1 = {d - 1}, got {df.tolist()}")
        batch = torch.broadcast_shapes(df.shape, scale.shape[:-2])
        self.df = df.expand(batch)
        self.scale = scale.expand(*batch, d, d)
        super().__init__(torch.Size(batch), torch.Size((d, d)), validate_args=validate_args)

    def expand(self, batch_shape, _instance=None) -> InverseWishart:
        new = self._get_checked_instance(InverseWishart, _instance)
        batch_shape = torch.Size(batch_shape)
        new.df = self.df.expand(batch_shape)
        new.scale = self.scale.expand(*batch_shape, *self.event_shape)
        super(InverseWishart, new).__init__(batch_shape, self.event_shape, validate_args=False)
        new._validate_args = self._validate_args
        return new

    @property
    def mean(self) -> Tensor:
        """``[..., D, D]`` Ψ / (ν − D − 1) (infinite for ν ≤ D + 1)."""
        d = self.event_shape[-1]
        return self.scale / (self.df - d - 1)[..., None, None]

    def log_prob(self, value: Tensor) -> Tensor:
        """``[...]`` log density at ``value: [..., D, D]``."""
        if self._validate_args:
            self._validate_sample(value)
        d = self.event_shape[-1]
        df = self.df
        chol = torch.linalg.cholesky(value)
        log_det_value = 2.0 * chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        log_det_scale = torch.linalg.slogdet(self.scale)[1]
        trace = torch.cholesky_solve(self.scale.expand_as(value), chol)
        trace = trace.diagonal(dim1=-2, dim2=-1).sum(-1)
        return (
            0.5 * df * log_det_scale
            - 0.5 * df * d * math.log(2.0)
            - torch.mvlgamma(0.5 * df, p=d)
            - 0.5 * (df + d + 1) * log_det_value
            - 0.5 * trace
        )

    def sample(self, sample_shape=(), generator: torch.Generator | None = None) -> Tensor:
        """``[*sample_shape, *batch_shape, D, D]`` draws, reproducible from ``generator``."""
        wishart = Wishart(df=self.df, precision_matrix=self.scale, validate_args=False)
        with warnings.catch_warnings():
            # torch's Wishart.rsample tests its draws with an inverted flag, warns "Singular
            # sample detected" for valid ones and redraws them once: still exact, just noisy.
            warnings.filterwarnings("ignore", "Singular sample detected")
            precision = draw(wishart, torch.Size(sample_shape), generator)
        covariance = torch.cholesky_inverse(torch.linalg.cholesky(precision))
        return 0.5 * (covariance + covariance.transpose(-1, -2))


def dp_mixture_model(
    prior: NormalInverseWishartPrior,
    alpha: float,
    num_points: int | None = None,
    data: Tensor | None = None,
    num_draws: int | None = None,
) -> tuple[Tensor, Tensor, Tensor, Tensor]:
    """The DP Gaussian mixture as a Pyro model (CRP labels, non-linked H, data in a plate).

    N points sit at no more than N tables, so the model keeps N component slots: slot k < K
    (K the number of tables opened) holds table k's parameters, and the slots beyond are
    masked out of the density (``poutine.mask``). The log joint is therefore exact, not a
    truncation, and the model vectorises over independent draws (``num_draws``).

    Sites (B = ``num_draws``; without it the leading ``[B]`` and ``[B, 1]`` are absent):

    * ``label_0`` … ``label_{N-1}``: ``[B, 1]`` CRP labels, ``Categorical`` with probabilities
      n_k / (i + α) for the K open tables and α / (i + α) for table K;
    * in the plate ``components`` (N slots): ``means`` ``[B, N, D]`` ~ N(μ0, Σ0) and
      ``covariances`` ``[B, N, D, D]`` ~ IW(ν0, Ψ0) (Σ_k without the regularisation);
    * in the plate ``data`` (N points): ``y`` ``[B, N, D]`` ~ N(μ_{c_i}, Σ_{c_i} + R).

    Condition on ``state_sites`` to score a sampler state; run it unconditioned for
    forward draws (``state_from_trace`` turns a trace back into a state).

    Args:
        prior: the base distribution H (held fixed).
        alpha: DP concentration, a finite α > 0.
        num_points: N, a positive integer; taken from ``data`` when that is given.
        data: ``[N, D]`` finite observed y, or ``None``. With ``num_draws`` it must be
            ``[B, N, D]``, its leading dimension B = ``num_draws`` (one data set per draw;
            ``data.expand(B, N, D)`` gives every draw the same one).
        num_draws: run B independent copies of the model in a plate ``draws`` (dim −2);
            a positive integer or ``None``.

    Raises:
        ValueError: ``alpha``, ``num_points`` or ``num_draws`` out of range, ``data`` of
            the wrong shape or holding NaN or inf.
        TypeError: ``prior`` not a ``NormalInverseWishartPrior``, ``data`` not a
            floating-point tensor.

    Returns:
        labels ``[B, N]``, slot means ``[B, N, D]``, slot covariances ``[B, N, D, D]``
        (Σ + R, as the sampler stores them) and y ``[B, N, D]``.

    Example:
        >>> import pyro.poutine as poutine
        >>> from dipole_torch import NormalInverseWishartPrior
        >>> prior = NormalInverseWishartPrior.from_exploration(
        ...     torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64))
        >>> pyro.set_rng_seed(0)
        >>> labels, means, covariances, y = dp_mixture_model(prior, 1.0, 5, num_draws=1000)
        >>> labels.shape, y.shape
        (torch.Size([1000, 5]), torch.Size([1000, 5, 2]))
        >>> forward = poutine.trace(dp_mixture_model).get_trace(prior, 1.0, 5)
        >>> state, y = state_from_trace(forward, prior), forward.nodes["y"]["value"]
        >>> scored = poutine.trace(poutine.condition(dp_mixture_model, state_sites(state, y)))
        >>> log_joint = scored.get_trace(prior, 1.0, data=y).log_prob_sum()
        >>> bool(torch.isclose(log_joint, dp_log_joint(y, state, 1.0)))
        True
    """
    if not isinstance(prior, NormalInverseWishartPrior):
        raise TypeError(f"prior must be a NormalInverseWishartPrior, got {type(prior).__name__}")
    check_positive_finite(alpha, "alpha")
    check_count(num_draws, "num_draws", optional=True)
    num_draws = None if num_draws is None else int(num_draws)
    d = prior.dim
    if data is not None:
        check_real_tensor(data, "data")
        if num_draws is None:
            if data.dim() == 3:
                raise ValueError(
                    f"data of shape {list(data.shape)} has a leading batch dimension of "
                    f"{data.shape[0]}: pass num_draws={data.shape[0]} (one draw per data set); "
                    f"without num_draws data must have shape [N, {d}]"
                )
            check_matrix_shape(data, (-1, d), "data")
        elif data.dim() != 3 or data.shape[0] != num_draws or data.shape[-1] != d:
            raise ValueError(
                f"data must have shape [{num_draws}, N, {d}] with num_draws={num_draws} (its "
                f"leading batch dimension equal to num_draws, one data set per draw; "
                f"data.expand({num_draws}, N, {d}) gives every draw the same one), got "
                f"{list(data.shape)}"
            )
        check_finite(data, "data")
        num_points = data.shape[-2] if num_points is None else num_points
    check_count(num_points, "num_points")
    n = int(num_points)
    if data is not None and n != data.shape[-2]:
        raise ValueError(f"num_points={num_points} but data has {data.shape[-2]} rows")
    dtype, device = prior.mean_loc.dtype, prior.mean_loc.device
    draws = pyro.plate("draws", num_draws, dim=-2) if num_draws is not None else nullcontext()
    with draws:
        slots = torch.arange(n, device=device)
        counts = torch.zeros(n, dtype=dtype, device=device)
        tables = torch.zeros((), dtype=torch.long, device=device)
        labels = []
        for i in range(n):
            # [..., N] CRP weights: n_k for the open tables, α for the next, 0 beyond.
            weights = torch.where(slots < tables[..., None], counts, 0.0)
            weights = torch.where(slots == tables[..., None], alpha, weights)
            label = pyro.sample(f"label_{i}", Categorical(probs=weights / (i + alpha)))
            counts = counts + (slots == label[..., None]).to(dtype)
            tables = torch.maximum(tables, label + 1)
            labels.append(label)
        labels = torch.cat([label.reshape(-1, 1) for label in labels], -1)  # [B or 1, N]
        if num_draws is None:
            labels = labels[0]
        with pyro.plate("components", n, dim=-1), poutine.mask(mask=slots < tables[..., None]):
            means = pyro.sample("means", MultivariateNormal(prior.mean_loc, prior.mean_covariance))
            sigmas = pyro.sample("covariances", InverseWishart(prior.df, prior.scale))
        covariances = sigmas + prior.regularization
        point_means = torch.take_along_dim(means, labels[..., None], dim=-2)
        point_covariances = torch.take_along_dim(covariances, labels[..., None, None], dim=-3)
        with pyro.plate("data", n, dim=-1):
            y = pyro.sample("y", MultivariateNormal(point_means, point_covariances), obs=data)
    return labels, means, covariances, y


def canonical_state(state: DPMixtureState) -> DPMixtureState:
    """The same state with components renumbered in order of first appearance in the labels
    (the CRP's labelling; the partition and parameters are unchanged)."""
    labels = state.labels
    first = torch.full((state.num_components,), labels.numel(), dtype=torch.long)
    positions = torch.arange(labels.numel(), dtype=torch.long)
    first = first.scatter_reduce(0, labels.cpu(), positions, "amin")
    order = torch.argsort(first).to(labels.device)  # order[new] = old
    rank = torch.empty_like(order)
    rank[order] = torch.arange(order.numel(), device=labels.device)
    return DPMixtureState(
        labels=rank[labels],
        means=state.means[order],
        covariances=state.covariances[order],
        prior=state.prior,
    )


def state_sites(state: DPMixtureState, y: Tensor | None = None) -> dict[str, Tensor]:
    """Site values of ``dp_mixture_model`` for a sampler state (to ``poutine.condition``).

    Components are renumbered in order of first appearance (``canonical_state``); the
    N − K unused slots get H's mean and expected covariance (masked out of the density).

    Args:
        state: labels ``[N]``, means ``[K, D]``, covariances ``[K, D, D]`` (Σ + R).
        y: ``[N, D]`` data, included as site ``y`` when given.
    """
    state = canonical_state(state)
    prior = state.prior
    n, k, d = state.labels.numel(), state.num_components, prior.dim
    means = prior.mean_loc.expand(n, d).clone()
    sigmas = prior.expected_covariance.expand(n, d, d).clone()
    means[:k] = state.means
    sigmas[:k] = state.covariances - prior.regularization
    sites = {f"label_{i}": label for i, label in enumerate(state.labels)}
    sites["means"] = means
    sites["covariances"] = sigmas
    if y is not None:
        sites["y"] = y
    return sites


def state_from_trace(trace: pyro.poutine.Trace, prior: NormalInverseWishartPrior) -> DPMixtureState:
    """The sampler state of an unbatched ``dp_mixture_model`` trace (the K used slots,
    covariances with R added)."""
    num_points = sum(1 for name in trace.nodes if name.startswith("label_"))
    labels = torch.stack([trace.nodes[f"label_{i}"]["value"] for i in range(num_points)])
    if labels.dim() != 1:
        raise ValueError("state_from_trace takes a trace without num_draws")
    k = int(labels.max()) + 1
    return DPMixtureState(
        labels=labels.long(),
        means=trace.nodes["means"]["value"][:k],
        covariances=trace.nodes["covariances"]["value"][:k] + prior.regularization,
        prior=prior,
    )


def dp_log_joint(y: Tensor, state: DPMixtureState, alpha: float) -> Tensor:
    """log p(labels, μ, Σ, y) of the model, in closed form, for a sampler state.

    log α^K Γ(α) / Γ(α + N) Π_k Γ(n_k)  (the CRP's exchangeable partition probability)
    + Σ_k [log N(μ_k; μ0, Σ0) + log IW(Σ_k; ν0, Ψ0)] + Σ_i log N(y_i; μ_{c_i}, Σ_{c_i} + R).

    Args:
        y: ``[N, D]`` finite data, one row per label of ``state``.
        state: labels ``[N]`` in ``[0, K)``, each component holding one or more, means
            ``[K, D]``, covariances ``[K, D, D]`` (Σ + R), and H.
        alpha: DP concentration, a finite α > 0.

    Returns:
        A scalar tensor. −inf where some Σ_k = covariances_k − R is not positive definite.

    Raises:
        ValueError: ``alpha`` out of range, ``y`` not ``[N, D]`` or holding NaN or inf,
            ``state`` that fails ``DPMixtureState.check`` (a component without a point, a
            label out of range, covariances not positive definite).
        TypeError: ``y`` not a tensor, ``state`` not a ``DPMixtureState``.
    """
    if not isinstance(state, DPMixtureState):
        raise TypeError(f"state must be a DPMixtureState, got {type(state).__name__}")
    check_positive_finite(alpha, "alpha")
    prior = state.prior
    check_matrix_shape(y, (state.labels.numel(), prior.dim), "y")
    check_finite(y, "y")
    state.check(prior.dim)  # the model has no empty component
    counts = state.counts.to(prior.mean_loc.dtype)
    k, n = counts.numel(), counts.sum()
    alpha_t = torch.as_tensor(alpha, dtype=counts.dtype, device=counts.device)
    partition = (
        k * alpha_t.log()
        + torch.lgamma(alpha_t)
        - torch.lgamma(alpha_t + n)
        + torch.lgamma(counts).sum()
    )
    # Arguments checked here once; the distributions skip their own (Cholesky) validation.
    mean_distribution = MultivariateNormal(
        prior.mean_loc, prior.mean_covariance, validate_args=False
    )
    mean_term = mean_distribution.log_prob(state.means).sum()
    sigmas = state.covariances - prior.regularization
    if bool((torch.linalg.cholesky_ex(sigmas)[1] != 0).any()):
        return torch.full((), -math.inf, dtype=counts.dtype, device=counts.device)
    base = InverseWishart(prior.df, prior.scale.to(sigmas), validate_args=False)
    covariance_term = base.log_prob(sigmas).sum()
    # K factorisations rather than N: every point under every component, then its own.
    components = MultivariateNormal(state.means, state.covariances, validate_args=False)
    log_lik = components.log_prob(y.to(counts.dtype).unsqueeze(-2))  # [N, K]
    likelihood = log_lik.gather(-1, state.labels.unsqueeze(-1)).sum()
    return partition + mean_term + covariance_term + likelihood

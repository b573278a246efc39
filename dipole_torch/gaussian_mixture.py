"""A finite Gaussian mixture as a ``torch.distributions.Distribution`` (and a Pyro distribution),
with Gaussian mixture regression (GMR, Ghahramani & Jordan 1994)."""

from __future__ import annotations

import numbers
from collections.abc import Sequence

import torch
from pyro.distributions import TorchDistribution
from torch import Tensor
from torch.distributions import (
    Categorical,
    MixtureSameFamily,
    MultivariateNormal,
    constraints,
    register_kl,
)
from torch.distributions.kl import _kl_multivariatenormal_multivariatenormal

from dipole_torch.sampling import broadcast_shape, draw
from dipole_torch.validation import check_positive_definite


class GaussianMixture(TorchDistribution):
    """Mixture of K full-covariance Gaussians over a D-dimensional event.

    A ``torch.distributions.Distribution`` (through Pyro's ``TorchDistribution``, so it also
    goes straight into ``pyro.sample``): any leading batch shape ``[...]``, K components, event
    shape ``[D]``. The parameters' batch shapes broadcast, and their dtype is the promotion of
    the three (float32 parameters give a float32 mixture).

    Args:
        weights: ``[..., K]`` non-negative mixing weights (normalised here).
        means: ``[..., K, D]`` component means.
        covariances: ``[..., K, D, D]`` symmetric positive-definite component covariances.
        validate_args: check the parameters at construction (shapes, finiteness, positive
            definiteness, with an error naming the argument) and values in ``log_prob``.
            ``None`` follows ``torch.distributions.Distribution``'s default (on, unless
            switched off by ``Distribution.set_default_validate_args`` or
            ``pyro.enable_validation(False)``).

    There is no ``rsample``: a draw picks its component discretely, so no reparameterised
    sample carries gradients to the weights (``MixtureSameFamily`` has none either).

    Example:
        >>> gm = GaussianMixture(torch.tensor([0.5, 0.5]),
        ...                      torch.tensor([[0.0, 0.0], [3.0, 1.0]]),
        ...                      torch.eye(2).expand(2, 2, 2))
        >>> gm.condition([0], torch.tensor([3.0])).mean  # E[y | x=3]: mostly component 2
        tensor([0.9890])
        >>> gm.batch_shape, gm.event_shape, gm.dtype
        (torch.Size([]), torch.Size([2]), torch.float32)
    """

    arg_constraints = {
        "weights": constraints.simplex,
        "means": constraints.independent(constraints.real, 2),
        "covariances": constraints.independent(constraints.positive_definite, 1),
    }
    support = constraints.real_vector
    has_rsample = False

    def __init__(
        self,
        weights: Tensor,
        means: Tensor,
        covariances: Tensor,
        validate_args: bool | None = None,
    ):
        check = self._validate_args if validate_args is None else validate_args
        if check:
            _check_parameters(weights, means, covariances)
        dtype = _mixture_dtype(weights, means, covariances)
        # Broadcast the three batch shapes, as torch.distributions does for its parameters.
        k, d = means.shape[-2:]
        batch = broadcast_shape(weights.shape[:-1], means.shape[:-2], covariances.shape[:-3])
        weights = weights.to(dtype).expand(*batch, k)
        self.weights = weights / weights.sum(-1, keepdim=True)
        self.means = means.to(dtype).expand(*batch, k, d)
        self.covariances = covariances.to(dtype).expand(*batch, k, d, d)
        self._scale_tril: Tensor | None = None
        # The parameters were checked above with messages naming them; the base class would
        # repeat the Cholesky factorisations.
        super().__init__(torch.Size(batch), torch.Size((d,)), validate_args=False)
        if validate_args is None:  # read torch's default at use, as the base class does
            del self._validate_args
        else:
            self._validate_args = validate_args

    def expand(self, batch_shape, _instance=None) -> GaussianMixture:
        """The same mixture broadcast to ``batch_shape`` (views, no copies)."""
        new = self._get_checked_instance(GaussianMixture, _instance)
        batch_shape = torch.Size(batch_shape)
        k, d = self.num_components, self.event_shape[0]
        new.weights = self.weights.expand(*batch_shape, k)
        new.means = self.means.expand(*batch_shape, k, d)
        new.covariances = self.covariances.expand(*batch_shape, k, d, d)
        new._scale_tril = (
            None if self._scale_tril is None else self._scale_tril.expand(*batch_shape, k, d, d)
        )
        super(GaussianMixture, new).__init__(batch_shape, self.event_shape, validate_args=False)
        new._validate_args = self._validate_args
        return new

    @classmethod
    def infer_shapes(cls, weights, means, covariances) -> tuple[torch.Size, torch.Size]:
        """Batch and event shapes from the parameters' shapes (Pyro's shape inference)."""
        batch = broadcast_shape(weights[:-1], means[:-2], covariances[:-3])
        return torch.Size(batch), torch.Size(means[-1:])

    # ----------------------------------------------------------------- shapes and moments
    @property
    def num_components(self) -> int:
        return int(self.weights.shape[-1])

    @property
    def scale_tril(self) -> Tensor:
        """``[..., K, D, D]`` Cholesky factors of the component covariances."""
        if self._scale_tril is None:
            self._scale_tril = torch.linalg.cholesky(self.covariances)
        return self._scale_tril

    @property
    def mean(self) -> Tensor:
        """``[..., D]`` mixture mean Σ_k w_k μ_k."""
        return (self.weights.unsqueeze(-1) * self.means).sum(-2)

    @property
    def covariance_matrix(self) -> Tensor:
        """``[..., D, D]`` mixture covariance (law of total covariance)."""
        centred = self.means - self.mean.unsqueeze(-2)
        spread = self.covariances + centred.unsqueeze(-1) * centred.unsqueeze(-2)
        return (self.weights[..., None, None] * spread).sum(-3)

    @property
    def variance(self) -> Tensor:
        """``[..., D]`` marginal variances, the diagonal of ``covariance_matrix``."""
        return self.covariance_matrix.diagonal(dim1=-2, dim2=-1)

    @property
    def device(self) -> torch.device:
        return self.means.device

    @property
    def dtype(self) -> torch.dtype:
        return self.means.dtype

    # ----------------------------------------------------------------- densities and draws
    def component_log_prob(self, value: Tensor) -> Tensor:
        """``[..., K]`` log N(value; μ_k, Σ_k) for ``value: [..., D]``."""
        self._check_value(value)
        normal = MultivariateNormal(self.means, scale_tril=self.scale_tril, validate_args=False)
        return normal.log_prob(value.unsqueeze(-2))

    def log_prob(self, value: Tensor) -> Tensor:
        """``[...]`` mixture log density at ``value: [..., D]`` (``[...]`` broadcasts with the
        batch shape)."""
        self._check_value(value)
        if self._validate_args:
            self._validate_sample(value)
        return torch.logsumexp(self.weights.log() + self.component_log_prob(value), dim=-1)

    def responsibilities(self, value: Tensor) -> Tensor:
        """``[..., K]`` posterior component probabilities p(k | value)."""
        return torch.softmax(self.weights.log() + self.component_log_prob(value), dim=-1)

    def sample(
        self,
        sample_shape: torch.Size | tuple[int, ...] | int = (),
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """``[*sample_shape, *batch_shape, D]`` draws, reproducible from ``generator``
        (``None``: the global RNG, as ``torch.distributions`` and ``pyro.sample`` use it)."""
        if isinstance(sample_shape, int):
            sample_shape = (sample_shape,)
        return draw(self.to_distribution(), torch.Size(sample_shape), generator)

    def to_distribution(self) -> MixtureSameFamily:
        """The same mixture as a ``torch.distributions.MixtureSameFamily``."""
        return MixtureSameFamily(
            Categorical(probs=self.weights, validate_args=False),
            MultivariateNormal(self.means, scale_tril=self.scale_tril, validate_args=False),
            validate_args=False,
        )

    def component(self, index: int) -> MultivariateNormal:
        """Component ``index`` as a ``MultivariateNormal`` with this mixture's batch shape."""
        if not -self.num_components <= index < self.num_components:
            raise IndexError(f"index must be in [0, {self.num_components}), got {index}")
        return MultivariateNormal(
            self.means[..., index, :],
            scale_tril=self.scale_tril[..., index, :, :],
            validate_args=False,
        )

    # ----------------------------------------------------------------- marginals and GMR
    def marginal(self, dims: Sequence[int]) -> GaussianMixture:
        """The mixture over ``dims`` alone (same weights, sub-blocks of means and covariances)."""
        index = self._index(dims)
        return self._derived(
            self.weights, self.means[..., index], self.covariances[..., index[:, None], index]
        )

    def condition(self, dims: Sequence[int], values: Tensor) -> GaussianMixture:
        """Gaussian mixture regression: the mixture over the other dims given ``y[dims] = values``.

        For each component, μ_b|a = μ_b + Σ_ba Σ_aa⁻¹ (x_a − μ_a) and
        Σ_b|a = Σ_bb − Σ_ba Σ_aa⁻¹ Σ_ab; the weights become the responsibilities
        h_k ∝ w_k N(x_a; μ_a, Σ_aa).

        Args:
            dims: the observed dimensions (distinct, in ``[0, D)``, not all of them).
            values: ``[..., len(dims)]`` observed values; their batch shape broadcasts with
                the mixture's.

        Returns:
            A ``GaussianMixture`` over the remaining dims (in increasing order), with batch
            shape ``broadcast(batch_shape, values.shape[:-1])``. E.g. ``condition(θ_dims,
            θ).mean`` is E[r | θ].
        """
        a = self._index(dims)
        if a.numel() == self.event_shape[0]:
            raise ValueError("condition: dims covers every dimension; nothing is left to predict")
        if values.shape[-1:] != (a.numel(),):
            raise ValueError(
                f"condition: values must end in {a.numel()} (= len(dims)), got {list(values.shape)}"
            )
        if not torch.isfinite(values).all():
            raise ValueError("condition: values contain non-finite entries")
        b = torch.tensor(
            [i for i in range(self.event_shape[0]) if i not in set(a.tolist())], device=self.device
        )
        values = values.to(self.dtype)
        mu_a, mu_b = self.means[..., a], self.means[..., b]
        cov_aa = self.covariances[..., a[:, None], a]
        cov_ba = self.covariances[..., b[:, None], a]
        cov_bb = self.covariances[..., b[:, None], b]
        chol_aa = torch.linalg.cholesky(cov_aa)
        # gain_k = Σ_ba Σ_aa⁻¹, via a Cholesky solve rather than an explicit inverse.
        gain = torch.cholesky_solve(cov_ba.transpose(-1, -2), chol_aa).transpose(-1, -2)
        diff = values.unsqueeze(-2) - mu_a  # [..., K, |a|]
        cond_means = mu_b + (gain @ diff.unsqueeze(-1)).squeeze(-1)
        cond_covs = cov_bb - gain @ cov_ba.transpose(-1, -2)
        cond_covs = 0.5 * (cond_covs + cond_covs.transpose(-1, -2))
        log_lik = MultivariateNormal(mu_a, scale_tril=chol_aa, validate_args=False).log_prob(
            diff + mu_a
        )
        log_w = torch.log_softmax(self.weights.log() + log_lik, dim=-1)
        batch = broadcast_shape(self.batch_shape, values.shape[:-1])
        k, nb = self.num_components, b.numel()
        return self._derived(
            log_w.exp().expand(*batch, k),
            cond_means.expand(*batch, k, nb),
            cond_covs.expand(*batch, k, nb, nb),
        )

    # ----------------------------------------------------------------- persistence
    def state_dict(self) -> dict[str, Tensor]:
        return {
            "weights": self.weights.clone(),
            "means": self.means.clone(),
            "covariances": self.covariances.clone(),
        }

    def load_state_dict(self, state: dict[str, Tensor]) -> None:
        """Replace this mixture's parameters (validated) by those of ``state``."""
        _check_parameters(state["weights"], state["means"], state["covariances"])
        validate = self._validate_args
        self.__init__(state["weights"], state["means"], state["covariances"], validate_args=False)
        self._validate_args = validate

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor]) -> GaussianMixture:
        return cls(state["weights"], state["means"], state["covariances"])

    def to(self, *args, **kwargs) -> GaussianMixture:
        """A copy with parameters moved/cast as ``Tensor.to(*args, **kwargs)`` (a Cholesky
        factor already computed is cast with them, not recomputed in the new dtype)."""
        mixture = self._derived(
            self.weights.to(*args, **kwargs),
            self.means.to(*args, **kwargs),
            self.covariances.to(*args, **kwargs),
        )
        if self._scale_tril is not None:
            mixture._scale_tril = self._scale_tril.to(*args, **kwargs)
        return mixture

    def __repr__(self) -> str:
        return (
            f"GaussianMixture(batch_shape={list(self.batch_shape)}, "
            f"num_components={self.num_components}, event_shape={list(self.event_shape)})"
        )

    # ----------------------------------------------------------------- helpers
    def _derived(self, weights: Tensor, means: Tensor, covariances: Tensor) -> GaussianMixture:
        """A mixture computed from this one: parameters unchecked, value checks as this one's."""
        mixture = GaussianMixture(weights, means, covariances, validate_args=False)
        mixture._validate_args = self._validate_args
        return mixture

    def _index(self, dims: Sequence[int]) -> Tensor:
        d = self.event_shape[0]
        dims = list(dims)
        for i in dims:  # (a float or a bool would be cast to a dimension silently)
            integer = isinstance(i, numbers.Integral) or (
                isinstance(i, Tensor) and not i.is_floating_point() and i.dtype != torch.bool
            )
            if not integer or isinstance(i, bool):
                raise ValueError(f"dims must be integers, got {dims}")
        index = torch.as_tensor(dims, dtype=torch.long, device=self.device).reshape(-1)
        if index.numel() == 0:
            raise ValueError("dims must name at least one dimension")
        if (index < 0).any() or (index >= d).any() or index.unique().numel() != index.numel():
            raise ValueError(f"dims must be distinct integers in [0, {d}), got {list(dims)}")
        return index

    def _check_value(self, value: Tensor) -> None:
        if value.shape[-1:] != self.event_shape:
            raise ValueError(
                f"value must end in the event dim {self.event_shape[0]}, got {list(value.shape)}"
            )


def _mixture_dtype(weights: Tensor, means: Tensor, covariances: Tensor) -> torch.dtype:
    """The mixture's dtype: the three parameters' promotion, as torch.distributions'
    ``broadcast_all`` gives (integer parameters take torch's default dtype)."""
    dtype = torch.promote_types(torch.promote_types(weights.dtype, means.dtype), covariances.dtype)
    if not dtype.is_floating_point:
        dtype = torch.get_default_dtype()
    if dtype in (torch.float16, torch.bfloat16):
        # Refused here, not left to log_prob: torch's Cholesky has no kernel for them.
        raise TypeError(
            f"GaussianMixture needs float32 or float64 parameters (log_prob and sample "
            f"factorise the covariances, and torch's Cholesky has no {dtype} kernel); "
            f"got {dtype}: cast them with .float()"
        )
    return dtype


def _check_parameters(weights: Tensor, means: Tensor, covariances: Tensor) -> None:
    for name, tensor in (("weights", weights), ("means", means), ("covariances", covariances)):
        if not isinstance(tensor, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
    _mixture_dtype(weights, means, covariances)
    for name, tensor in (("weights", weights), ("means", means), ("covariances", covariances)):
        if not torch.isfinite(tensor).all():
            raise ValueError(f"{name} contains non-finite values")
    if weights.dim() < 1 or weights.shape[-1] < 1:
        raise ValueError(f"weights must have shape [..., K] with K >= 1, got {list(weights.shape)}")
    k = weights.shape[-1]
    if means.dim() < 2 or means.shape[-2] != k:
        raise ValueError(f"means must have shape [..., K={k}, D], got {list(means.shape)}")
    d = means.shape[-1]
    if covariances.dim() < 3 or covariances.shape[-3:] != (k, d, d):
        raise ValueError(
            f"covariances must have shape [..., {k}, {d}, {d}], got {list(covariances.shape)}"
        )
    try:
        broadcast_shape(weights.shape[:-1], means.shape[:-2], covariances.shape[:-3])
    except ValueError as error:
        raise ValueError(
            "the batch shapes of weights, means and covariances do not broadcast: "
            f"{list(weights.shape[:-1])}, {list(means.shape[:-2])}, {list(covariances.shape[:-3])}"
        ) from error
    if (weights < 0).any() or (weights.sum(-1) <= 0).any():
        raise ValueError("weights must be non-negative with a positive sum")
    check_positive_definite(covariances, "covariances")


# --------------------------------------------------------------------------- KL divergence
def _as_normal(mixture: GaussianMixture, role: str) -> MultivariateNormal:
    if mixture.num_components != 1:
        raise NotImplementedError(
            f"kl_divergence: {role} is a GaussianMixture with {mixture.num_components} "
            "components; the KL divergence between Gaussian mixtures has no closed form "
            "(only single-component mixtures have one). Estimate it by Monte Carlo: "
            "x = p.sample((n,)); (p.log_prob(x) - q.log_prob(x)).mean(0)"
        )
    return mixture.component(0)


@register_kl(GaussianMixture, GaussianMixture)
def _kl_mixture_mixture(p: GaussianMixture, q: GaussianMixture) -> Tensor:
    """Exact KL(p ‖ q) for single-component mixtures, ``[broadcast batch shape]``."""
    return _kl_multivariatenormal_multivariatenormal(_as_normal(p, "p"), _as_normal(q, "q"))


@register_kl(GaussianMixture, MultivariateNormal)
def _kl_mixture_normal(p: GaussianMixture, q: MultivariateNormal) -> Tensor:
    """Exact KL(p ‖ q) for a single-component mixture p."""
    return _kl_multivariatenormal_multivariatenormal(_as_normal(p, "p"), q)


@register_kl(MultivariateNormal, GaussianMixture)
def _kl_normal_mixture(p: MultivariateNormal, q: GaussianMixture) -> Tensor:
    """Exact KL(p ‖ q) for a single-component mixture q."""
    return _kl_multivariatenormal_multivariatenormal(p, _as_normal(q, "q"))

"""A finite Gaussian mixture with torch.distributions batch semantics and Gaussian mixture
regression (GMR, Ghahramani & Jordan 1994)."""

from __future__ import annotations

from collections.abc import Sequence

import torch
from torch import Tensor
from torch.distributions import Categorical, MixtureSameFamily, MultivariateNormal

from dipole_torch.sampling import draw
from dipole_torch.validation import check_positive_definite


class GaussianMixture:
    """Mixture of K full-covariance Gaussians over a D-dimensional event.

    Shapes follow ``torch.distributions``: any leading batch shape ``[...]``, K components,
    event shape ``[D]``.

    Args:
        weights: ``[..., K]`` non-negative mixing weights (normalised here).
        means: ``[..., K, D]`` component means.
        covariances: ``[..., K, D, D]`` symmetric positive-definite component covariances.
        validate_args: check shapes, finiteness and positive definiteness (default ``True``).

    Example:
        >>> gm = GaussianMixture(torch.tensor([0.5, 0.5]),
        ...                      torch.tensor([[0.0, 0.0], [3.0, 1.0]]),
        ...                      torch.eye(2).expand(2, 2, 2))
        >>> gm.condition([0], torch.tensor([3.0])).mean  # E[y | x=3]: mostly component 2
        tensor([0.9890])
    """

    def __init__(
        self, weights: Tensor, means: Tensor, covariances: Tensor, validate_args: bool = True
    ):
        if validate_args:
            _check_parameters(weights, means, covariances)
        # Broadcast the three batch shapes, as torch.distributions does for its parameters.
        k, d = means.shape[-2:]
        batch = torch.broadcast_shapes(weights.shape[:-1], means.shape[:-2], covariances.shape[:-3])
        weights = weights.expand(*batch, k)
        means = means.expand(*batch, k, d)
        covariances = covariances.expand(*batch, k, d, d)
        self.weights = weights / weights.sum(-1, keepdim=True)
        self.means = means
        self.covariances = covariances
        self._scale_tril: Tensor | None = None

    # ----------------------------------------------------------------- shapes and moments
    @property
    def batch_shape(self) -> torch.Size:
        return self.weights.shape[:-1]

    @property
    def event_shape(self) -> torch.Size:
        return self.means.shape[-1:]

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
        """``[...]`` mixture log density at ``value: [..., D]``."""
        return torch.logsumexp(self.weights.log() + self.component_log_prob(value), dim=-1)

    def responsibilities(self, value: Tensor) -> Tensor:
        """``[..., K]`` posterior component probabilities p(k | value)."""
        return torch.softmax(self.weights.log() + self.component_log_prob(value), dim=-1)

    def sample(
        self,
        sample_shape: torch.Size | tuple[int, ...] = (),
        generator: torch.Generator | None = None,
    ) -> Tensor:
        """``[*sample_shape, *batch_shape, D]`` draws, reproducible from ``generator``."""
        if isinstance(sample_shape, int):
            sample_shape = (sample_shape,)
        return draw(self.to_distribution(), sample_shape, generator)

    def to_distribution(self) -> MixtureSameFamily:
        """The same mixture as a ``torch.distributions.MixtureSameFamily``."""
        return MixtureSameFamily(
            Categorical(probs=self.weights, validate_args=False),
            MultivariateNormal(self.means, scale_tril=self.scale_tril, validate_args=False),
            validate_args=False,
        )

    # ----------------------------------------------------------------- marginals and GMR
    def marginal(self, dims: Sequence[int]) -> GaussianMixture:
        """The mixture over ``dims`` alone (same weights, sub-blocks of means and covariances)."""
        index = self._index(dims)
        return GaussianMixture(
            self.weights,
            self.means[..., index],
            self.covariances[..., index[:, None], index],
            validate_args=False,
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
        batch = torch.broadcast_shapes(self.batch_shape, values.shape[:-1])
        k, nb = self.num_components, b.numel()
        return GaussianMixture(
            log_w.exp().expand(*batch, k),
            cond_means.expand(*batch, k, nb),
            cond_covs.expand(*batch, k, nb, nb),
            validate_args=False,
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
        self.__init__(state["weights"], state["means"], state["covariances"], validate_args=False)

    @classmethod
    def from_state_dict(cls, state: dict[str, Tensor]) -> GaussianMixture:
        return cls(state["weights"], state["means"], state["covariances"])

    def to(self, *args, **kwargs) -> GaussianMixture:
        """A copy with parameters moved/cast as ``Tensor.to(*args, **kwargs)``."""
        return GaussianMixture(
            self.weights.to(*args, **kwargs),
            self.means.to(*args, **kwargs),
            self.covariances.to(*args, **kwargs),
            validate_args=False,
        )

    def __repr__(self) -> str:
        return (
            f"GaussianMixture(batch_shape={list(self.batch_shape)}, "
            f"num_components={self.num_components}, event_shape={list(self.event_shape)})"
        )

    # ----------------------------------------------------------------- helpers
    def _index(self, dims: Sequence[int]) -> Tensor:
        d = self.event_shape[0]
        index = torch.as_tensor(list(dims), dtype=torch.long, device=self.device).reshape(-1)
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


def _check_parameters(weights: Tensor, means: Tensor, covariances: Tensor) -> None:
    for name, tensor in (("weights", weights), ("means", means), ("covariances", covariances)):
        if not isinstance(tensor, Tensor):
            raise TypeError(f"{name} must be a torch.Tensor, got {type(tensor).__name__}")
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
        torch.broadcast_shapes(weights.shape[:-1], means.shape[:-2], covariances.shape[:-3])
    except RuntimeError as error:
        raise ValueError(
            "the batch shapes of weights, means and covariances do not broadcast: "
            f"{list(weights.shape[:-1])}, {list(means.shape[:-2])}, {list(covariances.shape[:-3])}"
        ) from error
    if (weights < 0).any() or (weights.sum(-1) <= 0).any():
        raise ValueError("weights must be non-negative with a positive sum")
    check_positive_definite(covariances, "covariances")

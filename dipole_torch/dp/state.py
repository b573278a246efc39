"""A state of the DP mixture's Gibbs chain, and the ways a chain starts."""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import numpy as np
import torch
from torch import Tensor

from dipole_torch.dp.conditionals import (
    data_mean,
    posterior_point_estimate,
    residual_sums,
    singular_by_rounding,
)
from dipole_torch.gaussian import DTYPE, LOG_2PI, gaussian_log_prob
from dipole_torch.prior import NormalInverseWishartPrior
from dipole_torch.sampling import draw_categorical_numpy, uniforms
from dipole_torch.validation import check_finite, check_positive_definite

if TYPE_CHECKING:  # a Pyro distribution: Pyro is imported when a mixture is built
    from dipole_torch.gaussian_mixture import GaussianMixture

__all__ = ["DPMixtureState", "sequential_labels"]


@dataclass
class DPMixtureState:
    """One state of the Gibbs chain.

    Attributes:
        labels: ``[N]`` component index of every point, contiguous in ``[0, K)``.
        means: ``[K, D]`` component means.
        covariances: ``[K, D, D]`` component covariances (regularisation included).
        prior: the base distribution H, redrawn after every sweep when the sampler updates it.
    """

    labels: Tensor
    means: Tensor
    covariances: Tensor
    prior: NormalInverseWishartPrior

    @property
    def num_components(self) -> int:
        return int(self.means.shape[0])

    def check(
        self,
        dim: int,
        num_points: int | None = None,
        name: str = "state",
        allow_empty: bool = False,
    ) -> None:
        """Raise ``ValueError`` naming what does not fit a chain over ``dim``-dimensional
        points (``num_points`` of them, when given): tensors of the wrong kind or shape,
        labels outside ``[0, K)`` or a component without a point (unless ``allow_empty``:
        a chain's start may hold one, which the sampler gives no point and drops), means
        that are not finite, covariances that are not symmetric positive definite."""
        labels, means, covs = self.labels, self.means, self.covariances
        for key, value in (("labels", labels), ("means", means), ("covariances", covs)):
            if not isinstance(value, Tensor):
                raise ValueError(f"{name}.{key} must be a tensor, got {type(value).__name__}")
        if labels.dim() != 1 or labels.is_floating_point() or labels.dtype == torch.bool:
            raise ValueError(
                f"{name}.labels must be [N] integers, got {labels.dtype} {list(labels.shape)}"
            )
        if num_points is not None and labels.shape[0] != num_points:
            shape = list(labels.shape)
            raise ValueError(f"{name}.labels must have shape [{num_points}], got {shape}")
        if means.dim() != 2 or means.shape[1] != dim:
            raise ValueError(f"{name}.means must have shape [K, {dim}], got {list(means.shape)}")
        k = means.shape[0]
        if tuple(covs.shape) != (k, dim, dim):
            raise ValueError(
                f"{name}.covariances must have shape [{k}, {dim}, {dim}], got {list(covs.shape)}"
            )
        if labels.numel() and (int(labels.min()) < 0 or int(labels.max()) >= k):
            raise ValueError(f"{name}.labels must lie in [0, {k}) (the components of means)")
        empty = labels.numel() and bool((torch.bincount(labels, minlength=k) == 0).any())
        if empty and not allow_empty:
            raise ValueError(f"{name}: every component of means must hold a point of labels")
        check_finite(means, f"{name}.means")
        check_positive_definite(covs.to(DTYPE), f"{name}.covariances")

    @property
    def counts(self) -> Tensor:
        """``[K]`` number of points per component."""
        return torch.bincount(self.labels, minlength=self.num_components)

    def mixture(self) -> GaussianMixture:
        """The fitted mixture, with weights proportional to the component sizes."""
        from dipole_torch.gaussian_mixture import GaussianMixture

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
        mean = data_mean(y)
        centred = y - mean  # the covariance from centred data: exact at any offset
        cov = centred.T @ centred / max(n - 1, 1) + prior.regularization
        # Fewer points than dimensions (or collinear ones) leave the data's covariance singular:
        # unless the regularisation holds it up, a factorisation then either fails or
        # succeeds on rounding, its pivots a few ulps of the diagonal, and the chain goes to
        # NaN. H's expected covariance starts the chain instead.
        tril, info = torch.linalg.cholesky_ex(cov)
        if info != 0 or n < 2 or bool(singular_by_rounding(tril, cov)):
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
        """A state with the given partition (any integer numbering) and each component at its
        conditional posterior mean (``posterior_point_estimate``),
        e.g. to warm-start a chain."""
        n = y.shape[0] if isinstance(y, Tensor) and y.dim() == 2 else None
        integers = isinstance(labels, Tensor) and not labels.is_floating_point()
        if not integers or labels.dtype == torch.bool:
            raise ValueError(f"labels must be an integer tensor, got {labels!r:.60}")
        if n is None or n < 1 or tuple(labels.shape) != (n,):
            raise ValueError(
                f"labels must have shape [N] for y [N, D], N >= 1; got labels "
                f"{list(labels.shape)} for y {list(getattr(y, 'shape', []))}"
            )
        y = y.to(DTYPE)
        labels = torch.unique(labels, return_inverse=True)[1].to(y.device)
        k = int(labels.max()) + 1
        centre = data_mean(y)
        counts = torch.bincount(labels, minlength=k).to(DTYPE)
        means = centre + residual_sums(y, labels, centre, k) / counts[:, None]
        covs = (prior.expected_covariance + prior.regularization).expand(k, -1, -1).clone()
        return posterior_point_estimate(y, cls(labels, means, covs, prior))

    @classmethod
    def sequential(
        cls,
        y: Tensor,
        prior: NormalInverseWishartPrior,
        alpha: float,
        generator: torch.Generator | None,
    ) -> DPMixtureState:
        """A state from one sequential Chinese-restaurant pass (``sequential_labels``)."""
        return cls.from_labels(y, sequential_labels(y, prior, alpha, generator), prior)

    def state_dict(self) -> dict:
        return {
            "labels": self.labels,
            "means": self.means,
            "covariances": self.covariances,
            "prior": self.prior.state_dict(),
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> DPMixtureState:
        missing = sorted({"labels", "means", "covariances", "prior"} - set(state))
        if missing:
            raise ValueError(f"a DP mixture state's dict lacks {missing}")
        return cls(
            labels=state["labels"],
            means=state["means"],
            covariances=state["covariances"],
            prior=NormalInverseWishartPrior.from_state_dict(state["prior"]),
        )


def sequential_labels(
    y: Tensor, prior: NormalInverseWishartPrior, alpha: float, generator: torch.Generator | None
) -> Tensor:
    """Initial labels from one sequential Chinese-restaurant pass (an initialisation only;
    the Gibbs sweeps that follow are exact).

    Points are added one at a time, in an order drawn from ``generator``; point i joins
    cluster c with probability ∝ n_c N(y_i; ȳ_c, (1 + 1/n_c) E_H[Σ]) (the predictive density
    with Σ fixed at its prior mean and a flat prior on the cluster mean) or opens a new one
    ∝ α N(y_i; μ0, Σ0 + E_H[Σ]), the marginal likelihood under H with Σ fixed at its prior mean.

    Single-site Gibbs merges far more easily than it splits: from one component, a point
    opens a new cluster only if (α/m)·N(y_i; aux) beats (n − 1)·N(y_i; all data), which for
    clusters spread over a low-dimensional subspace of a 10-D space essentially never
    happens. Start a large, fresh data set from these labels.

    Returns:
        ``[N]`` labels in ``[0, K)``.
    """
    y = y.to(DTYPE)
    n, d = y.shape
    cov = prior.expected_covariance + prior.regularization
    chol = torch.linalg.cholesky(cov)
    new_log_lik = gaussian_log_prob(y, prior.mean_loc, prior.mean_covariance + cov)  # [N]
    draws = uniforms(n, generator, y.device).tolist()
    log_alpha = math.log(alpha)
    where = generator.device if generator is not None else y.device
    order = torch.randperm(n, generator=generator, device=where).tolist()
    # The per-point work in numpy, in coordinates whitened by chol (z = L⁻¹ (y − ȳ), centred
    # first so that large offsets cancel): log N(y; ȳ_c, s C) = −½ (‖z − z̄_c‖² / s
    # + D log s + log|2π C|) with s = 1 + 1/n_c.
    z = torch.linalg.solve_triangular(chol, (y - data_mean(y)).T, upper=False).T.cpu().numpy()
    const = -0.5 * d * LOG_2PI - float(chol.diagonal().log().sum())
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
        c = draw_categorical_numpy(logits[: k + 1], draws[i])
        k = max(k, c + 1)
        labels[i] = c
        sums[c] += z[i]
        counts[c] += 1
    return torch.as_tensor(labels, device=y.device)

"""The non-linked Normal / Inverse-Wishart base distribution H of the DP mixture."""

from __future__ import annotations

import warnings
from dataclasses import dataclass

import torch
from torch import Tensor
from torch.distributions import MultivariateNormal, Wishart

from dipole_torch.sampling import draw, draw_with_uniforms
from dipole_torch.validation import check_finite, check_matrix_shape, check_positive_definite


@dataclass
class NormalInverseWishartPrior:
    """H: μ ~ N(μ0, Σ0) and Σ ~ IW(ν0, Ψ0), *independently* (non-linked).

    The conjugate Normal-Inverse-Wishart links the spread of the means to the covariance
    (μ | Σ ~ N(μ0, Σ/κ0)). DIPOLE keeps them apart because the spread of the policies over
    parameter space has nothing to do with each policy's exploration noise; the price is a
    non-conjugate model, hence Neal's Algorithm 8.

    Attributes:
        mean_loc: ``[D]`` μ0, prior mean of the component means.
        mean_covariance: ``[D, D]`` Σ0, prior covariance of the component means.
        df: ν0 > D + 1 (so that E[Σ] = Ψ0 / (ν0 − D − 1) exists).
        scale: ``[D, D]`` Ψ0, inverse-Wishart scale.
        regularization: ``[D, D]`` positive semi-definite matrix added to every component
            covariance (drawn or estimated) to keep the mixture non-degenerate; the paper
            derives it from the initial exploration noise.

    Conventions: Σ ~ IW(ν, Ψ) is drawn as Σ = W⁻¹ with
    ``W ~ torch.distributions.Wishart(df=ν, precision_matrix=Ψ)`` (i.e. W has scale Ψ⁻¹);
    tests check E[Σ] = Ψ / (ν − D − 1).
    """

    mean_loc: Tensor
    mean_covariance: Tensor
    df: float
    scale: Tensor
    regularization: Tensor

    def __post_init__(self) -> None:
        d = self.mean_loc.shape[-1] if self.mean_loc.dim() == 1 else -1
        if not float(self.df) > d + 1:
            raise ValueError(
                f"df must exceed D + 1 = {d + 1} for a finite prior mean, got {self.df}"
            )
        check_matrix_shape(self.mean_loc, (d,), "mean_loc")
        check_finite(self.mean_loc, "mean_loc")
        check_matrix_shape(self.mean_covariance, (d, d), "mean_covariance")
        check_positive_definite(self.mean_covariance, "mean_covariance")
        check_matrix_shape(self.scale, (d, d), "scale")
        check_positive_definite(self.scale, "scale")
        check_matrix_shape(self.regularization, (d, d), "regularization")
        check_finite(self.regularization, "regularization")

    @property
    def dim(self) -> int:
        return int(self.mean_loc.shape[-1])

    @classmethod
    def from_exploration(
        cls,
        mean: Tensor,
        covariance: Tensor,
        df: float | None = None,
        regularization: float = 1e-3,
    ) -> NormalInverseWishartPrior:
        """H centred on an exploration distribution N(mean, covariance).

        μ0 = mean, Σ0 = covariance, and Ψ0 = (ν0 − D − 1)·covariance so that E[Σ] equals the
        exploration covariance. ν0 defaults to D + 3, the least integer with a finite prior
        variance, so the data quickly dominate the prior. The regularisation is
        ``regularization · diag(covariance)``.
        """
        d = mean.shape[-1]
        df = float(d + 3) if df is None else float(df)
        covariance = 0.5 * (covariance + covariance.transpose(-1, -2))
        return cls(
            mean_loc=mean.clone(),
            mean_covariance=covariance.clone(),
            df=df,
            scale=(df - d - 1) * covariance,
            regularization=regularization * torch.diag_embed(covariance.diagonal()),
        )

    @property
    def expected_covariance(self) -> Tensor:
        """``[D, D]`` E[Σ] = Ψ0 / (ν0 − D − 1)."""
        return self.scale / (self.df - self.dim - 1)

    def mean_distribution(self) -> MultivariateNormal:
        return MultivariateNormal(self.mean_loc, covariance_matrix=self.mean_covariance)

    def precision_distribution(self, df: Tensor | float, scale: Tensor) -> Wishart:
        """W ~ Wishart with W⁻¹ ~ IW(df, scale); ``scale: [..., D, D]``."""
        df = torch.as_tensor(df, dtype=scale.dtype, device=scale.device)
        return Wishart(df=df, precision_matrix=scale, validate_args=False)

    def sample_inverse_wishart(
        self,
        df: Tensor | float,
        scale: Tensor,
        generator: torch.Generator | None,
        num_uniforms: int = 0,
    ) -> Tensor | tuple[Tensor, Tensor]:
        """``[..., D, D]`` draws of IW(df, scale) (batched over ``scale``'s leading dims).

        With ``num_uniforms > 0``, also ``[num_uniforms]`` U(0, 1) draws from the same seed of
        ``generator`` (:func:`dipole_torch.sampling.draw_with_uniforms`), returned as a pair.
        """
        with warnings.catch_warnings():
            # torch's Wishart.rsample tests its draws with an inverted flag, warns "Singular
            # sample detected" for valid ones and redraws them once: still exact, just noisy.
            warnings.filterwarnings("ignore", "Singular sample detected")
            precision, uniforms = draw_with_uniforms(
                self.precision_distribution(df, scale), num_uniforms, (), generator
            )
        covariance = torch.cholesky_inverse(torch.linalg.cholesky(precision))
        covariance = 0.5 * (covariance + covariance.transpose(-1, -2))
        return (covariance, uniforms) if num_uniforms > 0 else covariance

    def sample(self, n: int, generator: torch.Generator | None = None) -> tuple[Tensor, Tensor]:
        """Draw n component parameters from H.

        Returns:
            means ``[n, D]``, covariances ``[n, D, D]`` (regularised).
        """
        means = draw(self.mean_distribution(), (n,), generator)
        scale = self.scale.expand(n, self.dim, self.dim)
        covariances = self.sample_inverse_wishart(self.df, scale, generator)
        return means, covariances + self.regularization

    def updated(
        self,
        means: Tensor,
        covariances: Tensor,
        initial: NormalInverseWishartPrior,
        generator: torch.Generator | None = None,
    ) -> NormalInverseWishartPrior:
        """H redrawn from its conditional posterior given the components (Algorithm 1's
        "update priors for the DP using posterior information").

        The hyperparameters get conjugate hyperpriors centred on ``initial`` (as in Rasmussen's
        infinite GMM) and one Gibbs step each:

        * μ0 | Σ0, {μ_k} ~ N, with hyperprior μ0 ~ N(μ0_init, Σ0_init);
        * Σ0 | μ0, {μ_k} ~ IW(ν_s + K, Ψ_s + Σ_k (μ_k − μ0)(μ_k − μ0)ᵀ), with
          ν_s = D + 3 and Ψ_s = 2 Σ0_init (so E[Σ0] = Σ0_init a priori);
        * Ψ0 | {Σ_k} ~ Wishart(ν_h + K ν0, (V⁻¹ + Σ_k Σ_k⁻¹)⁻¹), with hyperprior
          Ψ0 ~ Wishart(ν_h, V), ν_h = D + 1 and V = Ψ0_init / ν_h (so E[Ψ0] = Ψ0_init).

        The last step is what lets the exploration covariance of new components follow the
        current ones (DIPOLE's automatic exploration adaptation); being an exact Gibbs step it
        cannot run away towards ever smaller clusters.

        Args:
            means: ``[K, D]`` component means.
            covariances: ``[K, D, D]`` component covariances, regularisation excluded.
            initial: the prior the chain started from; it defines the hyperpriors.
            generator: source of the draws.
        """
        d, k = self.dim, means.shape[0]
        # μ0 | Σ0, {μ_k}
        hyper_precision = _inverse(initial.mean_covariance)
        spread_precision = _inverse(self.mean_covariance)
        precision = hyper_precision + k * spread_precision
        # loc = P⁻¹ (Σ_h⁻¹ μ0_init + Σ0⁻¹ Σ_k μ_k), written about μ0_init so that large offsets
        # of the means cancel before the solve rather than after it.
        rhs = spread_precision @ (means - initial.mean_loc).sum(0)
        chol = torch.linalg.cholesky(precision)
        loc = initial.mean_loc + torch.cholesky_solve(rhs[:, None], chol).squeeze(-1)
        mean_loc = draw(
            MultivariateNormal(loc, precision_matrix=_symmetric(precision)), (), generator
        )
        # Σ0 | μ0, {μ_k}
        centred = means - mean_loc
        scale_s = 2.0 * initial.mean_covariance + centred.T @ centred
        mean_covariance = self.sample_inverse_wishart(d + 3 + k, _symmetric(scale_s), generator)
        # Ψ0 | {Σ_k}
        hyper_df = d + 1.0
        posterior_precision = hyper_df * _inverse(initial.scale) + _inverse(covariances).sum(0)
        wishart = Wishart(
            df=torch.as_tensor(hyper_df + k * self.df, dtype=means.dtype, device=means.device),
            precision_matrix=_symmetric(posterior_precision),
            validate_args=False,
        )
        with warnings.catch_warnings():
            warnings.filterwarnings("ignore", "Singular sample detected")
            scale = draw(wishart, (), generator)
        return NormalInverseWishartPrior(
            mean_loc=mean_loc,
            mean_covariance=mean_covariance,
            df=self.df,
            scale=_symmetric(scale),
            regularization=self.regularization,
        )

    def state_dict(self) -> dict[str, Tensor | float]:
        return {
            "mean_loc": self.mean_loc,
            "mean_covariance": self.mean_covariance,
            "df": self.df,
            "scale": self.scale,
            "regularization": self.regularization,
        }

    @classmethod
    def from_state_dict(cls, state: dict) -> NormalInverseWishartPrior:
        return cls(**state)


def _symmetric(matrix: Tensor) -> Tensor:
    return 0.5 * (matrix + matrix.transpose(-1, -2))


def _inverse(matrix: Tensor) -> Tensor:
    """Inverse of symmetric positive-definite ``matrix: [..., D, D]`` via Cholesky."""
    return _symmetric(torch.cholesky_inverse(torch.linalg.cholesky(matrix)))

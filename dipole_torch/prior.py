"""The non-linked Normal / Inverse-Wishart base distribution H of the DP mixture."""

from __future__ import annotations

import math
import numbers
from dataclasses import dataclass, fields

import torch
from torch import Tensor
from torch.distributions import MultivariateNormal

from dipole_torch.gaussian import DTYPE, symmetric
from dipole_torch.memo import Memo
from dipole_torch.sampling import _to, bartlett_factor, inverse_wishart, inverse_wishart_from_factor
from dipole_torch.validation import (
    check_finite,
    check_matrix_shape,
    check_positive_definite,
    check_well_conditioned,
)


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

    The tensors are kept in float64 (``dipole_torch.gaussian.DTYPE``): a float32 or list
    field is converted when the prior is built.

    Conventions: Σ ~ IW(ν, Ψ) has Σ⁻¹ ~ Wishart(ν, Ψ⁻¹) and E[Σ] = Ψ / (ν − D − 1); it is
    drawn directly by Bartlett's decomposition (``dipole_torch.sampling.inverse_wishart``);
    tests/test_sampling.py checks the moments against ``torch.distributions.Wishart``'s.
    """

    mean_loc: Tensor
    mean_covariance: Tensor
    df: float
    scale: Tensor
    regularization: Tensor

    def __post_init__(self) -> None:
        # The DP mathematics runs in float64 (a float32 prior met float64 data deep inside
        # the sampler, with an error about index_put's dtypes).
        for name in ("mean_loc", "mean_covariance", "scale", "regularization"):
            value = getattr(self, name)
            if not isinstance(value, Tensor) or value.dtype != DTYPE:
                setattr(self, name, torch.as_tensor(value, dtype=DTYPE))
        self._check(well_conditioned=True)

    def _check(self, well_conditioned: bool) -> None:
        """Raise ``ValueError`` naming the field that is malformed (shape, finiteness,
        definiteness) or, with ``well_conditioned``, too close to singular for float64."""
        d = self.mean_loc.shape[-1] if self.mean_loc.dim() == 1 else -1
        number = isinstance(self.df, numbers.Real) and not isinstance(self.df, bool)
        if not (number or isinstance(self.df, Tensor) and self.df.numel() == 1):
            raise ValueError(f"df must be a real number, got {self.df!r}")
        if not math.isfinite(float(self.df)):
            raise ValueError(f"df must be finite, got {self.df}")
        if not float(self.df) > d + 1:
            raise ValueError(
                f"df must exceed D + 1 = {d + 1} for a finite prior mean, got {self.df}"
            )
        check_matrix_shape(self.mean_loc, (d,), "mean_loc")
        check_finite(self.mean_loc, "mean_loc")
        check_matrix_shape(self.mean_covariance, (d, d), "mean_covariance")
        check_positive_definite(self.mean_covariance, "mean_covariance")
        if well_conditioned:
            check_well_conditioned(self.mean_covariance, "mean_covariance")
        check_matrix_shape(self.scale, (d, d), "scale")
        check_positive_definite(self.scale, "scale")
        if well_conditioned:
            check_well_conditioned(self.scale, "scale")
        check_matrix_shape(self.regularization, (d, d), "regularization")
        check_finite(self.regularization, "regularization")
        # Added to every component's covariance: a negative part would eat into it.
        reg = self.regularization
        scale = float(reg.abs().max())
        symmetric = float((reg - reg.T).abs().max()) <= 1e-12 * scale
        if not symmetric or float(torch.linalg.eigvalsh(reg).min()) < -1e-12 * scale:
            raise ValueError("regularization must be symmetric positive semi-definite")

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
        exploration covariance. ν0 defaults to D + 3 (Ψ0 = 2·covariance): a weak prior, so
        the data quickly dominate it, whose mean E[Σ] is finite (that needs ν0 > D + 1; Σ's
        variance needs ν0 > D + 3, and stays infinite). The regularisation is
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

    def sample_inverse_wishart(
        self, df: Tensor | float, scale: Tensor, generator: torch.Generator | None
    ) -> Tensor:
        """``[..., D, D]`` draws of IW(df, scale) (batched over ``scale``'s leading dims), a
        direct Bartlett draw (``dipole_torch.sampling.inverse_wishart``) from ``generator``.

        Args:
            df: scalar or ``[...]`` degrees of freedom.
            scale: ``[..., D, D]`` symmetric positive-definite scales.
        """
        return inverse_wishart(df, torch.linalg.cholesky(scale), generator)

    def sample(
        self, n: int, generator: torch.Generator | None = None, symmetrize: bool = True
    ) -> tuple[Tensor, Tensor]:
        """Draw n component parameters from H (means first, then covariances).

        Ψ0 and Σ0 are factorised once for all n draws. ``symmetrize=False`` leaves the
        covariances symmetric up to rounding (see ``dipole_torch.sampling.inverse_wishart``).

        Returns:
            means ``[n, D]``, covariances ``[n, D, D]`` (regularised).
        """
        d = self.dim
        where = generator.device if generator is not None else self.mean_loc.device
        z = torch.randn(n, d, generator=generator, dtype=self.mean_loc.dtype, device=where)
        means = self.mean_loc + _to(z, self.mean_loc.device) @ self._mean_tril().T
        scale_tril = self._scale_tril().expand(n, d, d)
        covariances = inverse_wishart(self.df, scale_tril, generator, symmetrize)
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
        device = means.device
        where = generator.device if generator is not None else device
        # The update's random numbers at once: μ0's normals, then the Bartlett factors of
        # Σ0's inverse-Wishart and Ψ0's Wishart draws.
        normals = _to(torch.randn(d, 1, generator=generator, dtype=DTYPE, device=where), device)
        degrees = torch.tensor([d + 3.0 + k, d + 1.0 + k * self.df], dtype=DTYPE, device=device)
        bartlett = bartlett_factor(degrees, d, generator)  # [2, D, D]
        # μ0 | Σ0, {μ_k}
        hyper_precision = initial._mean_precision()
        spread_precision = self._mean_precision()
        # loc = P⁻¹ (Σ_h⁻¹ μ0_init + Σ0⁻¹ Σ_k μ_k), written about μ0_init so that large offsets
        # of the means cancel before the solve rather than after it.
        rhs = spread_precision @ (means - initial.mean_loc).sum(0, keepdim=True).mT
        # (Positive definite by construction, as the scales below: factorised without the
        # error check's cost.)
        chol = torch.linalg.cholesky_ex(hyper_precision + k * spread_precision)[0]
        # μ0 = loc + L⁻ᵀ z = μ0_init + L⁻ᵀ (L⁻¹ rhs + z): covariance L⁻ᵀ L⁻¹ = P⁻¹.
        half = torch.linalg.solve_triangular(chol, rhs, upper=False) + normals
        step = torch.linalg.solve_triangular(chol.mT, half, upper=True)
        mean_loc = initial.mean_loc + step.squeeze(-1)
        # Σ0 | μ0, {μ_k} (terms of the initial prior alone are memoised on it: the same at
        # every sweep of a run; only the lower triangle of the scale is read)
        centred = means - mean_loc
        scale_s = initial._memo("twice_mean", "mean_covariance", lambda m: 2.0 * m)
        scale_s_tril = torch.linalg.cholesky_ex(scale_s + centred.mT @ centred)[0]
        mean_covariance = inverse_wishart_from_factor(bartlett[0], scale_s_tril)
        # Ψ0 | {Σ_k} ~ Wishart(ν_h + K ν0, P⁻¹), P = V⁻¹ + Σ_k Σ_k⁻¹: W = (M A)(M A)ᵀ for any
        # M Mᵀ = P⁻¹; with P = L Lᵀ, M = L⁻ᵀ (one triangular solve, no inverse of P).
        hyper_df = d + 1.0
        hyper_scale_precision = initial._memo(
            "hyper_precision", "scale", lambda _: hyper_df * initial._scale_inverse()
        )
        precisions = torch.cholesky_inverse(torch.linalg.cholesky(covariances)).sum(0)
        posterior_tril = torch.linalg.cholesky_ex(hyper_scale_precision + precisions)[0]
        root = torch.linalg.solve_triangular(posterior_tril.mT, bartlett[1], upper=True)
        scale = symmetric(root @ root.mT)
        # Both draws are positive definite in exact arithmetic, but rounding can take them
        # off it where the components' precisions are nearly singular (policies converged
        # without regularisation on returns that are a function of θ). Factorised here, as
        # the next sweep needs (memoised below, so nothing is factorised twice): a draw that
        # does not factorise fails this sweep like any other matrix that does not, instead
        # of ending the chain with an H that every later clustering would fail on.
        scale_tril, scale_info = torch.linalg.cholesky_ex(scale)
        mean_tril, mean_info = torch.linalg.cholesky_ex(mean_covariance)
        if bool(scale_info | mean_info):  # (info: 0, or the order of the failing minor)
            raise torch.linalg.LinAlgError(
                "the Gibbs update of H drew a scale Ψ0 or a mean covariance Σ0 that is not "
                "positive definite in float64"
            )
        # The rest of __post_init__'s validation (a few more factorisations) would run once
        # per sweep for nothing.
        prior = NormalInverseWishartPrior._unchecked(
            mean_loc=mean_loc,
            mean_covariance=mean_covariance,
            df=self.df,
            scale=scale,
            regularization=self.regularization,
        )
        prior._memo("scale_tril", "scale", lambda _: scale_tril)
        prior._memo("mean_tril", "mean_covariance", lambda _: mean_tril)
        return prior

    # The factorisations below are memoised on the prior (``dipole_torch.memo.Memo``): a
    # sweep needs each several times (H's draws, the μ step, H's update), the initial prior's
    # at every sweep of a run. Reusing a factor is exact (the same call on the same matrix); a
    # memo is recomputed when its field is replaced or modified in place.
    def _memo(self, name: str, field: str, compute) -> Tensor:
        """``compute(self.<field>)``, memoised while that field is the same unmodified tensor."""
        memo = self.__dict__.get("_memos")
        if memo is None:  # (priors built by ``updated`` skip __init__)
            memo = self.__dict__["_memos"] = Memo()
        source = getattr(self, field)
        return memo.get(name, (source,), lambda: compute(source))

    def _mean_tril(self) -> Tensor:
        """``[D, D]`` Cholesky factor of Σ0 (memoised; not to be modified)."""
        return self._memo("mean_tril", "mean_covariance", torch.linalg.cholesky)

    def _mean_precision(self) -> Tensor:
        """``[D, D]`` Σ0⁻¹ from its factor (memoised; not to be modified). Exactly symmetric:
        ``cholesky_inverse`` fills one triangle and mirrors it."""
        return self._memo(
            "mean_precision", "mean_covariance", lambda _: torch.cholesky_inverse(self._mean_tril())
        )

    def _scale_tril(self) -> Tensor:
        """``[D, D]`` Cholesky factor of Ψ0 (memoised; not to be modified)."""
        return self._memo("scale_tril", "scale", torch.linalg.cholesky)

    def _scale_inverse(self) -> Tensor:
        """``[D, D]`` Ψ0⁻¹ from its factor (memoised; exactly symmetric)."""
        return self._memo(
            "scale_inverse", "scale", lambda _: torch.cholesky_inverse(self._scale_tril())
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
        """The prior ``state_dict`` saved, checked for shapes, finiteness and definiteness
        but not for conditioning: a prior the chain drew (``updated``) can be closer to
        singular than one a user may pass (the chain went on with it), and a checkpoint
        must restore the run it saved."""
        names = {field.name for field in fields(cls)}
        if set(state) != names:
            raise ValueError(f"a prior's state dict holds {sorted(names)}; got {sorted(state)}")
        prior = cls._unchecked(**state)
        prior._check(well_conditioned=False)
        return prior

    @classmethod
    def _unchecked(cls, **values) -> NormalInverseWishartPrior:
        """A prior with these field values, without ``__post_init__``'s validation (whose
        callers check what they need themselves)."""
        prior = object.__new__(cls)
        prior.__dict__.update(values)
        return prior

"""Reproducible draws from ``torch.distributions`` objects with an explicit ``torch.Generator``.

``Distribution.sample`` reads the global RNG and takes no generator. The library must never
touch the global RNG (a caller's ``torch.manual_seed`` stream stays the caller's), yet every
draw goes through a distribution object. So a draw forks the global RNG of the distribution's
device, seeds it from the caller's generator, samples, and restores the global state: the
result depends on the generator alone, and the caller's own global-RNG stream is left exactly
as it was.

The (inverse-)Wishart draws of the Gibbs sweep are the exception: they are made directly from
the generator by Bartlett's decomposition (``inverse_wishart``, ``wishart``), because
``torch.distributions.Wishart`` factorises its scale once per draw, checks its support and
draws every sample twice, which made them most of a sweep's time at large N.
"""

from __future__ import annotations

import functools
import math
from collections.abc import Sequence

import numpy as np
import torch
from torch.distributions import Categorical, Distribution, MultivariateNormal
from torch.distributions.multivariate_normal import _batch_mv

_SEED_HIGH = 2**62


def _device_of(distribution: Distribution) -> torch.device:
    for value in vars(distribution).values():
        if isinstance(value, torch.Tensor):
            return value.device
        if isinstance(value, Distribution):
            return _device_of(value)
    return torch.device("cpu")


def draw(
    distribution: Distribution,
    sample_shape: torch.Size | tuple[int, ...] = (),
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """``distribution.sample(sample_shape)``, seeded from ``generator`` when one is given.

    Args:
        distribution: any ``torch.distributions`` / ``pyro.distributions`` object.
        sample_shape: leading sample shape, as for ``Distribution.sample``.
        generator: the source of randomness; ``None`` falls back to the global RNG.

    Returns:
        ``[*sample_shape, *batch_shape, *event_shape]`` sample.
    """
    return draw_with_uniforms(distribution, 0, sample_shape, generator)[0]


def draw_with_uniforms(
    distribution: Distribution,
    num_uniforms: int,
    sample_shape: torch.Size | tuple[int, ...] = (),
    generator: torch.Generator | None = None,
) -> tuple[torch.Tensor, torch.Tensor]:
    """``draw``, followed by ``num_uniforms`` U(0, 1) draws from the same seed.

    A Metropolis-Hastings step needs an acceptance uniform next to each proposal. Drawn here,
    from the one seed the proposal takes from ``generator`` anyway, they leave the generator's
    stream, and so every later draw, as it would be without the acceptance test.

    Returns:
        The sample, and ``[num_uniforms]`` float64 uniforms on the distribution's device.
    """
    device = _device_of(distribution)
    shape = torch.Size(sample_shape)

    def sample() -> tuple[torch.Tensor, torch.Tensor]:
        value = distribution.sample(shape)
        if num_uniforms == 0:  # plain draw: touch no RNG beyond the distribution's own
            return value, torch.empty(0, dtype=torch.float64, device=device)
        return value, torch.rand(num_uniforms, dtype=torch.float64, device=device)

    if generator is None:
        return sample()
    seed = _take_seed(generator)
    if type(distribution) is MultivariateNormal and device.type == "cpu":
        return _draw_normal_seeded(distribution, num_uniforms, shape, seed)
    devices = [device] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices, device_type=device.type):
        torch.random.default_generator.manual_seed(seed)
        if device.type == "cuda":
            with torch.cuda.device(device):
                torch.cuda.manual_seed(seed)
        return sample()


def draw_gaussian(
    loc: torch.Tensor,
    covariance: torch.Tensor,
    sample_shape: torch.Size | tuple[int, ...] = (),
    generator: torch.Generator | None = None,
) -> torch.Tensor:
    """``draw(MultivariateNormal(loc, covariance_matrix=covariance), sample_shape, generator)``
    without building the distribution, with the same numbers.

    The distribution object's construction (``torch.broadcast_shapes``, expands, its
    bookkeeping) costs several times the draw itself at small D. Here: the same Cholesky
    factor, the same seed taken from ``generator``, the same normals and the same
    ``loc + L ε``. No argument validation (as ``validate_args=False``).

    Args:
        loc: ``[*batch_l, D]`` means.
        covariance: ``[*batch_c, D, D]`` positive-definite covariances (batch dims broadcast).

    Returns:
        ``[*sample_shape, *batch, D]`` draws.
    """
    if generator is None or loc.device.type != "cpu":
        mvn = MultivariateNormal(loc, covariance_matrix=covariance, validate_args=False)
        return draw(mvn, sample_shape, generator)
    tril = torch.linalg.cholesky(covariance)
    batch = broadcast_shape(covariance.shape[:-2], loc.shape[:-1])
    loc = _expand(loc, (*batch, loc.shape[-1]))
    value, _ = _seeded_gaussian(loc, tril, tuple(sample_shape), _take_seed(generator))
    return value


def _take_seed(generator: torch.Generator) -> int:
    """The one seed a draw takes from ``generator``."""
    return int(torch.randint(0, _SEED_HIGH, (1,), generator=generator, device=generator.device))


def _seeded_gaussian(
    loc: torch.Tensor, tril: torch.Tensor, sample_shape: tuple[int, ...], seed: int
) -> tuple[torch.Tensor, torch.Generator]:
    """``[*sample_shape, *loc.shape]`` draws loc + L ε on CPU, as ``MultivariateNormal.sample``
    makes them (ε filled by ``normal_``), from a private CPU generator seeded with ``seed``:
    the same Mersenne twister a forked global one would be, so the numbers are the same.
    Returns the draws and that generator (for draws that follow from the same seed).

    Args:
        loc: ``[*batch, D]`` means, already broadcast to the batch shape.
        tril: ``[*batch_c, D, D]`` lower Cholesky factors (batch dims broadcast with loc's).
    """
    generator = torch.Generator()
    generator.manual_seed(seed)
    with torch.no_grad():
        eps = torch.empty((*sample_shape, *loc.shape), dtype=loc.dtype, device=loc.device)
        eps.normal_(generator=generator)
        return loc + _batch_mv(tril, eps), generator


def _draw_normal_seeded(
    distribution: MultivariateNormal, num_uniforms: int, shape: torch.Size, seed: int
) -> tuple[torch.Tensor, torch.Tensor]:
    """``draw_with_uniforms`` of a CPU ``MultivariateNormal`` without forking the global
    RNG (saving and restoring its state cost more than the draw): the draw of
    ``_seeded_gaussian``, then the uniforms from the same private generator."""
    value, generator = _seeded_gaussian(
        distribution.loc, distribution._unbroadcasted_scale_tril, tuple(shape), seed
    )
    if num_uniforms == 0:
        return value, torch.empty(0, dtype=torch.float64)
    return value, torch.rand(num_uniforms, dtype=torch.float64, generator=generator)


def draw_categorical(logits: torch.Tensor, uniform: torch.Tensor) -> torch.Tensor:
    """Inverse-CDF draw from ``Categorical(logits=logits)`` given pre-drawn uniforms.

    The Gibbs sweep draws one label per data point; pre-drawing all its uniforms from the
    generator in one call keeps the per-point cost to a few tensor ops.

    Args:
        logits: ``[..., C]`` unnormalised log probabilities.
        uniform: ``[...]`` draws from U(0, 1).

    Returns:
        ``[...]`` integer labels in ``[0, C)``.
    """
    probs = Categorical(logits=logits, validate_args=False).probs
    cdf = probs.cumsum(-1)
    total = cdf[..., -1]
    # The label is the first slot whose CDF exceeds v = u·total (right-sided search), so
    # v ∈ [cdf[j-1], cdf[j]) and probs[j] > 0: u = 0 skips leading zero-probability slots.
    # v is kept strictly below total, or u → 1 rounding v up to total would pick trailing ones.
    below_total = torch.nextafter(total, torch.zeros_like(total))
    value = torch.minimum(uniform.to(cdf.dtype) * total, below_total)
    label = torch.searchsorted(cdf, value.unsqueeze(-1), right=True).squeeze(-1)
    return label.clamp_(max=logits.shape[-1] - 1)


def draw_categorical_numpy(logits: np.ndarray, uniform: float) -> int:
    """``draw_categorical`` for one ``[C]`` float64 numpy row: the same right-sided
    inverse-CDF search, at a fraction of the cost per call (the CPU label loop's draw).

    Args:
        logits: ``[C]`` unnormalised log probabilities, at least one finite.
        uniform: a draw from U(0, 1).

    Returns:
        The label in ``[0, C)``.
    """
    top = logits.max()
    if not top > -math.inf:  # every label impossible (or NaN): no distribution to draw from
        raise FloatingPointError(
            "every label has probability 0 (its log-likelihood under each component overflowed)"
        )
    cdf = np.exp(logits - top).cumsum()
    total = float(cdf[-1])
    value = min(uniform * total, math.nextafter(total, 0.0))  # see draw_categorical
    return min(int(cdf.searchsorted(value, side="right")), len(cdf) - 1)


def bartlett_factor(
    df: torch.Tensor, dim: int, generator: torch.Generator | None = None
) -> torch.Tensor:
    """``[*batch, p, p]`` lower-triangular A with A Aᵀ ~ Wishart(df, I_p) (Bartlett 1933).

    A_ii = sqrt(χ²(df − i)) for i = 0 … p − 1, A_ij ~ N(0, 1) below the diagonal, zero above.
    The normals (first) and then the χ² draws come from ``generator``, on its device (a CPU
    generator may feed CUDA tensors), and are moved to ``df``'s.

    Args:
        df: ``[*batch]`` degrees of freedom, each > p − 1 (float64 for the DP mixture).
        dim: p.
        generator: the source of randomness (``None``: the global RNG).
    """
    where = generator.device if generator is not None else df.device
    lower, diagonal, steps = _bartlett_indices(dim, df.device, where, df.dtype)
    normal = torch.randn(
        (*df.shape, dim * (dim - 1) // 2), generator=generator, dtype=df.dtype, device=where
    )
    # torch._standard_gamma is what torch.distributions.Gamma samples with; called directly
    # it takes the generator, so no fork of the global RNG is needed. χ²(k) = 2 Gamma(k/2).
    half_df = 0.5 * (_to(df, where)[..., None] - steps)
    chi2 = 2.0 * torch._standard_gamma(half_df, generator=generator)
    factor = torch.zeros(*df.shape, dim * dim, dtype=df.dtype, device=df.device)
    # Flat index_copy_ rather than an advanced-index assignment and a diagonal view's copy_.
    factor.index_copy_(-1, lower, _to(normal, df.device))
    factor.index_copy_(-1, diagonal, _to(chi2.sqrt(), df.device))
    return factor.view(*df.shape, dim, dim)


@functools.lru_cache(maxsize=64)
def _bartlett_indices(
    dim: int, device: torch.device, where: torch.device, dtype: torch.dtype
) -> tuple[torch.Tensor, torch.Tensor, torch.Tensor]:
    """The flat (row-major) positions in a p × p factor of its ``[p(p−1)/2]`` strict lower
    triangle and ``[p]`` diagonal (on ``device``), and ``[p]`` 0 … p − 1 (on ``where``):
    made once per shape rather than at every draw (each is a small-tensor op). Not to be
    modified."""
    rows, cols = torch.tril_indices(dim, dim, -1, device=device)
    diagonal = torch.arange(dim, device=device)
    return rows * dim + cols, diagonal * (dim + 1), torch.arange(dim, dtype=dtype, device=where)


def uniforms(n: int, generator: torch.Generator | None, device: torch.device) -> torch.Tensor:
    """``[n]`` float64 U(0, 1) draws from ``generator`` (on its own device), moved to
    ``device``: a sweep's label draws pre-drawn in one call."""
    where = generator.device if generator is not None else device
    return _to(torch.rand(n, generator=generator, dtype=torch.float64, device=where), device)


def _expand(tensor: torch.Tensor, shape: tuple[int, ...]) -> torch.Tensor:
    """``tensor.expand(shape)``, without the dispatch when it has that shape already."""
    return tensor if tuple(tensor.shape) == tuple(shape) else tensor.expand(shape)


def _to(tensor: torch.Tensor, device: torch.device) -> torch.Tensor:
    """``tensor.to(device)``, without the dispatch when it is already there."""
    return tensor if tensor.device == device else tensor.to(device)


def inverse_wishart(
    df: torch.Tensor | float,
    scale_tril: torch.Tensor,
    generator: torch.Generator | None = None,
    symmetrize: bool = True,
) -> torch.Tensor:
    """Σ ~ IW(df, Ψ) with Ψ = L Lᵀ, drawn as Σ = (L A⁻ᵀ)(L A⁻ᵀ)ᵀ
    (``inverse_wishart_from_factor`` with a fresh Bartlett factor A).

    Args:
        df: ``[*batch]`` or scalar degrees of freedom, > p − 1.
        scale_tril: ``[*batch, p, p]`` lower Cholesky factor L of Ψ (batch dims broadcast
            with ``df``'s; an expanded L costs no extra factorisations).
        generator: the source of randomness.
        symmetrize: average the draw with its transpose. ``Bᵀ B`` is symmetric only up to
            rounding; a caller that reads one triangle (a Cholesky factorisation) can skip
            the extra pass over N·m auxiliary matrices and symmetrise the few it keeps.

    Returns:
        ``[*batch, p, p]`` symmetric positive-definite draws.
    """
    p = scale_tril.shape[-1]
    df, batch = _df_and_batch(df, scale_tril)
    factor = bartlett_factor(_expand(df, batch), p, generator)
    return inverse_wishart_from_factor(factor, _expand(scale_tril, (*batch, p, p)), symmetrize)


def inverse_wishart_from_factor(
    factor: torch.Tensor, scale_tril: torch.Tensor, symmetrize: bool = True
) -> torch.Tensor:
    """``[*batch, p, p]`` Σ = (L A⁻ᵀ)(L A⁻ᵀ)ᵀ ~ IW(df, L Lᵀ) from a Bartlett factor A of
    Wishart(df, I) (``bartlett_factor``).

    Σ⁻¹ = L⁻ᵀ A Aᵀ L⁻¹ is Wishart(df, Ψ⁻¹) by Bartlett's decomposition (any factor M with
    M Mᵀ = Ψ⁻¹ serves, here M = L⁻ᵀ), so E[Σ] = Ψ / (df − p − 1). One triangular solve and one
    product per draw; Ψ is factorised once per distinct scale, never per draw.

    Args:
        factor: ``[*batch, p, p]`` lower-triangular A.
        scale_tril: ``[*batch, p, p]`` lower Cholesky factor L of Ψ.
        symmetrize: see ``inverse_wishart``.
    """
    # B = A⁻¹ Lᵀ = (L A⁻ᵀ)ᵀ, so Σ = Bᵀ B.
    root = torch.linalg.solve_triangular(factor, scale_tril.transpose(-1, -2), upper=False)
    sigma = root.transpose(-1, -2) @ root
    return 0.5 * (sigma + sigma.transpose(-1, -2)) if symmetrize else sigma


def wishart(
    df: torch.Tensor | float, scale_tril: torch.Tensor, generator: torch.Generator | None = None
) -> torch.Tensor:
    """W ~ Wishart(df, V) with V = L Lᵀ, drawn as W = (L A)(L A)ᵀ (Bartlett); E[W] = df · V.

    Args:
        df: ``[*batch]`` or scalar degrees of freedom, > p − 1.
        scale_tril: ``[*batch, p, p]`` lower Cholesky factor of the scale matrix V.
        generator: the source of randomness.

    Returns:
        ``[*batch, p, p]`` symmetric positive-definite draws.
    """
    p = scale_tril.shape[-1]
    df, batch = _df_and_batch(df, scale_tril)
    root = scale_tril @ bartlett_factor(_expand(df, batch), p, generator)
    w = root @ root.transpose(-1, -2)
    return 0.5 * (w + w.transpose(-1, -2))


def broadcast_shape(*shapes: Sequence[int]) -> tuple[int, ...]:
    """The broadcast of ``shapes``, as ``torch.broadcast_shapes`` gives it, by hand: that one
    costs more than the draws it serves, and its first call in a process imports sympy.
    Raises ``ValueError`` naming the shapes when they do not broadcast."""
    width = max((len(shape) for shape in shapes), default=0)
    result = [1] * width
    for shape in shapes:
        for axis, size in enumerate(shape, start=width - len(shape)):
            if size != 1 and result[axis] not in (1, size):
                listed = ", ".join(str(list(shape)) for shape in shapes)
                raise ValueError(f"shapes {listed} do not broadcast")
            result[axis] = result[axis] if size == 1 else size
    return tuple(result)


def _df_and_batch(df: torch.Tensor | float, scale_tril: torch.Tensor) -> tuple[torch.Tensor, tuple]:
    """``df`` as a tensor like ``scale_tril``, and the broadcast batch shape of the two."""
    df = torch.as_tensor(df, dtype=scale_tril.dtype, device=scale_tril.device)
    try:
        batch = broadcast_shape(df.shape, scale_tril.shape[:-2])
    except ValueError:
        message = f"df's shape {list(df.shape)} does not broadcast with scale_tril's"
        raise ValueError(message) from None
    return df, batch

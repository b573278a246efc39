"""Reproducible draws from ``torch.distributions`` objects with an explicit ``torch.Generator``.

``Distribution.sample`` reads the global RNG and takes no generator. The library must never
touch the global RNG (DESIGN.md), yet every draw goes through a distribution object. So a draw
forks the global RNG of the distribution's device, seeds it from the caller's generator, samples,
and restores the global state: the result depends on the generator alone, and the caller's own
global-RNG stream is left exactly as it was.
"""

from __future__ import annotations

import torch
from torch.distributions import Categorical, Distribution

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
    """:func:`draw`, followed by ``num_uniforms`` U(0, 1) draws from the same seed.

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
    seed = int(torch.randint(0, _SEED_HIGH, (1,), generator=generator, device=generator.device))
    devices = [device] if device.type == "cuda" else []
    with torch.random.fork_rng(devices=devices, device_type=device.type):
        torch.random.default_generator.manual_seed(seed)
        if device.type == "cuda":
            with torch.cuda.device(device):
                torch.cuda.manual_seed(seed)
        return sample()


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

"""A toy task with several separated optima of equal height."""

from __future__ import annotations

import math
import numbers
from collections.abc import Sequence

import torch
from dipole_torch.tasks.base import EpisodicTask
from torch import Tensor

# The noise-free return at which a policy has found an optimum: within 0.14 bump widths
# (0.035 at the default width 0.25) of its centre.
FOUND_RETURN = 0.99


class MultimodalTask(EpisodicTask):
    """Reward with ``num_optima`` equally high Gaussian bumps, one policy evaluation a trial.

    Description:
        A stand-in for a task that can be solved in several distinct ways: the return of
        ``θ ∈ R^D`` is the height of the highest of ``num_optima`` Gaussian bumps,
        ``r(θ) = max_i exp(−‖θ − c_i‖² / (2 w²))``, with centres c_i spread evenly on a circle
        of radius ``radius`` in the first two coordinates (0 in the others). The initial policy
        θ0 = 0 sits at the centre, between the optima, where every bump is equally (un)likely.
        DIPOLE should end with policies on several optima; PoWER, with one policy, on one.

    Action Space / Observation Space:
        None: a single-step (bandit) task; the policy *is* θ.

    Rewards:
        In [0, 1]; 1 exactly at an optimum. ``reward_range = (0, 1)``.

    Starting State:
        θ0 = 0, Σ_start = ``exploration_std``² I.

    Episode End:
        After one evaluation.

    Arguments:
        dim: D in [2, 5].
        num_optima: number of bumps (≥ 2).
        radius: distance of every optimum from θ0.
        width: bump width w.
        exploration_std: initial exploration standard deviation per coordinate.
        noise_std: standard deviation of Gaussian noise on the return, clamped to [0, 1]
            (0 by default: deterministic).
        device: torch device of the evaluation.

    Example:
        >>> task = MultimodalTask(dim=2, num_optima=4)
        >>> task.evaluate(task.optima).tolist()
        [1.0, 1.0, 1.0, 1.0]
    """

    def __init__(
        self,
        dim: int = 2,
        num_optima: int = 4,
        radius: float = 1.0,
        width: float = 0.25,
        exploration_std: float = 0.6,
        noise_std: float = 0.0,
        device: str | torch.device = "cpu",
        optima: Sequence[Sequence[float]] | None = None,
    ):
        for name, value in (("dim", dim), ("num_optima", num_optima)):
            if isinstance(value, bool) or not isinstance(value, numbers.Integral):
                raise ValueError(f"{name} must be an integer, got {value!r}")
        if not 2 <= dim <= 5:
            raise ValueError(f"dim must be in [2, 5], got {dim}")
        if num_optima < 2:
            raise ValueError(f"num_optima must be >= 2, got {num_optima}")
        for name, value in (
            ("radius", radius),
            ("width", width),
            ("exploration_std", exploration_std),
        ):
            if not 0 < value < math.inf:
                raise ValueError(f"{name} must be positive and finite, got {value}")
        if not 0 <= noise_std < math.inf:
            raise ValueError(f"noise_std must be non-negative and finite, got {noise_std}")
        self.device = torch.device(device)
        self.dtype = torch.float32
        angles = 2 * torch.pi * torch.arange(num_optima, dtype=torch.float64) / num_optima
        centres = torch.zeros(num_optima, dim, dtype=torch.float64)
        centres[:, 0] = radius * torch.cos(angles + torch.pi / num_optima)
        centres[:, 1] = radius * torch.sin(angles + torch.pi / num_optima)
        if optima is not None:
            centres = torch.as_tensor(optima, dtype=torch.float64)
            if centres.shape != (num_optima, dim):
                raise ValueError(
                    f"optima must have shape [{num_optima}, {dim}], got {list(centres.shape)}"
                )
            if not bool(centres.isfinite().all()):
                raise ValueError("optima contains non-finite values (NaN or inf)")
        self.optima = centres.to(self.device, self.dtype)
        self.width = float(width)
        self.noise_std = float(noise_std)
        self.default_seed = 0  # the noise when evaluate is given no generator
        self.theta0 = torch.zeros(dim, device=self.device)
        self.sigma_start = exploration_std**2 * torch.eye(dim, device=self.device)
        self.reward_range = (0.0, 1.0)

    def nearest_optimum(self, theta: Tensor) -> Tensor:
        """``[B]`` index of the optimum closest to each row of ``theta: [B, D]``."""
        theta = self.check_theta(theta)
        return torch.cdist(theta, self.optima).argmin(-1)

    def height(self, theta: Tensor) -> Tensor:
        """``[B]`` the noise-free return of ``theta: [B, D]``: the highest bump's height."""
        theta = self.check_theta(theta)
        sq = torch.cdist(theta, self.optima).square().amin(-1)
        return torch.exp(-sq / (2 * self.width**2))

    def evaluate(self, theta: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """``[B]`` returns of ``theta: [B, D]``; with ``noise_std``, the noise drawn from
        ``generator``, or (``None``) from a fixed seed, as the base class promises: equal
        ``theta`` give equal returns."""
        reward = self.height(theta)
        if self.noise_std > 0:
            if generator is None:
                generator = torch.Generator().manual_seed(self.default_seed)
            noise = torch.randn(reward.shape, generator=generator, device=generator.device)
            reward = (reward + self.noise_std * noise.to(self.device)).clamp(0.0, 1.0)
        return reward

    def optima_found(self, theta: Tensor) -> list[int]:
        """The optima, by index, sorted, that some row of ``theta: [K, D]`` has found: its
        noise-free return at least ``FOUND_RETURN`` (within 0.14 bump widths of the centre)."""
        with torch.no_grad():
            found = self.height(theta) >= FOUND_RETURN
            return sorted(set(self.nearest_optimum(theta)[found].tolist()))

    def describe_policies(self, theta: Tensor) -> list[str]:
        """``optimum 2, return 0.9993`` for each row of ``theta: [K, D]``: the nearest
        optimum and the noise-free return."""
        with torch.no_grad():
            nearest, heights = self.nearest_optimum(theta).tolist(), self.height(theta).tolist()
        return [f"optimum {i}, return {h:.4g}" for i, h in zip(nearest, heights, strict=True)]

    def policy_scalars(self, theta: Tensor) -> dict[str, float]:
        """``{"optima": n}``: the optima the policies ``theta: [K, D]`` have found."""
        return {"optima": float(len(self.optima_found(theta)))}

    def describe_policy_set(self, theta: Tensor) -> str:
        """E.g. ``3 of the 4 optima at return ≥ 0.99: 0, 1, 3``."""
        found = self.optima_found(theta)
        listed = ": " + ", ".join(map(str, found)) if found else ""
        return f"{len(found)} of the {len(self.optima)} optima at return ≥ {FOUND_RETURN:g}{listed}"

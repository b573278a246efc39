"""DS-GMR: a virtual spring-damper pulled along an attractor path retrieved by GMR.

Calinon, Li, Alizadeh, Tsagarakis & Caldwell (2012), "Statistical dynamical systems for skills
acquisition in humanoids" (Humanoids 2012); the public pbdlib-matlab ``demo_DSGMR01`` shows the
same scheme. A Gaussian mixture over ``[t, x]`` encodes the path of the spring's equilibrium
point: Gaussian mixture regression (GMR, ``dipole_torch.GaussianMixture.condition``) gives
the attractor

    x̂(t) = Σ_i h_i(t) μ_i^x,    h_i(t) ∝ N(t; μ_i^t, σ_t²),

and the tip follows the critically damped spring-damper

    ẍ = K_P (x̂(t) − x) − K_V ẋ,    K_V = 2 √K_P,

from rest at the start point. The policy parameters θ are the stacked attractor centres μ_i^x
(``[B, K·dim]``, component-major: ``θ[:, i·dim:(i+1)·dim] = μ_i^x``).

Optionally (``goal_time``) the mixture has one more, **fixed** component centred at the goal
point ``g`` at time ``goal_time`` (not part of θ): x̂(t) = Σ_i h_i(t) μ_i^x + h_g(t) g, so the
path ends at the goal whatever θ is, once the goal component dominates (the spring then pulls
the tip there and it settles at rest, like the final attractor of Calinon et al.'s DS-GMR).

Choices:

* The time centres μ_i^t are fixed and evenly spaced. Without a goal component,
  ``μ_i^t = i · duration / K`` (``i = 0..K−1``): the first attractor is active at the start,
  the last one for the final ``duration / K`` seconds, so a policy whose first and last
  attractors sit on the start and target points starts and ends there at rest. With one,
  the K learned components and the goal are evenly spaced on ``[0, goal_time]``:
  ``μ_i^t = i · goal_time / K``, the goal at ``goal_time``; the motion may last longer than
  ``goal_time`` to let the tip settle on the goal. Time std ``σ_t`` defaults to half the
  spacing.
* The component covariances are fixed and block-diagonal (no t–x coupling), so the GMR
  regression term Σ_xt Σ_tt⁻¹ (t − μ_i^t) vanishes and x̂(t) is the h-weighted average of the
  centres; the spatial block only matters for the (unused) conditional covariance.
* K_V = 2 √K_P is the critical damping of ẍ + K_V ẋ + K_P x = 0 (discriminant K_V² − 4 K_P = 0).
  √(2 K_P), also met in descriptions of DS-GMR, is under-damped (ζ = 1/√2); we use the
  critically damped value.
* Integration: semi-implicit (symplectic) Euler with a fixed ``dt``, a batched torch loop over
  time; every operation is differentiable in θ.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np
import torch
from numpy.typing import NDArray
from torch import Tensor

if TYPE_CHECKING:
    from dipole_torch import GaussianMixture


class DSGMR:
    """Batched DS-GMR trajectory generator.

    Args:
        num_attractors: K, the number of GMM components (attractors).
        duration: length of the motion in seconds.
        dt: integration step in seconds; ``duration / dt`` must be (close to) an integer.
        stiffness: K_P in 1/s²; the damping is K_V = 2 √K_P (critical).
        dim: dimension of the task space (3 for a Cartesian position).
        time_std: σ_t of every component's time marginal, seconds (default: half the spacing
            of the time centres).
        goal_time: time centre (s, in ``(0, duration]``) of a fixed final component at the
            goal point passed to ``rollout``; ``None`` (default): no fixed component.
        device, dtype: of the time grid and of the generated trajectories.
    """

    def __init__(
        self,
        num_attractors: int,
        duration: float,
        dt: float,
        stiffness: float,
        dim: int = 3,
        time_std: float | None = None,
        goal_time: float | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ):
        if num_attractors < 1:
            raise ValueError(f"num_attractors must be >= 1, got {num_attractors}")
        if not (duration > 0 and dt > 0 and stiffness > 0):
            raise ValueError(
                f"duration, dt and stiffness must be positive, got {duration}, {dt}, {stiffness}"
            )
        steps = round(duration / dt)
        if steps < 1 or abs(steps * dt - duration) > 1e-6 * duration:
            raise ValueError(f"duration ({duration}) must be a multiple of dt ({dt})")
        self.num_attractors = num_attractors
        self.dim = dim
        self.duration = float(duration)
        self.dt = float(dt)  # seconds per integration step
        self.steps = steps
        self.stiffness = float(stiffness)  # K_P, 1/s²
        self.damping = 2.0 * math.sqrt(stiffness)  # K_V, 1/s (critical damping)
        self.device = torch.device(device)
        self.dtype = dtype
        if goal_time is not None and not (0 < goal_time <= duration):
            raise ValueError(f"goal_time must lie in (0, duration={duration}], got {goal_time}")
        self.goal_time = None if goal_time is None else float(goal_time)
        spacing = (duration if goal_time is None else goal_time) / num_attractors
        self._spacing = spacing  # seconds between time centres
        self.time_std = float(time_std) if time_std is not None else 0.5 * spacing
        factory = {"device": self.device, "dtype": dtype}
        self.times = torch.arange(steps + 1, **factory) * self.dt  # [T+1] seconds
        # [C] μ_i^t of the C = K (+1 with a goal) components, the goal's last.
        components = num_attractors + (goal_time is not None)
        self.time_centres = torch.arange(components, **factory) * spacing
        # Block-diagonal component covariances over [t, x]: σ_t² in time, identity in space.
        covariance = torch.eye(1 + dim, **factory)
        covariance[0, 0] = self.time_std**2
        self._covariances = covariance.expand(components, 1 + dim, 1 + dim)
        self._weights = torch.full((components,), 1.0 / components, **factory)
        self._activations: Tensor | None = None  # h_i(t) [T+1, C], computed on first use
        self._activations_numpy: NDArray[np.float64] | None = None  # the same, float64

    @property
    def parameter_dim(self) -> int:
        """K · dim, the length of θ."""
        return self.num_attractors * self.dim

    def _centres(self, theta: Tensor) -> Tensor:
        if theta.dim() != 2 or theta.shape[-1] != self.parameter_dim:
            raise ValueError(
                f"theta must have shape [B, {self.parameter_dim}] (K={self.num_attractors} "
                f"attractors x dim={self.dim}), got {list(theta.shape)}"
            )
        return theta.reshape(theta.shape[0], self.num_attractors, self.dim)

    def _all_centres(self, theta: Tensor, goal: Tensor | None) -> Tensor:
        """``[B, C, dim]``: the learned centres, then the goal's (with a goal component)."""
        centres = self._centres(theta)
        if self.goal_time is None:
            if goal is not None:
                raise ValueError("goal given, but this DSGMR has no goal component (goal_time)")
            return centres
        if goal is None or goal.shape != (self.dim,):
            shape = None if goal is None else list(goal.shape)
            raise ValueError(f"goal must be a [{self.dim}] point (goal_time is set), got {shape}")
        goal = goal.to(theta).expand(theta.shape[0], 1, self.dim)
        return torch.cat([centres, goal], dim=1)

    def gmm(self, theta: Tensor, goal: Tensor | None = None) -> GaussianMixture:
        """The GMM over ``[t, x]`` of policies ``theta: [B, K·dim]`` (batch shape ``[B]``;
        with a goal component, ``goal: [dim]`` is its fixed centre and is the last
        component)."""
        from dipole_torch import GaussianMixture  # (imports Pyro: not needed for the paths)

        centres = self._all_centres(theta, goal)
        time_column = self.time_centres.to(theta.dtype).expand(theta.shape[0], -1).unsqueeze(-1)
        means = torch.cat([time_column, centres], dim=-1)  # [B, K, 1+dim]
        return GaussianMixture(
            self._weights.to(theta.dtype),
            means,
            self._covariances.to(theta.dtype),
            validate_args=False,
        )

    def attractor_path(self, theta: Tensor, goal: Tensor | None = None) -> Tensor:
        """GMR attractor x̂(t) ``[B, T+1, dim]`` on the time grid ``times`` (``goal:
        [dim]`` required with a goal component, else ``None``).

        Without t–x coupling, GMR's mean is ``Σ_i h_i(t) μ_i^x`` with the responsibilities
        ``h_i(t)`` of the time marginal, which do not depend on θ: they are computed once
        (``GaussianMixture.responsibilities``) and the path is one matrix product.
        """
        centres = self._all_centres(theta, goal)
        if self._activations is None or self._activations.dtype != theta.dtype:
            self._activations = self._time_activations(theta.dtype)
        return self._activations @ centres

    def _time_activations(self, dtype: torch.dtype) -> Tensor:
        """``[T+1, C]`` responsibilities h_i(t) of the time marginal on the time grid."""
        probe = torch.zeros(1, self.parameter_dim, device=self.device, dtype=dtype)
        probe_goal = None if self.goal_time is None else probe.new_zeros(self.dim)
        time_marginal = self.gmm(probe, probe_goal).marginal([0])
        times = self.times.to(dtype)[:, None, None]  # [T+1, 1, 1]: one batch row per time
        return time_marginal.responsibilities(times)[:, 0]

    def rollout(self, theta: Tensor, start: Tensor, goal: Tensor | None = None) -> Tensor:
        """Tip positions ``[B, T+1, dim]`` of the spring-damper, from rest at ``start: [dim]``
        (``goal: [dim]``: the fixed final component's centre, with ``goal_time`` only)."""
        attractor = self.attractor_path(theta, goal)
        position = start.to(theta).expand(theta.shape[0], self.dim)
        velocity = torch.zeros_like(position)
        path = [position]
        for step in range(self.steps):
            acceleration = (
                self.stiffness * (attractor[:, step] - position) - self.damping * velocity
            )
            velocity = velocity + self.dt * acceleration
            position = position + self.dt * velocity
            path.append(position)
        return torch.stack(path, dim=1)

    def rollout_numpy(
        self,
        theta: NDArray[np.float64],
        start: NDArray[np.float64],
        goal: NDArray[np.float64] | None = None,
    ) -> NDArray[np.float64]:
        """``rollout`` in float64 numpy (the viapoint task's CPU engine): tip positions
        ``[B, T+1, dim]`` of policies ``theta: [B, K·dim]``, from rest at ``start: [dim]``."""
        if theta.ndim != 2 or theta.shape[-1] != self.parameter_dim:
            raise ValueError(
                f"theta must have shape [B, {self.parameter_dim}], got {list(theta.shape)}"
            )
        if (goal is None) != (self.goal_time is None):
            raise ValueError("goal must be given exactly when this DSGMR has a goal_time")
        if self._activations_numpy is None:
            # h_i(t) of the time marginal, as _time_activations computes them, written out in
            # float64 from __init__'s definitions: log h_i(t) = log N(t; μ_i^t, σ_t²) −
            # log Σ_j N(t; μ_j^t, σ_t²), the weights and σ_t being equal. (No torch
            # distribution: the first one a process builds imports sympy.)
            components = self.num_attractors + (self.goal_time is not None)
            times = np.arange(self.steps + 1, dtype=np.float64)[:, None] * self.dt
            centres = np.arange(components, dtype=np.float64) * self._spacing
            log_density = -0.5 * (times - centres) ** 2 / self.time_std**2  # [T+1, C]
            log_density -= log_density.max(axis=1, keepdims=True)
            activations = np.exp(log_density)
            self._activations_numpy = activations / activations.sum(axis=1, keepdims=True)
        centres = theta.reshape(theta.shape[0], self.num_attractors, self.dim)
        if self.goal_time is not None:
            goal = np.broadcast_to(goal, (theta.shape[0], 1, self.dim))
            centres = np.concatenate([centres, goal], axis=1)
        attractor = self._activations_numpy @ centres  # [B, T+1, dim]
        path = np.empty_like(attractor)
        position = np.broadcast_to(start, (theta.shape[0], self.dim))
        velocity = np.zeros_like(position)
        path[:, 0] = position
        for step in range(self.steps):
            acceleration = (
                self.stiffness * (attractor[:, step] - position) - self.damping * velocity
            )
            velocity = velocity + self.dt * acceleration
            position = position + self.dt * velocity
            path[:, step + 1] = position
        return path

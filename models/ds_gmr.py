"""DS-GMR: a virtual spring-damper pulled along an attractor path retrieved by GMR.

Calinon, Li, Alizadeh, Tsagarakis & Caldwell (2012), "Statistical dynamical systems for skills
acquisition in humanoids" (Humanoids 2012); the public pbdlib-matlab ``demo_DSGMR01`` shows the
same scheme. A Gaussian mixture over ``[t, x]`` encodes the path of the spring's equilibrium
point: Gaussian mixture regression (GMR, :meth:`dipole_torch.GaussianMixture.condition`) gives
the attractor

    x̂(t) = Σ_i h_i(t) μ_i^x,    h_i(t) ∝ N(t; μ_i^t, σ_t²),

and the tip follows the critically damped spring-damper

    ẍ = K_P (x̂(t) − x) − K_V ẋ,    K_V = 2 √K_P,

from rest at the start point. The policy parameters θ are the stacked attractor centres μ_i^x
(``[B, K·dim]``, component-major: ``θ[:, i·dim:(i+1)·dim] = μ_i^x``).

Choices:

* The time centres μ_i^t are fixed and evenly spaced, ``μ_i^t = i · duration / K``
  (``i = 0..K−1``): the first attractor is active at the start, the last one for the final
  ``duration / K`` seconds, so a policy whose first and last attractors sit on the start and
  target points starts and ends there at rest. Time std ``σ_t`` defaults to half the spacing.
* The component covariances are fixed and block-diagonal (no t–x coupling), so the GMR
  regression term Σ_xt Σ_tt⁻¹ (t − μ_i^t) vanishes and x̂(t) is the h-weighted average of the
  centres; the spatial block only matters for the (unused) conditional covariance.
* K_V = 2 √K_P is the critical damping of ẍ + K_V ẋ + K_P x = 0 (discriminant K_V² − 4 K_P = 0).
  ``DESIGN.md`` writes √(2 K_P), which is under-damped (ζ = 1/√2); we use the critically
  damped value.
* Integration: semi-implicit (symplectic) Euler with a fixed ``dt``, a batched torch loop over
  time; every operation is differentiable in θ.
"""

from __future__ import annotations

import math

import torch
from torch import Tensor

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
        spacing = duration / num_attractors
        self.time_std = float(time_std) if time_std is not None else 0.5 * spacing
        factory = {"device": self.device, "dtype": dtype}
        self.times = torch.arange(steps + 1, **factory) * self.dt  # [T+1] seconds
        self.time_centres = torch.arange(num_attractors, **factory) * spacing  # [K] μ_i^t
        # Block-diagonal component covariances over [t, x]: σ_t² in time, identity in space.
        covariance = torch.eye(1 + dim, **factory)
        covariance[0, 0] = self.time_std**2
        self._covariances = covariance.expand(num_attractors, 1 + dim, 1 + dim)
        self._weights = torch.full((num_attractors,), 1.0 / num_attractors, **factory)
        self._activations: Tensor | None = None  # h_i(t) [T+1, K], computed on first use

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

    def gmm(self, theta: Tensor) -> GaussianMixture:
        """The GMM over ``[t, x]`` of policies ``theta: [B, K·dim]`` (batch shape ``[B]``)."""
        centres = self._centres(theta)
        time_column = self.time_centres.to(theta.dtype).expand(theta.shape[0], -1).unsqueeze(-1)
        means = torch.cat([time_column, centres], dim=-1)  # [B, K, 1+dim]
        return GaussianMixture(
            self._weights.to(theta.dtype),
            means,
            self._covariances.to(theta.dtype),
            validate_args=False,
        )

    def attractor_path(self, theta: Tensor) -> Tensor:
        """GMR attractor x̂(t) ``[B, T+1, dim]`` on the time grid :attr:`times`.

        Without t–x coupling, GMR's mean is ``Σ_i h_i(t) μ_i^x`` with the responsibilities
        ``h_i(t)`` of the time marginal, which do not depend on θ: they are computed once
        (:meth:`GaussianMixture.responsibilities`) and the path is one matrix product.
        """
        centres = self._centres(theta)
        if self._activations is None or self._activations.dtype != theta.dtype:
            time_marginal = self.gmm(torch.zeros_like(theta[:1])).marginal([0])
            self._activations = time_marginal.responsibilities(
                self.times.to(theta.dtype).unsqueeze(-1).unsqueeze(-1)
            )[:, 0]  # [T+1, K]
        return self._activations @ centres

    def rollout(self, theta: Tensor, start: Tensor) -> Tensor:
        """Tip positions ``[B, T+1, dim]`` of the spring-damper, from rest at ``start: [dim]``."""
        attractor = self.attractor_path(theta)
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

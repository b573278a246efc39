"""Mountain car with a bang-bang feature policy (Bruno, Calinon & Caldwell 2013, Fig. 1 right)."""

from __future__ import annotations

import functools
import math

import torch
from dipole_torch.tasks.base import floating_dtype
from dipole_torch.tasks.control import (
    ControlTask,
    check_positive_int,
    choose_engine,
    compiled,
    single_threaded,
    start_distribution,
)
from torch import Tensor

__all__ = ["MountainCarTask"]


class MountainCarTask(ControlTask):
    r"""Drive an under-powered car out of a valley within ``steps`` steps.

    ## Description

    The mountain-car benchmark of the paper's section "Cart-pole and Mountain car benchmarks"
    (Bruno, Calinon & Caldwell, AAAI 2013), after Sutton & Barto (1998) "Reinforcement
    Learning: An Introduction", with the paper's constants: per step,

        ẍ = α u − β cos(3x),   ẋ ← clip(ẋ + ẍ, −0.07, 0.07),   x ← x + ẋ,

    with ``α = 0.001`` and ``β = 0.0055``. Full throttle (``α·4 = 0.004``) is weaker than the
    steepest slope (``β = 0.0055``): the car must swing back and forth to build up energy.
    The policy follows Strens & Moore (2002) as in the paper: the features
    ``φ(x) = [x, x², x ẋ, x ẋ²]`` and ``u = 4 · sign(θᵀφ)`` (eq. 8 followed by the
    full-forward / full-backward choice), so ``D = 4``. The policy is invariant to a positive
    rescaling of ``θ``.

    ``evaluate`` runs one episode per row of ``theta: [B, 4]``, on the CPU by default one
    at a time in Python floats, each stopping at the goal (``engine="python"``), else as a
    single batched torch rollout (``"torch"``; see ``engine`` below); the torch ``step``
    drives the gymnasium environment ``dipole/MountainCar-v0``
    (``dipole_torch.tasks.gym_envs.MountainCarEnv``).

    ## Action Space

    ``u ∈ {−4, +4}``: ``+4`` when ``θᵀφ ≥ 0`` (``sign(0)`` is taken as ``+``), else ``−4``.

    ## Observation Space

    | Num | Observation     | Unit        | Range          |
    |-----|-----------------|-------------|----------------|
    | 0   | Position x      | (arbitrary) | [−1.5, 1.5]    |
    | 1   | Velocity ẋ      | per step    | [−0.07, 0.07]  |

    ## Rewards

    The paper's counter: it starts at 101 and loses 1 per step until the goal is reached;
    the episode lasts at most 100 steps. Reaching the goal on step ``t`` (``1 ≤ t ≤ 100``)
    gives the return ``101 − t`` (in ``[1, 100]``); not reaching it gives ``0`` (the counter
    runs out). So returns lie in ``reward_range = (0, 100)``, the paper's "from 0 to 100"
    (the optimizers map them to eq. 6 weights with ``w = r / 100``, clamped to a small
    positive floor).

    ## Starting State

    ``x0 ~ U(−0.6, −0.4)`` (gymnasium's ``MountainCar-v0``) and ``ẋ0 = 0``. ``evaluate``
    draws one start per row from ``generator``; with ``generator=None`` every row starts from
    the same state, drawn once from the seed ``default_seed``. ``initial_state: [2]`` or
    ``[B, 2]`` overrides both.

    ## Episode End

    Success when ``x ≥ goal_position = 0.5``, which settles the return. Otherwise the episode
    stops after ``steps = 100`` steps.

    ## Arguments

    * ``steps``: maximum episode length (100).
    * ``goal_position``: the goal is ``x ≥ goal_position`` (0.5).
    * ``alpha``, ``beta``: engine and gravity constants (0.001, 0.0055).
    * ``theta0``: initial policy parameters, ``[4]`` (default zeros).
    * ``exploration_std``: standard deviations of the initial exploration, a number or
      ``[4]``; ``sigma_start = diag(exploration_std²)`` (default ``[1, 1, 10, 100]``).
    * ``default_seed``: seed of the start used when ``generator`` is ``None`` (0).
    * ``engine``: ``"python"`` (one episode at a time in Python floats, double precision,
      stopped at the goal), ``"torch"`` (one batched rollout in ``dtype`` on ``device``) or
      ``"auto"`` (the default: ``"torch"`` on an accelerator or with ``compile``, else
      ``"python"``).
    * ``compile``, ``chunk``: run the torch rollout in chunks of ``chunk`` (10) steps, each
      through ``torch.compile`` when ``compile`` is true (as
      ``dipole_torch.tasks.cartpole.CartPoleTask``).
    * ``device``: where torch rollouts run (``"cpu"``, ``"cuda"``, ...).
    * ``dtype``: the precision torch rollouts run in and returns are given in (float32; a
      floating dtype or its name, ``"float64"``; set in code, not a config key).

    ## Deviations from the paper

    * The paper both says "+100 at the goal" on top of an initial 101 and "returns range from
      0 to 100", which cannot both hold; we keep the range: return ``101 − t`` at the goal
      on step ``t``, ``0`` without it.

    ## Choices where the paper is silent

    * "Variables are reset when they exit their range": read as Sutton & Barto do it, the
      velocity is clipped to ``[−0.07, 0.07]``, and a position leaving ``[−1.5, 1.5]`` is put
      back on the bound with zero velocity (the car hits a wall).
    * The goal ``x ≥ 0.5`` (classic mountain car) sits just before the right hilltop at
      ``π/6 ≈ 0.524``. It is reachable in time: the policy ``θ = [1, 1, −10, −100]`` reaches
      it within 60 steps (return ≥ 41) from every start in ``[−0.6, −0.4]``. The left hilltop
      ``−π/2`` lies outside the range, so the left wall at ``−1.5`` is on the slope.
    * Start distribution as gymnasium's ``MountainCar-v0``.
    * ``theta0 = 0``: an uninformed policy, always full forward (``sign(0) = +``), which
      reaches the goal only from starts left of the valley floor ``−π/6`` (``x0 < −0.53``
      roughly; the default start ``x0 ≈ −0.406`` gives 0).
    * ``exploration_std = [1, 1, 10, 100]``, scaled to the size of each feature (``|x|, x² ≈
      1``, ``|x ẋ| ≈ 0.05``, ``|x ẋ²| ≈ 0.003``); about 4% of draws from
      ``N(theta0, sigma_start)`` reach the goal from random starts.

    Example:
        >>> import torch
        >>> task = MountainCarTask()
        >>> task.evaluate(torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, 1.0, -10.0, -100.0]]))
        tensor([ 0., 42.])
    """

    state_dim = 2
    min_position = -1.5  # position range (the paper's x ∈ (−1.5, 1.5))
    max_position = 1.5
    max_speed = 0.07  # per step (the paper's ẋ ∈ (−0.07, 0.07))
    force = 4.0  # the paper's u ∈ {−4, 4}

    def __init__(
        self,
        steps: int = 100,
        goal_position: float = 0.5,
        alpha: float = 0.001,
        beta: float = 0.0055,
        theta0: Tensor | list[float] | None = (0.0, 0.0, 0.0, 0.0),
        exploration_std: float | list[float] | Tensor = (1.0, 1.0, 10.0, 100.0),
        default_seed: int = 0,
        engine: str = "auto",
        compile: bool = False,
        chunk: int = 10,
        device: str | torch.device = "cpu",
        dtype: torch.dtype | str = torch.float32,
    ) -> None:
        check_positive_int(steps=steps, chunk=chunk)
        if not (math.isfinite(goal_position) and -0.4 < goal_position < self.max_position):
            raise ValueError(
                f"goal_position must be in (-0.4, {self.max_position}), beyond every start, "
                f"got {goal_position!r}"
            )
        for name, value in (("alpha", alpha), ("beta", beta)):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        self.steps = steps
        self.goal_position = float(goal_position)
        self.alpha = float(alpha)
        self.beta = float(beta)
        self.default_seed = int(default_seed)
        self.compile = bool(compile)
        self.chunk = chunk
        self.device = torch.device(device)
        self.engine = choose_engine(engine, self.device, self.compile)
        self.dtype = floating_dtype(dtype)
        self.reward_range = (0.0, float(steps))
        self.theta0, self.sigma_start = start_distribution(
            theta0, exploration_std, 4, self.device, self.dtype
        )

    # ------------------------------------------------------------------ dynamics
    def step(self, state: Tensor, force: Tensor) -> Tensor:
        """One step ``ẋ ← clip(ẋ + αu − β cos 3x)``, ``x ← x + ẋ``, walls at ``±1.5``.

        Args:
            state: ``[B, 2]`` states ``[x, ẋ]``.
            force: ``[B]`` forces, ``±4``.

        Returns:
            ``[B, 2]`` next states (``state`` is not modified).
        """
        x, velocity = state.clone().unbind(-1)
        self._step_(x, velocity, force.to(state.dtype))
        return torch.stack((x, velocity), dim=-1)

    def _step_(self, x: Tensor, velocity: Tensor, force: Tensor) -> None:
        """``step`` in place on ``x, velocity: [B]`` (the rollout's hot loop)."""
        velocity.add_(force, alpha=self.alpha).sub_(torch.cos(3 * x), alpha=self.beta)
        velocity.clamp_(-self.max_speed, self.max_speed)
        x.add_(velocity)
        outside = (x < self.min_position) | (x > self.max_position)  # hit a wall: stop there
        x.clamp_(self.min_position, self.max_position)
        velocity.masked_fill_(outside, 0.0)

    @staticmethod
    def features(state: Tensor) -> Tensor:
        """Strens & Moore's primitives ``φ = [x, x², x ẋ, x ẋ²]``: ``[B, 2] -> [B, 4]``."""
        x, velocity = state.unbind(-1)
        x_velocity = x * velocity
        return torch.stack((x, x * x, x_velocity, x_velocity * velocity), dim=-1)

    def policy(self, theta: Tensor, state: Tensor) -> Tensor:
        """``u = 4 · sign(θᵀφ(x))`` with ``sign(0) = +``: ``[B, 4], [B, 2] -> [B]``. The
        one-step form (the tests); ``evaluate`` computes the same in place, fused with
        the dynamics."""
        activation = (theta * self.features(state)).sum(-1)
        return torch.where(activation >= 0, self.force, -self.force).to(state.dtype)

    def at_goal(self, state: Tensor) -> Tensor:
        """``[B, 2] -> [B]`` bool: ``x ≥ goal_position``."""
        return state[..., 0] >= self.goal_position

    def sample_initial_state(
        self, batch_size: int, generator: torch.Generator | None = None
    ) -> Tensor:
        """``[batch_size, 2]`` starts: ``x0 ~ U(−0.6, −0.4)``, ``ẋ0 = 0``."""
        state = torch.zeros(batch_size, self.state_dim, device=self.device, dtype=self.dtype)
        u = torch.rand(batch_size, generator=generator, dtype=torch.float64)
        state[:, 0] = (-0.6 + 0.2 * u).to(self.device, self.dtype)
        return state

    # ------------------------------------------------------------------ episodes
    def evaluate(
        self,
        theta: Tensor,
        generator: torch.Generator | None = None,
        initial_state: Tensor | None = None,
    ) -> Tensor:
        """Run one episode of at most ``steps`` steps per policy; ``[B]`` returns in ``[0, 100]``.

        Args:
            theta: ``[B, 4]`` feature weights.
            generator: draws one random start per row; ``None`` starts every row from the
                same fixed state (seed ``default_seed``).
            initial_state: ``[2]`` or ``[B, 2]`` starts overriding ``generator``.
        """
        theta = self.check_theta(theta)
        batch_size = theta.shape[0]
        state = self._initial_states(batch_size, generator, initial_state)
        if initial_state is not None:
            x, velocity = state.T
            inside = (x >= self.min_position) & (x <= self.max_position)
            if not bool((inside & (velocity.abs() <= self.max_speed)).all()):
                raise ValueError(
                    f"initial_state must lie between the walls ({self.min_position}, "
                    f"{self.max_position}) at a speed within ±{self.max_speed}"
                )
        if self.engine == "python":
            return self._episodes(theta, state)
        with torch.inference_mode(), single_threaded(self.device, batch_size):
            x, velocity = state.T.contiguous().clone().unbind(0)
            gains = theta.T.contiguous().unbind(0)
            done = self.at_goal(state)  # bool [B]: the goal has been reached
            # Counted in integers: bfloat16 cannot count past 256 one by one.
            open_steps = torch.zeros_like(x, dtype=torch.int32)  # steps ended away from the goal
            advance = self._advance_
            if self.compile:
                advance = functools.partial(compiled(MountainCarTask._advance_), self)
            for start in range(0, self.steps, self.chunk):
                if done.all():
                    break  # every car is at the goal
                n = min(self.chunk, self.steps - start)
                x, velocity, done, open_steps = advance(n, x, velocity, *gains, done, open_steps)
            # Goal on step t = open_steps + 1: return 101 − t; never: 0.
            total = torch.where(done, self.steps - open_steps, torch.zeros_like(open_steps))
        return total.to(self.dtype).clamp(*self.reward_range)

    def _advance_(
        self,
        n: int,
        x: Tensor,
        velocity: Tensor,
        gain_x: Tensor,
        gain_x2: Tensor,
        gain_xv: Tensor,
        gain_xv2: Tensor,
        done: Tensor,
        open_steps: Tensor,
    ) -> tuple[Tensor, ...]:
        """``n`` steps of the rollout, policy and bookkeeping included (all ``[B]``).

        The policy is ``policy`` factored as ``θᵀφ = x (θ0 + θ1 x + ẋ (θ2 + θ3 ẋ))``.
        Cars at the goal keep moving, but their return is settled.
        """
        x, velocity, done, open_steps = (
            x.clone(),
            velocity.clone(),
            done.clone(),
            open_steps.clone(),
        )
        for _ in range(n):
            activation = torch.addcmul(gain_xv, gain_xv2, velocity).mul_(velocity)
            activation.addcmul_(gain_x2, x).add_(gain_x).mul_(x)
            force = torch.where(activation >= 0, self.force, -self.force)
            self._step_(x, velocity, force)
            done.logical_or_(x >= self.goal_position)
            open_steps.add_(~done)
        return x, velocity, done, open_steps

    def _episode(self, gains: list[float], start: list[float]) -> float:
        """One episode of the ``"python"`` engine: the policy of ``_advance_`` and the
        step of ``_step_`` in Python floats, stopped at the goal."""
        gain_x, gain_x2, gain_xv, gain_xv2 = gains
        x, velocity = start
        if x >= self.goal_position:
            return float(self.steps)  # at the goal before the first step
        cos, alpha, beta, force = math.cos, self.alpha, self.beta, self.force
        low, high, max_speed = self.min_position, self.max_position, self.max_speed
        for t in range(self.steps):
            # θᵀφ factored as x (θ0 + θ1 x + ẋ (θ2 + θ3 ẋ)), as in the torch rollout.
            activation = ((gain_xv + gain_xv2 * velocity) * velocity + gain_x2 * x + gain_x) * x
            velocity = velocity + alpha * (force if activation >= 0 else -force)
            velocity = velocity - beta * cos(3 * x)
            velocity = -max_speed if velocity < -max_speed else min(velocity, max_speed)
            x = x + velocity
            if x < low or x > high:  # hit a wall: stop there
                x, velocity = (low if x < low else high), 0.0
            if x >= self.goal_position:
                return float(self.steps - t)  # the goal on step t + 1: 101 − (t + 1)
        return 0.0

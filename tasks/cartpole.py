"""Cart-pole balancing with a linear policy (Bruno, Calinon & Caldwell 2013, Fig. 1 left)."""

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

__all__ = ["CartPoleTask"]


class CartPoleTask(ControlTask):
    r"""Balance a pole on a cart for ``steps`` time steps with the linear policy ``u = θᵀx``.

    ## Description

    The cart-pole benchmark of the paper's section "Cart-pole and Mountain car benchmarks"
    (Bruno, Calinon & Caldwell, AAAI 2013), on the classic Barto, Sutton & Anderson (1983)
    system "Neuronlike adaptive elements that can solve difficult learning control problems":
    a pole is hinged to a cart that moves along a frictionless track, and a horizontal force
    on the cart keeps the pole upright. The physics and constants are those of gymnasium's
    ``CartPole-v1`` (explicit Euler, ``tau = 0.02`` s; derivation in
    https://coneural.org/florian/papers/05_cart_pole.pdf). The policy is the paper's eq. 8,
    ``u = θᵀx`` with the state ``x`` itself as features, so ``D = 4``.

    ``evaluate`` runs one episode per row of ``theta: [B, 4]``, with one of two engines
    (``engine``): on the CPU by default one episode at a time in Python floats, each stopping
    when it fails (``"python"``); on an accelerator, or when asked, as a single batched torch
    rollout, a loop over time steps only (``"torch"``). The torch ``step`` and
    ``step_reward`` drive the gymnasium environment ``dipole/CartPole-v1``
    (``dipole_torch.tasks.gym_envs.CartPoleEnv``).

    ## Action Space

    A continuous horizontal force ``u = θᵀx`` in newtons, positive pushing the cart to the
    right, clipped to ``[-force_limit, force_limit]``.

    ## Observation Space

    | Num | Observation           | Unit  | Failure when outside |
    |-----|-----------------------|-------|----------------------|
    | 0   | Cart position x       | m     | ±``x_threshold`` (2.4) |
    | 1   | Cart velocity ẋ       | m/s   | -                    |
    | 2   | Pole angle φ          | rad   | ±``angle_threshold`` (12° ≈ 0.2094) |
    | 3   | Pole angular vel. φ̇   | rad/s | -                    |

    φ = 0 is upright; φ > 0 leans to the right (the direction of positive force).

    ## Rewards

    Per step, as in the paper: ``+1`` while the pole is within ``upright_angle = π/60`` (3°)
    of vertical, ``-1`` when the pole is falling or the cart is far from the origin (the
    episode has failed: ``|φ| > angle_threshold`` or ``|x| > x_threshold``), ``0`` otherwise.
    Failure is absorbing: from the step it happens on, every remaining step of the ``steps``
    is worth ``-1``. The return is the sum over ``steps`` steps, in
    ``reward_range = (-steps, steps) = (-1000, 1000)``.

    The optimizers turn returns into the positive weights of the paper's eq. 6 with the affine
    map ``w = (r - low) / (high - low)`` (clamped to a small positive floor) using
    ``reward_range``; a failure at the first step maps to the floor and 1000 balanced steps
    to 1.

    ## Starting State

    The cart at rest at the origin and the pole at rest at a random small angle
    ``φ0 ~ U(-initial_angle, initial_angle)`` with ``initial_angle = 0.05`` rad (gymnasium's
    range). ``evaluate`` draws one start per row from ``generator``; with
    ``generator=None`` every row starts from the same state, drawn once from the seed
    ``default_seed``, so that ``evaluate`` is a deterministic function of ``theta``.
    ``initial_state: [4]`` or ``[B, 4]`` overrides both.

    ## Episode End

    After ``steps = 1000`` steps (the paper's horizon). A failure does not end the rollout
    early, the step reward just stays ``-1`` (see Rewards). The gymnasium
    environment instead terminates at failure and pays the remaining ``-1`` rewards at once,
    so its undiscounted return equals ``evaluate``'s.

    ## Arguments

    * ``steps``: episode length (1000).
    * ``force_limit``: bound of the force in newtons (10, gymnasium's ``force_mag``).
    * ``initial_angle``: half-width of the initial-angle distribution in radians (0.05).
    * ``theta0``: initial policy parameters, ``[4]`` (default zeros: no control).
    * ``exploration_std``: standard deviations of the initial exploration, a number or ``[4]``;
      ``sigma_start = diag(exploration_std²)`` (default ``[1, 1, 20, 3]``).
    * ``default_seed``: seed of the start used when ``generator`` is ``None`` (0).
    * ``engine``: how ``evaluate`` runs the episodes, ``"python"``, ``"torch"`` or
      ``"auto"`` (the default; see below). In detail:

      - ``"python"``: one episode at a time, a plain Python loop over the steps in double
        precision (Python floats, whatever ``dtype``), stopped at the failure (the remaining
        steps are counted at -1). Eager torch pays a fixed overhead per tensor operation,
        a few dozen of them per step whatever the batch size, so on a CPU this is the fast
        engine up to batches of a few hundred episodes (``python
        benchmarks/bench_rollout.py`` measures both).
      - ``"torch"``: a single rollout of the whole batch in ``dtype`` on ``device``, the
        engine for large batches and for accelerators.
      - ``"auto"``: ``"torch"`` on an accelerator or with ``compile``, else ``"python"``.

      Both engines give each episode a return that does not depend on the rest of the batch.
      Their returns differ at most where a trajectory grazes a threshold (``dtype`` and
      rounding differ: torch's fused ``addcmul`` and vectorised sin/cos against libm's).
    * ``compile``: run the torch rollout through ``torch.compile`` (``False``). The time loop
      is cut in chunks of ``chunk`` (25) steps; compiled, a chunk becomes one fused kernel,
      which removes the per-op overhead that dominates small batches, at the price of a
      one-off compilation (cached by inductor afterwards). The maths is the same code,
      compiled or not.
    * ``device``: where torch rollouts run (``"cpu"``, ``"cuda"``, ...).
    * ``dtype``: the precision torch rollouts run in and returns are given in (float32; a
      floating dtype or its name, ``"float64"``; set in code, not a config key).

    ## Deviations from the paper

    * The paper does not say how "falling" is detected nor what happens afterwards; we use
      gymnasium's failure thresholds and make failure absorbing with ``-1`` per remaining
      step, so that the return is in ``[-1000, 1000]`` and balancing longer always pays.

    ## Choices where the paper is silent

    * Physics: gymnasium ``CartPole-v1`` constants (gravity 9.8 m/s², cart 1.0 kg, pole 0.1 kg,
      half-length 0.5 m, ``tau`` 0.02 s, explicit Euler).
    * The force ``θᵀx`` is clipped to ±10 N (gymnasium's ``force_mag``): a linear gain alone
      could push arbitrarily hard.
    * Only the pole angle is random at the start, ``U(-0.05, 0.05)`` rad; the rest is zero.
    * ``theta0 = 0`` (no control: the pole falls within about 1.5 s; return -966 from the
      default start) and
      ``exploration_std = [1, 1, 20, 3]`` (scaled to the typical size of each state variable
      so that a random draw sometimes stabilises the pole; LQR-like gains are ≈ ``[1, 2, 30, 5]``).

    Example:
        >>> import torch
        >>> task = CartPoleTask()
        >>> task.evaluate(torch.tensor([[0.0, 0.0, 0.0, 0.0], [1.0, 2.0, 30.0, 5.0]]))
        tensor([-966., 1000.])
    """

    gravity = 9.8  # m/s²
    masscart = 1.0  # kg
    masspole = 0.1  # kg
    total_mass = masspole + masscart  # kg
    length = 0.5  # m, half the pole's length
    polemass_length = masspole * length  # kg·m
    tau = 0.02  # seconds between state updates (explicit Euler)
    x_threshold = 2.4  # m, the cart is "far from the origin" beyond it
    angle_threshold = 12 * 2 * math.pi / 360  # rad, the pole is "falling" beyond it
    upright_angle = math.pi / 60  # rad, the pole is "vertical" within it (the paper's π/60)

    state_dim = 4

    def __init__(
        self,
        steps: int = 1000,
        force_limit: float = 10.0,
        initial_angle: float = 0.05,
        theta0: Tensor | list[float] | None = (0.0, 0.0, 0.0, 0.0),
        exploration_std: float | list[float] | Tensor = (1.0, 1.0, 20.0, 3.0),
        default_seed: int = 0,
        engine: str = "auto",
        compile: bool = False,
        chunk: int = 25,
        device: str | torch.device = "cpu",
        dtype: torch.dtype | str = torch.float32,
    ) -> None:
        check_positive_int(steps=steps, chunk=chunk)
        if not (math.isfinite(force_limit) and force_limit > 0):
            raise ValueError(f"force_limit must be a positive finite number, got {force_limit!r}")
        if not (math.isfinite(initial_angle) and 0 <= initial_angle < self.angle_threshold):
            raise ValueError(
                f"initial_angle must be in [0, {self.angle_threshold:.4f}) rad, "
                f"got {initial_angle!r}"
            )
        self.steps = steps
        self.force_limit = float(force_limit)
        self.initial_angle = float(initial_angle)
        self.default_seed = int(default_seed)
        self.compile = bool(compile)
        self.chunk = chunk
        self.device = torch.device(device)
        self.engine = choose_engine(engine, self.device, self.compile)
        self.dtype = floating_dtype(dtype)
        self.reward_range = (-float(steps), float(steps))
        self.theta0, self.sigma_start = start_distribution(
            theta0, exploration_std, self.state_dim, self.device, self.dtype
        )

    # ------------------------------------------------------------------ dynamics
    def step(self, state: Tensor, force: Tensor) -> Tensor:
        """One explicit-Euler step of the cart-pole physics (gymnasium ``CartPole-v1``).

        Args:
            state: ``[B, 4]`` states ``[x, ẋ, φ, φ̇]``.
            force: ``[B]`` forces in newtons (already clipped).

        Returns:
            ``[B, 4]`` next states (``state`` is not modified).
        """
        x, x_dot, angle, angle_dot = state.clone().unbind(-1)
        self._step_(x, x_dot, angle, angle_dot, force.to(state.dtype))
        return torch.stack((x, x_dot, angle, angle_dot), dim=-1)

    def _step_(self, x: Tensor, x_dot: Tensor, angle: Tensor, angle_dot: Tensor, force: Tensor):
        """``step`` in place on the four ``[B]`` state variables (the rollout's hot loop).

        The equations of Florian (2007), https://coneural.org/florian/papers/05_cart_pole.pdf,
        as written in gymnasium's ``CartPole-v1``::

            temp  = (u + m_p l φ̇² sin φ) / M
            φ̈     = (g sin φ − cos φ · temp) / (l (4/3 − m_p cos² φ / M))
            ẍ     = temp − m_p l φ̈ cos φ / M

        followed by explicit Euler with ``tau``. Written with in-place ops to avoid per-step
        allocations; the arithmetic is the same.
        """
        cos = torch.cos(angle)
        sin = torch.sin(angle)
        temp = angle_dot * angle_dot  # temp = (u + m_p l φ̇² sin φ) / M
        temp.mul_(sin).mul_(self.polemass_length).add_(force).div_(self.total_mass)
        denominator = cos * cos  # l (4/3 − m_p cos² φ / M)
        denominator.mul_(-self.masspole / self.total_mass).add_(4.0 / 3.0).mul_(self.length)
        angle_acc = sin.mul_(self.gravity)  # φ̈ = (g sin φ − cos φ temp) / denominator
        angle_acc.addcmul_(cos, temp, value=-1.0).div_(denominator)
        x_acc = temp.addcmul_(angle_acc, cos, value=-self.polemass_length / self.total_mass)
        x.add_(x_dot, alpha=self.tau)
        x_dot.add_(x_acc, alpha=self.tau)
        angle.add_(angle_dot, alpha=self.tau)
        angle_dot.add_(angle_acc, alpha=self.tau)

    def policy(self, theta: Tensor, state: Tensor) -> Tensor:
        """Eq. 8, ``u = θᵀx`` clipped to ``±force_limit``: ``[B, 4], [B, 4] -> [B]``. The
        one-step form (a gymnasium policy, the tests); ``evaluate`` computes the same
        in place, fused with the dynamics."""
        return (theta * state).sum(-1).clamp(-self.force_limit, self.force_limit)

    def failed(self, state: Tensor) -> Tensor:
        """``[B, 4] -> [B]`` bool: the pole is falling or the cart is far from the origin."""
        return (state[..., 0].abs() > self.x_threshold) | (
            state[..., 2].abs() > self.angle_threshold
        )

    def step_reward(self, state: Tensor, failed: Tensor) -> Tensor:
        """The paper's per-step reward of ``state: [B, 4]`` given ``failed: [B]``: ``[B]``."""
        upright = (state[..., 2].abs() < self.upright_angle).to(state.dtype)
        return torch.where(failed, -torch.ones_like(upright), upright)

    def sample_initial_state(
        self, batch_size: int, generator: torch.Generator | None = None
    ) -> Tensor:
        """``[batch_size, 4]`` starts: at rest, pole angle ``U(-initial_angle, initial_angle)``."""
        state = torch.zeros(batch_size, self.state_dim, device=self.device, dtype=self.dtype)
        u = torch.rand(batch_size, generator=generator, dtype=torch.float64)
        state[:, 2] = ((2 * u - 1) * self.initial_angle).to(self.device, self.dtype)
        return state

    # ------------------------------------------------------------------ episodes
    def evaluate(
        self,
        theta: Tensor,
        generator: torch.Generator | None = None,
        initial_state: Tensor | None = None,
    ) -> Tensor:
        """Run one ``steps``-long episode per policy; returns ``[B]`` in ``reward_range``.

        Args:
            theta: ``[B, 4]`` linear policy gains.
            generator: draws one random start per row; ``None`` starts every row from the
                same fixed state (seed ``default_seed``).
            initial_state: ``[4]`` or ``[B, 4]`` starts overriding ``generator``.
        """
        theta = self.check_theta(theta)
        state = self._initial_states(theta.shape[0], generator, initial_state)
        if self.engine == "python":
            return self._episodes(theta, state)
        with torch.inference_mode(), single_threaded(self.device, theta.shape[0]):
            x, x_dot, angle, angle_dot = state.T.contiguous().clone().unbind(0)
            gains = theta.T.contiguous().unbind(0)
            alive = ~self.failed(state)  # bool [B]: no failure so far
            # Counted in integers: float16 and bfloat16 cannot count to 5000 one by one.
            upright_steps = torch.zeros_like(x, dtype=torch.int32)  # within π/60, alive
            alive_steps = torch.zeros_like(x, dtype=torch.int32)  # steps before the failing one
            advance = self._advance_
            if self.compile:
                advance = functools.partial(compiled(CartPoleTask._advance_), self)
            for start in range(0, self.steps, self.chunk):
                if not alive.any():
                    break  # every episode has failed: the remaining steps are all -1
                n = min(self.chunk, self.steps - start)
                x, x_dot, angle, angle_dot, alive, upright_steps, alive_steps = advance(
                    n, x, x_dot, angle, angle_dot, *gains, alive, upright_steps, alive_steps
                )
            # +1 per upright step, -1 per step from the failure on, 0 otherwise.
            total = upright_steps - (self.steps - alive_steps)
        return total.to(self.dtype)

    def _advance_(
        self,
        n: int,
        x: Tensor,
        x_dot: Tensor,
        angle: Tensor,
        angle_dot: Tensor,
        gain_x: Tensor,
        gain_x_dot: Tensor,
        gain_angle: Tensor,
        gain_angle_dot: Tensor,
        alive: Tensor,
        upright_steps: Tensor,
        alive_steps: Tensor,
    ) -> tuple[Tensor, ...]:
        """``n`` steps of the rollout, policy and reward bookkeeping included (all ``[B]``).

        Failed episodes keep integrating, but failure is absorbing: their state no longer
        matters (every remaining step is worth -1). Returns the updated tensors.

        The loop records the cart position and pole angle of every step, and the failure
        and upright tests run once over the ``[n, B]`` record: ten per-step tensor ops fewer
        (eager torch's per-op overhead is the cost of a small batch), the same counts.
        """
        x, x_dot, angle, angle_dot = x.clone(), x_dot.clone(), angle.clone(), angle_dot.clone()
        positions = x.new_empty(n, x.shape[0])
        angles = x.new_empty(n, x.shape[0])
        for t in range(n):
            force = gain_x * x  # the policy, eq. 8: u = clip(θᵀx)
            force.addcmul_(gain_x_dot, x_dot).addcmul_(gain_angle, angle)
            force.addcmul_(gain_angle_dot, angle_dot).clamp_(-self.force_limit, self.force_limit)
            self._step_(x, x_dot, angle, angle_dot, force)
            positions[t].copy_(x)
            angles[t].copy_(angle)
        angle_magnitude = angles.abs()
        inside = (positions.abs() <= self.x_threshold) & (angle_magnitude <= self.angle_threshold)
        # alive after step t: alive before the chunk and inside at every step up to t.
        alive_after = inside.to(torch.uint8).cumprod(0).bool() & alive
        upright = alive_after & (angle_magnitude < self.upright_angle)
        alive_steps = alive_steps + alive_after.sum(0)
        upright_steps = upright_steps + upright.sum(0)
        return x, x_dot, angle, angle_dot, alive_after[-1], upright_steps, alive_steps

    def _episode(self, gains: list[float], start: list[float]) -> float:
        """One episode of the ``"python"`` engine: the equations of ``_step_`` and the
        policy and rewards of ``_advance_``, in Python floats, stopped at the failure."""
        gain_x, gain_x_dot, gain_angle, gain_angle_dot = gains
        x, x_dot, angle, angle_dot = start
        if abs(x) > self.x_threshold or abs(angle) > self.angle_threshold:
            return -float(self.steps)  # failed before the first step
        cos, sin = math.cos, math.sin
        limit, tau, gravity, length = self.force_limit, self.tau, self.gravity, self.length
        total_mass, polemass_length = self.total_mass, self.polemass_length
        mass_ratio = -self.masspole / self.total_mass
        x_acc_scale = -self.polemass_length / self.total_mass
        x_limit, angle_limit = self.x_threshold, self.angle_threshold
        upright_angle = self.upright_angle
        upright = 0
        for t in range(self.steps):
            force = gain_x * x + gain_x_dot * x_dot + gain_angle * angle
            force = force + gain_angle_dot * angle_dot
            force = -limit if force < -limit else (limit if force > limit else force)
            cos_angle, sin_angle = cos(angle), sin(angle)
            temp = (angle_dot * angle_dot * sin_angle * polemass_length + force) / total_mass
            denominator = (cos_angle * cos_angle * mass_ratio + 4.0 / 3.0) * length
            angle_acc = (sin_angle * gravity - cos_angle * temp) / denominator
            x_acc = temp + x_acc_scale * angle_acc * cos_angle
            x, x_dot = x + tau * x_dot, x_dot + tau * x_acc
            angle, angle_dot = angle + tau * angle_dot, angle_dot + tau * angle_acc
            if not (abs(x) <= x_limit and abs(angle) <= angle_limit):  # (NaN: failed)
                # Failed on step t: -1 for it and for every step after it.
                return float(upright - (self.steps - t))
            if abs(angle) < upright_angle:
                upright += 1
        return float(upright)

"""Gymnasium environments for the classic-control tasks, registered on
``import dipole_torch.tasks``.

| id                        | class                   | max_episode_steps | reward_threshold |
|---------------------------|-------------------------|-------------------|------------------|
| ``dipole/CartPole-v1``    | ``CartPoleEnv``    | 1000              | 950              |
| ``dipole/MountainCar-v0`` | ``MountainCarEnv`` | 100               | 50               |

Each environment steps a batch of one state through its task's own torch physics
(``dipole_torch.tasks.cartpole.CartPoleTask.step``,
``dipole_torch.tasks.mountain_car.MountainCarTask.step``): there is no second copy of the
dynamics, and a policy run in the environment earns the same undiscounted return as the task's
``evaluate`` from the same start (pass it with
``reset(options={"initial_state": ...})``): bit for bit as its ``engine="torch"`` rollout, and as
its default Python episodes (double precision) but where rounding moves a trajectory across a
threshold. Keyword arguments of ``gymnasium.make`` go to the task's constructor (``steps``,
``force_limit``, ``dtype``, ...), except ``render_mode``.

The registered ``max_episode_steps`` (gymnasium's ``TimeLimit``) is the task's horizon, the
paper's, and ``reward_threshold`` the mean return that counts as solved (each class says how it
was chosen); both are for the default task. An environment made with ``steps=N`` ends its
episodes after ``N`` steps by itself, but gymnasium's ``TimeLimit`` still cuts them at the
registered horizon: for ``N`` beyond it, pass ``max_episode_steps=N`` to ``gymnasium.make`` as
well (``steps=200`` alone cut mountain car's episodes at 100, before its end's penalty: a
policy that never reaches the goal returned 101).

Rendering: ``render_mode="rgb_array"`` returns each frame as an RGB ``uint8`` array
``[400, 600, 3]``, drawn with numpy (``dipole_torch.tasks.rendering``, no extra
dependency), so gymnasium's ``RecordVideo`` wrapper (which needs moviepy) and
``RenderCollection`` work, and so does ``render_mode="rgb_array_list"`` (``gymnasium.make``
adds ``RenderCollection``). ``render_mode="human"`` shows the frames in a pygame window during
``reset`` and ``step``; it needs pygame and a display, and is refused at construction where
either is missing. ``metadata["render_fps"]`` is one frame a step at the task's time step.
Drawing reads the state only: returns and observations are the same whatever the mode.

``gymnasium.utils.env_checker.check_env`` passes on both without a warning
(``tests/test_gym_envs.py``).
"""

from __future__ import annotations

import math
from typing import Any

import gymnasium as gym
import numpy as np
import torch
from dipole_torch.tasks.cartpole import CartPoleTask
from dipole_torch.tasks.mountain_car import MountainCarTask
from dipole_torch.tasks.rendering import (
    FRAME_HEIGHT,
    FRAME_WIDTH,
    Window,
    cartpole_frame,
    mountain_car_frame,
)
from gymnasium import spaces

__all__ = ["CartPoleEnv", "MountainCarEnv", "register_envs"]

BOUND_MARGIN = 1e-3  # relative slack on derived bounds, for float32 rounding of the dynamics


class _TaskEnv(gym.Env):
    """Shared reset, rendering and episode bookkeeping: a ``[1, S]`` torch state advanced by
    the task's ``step``."""

    metadata: dict[str, Any] = {"render_modes": []}
    task: CartPoleTask | MountainCarTask
    start_space: spaces.Box  # where reset(options={"initial_state": ...}) may start
    _start_space_meaning: str  # start_space in words, for the error message

    def __init__(self, render_mode: str | None = None) -> None:
        valid = self.metadata["render_modes"]
        if render_mode is not None and render_mode not in valid:
            raise ValueError(
                f"render_mode must be None or one of {', '.join(map(repr, valid))}, "
                f"got {render_mode!r}"
            )
        self.render_mode = render_mode
        self._window = None
        if render_mode == "human":
            self._window = Window(
                type(self).__name__, FRAME_WIDTH, FRAME_HEIGHT, self.metadata["render_fps"]
            )
        self._state: torch.Tensor | None = None
        self._t = 0
        self._ended = False

    def _observation(self) -> np.ndarray:
        assert self._state is not None
        return self._state[0].to(torch.float32).numpy().copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; ``options={"initial_state": [S]}`` sets the start exactly (it must
        lie in ``start_space``)."""
        super().reset(seed=seed)
        options = options or {}
        unknown = set(options) - {"initial_state"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; only 'initial_state'")
        if options.get("initial_state") is not None:
            initial = np.asarray(options["initial_state"], dtype=np.float64)
            if initial.shape != (self.task.state_dim,):
                raise ValueError(
                    f"initial_state must have shape [{self.task.state_dim}], "
                    f"got {list(initial.shape)}"
                )
            low, high = self.start_space.low, self.start_space.high
            if not (np.all(initial >= low) and np.all(initial <= high)):
                raise ValueError(
                    f"initial_state must lie in start_space, [{_format(low)}] to "
                    f"[{_format(high)}] ({self._start_space_meaning}), got [{_format(initial)}]"
                )
            self._state = self.task._initial_states(1, None, torch.from_numpy(initial))
        else:
            generator = torch.Generator().manual_seed(int(self.np_random.integers(2**62)))
            self._state = self.task.sample_initial_state(1, generator)
        self._t = 0
        self._ended = False
        if self.render_mode == "human":
            self.render()
        return self._observation(), {}

    def _advance(self, force: float) -> None:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        if self._ended:
            raise RuntimeError("the episode has ended (terminated or truncated): call reset()")
        force_tensor = torch.tensor([force], dtype=self.task.dtype)
        with torch.inference_mode():
            self._state = self.task.step(self._state, force_tensor)
        self._t += 1

    def _finish_step(
        self, reward: float, terminated: bool, truncated: bool
    ) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        self._ended = terminated or truncated
        if self.render_mode == "human":
            self.render()
        return self._observation(), reward, terminated, truncated, {}

    def render(self) -> np.ndarray | None:
        """The current state drawn as an RGB ``uint8`` array ``[400, 600, 3]``
        (``"rgb_array"``), or shown in the window (``"human"``, returns ``None``)."""
        if self.render_mode is None:
            name = self.spec.id if self.spec is not None else type(self).__name__
            gym.logger.warn(
                "render() was called without a render_mode; make the environment with one, "
                f'e.g. gymnasium.make("{name}", render_mode="rgb_array")'
            )
            return None
        if self._state is None:
            raise RuntimeError("call reset() before render()")
        frame = self._draw(self._state[0].tolist())
        if self._window is not None:
            self._window.show(frame)
            return None
        return frame

    def _draw(self, state: list[float]) -> np.ndarray:
        raise NotImplementedError

    def close(self) -> None:
        if self._window is not None:
            self._window.close()
        super().close()


def _format(values: np.ndarray) -> str:
    return ", ".join(f"{float(value):.6g}" for value in values)


def _cartpole_bounds(task: CartPoleTask) -> tuple[np.ndarray, np.ndarray]:
    """``(live, reached)``, each ``[4]``: the half-widths of the start box and the bounds on
    every observation of an episode started in it (derivation in ``CartPoleEnv``)."""
    tau = task.tau
    sin_max = math.sin(task.angle_threshold)
    # l (4/3 - m_p cos²φ / M) >= l (4/3 - m_p / M), the denominator of the angular acceleration.
    denominator = task.length * (4.0 / 3.0 - task.masspole / task.total_mass)

    def temp_max(angle_velocity: float) -> float:  # |(u + m_p l φ̇² sin φ) / M|
        return (
            task.force_limit + task.polemass_length * angle_velocity**2 * sin_max
        ) / task.total_mass

    def angle_acc_max(angle_velocity: float) -> float:  # |φ̈|
        return (task.gravity * sin_max + temp_max(angle_velocity)) / denominator

    def x_acc_max(angle_velocity: float) -> float:  # |ẍ|
        return (
            temp_max(angle_velocity)
            + task.polemass_length * angle_acc_max(angle_velocity) / task.total_mass
        )

    live_x, live_angle = task.x_threshold, task.angle_threshold
    live_x_dot, live_angle_dot = 2 * live_x / tau, 2 * live_angle / tau
    last_x_dot = live_x_dot + tau * x_acc_max(live_angle_dot)  # the last live state
    last_angle_dot = live_angle_dot + tau * angle_acc_max(live_angle_dot)
    reached = np.array(
        [
            live_x + tau * last_x_dot,
            last_x_dot + tau * x_acc_max(last_angle_dot),
            live_angle + tau * last_angle_dot,
            last_angle_dot + tau * angle_acc_max(last_angle_dot),
        ]
    )
    live = np.array([live_x, live_x_dot, live_angle, live_angle_dot])
    return live, reached * (1 + BOUND_MARGIN)


class CartPoleEnv(_TaskEnv):
    r"""``dipole_torch.tasks.cartpole.CartPoleTask`` as the gymnasium environment
    ``dipole/CartPole-v1``.

    ## Description

    The cart-pole benchmark of Bruno, Calinon & Caldwell, "Bayesian Nonparametric
    Multi-Optima Policy Search in Reinforcement Learning" (AAAI 2013), on the Barto, Sutton &
    Anderson (1983) system: a pole hinged to a cart on a frictionless track, kept upright by a
    horizontal force on the cart. The physics is the task's (gymnasium ``CartPole-v1``'s
    equations and constants, explicit Euler with ``tau = 0.02`` s), run by
    ``step``; the rewards are the paper's.

    ## Action Space

    ``Box(-1, 1, (1,), float32)``: the push, as a fraction of the task's ``force_limit``
    (10 N): the force on the cart is ``a · force_limit`` newtons, positive to the right.
    Actions outside ``[-1, 1]`` are clipped; a non-finite action is refused. The linear policy
    of the paper, ``u = θᵀx`` newtons, is the action ``θᵀx / force_limit``.

    ## Observation Space

    ``[x, ẋ, φ, φ̇]`` (float32), ``φ = 0`` upright and ``φ > 0`` leaning right:

    | Num | Observation          | Unit  | Episode fails outside | ``observation_space`` |
    |-----|----------------------|-------|-----------------------|-----------------------|
    | 0   | Cart position x      | m     | ±2.4                  | ≈ ±7.21               |
    | 1   | Cart velocity ẋ      | m/s   | -                     | ≈ ±240.8              |
    | 2   | Pole angle φ         | rad   | ±0.2094 (12°)         | ≈ ±0.639              |
    | 3   | Pole angular vel. φ̇  | rad/s | -                     | ≈ ±21.96              |

    The bounds hold for every observation of an episode started in ``start_space`` (see
    Starting State), the failing one included; they are loose, since they do not use the
    trajectory. Until the episode fails the cart and pole stay within the thresholds,
    ``|x| ≤ 2.4`` and ``|φ| ≤ 12°``, and an explicit Euler step moves the position by ``τ``
    times the velocity, so a state followed by another live one has ``|ẋ| ≤ 2 · 2.4 / τ``
    and ``|φ̇| ≤ 2 · 12° / τ``. The accelerations of a live state are bounded given ``|φ̇|``
    (the force by ``force_limit``, ``sin φ`` by ``sin 12°``, the denominator of ``φ̈`` from
    below by ``l (4/3 − m_p / M)``), so the last live state and the failing one are at most
    one and two steps of bounded acceleration away: the position bounds are ``2.4 + τ V``
    and ``12° + τ W``, with ``V`` and ``W`` the velocity bounds of the last live state. They
    are computed from the task's attributes (another ``force_limit`` gives other bounds) and
    widened by 0.1% for float32 rounding.

    ## Rewards

    The paper's ``+1`` while the pole is within ``π/60`` of vertical, ``0`` while it is
    farther but the episode has not failed, and ``-1`` at failure (``|φ| > 12°`` or
    ``|x| > 2.4`` m). Failure is absorbing in the task (``-1`` for every remaining step); the
    environment terminates at the failing step ``t`` and pays ``-(steps - t + 1)`` for it,
    the task's ``-1`` for that step and each remaining one, so that the undiscounted return
    equals ``evaluate``'s, in
    ``[-steps, steps]``.

    ``spec.reward_threshold = 950`` (for the default 1000 steps): gymnasium's ``CartPole-v1``
    counts 475 of its 500-step maximum, 95%, as solved, and 950 is 95% of this task's
    1000-step maximum. An episode
    earning it kept the pole within ``π/60`` for at least 950 steps and did not fail before
    step 976 (failing on step ``t`` leaves at most ``2t − 1002``).

    ## Starting State

    At rest at the origin with the pole at ``φ0 ~ U(−0.05, 0.05)`` rad (the task's
    ``sample_initial_state``, seeded by ``reset(seed=...)``), or exactly
    ``reset(options={"initial_state": [x, ẋ, φ, φ̇]})``, which must lie in ``start_space``:
    a live state, ``|x| ≤ 2.4`` and ``|φ| ≤ 12°``, with ``|ẋ| ≤ 2 · 2.4 / τ`` and
    ``|φ̇| ≤ 2 · 12° / τ``, the region the observation bounds are derived from.

    ## Episode End

    Terminated at failure (``|φ| > 12°`` or ``|x| > 2.4`` m); truncated after the task's
    ``steps`` steps (the paper's 1000, ``spec.max_episode_steps``). Stepping an ended episode
    raises: call ``reset()``.

    ## Arguments

    * ``render_mode``: ``None``, ``"rgb_array"`` or ``"human"`` (``"rgb_array_list"`` through
      ``gymnasium.make``).
    * Every other keyword goes to ``CartPoleTask``:
      ``steps`` (1000), ``force_limit`` (10 N), ``initial_angle`` (0.05 rad), ``dtype`` of the
      physics (float32), ... The task runs on the CPU.

    ## Rendering

    A frame is 600 × 400 pixels, as gymnasium's ``CartPole-v1`` draws it: the track spans the
    image between the failure thresholds, the cart is a black box on it and the pole a brown
    bar leaning by ``φ`` (a cart beyond a threshold leaves the picture).
    ``metadata["render_fps"] = 1 / tau = 50``: a recorded episode plays in real time, and
    ``"human"`` shows the frames in a pygame window at that rate (it needs pygame and a
    display, and is refused at construction without them).

    Example:
        >>> import gymnasium as gym
        >>> import numpy as np
        >>> import dipole_torch.tasks  # registers the environments
        >>> env = gym.make("dipole/CartPole-v1", render_mode="rgb_array")
        >>> env.spec.max_episode_steps, env.spec.reward_threshold
        (1000, 950.0)
        >>> observation, info = env.reset(seed=0)
        >>> gains = np.array([0.91, 2.14, 30.9, 7.9]) / 10  # u = θᵀx newtons, over force_limit
        >>> observation, reward, terminated, truncated, info = env.step([gains @ observation])
        >>> reward, terminated, env.render().shape
        (1.0, False, (400, 600, 3))
    """

    metadata: dict[str, Any] = {
        "render_modes": ["human", "rgb_array"],
        "render_fps": round(1 / CartPoleTask.tau),
    }

    def __init__(self, render_mode: str | None = None, **task_kwargs: Any) -> None:
        self.task = CartPoleTask(device="cpu", **task_kwargs)
        super().__init__(render_mode)
        self.action_space = spaces.Box(-1.0, 1.0, shape=(1,), dtype=np.float32)
        live, reached = _cartpole_bounds(self.task)
        self.start_space = spaces.Box(-live, live, dtype=np.float64)
        self._start_space_meaning = "a live state with the speeds the observation bounds allow"
        high = reached.astype(np.float32)
        high = np.where(high < reached, np.nextafter(high, np.float32(np.inf)), high)
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        push = np.asarray(action, dtype=np.float64)
        if push.size != 1:
            raise ValueError(f"action must hold one number, got shape {list(push.shape)}")
        push = float(push.reshape(-1)[0])
        if not math.isfinite(push):
            raise ValueError(f"action must be finite, got {action!r}")
        self._advance(min(max(push, -1.0), 1.0) * self.task.force_limit)
        assert self._state is not None
        failed = self.task.failed(self._state)
        reward = float(self.task.step_reward(self._state, failed)[0])
        terminated = bool(failed[0])
        if terminated:
            reward = -float(self.task.steps - self._t + 1)
        truncated = not terminated and self._t >= self.task.steps
        return self._finish_step(reward, terminated, truncated)

    def _draw(self, state: list[float]) -> np.ndarray:
        return cartpole_frame(self.task, state)


class MountainCarEnv(_TaskEnv):
    r"""``dipole_torch.tasks.mountain_car.MountainCarTask`` as the gymnasium environment
    ``dipole/MountainCar-v0``.

    ## Description

    The mountain-car benchmark of Bruno, Calinon & Caldwell, "Bayesian Nonparametric
    Multi-Optima Policy Search in Reinforcement Learning" (AAAI 2013), after Sutton & Barto
    (1998), with the paper's constants: an under-powered car in a valley must swing back and
    forth to climb out to the goal, per step ``ẋ ← clip(ẋ + α u − β cos 3x, ±0.07)``,
    ``x ← x + ẋ``, walls at ``±1.5``
    (``step``).

    ## Action Space

    ``Discrete(2)``: ``0`` full backward (``u = −4``), ``1`` full forward (``u = +4``), the
    paper's bang-bang control. The paper's policy ``u = 4 · sign(θᵀφ(x))`` is the action
    ``int(θᵀφ(x) ≥ 0)``.

    ## Observation Space

    ``[x, ẋ]`` (float32), bounded by the dynamics themselves:

    | Num | Observation | Unit        | ``observation_space``                 |
    |-----|-------------|-------------|---------------------------------------|
    | 0   | Position x  | (arbitrary) | [−1.5, 1.5] (a wall stops the car)    |
    | 1   | Velocity ẋ  | per step    | [−0.07, 0.07] (clipped every step)    |

    ## Rewards

    The paper's counter paid step by step: it starts at 101, paid with the first step, and
    loses 1 per step (first step ``+100``, then ``−1``); not reaching the goal by step
    ``steps`` (100) costs one more point. Returns are ``101 − t`` at the goal on step ``t``,
    else ``0``, as ``evaluate``'s.

    ``spec.reward_threshold = 50`` (for the default 100 steps): the goal reached, on average,
    by step 51, in the first half of the horizon. It asks for what gymnasium's
    ``MountainCar-v0`` asks with its −110 (the goal within 110 of its 200 steps): an
    efficient swing, not just getting there. Backing up for the right few steps, then
    driving forward, earns more than 50 from every start.

    ## Starting State

    ``x0 ~ U(−0.6, −0.4)``, ``ẋ0 = 0`` (the task's ``sample_initial_state``, seeded by
    ``reset(seed=...)``), or exactly ``reset(options={"initial_state": [x, ẋ]})`` anywhere
    in ``start_space``: the observation space short of the goal (``x < goal_position``).

    ## Episode End

    Terminated at the goal (``x ≥ goal_position = 0.5``); truncated after the task's
    ``steps`` steps (the paper's 100, ``spec.max_episode_steps``). Stepping an ended episode
    raises: call ``reset()``.

    ## Arguments

    * ``render_mode``: ``None``, ``"rgb_array"`` or ``"human"`` (``"rgb_array_list"`` through
      ``gymnasium.make``).
    * Every other keyword goes to ``MountainCarTask``:
      ``steps`` (100), ``goal_position`` (0.5), ``alpha``, ``beta``, ``dtype`` of the physics
      (float32), ... The task runs on the CPU.

    ## Rendering

    A frame is 600 × 400 pixels, laid out as gymnasium's ``MountainCar-v0`` draws it: the road
    ``0.45 sin(3x)`` (the hill the gravity term ``−β cos 3x`` comes down from) over the whole
    position range, with a wall at each end, the valley floor at ``x = −π/6``, a yellow flag
    at the goal and the car tilted with the road. The dynamics count in steps, with no time
    step in seconds: ``metadata["render_fps"] = 30``, gymnasium's ``MountainCar-v0`` rate for
    the same per-step formulation. ``"human"`` shows the frames in a pygame window at that
    rate (it needs pygame and a display, and is refused at construction without them).

    Example:
        >>> import gymnasium as gym
        >>> import dipole_torch.tasks  # registers the environments
        >>> env = gym.make("dipole/MountainCar-v0", render_mode="rgb_array")
        >>> env.spec.max_episode_steps, env.spec.reward_threshold
        (100, 50.0)
        >>> observation, info = env.reset(seed=0)
        >>> observation, reward, terminated, truncated, info = env.step(1)
        >>> reward, terminated, env.render().dtype
        (100.0, False, dtype('uint8'))
    """

    metadata: dict[str, Any] = {"render_modes": ["human", "rgb_array"], "render_fps": 30}

    def __init__(self, render_mode: str | None = None, **task_kwargs: Any) -> None:
        self.task = MountainCarTask(device="cpu", **task_kwargs)
        super().__init__(render_mode)
        self.action_space = spaces.Discrete(2)
        low = np.array([self.task.min_position, -self.task.max_speed], dtype=np.float32)
        high = np.array([self.task.max_position, self.task.max_speed], dtype=np.float32)
        self.observation_space = spaces.Box(low, high, dtype=np.float32)
        # Short of the goal as the physics' dtype compares it: a start at the goal has no
        # episode (the task counts it as reached before the first step).
        goal = torch.tensor(self.task.goal_position, dtype=self.task.dtype)
        if goal.dtype == torch.bfloat16:  # (numpy has no bfloat16: a step of its epsilon)
            short_of_goal = float(goal - torch.finfo(goal.dtype).eps * goal.abs())
        else:
            short_of_goal = float(np.nextafter(goal.numpy(), -np.inf))
        self.start_space = spaces.Box(
            np.array([self.task.min_position, -self.task.max_speed]),
            np.array([short_of_goal, self.task.max_speed]),
            dtype=np.float64,
        )
        self._start_space_meaning = "a position short of the goal and a speed within the limit"

    def step(self, action: int) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        if not self.action_space.contains(action):
            raise ValueError(f"action must be 0 or 1, got {action!r}")
        self._advance(self.task.force if int(action) == 1 else -self.task.force)
        assert self._state is not None
        terminated = bool(self.task.at_goal(self._state)[0])
        reward = -1.0 + (self.task.steps + 1 if self._t == 1 else 0.0)
        truncated = not terminated and self._t >= self.task.steps
        if truncated:
            reward -= 1.0
        return self._finish_step(reward, terminated, truncated)

    def _draw(self, state: list[float]) -> np.ndarray:
        return mountain_car_frame(self.task, state)


# id, entry point, max_episode_steps (the task's default horizon), reward_threshold (the
# class docstrings say how each was chosen).
ENV_SPECS = (
    ("dipole/CartPole-v1", "dipole_torch.tasks.gym_envs:CartPoleEnv", 1000, 950.0),
    ("dipole/MountainCar-v0", "dipole_torch.tasks.gym_envs:MountainCarEnv", 100, 50.0),
)


def register_envs() -> None:
    """Register ``dipole/CartPole-v1`` and ``dipole/MountainCar-v0`` (idempotent)."""
    for env_id, entry_point, max_episode_steps, reward_threshold in ENV_SPECS:
        if env_id not in gym.registry:
            gym.register(
                id=env_id,
                entry_point=entry_point,
                max_episode_steps=max_episode_steps,
                reward_threshold=reward_threshold,
            )


register_envs()

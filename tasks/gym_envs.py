"""Gymnasium environments for the classic-control tasks, registered on
``import dipole_torch.tasks``.

* ``gymnasium.make("dipole/CartPole-v0")`` -> :class:`CartPoleEnv`
* ``gymnasium.make("dipole/MountainCar-v0")`` -> :class:`MountainCarEnv`

Each environment steps a batch of one state through its task's own torch physics
(:meth:`dipole_torch.tasks.cartpole.CartPoleTask.step`,
:meth:`dipole_torch.tasks.mountain_car.MountainCarTask.step`): there is no second copy of the
dynamics, and a policy run in the environment earns the same undiscounted return as the task's
:meth:`~dipole_torch.tasks.base.EpisodicTask.evaluate` from the same start (pass it with
``reset(options={"initial_state": ...})``): bit for bit as its ``engine="torch"`` rollout, and as
its default Python episodes (double precision) but where rounding moves a trajectory across a
threshold. Keyword arguments of ``gymnasium.make`` go to the task's constructor (``steps``,
``force_limit``, ``dtype``, ...).
"""

from __future__ import annotations

from typing import Any

import gymnasium as gym
import numpy as np
import torch
from dipole_torch.tasks.cartpole import CartPoleTask
from dipole_torch.tasks.mountain_car import MountainCarTask
from gymnasium import spaces

__all__ = ["CartPoleEnv", "MountainCarEnv", "register_envs"]


class _TaskEnv(gym.Env):
    """Shared reset logic: a ``[1, S]`` torch state advanced by the task's ``step``."""

    metadata: dict[str, Any] = {"render_modes": []}
    task: CartPoleTask | MountainCarTask

    def __init__(self, render_mode: str | None = None) -> None:
        if render_mode is not None:
            raise ValueError(f"render_mode must be None (no rendering), got {render_mode!r}")
        self.render_mode = None
        self._state: torch.Tensor | None = None
        self._t = 0

    def _observation(self) -> np.ndarray:
        assert self._state is not None
        return self._state[0].to(torch.float32).numpy().copy()

    def reset(
        self, *, seed: int | None = None, options: dict[str, Any] | None = None
    ) -> tuple[np.ndarray, dict[str, Any]]:
        """Start an episode; ``options={"initial_state": [S]}`` sets the start exactly."""
        super().reset(seed=seed)
        options = options or {}
        unknown = set(options) - {"initial_state"}
        if unknown:
            raise ValueError(f"unknown reset options {sorted(unknown)}; only 'initial_state'")
        if options.get("initial_state") is not None:
            initial = torch.as_tensor(np.asarray(options["initial_state"], dtype=np.float64))
            if initial.shape != (self.task.state_dim,):
                raise ValueError(
                    f"initial_state must have shape [{self.task.state_dim}], "
                    f"got {list(initial.shape)}"
                )
            self._state = self.task._initial_states(1, None, initial)
        else:
            generator = torch.Generator().manual_seed(int(self.np_random.integers(2**62)))
            self._state = self.task.sample_initial_state(1, generator)
        self._t = 0
        return self._observation(), {}

    def _advance(self, force: float) -> None:
        if self._state is None:
            raise RuntimeError("call reset() before step()")
        force_tensor = torch.tensor([force], dtype=self.task.dtype)
        with torch.inference_mode():
            self._state = self.task.step(self._state, force_tensor)
        self._t += 1


class CartPoleEnv(_TaskEnv):
    """:class:`dipole_torch.tasks.cartpole.CartPoleTask` as a gymnasium environment.

    * Action: ``Box(-force_limit, force_limit, (1,))``, the force in newtons (clipped).
    * Observation: ``[x, ẋ, φ, φ̇]`` (float32), bounds as gymnasium's ``CartPole-v1``.
    * Reward: the paper's ``+1`` (upright within π/60), ``0``, or ``-1`` per step. At failure
      (|φ| > 12° or |x| > 2.4 m) the episode *terminates* and the reward of that step is
      ``-(steps - t + 1)``: the task's absorbing ``-1`` for the failing and every remaining
      step, paid at once, so that the return equals ``CartPoleTask.evaluate``'s.
    * Truncation after ``steps`` (1000) steps.
    """

    def __init__(self, render_mode: str | None = None, **task_kwargs: Any) -> None:
        super().__init__(render_mode)
        self.task = CartPoleTask(device="cpu", **task_kwargs)
        limit = np.float32(self.task.force_limit)
        self.action_space = spaces.Box(-limit, limit, shape=(1,), dtype=np.float32)
        high = np.array(
            [2 * self.task.x_threshold, np.inf, 2 * self.task.angle_threshold, np.inf],
            dtype=np.float32,
        )
        self.observation_space = spaces.Box(-high, high, dtype=np.float32)

    def step(self, action: np.ndarray) -> tuple[np.ndarray, float, bool, bool, dict[str, Any]]:
        force = float(np.asarray(action, dtype=np.float64).reshape(-1)[0])
        if not np.isfinite(force):
            raise ValueError(f"action must be finite, got {action!r}")
        limit = self.task.force_limit
        self._advance(float(torch.tensor(force, dtype=self.task.dtype).clamp(-limit, limit)))
        assert self._state is not None
        failed = self.task.failed(self._state)
        reward = float(self.task.step_reward(self._state, failed)[0])
        terminated = bool(failed[0])
        if terminated:
            reward = -float(self.task.steps - self._t + 1)
        truncated = not terminated and self._t >= self.task.steps
        return self._observation(), reward, terminated, truncated, {}


class MountainCarEnv(_TaskEnv):
    """:class:`dipole_torch.tasks.mountain_car.MountainCarTask` as a gymnasium environment.

    * Action: ``Discrete(2)``: ``0`` full backward (``u = -4``), ``1`` full forward (``+4``).
    * Observation: ``[x, ẋ]`` (float32) in ``[-1.5, 1.5] × [-0.07, 0.07]``.
    * Reward: the paper's counter paid step by step: it starts at 101, paid with the first
      step, and loses 1 per step (first step ``+100``, then ``-1``); the episode terminates
      at the goal (``x ≥ 0.5``). Not reaching it by step ``steps`` (100) costs one more
      point and truncates. Returns are ``101 - t`` at the goal on step ``t``, else ``0``,
      as ``MountainCarTask.evaluate``'s.
    """

    def __init__(self, render_mode: str | None = None, **task_kwargs: Any) -> None:
        super().__init__(render_mode)
        self.task = MountainCarTask(device="cpu", **task_kwargs)
        self.action_space = spaces.Discrete(2)
        self.observation_space = spaces.Box(
            np.array([self.task.min_position, -self.task.max_speed], dtype=np.float32),
            np.array([self.task.max_position, self.task.max_speed], dtype=np.float32),
            dtype=np.float32,
        )

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
        return self._observation(), reward, terminated, truncated, {}


def register_envs() -> None:
    """Register ``dipole/CartPole-v0`` and ``dipole/MountainCar-v0`` (idempotent)."""
    for env_id, entry_point in (
        ("dipole/CartPole-v0", "dipole_torch.tasks.gym_envs:CartPoleEnv"),
        ("dipole/MountainCar-v0", "dipole_torch.tasks.gym_envs:MountainCarEnv"),
    ):
        if env_id not in gym.registry:
            gym.register(id=env_id, entry_point=entry_point)


register_envs()

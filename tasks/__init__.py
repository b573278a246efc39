"""Episodic tasks: batched torch dynamics and rewards, one file a task.

Every task is an :class:`tasks.base.EpisodicTask`: it maps a batch of policy parameters
``theta: [B, D]`` to one return each, ``r: [B]``, in a single batched rollout.
"""

import tasks.gym_envs  # noqa: F401  (registers dipole/CartPole-v0 and dipole/MountainCar-v0)
from tasks.base import EpisodicTask

__all__ = ["EpisodicTask"]

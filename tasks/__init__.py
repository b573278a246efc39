"""Episodic tasks: batched torch dynamics and rewards, one file a task.

Every task is an ``dipole_torch.tasks.base.EpisodicTask``: it maps a batch of policy parameters
``theta: [B, D]`` to one return each, ``r: [B]``, in a single batched rollout.
"""

import dipole_torch.tasks.gym_envs  # noqa: F401  (registers dipole/CartPole-v1 and dipole/MountainCar-v0)
from dipole_torch.tasks.base import EpisodicTask

__all__ = ["EpisodicTask"]

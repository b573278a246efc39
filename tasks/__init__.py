"""Episodic tasks: batched torch dynamics and rewards, one file a task.

Every task is an :class:`tasks.base.EpisodicTask`: it maps a batch of policy parameters
``theta: [B, D]`` to one return each, ``r: [B]``, in a single batched rollout.
"""

from tasks.base import EpisodicTask

__all__ = ["EpisodicTask"]

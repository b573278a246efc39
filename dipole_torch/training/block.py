"""The block experiment (``task=viapoint_blocked``): mid-run, the world changes."""

from __future__ import annotations

import logging

from dipole_torch.training.board import Board, policy_figure
from dipole_torch.training.results import policy_set_line, task_returns

__all__ = ["block_the_route"]

log = logging.getLogger("train")


def block_the_route(task, optimizer, block, board: Board, generator):
    """An obstacle appears on the route of the best policy.

    The optimizer evaluates its stored policies once each in the new world and is told
    (``reevaluate``, K trials): its best policy becomes the one it executes, the policies the
    obstacle hurt search again. Logs the policies' paths before and after (``world/before``,
    ``world/after``) and what happened (``world/block``: the obstacle, each policy re-evaluated
    and, where the task describes a policy set, the routes they take before and after).

    Args:
        task: the viapoint task (``blocking_obstacle``, ``with_obstacles``).
        optimizer: the run's optimizer.
        block: ``task.block`` (``radius``, ``threshold``).
        board: the run's TensorBoard.
        generator: the episodes' generator.

    Returns:
        The blocked task, and what happened (for the checkpoint and ``results.json``).
    """
    means = optimizer.policy_means.to(task.device, task.dtype)
    ids = optimizer.policy_set.ids.tolist()
    trial = optimizer.trials
    title = f"before the block: {len(means)} policies after {trial} trials"
    board.figure("world/before", policy_figure(task, optimizer, title), trial)
    obstacle, description = task.blocking_obstacle(means, block.radius, block.threshold)
    known = policy_set_line(task, means)  # e.g. the routes the policies take, before
    task = task.with_obstacles([*task.obstacles, obstacle])
    returns = task_returns(task, means, generator)
    optimizer.reevaluate(returns)
    switched = ids[int(returns.argmax())]
    title = f"after the block: the same policies, re-evaluated ({optimizer.trials} trials)"
    board.figure("world/after", policy_figure(task, optimizer, title), optimizer.trials)
    lines = task.describe_policies(means)
    report = (
        f"block at {trial} trials: {description}; the {len(means)} stored policies "
        f"re-evaluated (now {optimizer.trials} trials), switching to policy {switched}:"
        + "".join(f"\n  policy {k}: {line}" for k, line in zip(ids, lines, strict=True))
        + (
            f"\nbefore the block: {known}\nafter it: {policy_set_line(task, means)}"
            if known
            else ""
        )
    )
    log.info(report)
    board.text("world/block", report, optimizer.trials)
    info = {
        "trial": trial,
        "obstacle": obstacle,
        "description": description,
        "returns": returns.double().tolist(),
        "switched_to": switched,
    }
    return task, info

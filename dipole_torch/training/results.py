"""A training run's results: ``results.json`` and ``policies.pt``."""

from __future__ import annotations

import json
import math
from collections.abc import Mapping
from pathlib import Path

import torch

from dipole_torch import Dipole
from dipole_torch.checkpoint import atomic_save, atomic_write_text
from dipole_torch.reward import check_rewards
from dipole_torch.training import checks

__all__ = [
    "check_task_hooks",
    "policy_set_line",
    "policy_set_summary",
    "policy_summary",
    "repeat_summary",
    "task_returns",
    "task_scalars",
    "write_results",
]


def task_returns(task, theta: torch.Tensor, generator: torch.Generator | None) -> torch.Tensor:
    """``task.evaluate(theta, generator=generator)``: ``[B]`` returns, one per row of
    ``theta: [B, D]``; a tensor as the task gives it, a numpy array or a list of numbers (a
    task wrapping a numpy simulator) as a float64 tensor, as ``tell`` takes them. Another
    shape or kind is a ``ValueError`` / ``TypeError`` naming the task's method, at the first
    batch (the end of a run stacks the returns of its policies)."""
    returns = task.evaluate(theta, generator=generator)
    name = f"{type(task).__name__}.evaluate's returns"
    with checks.reported("task.env"):  # one line and status 2, as a bad config value
        if not isinstance(returns, torch.Tensor):
            return check_rewards(returns, theta.shape[0], "row of θ", name)
        if returns.shape != (theta.shape[0],):
            raise ValueError(
                f"{name} must have shape [{theta.shape[0]}] (one per row of θ), got "
                f"{list(returns.shape)}"
            )
    return returns


def policy_summary(task, optimizer, generator: torch.Generator | None = None) -> list[dict]:
    """One entry per policy: its id, mean, covariance, weight, the return of its mean
    (evaluated without exploration; on returns the repeats found noisy, the mean of
    ``best_evaluations`` rollouts, as ``best()``'s: ``mean_evaluations``) and the task's
    description of it. One rollout runs the task's fixed default episode (``generator=None``:
    equal means give equal returns); several, their episodes from ``generator``, each its own
    (the task's default would repeat one episode, and its noise, n times)."""
    means = optimizer.policy_means.to(task.device, task.dtype)
    rollouts = mean_evaluations(optimizer)
    episodes = generator if rollouts > 1 else None
    with torch.no_grad():
        each = [task_returns(task, means, episodes) for _ in range(rollouts)]
        returns = torch.stack(each).mean(0)
    weights = optimizer.policies.weights
    descriptions = task.describe_policies(means)
    ids = optimizer.policy_set.ids.tolist()
    return [
        {
            "id": ids[k],
            "mean": optimizer.policy_means[k].tolist(),
            "covariance": optimizer.policy_covariances[k].tolist(),
            "weight": float(weights[k]),
            "return_of_mean": float(returns[k]),
            "description": descriptions[k],
        }
        for k in range(optimizer.num_policies)
    ]


def task_scalars(task, theta: torch.Tensor) -> dict[str, float]:
    """``task.policy_scalars(theta)`` (``theta: [K, D]`` on the task's device and dtype) as
    finite floats by name: what TensorBoard and ``results.json`` (strict JSON) take. A task's
    own method may return tensors or numpy numbers; anything else, or a value that is not
    finite, is a ``TypeError`` / ``ValueError`` naming the method and the name."""
    where = f"{type(task).__name__}.policy_scalars"
    with torch.no_grad():
        scalars = task.policy_scalars(theta)
    if not isinstance(scalars, Mapping):
        raise TypeError(f"{where} must return a dict of names to numbers, got {scalars!r}")
    numbers = {}
    for name, value in scalars.items():
        if not isinstance(name, str) or not name:
            raise TypeError(f"{where}: a name must be a non-empty string, got {name!r}")
        try:
            if isinstance(value, str | bytes):  # (float() would read "3")
                raise TypeError
            number = float(value)  # (a one-element tensor or numpy number converts too)
        except (TypeError, ValueError, RuntimeError):
            raise TypeError(f"{where}: {name!r} must be a number, got {value!r}") from None
        if not math.isfinite(number):
            raise ValueError(f"{where}: {name!r} must be finite, got {number}")
        numbers[name] = number
    return numbers


def policy_set_line(task, theta: torch.Tensor) -> str:
    """``task.describe_policy_set(theta)``, checked to be a string."""
    with torch.no_grad():
        line = task.describe_policy_set(theta)
    if not isinstance(line, str):
        raise TypeError(
            f"{type(task).__name__}.describe_policy_set must return a str, got {line!r}"
        )
    return line


def check_task_hooks(task) -> None:
    """Call the task's figures of a policy set once on θ0 alone, at the start of a run: a
    method that returns what a run cannot log stops the run there, not at its end."""
    theta0 = task.theta0.reshape(1, -1).to(task.device, task.dtype)
    task_scalars(task, theta0)
    policy_set_line(task, theta0)


def policy_set_summary(task, optimizer) -> dict:
    """``{"policy_set": {"scalars": ..., "description": ...}}``: the task's scalars of the
    final policy means taken together (``EpisodicTask.policy_scalars``, e.g. the viapoint
    task's ``routes``) and its line on them (``describe_policy_set``); ``{}`` for a task
    with neither."""
    means = optimizer.policy_means.to(task.device, task.dtype)
    scalars, description = task_scalars(task, means), policy_set_line(task, means)
    if not scalars and not description:
        return {}
    return {"policy_set": {"scalars": scalars, "description": description}}


def mean_evaluations(optimizer) -> int:
    """Rollouts whose mean ``policy_summary`` reports for each policy mean: the optimizer's
    ``best_evaluations`` once its repeats found the returns noisy, else 1."""
    repeats = optimizer.repeats
    return repeats.evaluations if repeats.noisy else 1


def repeat_summary(optimizer) -> dict:
    """With ``best_evaluations`` > 1: ``{"repeats": {...}}``, what the repeated evaluations
    found the returns to be (``RepeatedEvaluations.returns``); ``{}`` otherwise."""
    repeats = optimizer.repeats
    if repeats.evaluations <= 1:
        return {}
    return {
        "repeats": {
            "best_evaluations": repeats.evaluations,
            "returns": repeats.returns,
            "identical_repeats": repeats.identical,
            # (best_reward: the mean of best_evaluations returns, or a single one)
            "best_reward_evaluations": repeats.reported_evaluations,
            # (each policy's return_of_mean: the mean of this many rollouts)
            "mean_evaluations": mean_evaluations(optimizer),
        }
    }


def write_results(out: Path, results: dict, optimizer) -> None:
    """``results.json`` (the policies, the best return, the learning curves) and
    ``policies.pt`` (the policies, and DIPOLE's mixture over [θ, r], as ``GaussianMixture``
    state dicts), each written atomically."""
    artefacts = {"policies": optimizer.policies.state_dict()}
    if isinstance(optimizer, Dipole):
        artefacts["mixture"] = optimizer.mixture.state_dict()
    atomic_save(artefacts, out / "policies.pt")
    atomic_write_text(out / "results.json", json.dumps(results, indent=1, allow_nan=False))

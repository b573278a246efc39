"""A training run's results: ``results.json`` and ``policies.pt``."""

from __future__ import annotations

import json
from pathlib import Path

import torch

from dipole_torch import Dipole
from dipole_torch.checkpoint import atomic_save, atomic_write_text

__all__ = ["policy_set_summary", "policy_summary", "repeat_summary", "write_results"]


def policy_summary(task, optimizer) -> list[dict]:
    """One entry per policy: its id, mean, covariance, weight, the return of its mean
    (evaluated without exploration; on returns the repeats found noisy, the mean of
    ``best_evaluations`` rollouts, as ``best()``'s: ``mean_evaluations``) and the task's
    description of it."""
    means = optimizer.policy_means.to(task.device, task.dtype)
    with torch.no_grad():
        returns = torch.stack(
            [task.evaluate(means) for _ in range(mean_evaluations(optimizer))]
        ).mean(0)
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


def policy_set_summary(task, optimizer) -> dict:
    """``{"policy_set": {"scalars": ..., "description": ...}}``: the task's scalars of the
    final policy means taken together (``EpisodicTask.policy_scalars``, e.g. the viapoint
    task's ``routes``) and its line on them (``describe_policy_set``); ``{}`` for a task
    with neither."""
    means = optimizer.policy_means.to(task.device, task.dtype)
    with torch.no_grad():
        scalars = task.policy_scalars(means)
        description = task.describe_policy_set(means)
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

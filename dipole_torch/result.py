"""Where a policy search stands: the best evaluation and every policy."""

from __future__ import annotations

from dataclasses import dataclass

import torch
from torch import Tensor

__all__ = ["SearchResult"]


@dataclass(frozen=True)
class SearchResult:
    """Where a run stands (pycma's ``result``): the best evaluation and every policy.

    Attributes:
        best_theta: ``[D]`` the best parameters evaluated so far.
        best_reward: their return (the mean of ``best_evaluations`` returns).
        trials: reward evaluations told so far.
        iterations: tells after the first batch.
        means: ``[K, D]`` the policies' means.
        covariances: ``[K, D, D]`` their exploration covariances.
        best_rewards: ``[K]`` each policy's best kept return (−inf: none kept).
        active: ``[K]`` whether each policy is still sampled (not retired; beyond
            ``max_sampled`` it waits for its turn).
        converged: ``[K]`` whether each policy's exploration has converged.
        ids: ``[K]`` each policy's id (int64), kept for the whole run while rows move as
            policies are dropped: ``train.py``'s summary and ``results.json`` name policies
            by it.
        best_evaluations: the returns ``best_reward`` averages: 1, or ``best_evaluations``
            once repeated evaluations found the returns noisy (``PolicySearch.best``).
    """

    best_theta: Tensor
    best_reward: float
    trials: int
    iterations: int
    means: Tensor
    covariances: Tensor
    best_rewards: Tensor
    active: Tensor
    converged: Tensor
    ids: Tensor
    best_evaluations: int = 1

    def __str__(self) -> str:
        count = self.means.shape[0]
        noun = "policy" if count == 1 else "policies"
        averaged = f" (the mean of {self.best_evaluations})" if self.best_evaluations > 1 else ""
        lines = [
            f"best return {self.best_reward:.6g}{averaged} after {self.trials} trials "
            f"({self.iterations} iterations); {count} {noun}, best first:"
        ]
        # Best first, each named by its row of ``means`` (the index a user reads it with)
        # and its id (the name train.py's outputs give it).
        order = torch.argsort(self.best_rewards, descending=True, stable=True).tolist()
        for k in order:
            state = "converged" if self.converged[k] else "active" if self.active[k] else "waiting"
            mean = ", ".join(f"{v:.4g}" for v in self.means[k].tolist())
            lines.append(
                f"  means[{k}] = [{mean}]  best return {float(self.best_rewards[k]):.6g}"
                f"  ({state}, policy {int(self.ids[k])})"
            )
        return "\n".join(lines)

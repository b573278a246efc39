"""What the paper-reproduction scripts share: many learning runs advanced in lockstep through
one batched rollout per iteration, their curves on a common trials grid, and the
best-policy / average-policy figure."""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from hydra.utils import instantiate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def compose_config(*overrides: str):
    """``train.py``'s config with ``overrides`` (``task=viapoint``, ``algo=power``), composed
    through Hydra's compose API from the package ``dipole_torch.configs``."""
    from hydra import compose, initialize_config_module

    with initialize_config_module("dipole_torch.configs", version_base=None):
        return compose("config", overrides=list(overrides))


def load_task(name: str, **overrides):
    """The task of ``configs/task/<name>.yaml`` on CPU (constructor ``overrides`` applied),
    its trial budget and n0."""
    config = compose_config(f"task={name}", "device=cpu")
    task = instantiate(config.task.env, **overrides)
    return task, int(config.task.trials), int(config.task.n0)


def run_in_lockstep(
    task,
    optimizers: list,
    trials: int | Sequence[int],
    generator: torch.Generator | None = None,
) -> list[np.ndarray]:
    """Ask/tell every optimizer until it has used its ``trials`` reward evaluations (one
    budget for all, or one per optimizer).

    Each iteration stacks the active runs' ``ask()`` into one ``task.evaluate`` call (tasks
    are batch-independent) and splits the returns back for ``tell()``. A run's result
    depends on its own seed and budget only, not on the runs it is stacked with.

    Returns:
        Per run, rows ``[trials, best, average, policies]`` after every tell: the highest and
        the mean return of the batch just told, and the number of policies.
    """
    budgets = [trials] * len(optimizers) if isinstance(trials, int) else list(trials)
    if len(budgets) != len(optimizers):
        raise ValueError(f"{len(budgets)} budgets for {len(optimizers)} optimizers")
    history: list[list[tuple[int, float, float, int]]] = [[] for _ in optimizers]
    while True:
        active = [i for i, opt in enumerate(optimizers) if opt.trials < budgets[i]]
        if not active:
            break
        asked = [optimizers[i].ask() for i in active]
        rewards = task.evaluate(torch.cat(asked).to(task.dtype), generator)
        for i, theta, r in zip(active, asked, rewards.split([len(a) for a in asked]), strict=True):
            opt = optimizers[i]
            opt.tell(theta, r)
            last = opt.last_rewards
            history[i].append((opt.trials, float(last.max()), float(last.mean()), opt.num_policies))
    return [np.array(h) for h in history]


def on_grid(history: np.ndarray, grid: np.ndarray) -> np.ndarray:
    """``[2, G]``: best and average of the latest batch told at or before each grid trial
    (NaN before the first tell)."""
    out = np.full((2, len(grid)), np.nan)
    index = np.searchsorted(history[:, 0], grid, side="right") - 1
    valid = index >= 0
    out[:, valid] = history[index[valid], 1:3].T
    return out


def plot_best_and_average(
    grid: np.ndarray,
    curves: dict[str, np.ndarray],
    colors: dict[str, str],
    path: Path,
    *,
    task_title: str,
    ylabel: str,
    xlabel: str = "trials",
    suptitle: str | None = None,
    ylim: tuple[float, float] | None = None,
) -> None:
    """Two panels (best policy, average of policies): mean ± std over runs of each curve.

    Args:
        curves: label -> ``[runs, 2, G]`` values from :func:`on_grid`.
        colors: label -> matplotlib colour.
    """
    fig, axes = plt.subplots(1, 2, figsize=(10, 3.8), sharey=True)
    for ax, which, title in ((axes[0], 0, "best policy"), (axes[1], 1, "average of policies")):
        for label, values in curves.items():
            mean, std = np.nanmean(values[:, which], 0), np.nanstd(values[:, which], 0)
            ax.plot(grid, mean, color=colors[label], label=label)
            ax.fill_between(grid, mean - std, mean + std, color=colors[label], alpha=0.2)
        ax.set_title(f"{task_title}: {title}")
        ax.set_xlabel(xlabel)
        if ylim is not None:
            ax.set_ylim(*ylim)
        ax.grid(alpha=0.3)
    axes[0].set_ylabel(ylabel)
    axes[0].legend(loc="lower right", fontsize="small")
    if suptitle:
        fig.suptitle(suptitle)
    fig.tight_layout()
    fig.savefig(path, dpi=120)
    plt.close(fig)

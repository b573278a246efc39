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

from dipole_torch.training.hydra_compat import VERSION_BASE, instantiate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


def compose_config(*overrides: str):
    """``train.py``'s config with ``overrides`` (``task=viapoint``, ``algo=power``), composed
    through Hydra's compose API from the package ``dipole_torch.configs``."""
    from hydra import compose, initialize_config_module

    with initialize_config_module("dipole_torch.configs", **VERSION_BASE):
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
    bounds: tuple[float, float] | None = None,
) -> None:
    """Two panels (best policy, average of policies): each curve's mean over runs, with a
    band from its 25 % to its 75 % quantile over runs (inside the range the runs reached,
    unlike ± std). The y-axis spans the data (within ``bounds``, the feasible range), the
    legend sits below the panels. Written as ``path`` (PNG, 200 dpi) and as PDF beside it.

    Args:
        curves: label -> ``[runs, 2, G]`` values from ``on_grid``.
        colors: label -> matplotlib colour.
    """
    fig, axes = plt.subplots(1, 2, figsize=(10, 4.2), sharey=True)
    low, high = np.inf, -np.inf
    for ax, which, title in ((axes[0], 0, "best policy"), (axes[1], 1, "average of policies")):
        for label, values in curves.items():
            mean, (q25, q75) = np.nanmean(values[:, which], 0), quartiles(values[:, which])
            ax.plot(grid, mean, color=colors[label], label=label)
            ax.fill_between(grid, q25, q75, color=colors[label], alpha=0.2, lw=0)
            low, high = min(low, np.nanmin(q25), np.nanmin(mean)), max(high, np.nanmax(q75))
        ax.set_title(f"{task_title}: {title}")
        ax.set_xlabel(xlabel)
        ax.set_xlim(grid[0], grid[-1])
        ax.grid(alpha=0.3)
    axes[0].set_ylim(*data_limits(low, high, bounds))
    axes[0].set_ylabel(ylabel)
    handles, labels = axes[0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), frameon=False)
    if suptitle:
        fig.suptitle(suptitle)
    fig.tight_layout(rect=(0, 0.08, 1, 1))
    save_figure(fig, path)
    plt.close(fig)


def quartiles(values: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """``([G], [G])`` the 25 % and 75 % quantiles over runs of ``values: [runs, G]``, each
    over the runs that have a value there (NaN: not yet); NaN where no run has one (a grid
    point before every run's first return, or never reached: null in the JSON)."""
    seen = ~np.isnan(values).all(axis=0)
    q25, q75 = np.full(values.shape[1:], np.nan), np.full(values.shape[1:], np.nan)
    if seen.any():
        q25[seen] = np.nanquantile(values[:, seen], 0.25, axis=0)
        q75[seen] = np.nanquantile(values[:, seen], 0.75, axis=0)
    return q25, q75


def data_limits(
    low: float, high: float, bounds: tuple[float, float] | None = None
) -> tuple[float, float]:
    """Axis limits around ``[low, high]`` with a 4 % margin, inside ``bounds``."""
    margin = 0.04 * max(high - low, 1e-12)
    low, high = low - margin, high + margin
    if bounds is not None:
        low, high = max(low, bounds[0]), min(high, bounds[1])
    return low, high


def save_figure(fig, path: Path) -> None:
    """``path`` as a 200-dpi PNG and the same figure as a PDF (vector) beside it."""
    fig.savefig(path, dpi=200)
    fig.savefig(path.with_suffix(".pdf"))

"""A training run's TensorBoard: scalars against trials, the policy figure, the config and
the hyperparameters.

Tags (the step is always the trial count, the x-axis of the paper's plots), grouped so that
TensorBoard's Time Series tab opens on the returns:

* ``reward/best``, ``reward/mean``: the best and mean of each policy's latest return
  (``last_rewards``); ``reward/best_so_far``: the best return evaluated so far (``best()``: on noisy
  returns with ``best_evaluations`` > 1, the best mean of that many);
* ``search/policies``: the number of policies; ``search/log10_exploration_std``: log10 of
  the mean, over the active policies, of each one's largest per-axis exploration std
  relative to Σ_start's (``relative_std``; it shrinks geometrically as they converge);
  ``search/rewards``: histogram of the policies' returns;
  ``search/figure``: the task's policy figure, where it has one;
* ``task/<name>``: the task's scalars of the policies taken together
  (``EpisodicTask.policy_scalars``; the viapoint task's ``task/routes``), with the figure;
* ``world/before``, ``world/after``, ``world/block``: the block experiment (viapoint_blocked).

The Custom Scalars tab shows the returns in one chart. The HPARAMS tab gets the flattened
config with the final ``reward/best_so_far``, ``search/policies`` and ``task/<name>`` (no
scalars of its own).
The resolved config is the ``config`` text.
"""

from __future__ import annotations

import json
import math
from pathlib import Path

import torch
from omegaconf import DictConfig, OmegaConf

from dipole_torch.training.results import task_scalars
from dipole_torch.training.resume import flatten

__all__ = ["Board"]

LAYOUT = {
    "returns": {
        "reward": ["Multiline", ["reward/best", "reward/mean", "reward/best_so_far"]],
    },
    "search": {
        "policies": ["Multiline", ["search/policies"]],
        "relative exploration std (log10)": ["Multiline", ["search/log10_exploration_std"]],
        "clusterings skipped": ["Multiline", ["search/clusterings_skipped"]],
    },
}


class Board:
    """The run's ``SummaryWriter`` with its tags and layout.

    Args:
        directory: the run's ``tensorboard/`` directory.
        cfg: the run's config (logged resolved, as text).
        purge_step: the first step of an earlier session's events to hide (a resumed run:
            the checkpoint's trial count + 1, so that the events a killed session logged
            after its last checkpoint are hidden).
    """

    def __init__(self, directory: Path, cfg: DictConfig, purge_step: int | None = None):
        self.directory, self.purge_step = directory, purge_step
        self.config = OmegaConf.to_yaml(cfg, resolve=True)
        self._writer = None

    @property
    def writer(self):
        """The ``SummaryWriter``, opened at the first write: TensorBoard's import is not part
        of a run's start-up (``benchmarks/bench_startup.py``)."""
        if self._writer is None:
            from torch.utils.tensorboard import SummaryWriter

            self._writer = SummaryWriter(str(self.directory), purge_step=self.purge_step)
            if self.purge_step is None:
                self._writer.add_custom_scalars(LAYOUT)
                self._writer.add_text("config", f"```yaml\n{self.config}\n```")
        return self._writer

    def log_iteration(self, optimizer) -> dict[str, float]:
        """Write this iteration's scalars; return them for the history."""
        rewards = optimizer.last_rewards
        relative = optimizer.relative_std()
        sampled = relative[optimizer.active] if bool(optimizer.active.any()) else relative
        row = {
            "trials": optimizer.trials,
            "best": float(rewards.max()),
            "mean": float(rewards.mean()),
            "best_so_far": optimizer.best()[1],
            "num_policies": optimizer.num_policies,
            "exploration_std": float(sampled.mean()),
        }
        step = optimizer.trials
        self.writer.add_scalar("reward/best", row["best"], step)
        self.writer.add_scalar("reward/mean", row["mean"], step)
        self.writer.add_scalar("reward/best_so_far", row["best_so_far"], step)
        self.writer.add_scalar("search/policies", row["num_policies"], step)
        # log10: it shrinks geometrically as policies converge (floored: a chart drops -inf).
        log_std = math.log10(max(row["exploration_std"], 1e-30))
        self.writer.add_scalar("search/log10_exploration_std", log_std, step)
        self.writer.add_histogram("search/rewards", rewards.float(), step)
        skipped = getattr(optimizer, "clusterings_skipped", None)  # (DIPOLE's; not PoWER's)
        if skipped is not None:
            # Clusterings that failed numerically and were skipped: a count that keeps rising
            # says the DP mixture no longer runs (see docs/reliability.md).
            self.writer.add_scalar("search/clusterings_skipped", skipped, step)
        return row

    def figure(self, tag: str, figure, step: int) -> None:
        """A matplotlib figure (closed once written); ``None`` writes nothing."""
        if figure is not None:
            self.writer.add_figure(tag, figure, step)

    def policy_set(self, task, optimizer) -> None:
        """The task's figure of the policy means (``search/figure``) and its scalars of
        them taken together (``task/<name>``, e.g. ``task/routes``), at the trial count."""
        means = optimizer.policy_means.to(task.device, task.dtype)
        for name, value in task_scalars(task, means).items():
            self.writer.add_scalar(f"task/{name}", value, optimizer.trials)
        self.figure("search/figure", policy_figure(task, optimizer), optimizer.trials)

    def text(self, tag: str, text: str, step: int) -> None:
        self.writer.add_text(tag, text.replace("\n", "  \n"), step)

    def hparams(
        self,
        cfg: DictConfig,
        best_reward: float,
        num_policies: int,
        task_scalars: dict[str, float] | None = None,
    ) -> None:
        """The HPARAMS tab: the flattened config (``algo.optimizer.alpha``, …), with the run's
        final ``reward/best_so_far``, ``search/policies`` and the task's ``task/<name>``
        scalars (``policy_set``'s) as its metrics."""
        config = flatten(OmegaConf.to_container(cfg, resolve=True))
        # TensorBoard takes numbers, strings and booleans: lists and null as text.
        values = {
            key: value if isinstance(value, bool | int | float | str) else json.dumps(value)
            for key, value in config.items()
        }
        from torch.utils.tensorboard.summary import hparams

        metrics = {"reward/best_so_far": best_reward, "search/policies": num_policies}
        metrics.update({f"task/{name}": value for name, value in (task_scalars or {}).items()})
        for summary in hparams(values, metrics):
            self.writer.file_writer.add_summary(summary)

    def close(self) -> None:
        self.writer.close()  # opened here if nothing was written: a run always has its log


def policy_figure(task, optimizer, title: str | None = None):
    """The task's figure of the optimizer's policy means (``None`` where it has none)."""
    means = optimizer.policy_means.to(task.device, task.dtype)
    with torch.no_grad():
        return task.plot_policies(means, **({} if title is None else {"title": title}))

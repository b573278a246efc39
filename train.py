"""Train DIPOLE or PoWER on a task: ``python train.py task=viapoint algo=dipole seed=3``.

Reads top to bottom: config, seeding, task and optimizer, the ask/tell loop with TensorBoard
logging and checkpoints, results. Everything else lives in ``dipole_torch`` and ``tasks``.
Outputs (Hydra's run directory, ``outputs/<task>/<algo>/seed<seed>_<time>/``):

* ``tensorboard/`` -- scalars against trials: ``reward/best``, ``reward/mean`` (best and
  mean return of the latest batch, one sample per policy), ``reward/best_so_far``,
  ``policies/count``, ``policies/exploration_std``; histogram ``policies/rewards``; the
  task's policy figure where it has one.
* ``results.json`` -- final policies, best return, learning curves.
* ``policies.pt`` -- the final policies (and DIPOLE's mixture over [θ, r]) as
  ``GaussianMixture`` state dicts: see the README's "Use the policies in your code".
* ``checkpoint.pt`` -- resume with ``resume=<path>``; the resumed run makes exactly the
  draws the uninterrupted one would have made.
"""

from __future__ import annotations

import json
import math
import time
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

from dipole_torch import Dipole


def check_config(cfg: DictConfig) -> None:
    """Reject bad values with a message naming the key (Hydra itself rejects unknown
    task/algo names, listing the available ones)."""
    if not isinstance(cfg.trials, int) or cfg.trials <= 0:
        raise ValueError(
            f"trials (the trial budget) must be a positive integer, got {cfg.trials!r}"
        )
    if not isinstance(cfg.seed, int):
        raise ValueError(f"seed must be an integer, got {cfg.seed!r}")
    if not isinstance(cfg.task.n0, int) or cfg.task.n0 <= 0:
        raise ValueError(
            f"task.n0 (initial samples) must be a positive integer, got {cfg.task.n0!r}"
        )
    for key in ("threads", "checkpoint_every"):
        if not isinstance(cfg[key], int) or cfg[key] < 1:
            raise ValueError(f"{key} must be a positive integer, got {cfg[key]!r}")
    if not isinstance(cfg.figure_every, int) or cfg.figure_every < 0:
        raise ValueError(f"figure_every must be a non-negative integer, got {cfg.figure_every!r}")
    device = str(cfg.device)
    if not (device == "cpu" or device.startswith("cuda")):
        raise ValueError(f"device must be 'cpu' or 'cuda[:N]', got {device!r}")
    if device.startswith("cuda") and not torch.cuda.is_available():
        raise ValueError(f"device={device!r} but CUDA is not available on this machine")


def log_iteration(writer: SummaryWriter, optimizer, iteration: int) -> dict[str, float]:
    """Write this iteration's scalars against trials; return them for the history."""
    rewards = optimizer.last_rewards
    covs = optimizer.policy_covariances
    exploration_std = covs.diagonal(dim1=-2, dim2=-1).mean(-1).sqrt().mean()
    row = {
        "trials": optimizer.trials,
        "best": float(rewards.max()),
        "mean": float(rewards.mean()),
        "best_so_far": optimizer.best()[1],
        "num_policies": optimizer.num_policies,
        "exploration_std": float(exploration_std),
    }
    step = optimizer.trials
    writer.add_scalar("reward/best", row["best"], step)
    writer.add_scalar("reward/mean", row["mean"], step)
    writer.add_scalar("reward/best_so_far", row["best_so_far"], step)
    writer.add_scalar("policies/count", row["num_policies"], step)
    writer.add_scalar("policies/exploration_std", row["exploration_std"], step)
    writer.add_histogram("policies/rewards", rewards.float(), step)
    return row


def policy_summary(task, optimizer) -> list[dict]:
    means = optimizer.policy_means
    returns = task.evaluate(means.to(task.device, task.dtype))  # the means, without exploration
    weights = optimizer.policies.weights
    descriptions = task.describe_policies(means.to(task.device, task.dtype))
    return [
        {
            "mean": means[k].tolist(),
            "covariance": optimizer.policy_covariances[k].tolist(),
            "weight": float(weights[k]),
            "return_of_mean": float(returns[k]),
            "description": descriptions[k],
        }
        for k in range(optimizer.num_policies)
    ]


@hydra.main(version_base=None, config_path="configs", config_name="config")
def main(cfg: DictConfig) -> dict:
    check_config(cfg)
    torch.set_num_threads(cfg.threads)
    out = Path(HydraConfig.get().runtime.output_dir)
    task = instantiate(cfg.task.env)
    generator = torch.Generator().manual_seed(cfg.seed)  # the optimizer's draws
    # Episodes' random starts: a CPU generator (the tasks draw on the CPU, then move).
    task_generator = torch.Generator().manual_seed(cfg.seed + 1_000_003)
    optimizer = instantiate(
        cfg.algo.optimizer,
        theta0=task.theta0.double(),
        sigma_start=task.sigma_start.double(),
        n0=cfg.task.n0,
        reward_range=tuple(task.reward_range) if cfg.algo.use_task_reward_range else None,
        generator=generator,
    )
    history: list[dict] = []
    if cfg.resume:
        checkpoint = torch.load(cfg.resume, weights_only=False)
        optimizer.load_state_dict(checkpoint["optimizer"])
        task_generator.set_state(checkpoint["task_generator"])
        history = checkpoint["history"]
    writer = SummaryWriter(str(out / "tensorboard"))
    writer.add_text("config", f"```\n{OmegaConf.to_yaml(cfg)}\n```")

    def save_checkpoint() -> None:
        torch.save(
            {
                "optimizer": optimizer.state_dict(),
                "task_generator": task_generator.get_state(),
                "history": history,
                "config": OmegaConf.to_container(cfg, resolve=True),
            },
            out / "checkpoint.pt",
        )

    start = time.perf_counter()
    bar = tqdm(total=cfg.trials, initial=optimizer.trials, unit="trial", disable=not cfg.progress)
    while optimizer.trials < cfg.trials:
        theta = optimizer.ask()
        rewards = task.evaluate(theta.to(task.device, task.dtype), generator=task_generator)
        optimizer.tell(theta, rewards)
        row = log_iteration(writer, optimizer, len(history))
        history.append(row)
        bar.update(theta.shape[0])
        bar.set_postfix(best=f"{row['best_so_far']:.3g}", policies=row["num_policies"])
        if cfg.figure_every and len(history) % cfg.figure_every == 0:
            figure = task.plot_policies(optimizer.policy_means.to(task.device, task.dtype))
            if figure is not None:
                writer.add_figure("policies/figure", figure, optimizer.trials)
        if len(history) % cfg.checkpoint_every == 0:
            save_checkpoint()
    bar.close()
    save_checkpoint()

    figure = task.plot_policies(optimizer.policy_means.to(task.device, task.dtype))
    if figure is not None:
        writer.add_figure("policies/figure", figure, optimizer.trials)
    writer.close()
    policies = policy_summary(task, optimizer)
    artefacts = {"policies": optimizer.policies.state_dict()}
    if isinstance(optimizer, Dipole):
        artefacts["mixture"] = optimizer.mixture.state_dict()
    torch.save(artefacts, out / "policies.pt")
    best_theta, best_reward = optimizer.best()
    results = {
        "task": cfg.task.name,
        "algo": cfg.algo.name,
        "seed": cfg.seed,
        "trials": optimizer.trials,
        "wall_time_s": time.perf_counter() - start,
        "best_reward": best_reward,
        "best_theta": best_theta.tolist(),
        "policies": policies,
        "history": {key: [row[key] for row in history] for key in history[0]} if history else {},
    }
    (out / "results.json").write_text(json.dumps(results, indent=1, allow_nan=False))
    print(
        f"\n{cfg.algo.name} on {cfg.task.name}: best return {best_reward:.4g} in "
        f"{optimizer.trials} trials; {len(policies)} policies (return of each mean):"
    )
    for k, policy in sorted(enumerate(policies), key=lambda kp: -kp[1]["return_of_mean"]):
        text = f"  policy {k}: return {policy['return_of_mean']:.4g}"
        if policy["description"]:
            text += f"  {policy['description']}"
        print(text)
    print(f"outputs in {out}")
    assert math.isfinite(best_reward)
    return results


if __name__ == "__main__":
    main()

"""Train DIPOLE or PoWER on a task: ``python train.py task=viapoint algo=dipole seed=3``.

Installed from a wheel, the same script is ``dipole_torch.train`` and the ``dipole-train``
command. It reads top to bottom: config, seeding, task and optimizer, the ask/tell loop with
TensorBoard and checkpoints, results. The rest is in ``dipole_torch`` (the library),
``dipole_torch.tasks`` and ``dipole_torch.training`` (the config schemas, resume, signals,
TensorBoard, console output, the block experiment); ``python train.py --help`` lists every
setting. Outputs, in Hydra's run directory ``outputs/<task>/<algo>/seed<seed>_<time>/``:

* ``tensorboard/`` (``dipole_torch.training.board``), ``train.log`` (the log lines);
* ``results.json`` (the policies, the best return, the learning curves) and ``policies.pt``
  (the policies, and DIPOLE's mixture over [θ, r], as ``GaussianMixture`` state dicts);
* ``checkpoint.pt``: ``resume=<path>`` continues the run exactly, in its directory.

A run evaluates exactly ``trials``: the batch that would cross the budget is cut to its first
rows, and the checkpoint keeps the run before that batch (and the trials it ended at), so
that a resume with a larger budget makes the draws of an uninterrupted run. Every output is
written atomically; SIGTERM or SIGINT finish the iteration, write a checkpoint, print the
command that resumes and exit with status 128 + the signal number; a bad value ends the run
with one line and status 2.
"""

from __future__ import annotations

import dataclasses
import logging
import shutil
import sys
import time
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.types import RunMode
from omegaconf import DictConfig, OmegaConf

from dipole_torch.training.config import register
from dipole_torch.training.hydra_compat import VERSION_BASE, instantiate
from dipole_torch.training.resume import register_resolvers

register()  # the schemas configs/ extends
register_resolvers()
log = logging.getLogger("train")  # Hydra's job logging: stdout and the run's train.log
OUTPUTS = ("checkpoint.pt", "results.json", "policies.pt")  # each written atomically


CONFIGS = str(Path(__file__).parent / "configs")


@hydra.main(config_path=CONFIGS, config_name="config", **VERSION_BASE)
def train(cfg: DictConfig) -> dict:
    from dipole_torch.checkpoint import CheckpointError
    from dipole_torch.training import board, checks, console, resume, run_directory
    from dipole_torch.training.block import block_the_route
    from dipole_torch.training.results import (
        check_task_hooks,
        policy_set_summary,
        policy_summary,
        repeat_summary,
        task_returns,
        write_results,
    )
    from dipole_torch.training.signals import StopRequest

    with checks.reported():
        checks.check_config(cfg)
    torch.set_num_threads(cfg.threads)
    out = Path(HydraConfig.get().runtime.output_dir)
    overrides = list(HydraConfig.get().overrides.task)
    # One process writes a run's directory at a time (a second resume of it is refused).
    with checks.reported(), run_directory.lock_run_directory(out):
        checkpoint = resume.load_resume(cfg, overrides) if cfg.resume else None  # its seed
        if checkpoint is None and (out / "checkpoint.pt").exists():
            refused = out / str(HydraConfig.get().output_subdir)  # .hydra/refused_<time>
            if refused.name.startswith("refused_"):
                shutil.rmtree(refused, ignore_errors=True)  # the finished run's record stays
            swept = HydraConfig.get().mode == RunMode.MULTIRUN
            elsewhere = (
                "or give this sweep another hydra.sweep.dir, or a hydra.sweep.subdir that tells "
                "its runs apart (the budget, device and threads do not name a run's directory; "
                "for a sweep over the budget: 'hydra.sweep.subdir=${task.name}_${algo.name}"
                "_seed${seed}_trials${trials}')"
                if swept
                else "or choose another hydra.run.dir"
            )
            raise CheckpointError(
                f"{out} already holds a run's checkpoint.pt; continue it with "
                f"{resume.resume_override(out / 'checkpoint.pt')}, {elsewhere}"
            )
        run_directory.remove_stale_temporaries(out, OUTPUTS)  # left by a killed session

        # The task, the optimizer and their generators.
        with checks.reported("task.env"):
            task = instantiate(cfg.task.env)
            check_task_hooks(task)  # what it says of a policy set can be logged
        generator = torch.Generator().manual_seed(cfg.seed)  # the optimizer's draws
        task_generator = torch.Generator().manual_seed(cfg.seed + 1_000_003)  # the starts
        reward_range = tuple(task.reward_range) if cfg.algo.use_task_reward_range else None
        with checks.reported("algo.optimizer"):
            optimizer = instantiate(
                cfg.algo.optimizer,
                _convert_="all",  # bounds as plain lists
                theta0=task.theta0.double(),
                sigma_start=task.sigma_start.double(),
                n0=cfg.task.n0,
                reward_range=reward_range,
                generator=generator,
            )
        shape = {"dimension": optimizer.dim, "reward_range": reward_range}
        history, elapsed, blocked = [], 0.0, None  # elapsed: wall time of earlier sessions
        figure_trials = None  # the trial count of the latest policy figure in TensorBoard
        if checkpoint is not None:
            history, elapsed, blocked = resume.restore(
                checkpoint, cfg.resume, optimizer, task_generator, shape, cfg.trials
            )
            figure_trials = checkpoint.get("figure_trials")  # (kept: the purge is after it)
            if blocked is not None:  # the checkpoint's world: with the obstacle
                task = task.with_obstacles([*task.obstacles, blocked["obstacle"]])
            log.info(f"resumed {cfg.resume} at {optimizer.trials} trials (seed {cfg.seed})")
        checkpointer = resume.Checkpointer(
            out / "checkpoint.pt", OmegaConf.to_yaml(cfg, resolve=True), overrides, shape
        )
        writer = board.Board(out / "tensorboard", cfg, optimizer.trials + 1 if checkpoint else None)
        block = cfg.task.get("block")  # viapoint_blocked: the world changes mid-run
        start = time.perf_counter()

        def save_checkpoint(run_trials: int | None = None) -> None:
            wall = elapsed + time.perf_counter() - start
            checkpointer.save(
                optimizer, task_generator, history, blocked, wall, figure_trials, run_trials
            )

        # The ask/tell loop: one iteration a batch.
        progress = console.Progress(cfg.trials, optimizer.trials, enabled=cfg.progress)
        last_batch_cut = False
        # DIPOLE's coverage_from (task=viapoint sets it): said once, when the run reaches it.
        cover_from = getattr(getattr(optimizer, "options", None), "coverage_from", None)
        with StopRequest() as stop, progress.messages():
            while optimizer.trials < cfg.trials and not stop:
                rows = optimizer.batch_size
                block_due = block is not None and blocked is None and block.trial < cfg.trials
                if block_due and optimizer.trials >= block.trial:  # the world changes
                    if optimizer.trials + optimizer.num_policies > cfg.trials:
                        log.info(f"no block: re-evaluating would take the run past {cfg.trials}")
                        break
                    trials = optimizer.trials
                    task, blocked = block_the_route(task, optimizer, block, writer, task_generator)
                    history.append(writer.log_iteration(optimizer))
                    progress.update(optimizer.trials, optimizer.trials - trials, history[-1])
                    continue
                if block_due and optimizer.trials + rows > block.trial:
                    rows = block.trial - optimizer.trials  # the block comes at its trial exactly
                elif optimizer.trials + rows > cfg.trials:
                    # The batch crossing the budget: its first rows end the run at the budget
                    # exactly. The checkpoint keeps the run before it, and where it ends.
                    save_checkpoint(run_trials=cfg.trials)
                    log.info(
                        f"the last batch is cut to its first {cfg.trials - optimizer.trials} "
                        f"of {rows} rows, to end at {cfg.trials} trials"
                    )
                    rows, last_batch_cut = cfg.trials - optimizer.trials, True
                if cover_from is not None and optimizer.trials >= cover_from:
                    cap = optimizer.options.coverage_max_policies
                    log.info(
                        f"from trial {optimizer.trials} on, DIPOLE covers alternatives "
                        f"(coverage_from={cover_from}): candidates the hill-valley probe "
                        "cannot judge become policies, and every active policy is sampled"
                        + ("" if cap is None else f" (at most {cap} active)")
                    )
                    cover_from = None
                theta = optimizer.ask(max_rows=rows)
                rewards = task_returns(task, theta.to(task.device, task.dtype), task_generator)
                optimizer.tell(theta, rewards)
                history.append(writer.log_iteration(optimizer))
                progress.update(optimizer.trials, theta.shape[0], history[-1])
                if cfg.figure_every and len(history) % cfg.figure_every == 0:
                    writer.policy_set(task, optimizer)  # the figure, the task's scalars
                    figure_trials = optimizer.trials
                if len(history) % cfg.checkpoint_every == 0 and not last_batch_cut:
                    save_checkpoint()
            progress.close()
            if not stop and figure_trials != optimizer.trials:
                # The final policies, unless just drawn (by this session or, at the
                # checkpoint's trials, by the one that wrote it), before the checkpoint says so.
                writer.policy_set(task, optimizer)
                figure_trials = optimizer.trials
            if not last_batch_cut:
                save_checkpoint()
        if stop:
            writer.close()
            log.info(
                f"\nstopped by {stop.name} at {optimizer.trials} of {cfg.trials} trials; "
                f"checkpoint at {checkpointer.trials} trials written to {checkpointer.path}\n"
                "resume with:\n  "
                f"{resume.resume_command(overrides, checkpointer.path)}"
            )
            raise SystemExit(128 + stop.signum)

        # Results.
        best_theta, best_reward = optimizer.best()
        results = {
            "task": cfg.task.name,
            "algo": cfg.algo.name,
            "seed": cfg.seed,
            "trials": optimizer.trials,
            "trial_budget": cfg.trials,
            "wall_time_s": elapsed + time.perf_counter() - start,
            "best_reward": best_reward,
            "best_theta": best_theta.tolist(),
            "policies": policy_summary(task, optimizer, task_generator),
            **policy_set_summary(task, optimizer),
            **repeat_summary(optimizer),
            **({"block": blocked} if blocked is not None else {}),
            "history": {key: [row[key] for row in history] for key in history[0]}
            if history
            else {},
        }
        write_results(out, results, optimizer)
        policy_set = results.get("policy_set", {})
        writer.hparams(cfg, best_reward, len(results["policies"]), policy_set.get("scalars"))
        writer.close()
    log.info("\n" + console.summary(cfg.algo.name, cfg.task.name, results, out))
    return results


def main():
    """The command: ``--help`` lists every setting (dipole_torch.training.config), the rest is
    Hydra's (overrides, ``-m`` sweeps, ``--hydra-help``)."""
    if "--help" in sys.argv[1:] or "-h" in sys.argv[1:]:
        from dipole_torch.training.config import print_help

        return print_help(sys.argv[1:], CONFIGS)
    from dipole_torch.training import checks
    from dipole_torch.training.config import Config

    # trails=60: Hydra would suggest +trails=60; the nearest setting is named instead.
    settings = [field.name for field in dataclasses.fields(Config)]
    checks.check_command_line(sys.argv[1:], [*settings, "task_algo", "hydra"])
    return train()


if __name__ == "__main__":
    main()

"""Train DIPOLE or PoWER on a task: ``python train.py task=viapoint algo=dipole seed=3``.

Installed from a wheel, the same script is ``dipole_torch.train`` and the ``dipole-train``
command: ``dipole-train task=viapoint algo=dipole seed=3`` (setup.py puts this file into the
wheel; ``configs/`` sits next to it in both places).

Reads top to bottom: config, seeding, task and optimizer, the ask/tell loop with TensorBoard
logging and checkpoints, results. Everything else lives in ``dipole_torch`` (the library) and
``dipole_torch.tasks`` (``tasks/``).
Outputs (Hydra's run directory, ``outputs/<task>/<algo>/seed<seed>_<time>/``):

* ``tensorboard/`` -- scalars against trials: ``reward/best``, ``reward/mean`` (best and
  mean of each policy's latest return, ``last_rewards``), ``reward/best_so_far``,
  ``policies/count``, ``policies/exploration_std``; histogram ``policies/rewards``; the
  task's policy figure where it has one.
* ``results.json`` -- final policies, best return, learning curves.
* ``policies.pt`` -- the final policies (and DIPOLE's mixture over [θ, r]) as
  ``GaussianMixture`` state dicts: see the README's "Use the policies in your code".
* ``checkpoint.pt`` -- resume with ``resume=<path>``; the resumed run makes exactly the
  draws the uninterrupted one would have made.
* With ``task=viapoint_blocked`` (a ``task.block`` section), the world changes mid-run: after
  ``task.block.trial`` trials an obstacle blocks the route of the best policy, the optimizer
  re-evaluates its stored policies there (``optimizer.reevaluate``, one trial each) and goes
  on; TensorBoard gets the policies' paths before and after (``block/before``,
  ``block/after``), the scalars go on across the block, ``results.json`` says what happened
  (``block``).
* ``train.log`` -- the run's log lines (Hydra's job logging; also on stdout, with the final
  summary). TensorBoard's HPARAMS tab gets the flattened config with the final best return,
  number of policies and trials.

Config: ``configs/*.yaml`` extend the structured configs of ``dipole_torch.config``, so a
value of the wrong type fails when the config is composed, naming its key;
``python train.py --help`` lists every field. ``check_config`` checks what types cannot say.

Trial budget: a run evaluates exactly ``trials``. The batch (one sample per active policy,
plus DIPOLE's scouts and probes) that would cross it is cut to its first rows (``tell``
takes the first rows of an ask); the checkpoint keeps the run before that batch, so a resume
with a larger budget makes the draws an uninterrupted run would have made.

Reliability (README's "Reliability"): every output file is written under a temporary name
and moved into place (``dipole_torch.checkpoint``), so ``kill -9`` at any moment leaves the
previous complete file; SIGTERM and SIGINT finish the current iteration, write a checkpoint,
print the command that resumes and exit with status 128 + the signal number (143, 130);
``resume=`` loads with ``torch.load(weights_only=True)``, refuses a checkpoint whose task,
dimension, reward range or algorithm settings differ from the config (naming the keys), and
continues in the checkpoint's directory with the checkpoint's seed.
"""

from __future__ import annotations

import json
import logging
import math
import os
import re
import shlex
import signal
import sys
import time
from pathlib import Path

import hydra
import torch
from hydra.core.hydra_config import HydraConfig
from hydra.utils import instantiate
from omegaconf import DictConfig, OmegaConf
from torch.utils.tensorboard import SummaryWriter
from tqdm import tqdm

import dipole_torch.config  # noqa: F401 (registers the schemas configs/ extends)
from dipole_torch import Dipole
from dipole_torch.checkpoint import (
    CheckpointError,
    atomic_save,
    atomic_write_text,
    config_differences,
    flatten,
    load_checkpoint,
    remove_stale_temporaries,
)

log = logging.getLogger("train")  # Hydra's job logging: stdout and the run's train.log

CHECKPOINT_KEYS = ("optimizer", "task_generator", "history", "config")
OUTPUTS = ("checkpoint.pt", "results.json", "policies.pt")  # each written atomically
# Config keys a resumed run may change: the budget, where and how fast it runs, what it
# prints. Everything else (task, its dimension and reward range, algorithm and settings)
# must match the checkpoint. The seed follows the checkpoint (see load_resume).
RESUME_MAY_CHANGE = (
    "trials",
    "task.trials",
    "device",
    "task.env.device",
    "threads",
    "checkpoint_every",
    "figure_every",
    "resume",
    "progress",
    "seed",
)
# Keys added to the configs after checkpoints were written, with the values that reproduce
# the runs that wrote them: such a checkpoint resumes (where this config has the key).
ADDED_KEYS = {
    "task.env.obstacles": [],
    "task.env.penetration_scale": 0.02,
    "task.block": None,
    "algo.optimizer.pair_points": 1,
    "algo.optimizer.bounds": None,
    # Runs from before it drew fresh auxiliary components; "auto" does too below D = 31 (and
    # above, re-uses them: another exact sampler of the same clustering).
    "algo.optimizer.auxiliary": "auto",
    # Runs from before it sampled every active policy in every iteration.
    "algo.optimizer.max_sampled": None,
    # Runs from before the engines rolled out in torch, and resume with
    # the default engine (on a CPU the Python episodes of cart-pole and mountain car, whose
    # returns differ from torch's only where rounding moves a trajectory across a
    # threshold, and the viapoint task's float64 numpy rollouts, ~1e-7 from float32 torch's).
    "task.env.engine": "auto",
}
# Task classes that moved (top-level tasks/ became dipole_torch.tasks): a checkpoint whose
# config names the old module resumes.
MOVED_PREFIXES = {"tasks.": "dipole_torch.tasks."}

# On resume, Hydra's run directory is the checkpoint's (unless hydra.run.dir is given) and
# Hydra's own record goes to .hydra/resume_<time>, keeping the original run's .hydra/.
OmegaConf.register_new_resolver(
    "checkpoint_dir",
    lambda resume, fresh: fresh if not resume else str(_run_dir_of(Path(resume))),
    replace=True,
)
OmegaConf.register_new_resolver(
    "if_resumed", lambda resume, resumed, fresh: resumed if resume else fresh, replace=True
)


def _run_dir_of(resume: Path) -> Path:
    return resume if resume.is_dir() else resume.parent  # a directory is refused later


def check_config(cfg: DictConfig) -> None:
    """Reject values that have the right type but not a valid value, naming the key.

    Types are checked earlier, when Hydra composes the config against the schemas of
    ``dipole_torch.config`` (OmegaConf's ``ValidationError`` names the key); Hydra rejects
    unknown task/algo names, listing the available ones. The optimizers and tasks check their
    own arguments' ranges when they are built."""
    if cfg.trials < 1:
        raise ValueError(
            f"trials (the trial budget) must be a positive integer, got {cfg.trials!r}"
        )
    if cfg.seed < 0:
        raise ValueError(f"seed must be a non-negative integer, got {cfg.seed!r}")
    if cfg.task.n0 < 1:
        raise ValueError(
            f"task.n0 (initial samples) must be a positive integer, got {cfg.task.n0!r}"
        )
    if cfg.resume is None and cfg.trials < cfg.task.n0:
        raise ValueError(
            f"trials={cfg.trials} is below task.n0={cfg.task.n0}: the first batch (n0 trials) "
            "would exceed the trial budget"
        )
    for key in ("threads", "checkpoint_every"):
        if cfg[key] < 1:
            raise ValueError(f"{key} must be a positive integer, got {cfg[key]!r}")
    if cfg.figure_every < 0:
        raise ValueError(f"figure_every must be a non-negative integer, got {cfg.figure_every!r}")
    device = str(cfg.device)
    if not re.fullmatch(r"cpu|cuda(:\d+)?", device):
        raise ValueError(f"device must be 'cpu', 'cuda' or 'cuda:N', got {device!r}")
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ValueError(f"device={device!r} but CUDA is not available on this machine")
        index = int(device.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            raise ValueError(
                f"device={device!r} but this machine has {torch.cuda.device_count()} CUDA device(s)"
            )
    block = cfg.task.get("block")
    if block is not None and block.trial < cfg.task.n0:
        raise ValueError(
            f"task.block.trial={block.trial} is below task.n0={cfg.task.n0}: the block "
            "re-evaluates learned policies, after the first batch at least"
        )
    if cfg.resume is not None and not cfg.resume:
        raise ValueError(f"resume must be the path of a checkpoint.pt, got {cfg.resume!r}")


def load_resume(cfg: DictConfig) -> dict:
    """Load ``cfg.resume`` safely and check it against ``cfg``; adopt its seed.

    Raises ``CheckpointError`` (a ``ValueError``) naming the file for a missing, truncated
    or unsafe file or another kind of file (e.g. ``policies.pt``), and naming the keys
    whose values differ from the checkpoint's config.
    """
    checkpoint = load_checkpoint(
        cfg.resume,
        required=CHECKPOINT_KEYS,
        kind="train.py checkpoint",
        hint="Resume from the checkpoint.pt of a run (policies.pt holds only its result).",
    )
    saved = checkpoint["config"]
    saved = OmegaConf.to_container(OmegaConf.create(saved)) if isinstance(saved, str) else saved
    if not isinstance(saved, dict):
        raise CheckpointError(f"{cfg.resume!r} holds no config (got {type(saved).__name__})")
    current = OmegaConf.to_container(cfg, resolve=True)
    filled = {}  # keys the checkpoint predates, with the values its run had
    for key, value in ADDED_KEYS.items():
        if key in flatten(current) and key not in flatten(saved):
            *parents, leaf = key.split(".")
            node = saved
            for parent in parents:
                node = node.setdefault(parent, {})
            node[leaf] = filled[key] = value
    env = saved.get("task", {}).get("env")
    target = env.get("_target_") if isinstance(env, dict) else None
    for old, new in MOVED_PREFIXES.items():
        if isinstance(target, str) and target.startswith(old):
            env["_target_"] = new + target.removeprefix(old)
    differences = config_differences(saved, current, ignore=RESUME_MAY_CHANGE)
    if differences:
        # The group choices (task.name, algo.name) first, then the settings.
        differences.sort(key=lambda d: (not d[0].endswith(".name"), d[0]))
        shown = [f"{key} ({a!r} in the checkpoint, {b!r} now)" for key, a, b in differences[:8]]
        if len(differences) > 8:
            shown.append(
                f"and {len(differences) - 8} more: " + ", ".join(k for k, *_ in differences[8:])
            )
        command = checkpoint.get("overrides")
        if command is not None:
            # A key added since, whose default has changed too (algo.optimizer.max_sampled):
            # the run resumes with the value it had.
            command = command + [
                f"{key}={json.dumps(filled[key])}" for key, *_ in differences if key in filled
            ]
        raise CheckpointError(
            f"cannot resume {cfg.resume!r}: the config differs from the checkpoint's in "
            f"{len(differences)} key(s) that must match: {'; '.join(shown)}. "
            + (
                f"The checkpoint's run resumes with: {resume_command(command, cfg.resume)}"
                if command is not None
                else "Give the run's own settings."
            )
        )
    seed = saved.get("seed", cfg.seed)
    if seed != cfg.seed:
        overridden = any(o.split("=", 1)[0].lstrip("+~") == "seed" for o in _overrides())
        if overridden:
            raise CheckpointError(
                f"cannot resume {cfg.resume!r} with seed={cfg.seed}: the checkpoint's run has "
                f"seed={seed}, and a resumed run keeps its seed (drop seed=)"
            )
        cfg.seed = seed
    return checkpoint


def restore(checkpoint: dict, path: str, optimizer, task_generator, shape: dict):
    """Load the checkpoint's optimizer and episode-generator states; return its history and
    elapsed wall time. ``shape``: this config's task dimension and reward range, which must
    be the checkpoint's."""
    saved = {key: checkpoint.get(key, shape[key]) for key in shape}
    saved["reward_range"] = saved["reward_range"] and tuple(saved["reward_range"])
    if saved != shape:
        raise CheckpointError(
            f"cannot resume {path!r}: the checkpoint's task has {saved}, this config's {shape}"
        )
    try:
        optimizer.load_state_dict(checkpoint["optimizer"])
        task_generator.set_state(checkpoint["task_generator"])
    except (KeyError, ValueError, TypeError, RuntimeError) as error:
        raise CheckpointError(
            f"{path!r} does not fit this optimizer ({type(error).__name__}: {error})"
        ) from None
    return checkpoint["history"], float(checkpoint.get("wall_time_s", 0.0))


def _overrides() -> list[str]:
    return list(HydraConfig.get().overrides.task)


def resume_command(overrides: list[str], checkpoint: str | Path) -> str:
    """The shell command that resumes this run from ``checkpoint``: ``python train.py ...``,
    or ``dipole-train ...`` when the run was started by that command."""
    program = sys.argv[0] or "train.py"
    launcher = ["python", program] if program.endswith(".py") else [Path(program).name]
    keep = [
        o
        for o in overrides
        if o.split("=", 1)[0].lstrip("+~") not in ("resume", "hydra.run.dir", "hydra.output_subdir")
    ]
    return shlex.join([*launcher, *keep, f"resume={checkpoint}"])


class StopRequest:
    """SIGTERM / SIGINT handler: ask the loop to checkpoint and stop after this iteration.

    A second signal stops at once (``KeyboardInterrupt``); the files on disk are then the
    last complete ones, since every write is atomic.
    """

    def __init__(self) -> None:
        self.signum: int | None = None
        self._previous: dict[int, object] = {}

    def __call__(self, signum: int, frame) -> None:
        if self.signum is not None:
            raise KeyboardInterrupt(f"second {signal.Signals(signum).name}")
        self.signum = signum
        # os.write, not print: the handler may interrupt a print (tqdm's) to the same stream.
        message = (
            f"\n{signal.Signals(signum).name} received: finishing this iteration, then writing "
            "a checkpoint (send it again to stop at once)\n"
        )
        os.write(sys.stderr.fileno(), message.encode())

    def __enter__(self) -> StopRequest:
        for signum in (signal.SIGTERM, signal.SIGINT):
            try:
                self._previous[signum] = signal.signal(signum, self)
            except ValueError:  # not the main thread (e.g. a threaded Hydra launcher)
                pass
        return self

    def __exit__(self, *exc) -> None:
        for signum, handler in self._previous.items():
            signal.signal(signum, handler)


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


def ask_within_budget(optimizer, budget: int):
    """The next batch, or ``None`` when evaluating it would take the run past ``budget`` trials.

    A batch crossing the budget is taken back: the optimizer is restored to its state before
    the ask (its generator included), so that asking again proposes the same batch, and a run
    resumed with a larger budget makes the draws an uninterrupted one would have made."""
    generator_state = optimizer.generator.get_state()
    theta = optimizer.ask()
    if optimizer.trials + theta.shape[0] <= budget:
        return theta
    state = optimizer.state_dict()
    state.update(generator=generator_state, pending=None, pending_owner=None)
    optimizer.load_state_dict(state)
    return None


def block_the_route(task, optimizer, block: DictConfig, writer: SummaryWriter, generator):
    """The world changes (``task.block``): an obstacle appears on the route of the best policy.

    The optimizer evaluates its stored policies once each in the new world and is told
    (``reevaluate``, K trials): its best policy mean becomes the policy it executes, policies
    the obstacle hurt search again. Returns the blocked task and what happened (for the
    checkpoint and ``results.json``)."""
    means = optimizer.policy_means.to(task.device, task.dtype)
    trial = optimizer.trials
    title = f"before the block: {len(means)} policies after {trial} trials"
    writer.add_figure("block/before", task.plot_policies(means, title=title), trial)
    obstacle, description = task.blocking_obstacle(means, block.radius, block.threshold)
    task = task.with_obstacles([*task.obstacles, obstacle])
    returns = task.evaluate(means, generator=generator)
    optimizer.reevaluate(returns)
    switched = int(returns.argmax())
    title = f"after the block: the same policies, re-evaluated ({optimizer.trials} trials)"
    writer.add_figure("block/after", task.plot_policies(means, title=title), optimizer.trials)
    lines = task.describe_policies(means)
    report = (
        f"block at {trial} trials: {description}; the {len(means)} stored policies "
        f"re-evaluated (now {optimizer.trials} trials), switching to policy {switched}: "
        + "\n  ".join(["", *(f"policy {k}: {line}" for k, line in enumerate(lines))])
    )
    log.info(report)
    writer.add_text("block", report.replace("\n", "  \n"), optimizer.trials)
    info = {
        "trial": trial,
        "obstacle": obstacle,
        "description": description,
        "returns": returns.double().tolist(),
        "switched_to": switched,
    }
    return task, info


def log_hparams(writer: SummaryWriter, cfg: DictConfig, results: dict) -> None:
    """TensorBoard's HPARAMS tab: the flattened config (``algo.optimizer.alpha``, ...) with
    the final metrics, in the run's tensorboard directory."""
    config = flatten(OmegaConf.to_container(cfg, resolve=True))
    # TensorBoard takes numbers, strings and booleans: lists and null as text.
    hparams = {
        key: value if isinstance(value, bool | int | float | str) else json.dumps(value)
        for key, value in config.items()
    }
    metrics = {
        "hparam/best_reward": results["best_reward"],
        "hparam/num_policies": len(results["policies"]),
        "hparam/trials": results["trials"],
    }
    writer.add_hparams(hparams, metrics, run_name=".", global_step=results["trials"])


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


# An absolute config path: main() also runs when train.py is imported (tests, drivers), and
# as dipole_torch.train (the dipole-train command), where configs/ is dipole_torch/configs/.
@hydra.main(
    version_base=None, config_path=str(Path(__file__).parent / "configs"), config_name="config"
)
def main(cfg: DictConfig) -> dict:
    check_config(cfg)
    torch.set_num_threads(cfg.threads)
    out = Path(HydraConfig.get().runtime.output_dir)
    checkpoint = load_resume(cfg) if cfg.resume else None  # may adopt the checkpoint's seed
    if checkpoint is None and (out / "checkpoint.pt").exists():
        raise CheckpointError(
            f"{out} already holds a run's checkpoint.pt; continue it with "
            f"resume={out / 'checkpoint.pt'}, or choose another hydra.run.dir"
        )
    remove_stale_temporaries(out, OUTPUTS)  # left by a session killed mid-write
    task = instantiate(cfg.task.env)
    generator = torch.Generator().manual_seed(cfg.seed)  # the optimizer's draws
    # Episodes' random starts: a CPU generator (the tasks draw on the CPU, then move).
    task_generator = torch.Generator().manual_seed(cfg.seed + 1_000_003)
    reward_range = tuple(task.reward_range) if cfg.algo.use_task_reward_range else None
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
    history: list[dict] = []
    elapsed = 0.0  # wall time of the run's earlier sessions
    block, blocked = cfg.task.get("block"), None  # viapoint_blocked: the world changes
    if checkpoint is not None:
        history, elapsed = restore(checkpoint, cfg.resume, optimizer, task_generator, shape)
        blocked = checkpoint.get("block")
        if blocked is not None:  # the checkpoint's world: with the obstacle
            task = task.with_obstacles([*task.obstacles, blocked["obstacle"]])
        log.info(f"resumed {cfg.resume} at {optimizer.trials} trials (seed {cfg.seed})")
    # purge_step hides events that a killed session logged after its last checkpoint.
    writer = SummaryWriter(
        str(out / "tensorboard"), purge_step=optimizer.trials + 1 if checkpoint else None
    )
    writer.add_text("config", f"```\n{OmegaConf.to_yaml(cfg)}\n```")
    checkpoint_path = out / "checkpoint.pt"
    start = time.perf_counter()

    # Weights-only loadable: tensors, dicts, lists, strings and numbers (the config as YAML).
    config_yaml, overrides = OmegaConf.to_yaml(cfg, resolve=True), _overrides()

    def save_checkpoint() -> None:
        # Written under a temporary name and moved into place: never a partial file.
        atomic_save(
            {
                "optimizer": optimizer.state_dict(),
                "task_generator": task_generator.get_state(),
                "history": history,
                "config": config_yaml,
                "overrides": overrides,
                "wall_time_s": elapsed + time.perf_counter() - start,
                "block": blocked,
                **shape,
            },
            checkpoint_path,
        )

    bar = tqdm(total=cfg.trials, initial=optimizer.trials, unit="trial", disable=not cfg.progress)
    figure_trials = None  # trials at the last policy figure logged
    last_batch_cut = False
    with StopRequest() as stop:
        while optimizer.trials < cfg.trials and stop.signum is None:
            block_due = block is not None and blocked is None and block.trial < cfg.trials
            theta = ask_within_budget(optimizer, block.trial if block_due else cfg.trials)
            if theta is None and block_due:  # the next batch would cross the block
                trials = optimizer.trials
                if trials + optimizer.num_policies > cfg.trials:
                    log.info(f"no block: re-evaluating would take the run past {cfg.trials}")
                    break
                task, blocked = block_the_route(task, optimizer, block, writer, task_generator)
                history.append(log_iteration(writer, optimizer, len(history)))
                bar.update(optimizer.trials - trials)
                continue
            if theta is None:
                # The batch crossing the budget: its first rows end the run at the budget
                # exactly. The checkpoint keeps the run before it, so that a resume with a
                # larger budget makes the draws of an uninterrupted run.
                save_checkpoint()
                theta = optimizer.ask()  # the same batch: ask_within_budget restored the state
                log.info(
                    f"the last batch is cut to its first {cfg.trials - optimizer.trials} of "
                    f"{theta.shape[0]} rows, to end at {cfg.trials} trials"
                )
                theta, last_batch_cut = theta[: cfg.trials - optimizer.trials], True
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
                    figure_trials = optimizer.trials
            if len(history) % cfg.checkpoint_every == 0 and not last_batch_cut:
                save_checkpoint()
        bar.close()
        if not last_batch_cut:
            save_checkpoint()
        if stop.signum is not None:
            writer.close()
            name = signal.Signals(stop.signum).name
            log.info(
                f"\nstopped by {name} at {optimizer.trials} of {cfg.trials} trials; "
                f"checkpoint written to {checkpoint_path}\nresume with:\n  "
                f"{resume_command(overrides, checkpoint_path)}"
            )
            raise SystemExit(128 + stop.signum)

    if figure_trials != optimizer.trials:  # the final policies, unless just drawn
        figure = task.plot_policies(optimizer.policy_means.to(task.device, task.dtype))
        if figure is not None:
            writer.add_figure("policies/figure", figure, optimizer.trials)
    policies = policy_summary(task, optimizer)
    artefacts = {"policies": optimizer.policies.state_dict()}
    if isinstance(optimizer, Dipole):
        artefacts["mixture"] = optimizer.mixture.state_dict()
    atomic_save(artefacts, out / "policies.pt")
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
        "policies": policies,
        **({"block": blocked} if blocked is not None else {}),
        "history": {key: [row[key] for row in history] for key in history[0]} if history else {},
    }
    atomic_write_text(out / "results.json", json.dumps(results, indent=1, allow_nan=False))
    log_hparams(writer, cfg, results)
    writer.close()
    # The summary: on stdout (plain) and in train.log, like every log line.
    summary = [
        f"\n{cfg.algo.name} on {cfg.task.name}: best return {best_reward:.4g} in "
        f"{optimizer.trials} trials (budget {cfg.trials}); {len(policies)} policies (return "
        "of each mean):"
    ]
    for k, policy in sorted(enumerate(policies), key=lambda kp: -kp[1]["return_of_mean"]):
        text = f"  policy {k}: return {policy['return_of_mean']:.4g}"
        if policy["description"]:
            text += f"  {policy['description']}"
        summary.append(text)
    summary.append(f"outputs in {out}")
    log.info("\n".join(summary))
    assert math.isfinite(best_reward)
    return results


if __name__ == "__main__":
    main()

"""Checkpoints of a training run, and resuming one exactly.

A checkpoint (``checkpoint.pt``, written atomically with an integrity digest by
``dipole_torch.checkpoint.atomic_save``) holds the optimizer's state, the episode
generator's, the history, the config as resolved YAML and the overrides of the command that
started the run. ``resume=<path>`` loads it safely, checks it against the config (naming the
keys that must match and printing the command that resumes the run as it ran), continues in
its directory with its seed, and makes exactly the draws the uninterrupted run would have.
"""

from __future__ import annotations

import hashlib
import json
import re
import shlex
import sys
from collections.abc import Iterable, Mapping
from pathlib import Path
from typing import Any

import torch
import yaml
from omegaconf import DictConfig, OmegaConf

from dipole_torch.checkpoint import CheckpointError, atomic_save, load_checkpoint
from dipole_torch.mechanisms.exploration import IGEL_TARGET_SUCCESS
from dipole_torch.options import PAPER_INERT
from dipole_torch.training.hydra_compat import register_resolver

__all__ = [
    "CHECKPOINT_KEYS",
    "Checkpointer",
    "config_differences",
    "flatten",
    "load_resume",
    "register_resolvers",
    "restore",
    "resume_command",
]

CHECKPOINT_KEYS = ("optimizer", "task_generator", "history", "config")
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
    # Runs from before the engines rolled out in torch, and resume with the default engine.
    "task.env.engine": "auto",
    # Runs from before DIPOLE's matching was an option: the default variant's.
    "algo.optimizer.matching": "overlap",
    # Runs from before retired policies were woken to refine them.
    "algo.optimizer.refine": 0.0,
    "algo.optimizer.refine_share": 0.2,
    # Runs from before a clustering could end once its partition settled.
    "algo.optimizer.settle": None,
    # Runs from before restarts could draw uniformly in a finite box.
    "algo.optimizer.restarts": "start",
    # Runs from before a clustering of scouts alone ran one sweep.
    "algo.optimizer.scout_sweeps": None,
    # Runs from before the policies accepted unjudged could be held to a share.
    "algo.optimizer.unjudged_share": None,
    # Runs from before a policy could retire on the spread of its kept returns.
    "algo.optimizer.retire_spread": 0.0,
    # Runs from before the coverage options could start at a trial.
    "algo.optimizer.coverage_from": None,
    # Runs from before the covering phase could have a cap of its own.
    "algo.optimizer.coverage_max_policies": None,
    # Runs from before the wakes went to the policies near the best return first (and
    # before the opt-in wakes beside active policies and cap on a new policy's exploration).
    "algo.optimizer.refine_gate": 1.0,
    "algo.optimizer.wake_while_active": False,
    "algo.optimizer.start_cap": 0.0,
    # Runs from before the success rule's target rate was an option (Igel et al.'s 2/11).
    "algo.optimizer.success_target": IGEL_TARGET_SUCCESS,
    # Runs from before a kept sample could be evaluated again (every return trusted).
    "algo.optimizer.best_evaluations": 1,
}
# Keys an algorithm's config no longer has, whose values changed nothing in its runs: a
# checkpoint that has them resumes without them (``algo=dipole_paper`` listed the options
# its algorithm leaves inert until they were dropped from its schema).
DROPPED_KEYS = {"dipole_paper": tuple(f"algo.optimizer.{key}" for key in PAPER_INERT)}
# Task classes that moved (top-level tasks/ became dipole_torch.tasks): a checkpoint whose
# config names the old module resumes.
MOVED_PREFIXES = {"tasks.": "dipole_torch.tasks."}


def register_resolvers() -> None:
    """The resolvers ``configs/config.yaml`` uses: a resumed run's Hydra run directory is the
    checkpoint's (unless ``hydra.run.dir`` is given), and Hydra's own record goes to
    ``.hydra/resume_<time>``, keeping the original run's ``.hydra/`` (``record_subdir``); a
    sweep's run directory is named by its settings (``setting_suffix``)."""
    register_resolver(
        "checkpoint_dir",
        lambda resume, fresh: fresh if not resume else str(_run_dir_of(Path(resume))),
    )
    register_resolver("record_subdir", record_subdir)
    register_resolver("setting_suffix", setting_suffix)


def record_subdir(resume, output_dir: str, time: str) -> str:
    """Where Hydra writes a run's record (its config and overrides) in the run directory:
    ``.hydra`` for a new run; ``.hydra/resume_<time>`` for a resumed one, keeping the
    original's; ``.hydra/refused_<time>`` for a new run into a directory that holds a run's
    checkpoint, which train.py refuses and then removes that record (Hydra writes it before
    the run starts: written to ``.hydra``, it relabelled the finished run)."""
    if resume:
        return f".hydra/resume_{time}"
    if (Path(output_dir) / "checkpoint.pt").exists():
        return f".hydra/refused_{time}"
    return ".hydra"


# Overrides that do not name a sweep's run directory: those in its name already (task, algo,
# seed) and the run's settings that a resume may change (the budget, device, threads, ...).
NOT_IN_DIRECTORY_NAMES = ("task", "algo", *RESUME_MAY_CHANGE)


def setting_suffix(overrides) -> str:
    """A sweep run's directory name after ``<task>_<algo>_seed<seed>``: ``_`` and its other
    settings from the command line (``_algo.optimizer.M=4``), sorted, so that the runs of a
    sweep over a hyperparameter do not share one directory; ``""`` where there are none
    (a sweep over seeds, tasks or algorithms, or with another budget)."""
    settings = sorted(
        str(o).replace("/", "_")
        for o in overrides
        if str(o).split("=", 1)[0].lstrip("+~") not in NOT_IN_DIRECTORY_NAMES
    )
    suffix = "_" + ",".join(settings) if settings else ""
    if len(suffix.encode()) > MAX_SUFFIX_BYTES:
        # A file name holds 255 bytes: the start of the settings, then a digest of them all
        # (runs that differ only past the cut still get directories of their own).
        digest = hashlib.sha1(suffix.encode()).hexdigest()[:10]
        start = suffix.encode()[: MAX_SUFFIX_BYTES - 12].decode(errors="ignore")
        suffix = f"{start}~{digest}"
    return suffix


# A sweep run's directory name after <task>_<algo>_seed<seed>: room left within a file name's
# 255 bytes for the longest task and algorithm names.
MAX_SUFFIX_BYTES = 160


def _run_dir_of(resume: Path) -> Path:
    return resume if resume.is_dir() else resume.parent  # a directory is refused later


def flatten(tree: Mapping, prefix: str = "") -> dict[str, Any]:
    """``{"a": {"b": 1}}`` → ``{"a.b": 1}``; lists are leaves."""
    flat: dict[str, Any] = {}
    for key, value in tree.items():
        name = f"{prefix}{key}"
        if isinstance(value, Mapping) and value:
            flat.update(flatten(value, f"{name}."))
        else:
            flat[name] = value
    return flat


def config_differences(
    saved: Mapping, current: Mapping, ignore: Iterable[str] = ()
) -> list[tuple[str, Any, Any]]:
    """``[(key, saved value, current value)]`` for every dotted key whose values differ
    (a key present in only one side has ``<missing>`` on the other), except keys in
    ``ignore`` and keys under an ignored prefix (``"hydra"`` ignores ``"hydra.run.dir"``)."""
    ignore = tuple(ignore)
    a, b = flatten(saved), flatten(current)
    differences = []
    for key in sorted(set(a) | set(b)):
        if any(key == skip or key.startswith(f"{skip}.") for skip in ignore):
            continue
        left, right = a.get(key, "<missing>"), b.get(key, "<missing>")
        if left != right:
            differences.append((key, left, right))
    return differences


def load_resume(cfg: DictConfig, overrides: list[str]) -> dict:
    """Load ``cfg.resume`` safely and check it against ``cfg``; adopt its seed.

    Raises ``CheckpointError`` (a ``ValueError``) naming the file for a missing, truncated,
    corrupt or unsafe file, another kind of file (e.g. ``policies.pt``) or contents of the
    wrong kind, and naming the keys whose values differ from the checkpoint's config, with
    the command that resumes the run as it ran.
    """
    path = cfg.resume
    checkpoint = load_checkpoint(
        path,
        required=CHECKPOINT_KEYS,
        kind="train.py checkpoint",
        hint="Resume from the checkpoint.pt of a run (policies.pt holds only its result).",
    )
    _check_contents(checkpoint, path)
    saved = _saved_config(checkpoint["config"], path)
    current = OmegaConf.to_container(cfg, resolve=True)
    filled = {}  # keys the checkpoint predates, with the values its run had
    for key, value in ADDED_KEYS.items():
        if key in flatten(current) and key not in flatten(saved):
            *parents, leaf = key.split(".")
            node = saved
            for parent in parents:
                node = node.setdefault(parent, {})
            node[leaf] = filled[key] = value
    algo = saved.get("algo", {})
    optimizer = algo.get("optimizer") if isinstance(algo, dict) else None
    for key in DROPPED_KEYS.get(algo.get("name") if isinstance(algo, dict) else None, ()):
        if isinstance(optimizer, dict) and key not in flatten(current):
            optimizer.pop(key.removeprefix("algo.optimizer."), None)
    env = saved.get("task", {}).get("env")
    target = env.get("_target_") if isinstance(env, dict) else None
    for old, new in MOVED_PREFIXES.items():
        if isinstance(target, str) and target.startswith(old):
            env["_target_"] = new + target.removeprefix(old)
    differences = config_differences(saved, current, ignore=RESUME_MAY_CHANGE)
    if differences:
        raise CheckpointError(_mismatch(path, differences, checkpoint.get("overrides")))
    seed = saved.get("seed", cfg.seed)
    if seed != cfg.seed:
        if any(o.split("=", 1)[0].lstrip("+~") == "seed" for o in overrides):
            raise CheckpointError(
                f"cannot resume {path!r} with seed={cfg.seed}: the checkpoint's run has "
                f"seed={seed}, and a resumed run keeps its seed (drop seed=)"
            )
        cfg.seed = seed
    return checkpoint


def _check_contents(checkpoint: dict, path: str) -> None:
    """Refuse contents of the wrong kind before anything is built from them."""
    kinds = {"optimizer": dict, "history": list, "config": (str, dict), "overrides": list}
    for key, kind in kinds.items():
        if (
            key in checkpoint
            and checkpoint[key] is not None
            and not isinstance(checkpoint[key], kind)
        ):
            raise CheckpointError(
                f"{path!r} holds a {type(checkpoint[key]).__name__} as its {key!r}, not a "
                f"train.py checkpoint's {getattr(kind, '__name__', 'str or dict')}"
            )
    if not all(isinstance(row, dict) for row in checkpoint["history"]):
        raise CheckpointError(f"{path!r}: its 'history' is not a list of dicts")


def _saved_config(saved, path: str) -> dict:
    """The checkpoint's config as a plain dict (OmegaConf's safe YAML loader: a Python tag
    is an error, not an object)."""
    if isinstance(saved, str):
        try:
            saved = OmegaConf.to_container(OmegaConf.create(saved))
        except (yaml.YAMLError, ValueError, TypeError) as error:
            first = str(error).splitlines()[0]
            raise CheckpointError(
                f"{path!r} holds a config that is not plain YAML ({first})"
            ) from None
    if not isinstance(saved, dict):
        raise CheckpointError(f"{path!r} holds no config (got {type(saved).__name__})")
    return saved


def _mismatch(path: str, differences: list, overrides: list[str] | None) -> str:
    """The message of a resume whose config differs from the checkpoint's, naming the keys
    (the group choices first) and giving the command that resumes the run as it ran."""
    differences.sort(key=lambda d: (not d[0].endswith(".name"), d[0]))
    shown = [f"{key} ({a!r} in the checkpoint, {b!r} now)" for key, a, b in differences[:8]]
    if len(differences) > 8:
        rest = ", ".join(key for key, *_ in differences[8:])
        shown.append(f"and {len(differences) - 8} more: {rest}")
    message = (
        f"cannot resume {path!r}: the config differs from the checkpoint's in "
        f"{len(differences)} key(s) that must match: {'; '.join(shown)}. "
    )
    if overrides is None:
        return message + "Give the run's own settings."
    # The run's own command, plus the value it had of every key whose default has moved
    # since (the group choices are in the command already, and with them the keys of a group
    # chosen otherwise now: task=cartpole against a viapoint run differs in all of task.*).
    given = {o.split("=", 1)[0].lstrip("+~") for o in overrides}
    regrouped = tuple(key.removesuffix("name") for key, *_ in differences if key.endswith(".name"))
    moved = [
        f"{key}={json.dumps(saved)}"
        for key, saved, _ in differences
        if key not in given
        and not key.endswith(".name")
        and not key.startswith(regrouped)
        and saved != "<missing>"
    ]
    return message + f"The checkpoint's run resumes with: {resume_command(overrides + moved, path)}"


def restore(checkpoint: dict, path: str, optimizer, task_generator, shape: dict, budget: int):
    """Load the checkpoint's optimizer and episode-generator states; return its history,
    elapsed wall time and block (``None``: the world did not change). ``shape``: this
    config's task dimension and reward range, which must be the checkpoint's; ``budget``:
    this config's ``trials``, at least the checkpoint's and the trials its run ended at
    (at the checkpoint's, nothing runs and the results are written from it: a session
    killed before it wrote them)."""
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
    # A run whose last batch was cut at its budget ended past its checkpoint (Checkpointer).
    ended = int(checkpoint.get("run_trials", optimizer.trials))
    if optimizer.trials > budget:
        held = f"holds {optimizer.trials} trials already"
    elif ended > budget:
        held = (
            f"ended at {ended} trials (its checkpoint keeps it at {optimizer.trials}, before "
            "the last batch, cut at that budget)"
        )
    else:
        held = None
    if held:
        raise CheckpointError(
            f"cannot resume {path!r} with trials={budget}: its run {held}, and a run cannot "
            f"go back; give trials={max(ended, optimizer.trials)} or more"
        )
    return checkpoint["history"], float(checkpoint.get("wall_time_s", 0.0)), checkpoint.get("block")


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
    return shlex.join([*launcher, *keep, resume_override(checkpoint)])


def resume_override(checkpoint: str | Path) -> str:
    """``resume=<checkpoint>`` as Hydra parses it: a path with characters of the override
    grammar (a sweep's directory ``..._seed0_algo.optimizer.alpha=2``) in double quotes,
    where Hydra read ``=`` as the override's own."""
    path = str(checkpoint)
    if re.fullmatch(r"[\w./~:+@%-]*", path):
        return f"resume={path}"
    return 'resume="' + path.replace("\\", "\\\\").replace('"', '\\"') + '"'


class Checkpointer:
    """Writes a run's ``checkpoint.pt`` (atomically, with its digest).

    Args:
        path: the file.
        config_yaml: the resolved config (weights-only loadable, unlike a DictConfig).
        overrides: the command's overrides (to print the resume command).
        shape: the task's dimension and reward range (checked on resume).
    """

    def __init__(self, path: Path, config_yaml: str, overrides: list[str], shape: dict):
        self.path, self.config_yaml = path, config_yaml
        self.overrides, self.shape = overrides, shape
        self.trials: int | None = None  # the trials of the last checkpoint written

    def save(
        self,
        optimizer,
        task_generator: torch.Generator,
        history: list,
        block: dict | None,
        wall_time_s: float,
        figure_trials: int | None = None,
        run_trials: int | None = None,
    ) -> None:
        """``figure_trials``: the trial count of the run's latest policy figure (a resumed
        run at that count does not draw it again). ``run_trials``: for the checkpoint written
        before the last batch, cut at the budget, the trials the run ends at: a resume asking
        for fewer would write a shorter run's results over the finished one's, and is
        refused (``restore``)."""
        ended = {} if run_trials is None else {"run_trials": int(run_trials)}
        atomic_save(
            {
                "optimizer": optimizer.state_dict(),
                "task_generator": task_generator.get_state(),
                "history": history,
                "config": self.config_yaml,
                "overrides": self.overrides,
                "wall_time_s": wall_time_s,
                "block": block,
                "figure_trials": figure_trials,
                **self.shape,
                **ended,
            },
            self.path,
        )
        self.trials = optimizer.trials

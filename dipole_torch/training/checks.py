"""Values a config's types cannot refuse, and how a run reports a bad one.

Types are checked when Hydra composes the config against the schemas (OmegaConf names the
key); Hydra refuses an unknown task or algorithm, listing the available ones. What remains
(ranges, whether a device exists, a checkpoint that does not fit) is checked here, by the
optimizers' and tasks' constructors, and on resume: ``reported`` turns each into one
line on stderr naming the key and the value (also written to the run's ``train.log``), and
exit status 2, with no traceback.
"""

from __future__ import annotations

import contextlib
import dataclasses
import difflib
import logging
import os
import re
import sys

import torch
from hydra.errors import InstantiationException
from omegaconf import DictConfig, OmegaConf

from dipole_torch.checkpoint import CheckpointError

__all__ = ["ConfigValueError", "check_command_line", "check_config", "reported"]

EXIT_BAD_CONFIG = 2
# torch.Generator seeds are below 2**64, and train.py seeds the episodes' with seed + 1000003.
SEED_LIMIT = 2**64 - 1_000_003


class ConfigValueError(ValueError):
    """A config value of the right type but not a valid value; the message names the key and
    the value."""

    def __init__(self, key: str, value, message: str):
        super().__init__(message)
        self.key, self.value = key, value


def check_config(cfg: DictConfig) -> None:
    """Refuse values that have the right type but not a valid value, and keys that no schema
    has (added with ``+``, which Hydra suggests for a misspelled key), naming the key."""
    unknown = _unknown_keys(cfg)
    if unknown:
        guess = _closest_key(unknown[0], cfg, unknown)
        hint = f"did you mean {guess}?" if guess else "a misspelling?"
        if guess and guess.split(".")[0] in ("task", "algo") and guess.count(".") == 1:
            hint += " task=<name> and algo=<name> choose the task and the optimizer;"
        raise ConfigValueError(
            unknown[0],
            OmegaConf.select(cfg, unknown[0]),
            f"unknown key(s) {', '.join(unknown)}: no setting of that name ({hint} "
            "python train.py --help lists every key)",
        )
    counts = (
        ("trials", "trials (the trial budget)", 1),
        ("task.n0", "task.n0 (initial samples)", 1),
        ("threads", "threads", 1),
        ("checkpoint_every", "checkpoint_every", 1),
        ("seed", "seed", 0),
        ("figure_every", "figure_every", 0),
    )
    for key, name, least in counts:
        value = OmegaConf.select(cfg, key)
        if value < least:
            kind = "a positive integer" if least else "a non-negative integer"
            raise ConfigValueError(key, value, f"{name} must be {kind}, got {value!r}")
    if cfg.seed >= SEED_LIMIT:
        raise ConfigValueError("seed", cfg.seed, f"seed must be below {SEED_LIMIT}, got {cfg.seed}")
    cores = os.cpu_count() or 1
    if cfg.threads > 4 * cores:  # thousands of threads end the process without a word
        raise ConfigValueError(
            "threads",
            cfg.threads,
            f"threads={cfg.threads} is more than 4 times this machine's {cores} cores "
            "(1 is fastest at these sizes)",
        )
    if cfg.resume is None and cfg.trials < cfg.task.n0:
        raise ConfigValueError(
            "trials",
            cfg.trials,
            f"trials={cfg.trials} is below task.n0={cfg.task.n0}: the first batch (n0 trials) "
            "would exceed the trial budget",
        )
    check_device(str(cfg.device))
    task_device = OmegaConf.select(cfg, "task.env.device")  # ${device} unless set apart
    if isinstance(task_device, str) and task_device != cfg.device:
        check_device(task_device, "task.env.device")
    block = cfg.task.get("block")
    if block is not None and block.trial < cfg.task.n0:
        raise ConfigValueError(
            "task.block.trial",
            block.trial,
            f"task.block.trial={block.trial} is below task.n0={cfg.task.n0}: the block "
            "re-evaluates learned policies, after the first batch at least",
        )
    if block is not None and block.trial >= cfg.trials:
        raise ConfigValueError(
            "task.block.trial",
            block.trial,
            f"task.block.trial={block.trial} is not below trials={cfg.trials}: the run would "
            "end before the world changes; give a larger trials= or a smaller task.block.trial",
        )
    if cfg.resume is not None and not cfg.resume:
        raise ConfigValueError(
            "resume", cfg.resume, f"resume must be the path of a checkpoint.pt, got {cfg.resume!r}"
        )


def check_command_line(argv: list[str], root_keys: list[str]) -> None:
    """Before Hydra composes the config: an override of a key at the config's root that no
    setting has (``trails=60``; ``root_keys``: the settings, the config groups and ``hydra``)
    ends the command with one line naming the nearest key and exit status 2. Hydra's own
    message suggests adding the key (``+trails=60``), which ``check_config`` then refuses: a
    detour. Keys inside a section, and keys added with ``+``, are left to those two."""
    try:
        from hydra._internal.utils import get_args_parser
        from hydra.core.override_parser.overrides_parser import OverridesParser

        parsed, rest = get_args_parser().parse_known_args(argv)
        overrides = OverridesParser.create().parse_overrides(
            [*parsed.overrides, *(a for a in rest if "=" in a and not a.startswith("-"))]
        )
    except Exception:  # noqa: BLE001 (Hydra reports what it cannot parse, in its words)
        return
    for override in overrides:
        key = override.key_or_group
        if override.is_add() or override.is_force_add() or override.is_delete():
            continue
        # (a config group's key is a path: hydra/launcher=joblib)
        if override.package is not None or re.split(r"[./]", key)[0] in root_keys:
            continue
        close = difflib.get_close_matches(key, root_keys, n=1, cutoff=0.6)
        hint = f"did you mean {close[0]}?" if close else "a misspelling?"
        sys.stdout.flush()
        print(
            f"error: unknown key {key} ({override.input_line}): no setting of that name "
            f"({hint} python train.py --help lists every key)",
            file=sys.stderr,
        )
        raise SystemExit(EXIT_BAD_CONFIG)


def _closest_key(key: str, cfg: DictConfig, unknown: list[str]) -> str | None:
    """The known dotted key nearest ``key`` (``unknown``: the keys no schema has): one that
    ends with it (``optimizer``: ``algo.optimizer``), else the closest spelling (``tirals``:
    ``trials``)."""
    known = [k for k in _dotted_keys(cfg) if k not in unknown and not k.startswith("hydra")]
    ending = [k for k in known if k.endswith("." + key)]
    if ending:
        return min(ending, key=len)
    close = difflib.get_close_matches(key, known, n=1, cutoff=0.75)
    return close[0] if close else None


def _dotted_keys(node: DictConfig, prefix: str = "") -> list[str]:
    """Every dotted key under ``node``, its sections included."""
    keys = []
    for key in node.keys():
        keys.append(f"{prefix}{key}")
        child = node._get_node(key)
        if isinstance(child, DictConfig) and not child._is_none() and not child._is_missing():
            keys += _dotted_keys(child, f"{prefix}{key}.")
    return keys


def _unknown_keys(node: DictConfig, prefix: str = "") -> list[str]:
    """The dotted keys under ``node`` that its schema (a dataclass) does not have."""
    unknown = []
    schema = OmegaConf.get_type(node)
    names = (
        {f.name for f in dataclasses.fields(schema)} if dataclasses.is_dataclass(schema) else None
    )
    for key in node.keys():
        if names is not None and key not in names:
            unknown.append(f"{prefix}{key}")
            continue
        child = node._get_node(key)
        if isinstance(child, DictConfig) and not child._is_none() and not child._is_missing():
            unknown += _unknown_keys(child, f"{prefix}{key}.")
    return unknown


def check_device(device: str, key: str = "device") -> None:
    """``cpu``, ``cuda``, ``cuda:N`` (a device this machine has) or ``mps`` (where torch has
    it); ``key``: the config key that holds it (``device``, ``task.env.device``)."""
    if not re.fullmatch(r"cpu|cuda(:\d+)?|mps", device):
        raise ConfigValueError(
            key, device, f"{key} must be 'cpu', 'cuda', 'cuda:N' or 'mps', got {device!r}"
        )
    if device.startswith("cuda"):
        if not torch.cuda.is_available():
            raise ConfigValueError(
                key, device, f"{key}={device!r} but CUDA is not available on this machine"
            )
        index = int(device.partition(":")[2] or 0)
        if index >= torch.cuda.device_count():
            count = torch.cuda.device_count()
            raise ConfigValueError(
                key, device, f"{key}={device!r} but this machine has {count} CUDA device(s)"
            )
    if device == "mps" and not torch.backends.mps.is_available():
        raise ConfigValueError(
            key, device, f"{key}={device!r} but MPS is not available on this machine"
        )


@contextlib.contextmanager
def reported(where: str | None = None):
    """Report a bad value inside the block as one line on stderr and exit with status 2.

    ``where`` names the config node whose constructor runs in the block (``task.env``,
    ``algo.optimizer``): its own errors name the argument, and the line adds the node. With
    ``HYDRA_FULL_ERROR=1`` (Hydra's switch for full tracebacks) the error is raised as it is.
    """
    if os.environ.get("HYDRA_FULL_ERROR") == "1":
        yield
        return
    try:
        yield
    except (ConfigValueError, CheckpointError) as error:
        _exit(str(error))
    except InstantiationException as error:
        cause = error.__cause__ or error
        if not isinstance(cause, ValueError | TypeError | FileNotFoundError):
            raise
        _exit(f"{where}: {_first_line(cause)}" if where else _first_line(cause))
    except (ValueError, TypeError, FileNotFoundError) as error:
        if where is None:
            raise
        _exit(f"{where}: {_first_line(error)}")


def _first_line(error: BaseException) -> str:
    lines = [line for line in str(error).splitlines() if line.strip()]
    return lines[0] if lines else type(error).__name__


def _exit(message: str) -> None:
    sys.stdout.flush()
    line = f"error: {message} (HYDRA_FULL_ERROR=1 for the traceback)"
    print(line, file=sys.stderr)
    # The run's train.log says why the run stopped (the directory exists by now); the line
    # goes to the log's files only, as stderr already shows it on the terminal.
    record = logging.LogRecord("train", logging.ERROR, __file__, 0, line, None, None)
    for handler in logging.getLogger().handlers:
        if isinstance(handler, logging.FileHandler):
            handler.handle(record)
    raise SystemExit(EXIT_BAD_CONFIG)

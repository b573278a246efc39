"""``train.py``'s config: the run's settings, the task and algorithm schemas, their
registration in Hydra's ConfigStore and the ``--help`` page.

``configs/config.yaml`` extends ``Config``; ``configs/task/<name>.yaml`` extends the
task's schema ``dipole_torch_task_<name>`` (its ``name``, ``trials`` and ``n0``, and ``env``:
the task's constructor, ``builds``); ``configs/algo/<name>.yaml``
extends ``dipole_torch_algo_<name>``. A task of your own extends ``dipole_torch_task``
(``env`` untyped: any ``_target_`` with its own arguments).
"""

from __future__ import annotations

import dataclasses
import importlib.resources
import sys
import textwrap
import types
import typing
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

from dipole_torch.training.schemas import _field, _first_sentence, builds

__all__ = ["ALGOS", "TASKS", "AlgoConfig", "Config", "TaskConfig", "help_text", "register"]


@dataclass
class Config:
    """``configs/config.yaml``: one run of an algorithm on a task."""

    task: Any = _field(MISSING, "the task (config group task: configs/task/<name>.yaml)")
    algo: Any = _field(MISSING, "the algorithm (config group algo: configs/algo/<name>.yaml)")
    seed: int = _field(0, "seeds the optimizer's and the task's torch.Generator (>= 0)")
    trials: int = _field(
        "${task.trials}",
        "trial budget: reward evaluations (one trial = one episode); a run evaluates exactly "
        "this many (the batch that would cross it is cut to its first rows)",
    )
    device: str = _field("cpu", "cpu, cuda, cuda:N or mps: rollouts and optimizer")
    threads: int = _field(1, "torch CPU threads; 1 is fastest for these small tensors")
    checkpoint_every: int = _field(20, "iterations between checkpoints (also written at the end)")
    figure_every: int = _field(25, "iterations between policy figures in TensorBoard (0: never)")
    resume: str | None = _field(
        None, "path of a checkpoint.pt: continue that run exactly, in its directory"
    )
    progress: bool = _field(
        True, "progress: a bar on a terminal, else a log line every ~10% of the budget"
    )


@dataclass
class TaskConfig:
    """Every task: a name, a budget, the initial samples and the environment to build."""

    name: str = _field(MISSING, "the task's name (output directories, results.json)")
    trials: int = _field(MISSING, "the task's trial budget (the default of the top-level trials)")
    n0: int = _field(MISSING, "initial samples from N(theta0, sigma_start); PoWER uses the same")
    env: Any = _field(MISSING, "the task, built by hydra.utils.instantiate from its _target_")


@dataclass
class AlgoConfig:
    """Every algorithm: a name, whether returns are mapped by the task's reward range, and
    the optimizer built by ``hydra.utils.instantiate``."""

    name: str = _field(MISSING, "the algorithm's name (output directories, results.json)")
    use_task_reward_range: bool = _field(
        MISSING, "map returns by the task's reward range (false: learn it from the samples)"
    )
    optimizer: Any = _field(MISSING, "the optimizer, built from its _target_")


@dataclass
class ViapointBlock:
    """``task.block``: after ``trial`` trials on the layout, a sphere blocks the route of the
    best policy; the optimizer re-evaluates its stored policies and goes on learning."""

    trial: int = _field(MISSING, "trials before the block")
    radius: float = _field(MISSING, "m: radius of the sphere put on the best policy's route")
    threshold: float = _field(
        MISSING, "return of a good policy: the block keeps the most good routes open"
    )


def _task(name: str, target: str, module: str, exclude=(), extra=()) -> type:
    """The schema of task ``name``: ``TaskConfig`` with ``env`` built from the class."""
    cls = getattr(__import__(module, fromlist=[target]), target)
    env = builds(
        cls,
        target_path=f"{module}.{target}",
        exclude=("dtype", *exclude),
        values={"device": "${device}"},
    )
    summary = _first_sentence((cls.__doc__ or name).strip().split("\n\n")[0])
    fields = [("env", env, field(default_factory=env, metadata={"help": f"{module}.{target}"}))]
    return dataclasses.make_dataclass(
        f"{target}Schema", [*fields, *extra], bases=(TaskConfig,), namespace={"__doc__": summary}
    )


def _algo(name: str, summary: str, optimizer: type) -> type:
    fields = [("optimizer", optimizer, field(default_factory=optimizer, metadata={"help": ""}))]
    return dataclasses.make_dataclass(
        f"{name}_schema", fields, bases=(AlgoConfig,), namespace={"__doc__": summary}
    )


def task_schemas() -> dict[str, type]:
    """``{name: schema}`` of the bundled tasks (imports their modules)."""
    block = ("block", ViapointBlock | None, _field(None, "null: the layout stays"))
    return {
        "multimodal": _task("multimodal", "MultimodalTask", "dipole_torch.tasks.multimodal",
                            exclude=("optima",)),
        "cartpole": _task("cartpole", "CartPoleTask", "dipole_torch.tasks.cartpole",
                          exclude=("compile", "chunk")),
        "mountain_car": _task("mountain_car", "MountainCarTask", "dipole_torch.tasks.mountain_car",
                              exclude=("compile", "chunk")),
        "viapoint": _task("viapoint", "ViapointTask", "dipole_torch.tasks.viapoint",
                          extra=(block,)),
    }  # fmt: skip


def algo_schemas() -> dict[str, type]:
    """``{name: schema}`` of the algorithms: DIPOLE's options (the paper's set fixed for
    ``dipole_paper``) and PoWER's arguments."""
    from dipole_torch import Dipole, DipoleOptions, Power
    from dipole_torch.options import PAPER, PAPER_INERT

    given = ("theta0", "sigma_start", "n0", "reward_range", "generator", "options")
    return {
        "dipole": _algo(
            "dipole",
            "DIPOLE, this library's default variant",
            builds(DipoleOptions, target_path="dipole_torch.Dipole", exclude=given,
                   also=(Dipole, ("bounds",)), name="DipoleConfig"),
        ),
        "dipole_paper": _algo(
            "dipole_paper",
            "DIPOLE exactly as in the paper (Dipole.paper: its options fixed, counts free)",
            builds(DipoleOptions, target_path="dipole_torch.Dipole.paper",
                   exclude=(*given, *PAPER, *PAPER_INERT), also=(Dipole, ("bounds",)),
                   name="DipolePaperConfig"),
        ),
        "power": _algo(
            "power",
            "PoWER, Algorithm 3 of the paper: one policy, fixed exploration covariance",
            builds(Power, target_path="dipole_torch.Power", exclude=given, name="PowerConfig"),
        ),
    }  # fmt: skip


TASKS: dict[str, type] = {}
ALGOS: dict[str, type] = {}


def register(store: ConfigStore | None = None) -> None:
    """Put the schemas into Hydra's ConfigStore (idempotent): top-level names
    ``dipole_torch_config``, ``dipole_torch_task[_<name>]`` and ``dipole_torch_algo_<name>``."""
    store = store or ConfigStore.instance()
    if not TASKS:
        TASKS.update(task_schemas())
        ALGOS.update(algo_schemas())
    nodes = {
        "dipole_torch_config": Config,
        "dipole_torch_task": TaskConfig,
        **{f"dipole_torch_task_{name}": schema for name, schema in TASKS.items()},
        **{f"dipole_torch_algo_{name}": schema for name, schema in ALGOS.items()},
    }
    for name, node in nodes.items():
        # Stored once: each store builds the schema's config anew (OmegaConf.structured),
        # and train.py, the configs package and --help each register.
        if f"{name}.yaml" not in store.repo:
            store.store(name=name, node=node)


# ------------------------------------------------------------------ --help
def _type_name(annotation: Any) -> str:
    origin = typing.get_origin(annotation)
    args = typing.get_args(annotation)
    if origin in (types.UnionType, typing.Union) and type(None) in args:
        inner = [a for a in args if a is not type(None)]
        return f"{_type_name(inner[0])} or null"
    if origin is list:
        return f"list[{_type_name(args[0])}]"
    if annotation is Any:
        return "any"
    return getattr(annotation, "__name__", str(annotation))


def _default(f: dataclasses.Field) -> str:
    if f.default is not dataclasses.MISSING:
        value = f.default
    elif f.default_factory is not dataclasses.MISSING:
        value = f.default_factory()
    else:
        return ""
    if dataclasses.is_dataclass(value) or value is MISSING:
        return ""
    text = "null" if value is None else str(value).lower() if isinstance(value, bool) else value
    text = str(text)
    if text.startswith("${") and text.endswith("}"):  # an interpolation: say which key
        text = f"the value of {text[2:-1]}"
    return f" = {text if len(text) <= 40 else text[:37] + '...'}"


def _fields(schema: type, prefix: str, skip=()) -> list[str]:
    """One entry per leaf field: ``  key: type = default`` and the help below it. A section
    that may be null (e.g. ``task.block``) gets its own entry, then its fields."""
    lines = []
    hints = typing.get_type_hints(schema)
    for f in dataclasses.fields(schema):
        if f.name in skip or f.name == "_target_":
            continue
        value_type = hints[f.name]
        if dataclasses.is_dataclass(value_type):
            lines += _fields(value_type, f"{prefix}{f.name}.")
            continue
        lines.append(f"  {prefix}{f.name}: {_type_name(value_type)}{_default(f)}")
        lines += textwrap.wrap(
            f.metadata.get("help", ""), 92, initial_indent=" " * 6, subsequent_indent=" " * 6
        )
        inner = [a for a in typing.get_args(value_type) if dataclasses.is_dataclass(a)]
        if inner:  # an optional section
            lines += _fields(inner[0], f"{prefix}{f.name}.")
    return lines


def _program() -> str:
    """How this process was started: ``python train.py``, or ``dipole-train`` (installed)."""
    program = sys.argv[0] if sys.argv and sys.argv[0] else "train.py"
    return f"python {Path(program).name}" if program.endswith(".py") else Path(program).name


def _choices(group: str) -> str:
    """The YAML files of ``configs/<group>`` (the package ``dipole_torch.configs``: in the
    source tree the repository's ``configs/``)."""
    folder = importlib.resources.files("dipole_torch.configs") / group
    return ", ".join(sorted(p.name[:-5] for p in folder.iterdir() if p.name.endswith(".yaml")))


def _presets() -> list[str]:
    """A heading for each algorithm YAML of ``configs/algo`` that is another's settings with
    a few changed (``dipole_coverage``): what it is built on and what it changes."""
    from omegaconf import OmegaConf

    folder = importlib.resources.files("dipole_torch.configs") / "algo"
    lines = []
    for path in sorted(folder.iterdir(), key=lambda p: p.name):
        name = path.name.removesuffix(".yaml")
        if not path.name.endswith(".yaml") or name in ALGOS:
            continue
        preset = OmegaConf.create(path.read_text())
        base = next(d for d in preset.get("defaults", []) if isinstance(d, str))
        changes = OmegaConf.to_container(preset.get("optimizer", {}))
        values = ", ".join(f"{key}={_yaml(value)}" for key, value in changes.items())
        lines += ["", f"== algo={name}: the algo={base} settings above, with {values} =="]
    return lines


def _yaml(value: Any) -> str:
    """``value`` as a command-line override writes it (``true``, ``null``, ``0.5``)."""
    if value is None:
        return "null"
    return str(value).lower() if isinstance(value, bool) else str(value)


def help_text(config: str) -> str:
    """The ``--help`` page: the choices, then every field with its type, default and help,
    then ``config`` (this run's config, as YAML)."""
    program = _program()
    lines = [
        f"{program} [task=<task>] [algo=<algo>] [key=value ...]",
        "",
        "Trains DIPOLE or PoWER on a task. Every field below is a Hydra override, e.g.",
        f"  {program} task=viapoint algo=power seed=3 trials=200 algo.optimizer.M=10",
        f"  {program} -m task=multimodal seed=0,1,2      (a sweep, into multirun/)",
        "Types are checked when the config is composed (OmegaConf names the key), values",
        "before the run starts (one line naming the key; exit status 2).",
        "",
        f"== Tasks: task={_choices('task')} ==",
        f"== Algorithms: algo={_choices('algo')} ==",
        f"== One task's settings for one algorithm (task_algo/<task>_<algo>): "
        f"{_choices('task_algo')} ==",
        "",
        "== Run ==",
    ]
    lines += _fields(Config, "", skip=("task", "algo"))
    lines += ["", "== Every task (task.*) =="]
    lines += _fields(TaskConfig, "task.", skip=("env",))
    common = [f.name for f in dataclasses.fields(TaskConfig)]
    for name, schema in TASKS.items():
        lines += ["", f"== task={name}: {schema.__doc__} =="]
        lines += _fields(typing.get_type_hints(schema)["env"], "task.env.")
        lines += _fields(schema, "task.", skip=common)  # its own sections (task.block)
    lines += ["", "== Every algorithm (algo.*) =="]
    lines += _fields(AlgoConfig, "algo.", skip=("optimizer",))
    for name, schema in ALGOS.items():
        lines += ["", f"== algo={name}: {schema.__doc__} =="]
        lines += _fields(typing.get_type_hints(schema)["optimizer"], "algo.optimizer.")
    lines += _presets()
    lines += [
        "",
        "== This run's config (with the overrides given) ==",
        config,
        f"Hydra's own options: {program} --hydra-help",
    ]
    return "\n".join(lines)


def print_help(argv: list[str], config_dir: str) -> None:
    """Answer ``--help`` with ``help_text`` and the config the other arguments compose
    (one compose; Hydra's own ``--help`` composes the config once per config group)."""
    from hydra import compose, initialize_config_dir
    from omegaconf import OmegaConf

    from dipole_torch.training.hydra_compat import VERSION_BASE

    overrides = [a for a in argv if a not in ("--help", "-h") and not a.startswith("-")]
    register()
    with initialize_config_dir(config_dir, **VERSION_BASE):
        cfg = compose("config", overrides=overrides)
    header = f"{_program()}: DIPOLE (Bruno et al., AAAI 2013) and PoWER in PyTorch"
    print(header + "\n\n" + help_text(OmegaConf.to_yaml(cfg)))

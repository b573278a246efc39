"""Structured configs (Hydra ConfigStore schemas) of ``train.py``: the top level, the tasks and
the algorithms.

The YAML files in ``configs/`` extend these schemas (``defaults: [base_<name>, _self_]``), so
OmegaConf checks every value's type when the config is composed and names the key in its
error: ``algo.optimizer.alpha=abc`` fails with a ``ValidationError`` whose ``full_key`` is
``algo.optimizer.alpha``, before anything runs. What a type cannot say (ranges, whether CUDA is
there) is checked by ``train.check_config`` and by the optimizers' and tasks' constructors.

Every field carries ``metadata={"help": ...}``; ``python train.py --help`` lists them (the
``hydra/help`` config ``dipole`` built by :func:`help_text`). The schemas hold exactly the
keys of the YAML files, so checkpoints of runs made before the schemas existed still resume.

Importing this module registers the schemas (:func:`register`). ``train.py`` imports it, and
``hydra_plugins/dipole_torch_configs`` imports it whenever Hydra starts, so ``configs/``
composes in any process (``hydra.compose`` in a test or a notebook included).
"""

import dataclasses
import sys
import textwrap
import types
import typing
from collections.abc import Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hydra.core.config_store import ConfigStore
from omegaconf import MISSING

__all__ = [
    "AlgoConfig",
    "CartPoleEnv",
    "CartPoleTask",
    "Config",
    "DipoleAlgo",
    "DipoleOptimizer",
    "DipolePaperAlgo",
    "DipolePaperOptimizer",
    "MountainCarEnv",
    "MountainCarTask",
    "MultimodalEnv",
    "MultimodalTask",
    "Obstacle",
    "PowerAlgo",
    "PowerOptimizer",
    "TaskConfig",
    "ViapointBlock",
    "ViapointEnv",
    "ViapointTask",
    "help_text",
    "register",
]


def _field(default: Any, help: str) -> Any:  # noqa: A002 (the metadata key Hydra users know)
    """A dataclass field with a ``help`` string; a list default is copied per instance."""
    if isinstance(default, list):
        return field(default_factory=lambda: [*default], metadata={"help": help})
    return field(default=default, metadata={"help": help})


_DEVICE = "${device}"
_DEVICE_HELP = "device the episodes run on (the top-level device)"
_TASK_NAME_HELP = "the task's name (output directories, results.json)"
_TRIALS_HELP = "the task's trial budget (the default of the top-level trials)"
_N0_HELP = "initial samples from N(theta0, sigma_start); PoWER uses the same"
_ALGO_NAME_HELP = "the algorithm's name (output directories, results.json)"


# ------------------------------------------------------------------ top level
@dataclass
class Config:
    """``configs/config.yaml``: one run of an algorithm on a task."""

    task: Any = _field(MISSING, "the task (config group task: configs/task/<name>.yaml)")
    algo: Any = _field(MISSING, "the algorithm (config group algo: configs/algo/<name>.yaml)")
    seed: int = _field(0, "seeds the optimizer's and the task's torch.Generator (>= 0)")
    trials: int = _field(
        "${task.trials}",
        "trial budget: reward evaluations (one trial = one episode), never exceeded; PoWER "
        "reaches it exactly, DIPOLE stops at the last whole batch within it",
    )
    device: str = _field("cpu", "cpu, cuda or cuda:N: rollouts and optimizer")
    threads: int = _field(1, "torch CPU threads; 1 is fastest for these small tensors")
    checkpoint_every: int = _field(20, "iterations between checkpoints (also written at the end)")
    figure_every: int = _field(25, "iterations between policy figures in TensorBoard (0: never)")
    resume: str | None = _field(
        None, "path of a checkpoint.pt: continue that run exactly, in its directory"
    )
    progress: bool = _field(True, "tqdm progress bar")


# ------------------------------------------------------------------ tasks
@dataclass
class TaskConfig:
    """Every task: a name, a budget, the initial samples and the environment to build.

    ``base_task`` is this schema with an untyped ``env``: a task of your own (another
    ``_target_`` with its own arguments) extends it."""

    name: str = _field(MISSING, _TASK_NAME_HELP)
    trials: int = _field(MISSING, _TRIALS_HELP)
    n0: int = _field(MISSING, _N0_HELP)
    env: Any = _field(MISSING, "the task, built by hydra.utils.instantiate from its _target_")


@dataclass
class MultimodalEnv:
    _target_: str = _field("dipole_torch.tasks.multimodal.MultimodalTask", "the task's class")
    device: str = _field(_DEVICE, _DEVICE_HELP)
    dim: int = _field(2, "parameter dimension D")
    num_optima: int = _field(4, "equally high optima on a circle around theta0 = 0")
    radius: float = _field(1.0, "radius of the circle of optima")
    width: float = _field(0.25, "width (std) of each optimum's bump")
    exploration_std: float = _field(0.6, "initial exploration std: sigma_start = std^2 I")
    noise_std: float = _field(0.0, "std of Gaussian noise added to each return")


@dataclass
class MultimodalTask(TaskConfig):
    """Toy task: four equally high optima on a circle around theta0 = 0."""

    name: str = _field("multimodal", _TASK_NAME_HELP)
    trials: int = _field(300, _TRIALS_HELP)
    n0: int = _field(10, _N0_HELP)
    env: MultimodalEnv = field(
        default_factory=MultimodalEnv,
        metadata={"help": "dipole_torch.tasks.multimodal.MultimodalTask"},
    )


_ENGINE_HELP = (
    "how episodes run: python (one at a time in Python floats, stopped once settled), torch "
    "(one batched rollout on the device), auto (torch on an accelerator, else python)"
)


@dataclass
class CartPoleEnv:
    _target_: str = _field("dipole_torch.tasks.cartpole.CartPoleTask", "the task's class")
    device: str = _field(_DEVICE, _DEVICE_HELP)
    steps: int = _field(1000, "episode horizon in steps (the paper's 1000)")
    force_limit: float = _field(10.0, "N: the force theta^T x is clipped to +-force_limit")
    initial_angle: float = _field(0.05, "rad: the pole starts at U(-initial_angle, initial_angle)")
    theta0: list[float] | None = _field(
        [0.0, 0.0, 0.0, 0.0], "initial policy: gains on (x, x', angle, angle'); null: zeros"
    )
    exploration_std: list[float] = _field(
        [1.0, 1.0, 20.0, 3.0], "per-gain exploration std: sigma_start = diag(std^2)"
    )
    default_seed: int = _field(0, "seed of the random start when evaluate gets no generator")
    engine: str = _field("auto", _ENGINE_HELP)


@dataclass
class CartPoleTask(TaskConfig):
    """Cart-pole balancing, the paper's Fig. 1 (left)."""

    name: str = _field("cartpole", _TASK_NAME_HELP)
    trials: int = _field(500, _TRIALS_HELP)
    n0: int = _field(10, _N0_HELP)
    env: CartPoleEnv = field(
        default_factory=CartPoleEnv, metadata={"help": "dipole_torch.tasks.cartpole.CartPoleTask"}
    )


@dataclass
class MountainCarEnv:
    _target_: str = _field("dipole_torch.tasks.mountain_car.MountainCarTask", "the task's class")
    device: str = _field(_DEVICE, _DEVICE_HELP)
    steps: int = _field(100, "maximum time in steps (the paper's 100)")
    goal_position: float = _field(0.5, "the goal is x >= goal_position")
    alpha: float = _field(0.001, "engine: x'' = alpha u - beta cos(3x), u in {-4, 4}")
    beta: float = _field(0.0055, "gravity term beta")
    theta0: list[float] | None = _field(
        [0.0, 0.0, 0.0, 0.0], "initial policy (4 parameters); null: zeros"
    )
    exploration_std: list[float] = _field(
        [1.0, 1.0, 10.0, 100.0], "per-parameter exploration std: sigma_start = diag(std^2)"
    )
    default_seed: int = _field(0, "seed of the random start when evaluate gets no generator")
    engine: str = _field("auto", _ENGINE_HELP)


@dataclass
class MountainCarTask(TaskConfig):
    """Mountain car, the paper's Fig. 1 (right)."""

    name: str = _field("mountain_car", _TASK_NAME_HELP)
    trials: int = _field(500, _TRIALS_HELP)
    n0: int = _field(10, _N0_HELP)
    env: MountainCarEnv = field(
        default_factory=MountainCarEnv,
        metadata={"help": "dipole_torch.tasks.mountain_car.MountainCarTask"},
    )


@dataclass
class Obstacle:
    """A sphere in the viapoint task's space that the end effector's path must not enter."""

    centre: list[float] = _field(MISSING, "m: [x, y, z] centre in the arm's base frame")
    radius: float = _field(MISSING, "m: radius")


@dataclass
class ViapointEnv:
    _target_: str = _field("dipole_torch.tasks.viapoint.ViapointTask", "the task's class")
    device: str = _field(_DEVICE, _DEVICE_HELP)
    urdf: str = _field(
        "models/wam/wam7.urdf", "the arm's URDF: absolute, or relative to the cwd or the project"
    )
    end_effector: str = _field("wam_tool", "link moved through the viapoints")
    base_link: str | None = _field(None, "frame of all points (null: the URDF's root link)")
    joint_lower: list[float] | None = _field(None, "[n] rad lower joint limits; null: the URDF's")
    joint_upper: list[float] | None = _field(None, "[n] rad upper joint limits; null: the URDF's")
    initial_joints: list[float] | None = _field(
        [0.0, 0.6, 0.0, 1.6, 0.0, 0.0, 0.0], "rad: start posture (the IK's guess for start)"
    )
    kinematics: str = _field(
        "pytorch_kinematics", "pytorch_kinematics (any URDF) or wam_dh (the WAM's fast path)"
    )
    engine: str = _field(
        "auto",
        "how rollouts run: numpy (float64 arrays on the CPU, no gradient), torch "
        "(differentiable, any device), auto (numpy on the CPU unless theta requires a gradient)",
    )
    start: list[float] | None = _field(
        [0.5, -0.35, 0.0], "m: start point; null: the end effector of initial_joints"
    )
    target: list[float] = _field([0.5, 0.35, 0.0], "m: target point")
    pass_times: list[float] = _field(
        [0.4, 1.2, 2.0], "s: one learned DS-GMR attractor per pass time"
    )
    viapoints: list[list[list[float]]] = _field(
        [
            [[0.5, -0.29, -0.1], [0.5, -0.29, 0.1]],
            [[0.4, 0.06, 0.0], [0.6, 0.06, 0.0]],
            [[0.5, 0.34, -0.1], [0.5, 0.34, 0.1]],
        ],
        "m: per pass time, the alternative viapoints",
    )
    reward_alpha: float = _field(2.5, "1/m: alpha of eq. 9 (reward 0.9 at 4.2 cm)")
    stiffness: float = _field(100.0, "1/s^2: K_P; K_V = 2 sqrt(K_P) (critical damping)")
    dt: float = _field(0.02, "s: integration step")
    duration: float = _field(2.8, "s: episode length")
    time_std: float | None = _field(0.28, "s: std of each GMM component in time")
    end_at_target: bool = _field(True, "a fixed final DS-GMR component at the target")
    goal_time: float | None = _field(
        None, "s: its time centre; null: halfway from the last pass time to the end"
    )
    exploration_std: float = _field(0.05, "m: initial exploration std of each coordinate")
    ik_damping: float = _field(0.05, "m: lambda of the damped-least-squares IK")
    obstacles: list[Obstacle] = _field(
        [], "spheres {centre: [x, y, z], radius} (m) the end effector's path must not enter"
    )
    penetration_scale: float = _field(
        0.02, "m: penetration depth into an obstacle that divides the reward by e"
    )


@dataclass
class ViapointBlock:
    """``task.block``: after ``trial`` trials on the layout, a sphere blocks the route of the
    best policy; the optimizer re-evaluates its stored policies and goes on learning."""

    trial: int = _field(300, "trials before the block (the optimizer's last whole batch)")
    radius: float = _field(0.08, "m: radius of the sphere put on the best policy's route")
    threshold: float = _field(
        0.9, "return of a good policy: the block keeps the most good routes open"
    )


@dataclass
class ViapointTask(TaskConfig):
    """Viapoint task on the simulated Barrett WAM (or an arm of your own: README)."""

    name: str = _field("viapoint", _TASK_NAME_HELP)
    trials: int = _field(300, _TRIALS_HELP)
    n0: int = _field(30, _N0_HELP)
    env: ViapointEnv = field(
        default_factory=ViapointEnv, metadata={"help": "dipole_torch.tasks.viapoint.ViapointTask"}
    )
    block: ViapointBlock | None = _field(
        None, "null: the layout stays; else an obstacle blocks the best route (viapoint_blocked)"
    )


# ------------------------------------------------------------------ algorithms
@dataclass
class AlgoConfig:
    """Every algorithm: a name, whether returns are mapped by the task's reward range, and
    the optimizer built by ``hydra.utils.instantiate`` (``base_algo``: untyped optimizer)."""

    name: str = _field(MISSING, _ALGO_NAME_HELP)
    use_task_reward_range: bool = _field(
        MISSING, "map returns by the task's reward range (false: learn it from the samples)"
    )
    optimizer: Any = _field(MISSING, "the optimizer, built from its _target_")


_ALPHA = "DP concentration (> 0)"
_M_AUX = "auxiliary components of Neal's Algorithm 8"
_M = "importance-set size of PoWER"
_CLUSTER_EVERY = "iterations between DP clusterings ('every M steps'); null: M"
_SWEEPS = "Gibbs sweeps per clustering (warm-started)"
_INITIAL_SWEEPS = "Gibbs sweeps of the first clustering"
_REGULARIZATION = "DP component covariance floor, fraction of diag(sigma_start)"
_REWARD_FLOOR = "smallest reward weight"
_REWARD_WEIGHTED = "eq. 6 (false: eq. 5, an ablation)"
_PRIOR_DF = "nu0 of the inverse-Wishart prior (> D + 2); null: D + 3"
_BOUNDS = (
    "box of theta, [lower, upper]: each a number or a list of D numbers (null: no box; "
    "asked rows are clipped into it)"
)


@dataclass
class DipoleOptimizer:
    _target_: str = _field("dipole_torch.Dipole", "the optimizer's class")
    alpha: float = _field(1.0, _ALPHA)
    m: int = _field(10, _M_AUX)
    M: int = _field(5, _M)
    cluster_every: int | None = _field(5, _CLUSTER_EVERY)
    sweeps: int = _field(5, _SWEEPS)
    initial_sweeps: int = _field(20, _INITIAL_SWEEPS)
    regularization: float = _field(0.01, _REGULARIZATION)
    reward_floor: float = _field(0.001, _REWARD_FLOOR)
    reward_weighted: bool = _field(True, _REWARD_WEIGHTED)
    prior_df: float | None = _field(None, _PRIOR_DF)
    importance: str = _field(
        "policy", "policy: each policy keeps its own best M; global: the best K*M overall"
    )
    exploration: str = _field(
        "success", "success: success-rule exploration per policy; clustering: DP posterior"
    )
    explore: float = _field(0.05, "scouts from N(theta0, sigma_start) per policy sample, [0, 1]")
    max_policies: int | None = _field(8, "active policies at most (null: no limit)")
    max_sampled: int | None = _field(
        4, "policies sampled per iteration at most, the best ones; the others wait (null: all)"
    )
    retire_std: float = _field(
        0.001, "retire a policy once its exploration std is below this x sigma_start's"
    )
    merge_radius: float = _field(1.0, "drop a policy within this many exploration stds of another")
    hill_valley: bool = _field(True, "vet new policies and neighbours by a midpoint evaluation")
    pair_points: int = _field(
        1, "probes between two neighbouring policies before the worse is dropped (1: midpoint)"
    )
    auxiliary: str = _field(
        "auto",
        "fresh: Algorithm 8's m draws per point; reuse: Favaro & Teh's re-used draws (CPU); "
        "auto: reuse on the CPU once D + 1 >= 32",
    )
    bounds: Any = _field(None, _BOUNDS)


@dataclass
class DipoleAlgo(AlgoConfig):
    """DIPOLE, this library's default variant (README, "Search quality")."""

    name: str = _field("dipole", _ALGO_NAME_HELP)
    use_task_reward_range: bool = _field(
        False, "map returns by the task's reward range (false: learn it from the samples)"
    )
    optimizer: DipoleOptimizer = field(
        default_factory=DipoleOptimizer, metadata={"help": "dipole_torch.Dipole"}
    )


@dataclass
class DipolePaperOptimizer:
    _target_: str = _field("dipole_torch.Dipole.paper", "the optimizer's constructor")
    alpha: float = _field(1.0, _ALPHA)
    m: int = _field(10, _M_AUX)
    M: int = _field(5, _M)
    cluster_every: int | None = _field(5, _CLUSTER_EVERY)
    sweeps: int = _field(5, _SWEEPS)
    initial_sweeps: int = _field(20, _INITIAL_SWEEPS)
    regularization: float = _field(0.01, _REGULARIZATION)
    reward_floor: float = _field(0.001, _REWARD_FLOOR)
    reward_weighted: bool = _field(True, _REWARD_WEIGHTED)
    prior_df: float | None = _field(None, _PRIOR_DF)
    bounds: Any = _field(None, _BOUNDS)


@dataclass
class DipolePaperAlgo(AlgoConfig):
    """DIPOLE exactly as in the paper (Dipole.paper)."""

    name: str = _field("dipole_paper", _ALGO_NAME_HELP)
    use_task_reward_range: bool = _field(
        True, "map returns by the task's reward range (false: learn it from the samples)"
    )
    optimizer: DipolePaperOptimizer = field(
        default_factory=DipolePaperOptimizer, metadata={"help": "dipole_torch.Dipole.paper"}
    )


@dataclass
class PowerOptimizer:
    _target_: str = _field("dipole_torch.Power", "the optimizer's class")
    M: int = _field(5, "importance-set size")
    reward_floor: float = _field(0.001, _REWARD_FLOOR)
    exploration_decay: float = _field(
        1.0, "1: fixed sigma_start (the paper's PoWER); < 1: shrink every iteration"
    )
    min_exploration: float = _field(0.01, "floor of the shrink factor")
    bounds: Any = _field(None, _BOUNDS)


@dataclass
class PowerAlgo(AlgoConfig):
    """PoWER, Algorithm 3 of the paper: one policy, fixed exploration covariance."""

    name: str = _field("power", _ALGO_NAME_HELP)
    use_task_reward_range: bool = _field(
        True, "map returns by the task's reward range (false: learn it from the samples)"
    )
    optimizer: PowerOptimizer = field(
        default_factory=PowerOptimizer, metadata={"help": "dipole_torch.Power"}
    )


# Schema name in the ConfigStore -> dataclass; the YAML file <group>/<name>.yaml extends
# <group>/base_<name>.
TASKS = {
    "task": TaskConfig,
    "multimodal": MultimodalTask,
    "cartpole": CartPoleTask,
    "mountain_car": MountainCarTask,
    "viapoint": ViapointTask,
}
ALGOS = {
    "algo": AlgoConfig,
    "dipole": DipoleAlgo,
    "dipole_paper": DipolePaperAlgo,
    "power": PowerAlgo,
}


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


def _help_lines(f: dataclasses.Field) -> list[str]:
    return textwrap.wrap(f.metadata["help"], 92, initial_indent=" " * 6, subsequent_indent=" " * 6)


def _fields(schema: type, prefix: str, skip: Sequence[str] = ()) -> list[str]:
    """One entry per leaf field: ``  key: type = default`` and the help below it. A section
    that may be null (e.g. ``task.block``) gets its own entry, then its fields."""
    lines = []
    for f in dataclasses.fields(schema):
        if f.name in skip:
            continue
        value_type = typing.get_type_hints(schema)[f.name]
        if dataclasses.is_dataclass(value_type):
            lines += _fields(value_type, f"{prefix}{f.name}.")
            continue
        lines.append(f"  {prefix}{f.name}: {_type_name(value_type)}{_default(f)}")
        lines += _help_lines(f)
        inner = [a for a in typing.get_args(value_type) if dataclasses.is_dataclass(a)]
        if inner:  # an optional section
            lines += _fields(inner[0], f"{prefix}{f.name}.")
    return lines


def _program() -> str:
    """How this process was started: ``python train.py``, or ``dipole-train`` (installed)."""
    program = sys.argv[0] if sys.argv and sys.argv[0] else "train.py"
    return f"python {Path(program).name}" if program.endswith(".py") else Path(program).name


def help_text() -> str:
    """The ``--help`` page: the groups, then every field with its type, default and help.
    ``$APP_CONFIG_GROUPS`` and ``$CONFIG`` are filled in by Hydra."""
    top = [f for f in dataclasses.fields(Config) if f.name not in ("task", "algo")]
    program = _program()
    lines = [
        f"{program} [task=<task>] [algo=<algo>] [key=value ...]",
        "",
        "Trains DIPOLE or PoWER on a task. Every field below is a Hydra override, e.g.",
        f"  {program} task=viapoint algo=power seed=3 trials=200 algo.optimizer.M=10",
        f"  {program} -m task=multimodal seed=0,1,2      (a sweep, into multirun/)",
        "Values are type-checked when the config is composed (OmegaConf names the key).",
        "",
        "== Config groups (base_* are the schemas the options extend) ==",
        "$APP_CONFIG_GROUPS",
        "",
        "== Run ==",
    ]
    hints = typing.get_type_hints(Config)
    for f in top:
        lines.append(f"  {f.name}: {_type_name(hints[f.name])}{_default(f)}")
        lines += _help_lines(f)
    lines += ["", "== Every task (task.*) =="]
    common = [f.name for f in dataclasses.fields(TaskConfig)]
    lines += _fields(TaskConfig, "task.", skip=["env"])  # env: per task, below
    for name, schema in TASKS.items():
        if schema is TaskConfig:
            continue
        lines += ["", f"== task={name}: {schema.__doc__.splitlines()[0]} =="]
        lines += _fields(typing.get_type_hints(schema)["env"], "task.env.")
        lines += _fields(schema, "task.", skip=common)  # its own sections (task.block)
    lines += ["", "== Every algorithm (algo.*) =="]
    lines += _fields(AlgoConfig, "algo.", skip=["optimizer"])
    for name, schema in ALGOS.items():
        if schema is AlgoConfig:
            continue
        lines += ["", f"== algo={name}: {schema.__doc__.splitlines()[0]} =="]
        lines += _fields(typing.get_type_hints(schema)["optimizer"], "algo.optimizer.")
    lines += [
        "",
        "== This run's config (with the overrides given) ==",
        "$CONFIG",
        f"Hydra's own options: {program} --hydra-help",
    ]
    return "\n".join(lines)


def register(store: ConfigStore | None = None) -> None:
    """Put the schemas and the help page into Hydra's ConfigStore (idempotent)."""
    store = store or ConfigStore.instance()
    store.store(name="base_config", node=Config)
    for name, schema in TASKS.items():
        store.store(group="task", name=f"base_{name}", node=schema)
    for name, schema in ALGOS.items():
        store.store(group="algo", name=f"base_{name}", node=schema)
    text = help_text()
    # Hydra fills the page in with string.Template and OmegaConf resolves it: no other "$".
    assert text.count("$") == text.count("$APP_CONFIG_GROUPS") + text.count("$CONFIG")
    store.store(
        group="hydra/help",
        name="dipole",
        node={
            "app_name": _program(),
            "header": f"{_program()}: DIPOLE (Bruno et al., AAAI 2013) and PoWER in PyTorch",
            "footer": "",
            "template": "${hydra.help.header}\n\n" + text,
        },
    )


register()

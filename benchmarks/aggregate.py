"""Figure-1-style curves from a ``python train.py -m`` sweep, on any Hydra launcher.

Reads every run under one or more multirun directories (a run directory holds
``.hydra/config.yaml``, written when the run starts, and ``results.json``, written atomically
when it ends), groups the runs by task and algorithm, and draws per task the paper's two
panels -- best policy and average of policies, mean ± std over seeds against trials -- with
``benchmarks/lockstep.py``'s helpers, the same as ``reproduce_figure1.py``::

    python train.py -m hydra/launcher=joblib task=cartpole algo=dipole,power seed='range(0,50)'
    python benchmarks/aggregate.py multirun/2026-11-26_07-30-00 --out figures/cartpole

Per run, the curves are its ``results.json`` history: after every tell, the highest
(``best``) and the mean (``mean``) return of the batch just evaluated, as step functions of
the number of trials sampled on a common grid (``--grid-step`` trials apart, up to the
smallest trial budget of the task's runs; grid points before some run's first tell are
dropped). PoWER evaluates one policy per iteration, so its two curves coincide.

Runs of one task and algorithm whose configs differ in more than the seed (a hyperparameter
sweep such as ``algo.optimizer.exploration_decay=1.0,0.98``) are separate curves, labelled
with the keys that differ. Settings that do not change a run's numbers (``progress``,
``threads``, ``checkpoint_every``, ``figure_every``, ``resume``) are ignored.

Writes ``<out>/<task>.png`` per task and ``<out>/aggregate.json``: per task the trials grid
and, per curve, its seeds, run directories, and the mean and std over seeds of ``best``,
``average`` and ``best_so_far`` on the grid, and the final values, with the task's figures of
each run's final policies taken together where it has them (``final_policy_set``: on the
viapoint task the routes found, mean and std over runs). A run directory without
``results.json`` (still running, failed or killed) is an error unless ``--allow-incomplete``,
which leaves it out and lists it in the JSON. A run that cannot be read as train.py writes it
is an error (exit status 2) naming its file and what is wrong, before anything is written:
a config without task and algo groups, an integer seed and trials; a history with a value
that is not finite, or that ends before the config's trial budget (train.py writes
``results.json`` only at a run's end, so this is an error even with ``--allow-incomplete``);
``policy_set.scalars`` that are not finite numbers by name.
"""

from __future__ import annotations

import argparse
import json
import sys
from collections import defaultdict
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import yaml
from lockstep import on_grid, plot_best_and_average
from omegaconf import OmegaConf
from omegaconf.errors import OmegaConfBaseException

from dipole_torch.training.resume import flatten

# Config keys that do not change a run's numbers (train.py's RESUME_MAY_CHANGE, less the
# budget and the device).
IGNORED = ("seed", "progress", "threads", "checkpoint_every", "figure_every", "resume")
TASK_TITLES = {
    "cartpole": "Cart-pole",
    "mountain_car": "Mountain car",
    "multimodal": "Multimodal toy",
    "viapoint": "WAM viapoint",
}
ALGO_LABELS = {"dipole": "DIPOLE", "dipole_paper": "DIPOLE (paper)", "power": "PoWER"}
ALGO_COLORS = {"dipole": "tab:blue", "dipole_paper": "tab:cyan", "power": "tab:red"}
MORE_COLORS = ("tab:orange", "tab:green", "tab:purple", "tab:brown", "tab:pink", "tab:olive")
HISTORY_KEYS = ("trials", "best", "mean", "best_so_far", "num_policies")


class AggregateError(ValueError):
    """A multirun directory that cannot be aggregated; the message says why and where."""


@dataclass
class Run:
    directory: Path
    task: str
    algo: str
    seed: int
    budget: int  # the config's trial budget
    settings: dict  # the flattened, resolved config, less IGNORED
    history: np.ndarray  # rows [trials, best, mean, best_so_far, num_policies]
    # The task's figures of the final policies taken together (results.json's
    # policy_set.scalars; the viapoint task: routes), {} where the task has none.
    policy_scalars: dict[str, float]


def find_run_dirs(root: Path) -> list[Path]:
    """Every directory under ``root`` (``root`` included) holding ``.hydra/config.yaml``."""
    if not root.exists():
        raise AggregateError(f"{root} does not exist")
    if not root.is_dir():
        raise AggregateError(
            f"{root} is a file; give the multirun directory (the 'sweep output dir' that "
            "`python train.py -m` prints)"
        )
    return sorted(p.parent.parent for p in root.rglob("config.yaml") if p.parent.name == ".hydra")


def _is_integer(value) -> bool:
    """Whether ``value`` is an integer as YAML and JSON write one (a bool is not)."""
    return isinstance(value, int) and not isinstance(value, bool)


def _read_config(config_path: Path) -> dict:
    """The resolved ``.hydra/config.yaml``, checked to be a train.py config: ``task`` and
    ``algo`` mappings with a name, an integer ``seed`` and a positive integer ``trials``."""
    try:
        config = OmegaConf.to_container(OmegaConf.load(config_path), resolve=True)
    except (OSError, ValueError, yaml.YAMLError, OmegaConfBaseException) as error:
        message = " ".join(str(error).split())  # (YAML's messages take several lines)
        raise AggregateError(f"cannot read {config_path}: {message}") from None
    if not isinstance(config, dict) or not {"task", "algo", "seed", "trials"} <= set(config):
        raise AggregateError(
            f"{config_path} is not a train.py config (it needs task, algo, seed and trials)"
        )
    for key in ("task", "algo"):
        group = config[key]
        if not isinstance(group, dict) or not isinstance(group.get("name"), str):
            raise AggregateError(
                f"{config_path}: {key} must be a config group with a name (as train.py writes "
                f"it, {key}: {{name: ..., ...}}), got {group!r}"
            )
    if not _is_integer(config["seed"]):
        raise AggregateError(f"{config_path}: seed must be an integer, got {config['seed']!r}")
    if not _is_integer(config["trials"]) or config["trials"] < 1:
        raise AggregateError(
            f"{config_path}: trials must be a positive integer, got {config['trials']!r}"
        )
    return config


def _read_history(results_path: Path, results: dict) -> np.ndarray:
    """``results.json``'s learning history as rows [trials, best, mean, best_so_far,
    num_policies]: equal-length lists of finite numbers, trials increasing."""
    try:
        history = np.array([results["history"][key] for key in HISTORY_KEYS], dtype=float).T
    except (ValueError, KeyError, TypeError) as error:
        raise AggregateError(
            f"{results_path} is not a train.py results.json with a learning history "
            f"({type(error).__name__}: {error})"
        ) from None
    if history.ndim != 2 or len(history) == 0:
        raise AggregateError(
            f"{results_path} has an empty learning history (or one whose entries are not "
            "lists of numbers)"
        )
    for k, key in enumerate(HISTORY_KEYS):
        bad = np.flatnonzero(~np.isfinite(history[:, k]))
        if len(bad):
            raise AggregateError(
                f"{results_path}: history.{key}[{bad[0]}] is {history[bad[0], k]}, not a finite "
                f"number ({len(bad)} such value(s))"
            )
    if np.any(np.diff(history[:, 0]) <= 0):
        raise AggregateError(f"{results_path}: history.trials is not increasing")
    return history


def _check_finished(
    results_path: Path, results: dict, history: np.ndarray, config_path: Path, budget: int
) -> None:
    """Refuse a results.json whose run ended before its trial budget: its last values,
    carried forward to the grid's end, would make wrong means. (train.py writes results.json
    only when a run has evaluated all its trials, so this is not a run still going, which
    ``--allow-incomplete`` is for, but two runs' files in one directory, or a run resumed
    with a smaller budget than its config's.)"""
    trials, stated = results.get("trials"), results.get("trial_budget")
    for key, value in (("trials", trials), ("trial_budget", stated)):
        if value is not None and not _is_integer(value):
            raise AggregateError(f"{results_path}: {key} must be an integer, got {value!r}")
    if trials is not None and stated is not None and trials < stated:
        raise AggregateError(
            f"{results_path} says trials={trials} of trial_budget={stated}: the run ended "
            "before its budget; aggregate only finished runs"
        )
    end = int(history[-1, 0])
    if end < budget:
        raise AggregateError(
            f"{results_path}: the history ends at {end} trials, before the budget of "
            f"{config_path} (trials={budget}): its last values would stand for trials it never "
            f"ran. Finish the run (resume=<dir>/checkpoint.pt trials={budget}) or leave its "
            "directory out"
        )


def _policy_scalars(results_path: Path, results: dict) -> dict[str, float]:
    """results.json's ``policy_set.scalars``, finite numbers by name; {} without them."""
    policy_set = results.get("policy_set", {})
    if not isinstance(policy_set, dict):
        raise AggregateError(f"{results_path}: policy_set must be a mapping, got {policy_set!r}")
    scalars = policy_set.get("scalars", {})
    if not isinstance(scalars, dict):
        raise AggregateError(
            f"{results_path}: policy_set.scalars must be a mapping of names to numbers, "
            f"got {scalars!r}"
        )
    for name, value in scalars.items():
        number = isinstance(value, int | float) and not isinstance(value, bool)
        if not number or not np.isfinite(value):
            raise AggregateError(
                f"{results_path}: policy_set.scalars.{name} must be a finite number, got {value!r}"
            )
    return {name: float(value) for name, value in scalars.items()}


def load_run(directory: Path) -> Run | None:
    """The run in ``directory``, or None when it has no ``results.json`` yet."""
    config_path = directory / ".hydra" / "config.yaml"
    results_path = directory / "results.json"
    config = _read_config(config_path)
    if not results_path.exists():
        return None
    try:
        results = json.loads(results_path.read_text())
    except (OSError, ValueError) as error:
        raise AggregateError(
            f"{results_path} is not a train.py results.json ({type(error).__name__}: {error})"
        ) from None
    if not isinstance(results, dict):
        raise AggregateError(f"{results_path} is not a train.py results.json (not a mapping)")
    history = _read_history(results_path, results)
    task, algo = config["task"]["name"], config["algo"]["name"]
    for key, expected in (("task", task), ("algo", algo), ("seed", config["seed"])):
        if results.get(key) != expected:
            raise AggregateError(
                f"{results_path} says {key}={results.get(key)!r} but {config_path} says "
                f"{expected!r}: the directory mixes two runs"
            )
    # The run's budget: results.json's, which a resume to a larger budget raised (its config
    # keeps the first session's trials: the run was grouped and cut at that budget).
    budget = results.get("trial_budget", config["trials"])
    _check_finished(results_path, results, history, config_path, budget)
    settings = {
        key: value
        for key, value in flatten(config).items()
        if not any(key == skip or key.startswith(f"{skip}.") for skip in IGNORED)
    }
    if "trials" in settings:
        settings["trials"] = budget
    scalars = _policy_scalars(results_path, results)
    return Run(directory, task, algo, config["seed"], budget, settings, history, scalars)


def load_runs(roots: list[Path], allow_incomplete: bool) -> tuple[list[Run], list[Path]]:
    """All finished runs under ``roots`` and the run directories without results."""
    runs, incomplete = [], []
    for root in roots:
        directories = find_run_dirs(root)
        if not directories:
            raise AggregateError(
                f"no train.py runs under {root}: a run directory holds .hydra/config.yaml and "
                "results.json. Give the multirun directory that `python train.py -m` prints "
                "('sweep output dir'), e.g. multirun/<date_time>"
            )
        for directory in directories:
            run = load_run(directory)
            if run is None:
                incomplete.append(directory)
            else:
                runs.append(run)
    if incomplete and not allow_incomplete:
        shown = ", ".join(str(d) for d in incomplete[:5])
        more = f" and {len(incomplete) - 5} more" if len(incomplete) > 5 else ""
        raise AggregateError(
            f"{len(incomplete)} run(s) have no results.json (still running, failed or killed): "
            f"{shown}{more}. Finish them (resume=<dir>/checkpoint.pt) or pass "
            "--allow-incomplete to leave them out"
        )
    if not runs:
        raise AggregateError(
            f"none of the {len(incomplete)} run(s) under {', '.join(map(str, roots))} has "
            "finished (no results.json)"
        )
    return runs, incomplete


def group_runs(runs: list[Run]) -> dict[str, dict[str, list[Run]]]:
    """task -> curve label -> runs. One curve per algorithm and per setting that differs
    between its runs (beside the seed); each seed at most once per curve."""
    by_algo: dict[tuple[str, str], list[Run]] = defaultdict(list)
    for run in runs:
        by_algo[run.task, run.algo].append(run)
    groups: dict[str, dict[str, list[Run]]] = defaultdict(dict)
    for (task, algo), members in sorted(by_algo.items()):
        keys = sorted(set().union(*(run.settings for run in members)))
        varying = [key for key in keys if len({repr(run.settings.get(key)) for run in members}) > 1]
        curves: dict[str, list[Run]] = defaultdict(list)
        for run in members:
            suffix = ", ".join(f"{key}={run.settings.get(key)}" for key in varying)
            label = ALGO_LABELS.get(algo, algo) + (f" ({suffix})" if suffix else "")
            curves[label].append(run)
        for label, curve in sorted(curves.items()):
            curve.sort(key=lambda run: run.seed)
            for a, b in zip(curve, curve[1:], strict=False):
                if a.seed == b.seed:
                    raise AggregateError(
                        f"seed {a.seed} of {label} on {task} appears twice, in {a.directory} "
                        f"and {b.directory}: the same run would count twice; aggregate "
                        "one of the two sweeps"
                    )
            groups[task][label] = curve
    return dict(groups)


def _curve_stats(values: np.ndarray) -> dict:
    """``values``: ``[runs, G]`` -> mean and std over runs, rounded."""
    return {"mean": values.mean(0).round(4).tolist(), "std": values.std(0).round(4).tolist()}


def _final_scalars(curve: list[Run]) -> dict:
    """Per scalar of the task's final policy set (e.g. the viapoint task's ``routes``): its
    mean and std over the runs that report it, at each run's end (its own budget, not the
    grid's last point), and how many runs those are."""
    names = sorted({name for run in curve for name in run.policy_scalars})
    stats = {}
    for name in names:
        values = np.array([run.policy_scalars[name] for run in curve if name in run.policy_scalars])
        stats[name] = {
            "mean": float(values.mean()),
            "std": float(values.std()),
            "runs": len(values),
        }
    return stats


def aggregate(roots: list[Path], out: Path, grid_step: int, allow_incomplete: bool) -> dict:
    runs, incomplete = load_runs(roots, allow_incomplete)
    groups = group_runs(runs)
    figures = []  # plot_best_and_average's arguments per task, drawn once the JSON is made
    summary: dict = {
        "sources": [str(root) for root in roots],
        "incomplete_runs": [str(d) for d in incomplete],
        "tasks": {},
    }
    for task, curves in groups.items():
        members = [run for curve in curves.values() for run in curve]
        budget = min(run.budget for run in members)
        first = max(run.history[0, 0] for run in members)  # every run has told by here
        grid = np.arange(grid_step, budget + 1, grid_step)
        grid = grid[grid >= first]
        if len(grid) == 0:
            raise AggregateError(
                f"{task}: no grid point between the runs' first tell ({first:.0f} trials) and "
                f"the smallest budget ({budget} trials) with --grid-step {grid_step}"
            )
        values, entry = {}, {"trials": budget, "trials_grid": grid.tolist(), "curves": {}}
        for label, curve in curves.items():
            # on_grid reads columns 1:3: [best, mean], then [best_so_far, num_policies].
            sampled = np.stack([on_grid(run.history[:, :3], grid) for run in curve])
            later = np.stack([on_grid(run.history[:, [0, 3, 4]], grid) for run in curve])
            values[label] = sampled
            entry["curves"][label] = {
                "task": task,
                "algo": curve[0].algo,
                "settings": curve[0].settings,
                "runs": len(curve),
                "seeds": [run.seed for run in curve],
                "run_dirs": [str(run.directory) for run in curve],
                "best": _curve_stats(sampled[:, 0]),
                "average": _curve_stats(sampled[:, 1]),
                "best_so_far": _curve_stats(later[:, 0]),
                "num_policies": _curve_stats(later[:, 1]),
                **{
                    f"final_{kind}": {
                        "mean": float(sampled[:, k, -1].mean()),
                        "std": float(sampled[:, k, -1].std()),
                    }
                    for k, kind in enumerate(("best", "average"))
                },
                "final_policy_set": _final_scalars(curve),
            }
            final = entry["curves"][label]
            together = "".join(
                f", {name} {stats['mean']:.3g} ± {stats['std']:.2g} ({stats['runs']} runs)"
                for name, stats in final["final_policy_set"].items()
            )
            print(
                f"{task:>12} {label:>30}: {len(curve):3d} runs, at {grid[-1]} trials best "
                f"{final['final_best']['mean']:.4g} ± {final['final_best']['std']:.3g}, "
                f"average {final['final_average']['mean']:.4g} ± "
                f"{final['final_average']['std']:.3g}{together}"
            )
        colors, spare = {}, iter(MORE_COLORS * (1 + len(curves) // len(MORE_COLORS)))
        used = set()
        for label, curve in curves.items():
            color = ALGO_COLORS.get(curve[0].algo)
            colors[label] = color if color and color not in used else next(spare)
            used.add(colors[label])
        runs_text = sorted({len(curve) for curve in curves.values()})
        title = TASK_TITLES.get(task, task)
        figures.append(
            dict(
                grid=grid,
                curves=values,
                colors=colors,
                path=out / f"{task}.png",
                task_title=title,
                ylabel=f"return (mean ± std over {'/'.join(map(str, runs_text))} runs)",
                suptitle=f"{title}: {', '.join(curves)}",
            )
        )
        entry["figure"] = str(out / f"{task}.png")
        summary["tasks"][task] = entry
        try:  # (finite histories, but a mean can overflow)
            json.dumps(entry, allow_nan=False)
        except ValueError:
            raise AggregateError(
                f"{task}: a mean or std over the runs is not finite: returns too large for a "
                "float in their results.json"
            ) from None
    text = json.dumps(summary, indent=1, allow_nan=False)  # all checked: before any figure
    out.mkdir(parents=True, exist_ok=True)
    for figure in figures:
        plot_best_and_average(**figure)
    path = out / "aggregate.json"
    path.write_text(text)
    print(f"wrote {out}/<task>.png for {', '.join(groups)} and {path}")
    return summary


def main(argv: list[str] | None = None) -> int:
    from argtypes import output_dir

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("multirun_dirs", nargs="+", type=Path, metavar="MULTIRUN_DIR")
    parser.add_argument("--out", type=output_dir, required=True, help="directory for PNGs and JSON")
    parser.add_argument("--grid-step", type=int, default=10, help="trials between grid points")
    parser.add_argument(
        "--allow-incomplete",
        action="store_true",
        help="leave out run directories without results.json instead of failing",
    )
    args = parser.parse_args(argv)
    if args.grid_step < 1:
        parser.error(f"--grid-step must be a positive integer, got {args.grid_step}")
    try:
        aggregate(args.multirun_dirs, args.out, args.grid_step, args.allow_incomplete)
    except AggregateError as error:
        print(f"aggregate.py: error: {error}", file=sys.stderr)
        return 2
    return 0


if __name__ == "__main__":
    sys.exit(main())

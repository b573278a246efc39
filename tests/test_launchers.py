"""Sweeps through Hydra's launcher plugins (the ``sweep`` extra) and ``benchmarks/aggregate.py``.

Two real multiruns of ``train.py`` with a tiny budget, on joblib (4 seeds) and on
``submitit_local`` (2 seeds, the code path of a Slurm job on one machine), each aggregated
into curves that are checked against the runs' own ``results.json``; the Slurm config's sbatch
script, captured from a stub ``sbatch``; and the aggregator's grouping and errors on
hand-made run directories.
"""

from __future__ import annotations

import importlib.util
import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest
import yaml

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "benchmarks"))
import aggregate  # noqa: E402

TINY = ["task=multimodal", "trials=20", "progress=false", "figure_every=0"]
GRID_STEP = 5  # n0 = 10, budget 20: grid points 10, 15, 20


def plugin_installed(module: str) -> bool:
    """Whether Hydra's plugin ``hydra_plugins.<module>`` is installed; False also where no
    plugin is (``find_spec`` of a submodule raises when its parent package is missing)."""
    try:
        return importlib.util.find_spec(f"hydra_plugins.{module}") is not None
    except ModuleNotFoundError:
        return False


def needs_plugin(module: str):
    return pytest.mark.skipif(
        not plugin_installed(module),
        reason=f"{module} is not installed (pip install -e '.[sweep]')",
    )


def multirun(sweep_dir: Path, *overrides: str, env: dict | None = None, check: bool = True):
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "-m", *overrides, *TINY]
        + [f"hydra.sweep.dir={sweep_dir}"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        env=dict(os.environ, HYDRA_FULL_ERROR="1", **(env or {})),
        timeout=240,
    )
    if check and result.returncode != 0:
        raise AssertionError(f"train.py -m failed:\n{result.stdout}\n{result.stderr}")
    return result


def expected_curve(run_dir: Path, grid: list[int], key: str) -> list[float]:
    """The run's ``key`` at each grid point: its latest value at or before it (by hand)."""
    history = json.loads((run_dir / "results.json").read_text())["history"]
    return [
        [v for t, v in zip(history["trials"], history[key], strict=True) if t <= g][-1]
        for g in grid
    ]


def check_aggregate(sweep_dir: Path, out: Path, seeds: list[int]) -> dict:
    assert aggregate.main([str(sweep_dir), "--out", str(out), "--grid-step", str(GRID_STEP)]) == 0
    summary = json.loads((out / "aggregate.json").read_text())
    assert (out / "multimodal.png").stat().st_size > 10_000
    assert list(summary["tasks"]) == ["multimodal"] and summary["incomplete_runs"] == []
    task = summary["tasks"]["multimodal"]
    assert task["trials_grid"] == [10, 15, 20]
    assert list(task["curves"]) == ["DIPOLE"]
    curve = task["curves"]["DIPOLE"]
    assert curve["runs"] == len(seeds) and curve["seeds"] == seeds
    run_dirs = [Path(d) for d in curve["run_dirs"]]
    assert sorted(d.name for d in run_dirs) == [f"multimodal_dipole_seed{s}" for s in seeds]
    for key, name in (("best", "best"), ("average", "mean"), ("best_so_far", "best_so_far")):
        per_run = np.array([expected_curve(d, task["trials_grid"], name) for d in run_dirs])
        assert len(curve[key]["mean"]) == len(curve[key]["std"]) == 3
        np.testing.assert_allclose(curve[key]["mean"], per_run.mean(0), atol=1e-4)
        np.testing.assert_allclose(curve[key]["std"], per_run.std(0), atol=1e-4)
    assert curve["final_best"]["mean"] == pytest.approx(curve["best"]["mean"][-1], abs=1e-4)
    return curve


@needs_plugin("hydra_joblib_launcher")
def test_joblib_multirun_of_four_seeds_aggregates(tmp_path):
    sweep = tmp_path / "joblib"
    multirun(sweep, "hydra/launcher=joblib", "hydra.launcher.n_jobs=2", "seed=range(0,4)")
    assert yaml.safe_load((sweep / "multirun.yaml").read_text())["hydra"]["launcher"][
        "_target_"
    ].endswith("JoblibLauncher")
    check_aggregate(sweep, tmp_path / "figures", seeds=[0, 1, 2, 3])


@needs_plugin("hydra_submitit_launcher")
def test_submitit_local_multirun_of_two_seeds_aggregates(tmp_path):
    sweep = tmp_path / "submitit"
    multirun(sweep, "hydra/launcher=submitit_local", "seed=0,1")
    # submitit ran each run as its own job: a result pickle per job in the sweep directory.
    assert len(list((sweep / ".submitit").glob("*/*_result.pkl"))) == 2
    check_aggregate(sweep, tmp_path / "figures", seeds=[0, 1])


@needs_plugin("hydra_submitit_launcher")
def test_slurm_config_makes_a_one_cpu_array_job(tmp_path):
    # Stub sbatch/srun: submitit writes the sbatch script, the stub keeps it and refuses.
    bin_dir, captured = tmp_path / "bin", tmp_path / "captured.sh"
    bin_dir.mkdir()
    for name, body in (("srun", "exit 1"), ("sbatch", f'cp "$1" {captured}; exit 1')):
        (bin_dir / name).write_text(f"#!/bin/sh\n{body}\n")
        (bin_dir / name).chmod(0o755)
    path = f"{bin_dir}{os.pathsep}{os.environ['PATH']}"
    result = multirun(
        tmp_path / "slurm",
        "hydra/launcher=slurm",
        "seed=range(0,3)",
        env={"PATH": path},
        check=False,
    )
    assert result.returncode != 0 and captured.exists(), result.stderr
    script = captured.read_text()
    for line in (
        "#SBATCH --array=0-2%3",  # 3 runs, at most array_parallelism at once
        "#SBATCH --cpus-per-task=1",
        "#SBATCH --mem=2GB",
        "#SBATCH --time=60",
        "#SBATCH --signal=USR2@120",
    ):
        assert line in script.splitlines(), f"{line!r} not in\n{script}"
    assert f"{sys.executable} -u -m submitit.core._submit" in script


# ---- aggregate.py on hand-made run directories ---------------------------------------------


def fake_run(
    directory: Path,
    seed: int,
    *,
    decay: float = 1.0,
    finished: bool = True,
    policy_set: dict | None = None,
) -> None:
    """A run directory as train.py leaves it: PoWER on the multimodal task, budget 20;
    ``policy_set``: results.json's figures of the final policies taken together."""
    (directory / ".hydra").mkdir(parents=True)
    config = {
        "task": {"name": "multimodal", "trials": 300, "n0": 10},
        "algo": {"name": "power", "optimizer": {"exploration_decay": decay}},
        "seed": seed,
        "trials": 20,
        "progress": False,
    }
    (directory / ".hydra" / "config.yaml").write_text(yaml.safe_dump(config))
    if finished:
        trials = [10, 11, 12, 13, 14, 15, 16, 17, 18, 19, 20]
        best = [seed + t / 100 for t in trials]
        results = {
            "task": "multimodal",
            "algo": "power",
            "seed": seed,
            "history": {
                "trials": trials,
                "best": best,
                "mean": best,
                "best_so_far": best,
                "num_policies": [1] * len(trials),
            },
            **({} if policy_set is None else {"policy_set": policy_set}),
        }
        (directory / "results.json").write_text(json.dumps(results))


def run_aggregate(capsys, *args) -> tuple[int, str]:
    code = aggregate.main([str(a) for a in args])
    return code, capsys.readouterr().err


def test_aggregate_splits_a_hyperparameter_sweep_into_curves(tmp_path):
    for seed in range(3):
        for decay in (1.0, 0.98):
            fake_run(tmp_path / "sweep" / f"power_decay{decay}_seed{seed}", seed, decay=decay)
    summary = aggregate.aggregate([tmp_path / "sweep"], tmp_path / "out", 5, False)
    curves = summary["tasks"]["multimodal"]["curves"]
    assert set(curves) == {
        "PoWER (algo.optimizer.exploration_decay=0.98)",
        "PoWER (algo.optimizer.exploration_decay=1.0)",
    }
    for curve in curves.values():
        assert curve["seeds"] == [0, 1, 2]
        # best at trials 10, 15, 20 is seed + t/100: its mean over seeds 0..2 is 1 + t/100.
        assert curve["best"]["mean"] == pytest.approx([1.10, 1.15, 1.20])
        assert curve["best"]["std"] == pytest.approx([np.std([0, 1, 2])] * 3, abs=1e-4)


def test_an_extended_run_counts_with_its_final_budget(tmp_path):
    """A run resumed to a larger budget keeps its first session's trials in .hydra/: grouped
    by them, it made a curve of its own, cut at the first budget, beside the runs started
    with the larger one."""
    fake_run(tmp_path / "sweep" / "seed0", 0)
    fake_run(tmp_path / "sweep" / "seed1", 1)
    extended = tmp_path / "sweep" / "seed0" / "results.json"  # resumed from 20 to 30 trials
    results = json.loads(extended.read_text())
    for key, values in results["history"].items():
        results["history"][key] = values + [values[-1] + (10 if key == "trials" else 0)]
    results["trial_budget"] = results["trials"] = 30
    extended.write_text(json.dumps(results))
    for seed in (2, 3):  # started with the larger budget
        run = tmp_path / "sweep" / f"seed{seed}"
        fake_run(run, seed)
        config = yaml.safe_load((run / ".hydra" / "config.yaml").read_text())
        (run / ".hydra" / "config.yaml").write_text(yaml.safe_dump({**config, "trials": 30}))
        results = json.loads((run / "results.json").read_text())
        for key, values in results["history"].items():
            results["history"][key] = values + [values[-1] + (10 if key == "trials" else 0)]
        results["trial_budget"] = results["trials"] = 30
        (run / "results.json").write_text(json.dumps(results))
    summary = aggregate.aggregate([tmp_path / "sweep"], tmp_path / "out", 5, False)
    curves = summary["tasks"]["multimodal"]["curves"]
    assert {label: curve["seeds"] for label, curve in curves.items()} == {
        "PoWER (trials=20)": [1],
        "PoWER (trials=30)": [0, 2, 3],
    }


def test_aggregate_gives_the_final_policy_sets_figures_over_the_runs(tmp_path, capsys):
    """results.json's ``policy_set`` scalars (the viapoint task's routes) at each run's end:
    mean and std over the runs that report them."""
    for seed, routes in enumerate((3.0, 2.0, 4.0)):
        scalars = {"scalars": {"routes": routes}, "description": f"{routes:.0f} of the 8 routes"}
        fake_run(tmp_path / "sweep" / f"seed{seed}", seed, policy_set=scalars)
    summary = aggregate.aggregate([tmp_path / "sweep"], tmp_path / "out", 5, False)
    (curve,) = summary["tasks"]["multimodal"]["curves"].values()
    stats = curve["final_policy_set"]["routes"]
    assert stats == {"mean": 3.0, "std": pytest.approx(np.std([3, 2, 4])), "runs": 3}
    assert "routes 3 ± 0.82 (3 runs)" in capsys.readouterr().out
    fake_run(tmp_path / "plain" / "seed0", 0)  # a task with none
    summary = aggregate.aggregate([tmp_path / "plain"], tmp_path / "out2", 5, False)
    (curve,) = summary["tasks"]["multimodal"]["curves"].values()
    assert curve["final_policy_set"] == {}


def test_aggregate_errors_name_the_problem(tmp_path, capsys):
    code, err = run_aggregate(capsys, tmp_path / "missing", "--out", tmp_path / "o")
    assert code == 2 and "does not exist" in err
    (tmp_path / "empty").mkdir()
    code, err = run_aggregate(capsys, tmp_path / "empty", "--out", tmp_path / "o")
    assert code == 2 and "no train.py runs under" in err and "sweep output dir" in err
    (tmp_path / "file.yaml").write_text("x: 1\n")
    code, err = run_aggregate(capsys, tmp_path / "file.yaml", "--out", tmp_path / "o")
    assert code == 2 and "is a file" in err

    fake_run(tmp_path / "a" / "seed0", 0)
    fake_run(tmp_path / "a" / "seed1", 1, finished=False)
    code, err = run_aggregate(capsys, tmp_path / "a", "--out", tmp_path / "o")
    assert code == 2 and "1 run(s) have no results.json" in err and "seed1" in err
    code, err = run_aggregate(capsys, tmp_path / "a", "--out", tmp_path / "o", "--allow-incomplete")
    summary = json.loads((tmp_path / "o" / "aggregate.json").read_text())
    assert code == 0 and summary["incomplete_runs"] == [str(tmp_path / "a" / "seed1")]
    assert summary["tasks"]["multimodal"]["curves"]["PoWER"]["seeds"] == [0]

    fake_run(tmp_path / "b" / "seed0", 0)  # the same seed in a second sweep
    code, err = run_aggregate(
        capsys, tmp_path / "a", tmp_path / "b", "--out", tmp_path / "o", "--allow-incomplete"
    )
    assert code == 2 and "seed 0 of PoWER on multimodal appears twice" in err

    (tmp_path / "b" / "seed0" / "results.json").write_text('{"task": "multimodal"}')
    code, err = run_aggregate(capsys, tmp_path / "b", "--out", tmp_path / "o")
    assert code == 2 and "is not a train.py results.json" in err


# ---- aggregate.py refuses a bad run before it writes anything -------------------------------


def edit_results(directory: Path, **changes) -> None:
    """Set top-level keys of the run's results.json (``history`` is merged key by key)."""
    path = directory / "results.json"
    results = json.loads(path.read_text())
    results["history"].update(changes.pop("history", {}))
    results.update(changes)
    path.write_text(json.dumps(results))  # (json writes NaN and Infinity by default)


def edit_config(directory: Path, **changes) -> None:
    path = directory / ".hydra" / "config.yaml"
    config = yaml.safe_load(path.read_text())
    config.update(changes)
    path.write_text(yaml.safe_dump(config))


def refused(capsys, tmp_path, *flags) -> str:
    """aggregate.py's error on the sweep ``tmp_path/sweep``, checked to be exit status 2
    with nothing written."""
    out = tmp_path / "out"
    code, err = run_aggregate(capsys, tmp_path / "sweep", "--out", out, "--grid-step", 5, *flags)
    assert code == 2 and err.startswith("aggregate.py: error: "), err
    assert not out.exists() or not any(out.iterdir()), "wrote output for a refused sweep"
    return err


def two_runs(tmp_path) -> Path:
    """Seeds 0 and 1 of a finished sweep; returns seed 0's directory, the one to spoil."""
    fake_run(tmp_path / "sweep" / "seed1", 1)
    fake_run(tmp_path / "sweep" / "seed0", 0)
    return tmp_path / "sweep" / "seed0"


@pytest.mark.parametrize(
    "key, index, value",
    [("best", -1, float("nan")), ("mean", 3, float("inf")), ("best_so_far", 0, -float("inf"))],
)
def test_aggregate_refuses_a_history_that_is_not_finite(tmp_path, capsys, key, index, value):
    """A NaN at a grid point used to write the figures, then fail on the strict JSON; one
    between grid points went into the figures unseen."""
    run = two_runs(tmp_path)
    history = json.loads((run / "results.json").read_text())["history"]
    history[key][index] = value
    edit_results(run, history=history)
    err = refused(capsys, tmp_path)
    position = index % len(history[key])
    assert f"{run / 'results.json'}: history.{key}[{position}] is {value}" in err


@pytest.mark.parametrize(
    "policy_set, what",
    [
        (None, "policy_set must be a mapping, got None"),
        ([1, 2], "policy_set must be a mapping, got [1, 2]"),
        ({"scalars": [3.0]}, "policy_set.scalars must be a mapping of names to numbers"),
        ({"scalars": {"routes": "three"}}, "policy_set.scalars.routes must be a finite number"),
        ({"scalars": {"routes": [3.0]}}, "policy_set.scalars.routes must be a finite number"),
        ({"scalars": {"routes": float("nan")}}, "policy_set.scalars.routes must be a finite"),
    ],
)
def test_aggregate_refuses_a_policy_set_that_is_not_numbers_by_name(
    tmp_path, capsys, policy_set, what
):
    run = two_runs(tmp_path)
    edit_results(run, policy_set=policy_set)
    assert f"{run / 'results.json'}: {what}" in refused(capsys, tmp_path)


def test_aggregate_refuses_a_config_yaml_that_is_not_yaml(tmp_path, capsys):
    run = two_runs(tmp_path)
    (run / ".hydra" / "config.yaml").write_text("task: [multimodal\nseed: 0\n")
    err = refused(capsys, tmp_path)
    assert f"cannot read {run / '.hydra' / 'config.yaml'}: while parsing" in err
    assert len(err.strip().splitlines()) == 1  # (YAML's message on one line)


@pytest.mark.parametrize("key", ["task", "algo"])
def test_aggregate_refuses_a_task_or_algo_that_is_not_a_config_group(tmp_path, capsys, key):
    run = two_runs(tmp_path)
    edit_config(run, **{key: "multimodal"})
    err = refused(capsys, tmp_path)
    assert f"{run / '.hydra' / 'config.yaml'}: {key} must be a config group with a name" in err
    assert "got 'multimodal'" in err


@pytest.mark.parametrize("seed", ["abc", 1.5, True])
def test_aggregate_refuses_a_seed_that_is_not_an_integer(tmp_path, capsys, seed):
    """seed: 1.5 was cut to 1, then reported as seed 1 appearing twice (or, alone, passed)."""
    run = two_runs(tmp_path)
    edit_config(run, seed=seed)
    edit_results(run, seed=seed)
    err = refused(capsys, tmp_path)
    assert f"{run / '.hydra' / 'config.yaml'}: seed must be an integer, got {seed!r}" in err


@pytest.mark.parametrize("flags", [(), ("--allow-incomplete",)])
def test_aggregate_refuses_a_history_that_ends_before_the_budget(tmp_path, capsys, flags):
    """Its last values carried forward to the budget made wrong means. train.py writes
    results.json only at a run's end, so --allow-incomplete (runs without one) keeps it an
    error."""
    run = two_runs(tmp_path)
    for directory in (run, run.parent / "seed1"):
        edit_config(directory, trials=100)  # both 100: the grid would reach 100
    err = refused(capsys, tmp_path, *flags)
    assert f"{run / 'results.json'}: the history ends at 20 trials" in err
    assert f"{run / '.hydra' / 'config.yaml'} (trials=100)" in err

    shutil.rmtree(tmp_path / "sweep")
    run = two_runs(tmp_path)
    edit_results(run, trials=20, trial_budget=100)
    err = refused(capsys, tmp_path, *flags)
    assert f"{run / 'results.json'} says trials=20 of trial_budget=100" in err


def test_aggregate_checks_every_number_before_drawing_a_figure(tmp_path, capsys):
    """Finite returns whose mean overflows a float: refused before any figure is drawn."""
    run = two_runs(tmp_path)
    for directory in (run, run.parent / "seed1"):
        history = json.loads((directory / "results.json").read_text())["history"]
        edit_results(directory, history={"best": [1.7e308] * len(history["best"])})
    with np.errstate(over="ignore"):
        err = refused(capsys, tmp_path)
    assert "multimodal: a mean or std over the runs is not finite" in err

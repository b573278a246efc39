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

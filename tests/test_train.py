"""train.py end to end: outputs, TensorBoard scalars, resume, multirun, config errors."""

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest
import torch
from hydra import compose, initialize_config_dir
from hydra.utils import instantiate
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

ROOT = Path(__file__).resolve().parents[1]


def train(*overrides, cwd=ROOT, check=True):
    env = dict(os.environ, HYDRA_FULL_ERROR="0")
    result = subprocess.run(
        # Hydra's flags (-m) must precede the overrides.
        [sys.executable, str(ROOT / "train.py"), *sorted(overrides, key=lambda a: a[0] != "-")]
        + ["progress=false"],
        cwd=cwd,
        capture_output=True,
        text=True,
        env=env,
        timeout=300,
    )
    if check and result.returncode != 0:
        raise AssertionError(f"train.py failed:\n{result.stdout}\n{result.stderr}")
    return result


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("run")
    train("task=multimodal", "algo=dipole", "seed=0", "trials=80", f"hydra.run.dir={run_dir}")
    return run_dir


def test_outputs_and_tensorboard_scalars(finished_run):
    results = json.loads((finished_run / "results.json").read_text())
    assert results["trials"] >= 80 and results["algo"] == "dipole"
    history = results["history"]
    events = EventAccumulator(str(finished_run / "tensorboard"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {
        "reward/best",
        "reward/mean",
        "reward/best_so_far",
        "policies/count",
        "policies/exploration_std",
    } <= tags
    best = events.Scalars("reward/best")
    assert [e.step for e in best] == history["trials"]  # the x-axis is trials
    assert [e.value for e in best] == pytest.approx(history["best"], rel=1e-6)
    mean = events.Scalars("reward/mean")
    assert all(m.value <= b.value + 1e-6 for m, b in zip(mean, best, strict=True))
    counts = [e.value for e in events.Scalars("policies/count")]
    assert counts == history["num_policies"] and min(counts) >= 1
    assert 0.0 <= results["best_reward"] <= 1.0
    assert max(history["best_so_far"]) == pytest.approx(results["best_reward"])
    saved = torch.load(finished_run / "policies.pt")
    assert {"policies", "mixture"} <= set(saved)


def test_resume_continues_exactly(finished_run, tmp_path):
    straight = tmp_path / "straight"
    resumed = tmp_path / "resumed"
    train("trials=140", f"hydra.run.dir={straight}")
    train("trials=140", f"resume={finished_run / 'checkpoint.pt'}", f"hydra.run.dir={resumed}")
    a = json.loads((straight / "results.json").read_text())
    b = json.loads((resumed / "results.json").read_text())
    assert a["history"] == b["history"]
    assert a["best_theta"] == b["best_theta"]
    assert [p["mean"] for p in a["policies"]] == [p["mean"] for p in b["policies"]]


def test_multirun_over_seeds(tmp_path):
    out = train("-m", "seed=0,1", "trials=30", "algo=power", f"hydra.sweep.dir={tmp_path}")
    runs = sorted(tmp_path.glob("*/results.json"))
    assert len(runs) == 2, out.stdout
    seeds = sorted(json.loads(p.read_text())["seed"] for p in runs)
    assert seeds == [0, 1]


def test_the_papers_dipole_runs_from_the_command_line(tmp_path):
    train("task=multimodal", "algo=dipole_paper", "trials=40", f"hydra.run.dir={tmp_path}")
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["algo"] == "dipole_paper" and results["trials"] >= 40


def test_unknown_task_on_the_command_line(tmp_path):
    result = train("task=no_such_task", f"hydra.run.dir={tmp_path}", check=False)
    assert result.returncode != 0
    assert "Could not find 'task/no_such_task'" in result.stderr + result.stdout
    assert "multimodal" in result.stderr + result.stdout  # Hydra lists the available tasks


def compose_config(*overrides):
    with initialize_config_dir(str(ROOT / "configs"), version_base=None):
        return compose("config", overrides=list(overrides))


@pytest.mark.parametrize(
    "override, message",
    [
        ("trials=-5", "trials (the trial budget) must be a positive integer"),
        ("trials=0", "trials (the trial budget) must be a positive integer"),
        ("device=tpu", "device must be 'cpu', 'cuda' or 'cuda:N', got 'tpu'"),
        ("threads=0", "threads must be a positive integer"),
        ("task.n0=0", "task.n0 (initial samples) must be a positive integer"),
    ],
)
def test_bad_config_values_give_a_clear_error(override, message):
    from train import check_config

    with pytest.raises(ValueError) as error:
        check_config(compose_config(override))
    assert message in str(error.value)


def test_unknown_algo_and_bad_algo_parameters():
    with pytest.raises(Exception, match="Could not find 'algo/cmaes'"):
        compose_config("algo=cmaes")
    cfg = compose_config("algo.optimizer.alpha=-1")
    with pytest.raises(Exception, match=r"alpha \(DP concentration\) must be positive"):
        instantiate(cfg.algo.optimizer, theta0=torch.zeros(2), sigma_start=torch.eye(2))

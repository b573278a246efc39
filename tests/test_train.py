"""train.py end to end: outputs, TensorBoard scalars and hparams, train.log, the trial budget,
resume, multirun, typed configs and --help, config errors."""

import dataclasses
import itertools
import json
import math
import os
import re
import subprocess
import sys
import typing
from pathlib import Path

import numpy as np
import pytest
import torch
from dipole_torch.tasks.multimodal import MultimodalTask
from hydra import compose, initialize_config_dir
from hydra.errors import ConfigCompositionException
from omegaconf import OmegaConf
from omegaconf.errors import ValidationError
from tensorboard.backend.event_processing.event_accumulator import EventAccumulator
from tensorboard.plugins.hparams import plugin_data_pb2

from dipole_torch import Dipole
from dipole_torch.training import config as schemas
from dipole_torch.training import results as run_results
from dipole_torch.training.hydra_compat import VERSION_BASE, instantiate

schemas.register()  # (train.py does it; the tests below read the tables)

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
    assert results["trials"] <= 80 and results["algo"] == "dipole"
    history = results["history"]
    events = EventAccumulator(str(finished_run / "tensorboard"))
    events.Reload()
    tags = set(events.Tags()["scalars"])
    assert {
        "reward/best",
        "reward/mean",
        "reward/best_so_far",
        "search/policies",
        "search/log10_exploration_std",
        "search/clusterings_skipped",
    } <= tags
    assert not [tag for tag in tags if tag.startswith("hparam")]  # those are in HPARAMS only
    best = events.Scalars("reward/best")
    assert [e.step for e in best] == history["trials"]  # the x-axis is trials
    assert [e.value for e in best] == pytest.approx(history["best"], rel=1e-6)
    mean = events.Scalars("reward/mean")
    assert all(m.value <= b.value + 1e-6 for m, b in zip(mean, best, strict=True))
    skipped = [e.value for e in events.Scalars("search/clusterings_skipped")]
    assert [e.step for e in events.Scalars("search/clusterings_skipped")] == history["trials"]
    assert skipped == sorted(skipped) and skipped[-1] == 0  # a healthy run skips none
    counts = [e.value for e in events.Scalars("search/policies")]
    assert counts == history["num_policies"] and min(counts) >= 1
    assert 0.0 <= results["best_reward"] <= 1.0
    assert max(history["best_so_far"]) == pytest.approx(results["best_reward"])
    saved = torch.load(finished_run / "policies.pt")
    assert {"policies", "mixture"} <= set(saved)


def test_hparams_hold_the_config_and_the_final_metrics(finished_run):
    results = json.loads((finished_run / "results.json").read_text())
    events = EventAccumulator(str(finished_run / "tensorboard"))
    events.Reload()
    content = events.PluginTagToContent("hparams")
    assert {"_hparams_/experiment", "_hparams_/session_start_info"} <= set(content)
    start = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/session_start_info"])
    hparams = start.session_start_info.hparams
    assert hparams["algo.optimizer.alpha"].number_value == 1.0
    assert hparams["task.name"].string_value == "multimodal"
    assert hparams["trials"].number_value == 80  # the budget
    assert hparams["resume"].string_value == "null"
    experiment = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/experiment"])
    metrics = {m.name.tag for m in experiment.experiment.metric_infos}
    # The run's own scalars, and the task's of its final policies (the optima found).
    assert metrics == {"reward/best_so_far", "search/policies", "task/optima"}
    best = events.Scalars("reward/best_so_far")[-1]
    assert best.value == pytest.approx(results["best_reward"]) and best.step == results["trials"]
    assert events.Scalars("search/policies")[-1].value == len(results["policies"])


class LoggedSearch:
    """What ``Board.log_iteration`` reads of an optimizer: three policies, the middle one
    retired, their latest returns 1, 4 and −2, the best return so far 7.5 (told earlier)."""

    trials, num_policies, clusterings_skipped = 30, 3, 2
    last_rewards = torch.tensor([1.0, 4.0, -2.0], dtype=torch.float64)
    active = torch.tensor([True, False, True])

    def relative_std(self):
        return torch.tensor([1e-2, 1.0, 1e-4], dtype=torch.float64)

    def best(self):
        return torch.zeros(2, dtype=torch.float64), 7.5


def test_the_board_logs_each_iterations_scalars(tmp_path):
    """reward/best and reward/mean of the latest returns, reward/best_so_far from best(),
    search/log10_exploration_std the log10 of the active policies' mean relative std (all
    policies' once none is active), the returns' histogram, the clusterings skipped."""
    from dipole_torch.training.board import Board

    board = Board(tmp_path, OmegaConf.create({"seed": 0}))
    search = LoggedSearch()
    row = board.log_iteration(search)
    assert row == {
        "trials": 30, "best": 4.0, "mean": 1.0, "best_so_far": 7.5, "num_policies": 3,
        "exploration_std": pytest.approx(0.00505),
    }  # fmt: skip
    search.trials, search.active = 40, torch.zeros(3, dtype=torch.bool)
    assert board.log_iteration(search)["exploration_std"] == pytest.approx(1.0101 / 3)
    board.close()
    events = EventAccumulator(str(tmp_path))
    events.Reload()

    def values(tag):
        return [(event.step, event.value) for event in events.Scalars(tag)]

    assert values("reward/best") == [(30, 4.0), (40, 4.0)]
    assert values("reward/mean") == [(30, 1.0), (40, 1.0)]
    assert values("reward/best_so_far") == [(30, 7.5), (40, 7.5)]
    assert values("search/clusterings_skipped") == [(30, 2.0), (40, 2.0)]
    logged = [value for _, value in values("search/log10_exploration_std")]
    assert logged == pytest.approx([math.log10(0.00505), math.log10(1.0101 / 3)], rel=1e-6)
    assert "search/rewards" in events.Tags()["histograms"]


def test_train_log_holds_the_log_lines_and_the_summary(finished_run):
    results = json.loads((finished_run / "results.json").read_text())
    log = (finished_run / "train.log").read_text()
    assert f"dipole on multimodal: best return {results['best_reward']:.4g}" in log
    assert f"in {results['trials']} trials (budget 80)" in log
    assert "[train][INFO]" in log  # Hydra's file format: time, logger, level
    assert log.count("  policy ") == len(results["policies"])
    # The task's line on the policies together: the optima they found.
    found = {
        p["description"].split(",")[0] for p in results["policies"] if p["return_of_mean"] >= 0.99
    }
    assert results["policy_set"]["scalars"] == {"optima": len(found)}  # (1 on this seed)
    line = results["policy_set"]["description"]
    assert line.startswith(f"{len(found)} of the 4 optima at return ≥ 0.99") and line in log


def test_each_policy_figure_is_logged_once_with_the_tasks_scalars(tmp_path):
    """A figure every iteration, and the final one not drawn again at the same trial count;
    the viapoint task's ``task/routes`` with each, in the HPARAMS metrics, in results.json
    and in the summary."""
    train("task=viapoint", "trials=40", "task.n0=30", "figure_every=1", f"hydra.run.dir={tmp_path}")
    results = json.loads((tmp_path / "results.json").read_text())
    events = EventAccumulator(str(tmp_path / "tensorboard"), size_guidance={"images": 0})
    events.Reload()
    steps = [event.step for event in events.Images("search/figure")]
    assert steps == results["history"]["trials"] and steps[-1] == results["trials"] == 40
    # With the figure, the task's scalars of the policies: the routes they take.
    routes = events.Scalars("task/routes")
    assert [event.step for event in routes] == steps
    found = results["policy_set"]["scalars"]["routes"]
    assert routes[-1].value == found and 0 <= found <= 8
    good = {
        p["description"].split(":")[0] for p in results["policies"] if p["return_of_mean"] >= 0.9
    }
    assert found == len(good)  # the distinct routes of the policies at return ≥ 0.9
    description = results["policy_set"]["description"]
    assert description.startswith(f"{found:.0f} of the 8 routes at return ≥ 0.9")
    assert description in (tmp_path / "train.log").read_text()  # the summary's last lines
    content = events.PluginTagToContent("hparams")
    experiment = plugin_data_pb2.HParamsPluginData.FromString(content["_hparams_/experiment"])
    metrics = {m.name.tag for m in experiment.experiment.metric_infos}
    assert metrics == {"reward/best_so_far", "search/policies", "task/routes"}


def test_the_summary_is_on_stdout(tmp_path):
    out = train("algo=power", "trials=20", f"hydra.run.dir={tmp_path}").stdout
    assert "power on multimodal: best return" in out and "in 20 trials (budget 20)" in out
    assert "  policy 0: optimum " in out and f"outputs in {tmp_path}" in out
    assert "[INFO]" not in out  # plain lines on stdout; train.log has time and level


def test_power_evaluates_exactly_the_trial_budget(tmp_path):
    train("algo=power", "trials=37", f"hydra.run.dir={tmp_path}")
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["trials"] == 37 and results["trial_budget"] == 37
    assert results["history"]["trials"][-1] == 37
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    assert events.Scalars("reward/best")[-1].step == 37


def test_dipole_evaluates_exactly_the_trial_budget(tmp_path):
    """The batch that would cross the budget is cut to its first rows; the checkpoint keeps
    the run before it: its optimizer, asked again, proposes that whole batch. (The budget
    is set to cut a batch of an uninterrupted run of this seed after its first row.)"""
    straight = tmp_path / "straight"
    train("task=multimodal", "algo=dipole", "seed=0", "trials=90", f"hydra.run.dir={straight}")
    ends = json.loads((straight / "results.json").read_text())["history"]["trials"]
    before, after = next((a, b) for a, b in itertools.pairwise(ends) if b - a >= 2)
    budget = before + 1
    cut = tmp_path / "cut"
    train("task=multimodal", "algo=dipole", "seed=0", f"trials={budget}", f"hydra.run.dir={cut}")
    results = json.loads((cut / "results.json").read_text())
    assert results["trial_budget"] == budget
    assert results["trials"] == budget and results["history"]["trials"][-1] == budget
    message = f"the last batch is cut to its first 1 of {after - before} rows"
    assert message in (cut / "train.log").read_text()
    checkpoint = torch.load(cut / "checkpoint.pt", weights_only=True)
    trials = checkpoint["optimizer"]["trials"]
    assert trials == before
    assert checkpoint["optimizer"]["pending"] is None
    cfg = compose_config(f"trials={budget}")
    task = instantiate(cfg.task.env)
    optimizer = instantiate(
        cfg.algo.optimizer,
        theta0=task.theta0.double(),
        sigma_start=task.sigma_start.double(),
        n0=cfg.task.n0,
        generator=torch.Generator(),
    )
    assert isinstance(optimizer, Dipole)
    optimizer.load_state_dict(checkpoint["optimizer"])
    assert trials + optimizer.ask().shape[0] > budget
    # A resume with a larger budget makes the draws of an uninterrupted run.
    resumed = tmp_path / "resumed"
    train(
        "task=multimodal",
        "algo=dipole",
        "seed=0",
        "trials=90",
        f"resume={cut / 'checkpoint.pt'}",
        f"hydra.run.dir={resumed}",
    )
    a = json.loads((straight / "results.json").read_text())
    b = json.loads((resumed / "results.json").read_text())
    assert a["history"] == b["history"] and a["best_theta"] == b["best_theta"]
    # The checkpoint says where its run ended: a resume asking for fewer trials (even the
    # checkpoint's own) would write a shorter run's results over the finished one's.
    assert checkpoint["run_trials"] == budget
    finished = (cut / "results.json").read_bytes()
    refused = train(
        "task=multimodal",
        "seed=0",
        f"trials={before}",
        f"resume={cut / 'checkpoint.pt'}",
        check=False,
    )
    assert refused.returncode == 2, refused.stderr
    assert (
        f"with trials={before}: its run ended at {budget} trials (its checkpoint keeps it at "
        f"{before}, before the last batch, cut at that budget), and a run cannot go back; "
        f"give trials={budget} or more"
    ) in refused.stderr
    assert (cut / "results.json").read_bytes() == finished
    # At the budget it ended at, the resume makes the same run again (the same cut batch).
    train("task=multimodal", "seed=0", f"trials={budget}", f"resume={cut / 'checkpoint.pt'}")
    again = json.loads((cut / "results.json").read_text())
    assert again["history"] == results["history"] and again["best_theta"] == results["best_theta"]
    assert torch.load(cut / "checkpoint.pt", weights_only=True)["run_trials"] == budget


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


def test_a_run_says_when_it_starts_covering(finished_run, tmp_path):
    train(
        "task=multimodal",
        "trials=60",
        "algo.optimizer.coverage_from=30",
        f"hydra.run.dir={tmp_path}",
    )
    said = re.findall(r"from trial (\d+) on, DIPOLE covers alternatives \(coverage_from=30\)",
                      (tmp_path / "train.log").read_text())  # fmt: skip
    # At the first ask from trial 30: the run (the finished run's draws until then) reaches
    # 30 exactly, and says so there, not one batch later.
    first = min(t for t in json.loads((finished_run / "results.json").read_text())["history"]
                ["trials"] if t >= 30)  # fmt: skip
    assert len(said) == 1 and int(said[0]) == first == 30, said
    assert "active)" not in (tmp_path / "train.log").read_text()
    assert "covers alternatives" not in (finished_run / "train.log").read_text()
    capped = tmp_path / "capped"
    train(
        "task=multimodal",
        "trials=40",
        "algo.optimizer.coverage_from=30",
        "algo.optimizer.coverage_max_policies=10",
        f"hydra.run.dir={capped}",
    )
    assert (
        "every active policy is sampled (at most 10 active)" in (capped / "train.log").read_text()
    )


def test_multirun_over_seeds(tmp_path):
    out = train("-m", "seed=0,1", "trials=30", "algo=power", f"hydra.sweep.dir={tmp_path}")
    runs = sorted(tmp_path.glob("*/results.json"))
    assert len(runs) == 2, out.stdout
    seeds = sorted(json.loads(p.read_text())["seed"] for p in runs)
    assert seeds == [0, 1]
    # The run settings (the budget, progress) do not name a run's directory.
    assert [p.parent.name for p in runs] == ["multimodal_power_seed0", "multimodal_power_seed1"]


def test_a_sweep_over_a_hyperparameter_gives_each_run_its_own_directory(tmp_path):
    # The runs of one seed that differ in a setting wrote to one <task>_<algo>_seed<seed>/:
    # the second was refused ("already holds a run's checkpoint.pt") and the sweep failed.
    train("-m", "algo=power", "algo.optimizer.M=4,5", "trials=20", f"hydra.sweep.dir={tmp_path}")
    runs = sorted(path.parent.name for path in tmp_path.glob("*/results.json"))
    assert runs == [
        "multimodal_power_seed0_algo.optimizer.M=4",
        "multimodal_power_seed0_algo.optimizer.M=5",
    ]


def test_a_sweep_runs_directory_name_fits_a_file_name_however_many_settings():
    """Eight settings of an ablation made a name past a file name's 255 bytes, which no
    directory can have (ENAMETOOLONG): a long suffix keeps its start and a digest of all the
    settings, so that runs differing past the cut still differ."""
    from dipole_torch.training.resume import MAX_SUFFIX_BYTES, setting_suffix

    fixed = [f"algo.optimizer.{key}=0.0{i}" for i, key in enumerate("abcdefgh")] + [
        "task.env.obstacles=[{centre:[0.4,0.06,0.0],radius:0.05}]"
    ]
    names = {setting_suffix([*fixed, f"task.env.width={w}"]) for w in (0.25, 0.3)}
    assert len(names) == 2
    for name in names:
        assert len(name.encode()) <= MAX_SUFFIX_BYTES
        assert name.startswith("_algo.optimizer.a=0.00,algo.optimizer.b=0.01")
    assert len(f"viapoint_blocked_dipole_coverage_seed1000000{max(names)}".encode()) < 255
    assert setting_suffix(["algo.optimizer.M=4"]) == "_algo.optimizer.M=4"  # short: as it is


def test_a_sweep_whose_runs_share_a_directory_says_how_to_tell_them_apart(tmp_path):
    # The budget does not name a run's directory: a sweep over it alone sends both runs to
    # one, and the second is refused, pointing at the sweep's directories (not hydra.run.dir).
    out = train("-m", "algo=power", "trials=20,30", f"hydra.sweep.dir={tmp_path}", check=False)
    assert out.returncode == 2
    assert "already holds a run's checkpoint.pt" in out.stderr
    # The refused run's record did not replace the finished run's (Hydra writes it before the
    # run starts: the 20-trial run's .hydra said trials=30, and aggregate.py believed it).
    (record,) = tmp_path.glob("*/.hydra")
    assert "trials=20" in (record / "overrides.yaml").read_text()
    assert "trials: 20" in (record / "config.yaml").read_text()
    names = sorted(path.name for path in record.iterdir())
    assert names == ["config.yaml", "hydra.yaml", "overrides.yaml"]  # no refused_<time> left
    assert "hydra.sweep.subdir" in out.stderr and "hydra.run.dir" not in out.stderr
    # The subdir it gives for a sweep over the budget runs it.
    subdir = re.search(r"'(hydra\.sweep\.subdir=[^']*)'", out.stderr).group(1)
    other = tmp_path / "named"
    train("-m", "algo=power", "trials=20,30", f"hydra.sweep.dir={other}", subdir)
    runs = sorted(path.parent.name for path in other.glob("*/results.json"))
    assert runs == ["multimodal_power_seed0_trials20", "multimodal_power_seed0_trials30"]


def test_the_papers_dipole_runs_from_the_command_line(tmp_path):
    train("task=multimodal", "algo=dipole_paper", "trials=40", f"hydra.run.dir={tmp_path}")
    results = json.loads((tmp_path / "results.json").read_text())
    assert results["algo"] == "dipole_paper" and 30 < results["trials"] <= 40


def test_unknown_task_on_the_command_line(tmp_path):
    result = train("task=no_such_task", f"hydra.run.dir={tmp_path}", check=False)
    assert result.returncode != 0
    assert "Could not find 'task/no_such_task'" in result.stderr + result.stdout
    assert "multimodal" in result.stderr + result.stdout  # Hydra lists the available tasks


def compose_config(*overrides):
    with initialize_config_dir(str(ROOT / "configs"), **VERSION_BASE):
        return compose("config", overrides=list(overrides))


def test_the_runs_own_settings_default_to_the_documented_values():
    cfg = compose_config()
    keys = ("seed", "device", "threads", "checkpoint_every", "figure_every", "resume", "progress")
    assert {key: cfg[key] for key in keys} == {
        "seed": 0, "device": "cpu", "threads": 1, "checkpoint_every": 20, "figure_every": 25,
        "resume": None, "progress": True,
    }  # fmt: skip
    assert cfg.trials == cfg.task.trials == 300  # the task's budget
    # The task runs on the run's device unless set apart.
    assert compose_config("device=cuda:1").task.env.device == "cuda:1"


@pytest.mark.parametrize(
    "overrides, key, message",
    [
        (["algo.optimizer.alpha=abc"], "algo.optimizer.alpha", "could not be converted to Float"),
        (["algo=power", "algo.optimizer.M=2.5"], "algo.optimizer.M", "converted to Integer"),
        (
            ["algo=dipole_paper", "algo.optimizer.reward_weighted=maybe"],
            "algo.optimizer.reward_weighted",
            "Value 'maybe' is not a valid bool",
        ),
        (["task=viapoint", "task.env.pass_times=[0.4,soon]"], "task.env.pass_times[1]", "Float"),
        # A parameter typed str | Path is a string in the schema.
        (["task=viapoint", "task.env.urdf=[a.urdf]"], "task.env.urdf", "Cannot convert 'list'"),
        (["task=cartpole", "task.n0=ten"], "task.n0", "could not be converted to Integer"),
        (["trials=true"], "trials", "could not be converted to Integer"),
        (["seed=abc"], "seed", "could not be converted to Integer"),
    ],
)
def test_a_value_of_the_wrong_type_fails_naming_the_key(overrides, key, message):
    with pytest.raises(ConfigCompositionException) as error:
        compose_config(*overrides)
    cause = error.value.__cause__
    assert isinstance(cause, ValidationError), repr(cause)
    assert message in str(cause) and cause.full_key == key


def test_a_wrong_type_on_the_command_line_names_the_key(tmp_path):
    result = train("algo.optimizer.alpha=abc", f"hydra.run.dir={tmp_path}", check=False)
    assert result.returncode != 0 and not (tmp_path / "checkpoint.pt").exists()
    assert "Value 'abc' of type 'str' could not be converted to Float" in result.stderr
    assert "full_key: algo.optimizer.alpha" in result.stderr


def test_the_configs_extend_the_schemas_and_build_their_targets(tmp_path):
    """Every YAML option is typed by its schema, composed through Hydra's compose API in a
    fresh process started in another directory (importing dipole_torch.configs registers the
    schemas), and instantiates."""
    options = [(f"task={name}", "algo=dipole") for name in schemas.TASKS]
    options += [("task=multimodal", f"algo={name}") for name in schemas.ALGOS]
    code = (
        "import sys\n"
        "from hydra import compose, initialize_config_module\n"
        "from omegaconf import OmegaConf\n"
        "from dipole_torch.training.hydra_compat import VERSION_BASE\n"
        "with initialize_config_module('dipole_torch.configs', **VERSION_BASE):\n"
        f"    for overrides in {options!r}:\n"
        "        cfg = compose('config', overrides=list(overrides))\n"
        "        print(OmegaConf.get_type(cfg).__name__, OmegaConf.get_type(cfg.task).__name__,\n"
        "              OmegaConf.get_type(cfg.algo).__name__)\n"
        "assert 'train' not in sys.modules\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=tmp_path, capture_output=True, text=True, timeout=120
    )
    assert result.returncode == 0, result.stderr
    types = [line.split() for line in result.stdout.splitlines()]
    dipole = schemas.ALGOS["dipole"].__name__
    expected = [["Config", schemas.TASKS[name].__name__, dipole] for name in schemas.TASKS]
    expected += [
        ["Config", schemas.TASKS["multimodal"].__name__, schemas.ALGOS[name].__name__]
        for name in schemas.ALGOS
    ]
    assert types == expected
    # The optimizers build from their configs, keyword arguments and _target_ included.
    theta0, sigma = torch.zeros(2, dtype=torch.float64), torch.eye(2, dtype=torch.float64)
    paper = instantiate(
        compose_config("algo=dipole_paper", "algo.optimizer.alpha=2").algo.optimizer,
        theta0=theta0,
        sigma_start=sigma,
        reward_range=(0.0, 1.0),
    )
    assert paper.options.matching == "replace" and paper.options.alpha == 2.0
    default = instantiate(
        compose_config(
            "algo.optimizer.max_policies=null", "algo.optimizer.explore=0"
        ).algo.optimizer,
        theta0=theta0,
        sigma_start=sigma,
    )
    assert default.options.max_policies is None and default.options.explore == 0.0


def test_the_coverage_preset_is_the_library_variant_with_three_options_changed():
    """``algo=dipole_coverage`` builds a Dipole whose options are the defaults but for
    ``accept_unjudged=True``, ``max_sampled=None`` and ``unjudged_share=0.5`` (the three the
    docs' coverage rows use)."""
    from dipole_torch import DipoleOptions

    cfg = compose_config("algo=dipole_coverage").algo
    assert cfg.name == "dipole_coverage" and not cfg.use_task_reward_range
    opt = instantiate(cfg.optimizer, theta0=torch.zeros(2, dtype=torch.float64), sigma_start=1.0)
    assert isinstance(opt, Dipole)
    changed = {
        f.name
        for f in dataclasses.fields(DipoleOptions)
        if getattr(opt.options, f.name) != getattr(DipoleOptions(), f.name)
    }
    assert changed == {"accept_unjudged", "max_sampled", "unjudged_share"}
    assert opt.options.accept_unjudged is True and opt.options.max_sampled is None
    assert opt.options.unjudged_share == 0.5
    # An override still applies on top of the preset.
    cfg = compose_config("algo=dipole_coverage", "algo.optimizer.max_sampled=6").algo
    assert cfg.optimizer.max_sampled == 6 and cfg.optimizer.accept_unjudged


def test_the_viapoint_task_covers_from_its_default_budget_with_dipole_only():
    """``configs/task_algo/viapoint_dipole.yaml`` (Hydra's specializing pattern) sets
    ``coverage_from=300`` (with its cap of 10 active policies) for ``task=viapoint
    algo=dipole`` and for no other pair; an override sets it back."""
    cfg = compose_config("task=viapoint")
    assert cfg.algo.name == "dipole" and cfg.algo.optimizer.coverage_from == 300
    # (It is the task's default budget, written in both files: they must move together.)
    assert cfg.task.trials == cfg.algo.optimizer.coverage_from
    opt = instantiate(
        cfg.algo.optimizer, theta0=torch.zeros(2, dtype=torch.float64), sigma_start=1.0
    )
    assert opt.options.coverage_from == 300 and opt.options.unjudged_share is None
    assert opt.options.coverage_max_policies == 10 and opt.options.max_policies == 8
    # Turned off by coverage_from=null alone: the cap has nothing left to act on.
    off = compose_config("task=viapoint", "algo.optimizer.coverage_from=null").algo.optimizer
    opt = instantiate(off, theta0=torch.zeros(2, dtype=torch.float64), sigma_start=1.0)
    assert opt.options.coverage_from is None and opt.max_policies == 8
    for overrides in (
        ["task=viapoint", "algo.optimizer.coverage_from=null"],
        ["task=viapoint", "algo=dipole_coverage"],
        ["task=viapoint_blocked"],
        ["task=cartpole"],
        ["task=multimodal"],
        ["task=viapoint", "algo=dipole_paper"],
        ["task=viapoint", "algo=power"],  # (an option it does not have)
    ):
        optimizer = compose_config(*overrides).algo.optimizer
        assert optimizer.get("coverage_from") is None, overrides
        if overrides != ["task=viapoint", "algo.optimizer.coverage_from=null"]:
            assert optimizer.get("coverage_max_policies") is None, overrides


def test_each_default_is_stated_once_in_the_code():
    """The YAML files hold the experiments' own settings only; every task's and optimizer's
    argument and default comes from its signature (DIPOLE's: DipoleOptions)."""
    import inspect

    from dipole_torch import DipoleOptions, Power

    for group, table in (("task", schemas.TASKS), ("algo", schemas.ALGOS)):
        for name in table:
            yaml = OmegaConf.to_container(OmegaConf.load(ROOT / "configs" / group / f"{name}.yaml"))
            assert yaml.pop("defaults") == [f"/dipole_torch_{group}_{name}@_here_", "_self_"]
            own = {"name", "trials", "n0"} if group == "task" else {"name", "use_task_reward_range"}
            assert set(yaml) == own, name
    env = OmegaConf.structured(schemas.TASKS["viapoint"]).env
    env.device = "cpu"
    signature = inspect.signature(type(instantiate(env)).__init__).parameters
    for key, value in env.items():
        if key not in ("_target_", "device"):
            default = signature[key].default
            default = list(default) if isinstance(default, tuple) else default
            assert OmegaConf.to_container(OmegaConf.create({"v": value}))["v"] == (
                json.loads(json.dumps(default))
            ), key
    dipole = OmegaConf.structured(schemas.ALGOS["dipole"]).optimizer
    for key, value in dipole.items():
        if key not in ("_target_", "bounds"):
            assert value == getattr(DipoleOptions(), key), key
    power = OmegaConf.structured(schemas.ALGOS["power"]).optimizer
    parameters = inspect.signature(Power.__init__).parameters
    assert all(power[k] == parameters[k].default for k in power if k != "_target_")


def test_the_help_page_lists_the_choices_the_nullable_types_and_each_preset_once(monkeypatch):
    text = schemas.help_text("")
    lines = text.splitlines()
    tasks = sorted(p.stem for p in (ROOT / "configs" / "task").glob("*.yaml"))
    assert f"== Tasks: task={', '.join(tasks)} ==" in lines
    assert "  resume: str or null = null" in lines
    assert "  task.block: ViapointBlock or null = null" in lines
    assert "  task.env.start: list[float] or null = [0.5, -0.35, 0.0]" in lines  # a tuple default
    assert not [line for line in lines if "_target_" in line]  # what is built is no setting
    presets = [line for line in lines if "settings above" in line]
    assert presets == [
        "== algo=dipole_coverage: the algo=dipole settings above, with accept_unjudged=true, "
        "max_sampled=null, unjudged_share=0.5 =="
    ]
    # The program as it was started: the script, or the installed command.
    monkeypatch.setattr(sys, "argv", ["/usr/local/bin/dipole-train"])
    assert schemas.help_text("").startswith("dipole-train [task=<task>]")
    monkeypatch.setattr(sys, "argv", ["train.py"])
    assert schemas.help_text("").startswith("python train.py [task=<task>]")


def test_help_with_hydras_own_flags_shows_the_config_the_overrides_compose(capsys):
    # python train.py -m task=viapoint seed=3 --help: the flags are Hydra's, not overrides.
    schemas.print_help(["-m", "task=viapoint", "seed=3", "--help"], str(ROOT / "configs"))
    config = capsys.readouterr().out.split("== This run's config (with the overrides given) ==")[1]
    assert "name: viapoint" in config and "seed: 3" in config


def test_a_fields_help_is_the_first_sentence_of_its_docstring_entry():
    from dipole_torch.training.schemas import docstring_help

    doc = """Summary.

    Args:
        a: Use e.g. a :class:`~torch.Tensor` box
            (see Box.fit). Then more.
        b (int): ``k`` of eq. 9 in 1/m. Next.
        c: one; see Foo.bar
            note: a continued line, not an argument.
    """
    assert docstring_help(doc) == {"a": "Use e.g. a torch.Tensor box", "b": "k of eq. 9 in 1/m",
                                   "c": "one"}  # fmt: skip


def test_builds_refuses_a_value_for_an_argument_the_target_lacks():
    from dipole_torch import Power
    from dipole_torch.training.schemas import builds

    with pytest.raises(ValueError, match=r"dipole_torch.Power has no argument\(s\) \['devise'\]"):
        builds(Power, target_path="dipole_torch.Power", values={"devise": "cpu"})


def test_dash_h_is_the_same_help_as_dash_dash_help(capsys, monkeypatch):
    # -h lists the settings as --help does (not Hydra's own help); in this process.
    import train as script

    for flag in ("-h", "--help"):
        monkeypatch.setattr(sys, "argv", ["train.py", "task=viapoint", flag])
        script.main()
        text = " ".join(capsys.readouterr().out.split())
        assert "algo.optimizer.alpha: float = 1.0 DP concentration α > 0 (paper: 1)" in text
        assert "== task=viapoint: Move an arm's end effector" in text


def test_help_lists_every_field_with_its_help():
    result = subprocess.run(
        [sys.executable, str(ROOT / "train.py"), "--help"],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert result.returncode == 0, result.stderr
    text = " ".join(result.stdout.split())  # help lines are wrapped
    assert "algo.optimizer.alpha: float = 1.0 DP concentration α > 0 (paper: 1)" in text
    assert "task.env.reward_alpha: float = 2.5 α of eq. 9 in 1/m" in text  # not cut at "eq."
    # A clause after ";" is kept (the second choice), a pointer into the code's docs is not.
    assert '"box" (default) uniform in the box' in text and '"start" always N(θ0' in text
    assert "(see " not in text and "; see " not in text
    assert (
        "== task=viapoint: Move an arm's end effector from a start to a target point "
        "through one of several alternative viapoints at each of a few pass times ==" in text
    )
    assert (
        "== algo=dipole_coverage: the algo=dipole settings above, with "
        "accept_unjudged=true, max_sampled=null, unjudged_share=0.5 ==" in text
    )
    assert "trials: int = the value of task.trials" in text
    # The classic-control tasks' device said "where and in which precision ... a floating
    # dtype or its name" (their docstrings' entry for device and dtype together), and
    # task.env.device=float64 was refused: dtype is not a config key.
    assert (
        text.count('task.env.device: any = the value of device where torch rollouts run ("cpu"')
        == 2
    )
    assert "dtype or its name" not in text
    assert "python train.py [task=<task>]" in text
    assert "task.block.trial: int trials before the block" in text  # a section that may be null
    assert "base_viapoint" not in text and "dipole_torch_task" not in text  # no schema offered
    sections = [(schemas.Config, ""), (schemas.TaskConfig, "task."), (schemas.AlgoConfig, "algo.")]
    for table, key, prefix in (
        (schemas.TASKS, "env", "task.env."),
        (schemas.ALGOS, "optimizer", "algo.optimizer."),
    ):
        for schema in table.values():
            sections.append((typing.get_type_hints(schema)[key], prefix))
    assert len(sections) == 3 + 4 + 3
    for schema, prefix in sections:
        for f in dataclasses.fields(schema):
            if f.name in ("task", "algo", "env", "optimizer", "_target_"):
                continue
            assert f"{prefix}{f.name}: " in text, f"{prefix}{f.name}"
            assert f.metadata["help"], f"{prefix}{f.name} has no help in its docstring"
            assert " ".join(f.metadata["help"].split()) in text, f"{prefix}{f.name}"
    for name in [*schemas.TASKS, *schemas.ALGOS]:
        assert f"{'algo' if name in schemas.ALGOS else 'task'}={name}: " in text


@pytest.mark.parametrize(
    "override, message",
    [
        ("trials=-5", "trials (the trial budget) must be a positive integer"),
        ("trials=0", "trials (the trial budget) must be a positive integer"),
        ("device=tpu", "device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got 'tpu'"),
        ("threads=0", "threads must be a positive integer"),
        ("threads=100000", "threads=100000 is more than 4 times this machine's"),
        ("seed=18446744073709551615", "seed must be below 18446744073708551613"),
        ("task.n0=0", "task.n0 (initial samples) must be a positive integer"),
        ("trials=5", "trials=5 is below task.n0=10: the first batch (n0 trials) would exceed"),
        ("figure_every=-1", "figure_every must be a non-negative integer"),
    ],
)
def test_bad_config_values_give_a_clear_error(override, message):
    from dipole_torch.training.checks import check_config

    with pytest.raises(ValueError) as error:
        check_config(compose_config(override))
    assert message in str(error.value)


def test_unknown_algo_and_bad_algo_parameters():
    with pytest.raises(Exception, match="Could not find 'algo/cmaes'"):
        compose_config("algo=cmaes")
    cfg = compose_config("algo.optimizer.alpha=-1")
    with pytest.raises(Exception, match=r"alpha \(DP concentration\) must be positive"):
        instantiate(cfg.algo.optimizer, theta0=torch.zeros(2), sigma_start=torch.eye(2))


def test_a_box_from_the_command_line_holds_every_sample(tmp_path):
    # multimodal's optima lie on a circle of radius 1 around 0; a box [-1, 1] × [-2, 0.5]
    # set on the command line (lists per axis) is passed to the optimizer as plain lists.
    train(
        "task=multimodal",
        "algo=power",
        "trials=60",
        "algo.optimizer.bounds=[[-1,-2],[1,0.5]]",
        f"hydra.run.dir={tmp_path}",
    )
    checkpoint = torch.load(tmp_path / "checkpoint.pt", weights_only=True)
    thetas = checkpoint["optimizer"]["thetas"]
    lower = torch.tensor([-1.0, -2.0], dtype=thetas.dtype)
    upper = torch.tensor([1.0, 0.5], dtype=thetas.dtype)
    assert thetas.shape[0] > 0 and bool(((thetas >= lower) & (thetas <= upper)).all())
    cfg = compose_config("algo.optimizer.bounds=[1,-1]")
    with pytest.raises(Exception, match="bounds must have lower < upper on every axis"):
        instantiate(
            cfg.algo.optimizer, _convert_="all", theta0=torch.zeros(2), sigma_start=torch.eye(2)
        )


class ToyWithFigures(MultimodalTask):
    """The toy task with figures of a policy set as a user's own task might give them."""

    def __init__(self, scalars, line=""):
        super().__init__()
        self.scalars, self.line = scalars, line

    def policy_scalars(self, theta):
        return self.scalars

    def describe_policy_set(self, theta):
        return self.line


def test_the_tasks_figures_of_a_policy_set_are_numbers_or_a_clear_error():
    """Tensors and numpy numbers become floats (results.json is strict JSON); a value that
    is not a finite number, a name that is not a string, a line that is not a str: an
    error naming the task's method and the name, raised by the check a run makes first."""
    theta = torch.zeros(2, 2)
    toy = ToyWithFigures({"optima": torch.tensor(3), "spread": np.float32(0.5)}, "two hills")
    assert run_results.task_scalars(toy, theta) == {"optima": 3.0, "spread": 0.5}
    assert run_results.policy_set_line(toy, theta) == "two hills"
    run_results.check_task_hooks(toy)
    for scalars, error, message in [
        ({"optima": "four"}, TypeError, "ToyWithFigures.policy_scalars: 'optima' must be a number"),
        ({"optima": "4"}, TypeError, "'optima' must be a number, got '4'"),
        ({"optima": torch.ones(2)}, TypeError, "'optima' must be a number, got tensor"),
        ({"optima": math.nan}, ValueError, "'optima' must be finite, got nan"),
        ({3: 1.0}, TypeError, "a name must be a non-empty string, got 3"),
        ({"": 1.0}, TypeError, "a name must be a non-empty string, got ''"),
        ([1.0], TypeError, "must return a dict of names to numbers, got [1.0]"),
    ]:
        with pytest.raises(error) as raised:
            run_results.check_task_hooks(ToyWithFigures(scalars))
        assert message in str(raised.value)
    message = "ToyWithFigures.describe_policy_set must return a str, got 3"
    with pytest.raises(TypeError, match=message):
        run_results.check_task_hooks(ToyWithFigures({}, line=3))


def test_the_policy_set_summary_and_results_json(tmp_path):
    """The task's scalars are kept without a line (and the line without scalars); a task
    with neither adds nothing. results.json is strict JSON: a NaN is refused, not written."""
    from dipole_torch import Power

    opt = Power(torch.zeros(2), 1.0)
    summary = run_results.policy_set_summary(ToyWithFigures({"optima": 3}), opt)
    assert summary == {"policy_set": {"scalars": {"optima": 3.0}, "description": ""}}
    summary = run_results.policy_set_summary(ToyWithFigures({}, "two hills"), opt)
    assert summary == {"policy_set": {"scalars": {}, "description": "two hills"}}
    assert run_results.policy_set_summary(ToyWithFigures({}), opt) == {}
    run_results.write_results(tmp_path, {"best_reward": 1.0}, opt)
    assert json.loads((tmp_path / "results.json").read_text()) == {"best_reward": 1.0}
    with pytest.raises(ValueError, match="not JSON compliant"):
        run_results.write_results(tmp_path, {"best_reward": math.nan}, opt)


def train_custom(directory, configs: str, *overrides: str, check: bool = True):
    """``train`` in ``directory`` with the config directory ``configs`` (there) on Hydra's
    search path: a task of the test's own."""
    return train(f"hydra.searchpath=[file://{configs}]", *overrides, cwd=directory, check=check)


def test_a_task_whose_figures_cannot_be_logged_stops_the_run_at_its_start(tmp_path, monkeypatch):
    (tmp_path / "bad_task.py").write_text(
        "from dipole_torch.tasks.multimodal import MultimodalTask\n\n\n"
        "class Bad(MultimodalTask):\n"
        "    def policy_scalars(self, theta):\n"
        "        return {'optima': 'several'}\n"
    )
    (tmp_path / "bad_configs" / "task").mkdir(parents=True)
    (tmp_path / "bad_configs" / "task" / "bad.yaml").write_text(
        "defaults:\n  - /dipole_torch_task@_here_\n  - _self_\n"
        "name: bad\ntrials: 20\nn0: 10\nenv:\n  _target_: bad_task.Bad\n"
    )
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    run = tmp_path / "run"
    result = train_custom(tmp_path, "bad_configs", "task=bad", f"hydra.run.dir={run}", check=False)
    assert result.returncode == 2, result.stderr
    assert (
        "error: task.env: Bad.policy_scalars: 'optima' must be a number, got 'several'"
        in result.stderr
    )
    assert not (run / "checkpoint.pt").exists()  # before the first trial


def test_a_task_returning_numpy_runs_as_it_does_with_tensors_and_a_wrong_shape_stops_it(
    tmp_path, monkeypatch
):
    """A custom task wrapping a numpy simulator returns numpy: the run trained its whole
    budget (``tell`` takes numpy), then ended in ``torch.stack``'s TypeError with no
    results.json. A return of another shape stops the run at its first batch, naming it."""
    (tmp_path / "odd_tasks.py").write_text(
        "from dipole_torch.tasks.multimodal import MultimodalTask\n\n\n"
        "class NumpyReturns(MultimodalTask):\n"
        "    def evaluate(self, theta, generator=None):\n"
        "        return super().evaluate(theta, generator).numpy()\n\n\n"
        "class Column(MultimodalTask):\n"
        "    def evaluate(self, theta, generator=None):\n"
        "        return super().evaluate(theta, generator)[:, None]\n"
    )
    (tmp_path / "odd_configs" / "task").mkdir(parents=True)
    for name, target in (("numpy_returns", "NumpyReturns"), ("column", "Column")):
        (tmp_path / "odd_configs" / "task" / f"{name}.yaml").write_text(
            "defaults:\n  - multimodal\n  - _self_\n"
            f"name: {name}\nenv:\n  _target_: odd_tasks.{target}\n"
        )
    monkeypatch.setenv("PYTHONPATH", str(tmp_path))
    results = {}
    for task in ("numpy_returns", "multimodal"):
        train_custom(
            tmp_path, "odd_configs", f"task={task}", "trials=60", f"hydra.run.dir={tmp_path / task}"
        )
        results[task] = json.loads((tmp_path / task / "results.json").read_text())
    for key in ("trials", "best_reward", "best_theta", "policies", "history"):
        assert results["numpy_returns"][key] == results["multimodal"][key], key
    run = tmp_path / "column"
    result = train_custom(
        tmp_path, "odd_configs", "task=column", f"hydra.run.dir={run}", check=False
    )
    assert result.returncode == 2, result.stderr
    assert (
        "error: task.env: Column.evaluate's returns must have shape [10] (one per row of θ), "
        "got [10, 1]"
    ) in result.stderr
    assert not (run / "checkpoint.pt").exists()  # at the first batch


@pytest.mark.parametrize("evaluations", [1, 3])
def test_two_runs_of_a_noisy_task_write_the_same_results(tmp_path, evaluations):
    # The policies' returns in results.json were drawn from the global RNG on a noisy task:
    # two runs of one command differed there, and only there.
    common = [
        "task=multimodal",
        "task.env.noise_std=0.2",
        "trials=40",
        "seed=3",
        "figure_every=0",
        f"algo.optimizer.best_evaluations={evaluations}",
    ]
    results = []
    for name in ("a", "b"):
        train(*common, f"hydra.run.dir={tmp_path / name}")
        run = json.loads((tmp_path / name / "results.json").read_text())
        run.pop("wall_time_s")
        results.append(run)
    assert results[0] == results[1]

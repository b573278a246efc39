"""Reliability and security (issue 10): a transactional tell, validated inputs, a global-seed
default, atomic outputs, safe checkpoint loading, resume checks, runs that survive SIGKILL,
SIGTERM and SIGINT.

The SIGKILL / SIGTERM / SIGINT tests share one driver subprocess (this file run as a
script): it imports train.py once, then forks a child per session of ``train.main()``, so a
session starts in ~0.1 s instead of the ~5 s of a fresh interpreter, and kills the children.
"""

from __future__ import annotations

import json
import math
import os
import random
import shlex
import shutil
import signal
import subprocess
import sys
import time
import traceback
from pathlib import Path

import pytest
import torch
from filelock import FileLock

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT))

from dipole_torch import Dipole, Power  # noqa: E402
from dipole_torch.checkpoint import (  # noqa: E402
    CheckpointError,
    atomic_save,
    atomic_write_text,
    load_checkpoint,
)
from dipole_torch.training.resume import config_differences  # noqa: E402

F64 = torch.float64


# ------------------------------------------------------------------ helpers
def assert_same(a, b, path="state"):
    """Deep equality of nested dicts / lists / tensors / numbers (NaN equals NaN)."""
    if isinstance(a, torch.Tensor):
        assert isinstance(b, torch.Tensor), path
        assert a.dtype == b.dtype and a.shape == b.shape, path
        assert (
            torch.equal(a, b)
            or torch.equal(a.isnan(), b.isnan())
            and torch.equal(a.nan_to_num(), b.nan_to_num())
        ), path
    elif isinstance(a, dict):
        assert isinstance(b, dict) and a.keys() == b.keys(), path
        for key in a:
            assert_same(a[key], b[key], f"{path}.{key}")
    elif isinstance(a, list | tuple):
        assert type(a) is type(b) and len(a) == len(b), path
        for i, (x, y) in enumerate(zip(a, b, strict=True)):
            assert_same(x, y, f"{path}[{i}]")
    elif isinstance(a, float) and math.isnan(a):
        assert isinstance(b, float) and math.isnan(b), path
    else:
        assert a == b, f"{path}: {a!r} != {b!r}"


def bumps(theta):
    """Two bumps of height 1 at ±(1, 1): returns in (0, 1]."""
    theta = theta.double()
    d = torch.minimum((theta - 1).pow(2).sum(-1), (theta + 1).pow(2).sum(-1))
    return torch.exp(-d / 0.5)


BUILDERS = {
    "dipole": lambda g, **kw: Dipole(torch.zeros(2), 0.5 * torch.eye(2), generator=g, **kw),
    "dipole_paper": lambda g, **kw: Dipole.paper(
        torch.zeros(2), 0.5 * torch.eye(2), generator=g, **kw
    ),
    "power": lambda g, **kw: Power(torch.zeros(2), 0.5 * torch.eye(2), generator=g, **kw),
}


def advance(opt, iterations):
    for _ in range(iterations):
        theta = opt.ask()
        opt.tell(theta, bumps(theta))
    return opt


# ------------------------------------------------------------------ 4: a transactional tell
def rejected_inputs(opt, theta):
    """(description, theta, rewards) that tell() must refuse."""
    b = theta.shape[0]
    good = bumps(theta)
    cases = [
        ("theta of the wrong batch size", theta[:-1] if b > 1 else theta.repeat(2, 1), good),
        ("theta of the wrong dimension", theta[:, :1], good),
        ("theta with NaN", theta.clone().index_fill_(0, torch.tensor([0]), math.nan), good),
        ("theta with inf", theta.clone().index_fill_(0, torch.tensor([0]), math.inf), good),
        ("rewards of the wrong shape", theta, good[:-1] if b > 1 else good.repeat(2)),
        ("rewards [B, 1]", theta, good[:, None]),
        ("rewards with NaN", theta, good.clone().index_fill_(0, torch.tensor([0]), math.nan)),
        ("rewards with +inf", theta, good.clone().index_fill_(0, torch.tensor([0]), math.inf)),
        ("rewards with -inf", theta, good.clone().index_fill_(0, torch.tensor([0]), -math.inf)),
        ("boolean rewards", theta, good > 0.5),
        ("complex rewards", theta, good.to(torch.complex128)),
    ]
    scale = opt.reward_scale
    if getattr(scale, "positive", False):
        cases.append(("non-positive rewards", theta, good - 2.0))
    elif scale.low is not None:
        cases.append(("rewards above reward_range", theta, good + 10.0))
        cases.append(("rewards below reward_range", theta, good - 10.0))
    return cases


def fail_with(error):
    def fail(*args, **kwargs):
        raise error

    return fail


# Failures inside tell(), after the samples were stored (the case 4): (what, target,
# error). A target is a module function or an optimizer method; each raises when called.
FAILURES = [
    ("clustering", "dipole_torch.dp.sampler.DPSampler.fit", RuntimeError("clustering failed")),
    ("PoWER step", "dipole_torch.power.power_update", RuntimeError("PoWER step failed")),
    ("end of tell", "_iterate", RuntimeError("bookkeeping failed")),
    ("Ctrl-C at the end of tell", "_iterate", KeyboardInterrupt()),
    ("first clustering", "_after_initial_batch", RuntimeError("first clustering failed")),
]


@pytest.mark.parametrize(
    "name, reward_range",
    [
        ("dipole", None),
        ("dipole", (0.0, 1.0)),
        ("dipole_paper", "positive"),
        ("power", None),
        ("power", (0.0, 1.0)),
        ("power", "positive"),
    ],
)
def test_tell_is_transactional_over_every_rejected_input(name, reward_range, monkeypatch):
    """After any exception in tell(), state_dict() is as before the call, and the run goes
    on exactly as a twin that never saw the bad input."""
    build = BUILDERS[name]
    opt = build(torch.Generator().manual_seed(1), reward_range=reward_range)
    twin = build(torch.Generator().manual_seed(1), reward_range=reward_range)
    raised = {what: 0 for what, *_ in FAILURES}
    for iteration in range(7):  # the first tell (a clustering) and the clustering at 5
        theta, twin_theta = opt.ask(), twin.ask()
        assert torch.equal(theta, twin_theta)
        for what, bad_theta, bad_rewards in rejected_inputs(opt, theta):
            before = opt.state_dict()
            with pytest.raises((ValueError, TypeError)):
                opt.tell(bad_theta, bad_rewards)
            assert_same(opt.state_dict(), before, f"{what} at iteration {iteration}")
        for what, target, error in FAILURES:
            # On a copy: a failure that is not reached lets its tell() succeed.
            probe = build(torch.Generator(), reward_range=reward_range)
            probe.load_state_dict(opt.state_dict())
            before = probe.state_dict()
            with monkeypatch.context() as patch:
                if "." in target:
                    patch.setattr(target, fail_with(error))
                else:
                    patch.setattr(probe, target, fail_with(error))
                try:
                    probe.tell(theta, bumps(theta))
                except type(error):
                    raised[what] += 1
                    assert_same(probe.state_dict(), before, f"{what} at iteration {iteration}")
        opt.tell(theta, bumps(theta))
        twin.tell(twin_theta, bumps(twin_theta))
        assert_same(opt.state_dict(), twin.state_dict(), f"after iteration {iteration}")
    advance(opt, 4)
    advance(twin, 4)
    assert_same(opt.state_dict(), twin.state_dict(), "4 iterations later")
    # Every injected failure was met at least once (the clustering only by DIPOLE).
    expected = {what for what, *_ in FAILURES} - ({"clustering"} if name == "power" else set())
    assert {what for what, count in raised.items() if count} >= expected, raised


@pytest.mark.parametrize("name", list(BUILDERS))
def test_a_tell_that_raises_after_all_its_changes_is_undone(name, monkeypatch):
    """A failure at the very end of tell(), after every step of the iteration ran (its
    snapshot holds the optimizer's tensors uncopied: no step may write into one)."""
    opt = BUILDERS[name](torch.Generator().manual_seed(2), bounds=(-3.0, 3.0))
    for iteration in range(40):
        theta = opt.ask()
        probe = BUILDERS[name](torch.Generator(), bounds=(-3.0, 3.0))
        probe.load_state_dict(opt.state_dict())
        before = probe.state_dict()
        tell = probe._tell

        def tell_then_fail(*args, tell=tell):
            tell(*args)
            raise RuntimeError("failed after the iteration")

        monkeypatch.setattr(probe, "_tell", tell_then_fail)
        with pytest.raises(RuntimeError, match="after the iteration"):
            probe.tell(theta, bumps(theta))
        assert_same(probe.state_dict(), before, f"iteration {iteration}")
        opt.tell(theta, bumps(theta))


def test_tell_without_ask_changes_nothing():
    opt = advance(BUILDERS["dipole"](torch.Generator().manual_seed(0)), 2)
    theta = opt.ask()
    opt.tell(theta, bumps(theta))
    before = opt.state_dict()
    with pytest.raises(RuntimeError, match="without a pending ask"):
        opt.tell(theta, bumps(theta))  # the same batch told twice
    assert_same(opt.state_dict(), before)


@pytest.mark.parametrize("name", list(BUILDERS))
@pytest.mark.parametrize("low, high", [(-math.inf, 1.0), (0.0, math.inf), (math.nan, 1.0)])
def test_a_non_finite_reward_range_is_refused_at_construction(name, low, high):
    # Issue case 4: reward_range=(-inf, 1) was accepted and made the clustering raise later.
    with pytest.raises(ValueError, match="reward_range must be finite"):
        BUILDERS[name](None, reward_range=(low, high))


@pytest.mark.parametrize("name", ["dipole", "dipole_paper"])
def test_huge_offsets_with_tiny_exploration_learn_without_raising(name):
    # Issue case 4: θ0 = 1e6·1 with Σ_start = 1e-4·I raised inside the clustering.
    theta0 = torch.full((3,), 1e6, dtype=F64)
    target = theta0 + 0.01
    build = Dipole if name == "dipole" else Dipole.paper
    opt = build(theta0, 1e-4 * torch.eye(3, dtype=F64), generator=torch.Generator().manual_seed(0))
    first = None
    while opt.trials < 100:
        theta = opt.ask()
        rewards = torch.exp(-(theta - target).pow(2).sum(-1) / 1e-3)
        before = opt.state_dict()
        try:
            opt.tell(theta, rewards)
        except Exception:
            assert_same(opt.state_dict(), before)
            raise
        first = opt.best()[1] if first is None else first
    assert opt.best()[1] > first


# ------------------------------------------------------------------ 5, 6: inputs refused
@pytest.mark.parametrize("build", [Dipole, Power])
@pytest.mark.parametrize(
    "theta0, sigma_start, message",
    [
        # Integer and bool θ0 are refused, not converted (an integer θ0 gave truncated
        # asks, a bool one asked all True).
        (torch.zeros(2, dtype=torch.long), torch.eye(2), "theta0 must be a floating-point"),
        (torch.zeros(2, dtype=torch.int32), torch.eye(2), "theta0 must be a floating-point"),
        (torch.zeros(2, dtype=torch.bool), torch.eye(2), "theta0 must be a floating-point"),
        (["0.0", "0.0"], torch.eye(2), r"theta0 as a list must be \[D\] real numbers.*'0.0'"),
        # A nested list was called "not a floating-point torch.Tensor, got list".
        ([[0.0, 0.0]], torch.eye(2), r"theta0 as a list must be \[D\] real numbers.*\[0.0, 0.0\]"),
        (torch.zeros(2), torch.eye(2, dtype=torch.long), "sigma_start must be a floating-point"),
        # A number was called "not a floating-point torch.Tensor, got float".
        (
            0.0,
            1.0,
            r"theta0 must be \[D\] parameters .*got 0.0 \(float\) \(one parameter: \[0.0\]\)",
        ),
        (None, 1.0, r"theta0 must be \[D\] parameters .*got None \(NoneType\)"),
        (torch.tensor(0.0), 1.0, r"theta0 must have shape \[D\] \(D parameters\), got \[\]"),
        (torch.zeros(0), torch.eye(0), "theta0 must have at least one parameter"),
        (torch.zeros(2), torch.eye(2) * math.inf, "sigma_start contains non-finite"),
    ],
)
def test_bad_theta0_and_sigma_start_are_refused_naming_the_argument(
    build, theta0, sigma_start, message
):
    with pytest.raises((TypeError, ValueError), match=message):
        build(theta0, sigma_start)


@pytest.mark.parametrize("alpha", [math.inf, -math.inf, math.nan, 0.0, -1.0])
def test_alpha_must_be_positive_and_finite(alpha):
    # alpha = inf gave 181 policies in 12 iterations.
    with pytest.raises(ValueError, match=r"alpha \(DP concentration\) must be positive"):
        Dipole(torch.zeros(2), torch.eye(2), alpha=alpha)


# ------------------------------------------------------------------ 7: the global seed
@pytest.mark.parametrize("name", list(BUILDERS))
def test_an_optimizer_without_generator_follows_torch_manual_seed(name):
    def first_asks(seed):
        torch.manual_seed(seed)
        return BUILDERS[name](None).ask()

    a, b, again = first_asks(1), first_asks(2), first_asks(1)
    assert not torch.equal(a, b)  # the default generator's fixed seed made them equal
    assert torch.equal(a, again)


# ------------------------------------------------------------------ atomic writes
def test_a_failed_write_leaves_the_previous_file_and_no_temporary(tmp_path, monkeypatch):
    target = tmp_path / "checkpoint.pt"
    atomic_save({"x": torch.arange(3)}, target)
    real_save = torch.save

    def crash_midway(obj, handle, *args, **kwargs):
        real_save({"x": torch.arange(1000)}, handle)  # half of a new file, then a crash
        handle.truncate(50)
        raise OSError(28, "No space left on device")

    monkeypatch.setattr(torch, "save", crash_midway)
    with pytest.raises(OSError, match="No space left"):
        atomic_save({"x": torch.arange(5)}, target)
    monkeypatch.undo()
    assert torch.equal(load_checkpoint(target)["x"], torch.arange(3))
    assert sorted(p.name for p in tmp_path.iterdir()) == ["checkpoint.pt"]
    atomic_write_text(tmp_path / "results.json", '{"a": 1}')
    assert json.loads((tmp_path / "results.json").read_text()) == {"a": 1}
    assert (tmp_path / "results.json").stat().st_mode & 0o777 == 0o666 & ~_umask()


def _umask():
    mask = os.umask(0)
    os.umask(mask)
    return mask


def test_train_writes_every_output_through_os_replace(tmp_path, monkeypatch):
    """checkpoint.pt, results.json and policies.pt are each moved into place by os.replace
    from a temporary in the same directory (never written in place)."""
    replaced = []
    real_replace = os.replace

    def spy(src, dst):
        replaced.append((Path(src), Path(dst)))
        assert Path(src).parent == Path(dst).parent and Path(src).name.endswith(".tmp")
        real_replace(src, dst)

    monkeypatch.setattr(os, "replace", spy)
    run_dir = tmp_path / "run"
    run_train(f"hydra.run.dir={run_dir}", "trials=30", "checkpoint_every=1")
    names = {dst.name for _, dst in replaced}
    assert names == {"checkpoint.pt", "results.json", "policies.pt"}
    assert sum(dst.name == "checkpoint.pt" for _, dst in replaced) >= 3  # one per iteration
    assert not list(run_dir.glob(".*.tmp"))


# ------------------------------------------------------------------ 1, 6: safe loading
def test_a_checkpoint_holds_only_weights_only_loadable_data(finished_run):
    checkpoint = torch.load(finished_run / "checkpoint.pt", weights_only=True)
    assert isinstance(checkpoint["config"], str) and "multimodal" in checkpoint["config"]
    assert 30 < checkpoint["optimizer"]["trials"] <= 40  # the budget: never exceeded


def test_a_malicious_checkpoint_is_refused_and_runs_nothing(tmp_path):
    marker = tmp_path / "pwned"

    class Payload:
        def __reduce__(self):
            return (os.system, (f"touch {shlex.quote(str(marker))}",))

    evil = tmp_path / "checkpoint.pt"
    torch.save({"optimizer": Payload(), "task_generator": 0, "history": [], "config": ""}, evil)
    with pytest.raises(CheckpointError, match="refusing to load .* could run code"):
        run_train(f"resume={evil}", f"hydra.run.dir={tmp_path / 'out'}")
    assert not marker.exists()


def test_every_truncation_of_a_checkpoint_gives_a_clear_error(finished_run, tmp_path):
    data = (finished_run / "checkpoint.pt").read_bytes()
    broken = tmp_path / "checkpoint.pt"
    for size in [0, 1, *range(7, len(data), max(1, len(data) // 150)), len(data) - 1]:
        broken.write_bytes(data[:size])
        with pytest.raises(CheckpointError, match=r"is empty|truncated or corrupt") as error:
            load_checkpoint(broken, kind="train.py checkpoint")
        assert str(broken) in str(error.value)


@pytest.mark.parametrize(
    "what, message",
    [
        ("truncated", r"\(1000 bytes\) is truncated or corrupt"),
        ("empty", r"is empty \(0 bytes\)"),
        ("policies", r"policies.pt' is not a train.py checkpoint: it lacks \['optimizer'"),
        ("directory", r"is a directory; give the file"),
        ("missing", r"does not exist"),
    ],
)
def test_resume_from_a_bad_file_names_it_and_says_what_is_wrong(
    finished_run, tmp_path, what, message
):
    bad = {
        "truncated": tmp_path / "checkpoint.pt",
        "empty": tmp_path / "checkpoint.pt",
        "policies": finished_run / "policies.pt",
        "directory": finished_run,
        "missing": tmp_path / "nothing.pt",
    }[what]
    if what == "truncated":
        bad.write_bytes((finished_run / "checkpoint.pt").read_bytes()[:1000])
    if what == "empty":
        bad.write_bytes(b"")
    with pytest.raises(CheckpointError, match=message):
        run_train(f"resume={bad}", f"hydra.run.dir={tmp_path / 'out'}")


# ------------------------------------------------------------------ 3: resume checks
@pytest.mark.parametrize(
    "overrides, keys",
    [
        (["task=cartpole"], ["task.name"]),
        (["task.env.dim=3"], ["task.env.dim"]),
        (["algo=power"], ["algo.name"]),
        (["algo.optimizer.alpha=2.0", "algo.optimizer.M=4"], ["algo.optimizer.M", "alpha"]),
        (["algo.use_task_reward_range=true"], ["algo.use_task_reward_range"]),
    ],
)
def test_resume_refuses_a_different_config_naming_the_keys(finished_run, overrides, keys):
    with pytest.raises(CheckpointError, match="must match") as error:
        run_train(f"resume={finished_run / 'checkpoint.pt'}", "trials=60", *overrides)
    for key in keys:
        assert key in str(error.value)
    assert "The checkpoint's run resumes with: python" in str(error.value)


def test_the_resume_command_of_another_task_names_the_task_not_its_keys(finished_run):
    # The checkpoint's task (multimodal) against task=cartpole: every task.* key differs, and
    # task=multimodal in the command brings them all back; the command lists none of them.
    with pytest.raises(CheckpointError, match="must match") as error:
        run_train(f"resume={finished_run / 'checkpoint.pt'}", "trials=60", "task=cartpole")
    command = str(error.value).split("The checkpoint's run resumes with: ")[1]
    assert "task=multimodal" in command and "task." not in command, command


def test_resume_refuses_a_budget_below_the_checkpoints_trials(finished_run, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(finished_run, copy)
    held = load_checkpoint(copy / "checkpoint.pt")["optimizer"]["trials"]
    results = (copy / "results.json").read_bytes()
    with pytest.raises(CheckpointError, match=f"trials={held - 1}: its run holds {held} trials"):
        run_train(f"resume={copy / 'checkpoint.pt'}", f"trials={held - 1}")
    assert (copy / "results.json").read_bytes() == results  # nothing written
    # At the checkpoint's own trials nothing runs and the results are its (a session killed
    # after its last checkpoint and before its results resumes so).
    run_train(f"resume={copy / 'checkpoint.pt'}", f"trials={held}")
    assert json.loads((copy / "results.json").read_text())["trials"] == held


def test_resuming_a_finished_run_logs_its_final_policies_once(finished_run, tmp_path):
    # The run ended at its budget with its last batch whole: its final figure and task/optima
    # are drawn at that step. A resume at that budget runs nothing and must not draw them
    # again at the same step (TensorBoard showed two points there).
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    copy = tmp_path / "run"
    shutil.copytree(finished_run, copy)
    held = load_checkpoint(copy / "checkpoint.pt")["optimizer"]["trials"]
    assert held == 40  # (a whole last batch: a cut one would be run again, and purged)
    run_train(f"resume={copy / 'checkpoint.pt'}", f"trials={held}")
    events = EventAccumulator(str(copy / "tensorboard"))
    events.Reload()
    for tag in events.Tags()["scalars"]:
        steps = [e.step for e in events.Scalars(tag)]
        assert len(steps) == len(set(steps)), (tag, steps)
    assert [e.step for e in events.Scalars("task/optima")] == [held]


@pytest.mark.parametrize(
    "edit, message",
    [
        (lambda c: c.update(dimension=3), r"the checkpoint's task has \{'dimension': 3"),
        (lambda c: c.update(reward_range=(0.0, 2.0)), r"'reward_range': \(0.0, 2.0\)"),
        (lambda c: c["optimizer"].update(kind="Power"), "does not fit this optimizer"),
        (
            lambda c: c["optimizer"].pop("thetas"),
            r"does not fit this optimizer \(ValueError: state_dict has no 'thetas'",
        ),
    ],
)
def test_resume_refuses_a_checkpoint_whose_contents_do_not_fit(
    finished_run, tmp_path, edit, message
):
    checkpoint = load_checkpoint(finished_run / "checkpoint.pt")
    edit(checkpoint)
    atomic_save(checkpoint, tmp_path / "checkpoint.pt")
    with pytest.raises(CheckpointError, match=message):
        run_train(f"resume={tmp_path / 'checkpoint.pt'}", "trials=60")


def test_resume_keeps_the_seed_and_the_directory_of_the_checkpoint(finished_run, tmp_path):
    copy = tmp_path / "seed3_run"
    copy.mkdir()
    fresh_dir = tmp_path / "straight"
    run_train("seed=3", f"hydra.run.dir={copy}", "trials=40")
    run_train("seed=3", f"hydra.run.dir={fresh_dir}", "trials=70")
    # An explicit seed that differs from the checkpoint's is refused, naming both.
    with pytest.raises(CheckpointError, match="with seed=5: the checkpoint's run has seed=3"):
        run_train(f"resume={copy / 'checkpoint.pt'}", "seed=5", "trials=70")
    # Without seed=, the checkpoint's seed is used and the run continues in its directory.
    run_train(f"resume={copy / 'checkpoint.pt'}", "trials=70")
    resumed = json.loads((copy / "results.json").read_text())
    straight = json.loads((fresh_dir / "results.json").read_text())
    assert resumed["seed"] == 3 and 60 < resumed["trials"] == straight["trials"] <= 70
    assert resumed["history"] == straight["history"]
    # Hydra's record of the first session is kept; the resumed ones go to .hydra/resume_*.
    assert "trials: 40" in (copy / ".hydra" / "config.yaml").read_text()
    assert list((copy / ".hydra").glob("resume_*/config.yaml"))


def test_a_new_run_does_not_overwrite_a_runs_checkpoint(finished_run):
    before = (finished_run / "checkpoint.pt").read_bytes()
    with pytest.raises(CheckpointError, match="already holds a run's checkpoint.pt"):
        run_train(f"hydra.run.dir={finished_run}", "trials=40")
    assert (finished_run / "checkpoint.pt").read_bytes() == before


def test_a_cut_last_batch_is_not_checkpointed_even_at_the_checkpoint_cadence(
    finished_run, tmp_path
):
    # The budget cuts the first batch of several rows after its first row; with a
    # checkpoint at every iteration the cut iteration's turn must still not write one (a
    # checkpoint of the cut run would resume into other draws than an uninterrupted run's).
    ends = json.loads((finished_run / "results.json").read_text())["history"]["trials"]
    before = next(a for a, b in zip(ends, ends[1:], strict=False) if b - a >= 2)
    run_train(f"hydra.run.dir={tmp_path}", f"trials={before + 1}", "checkpoint_every=1")
    assert json.loads((tmp_path / "results.json").read_text())["trials"] == before + 1
    checkpoint = load_checkpoint(tmp_path / "checkpoint.pt")
    assert checkpoint["optimizer"]["trials"] == before
    assert checkpoint["optimizer"]["pending"] is None


def test_a_stopped_run_writes_its_checkpoint_draws_no_final_figure_and_exits_143(
    tmp_path, monkeypatch
):
    # SIGTERM during the third iteration: the loop finishes it, writes the checkpoint there,
    # says so, and exits with 128 + 15; the final figure is the finished run's alone (none
    # is drawn at a stop, figure_every=0 draws none before).
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    from dipole_torch.training import board

    log_iteration, logged = board.Board.log_iteration, []

    def stop_in_the_third(self, optimizer):
        logged.append(optimizer.trials)
        if len(logged) == 3:
            os.kill(os.getpid(), signal.SIGTERM)
        return log_iteration(self, optimizer)

    monkeypatch.setattr(board.Board, "log_iteration", stop_in_the_third)
    with pytest.raises(SystemExit) as stopped:
        run_train(f"hydra.run.dir={tmp_path}", "trials=40")
    assert stopped.value.code == 128 + signal.SIGTERM and len(logged) == 3
    checkpoint = load_checkpoint(tmp_path / "checkpoint.pt")
    assert checkpoint["optimizer"]["trials"] == logged[-1] < 40
    assert checkpoint["figure_trials"] is None
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()
    assert "task/optima" not in events.Tags()["scalars"] and not events.Tags()["images"]
    said = (tmp_path / "train.log").read_text()
    assert f"stopped by SIGTERM at {logged[-1]} of 40 trials; checkpoint at {logged[-1]}" in said
    assert not (tmp_path / "results.json").exists()


def test_a_resumed_runs_wall_time_counts_its_earlier_sessions(finished_run, tmp_path):
    copy = tmp_path / "run"
    shutil.copytree(finished_run, copy)
    checkpoint = load_checkpoint(copy / "checkpoint.pt")
    checkpoint["wall_time_s"] = 1e6  # the earlier sessions' time, as the checkpoint says it
    atomic_save(checkpoint, copy / "checkpoint.pt")
    run_train(f"resume={copy / 'checkpoint.pt'}", "trials=40")
    assert json.loads((copy / "results.json").read_text())["wall_time_s"] >= 1e6
    said = f"resumed {copy / 'checkpoint.pt'} at 40 trials (seed 0)"
    assert said in (copy / "train.log").read_text()
    assert load_checkpoint(copy / "checkpoint.pt")["wall_time_s"] >= 1e6


def test_a_policy_figure_comes_every_figure_every_iterations_and_at_the_end(tmp_path):
    # The cadence counts iterations (batches), not trials: with figure_every=3, the policy
    # figure and the task's scalars after the 3rd, 6th and 9th batches, and at the budget.
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    run_train(f"hydra.run.dir={tmp_path}", "trials=40", "figure_every=3")
    ends = json.loads((tmp_path / "results.json").read_text())["history"]["trials"]
    assert len(ends) % 3 != 0  # (so that the final figure is not also a cadence one)
    events = EventAccumulator(str(tmp_path / "tensorboard"))
    events.Reload()  # (this task draws no image: its figure's scalars mark each figure)
    assert [event.step for event in events.Scalars("task/optima")] == [*ends[2::3], 40]


def test_config_differences_lists_dotted_keys():
    saved = {"task": {"name": "a", "env": {"dim": 2}}, "trials": 5, "hydra": {"x": 1}}
    current = {"task": {"name": "b", "env": {"dim": 2, "new": 1}}, "trials": 9, "hydra": {}}
    assert config_differences(saved, current, ignore=("trials", "hydra")) == [
        ("task.env.new", "<missing>", 1),
        ("task.name", "a", "b"),
    ]
    # An ignored key covers its own subtree, not keys that merely begin with its name.
    assert config_differences({"trials": 1, "trialsx": 1}, {"trials": 2, "trialsx": 2},
                              ignore=("trials",)) == [("trialsx", 1, 2)]  # fmt: skip


@pytest.mark.parametrize(
    "override, message",
    [
        ("device=cudafoo", "device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got 'cudafoo'"),
        ("device=cuda:x", "device must be 'cpu', 'cuda', 'cuda:N' or 'mps'"),
        ("checkpoint_every=0", "checkpoint_every must be a positive integer, got 0"),
        ("seed=-1", "seed must be a non-negative integer"),
        ("resume=''", "resume must be the path of a checkpoint.pt"),
        # The task's own device, set apart from the run's: checked as the run's is (a meta
        # tensor failed deep in the task with a traceback, CUDA without CUDA with Hydra's).
        ("task.env.device=meta", "task.env.device must be 'cpu', 'cuda', 'cuda:N' or 'mps'"),
        ("task.env.device=cuda:x", "task.env.device must be 'cpu', 'cuda', 'cuda:N' or 'mps'"),
    ],
)
def test_more_bad_config_values(override, message):
    from hydra import compose, initialize_config_dir

    from dipole_torch.training.checks import check_config
    from dipole_torch.training.config import register
    from dipole_torch.training.hydra_compat import VERSION_BASE

    register()  # the schemas the configs extend (train.py registers them; run alone, this)
    with initialize_config_dir(str(ROOT / "configs"), **VERSION_BASE):
        cfg = compose("config", overrides=[override])
    with pytest.raises(ValueError) as error:
        check_config(cfg)
    assert message in str(error.value)


def composed(*overrides):
    """``configs/config.yaml`` composed with ``overrides``, as train.py composes it."""
    from hydra import compose, initialize_config_dir

    from dipole_torch.training.config import register
    from dipole_torch.training.hydra_compat import VERSION_BASE

    register()
    with initialize_config_dir(str(ROOT / "configs"), **VERSION_BASE):
        return compose("config", overrides=list(overrides))


def test_values_at_their_limits_are_accepted_and_one_past_them_refused():
    from dipole_torch.training.checks import SEED_LIMIT, check_config

    cores = os.cpu_count() or 1
    limits = [  # (override, one past it, what the refusal says)
        (f"seed={SEED_LIMIT - 1}", f"seed={SEED_LIMIT}", f"seed must be below {SEED_LIMIT}"),
        (f"threads={4 * cores}", f"threads={4 * cores + 1}", "more than 4 times"),
        ("trials=10", "trials=9", "trials=9 is below task.n0=10"),  # n0 = 10 trials at least
    ]
    for at, past, message in limits:
        check_config(composed(at))
        with pytest.raises(ValueError, match=message):
            check_config(composed(past))
    # The world may change right after the first batch (task.n0 = 30 trials).
    check_config(composed("task=viapoint_blocked", "task.block.trial=30"))
    with pytest.raises(ValueError, match="task.block.trial=29 is below task.n0=30"):
        check_config(composed("task=viapoint_blocked", "task.block.trial=29"))
    # A resumed run's budget is not held to n0: its first batch was told long ago.
    check_config(composed("resume=/a/run/checkpoint.pt", "trials=9"))


def test_a_misspelt_name_gets_a_guess_only_where_one_is_close():
    from dipole_torch.training.checks import check_config

    said = {}
    for override in ("+thread_count=2", "+algo.optimizer.alpah=2", "+optimizer=power", "+alpha=2"):
        with pytest.raises(ValueError) as refused:
            check_config(composed("task=mountain_car", override))
        said[override] = str(refused.value)
    assert "(a misspelling? python train.py --help" in said["+thread_count=2"]
    assert "did you mean" not in said["+thread_count=2"]
    # The word on choosing a task or an optimizer only where the guess is a section of one.
    assert "(did you mean algo.optimizer.alpha? python train.py" in said["+algo.optimizer.alpah=2"]
    assert "did you mean algo.optimizer? task=<name> and algo=<name>" in said["+optimizer=power"]
    # Of the keys that end with it (task.env.alpha, algo.optimizer.alpha), the shortest.
    assert "(did you mean task.env.alpha? python train.py" in said["+alpha=2"]


def test_reported_makes_a_constructors_refusal_one_line_and_lets_a_bug_through(capsys, monkeypatch):
    from hydra.errors import InstantiationException

    from dipole_torch.training.checks import reported

    monkeypatch.delenv("HYDRA_FULL_ERROR", raising=False)
    # A constructor's refusal in a named node: its first line, after the node; status 2.
    with pytest.raises(SystemExit) as stopped, reported("task.env"):
        raise ValueError("width must be positive, got -1\n  (more on the width)")
    assert stopped.value.code == 2
    assert capsys.readouterr().err.strip() == (
        "error: task.env: width must be positive, got -1 (HYDRA_FULL_ERROR=1 for the traceback)"
    )
    # A file the constructor cannot find, reaching train.py through Hydra's wrapper.
    with pytest.raises(SystemExit), reported("task.env"):
        raise InstantiationException("Error in call to target") from FileNotFoundError("no x.urdf")
    assert "error: task.env: no x.urdf (HYDRA_FULL_ERROR" in capsys.readouterr().err
    # Outside a named node a plain ValueError is no config value's: its traceback stays.
    with pytest.raises(ValueError, match="a bug"), reported():
        raise ValueError("a bug")


# ------------------------------------------------------------------ in-process train.py
def run_train(*overrides):
    """``python train.py <overrides>`` in this process (exceptions propagate)."""
    import train

    argv = sys.argv
    env = os.environ.get("HYDRA_FULL_ERROR")
    sys.argv = ["train.py", "task=multimodal", "progress=false", "figure_every=0", *overrides]
    os.environ["HYDRA_FULL_ERROR"] = "1"
    try:
        train.main()
    finally:
        sys.argv = argv
        if env is None:
            os.environ.pop("HYDRA_FULL_ERROR", None)
        else:
            os.environ["HYDRA_FULL_ERROR"] = env


@pytest.fixture(scope="module")
def finished_run(tmp_path_factory):
    run_dir = tmp_path_factory.mktemp("finished")
    run_train(f"hydra.run.dir={run_dir}", "trials=40")
    return run_dir


# ------------------------------------------------------------------ 2, 8: kill, signals
KILLS = 24
TRIALS = 150  # the SIGKILL run
SIGNAL_TRIALS = 60  # the SIGTERM and SIGINT runs
BASE = [
    "task=multimodal",
    "algo=dipole",
    f"trials={TRIALS}",
    "checkpoint_every=1",
    "figure_every=0",
    "progress=false",
]


@pytest.fixture(scope="module")
def driver_report(tmp_path_factory):
    """The driver's report; under pytest-xdist, one driver for all workers of the session."""
    if os.environ.get("PYTEST_XDIST_WORKER"):
        root = tmp_path_factory.getbasetemp().parent  # this session's, shared by its workers
    else:
        root = tmp_path_factory.mktemp("driver")
    report_file = root / "reliability_driver.json"
    with FileLock(f"{report_file}.lock"):
        if report_file.is_file():
            return json.loads(report_file.read_text())
        work = root / "reliability_driver"
        work.mkdir(exist_ok=True)
        result = subprocess.run(
            [sys.executable, __file__, str(work), str(KILLS)],
            capture_output=True,
            text=True,
            timeout=400,
            cwd=work,
        )
        assert result.returncode == 0, result.stdout[-3000:] + result.stderr[-3000:]
        report = json.loads(result.stdout.strip().splitlines()[-1])
        report_file.write_text(json.dumps(report))
    summary = {key: value for key, value in report["kill"].items() if key != "kills"}
    print(json.dumps({**report, "kill": summary}, indent=1))
    return report


def test_sigkill_at_random_moments_then_resume_gives_the_uninterrupted_results(driver_report):
    kill = driver_report["kill"]
    assert kill["failures"] == [], kill["failures"]
    assert len(kill["kills"]) >= 20
    # Some kills hit a session after it had written checkpoints, and the run moved on.
    trials = [k["checkpoint_trials"] for k in kill["kills"]]
    assert all(b >= a for a, b in zip(trials, trials[1:], strict=False))
    assert kill["resumes"] >= 20 and 0 < max(trials) < TRIALS
    assert len({t for t in trials if t}) >= 4  # kills at many different points of the run
    # Kills in the middle of a checkpoint write left its temporary (and the previous
    # checkpoint, which loaded); the next session removed it.
    assert kill["kills_leaving_a_temporary"] >= 3
    assert kill["max_temporaries_after_a_kill"] <= 1 and kill["temporaries_at_end"] == 0
    assert kill["identical"] == {"results": True, "policies": True, "checkpoint": True}


@pytest.mark.parametrize("name, code", [("SIGTERM", 143), ("SIGINT", 130)])
def test_a_signal_writes_a_checkpoint_and_prints_the_resume_command(driver_report, name, code):
    stop = driver_report[name]
    assert stop["exit_code"] == code, stop["log"]
    assert "Traceback" not in stop["log"], stop["log"]
    assert f"stopped by {name} at" in stop["log"] and "resume with:" in stop["log"]
    assert 0 < stop["checkpoint_trials"] < SIGNAL_TRIALS
    assert f"checkpoint at {stop['checkpoint_trials']} trials written to" in stop["log"]
    # The printed command, run as printed, finishes the run as if never stopped.
    assert stop["resumed_exit_code"] == 0, stop["resumed_log"]
    assert stop["identical"] == {"results": True, "policies": True, "checkpoint": True}


def test_stop_request_takes_sigterm_and_sigint_then_gives_the_handlers_back(capfd):
    # (The driver's runs see the exit codes; this sees each signal's own name and that the
    # handlers the run found are put back.)
    from dipole_torch.training.signals import StopRequest

    elsewhere = []  # the handlers found: a signal the request missed lands here

    def found(signum, frame):
        elsewhere.append(signum)

    previous = {s: signal.signal(s, found) for s in (signal.SIGTERM, signal.SIGINT)}
    try:
        for signum in (signal.SIGTERM, signal.SIGINT):
            with StopRequest() as stop:
                assert not stop and stop.name == ""
                signal.raise_signal(signum)
                assert stop and stop.signum == signum and stop.name == signum.name
            assert signal.getsignal(signal.SIGTERM) is signal.getsignal(signal.SIGINT) is found
            assert f"{signum.name} received: finishing this iteration" in capfd.readouterr().err
        assert elsewhere == []
    finally:
        for signum, handler in previous.items():
            signal.signal(signum, handler)


def test_stop_request_outside_the_main_thread_is_no_failure():
    # (A threaded Hydra launcher runs the loop in a thread, where no handler can be set.)
    import threading

    from dipole_torch.training.signals import StopRequest

    asked = []

    def loop():
        with StopRequest() as stop:
            asked.append(bool(stop))

    thread = threading.Thread(target=loop)
    thread.start()
    thread.join()
    assert asked == [False]


def test_a_second_stop_asked_exits_at_once_with_its_status():
    code = (
        "import signal\n"
        "from dipole_torch.training.signals import StopRequest\n"
        "with StopRequest():\n"
        "    signal.raise_signal(signal.SIGINT)\n"
        "    print('first signal: going on', flush=True)\n"
        "    signal.raise_signal(signal.SIGINT)\n"
        "    print('not stopped')\n"
    )
    result = subprocess.run(
        [sys.executable, "-c", code], cwd=ROOT, capture_output=True, text=True, timeout=60
    )
    assert result.returncode == 128 + signal.SIGINT, result.stderr
    assert result.stdout.split() == ["first", "signal:", "going", "on"]
    assert "second SIGINT: stopping now" in result.stderr and "Traceback" not in result.stderr


# ------------------------------------------------------------------ the driver process
def _fork_train(train, args, log, slow_disk=False):
    """Run ``train.main()`` with ``args`` in a forked child; return its pid. ``slow_disk``:
    every fsync takes 0.3 s longer (a stalled disk), so that a kill aimed at a write lands
    while its temporary exists even on a loaded machine (20 ms missed every aim there)."""
    sys.stdout.flush()
    sys.stderr.flush()
    pid = os.fork()
    if pid:
        return pid
    code = 1
    try:
        fd = os.open(log, os.O_WRONLY | os.O_CREAT | os.O_APPEND, 0o644)
        os.dup2(fd, 1)
        os.dup2(fd, 2)
        if slow_disk:
            fsync = os.fsync

            def slow_fsync(fd):
                time.sleep(0.3)
                fsync(fd)

            os.fsync = slow_fsync
        sys.argv = ["train.py", *args]
        train.main()
        code = 0
    except SystemExit as exit:
        code = exit.code if isinstance(exit.code, int) else 1
    except BaseException:
        traceback.print_exc()
    finally:
        sys.stdout.flush()
        sys.stderr.flush()
        os._exit(code)


def _wait(pid):
    return os.waitstatus_to_exitcode(os.waitpid(pid, 0)[1])


def _compare(reference: Path, run: Path) -> dict:
    a = json.loads((reference / "results.json").read_text())
    b = json.loads((run / "results.json").read_text())
    a.pop("wall_time_s"), b.pop("wall_time_s")
    same = {"results": a == b}
    for name, key in (("policies", None), ("checkpoint", "optimizer")):
        x = load_checkpoint(reference / f"{name}.pt")
        y = load_checkpoint(run / f"{name}.pt")
        x, y = (x, y) if key is None else (x[key], y[key])
        try:
            assert_same(x, y)
            same[name] = True
        except AssertionError:
            same[name] = False
    return same


def _checkpoint_trials(path: Path):
    if not path.exists():
        return 0
    return int(load_checkpoint(path, kind="checkpoint after a kill")["optimizer"]["trials"])


def _inode(path: Path):
    try:
        return path.stat().st_ino  # os.replace gives the file a new inode
    except FileNotFoundError:
        return None


def _driver(work: Path, kills: int) -> dict:
    torch.set_num_threads(1)
    import train

    report = {}
    # The uninterrupted run, in this process: it also does the lazy imports (sympy, ...)
    # once, so that the forked sessions start fast.
    reference = work / "reference"
    sys.argv = ["train.py", *BASE, f"hydra.run.dir={reference}"]
    start = time.perf_counter()
    train.main()
    report["reference_s"] = time.perf_counter() - start
    iterations = len(json.loads((reference / "results.json").read_text())["history"]["trials"])
    period = report["reference_s"] / iterations  # an iteration, its checkpoint included

    # SIGKILL at random moments: after a random number (0-1) of the session's checkpoint
    # writes, a random time within about one iteration. Each session resumes from whatever
    # checkpoint the previous one left.
    rng = random.Random(0)
    run = work / "killed"
    checkpoint = run / "checkpoint.pt"
    kill = {"kills": [], "failures": [], "resumes": 0, "max_temporaries_after_a_kill": 0}
    start = time.perf_counter()
    while True:
        resume = checkpoint.exists()
        kill["resumes"] += resume
        args = [*BASE, f"hydra.run.dir={run}"] + ([f"resume={checkpoint}"] if resume else [])
        killing = len(kill["kills"]) < kills
        # Every third kill lands while a checkpoint is being written (its temporary
        # exists), or after two iterations' time if none is seen.
        mid_write = killing and len(kill["kills"]) % 3 == 2
        pid = _fork_train(train, args, work / "killed.log", slow_disk=mid_write)
        status = None
        if killing:
            writes, delay = rng.choice([0, 0, 0, 1, 1]), rng.uniform(0.0, 0.8 * period)
            inode, deadline = _inode(checkpoint), None
            if mid_write:
                deadline = time.monotonic() + 1.0 + 2 * period + 0.6
            while status is None and (deadline is None or time.monotonic() < deadline):
                done, raw = os.waitpid(pid, os.WNOHANG)
                status = os.waitstatus_to_exitcode(raw) if done else None
                if mid_write:
                    if any(run.glob(".checkpoint.pt.*.tmp")):
                        break
                elif deadline is None and writes == 0:
                    deadline = time.monotonic() + delay
                elif deadline is None and _inode(checkpoint) != inode:
                    writes, inode = writes - 1, _inode(checkpoint)
                time.sleep(0.0002)
            if status is None:
                os.kill(pid, signal.SIGKILL)
                os.waitpid(pid, 0)
                temporaries = len(list(run.glob(".*.tmp")))
                kill["kills_leaving_a_temporary"] = kill.get("kills_leaving_a_temporary", 0) + (
                    temporaries > 0
                )
                kill["max_temporaries_after_a_kill"] = max(
                    kill["max_temporaries_after_a_kill"], temporaries
                )
                try:
                    trials = _checkpoint_trials(checkpoint)
                except CheckpointError as error:
                    kill["failures"].append(f"after kill {len(kill['kills'])}: {error}")
                    break
                kill["kills"].append({"checkpoint_trials": trials, "delay_s": delay})
                continue
        else:
            status = _wait(pid)
        if status != 0:
            log = (work / "killed.log").read_text()[-2000:]
            kill["failures"].append(f"a session exited with {status}: {log}")
        break
    kill["seconds"] = time.perf_counter() - start
    kill["temporaries_at_end"] = len(list(run.glob(".*.tmp")))
    if not kill["failures"]:
        kill["identical"] = _compare(reference, run)
    report["kill"] = kill

    # SIGTERM and SIGINT once the loop runs; then the printed command, as printed.
    short = [arg for arg in BASE if not arg.startswith("trials=")] + [f"trials={SIGNAL_TRIALS}"]
    short_reference = work / "short_reference"
    sys.argv = ["train.py", *short, f"hydra.run.dir={short_reference}"]
    train.main()
    for signum in (signal.SIGTERM, signal.SIGINT):
        run = work / signum.name
        log = work / f"{signum.name}.log"
        pid = _fork_train(train, [*short, f"hydra.run.dir={run}"], log)
        deadline = time.monotonic() + 60
        while not (run / "checkpoint.pt").exists() and time.monotonic() < deadline:
            time.sleep(0.002)
        time.sleep(0.02)
        os.kill(pid, signum)
        stop = {"exit_code": _wait(pid), "log": log.read_text(), "resumed_exit_code": None}
        stop["checkpoint_trials"] = _checkpoint_trials(run / "checkpoint.pt")
        lines = stop["log"].splitlines()
        if "resume with:" in lines:
            command = shlex.split(lines[lines.index("resume with:") + 1])
            assert command[0] == "python" and command[1].endswith("train.py"), command
            resumed_log = work / f"{signum.name}.resumed.log"
            stop["resumed_exit_code"] = _wait(_fork_train(train, command[2:], resumed_log))
            stop["resumed_log"] = resumed_log.read_text()[-2000:]
            if stop["resumed_exit_code"] == 0:
                stop["identical"] = _compare(short_reference, run)
        report[signum.name] = stop
    return report


if __name__ == "__main__":
    os.chdir(sys.argv[1])
    print(json.dumps(_driver(Path(sys.argv[1]), int(sys.argv[2]))))

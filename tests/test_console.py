"""What a training run prints: a bar on a terminal, lines every ~10 % otherwise, messages never
glued to the bar, a summary without repeats; a bad value is one line and exit status 2."""

import io
import logging
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from dipole_torch.training.console import Progress, summary

ROOT = Path(__file__).resolve().parents[1]


class Terminal(io.StringIO):
    def isatty(self) -> bool:
        return True


def test_piped_output_is_a_line_every_tenth_of_the_budget(caplog):
    caplog.set_level(logging.INFO, logger="train")
    stream = io.StringIO()
    progress = Progress(300, 0, stream=stream)
    trials = 0
    for batch in [30, *([4] * 67), 2]:
        trials += batch
        progress.update(trials, batch, {"best_so_far": 1000.0, "num_policies": 3})
    progress.close()
    lines = [r.getMessage() for r in caplog.records]
    assert stream.getvalue() == ""  # no bar, no carriage returns
    assert len(lines) == 10 and all("\r" not in line for line in lines)
    assert lines[0].startswith("30 of 300 trials (10 %): best return 1000, 3 policies")
    assert lines[-1].startswith("300 of 300 trials (100 %)")


def test_piped_lines_for_an_odd_budget_a_resumed_run_and_a_batch_over_several_tenths(caplog):
    caplog.set_level(logging.INFO, logger="train")
    row = {"best_so_far": 1.0, "num_policies": 2}

    def lines(total, start, batches):
        caplog.clear()
        progress, trials = Progress(total, start, stream=io.StringIO()), start
        for batch in batches:
            trials += batch
            progress.update(trials, batch, row)
        return [int(r.getMessage().split()[0]) for r in caplog.records]

    # 19 trials: a line every round(1.9) = 2, and one at the budget.
    assert lines(19, 0, [1] * 19) == [2, 4, 6, 8, 10, 12, 14, 16, 18, 19]
    # Resumed at 160 of 300: the next line at the next tenth, 180, then at 210.
    assert lines(300, 160, [10] * 6) == [180, 210]
    # One batch over several tenths: one line, then the next tenth after it.
    assert lines(100, 0, [35, 1, 1, 1, 1, 1, 10]) == [35, 40, 50]


def test_a_terminal_with_the_bar_turned_off_gets_lines(caplog):
    caplog.set_level(logging.INFO, logger="train")
    stream = Terminal()
    progress = Progress(100, 0, enabled=False, stream=stream)
    progress.update(10, 10, {"best_so_far": 1.0, "num_policies": 2})
    progress.close()
    assert stream.getvalue() == ""
    assert caplog.records[0].getMessage().startswith("10 of 100 trials (10 %)")


def test_a_terminal_gets_a_bar_and_messages_above_it():
    stream = Terminal()
    progress = Progress(100, 20, stream=stream)
    with progress.messages():
        progress.update(40, 20, {"best_so_far": 0.97211, "num_policies": 2})
        logging.getLogger("train").warning("a message")
    progress.close()
    text = stream.getvalue()
    assert "40/100" in text and "best=0.9721" in text and "policies=2" in text


def test_the_summary_names_each_policy_once_by_id():
    results = {
        "best_reward": 1000.0,
        "trials": 500,
        "trial_budget": 500,
        "policies": [
            {"id": 7, "return_of_mean": 0.5, "description": ""},
            {"id": 3, "return_of_mean": 0.9, "description": "route (0, 1): return 0.900"},
        ],
    }
    text = summary("dipole", "cartpole", results, "outputs/x")
    lines = text.splitlines()
    assert lines[0] == (
        "dipole on cartpole: best return 1000 in 500 trials (budget 500); 2 policies (their "
        "means, without exploration):"
    )
    assert lines[1:3] == ["  policy 3: route (0, 1): return 0.900", "  policy 7: return 0.5"]
    one = summary("power", "cartpole", results | {"policies": results["policies"][:1]}, "x")
    assert "; 1 policy (its mean, without exploration):" in one


def test_on_noisy_returns_a_description_is_followed_by_the_mean_that_orders_it():
    results = {
        "best_reward": 0.99,
        "trials": 500,
        "trial_budget": 500,
        "repeats": {"best_evaluations": 4, "returns": "noisy", "best_reward_evaluations": 4},
        "policies": [
            {"id": 1, "return_of_mean": 0.95, "description": "route a: return 0.999"},
            {"id": 2, "return_of_mean": 0.97, "description": "route b: return 0.93"},
            {"id": 3, "return_of_mean": 0.5, "description": ""},
        ],
    }
    lines = summary("dipole", "viapoint", results, "x").splitlines()
    assert lines[1:4] == [
        "  policy 2: route b: return 0.93 (one rollout; the mean of 4: 0.97)",
        "  policy 1: route a: return 0.999 (one rollout; the mean of 4: 0.95)",
        "  policy 3: return 0.5",
    ]


def test_the_summary_of_no_policies_an_empty_set_line_and_repeats():
    results = {"best_reward": 1.0, "trials": 100, "trial_budget": 100, "policies": []}
    assert "; 0 policies (their means" in summary("dipole", "cone", results, "x")
    # A task with policy-set scalars but no line on them adds no line.
    quiet = results | {"policy_set": {"scalars": {"routes": 2.0}, "description": ""}}
    assert summary("dipole", "cone", quiet, "x").splitlines()[1:] == ["outputs in x"]
    repeats = {"best_evaluations": 8, "returns": "noisy", "best_reward_evaluations": 3}
    lines = summary("dipole", "cone", results | {"repeats": repeats}, "x").splitlines()
    assert lines[0].startswith("dipole on cone: best return 1 (the mean of 3) in 100 trials")
    assert lines[1] == "returns noisy: each policy's best sample evaluated up to 8 times"


def test_one_policy_is_one_policy_in_the_log_lines(caplog):
    caplog.set_level(logging.INFO, logger="train")
    progress = Progress(100, 0, stream=io.StringIO())
    progress.update(20, 20, {"best_so_far": 1.0, "num_policies": 1})
    progress.close()
    assert caplog.records[0].getMessage().endswith("best return 1, 1 policy")


def run(*overrides, env=None):
    return subprocess.run(
        [sys.executable, str(ROOT / "train.py"), *overrides],
        cwd=ROOT,
        capture_output=True,
        text=True,
        timeout=120,
        env=dict(os.environ, HYDRA_FULL_ERROR="0", **(env or {})),
    )


@pytest.mark.parametrize(
    "overrides, line",
    [
        (["trials=-1"], "error: trials (the trial budget) must be a positive integer, got -1"),
        (["device=cuda:7"], "error: device='cuda:7' but"),
        (["device=tpu"], "error: device must be 'cpu', 'cuda', 'cuda:N' or 'mps', got 'tpu'"),
        (["algo.optimizer.alpha=-1"], "error: algo.optimizer: alpha (DP concentration) must be"),
        (["task.env.width=-1"], "error: task.env: "),
        (["resume=/no/such/checkpoint.pt"], "error: train.py checkpoint '/no/such/checkpoint.pt'"),
        (
            ["+tirals=100"],
            "error: unknown key(s) tirals: no setting of that name (did you mean trials?",
        ),
        (
            ["+algo.optimizer.alpah=2"],
            "error: unknown key(s) algo.optimizer.alpah: no setting "
            "of that name (did you mean algo.optimizer.alpha?",
        ),
        (
            ["+optimizer=power"],
            "error: unknown key(s) optimizer: no setting of that name (did you mean "
            "algo.optimizer? task=<name> and algo=<name> choose the task and the optimizer;",
        ),
    ],
)
def test_a_bad_value_is_one_line_naming_it_and_exit_status_2(overrides, line, tmp_path):
    result = run(*overrides, f"hydra.run.dir={tmp_path}")
    assert result.returncode == 2, result.stdout + result.stderr
    errors = [text for text in result.stderr.splitlines() if text.strip()]
    assert len(errors) == 1 and errors[0].startswith(line), result.stderr
    assert "Traceback" not in result.stderr + result.stdout
    # The run's directory says why it stopped.
    assert errors[0] in (tmp_path / "train.log").read_text()


@pytest.mark.parametrize(
    "overrides, line",
    [
        (["trails=60"], "error: unknown key trails (trails=60): no setting of that name (did you "
                        "mean trials? python train.py --help lists every key)"),
        (["-m", "sed=0,1"], "error: unknown key sed (sed=0,1): no setting of that name (did you "
                            "mean seed?"),
        (["--cfg", "job", "xyz=1"], "error: unknown key xyz (xyz=1): no setting of that name (a "
                                    "misspelling?"),
    ],
)  # fmt: skip
def test_a_misspelled_key_at_the_root_is_named_before_hydra_composes(overrides, line, tmp_path):
    """Hydra said "To append to your config use +trails=60", and the run's own check named
    trials only after that detour; the command ends before Hydra makes the run's directory."""
    result = run(*overrides, f"hydra.run.dir={tmp_path / 'run'}", f"hydra.sweep.dir={tmp_path}")
    assert result.returncode == 2, result.stdout + result.stderr
    errors = [text for text in result.stderr.splitlines() if text.strip()]
    assert len(errors) == 1 and errors[0].startswith(line), result.stderr
    assert not list(tmp_path.iterdir())


def test_a_second_signal_stops_at_once_without_a_traceback(tmp_path):
    process = subprocess.Popen(
        [sys.executable, str(ROOT / "train.py"), "task=viapoint", "trials=3000", "progress=false",
         f"hydra.run.dir={tmp_path}"],
        cwd=ROOT, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
    )  # fmt: skip
    deadline = time.time() + 60
    while not (tmp_path / "tensorboard").exists() and time.time() < deadline:
        time.sleep(0.2)
    time.sleep(1.0)  # in the loop
    process.send_signal(signal.SIGTERM)
    process.send_signal(signal.SIGTERM)
    out, err = process.communicate(timeout=60)
    assert process.returncode == 128 + signal.SIGTERM, err
    assert "Traceback" not in err and "KeyboardInterrupt" not in err

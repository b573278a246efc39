"""Runs of ``train.py`` with random tasks, algorithms, settings and resumes: a search for the
command lines that end in a traceback, a wrong result file or a resume that does not continue
the run exactly.

    python tests/fuzz_train.py --seeds 0 100              # seeds 0 ... 99
    python tests/fuzz_train.py --seeds 7 8 --keep         # one case again, its directory kept
    python tests/fuzz_train.py --seeds 0 1000 --minutes 60  # as many as fit

Not part of the test suite (a case starts one to three processes of a few seconds each); the
cases it finds become tests of their own (``tests/test_train.py``). Each seed draws, from its
own ``random.Random``:

* a task (``cartpole``, ``mountain_car``, ``multimodal``, ``viapoint``, ``viapoint_blocked``)
  with up to three of its ``task.env`` settings at ordinary or edge values, ``task.n0``, a
  budget of 20-400 trials and a seed;
* an algorithm (``dipole``, ``dipole_coverage``, ``dipole_paper``, ``power``) and, half the
  time, random values of its options (``tests/fuzz_long_runs.py``'s draws, those the
  algorithm's schema has), sometimes with a box (``bounds``);
* ``checkpoint_every``, ``figure_every`` and ``progress``;
* for the viapoint tasks, in 30 % of the cases, a vendor-style arm of ``tests/urdf/``
  instead of the WAM (drawn from a stream of its own, so that the other draws of a seed do
  not depend on it).

Then, for a run that ended well, in a third of the cases the run again in two sessions, the
first stopped by SIGINT after one of its progress lines and resumed (its results must be the
first run's, to the bit), and in another third a resume with a larger budget (it must end at
that budget).

A case fails when a process prints a traceback, exits with a status other than 0 (done) or 2
(refused before the run, one line naming the setting), or ends without a ``results.json`` of
the budget's trials and a finite best return. Printed: one line per failure (seed, what
failed, the command line, the output's end), and the counts of cases, failures and refusals.
"""

from __future__ import annotations

import argparse
import json
import math
import os
import random
import shlex
import shutil
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))

from fuzz_long_runs import options, power_options  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
TASKS = ("cartpole", "mountain_car", "multimodal", "viapoint", "viapoint_blocked")
ALGOS = ("dipole", "dipole_coverage", "dipole_paper", "power")
# The options each algorithm's schema has beyond those fuzz_long_runs draws for Dipole.
PAPER_KEYS = {"alpha", "m", "M", "regularization", "reward_weighted", "best_evaluations"}
POWER_KEYS = {"M", "reward_floor", "exploration_decay", "min_exploration", "best_evaluations"}
ENV = {
    "cartpole": {
        "steps": [50, 1000],
        "engine": ["python", "torch", "auto"],
        "initial_angle": [0.0, 0.05, 0.2],
        "force_limit": [1.0, 10.0, 1e6],
        "exploration_std": [1e-3, 1.0, [1.0, 1.0, 20.0, 3.0]],
    },
    "mountain_car": {
        "steps": [30, 100],
        "engine": ["python", "torch", "auto"],
        "goal_position": [0.3, 0.5, 1.45],
        "exploration_std": [1e-3, 1.0, [1.0, 1.0, 10.0, 100.0]],
    },
    "multimodal": {
        "dim": [2, 3, 5],
        "num_optima": [2, 4, 7],
        "width": [0.01, 0.25, 2.0],
        "noise_std": [0.0, 0.1, 1.0],
        "exploration_std": [1e-3, 0.6, 10.0],
    },
    "viapoint": {
        "reward_alpha": [1.0, 2.5, 50.0],
        "time_std": [None, 0.28, 2.0],
        "stiffness": [10.0, 100.0, 1000.0],
    },
    "viapoint_blocked": {"reward_alpha": [1.0, 2.5], "time_std": [None, 0.28]},
}


# Vendor-style arms (tests/urdf/): file, end effector, a start posture. The viapoint layout
# stays the WAM's: some points lie out of an arm's reach, which the task warns of.
ARMS = (
    ("iiwa_style.urdf", "lbr_iiwa_link_ee", [0.0, 0.5, 0.0, -1.2, 0.0, 0.6, 0.0]),
    ("panda_style.urdf", "panda_hand_tcp", [0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.785]),
    ("gen3_style.urdf", "tool_frame", [0.0, 0.4, 0.0, 1.6, 0.0, 1.0, 0.0]),
    ("xarm6_style.urdf", "link_eef", [0.0, -0.5, -0.8, 0.0, 1.3, 0.0]),
)


def hydra_value(value) -> str:
    """``value`` written as a Hydra override's right-hand side."""
    if value is None:
        return "null"
    if isinstance(value, bool):
        return str(value).lower()
    if isinstance(value, (list, tuple)):
        return "[" + ",".join(hydra_value(v) for v in value) + "]"
    return repr(value) if isinstance(value, float) else str(value)


def draw_case(seed: int) -> tuple[list[str], int]:
    """The overrides of case ``seed`` and its trial budget."""
    rng = random.Random(seed)
    task, algo = rng.choice(TASKS), rng.choice(ALGOS)
    trials = rng.choice([20, 60, 150, 400])
    if task == "viapoint_blocked":
        trials = rng.choice([400, 600])  # beyond the block, at 300 or at 60 trials
    overrides = [f"task={task}", f"algo={algo}", f"trials={trials}", f"seed={rng.randrange(10**6)}"]
    if task == "viapoint_blocked" and rng.random() < 0.5:
        overrides.append("task.block.trial=60")
    for key in rng.sample(sorted(ENV[task]), k=rng.randint(0, min(3, len(ENV[task])))):
        overrides.append(f"task.env.{key}={hydra_value(rng.choice(ENV[task][key]))}")
    if rng.random() < 0.5:
        overrides.append(f"task.n0={rng.choice([1, 3, 10, 40])}")
    changes: dict = {}
    if rng.random() < 0.5:
        if algo == "power":
            changes = power_options(rng)
            changes = {k: v for k, v in changes.items() if k in POWER_KEYS}
        else:
            _, changes = options(rng)
            if algo == "dipole_paper":
                changes = {k: v for k, v in changes.items() if k in PAPER_KEYS}
        if rng.random() < 0.2:
            changes["best_evaluations"] = rng.choice([1, 2, 4])
        if rng.random() < 0.2:
            changes["bounds"] = rng.choice([[-1e3, 1e3], [-50.0, 50.0]])
    overrides += [f"algo.optimizer.{k}={hydra_value(v)}" for k, v in changes.items()]
    arm = random.Random(seed + 2 * 10**9)  # (its own stream: the other draws stay the same)
    if task.startswith("viapoint") and arm.random() < 0.3:
        file, end_effector, posture = arm.choice(ARMS)
        overrides += [
            f"task.env.urdf={ROOT / 'tests' / 'urdf' / file}",
            f"task.env.end_effector={end_effector}",
            f"task.env.initial_joints={hydra_value(posture)}",
        ]
    overrides += [
        f"checkpoint_every={rng.choice([1, 3, 20])}",
        f"figure_every={rng.choice([0, 1, 7, 25])}",
        f"progress={hydra_value(rng.random() < 0.3)}",
    ]
    return overrides, trials


def run(args: list[str], directory: Path, interrupt_at: int | None = None):
    """``(status, output)`` of ``train.py args`` run in ``directory``; SIGINT once the
    ``interrupt_at``-th progress line is out (the run's loop has begun), when given."""
    command = [sys.executable, str(ROOT / "train.py"), *args, f"hydra.run.dir={directory}"]
    env = {**os.environ, "PYTHONUNBUFFERED": "1"}
    env.pop("HYDRA_FULL_ERROR", None)
    process = subprocess.Popen(
        command, cwd=ROOT, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True
    )
    lines, progress = [], 0
    for text in process.stdout:
        lines.append(text)
        progress += " trials (" in text
        if interrupt_at is not None and progress == interrupt_at:
            process.send_signal(signal.SIGINT)
            interrupt_at = None
    return process.wait(timeout=900), "".join(lines)


def results_problem(directory: Path, trials: int) -> str | None:
    """What is wrong with ``directory``'s results.json for a budget of ``trials``, or None."""
    path = directory / "results.json"
    if not path.exists():
        return "no results.json"
    results = json.loads(path.read_text())
    log = directory / "train.log"
    # Documented (docs/guide/switching.md): a block whose re-evaluation of the K stored
    # policies would pass the budget ends the run there, unblocked, below its budget.
    no_block = f"no block: re-evaluating would take the run past {trials}"
    unblocked = "block" not in results and log.exists() and no_block in log.read_text()
    if results["trials"] != trials and not (unblocked and results["trials"] < trials):
        return f"results.json has {results['trials']} trials, the budget {trials}"
    if not math.isfinite(results["best_reward"]):
        return f"best_reward {results['best_reward']}"
    return None


def check_case(seed: int, scratch: Path) -> tuple[str, str | None, str]:
    """``(outcome, failure, output)``: outcome "done", "refused" or "failed"."""
    overrides, trials = draw_case(seed)
    rng = random.Random(seed + 10**9)  # the follow-up's draws, apart from the case's
    first = scratch / "first"
    status, output = run(overrides, first)
    line = "python train.py " + " ".join(overrides)
    if "Traceback" in output or status not in (0, 2):
        return "failed", f"exit {status}: {line}", output
    if status == 2:
        return "refused", None, output
    if problem := results_problem(first, trials):
        return "failed", f"{problem}: {line}", output
    follow_up = rng.random()
    if follow_up < 1 / 3:  # stopped and resumed: the same results as one session
        second = scratch / "second"
        status, output = run(overrides, second, interrupt_at=rng.randint(1, 9))
        if "Traceback" in output or status not in (0, 130):
            return "failed", f"interrupted, exit {status}: {line}", output
        if status == 130:  # the command it prints, as a user would paste it
            printed = shlex.split(output.split("resume with:\n", 1)[-1].splitlines()[0])
            if printed[0] != "python" or not printed[1].endswith("train.py"):
                return "failed", f"interrupted, no resume command printed: {line}", output
            status, output = run(printed[2:], second)
            if "Traceback" in output or status != 0:
                return "failed", f"resumed after SIGINT, exit {status}: {line}", output
        one, two = (json.loads((d / "results.json").read_text()) for d in (first, second))
        for key in ("trials", "best_reward", "best_theta", "policies"):
            if one[key] != two[key]:
                return "failed", f"resumed run's {key} differs: {line}", output
    elif follow_up < 2 / 3:  # a larger budget
        more = trials + rng.choice([20, 100, 300])
        extended = [o for o in overrides if not o.startswith("trials=")] + [f"trials={more}"]
        status, output = run([*extended, f"resume={first / 'checkpoint.pt'}"], first)
        if "Traceback" in output or status != 0:
            return "failed", f"resumed to {more} trials, exit {status}: {line}", output
        if problem := results_problem(first, more):
            return "failed", f"resumed to {more}: {problem}: {line}", output
    return "done", None, output


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs=2, default=[0, 20], metavar=("FIRST", "END"))
    parser.add_argument("--minutes", type=float, default=None, help="stop starting cases after")
    parser.add_argument("--keep", action="store_true", help="keep each case's directories")
    args = parser.parse_args()
    deadline = None if args.minutes is None else time.monotonic() + 60 * args.minutes
    counts = {"done": 0, "refused": 0, "failed": 0}
    for seed in range(*args.seeds):
        if deadline is not None and time.monotonic() > deadline:
            print(f"time up before seed {seed}")
            break
        scratch = Path(tempfile.mkdtemp(prefix=f"fuzz_train_{seed}_"))
        outcome, failure, output = check_case(seed, scratch)
        counts[outcome] += 1
        if failure is not None:
            tail = "\n    ".join(output.strip().splitlines()[-12:])
            print(f"seed {seed} FAILED: {failure}\n    {tail}", flush=True)
        if args.keep or failure is not None:
            print(f"seed {seed}: {outcome}, directories in {scratch}", flush=True)
        else:
            shutil.rmtree(scratch, ignore_errors=True)
    print(f"{sum(counts.values())} cases: {counts['failed']} failed, {counts['refused']} refused "
          f"before the run with one line, {counts['done']} done")  # fmt: skip
    raise SystemExit(1 if counts["failed"] else 0)


if __name__ == "__main__":
    main()

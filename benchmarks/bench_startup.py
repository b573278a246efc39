"""Start-up of ``train.py``: CPU seconds from process start to the first ``ask``, and of
``--help``, each beside ``python -c "import torch"`` measured in the same run.

Each command runs ``--repeats`` times in a fresh process (one thread); the CPU time (user +
system) of the median run is printed, with its excess over ``import torch``. To stop a run at
its first ``ask``, the process runs ``train.py`` with ``PolicySearch.ask`` replaced by a
function that prints the process's CPU time and exits: everything a run does before it
(Python, torch, Hydra's compose, the schemas, the task, the optimizer, the run directory, the
TensorBoard writer) is counted. Also printed: a whole short run (``trials=10``), for scale, and
the ten slowest imports of the run (``python -X importtime``)::

    python benchmarks/bench_startup.py                # task=cartpole, 5 repeats
    python benchmarks/bench_startup.py --task viapoint --repeats 3
"""

from __future__ import annotations

import argparse
import os
import re
import resource
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

# The anchor of the first ask: the CPU time at the end of ``import torch``, from inside.
IMPORT_TORCH = """
import time
import torch
print(f"FIRST_ASK {time.process_time():.6f}", flush=True)
"""

# Runs train.py as __main__ and exits at the first ask, printing the CPU time until then.
FIRST_ASK = """
import os, runpy, sys, time
import dipole_torch.search as search

def first_ask(self, *args, **kwargs):
    print(f"FIRST_ASK {time.process_time():.6f}", flush=True)
    os._exit(0)

search.PolicySearch.ask = first_ask
sys.argv = sys.argv[1:]  # python -c CODE train.py ARGS: train.py as argv[0]
runpy.run_path(sys.argv[0], run_name="__main__")
"""


def child_cpu(command: list[str], env: dict) -> tuple[float, str]:
    """CPU seconds (user + system) of one child process, and its stdout + stderr."""
    before = resource.getrusage(resource.RUSAGE_CHILDREN)
    done = subprocess.run(command, env=env, capture_output=True, text=True, cwd=ROOT)
    after = resource.getrusage(resource.RUSAGE_CHILDREN)
    if done.returncode != 0:
        raise RuntimeError(f"{' '.join(command)} failed:\n{done.stderr[-3000:]}")
    cpu = (after.ru_utime - before.ru_utime) + (after.ru_stime - before.ru_stime)
    return cpu, done.stdout + done.stderr


def median_cpu(command: list[str], env: dict, repeats: int, first_ask: bool = False) -> float:
    """Median over ``repeats`` runs; with ``first_ask``, the CPU time the child printed
    (``command`` runs ``FIRST_ASK`` or ``IMPORT_TORCH``)."""
    times = []
    for _ in range(repeats):
        cpu, output = child_cpu(command, env)
        if first_ask:
            found = re.search(r"FIRST_ASK ([0-9.]+)", output)
            if found is None:
                raise RuntimeError(f"the run never reached its first ask:\n{output[-3000:]}")
            cpu = float(found.group(1))
        times.append(cpu)
    return statistics.median(times)


def slowest_imports(command: list[str], env: dict, count: int = 10) -> list[tuple[float, str]]:
    """The ``count`` imports with the largest cumulative time (seconds), top-level packages
    first-seen (``-X importtime`` of ``command``), excluding torch's own."""
    _, output = child_cpu([sys.executable, "-X", "importtime", *command[1:]], env)
    rows = []
    for line in output.splitlines():
        found = re.match(r"import time:\s+\d+ \|\s+(\d+) \|(\s*)(\S+)", line)
        if found and len(found.group(2)) <= 2:  # a top-level import of the run
            name = found.group(3)
            if not name.startswith("torch"):
                rows.append((int(found.group(1)) / 1e6, name))
    return sorted(rows, reverse=True)[:count]


def main() -> None:
    from argtypes import positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    tasks = sorted(path.stem for path in (ROOT / "configs" / "task").glob("*.yaml"))
    parser.add_argument("--task", default="cartpole", choices=tasks)
    parser.add_argument("--repeats", type=positive_int, default=5)
    args = parser.parse_args()

    env = {**os.environ, "OMP_NUM_THREADS": "1", "HYDRA_FULL_ERROR": "1"}
    py = sys.executable
    train = str(ROOT / "train.py")
    with tempfile.TemporaryDirectory() as tmp:

        def run_args(name: str, trials: int) -> list[str]:
            return [f"task={args.task}", f"trials={trials}", "threads=1", "progress=false",
                    f"hydra.run.dir={Path(tmp) / name}"]  # fmt: skip

        # Two anchors: a process's exit tears torch down (~0.3-0.4 s of CPU), which the
        # whole-process figures include and the first ask, printed from inside, does not.
        torch_cpu = median_cpu([py, "-c", "import torch"], env, args.repeats)
        torch_inside = median_cpu([py, "-c", IMPORT_TORCH], env, args.repeats, first_ask=True)
        help_cpu = median_cpu([py, train, "--help"], env, args.repeats)
        ask_cpu = median_cpu(
            [py, "-c", FIRST_ASK, train, *run_args("first_ask", 10)],
            env,
            args.repeats,
            first_ask=True,
        )
        runs = [[py, train, *run_args(f"run{i}", 10)] for i in range(args.repeats)]
        run_cpu = statistics.median(child_cpu(command, env)[0] for command in runs)
        imports = slowest_imports([py, train, *run_args("imports", 10)], env)

    from setting import setting_line  # (torch imported here, after the timed processes)

    print(setting_line(("torch", "hydra-core", "omegaconf"), threads=False))
    print(f"train.py start-up, task={args.task}, CPU seconds (median of {args.repeats}):")
    print(f"  {'import torch, whole process':34s} {torch_cpu:6.2f}")
    print(f"  {'  its CPU at the end of the import':34s} {torch_inside:6.2f}")
    for name, cpu, anchor in [
        ("train.py --help", help_cpu, torch_cpu),
        ("train.py to its first ask", ask_cpu, torch_inside),
        ("train.py trials=10 (whole run)", run_cpu, torch_cpu),
    ]:
        print(f"  {name:34s} {cpu:6.2f}   {cpu - anchor:+5.2f} s beyond import torch"
              f"   ({cpu / anchor:4.2f}x)")  # fmt: skip
    print("\nslowest top-level imports of a run (cumulative seconds, torch's excluded):")
    for seconds, name in imports:
        print(f"  {seconds:6.3f}  {name}")


if __name__ == "__main__":
    main()

"""Many seeds on one machine: the lockstep batching against a Hydra launcher, same runs.

Runs ``--seeds`` cart-pole learning runs of the default DIPOLE (``configs/task/cartpole.yaml``,
``configs/algo/dipole.yaml``) twice, on ``--workers`` cores both times:

* **lockstep**: ``reproduce_figure1.py``'s path: the seeds split in ``--workers`` jobs, one
  process each, every job's runs advancing together with one batched rollout per iteration;
* **launcher**: ``python train.py -m hydra/launcher=joblib hydra.launcher.n_jobs=<workers>
  task=cartpole seed='range(0,<seeds>)'``: one process per run, each with its own Python,
  torch and Hydra start-up, TensorBoard log, checkpoint and ``results.json``.

Prints each path's wall time, the ratio, and both paths' final best-policy return (mean ± std
over the seeds: the same algorithm, so they should agree in distribution; the episodes'
random starts differ, so not draw for draw)::

    python benchmarks/bench_launchers.py              # 50 seeds on 2 cores
    python benchmarks/bench_launchers.py --seeds 4    # quick look
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import subprocess
import sys
import tempfile
import time
from pathlib import Path

import numpy as np
from lockstep import load_task
from reproduce_figure1 import learn

ROOT = Path(__file__).resolve().parents[1]


def lockstep(seeds: int, workers: int) -> tuple[float, np.ndarray]:
    """Wall seconds and ``[seeds]`` final best-policy returns of the lockstep path."""
    _, trials, _ = load_task("cartpole")
    jobs = [
        ("cartpole", "DIPOLE", chunk.tolist(), trials, False, 1000 + i)
        for i, chunk in enumerate(np.array_split(np.arange(seeds), workers))
        if len(chunk)
    ]
    start = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(workers) as pool:
        results = pool.map(learn, jobs)
    wall = time.perf_counter() - start
    final = np.array([history[-1][1] for _, histories, _ in results for history in histories])
    return wall, final


def launcher(seeds: int, workers: int) -> tuple[float, np.ndarray]:
    """Wall seconds and ``[seeds]`` final best-policy returns of the joblib launcher path."""
    with tempfile.TemporaryDirectory() as tmp:
        command = [
            sys.executable,
            str(ROOT / "train.py"),
            "-m",
            "hydra/launcher=joblib",
            f"hydra.launcher.n_jobs={workers}",
            f"hydra.sweep.dir={tmp}/multirun",
            "task=cartpole",
            f"seed=range(0,{seeds})",
        ]
        start = time.perf_counter()
        done = subprocess.run(command, cwd=tmp, capture_output=True, text=True)
        if done.returncode != 0:  # (check=True showed the command line, not train.py's error)
            tail = (done.stdout + done.stderr)[-3000:]
            raise SystemExit(f"train.py -m failed (exit status {done.returncode}):\n{tail}")
        wall = time.perf_counter() - start
        runs = sorted(Path(tmp, "multirun").glob("*/results.json"))
        if len(runs) != seeds:
            raise RuntimeError(f"the launcher wrote {len(runs)} results.json, expected {seeds}")
        final = np.array([json.loads(path.read_text())["history"]["best"][-1] for path in runs])
    return wall, final


def main() -> None:
    from argtypes import positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=positive_int, default=50)
    parser.add_argument("--workers", type=positive_int, default=2, help="cores used by both paths")
    args = parser.parse_args()
    timings = {}
    for name, run in (("lockstep", lockstep), ("launcher (joblib)", launcher)):
        wall, final = run(args.seeds, args.workers)
        timings[name] = wall
        print(
            f"{name:18s} {args.seeds} cart-pole seeds on {args.workers} cores: {wall:6.1f} s "
            f"({wall * args.workers / args.seeds:.1f} core-s a run); final best "
            f"{final.mean():.1f} ± {final.std():.1f}",
            flush=True,
        )
    ratio = timings["launcher (joblib)"] / timings["lockstep"]
    print(f"launcher / lockstep wall time: {ratio:.2f}x")


if __name__ == "__main__":
    main()

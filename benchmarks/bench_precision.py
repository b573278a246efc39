"""How close does each method get to a single narrow peak, and after how many trials?

    python benchmarks/bench_precision.py                  # cone and spike, D = 2 and 10, 3 seeds
    python benchmarks/bench_precision.py --dims 2 --seeds 1 --json /tmp/precision.json

**Peaks** on the box [−5, 5]^D, the optimum c at ``linspace(−0.7, 0.6, D)``:

* *cone*: −‖θ − c‖, the value falls linearly from the top;
* *spike*: a broad quadratic hill (0.99 of the value) with a cone of height 1e-2 and radius
  1e-6 on its top: the last 1e-2 of the value lies within 1e-6 of the optimum and shows only
  once the sampling has shrunk to that scale.

**Gap**: (top − value) / (top − the value at the box's farthest corner), of the best point
told or, for DIPOLE, of the better of it and the best policy mean (evaluated without noise,
not charged). A method *reaches* an accuracy at the first trial after which its gap is below it.

**Methods**, each from what it gets on an unknown problem in the box (θ0 = 0, a start std of
2.5, the box's bounds):

* ``DIPOLE``: the library's defaults (retired policies are woken to refine them while trials
  remain, ``refine=0.1``);
* ``DIPOLE, refine=0``: the same with retirement alone (a policy retires once its
  exploration std is below ``retire_std = 1e-3`` of Σ_start's and stays there);
* ``CMA-ES`` (pycma): σ0 = 2.5, its default population, the box as bounds, no restarts, run
  until the budget or its own stop (tolx, tolfun), ``tolfun=1e-14``, ``tolx=1e-14``: the
  anchor for converging on one optimum.

Printed per (peak, D, method): the median over seeds of the trials to reach 1e-3, 1e-6 and
1e-9 (with how many seeds reached it) and the median final gap, with the optimizer's CPU
seconds. Everything goes to ``--json`` (default ``docs/figures/precision.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_multioptima import run_tasks  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
BOX = 5.0
SIGMA0 = 2.5
PEAKS = ("cone", "spike")
DIMS = (2, 10)
METHODS = ("DIPOLE", "DIPOLE, refine=0", "CMA-ES")
ACCURACIES = (1e-3, 1e-6, 1e-9)
BUDGET = {2: 3000, 10: 12000}
SEEDS = 3


def peak(kind: str, dim: int) -> tuple[Callable[[torch.Tensor], torch.Tensor], float, float]:
    """``f`` on ``[n, D]`` float64 rows, its top and its value range on the box."""
    c = torch.linspace(-0.7, 0.6, dim, dtype=torch.float64)

    def f(theta: torch.Tensor) -> torch.Tensor:
        d = (theta - c).norm(dim=-1)
        if kind == "cone":
            return -d
        return 0.99 * (1.0 - (d / BOX).square()) + 0.01 * (1.0 - d / 1e-6).clamp_min(0.0)

    corner = torch.where(c < 0, BOX, -BOX)[None].to(torch.float64)
    top = float(f(c[None]))
    return f, top, top - float(f(corner))


def run_case(case: tuple[str, int, str, int]) -> dict:
    """One (peak, D, method, seed): the gap after every batch (trials, gap)."""
    kind, dim, method, seed = case
    f, top, span = peak(kind, dim)
    budget = BUDGET.get(dim, 600 * dim)
    trace: list[tuple[int, float]] = []
    cpu = time.process_time()
    spent = 0.0  # the evaluations' CPU, taken off
    if method.startswith("DIPOLE"):
        from dipole_torch import Dipole

        lower = torch.full((dim,), -BOX, dtype=torch.float64)
        opt = Dipole(
            torch.zeros(dim, dtype=torch.float64),
            SIGMA0,
            bounds=(lower, -lower),
            generator=torch.Generator().manual_seed(seed),
            **({"refine": 0.0} if method.endswith("refine=0") else {}),
        )
        while not opt.stop(max_trials=budget):
            theta = opt.ask(max_rows=budget - opt.trials)
            t = time.process_time()
            returns = f(theta)
            spent += time.process_time() - t
            opt.tell(theta, returns)
            t = time.process_time()
            best = max(float(f(opt.policy_means).max()), opt.best()[1])
            spent += time.process_time() - t
            trace.append((opt.trials, (top - best) / span))
    else:
        import cma

        options = {"bounds": [-BOX, BOX], "seed": seed + 1, "verbose": -9, "maxfevals": budget,
                   "tolfun": 1e-14, "tolx": 1e-14, "tolflatfitness": 10**9}  # fmt: skip
        es = cma.CMAEvolutionStrategy(np.zeros(dim), SIGMA0, options)
        trials, best = 0, -np.inf
        while not es.stop() and trials < budget:
            xs = es.ask()
            t = time.process_time()
            values = f(torch.as_tensor(np.asarray(xs), dtype=torch.float64)).tolist()
            spent += time.process_time() - t
            es.tell(xs, [-v for v in values])
            trials, best = trials + len(xs), max(best, max(values))
            trace.append((trials, (top - best) / span))
        if trials < budget:  # stopped: the gap stays where it is
            trace.append((budget, trace[-1][1]))
    reached = {}
    for accuracy in ACCURACIES:
        hit = [t for t, g in trace if g < accuracy]
        reached[str(accuracy)] = hit[0] if hit else None
    return {
        "peak": kind, "dim": dim, "method": method, "seed": seed, "budget": budget,
        "trials_to": reached, "final_gap": trace[-1][1], "trials": trace[-1][0],
        "cpu_seconds": round(time.process_time() - cpu - spent, 2),
    }  # fmt: skip


def summarise(cases: list[dict]) -> tuple[str, list[dict]]:
    """A table (text) and its rows: per (peak, D, method), medians over the seeds."""
    rows, text = [], []
    head = "| peak | D | method | " + " | ".join(f"trials to {a:g}" for a in ACCURACIES)
    text.append(head + " | final gap | CPU s |")
    text.append("|---" * (len(ACCURACIES) + 5) + "|")
    for kind in PEAKS:
        for dim in sorted({c["dim"] for c in cases}):
            for method in METHODS:
                key = (kind, dim, method)
                group = [c for c in cases if (c["peak"], c["dim"], c["method"]) == key]
                if not group:
                    continue
                cells, row = [], {"peak": kind, "dim": dim, "method": method, "seeds": len(group)}
                for a in ACCURACIES:
                    hits = [c["trials_to"][str(a)] for c in group if c["trials_to"][str(a)]]
                    median = int(np.median(hits)) if hits else None
                    row[f"trials_to_{a:g}"] = median
                    row[f"reached_{a:g}"] = len(hits)
                    cells.append("—" if median is None else f"{median} ({len(hits)}/{len(group)})")
                row["final_gap"] = float(np.median([c["final_gap"] for c in group]))
                row["cpu_seconds"] = float(np.median([c["cpu_seconds"] for c in group]))
                rows.append(row)
                tail = f" | {row['final_gap']:.1e} | {row['cpu_seconds']:.1f} |"
                text.append(f"| {kind} | {dim} | {method} | " + " | ".join(cells) + tail)
    return "\n".join(text), rows


def _progress(i: int, n: int, case: dict) -> str:
    reached = case["trials_to"][str(1e-6)]
    return (f"[{i}/{n}] {case['peak']} D={case['dim']} {case['method']} seed={case['seed']}: "
            f"1e-6 at {reached} trials, final gap {case['final_gap']:.1e}")  # fmt: skip


def main(argv: Sequence[str] | None = None) -> None:
    from argtypes import Distinct, nonnegative_int, positive_int, report_path

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--peaks", nargs="+", action=Distinct, default=list(PEAKS), choices=PEAKS)
    parser.add_argument("--dims", type=positive_int, nargs="+", action=Distinct, default=list(DIMS))
    parser.add_argument(
        "--methods", nargs="+", action=Distinct, default=list(METHODS), choices=METHODS
    )
    parser.add_argument("--seeds", type=positive_int, default=SEEDS, help="seeds 0 … N−1")
    parser.add_argument(
        "--workers", type=nonnegative_int, default=2, help="processes (0: this one)"
    )
    parser.add_argument(
        "--json", type=report_path, default=ROOT / "docs" / "figures" / "precision.json"
    )
    args = parser.parse_args(argv)
    tasks = [(k, d, m, s) for k in args.peaks for d in args.dims for m in args.methods
             for s in range(args.seeds)]  # fmt: skip
    # One torch thread a process, the peers imported before any case is timed.
    cases, wall = run_tasks(run_case, tasks, args.workers, _progress)
    table, rows = summarise(cases)
    print(table)
    print(f"wall time {wall:.1f} s on {max(args.workers, 1)} process(es)")
    report = {"config": {"peaks": args.peaks, "dims": args.dims, "methods": args.methods,
                         "seeds": args.seeds, "budgets": BUDGET, "accuracies": ACCURACIES},
              "wall_seconds": round(wall, 1), "summary": rows, "cases": cases}  # fmt: skip
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()

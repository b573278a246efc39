"""How many of the viapoint task's 8 routes does each method cover, at 300 and 1000 trials?
DIPOLE against two quality-diversity peers from pyribs, which are handed the route as an
oracle behaviour descriptor.

    python benchmarks/bench_viapoint_qd.py                    # 10 seeds, 300 and 1000 trials
    python benchmarks/bench_viapoint_qd.py --seeds 2 --methods DIPOLE --json /tmp/qd.json
    python benchmarks/bench_viapoint_qd.py --methods "DIPOLE (coverage)" --keep-others
    python benchmarks/bench_viapoint_qd.py --methods "DIPOLE (converge only)" --json /tmp/q.json

**Task**: ``configs/task/viapoint.yaml`` (the simulated Barrett WAM, D = 9, 2 alternative
viapoints at each of 3 pass times: 8 routes of return 1), as in
``reproduce_viapoint.py``. A *route* is the alternative nearest to the arm's path at each
pass time (``ViapointTask.route``).

**Covered**: a run covers a route at level r when one of the solutions it returns takes
that route with return ≥ r (r = 0.9, the paper's count, and 0.95). Returned solutions:

* **DIPOLE**: as ``train.py task=viapoint`` runs it: the library's defaults
  (``configs/algo/dipole.yaml``, no reward range, n0 = 30) until trial 300, the task's
  default budget, and the coverage options from then on (``coverage_from=300``,
  ``configs/task_algo/viapoint_dipole.yaml``). Returned: the final policy means, evaluated
  without exploration noise as in ``reproduce_viapoint.py`` (these evaluations are not
  charged). DIPOLE is never told routes: it sees returns only.
* **DIPOLE (coverage)**: the same with the options a user sets to cover alternatives rather
  than converge on each (``configs/algo/dipole_coverage.yaml``: ``accept_unjudged=True``,
  ``max_sampled=None``, ``unjudged_share=0.5``).
* **DIPOLE (converge only)** (opt-in): the library's defaults throughout
  (``algo.optimizer.coverage_from=null``), as ``Dipole(...)`` without options runs.
* **MAP-Elites** and **CMA-MAE** (pyribs 0.12): the elites of an archive with one cell per
  route, **the route given as the behaviour descriptor: an oracle** that DIPOLE does not
  get (it would not exist for a task whose alternatives are unknown). The elites are
  evaluated solutions, charged like any trial.

  * MAP-Elites: ``GaussianEmitter`` (σ = 0.02 m on every coordinate, from θ0 until the
    archive holds an elite), 2 emitters of 10 solutions an iteration.
  * CMA-MAE (Fontaine & Nikolaidis 2023): 2 ``EvolutionStrategyEmitter`` (CMA-ES, σ0 =
    Σ_start's std 0.05 m, ranker ``"imp"``, ``selection_rule="mu"``, restarts ``"basic"``)
    of 10 solutions each on an archive with ``learning_rate = 0.01`` and
    ``threshold_min = 0``; the routes are counted in a separate result archive of the
    best solution per route, as the algorithm prescribes.

Both budgets come from one run per (method, seed): the state after the last batch that fits
the budget (the peers' batches of 20 fit both exactly). Work is spread over ``--workers``
processes (spawned, one torch thread each), one task per (method, seed). Printed: per method
and budget, the routes a run covers at 0.9 and 0.95 (mean ± std over seeds), the routes
covered over all seeds, and the best return. Everything goes to ``--json`` (default
``docs/figures/viapoint_qd.json``).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from collections.abc import Sequence
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))  # (lockstep, reproduce_viapoint)

ROOT = Path(__file__).resolve().parents[1]
# (Appended, not inserted: the peers' seeds derive from their index.)
METHODS = ("DIPOLE", "MAP-Elites", "CMA-MAE", "DIPOLE (coverage)")
# Run when asked for (--methods): the library's defaults without the task's coverage_from
# (docs: Precision and coverage).
OPT_IN = ("DIPOLE (converge only)",)
# DIPOLE's rows: the config (configs/algo/<name>.yaml, as train.py's task=viapoint
# algo=<name>, with configs/task_algo/viapoint_<name>.yaml where there is one) and its
# overrides.
CONFIGS = {
    "DIPOLE": ("dipole", ()),
    "DIPOLE (coverage)": ("dipole_coverage", ()),
    "DIPOLE (converge only)": ("dipole", ("algo.optimizer.coverage_from=null",)),
}
# The tables' order.
SHOWN = ("DIPOLE", "DIPOLE (coverage)", "DIPOLE (converge only)", "MAP-Elites", "CMA-MAE")
BUDGETS = (300, 1000)
LEVELS = (0.9, 0.95)
SEEDS = 10
QD_BATCH = 10  # solutions per pyribs emitter and iteration
QD_EMITTERS = 2
MAP_ELITES_SIGMA = 0.02  # m
CMA_MAE_LEARNING_RATE = 0.01


def _task():
    from lockstep import load_task

    task, _, n0 = load_task("viapoint")
    return task, n0


def _routes(task, theta: torch.Tensor) -> tuple[list[tuple[int, ...]], list[float]]:
    """The route and the return of each row of ``theta [n, 9]`` (no exploration noise)."""
    with torch.no_grad():
        path = task.trajectory(theta.to(task.dtype))
        routes = task.viapoint_distances(path).argmin(-1).tolist()
        rewards = task.reward(path).double().tolist()
    return [tuple(r) for r in routes], rewards


def _covered(routes, rewards) -> dict[str, float]:
    """Route (as a string) -> the best return among the solutions taking it."""
    best: dict[str, float] = {}
    for route, r in zip(routes, rewards, strict=True):
        key = str(list(route))
        best[key] = max(best.get(key, -np.inf), r)
    return best


def run_dipole(
    seed: int, budgets: Sequence[int], name: str = "dipole", overrides: tuple[str, ...] = ()
) -> dict[int, dict]:
    from reproduce_viapoint import make_optimizer

    task, n0 = _task()
    opt = make_optimizer("DIPOLE", task, n0, seed, name=name, overrides=overrides)
    snapshots = {}
    top = budgets[-1]
    while True:
        theta = opt.ask()
        if opt.trials + theta.shape[0] > top:
            break
        opt.tell(theta, task.evaluate(theta.to(task.dtype)).to(theta.dtype))
        for b in budgets:
            if opt.trials <= b:
                snapshots[b] = (opt.policy_means.clone(), opt.trials, opt.best()[1])
    out = {}
    for b in budgets:
        if b not in snapshots:
            raise ValueError(f"budget {b} is below DIPOLE's first batch of {n0} trials")
        means, trials, best = snapshots[b]
        routes, rewards = _routes(task, means)
        out[b] = {"trials": trials, "returned": len(routes), "routes": _covered(routes, rewards),
                  "best_sample": best}  # fmt: skip
    return out


def _grid_archive(task, seed: int, **kwargs):
    from ribs.archives import GridArchive

    return GridArchive(
        solution_dim=task.theta0.numel(),
        dims=list(task.num_alternatives),
        ranges=[(-0.5, a - 0.5) for a in task.num_alternatives],
        seed=seed,
        **kwargs,
    )


def run_qd(method: str, seed: int, budgets: Sequence[int]) -> dict[int, dict]:
    from ribs.emitters import EvolutionStrategyEmitter, GaussianEmitter
    from ribs.schedulers import Scheduler

    task, _ = _task()
    x0 = task.theta0.double().numpy()
    sigma0 = float(task.sigma_start.diagonal().sqrt().max())
    rng = np.random.SeedSequence([seed, METHODS.index(method)]).generate_state(QD_EMITTERS + 2)
    if method == "MAP-Elites":
        archive = _grid_archive(task, int(rng[0]))
        result = None
        emitters = [
            GaussianEmitter(
                archive, sigma=MAP_ELITES_SIGMA, x0=x0, batch_size=QD_BATCH, seed=int(rng[2 + i])
            )  # fmt: skip
            for i in range(QD_EMITTERS)
        ]
    else:
        archive = _grid_archive(
            task, int(rng[0]), learning_rate=CMA_MAE_LEARNING_RATE, threshold_min=0.0
        )
        result = _grid_archive(task, int(rng[1]))
        emitters = [
            EvolutionStrategyEmitter(
                archive,
                x0=x0,
                sigma0=sigma0,
                ranker="imp",
                selection_rule="mu",
                restart_rule="basic",
                batch_size=QD_BATCH,
                seed=int(rng[2 + i]),
            )  # fmt: skip
            for i in range(QD_EMITTERS)
        ]
    scheduler = Scheduler(archive, emitters, result_archive=result)
    counted = result if result is not None else archive
    used, best, out = 0, -np.inf, {}
    for b in budgets:
        while used + QD_BATCH * QD_EMITTERS <= b:
            solutions = scheduler.ask()
            theta = torch.as_tensor(solutions, dtype=task.dtype)
            routes, rewards = _routes(task, theta)
            scheduler.tell(np.asarray(rewards), np.asarray(routes, dtype=float))
            used += len(solutions)
            best = max(best, max(rewards))
        elites = counted.data(["solution", "objective"])
        theta = torch.as_tensor(elites["solution"], dtype=task.dtype).reshape(-1, x0.size)
        routes, rewards = _routes(task, theta)
        out[b] = {"trials": used, "returned": len(routes), "routes": _covered(routes, rewards),
                  "best_sample": best}  # fmt: skip
    return out


def run_case(method: str, seed: int, budgets: Sequence[int]) -> dict:
    """One run of ``method`` with ``seed`` up to the largest budget; per budget the routes
    its returned solutions take (route -> best return), their number and the trials used."""
    budgets = sorted({int(b) for b in budgets})
    start = time.perf_counter()
    if method in CONFIGS:
        per_budget = run_dipole(seed, budgets, *CONFIGS[method])
    else:
        per_budget = run_qd(method, seed, budgets)
    for b, v in per_budget.items():
        if v["trials"] > b:
            raise AssertionError(f"{method} used {v['trials']} trials for budget {b}")
    return {
        "method": method,
        "seed": seed,
        "budgets": {str(b): v for b, v in per_budget.items()},
        "seconds": round(time.perf_counter() - start, 2),
    }


def _worker(args: tuple) -> dict:
    torch.set_num_threads(1)
    method, seed, budgets = args
    try:
        return run_case(method, seed, budgets)
    except Exception as error:  # reported in the table and the JSON
        return {"method": method, "seed": seed, "error": repr(error)}


def summarize(cases: list[dict], methods, budgets) -> tuple[str, dict]:
    summary: dict = {}
    lines = []
    header = ["method", *[f"@{b}: ≥{r} a run" for b in budgets for r in LEVELS],
              *[f"@{b}: ≥0.9 all runs" for b in budgets], "s"]  # fmt: skip
    rows = []
    for m in methods:
        ok = [c for c in cases if c["method"] == m and "error" not in c]
        summary[m] = {"runs": len(ok), "errors": sum(c["method"] == m for c in cases) - len(ok)}
        row = [m]
        union_cells = []
        for b in budgets:
            runs = [c["budgets"][str(b)] for c in ok]
            per_level = {}
            for r in LEVELS:
                counts = [sum(v >= r for v in run["routes"].values()) for run in runs]
                per_level[str(r)] = [float(np.mean(counts)), float(np.std(counts))]
                row.append(f"{np.mean(counts):.1f} ± {np.std(counts):.1f}")
            union = sorted({k for run in runs for k, v in run["routes"].items() if v >= LEVELS[0]})
            union_cells.append(str(len(union)))
            summary[m][str(b)] = {
                "routes_per_run": per_level,
                "routes_over_runs": union,
                "best_sample": float(np.mean([run["best_sample"] for run in runs])),
            }
        row += union_cells
        row.append(f"{sum(c.get('seconds', 0.0) for c in ok):.0f}")
        rows.append(row)
    from bench_multioptima import _table

    lines.append(_table(header, rows))
    return "\n".join(lines), summary


def main(argv: Sequence[str] | None = None) -> None:
    from argtypes import Distinct, nonnegative_int, positive_int, report_path

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=positive_int, default=SEEDS, help="seeds 0 … N−1")
    parser.add_argument(
        "--budgets", type=positive_int, nargs="+", action=Distinct, default=list(BUDGETS)
    )
    parser.add_argument(
        "--methods", nargs="+", action=Distinct, default=list(METHODS), choices=METHODS + OPT_IN
    )
    parser.add_argument(
        "--workers", type=nonnegative_int, default=2, help="processes (0: this one)"
    )
    parser.add_argument(
        "--json", type=report_path, default=ROOT / "docs" / "figures" / "viapoint_qd.json"
    )
    from bench_multioptima import add_keep_others, run_keeping_others
    from setting import machine, version

    add_keep_others(parser)
    args = parser.parse_args(argv)
    budgets = sorted(set(args.budgets))
    methods = [m for m in SHOWN if m in args.methods]
    if any(m in CONFIGS for m in methods):  # DIPOLE's first batch is the task's n0 trials
        from lockstep import compose_config

        n0 = int(compose_config("task=viapoint", "device=cpu").task.n0)
        if budgets[0] < n0:
            parser.error(f"--budgets: {budgets[0]} is below DIPOLE's first batch of {n0} trials")

    tasks = [(m, s, budgets) for m in methods for s in range(args.seeds)]

    def progress(i: int, n: int, case: dict) -> str:
        tag = f"[{i}/{n}] {case['method']} seed={case['seed']}"
        if "error" in case:
            return f"{tag}: ERROR {case['error']}"
        found = ", ".join(
            f"{sum(v >= LEVELS[0] for v in r['routes'].values())} @{b}"
            for b, r in case["budgets"].items()
        )
        return f"{tag}: {found} routes ≥ {LEVELS[0]} ({case['seconds']:.0f} s)"

    grid = {"seeds": args.seeds, "budgets": budgets, "levels": list(LEVELS)}
    cases, wall, methods = run_keeping_others(_worker, tasks, args, grid, methods, SHOWN, progress)
    order = {m: i for i, m in enumerate(SHOWN)}
    cases.sort(key=lambda c: (order[c["method"]], c["seed"]))
    text, summary = summarize(cases, methods, budgets)
    print(text)
    print(f"wall time {wall:.1f} s on {max(args.workers, 1)} process(es)")
    versions = {package: version(package) for package in ("torch", "ribs")}
    report = {
        "config": {"seeds": args.seeds, "budgets": budgets, "methods": methods,
                   "levels": list(LEVELS), "versions": versions, "machine": machine(),
                   "qd_batch": QD_BATCH, "qd_emitters": QD_EMITTERS,
                   "map_elites_sigma": MAP_ELITES_SIGMA,
                   "cma_mae_learning_rate": CMA_MAE_LEARNING_RATE},
        "wall_seconds": round(wall, 1),
        "summary": summary,
        "cases": cases,
    }  # fmt: skip
    args.json.parent.mkdir(parents=True, exist_ok=True)
    args.json.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {args.json}")


if __name__ == "__main__":
    main()

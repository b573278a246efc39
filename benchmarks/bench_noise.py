"""Noisy returns: how many of k equally good optima each method finds when every return
carries Gaussian noise, on ``bench_multioptima``'s generated landscapes.

    python benchmarks/bench_noise.py                         # D = 2 and 5, 4 noise levels
    python benchmarks/bench_noise.py --dims 2 --noise 0 0.03 --json /tmp/noise.json   # a look

**Noise.** A told return is f(θ) + s·h·ε, ε ~ N(0, 1) from the case's own generator, h the
landscape's height (its value range): s = 1 % is a noise one tenth of what "found" allows
below the top, s = 10 % ten times it. "Found" is judged on the noise-free f, as in
``bench_multioptima`` (within 0.1 of the peak's width, within 0.01·h of its top).

**Methods**, each from ``bench_multioptima``'s runners and setups, the same trial budget
(every evaluation counts, repeated ones too):

* **DIPOLE**: the defaults (``best_evaluations=1``: every return trusted as told).
* **DIPOLE (best ×2)**, **DIPOLE (best ×4)**: ``best_evaluations=2`` / ``4``: a sampled
  policy's best kept sample is evaluated again at each ask until it has that many returns,
  and keeps their mean.
* **DIPOLE (mean of 4)**: what a user can do without the option: evaluate every θ four
  times and tell the mean (a quarter of the asks in the budget).
* **IPOP-CMA-ES** and **NMMSO**: as in ``bench_multioptima`` (pycma's restarts at 1e-3·σ0,
  pynmmso's defaults), each returning what it returns there (every restart's best evaluated
  point, chosen on noisy returns; every swarm's mode).
* **UH-IPOP-CMA-ES**: the same restarts with pycma's own noise handling (``NoiseHandler``,
  Hansen et al. 2009's uncertainty handling: it re-evaluates a few solutions each iteration,
  measures the rank changes and raises σ and the evaluations a solution gets, up to 30),
  every evaluation counted; returned: each restart's final mean (pycma's ``xfavorite``, its
  estimate under noise), the running one's included.

Printed: per dimension, optima found summed over the landscapes (k = 2, 4, 8; 6 seeds) at
each noise level, and the returned solutions. Everything goes to ``--json`` (default
``docs/figures/noise.json``).

``--best-gap`` measures something else on the same cases (noise above 0 only; no JSON):
DIPOLE with ``best_evaluations=4``, and how far the return that ``best()`` reports lies above
the noise-free value at its θ, against the best single return told (the luckiest), as
fractions of h: median and maximum over the landscapes, per dimension and noise level.
"""

from __future__ import annotations

import argparse
import statistics
import sys
from collections.abc import Callable, Sequence
from pathlib import Path

import torch
from torch import Tensor

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(Path(__file__).resolve().parent))

from bench_multioptima import (  # noqa: E402
    DTYPE,
    Landscape,
    _global_rngs,
    _run_ask_tell,
    _start,
    case_seeds,
    grid_error,
    ipop_restart,
    make_landscape,
    run_dipole,
    run_ipop_cmaes,
    run_nmmso,
    run_tasks,
    run_timed,
    write_report,
)

from dipole_torch import Dipole  # noqa: E402

DIMS = (2, 5)
KS = (2, 4, 8)
SEEDS = 6
BUDGET = 2000
NOISE = (0.0, 0.01, 0.03, 0.1)
REPEATS = 4  # evaluations averaged by "DIPOLE (mean of 4)"


class NoisyLandscape:
    """``landscape`` whose returns carry noise of std ``noise``·h, averaged over ``repeats``
    evaluations a θ; the box and the dimension of the landscape."""

    def __init__(self, landscape: Landscape, noise: float, seed: int, repeats: int = 1):
        self.landscape = landscape
        self.noise = noise * landscape.height
        self.repeats = repeats
        self.generator = torch.Generator().manual_seed(seed)
        self.lower, self.upper, self.dim = landscape.lower, landscape.upper, landscape.dim

    def __call__(self, theta: Tensor) -> Tensor:
        value = self.landscape(theta)
        shape = (self.repeats, *value.shape)
        noise = torch.randn(shape, generator=self.generator, dtype=value.dtype).mean(0)
        return value + self.noise * noise


class _BudgetSpent(Exception):
    pass


def run_uh_ipop_cmaes(problem, budgets: Sequence[int], seed: int):
    """IPOP-CMA-ES with pycma's ``NoiseHandler`` (UH-CMA-ES) on ``problem``'s box, until
    ``budgets[-1]`` evaluations (one budget: the snapshot is the end). Returned: each
    restart's final mean."""
    import warnings

    import cma
    import numpy as np

    (budget,) = budgets
    d = problem.dim
    rng = np.random.default_rng(seed)
    used = 0

    def f(x) -> float:  # one evaluation, negated (pycma minimises)
        nonlocal used
        if used >= budget:
            raise _BudgetSpent
        used += 1
        return -float(problem(torch.as_tensor(np.asarray(x)[None, :d], dtype=DTYPE))[0])

    means: list[np.ndarray] = []
    with _global_rngs(seed), warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for restart in range(10**6):
            es = ipop_restart(problem, restart, rng)
            noise = cma.NoiseHandler(es.N, maxevals=[1, 1, 30])
            try:
                while not es.stop():
                    solutions, fit = es.ask_and_eval(f, evaluations=noise.evaluations)
                    es.tell(solutions, fit)
                    es.sigma *= noise(solutions, fit, f, es.ask)
            except _BudgetSpent:
                means.append(np.array(es.result.xfavorite)[:d])
                break
            means.append(np.array(es.result.xfavorite)[:d])
    return {budget: (torch.as_tensor(np.array(means), dtype=DTYPE).reshape(-1, d), budget)}


def _dipole(**options) -> Callable:
    return lambda problem, budgets, seed: run_dipole(problem, budgets, seed, **options)


# method -> (runner, evaluations a told θ)
METHODS: dict[str, tuple[Callable, int]] = {
    "DIPOLE": (_dipole(), 1),
    "DIPOLE (best ×2)": (_dipole(best_evaluations=2), 1),
    "DIPOLE (best ×4)": (_dipole(best_evaluations=4), 1),
    "DIPOLE (mean of 4)": (_dipole(), REPEATS),
    "IPOP-CMA-ES": (run_ipop_cmaes, 1),
    "UH-IPOP-CMA-ES": (run_uh_ipop_cmaes, 1),
    "NMMSO": (run_nmmso, 1),
}


def run_case(dim: int, k: int, seed: int, noise: float, method: str, budget: int) -> dict:
    """One (landscape, noise level, method): optima found on the noise-free landscape."""
    landscape_seed, method_seed = case_seeds(dim, k, seed)
    landscape = make_landscape(dim, k, landscape_seed)
    runner, repeats = METHODS[method]
    problem = NoisyLandscape(landscape, noise, 1000 + method_seed, repeats)
    asks = budget // repeats
    snapshots, seconds = run_timed(runner, problem, [asks], method_seed, method)
    solutions, _ = snapshots[asks]
    return {
        "dim": dim,
        "k": k,
        "seed": seed,
        "noise": noise,
        "method": method,
        "found": int(landscape.found(solutions).sum()),
        "returned": int(solutions.shape[0]),
        "seconds": round(seconds, 3),
    }


def _task(args: tuple) -> dict:
    try:
        return run_case(*args)
    except Exception as error:  # reported in the table and the JSON
        dim, k, seed, noise, method, _ = args
        keys = {"dim": dim, "k": k, "seed": seed, "noise": noise, "method": method}
        return keys | {"error": repr(error)}


def _progress(i: int, n: int, case: dict) -> str:
    tag = f"[{i}/{n}] D={case['dim']} k={case['k']} seed={case['seed']} noise={case['noise']}"
    if "error" in case:
        return f"{tag} {case['method']}: ERROR {case['error']}"
    return f"{tag} {case['method']}: {case['found']}/{case['k']} ({case['seconds']:.1f} s)"


def _gap_progress(i: int, n: int, case: dict) -> str:
    tag = f"[{i}/{n}] D={case['dim']} k={case['k']} seed={case['seed']} noise={case['noise']}"
    return f"{tag}: best() +{case['best']:.4f}, told +{case['told']:.4f}"


def summarize(cases: list[dict], config: dict) -> tuple[str, dict]:
    """Per dimension, a table of optima found (summed) by method and noise level."""
    lines, summary = [], {}
    noises, methods = config["noise"], config["methods"]
    for dim in config["dims"]:
        total = config["seeds"] * sum(config["ks"])
        header = ["method"] + [f"noise {100 * s:g} %" for s in noises] + ["returned"]
        rows = []
        for method in methods:
            cells, returned = [], 0
            for noise in noises:
                mine = [
                    c for c in cases
                    if c["dim"] == dim and c["method"] == method and c["noise"] == noise
                ]  # fmt: skip
                errors = sum("error" in c for c in mine)
                found = sum(c.get("found", 0) for c in mine)
                returned += sum(c.get("returned", 0) for c in mine)
                cells.append(f"{found}/{total}" + (f" ({errors} errors)" if errors else ""))
                summary[f"D={dim} {method} noise={noise}"] = found
            rows.append([method, *cells, str(returned)])
        widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]
        lines.append(f"D = {dim}, {config['budget']} trials, optima found (k = "
                     f"{config['ks']}, {config['seeds']} seeds)")  # fmt: skip
        for row in [header, *rows]:
            lines.append("  ".join(cell.ljust(w) for cell, w in zip(row, widths, strict=True)))
        lines.append("")
    return "\n".join(lines), summary


def best_gap(dim: int, k: int, seed: int, noise: float, budget: int) -> dict:
    """One run of DIPOLE with ``best_evaluations=REPEATS`` on a noisy landscape: how far
    ``best()``'s return and the best single return told lie above the noise-free value at
    their θ, as fractions of the landscape's height."""
    landscape_seed, method_seed = case_seeds(dim, k, seed)
    landscape = make_landscape(dim, k, landscape_seed)
    problem = NoisyLandscape(landscape, noise, 1000 + method_seed)
    theta0, sigma_start, bounds = _start(landscape)
    generator = torch.Generator().manual_seed(method_seed)
    opt = Dipole(theta0, sigma_start, bounds=bounds, generator=generator,
                 best_evaluations=REPEATS)  # fmt: skip
    _run_ask_tell(opt, problem, [budget])
    reported_theta, reported = opt.best()
    state = opt.state_dict()  # (the best single return told, as best() reports it without)
    told_theta, told = state["best_theta"], state["best_reward"]

    def above(theta: Tensor, value: float) -> float:
        return (value - float(landscape(theta[None])[0])) / landscape.height

    return {"dim": dim, "k": k, "seed": seed, "noise": noise,
            "best": above(reported_theta, reported), "told": above(told_theta, told)}  # fmt: skip


def _gap_task(args: tuple) -> dict:
    return best_gap(*args)


def gap_table(cases: list[dict], dims: Sequence[int], noises: Sequence[float]) -> str:
    """Per dimension and noise level: median and maximum of both gaps."""
    lines = [f"best() with best_evaluations={REPEATS}, above the noise-free value at its θ, "
             "against the best single return told (fractions of h; median / max)"]  # fmt: skip
    for dim in dims:
        for noise in noises:
            mine = [c for c in cases if c["dim"] == dim and c["noise"] == noise]
            best, told = [c["best"] for c in mine], [c["told"] for c in mine]
            lines.append(
                f"  D = {dim}, noise {100 * noise:g} %: best() {statistics.median(best):.4f} / "
                f"{max(best):.4f}, told {statistics.median(told):.4f} / {max(told):.4f} "
                f"({len(mine)} runs)"
            )
    return "\n".join(lines)


def main(argv: Sequence[str] | None = None) -> None:
    from argtypes import (
        Distinct,
        nonnegative_float,
        nonnegative_int,
        positive_even_int,
        positive_int,
        report_path,
    )

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dims", type=positive_int, nargs="+", action=Distinct, default=list(DIMS))
    parser.add_argument(
        "--ks", type=positive_even_int, nargs="+", action=Distinct, default=list(KS)
    )
    parser.add_argument(
        "--seeds", type=positive_int, default=SEEDS, help="seeds 0 … N−1 per (D, k)"
    )
    parser.add_argument("--budget", type=positive_int, default=BUDGET)
    parser.add_argument("--noise", type=nonnegative_float, nargs="+", action=Distinct,
                        default=list(NOISE),
                        help="noise std as a fraction of the landscape's height")  # fmt: skip
    parser.add_argument(
        "--methods", nargs="+", action=Distinct, default=list(METHODS), choices=list(METHODS)
    )
    parser.add_argument(
        "--workers", type=nonnegative_int, default=2, help="processes (0: this one)"
    )
    parser.add_argument(
        "--json", type=report_path, default=ROOT / "docs" / "figures" / "noise.json"
    )
    parser.add_argument("--best-gap", action="store_true",
                        help="how far best()'s return lies above the truth (no JSON)")  # fmt: skip
    args = parser.parse_args(argv)
    if (error := grid_error(args.dims, args.ks)) is not None:
        parser.error(f"argument --ks: {error}")
    if args.best_gap:
        default_json = ROOT / "docs" / "figures" / "noise.json"
        if args.methods != list(METHODS) or args.json != default_json:
            parser.error("--best-gap runs DIPOLE alone and writes no JSON: drop --methods, --json")
        noises = [s for s in args.noise if s > 0]
        if not noises:
            parser.error("--best-gap measures noisy returns: give a --noise above 0")
        tasks = [(dim, k, seed, noise, args.budget)
                 for dim in args.dims for noise in noises
                 for k in args.ks for seed in range(args.seeds)]  # fmt: skip
        cases, _ = run_tasks(_gap_task, tasks, args.workers, _gap_progress)
        print(gap_table(cases, args.dims, noises))
        return
    methods = [m for m in METHODS if m in args.methods]
    tasks = [
        (dim, k, seed, noise, method, args.budget)
        for dim in sorted(args.dims, reverse=True)  # the slow ones first
        for method in methods
        for noise in args.noise
        for k in args.ks
        for seed in range(args.seeds)
    ]
    config = {
        "dims": args.dims, "ks": args.ks, "seeds": args.seeds, "budget": args.budget,
        "noise": args.noise, "methods": methods,
    }  # fmt: skip
    cases, wall = run_tasks(_task, tasks, args.workers, _progress)
    text, summary = summarize(cases, config)
    print(text)
    order = {m: i for i, m in enumerate(methods)}
    cases.sort(key=lambda c: (c["dim"], order[c["method"]], c["noise"], c["k"], c["seed"]))
    write_report(args.json, config, wall, summary, cases)


if __name__ == "__main__":
    main()

"""How many global optima of the CEC 2013 niching functions does each method find at equal
trials? DIPOLE against IPOP-CMA-ES, NMMSO and random search, in one run.

    python benchmarks/bench_niching.py                          # 10 functions, 4 seeds, 2 processes
    python benchmarks/bench_niching.py --functions 2 4 7 --seeds 2 --budgets 2000 \\
        --json /tmp/niching.json                                 # a quick look
    python benchmarks/bench_niching.py --methods DIPOLE --keep-others   # DIPOLE's rows anew
    python benchmarks/bench_niching.py --suite more     # six functions of other kinds

**Functions** (``FUNCTIONS``): F1–F10 of the CEC 2013 competition on niching methods
(Li, Engelbrecht & Epitropakis 2013, "Benchmark functions for CEC'2013 special session and
competition on niching methods for multimodal function optimization"), maximised on their
boxes: five-uneven-peak trap (1-D, 2 global optima on the box's ends), equal maxima (1-D, 5),
uneven decreasing maxima (1-D, 1), Himmelblau (2-D, 4), six-hump camel back (2-D, 2),
Shubert (2-D, 18 among 760 local optima; 3-D, 81), Vincent (2-D, 36 of widths that shrink
towards the box's corner; 3-D, 216) and the modified Rastrigin (2-D, 12). These are the
functions of the report whose optima are known in closed form (F11–F20 are compositions).
The generated landscapes of ``bench_multioptima.py`` are the development benchmark; these are
a check on functions the library was not tuned on.

**More functions** (``--suite more``, ``MORE_FUNCTIONS``, report
``docs/figures/niching_more.json``): six of kinds F1–F10 lack, counted the same way:
Branin (2-D, 3 optima), F2's peaks along both axes (2-D, 25), two Himmelblau functions side
by side (4-D, 16), Cauchy peaks of several widths (5-D, 7), the lowest of rotated quadratic
bowls of condition number 100 (10-D, 8) and of cones of several slopes (20-D, 6).

**Found** (the competition's own count, ``how_many_goptima``): the returned solutions, sorted
by value, best first, become seeds unless within the function's radius ρ of an earlier seed;
a seed within ``accuracy`` of the global optimum's value f* finds one optimum (at most the
number of global optima). Reported at the competition's accuracy levels 1e-1 … 1e-4.

**Methods**, each with the same trial budget (one trial = one evaluation), starting from what
it is given on an unknown function in its box [l, u]:

* **DIPOLE**: ``Dipole(θ0 = (l + u)/2, Σ_start = diag(((u − l)/4)²), bounds=(l, u))``, the
  library's defaults otherwise (no reward range). Returned: its final policy means (retired
  ones included). Its samples are clipped into the box (the functions are defined there
  only: F1 and Vincent rise beyond it).
* **IPOP-CMA-ES** and **NMMSO**: ``bench_multioptima``'s runners on the box (pycma with its
  bounds, sigma0 a quarter of the widest side and ``CMA_stds`` for the others, restarts at
  1e-3·sigma0, population doubled at each restart; pynmmso with its defaults). Returned:
  every restart's best; NMMSO's modes. pycma does not support 1-D optimization (it warns
  that it "may bail or work poorly"), so on F1–F3 it searches a second coordinate that the
  function ignores.
* **random search**: uniform samples in the box. Returned: all of them (the count's seeding
  does the niching, so random search is credited with every optimum its archive touches).

Both budgets come from one run per (function, method, seed), snapshotted as in
``bench_multioptima.py``. The competition's own budgets are 5·10⁴–4·10⁵ trials; the defaults
here (2000 and 10 000) are those of a policy search, where a trial is a rollout.

Printed: per accuracy level, optima found summed over seeds ("found/total") for each function
and budget, and each method's time. Everything, with per-run results, goes to ``--json``
(default ``docs/figures/niching.json``).
"""

from __future__ import annotations

import argparse
import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from pathlib import Path

import bench_multioptima as peers  # the peers' runners and helpers (this script's folder)
import torch
from torch import Tensor

ROOT = Path(__file__).resolve().parents[1]
DTYPE = torch.float64
METHODS = ("DIPOLE", "IPOP-CMA-ES", "NMMSO", "random search")
ACCURACIES = (1e-1, 1e-2, 1e-3, 1e-4)
BUDGETS = (2000, 10000)
SEEDS = 4


# ---------------------------------------------------------------------------------- functions
def five_uneven_peak_trap(x: Tensor) -> Tensor:
    x = x[:, 0]
    pieces = (
        (2.5, 80.0 * (2.5 - x)),
        (5.0, 64.0 * (x - 2.5)),
        (7.5, 64.0 * (7.5 - x)),
        (12.5, 28.0 * (x - 7.5)),
        (17.5, 28.0 * (17.5 - x)),
        (22.5, 32.0 * (x - 17.5)),
        (27.5, 32.0 * (27.5 - x)),
    )
    out = 80.0 * (x - 27.5)  # on [27.5, 30]
    for end, value in reversed(pieces):
        out = torch.where(x < end, value, out)
    return out


def equal_maxima(x: Tensor) -> Tensor:
    return torch.sin(5.0 * math.pi * x[:, 0]).pow(6)


def uneven_decreasing_maxima(x: Tensor) -> Tensor:
    x = x[:, 0]
    envelope = torch.exp(-2.0 * math.log(2.0) * ((x - 0.08) / 0.854).square())
    return envelope * torch.sin(5.0 * math.pi * (x.pow(0.75) - 0.05)).pow(6)


def himmelblau(x: Tensor) -> Tensor:
    a, b = x[:, 0], x[:, 1]
    return 200.0 - (a.square() + b - 11.0).square() - (a + b.square() - 7.0).square()


def six_hump_camel_back(x: Tensor) -> Tensor:
    a, b = x[:, 0], x[:, 1]
    a2, b2 = a.square(), b.square()
    return -((4.0 - 2.1 * a2 + a2.square() / 3.0) * a2 + a * b + (4.0 * b2 - 4.0) * b2)


def shubert(x: Tensor) -> Tensor:
    j = torch.arange(1, 6, dtype=x.dtype, device=x.device)
    return -(j * torch.cos((j + 1.0) * x[..., None] + j)).sum(-1).prod(-1)


def vincent(x: Tensor) -> Tensor:
    return torch.sin(10.0 * torch.log(x)).mean(-1)


def modified_rastrigin(x: Tensor) -> Tensor:
    k = torch.tensor([3.0, 4.0], dtype=x.dtype, device=x.device)
    return -(10.0 + 9.0 * torch.cos(2.0 * math.pi * k * x)).sum(-1)


@dataclass(frozen=True)
class NichingFunction:
    """One competition function, maximised on the box [lower, upper].

    Attributes:
        name: the report's name with its number and dimension, e.g. ``"F7 Vincent 2D"``.
        fn: ``[B, D] -> [B]`` the function.
        lower, upper: ``[D]`` the box's corners.
        optima: the number of global optima.
        f_star: the global optima's value.
        radius: ρ, the count's niche radius.
    """

    name: str
    fn: Callable[[Tensor], Tensor]
    lower: Tensor
    upper: Tensor
    optima: int
    f_star: float
    radius: float

    @property
    def dim(self) -> int:
        return int(self.lower.shape[0])

    def __call__(self, theta: Tensor) -> Tensor:
        """``[B]`` float64 values at ``theta: [B, D]`` (inside the box)."""
        return self.fn(theta.to(DTYPE))

    def found(self, solutions: Tensor, accuracy: float) -> int:
        """Global optima found by ``solutions: [n, D]`` (the competition's count)."""
        x = solutions.to(DTYPE).reshape(-1, self.dim)
        values = self(x)
        order = torch.argsort(values, descending=True, stable=True)
        seeds = x.new_empty(x.shape[0], self.dim)
        n_seeds = count = 0
        for i in order.tolist():
            if self.f_star - float(values[i]) > accuracy:
                break  # sorted: no later solution is within the accuracy either
            if n_seeds and bool(((seeds[:n_seeds] - x[i]).norm(dim=-1) <= self.radius).any()):
                continue
            seeds[n_seeds] = x[i]
            n_seeds += 1
            if abs(float(values[i]) - self.f_star) <= accuracy:
                count += 1
                if count == self.optima:
                    break
        return count


def _box(lower: Sequence[float], upper: Sequence[float]) -> tuple[Tensor, Tensor]:
    return torch.tensor(lower, dtype=DTYPE), torch.tensor(upper, dtype=DTYPE)


FUNCTIONS = (
    NichingFunction("F1 five-uneven-peak trap 1D", five_uneven_peak_trap, *_box([0], [30]),
                    2, 200.0, 0.01),
    NichingFunction("F2 equal maxima 1D", equal_maxima, *_box([0], [1]), 5, 1.0, 0.01),
    NichingFunction("F3 uneven decreasing maxima 1D", uneven_decreasing_maxima,
                    *_box([0], [1]), 1, 1.0, 0.01),
    NichingFunction("F4 Himmelblau 2D", himmelblau, *_box([-6, -6], [6, 6]), 4, 200.0, 0.01),
    NichingFunction("F5 six-hump camel back 2D", six_hump_camel_back,
                    *_box([-1.9, -1.1], [1.9, 1.1]), 2, 1.031628453489877, 0.5),
    NichingFunction("F6 Shubert 2D", shubert, *_box([-10, -10], [10, 10]), 18,
                    186.7309088310239, 0.5),
    NichingFunction("F7 Vincent 2D", vincent, *_box([0.25, 0.25], [10, 10]), 36, 1.0, 0.2),
    NichingFunction("F8 Shubert 3D", shubert, *_box([-10] * 3, [10] * 3), 81,
                    2709.093505572820, 0.5),
    NichingFunction("F9 Vincent 3D", vincent, *_box([0.25] * 3, [10] * 3), 216, 1.0, 0.2),
    NichingFunction("F10 modified Rastrigin 2D", modified_rastrigin, *_box([0, 0], [1, 1]),
                    12, -2.0, 0.01),
)  # fmt: skip


# ------------------------------------------------------------------------- more functions
# ``--suite more``: six functions of kinds F1–F10 lack (higher dimensions, rotated
# ill-conditioned basins, cones, peaks of several widths), each with a known set of equally
# good global optima. The centres are drawn once, from a fixed seed.
def branin(x: Tensor) -> Tensor:
    """Branin's function, negated: 3 global optima on [−5, 10] × [0, 15]."""
    a, b = x[:, 0], x[:, 1]
    quadratic = (b - 5.1 / (4.0 * math.pi**2) * a.square() + 5.0 / math.pi * a - 6.0).square()
    return -(quadratic + 10.0 * (1.0 - 1.0 / (8.0 * math.pi)) * torch.cos(a) + 10.0)


def equal_maxima_2d(x: Tensor) -> Tensor:
    """F2's peaks along both axes: 25 global optima on [0, 1]²."""
    return torch.sin(5.0 * math.pi * x).pow(6).prod(-1)


def double_himmelblau(x: Tensor) -> Tensor:
    """Two Himmelblau functions on (x1, x2) and (x3, x4): 16 global optima on [−6, 6]⁴."""
    return himmelblau(x[:, :2]) + himmelblau(x[:, 2:])


_CENTRES = torch.Generator().manual_seed(12345)
_BOWL_CENTRES = torch.rand(8, 10, generator=_CENTRES, dtype=DTYPE) * 8.0 - 4.0
_ROTATION = torch.linalg.qr(torch.randn(10, 10, generator=_CENTRES, dtype=DTYPE))[0]
# Eigenvalues 0.1 … 10: a condition number of 100.
_BOWL_SHAPE = _ROTATION @ torch.diag(torch.logspace(0, 2, 10, dtype=DTYPE)) @ _ROTATION.T / 10.0
_CONE_CENTRES = torch.rand(6, 20, generator=_CENTRES, dtype=DTYPE) * 8.0 - 4.0
_CONE_SLOPES = torch.linspace(0.5, 2.0, 6, dtype=DTYPE)
_PEAK_CENTRES = torch.rand(7, 5, generator=_CENTRES, dtype=DTYPE) * 8.0 - 4.0
_PEAK_WIDTHS = torch.linspace(0.5, 2.0, 7, dtype=DTYPE)


def cauchy_peaks(x: Tensor) -> Tensor:
    """7 peaks 1 / (1 + |x − c|² / w²) of widths 0.5 … 2: 7 global optima on [−5, 5]⁵."""
    distance = (x[:, None, :] - _PEAK_CENTRES).square().sum(-1)
    return (1.0 / (1.0 + distance / _PEAK_WIDTHS.square())).amax(-1)


def rotated_bowls(x: Tensor) -> Tensor:
    """The lowest of 8 rotated quadratic bowls (condition number 100), negated: 8 global
    optima on [−5, 5]¹⁰."""
    d = x[:, None, :] - _BOWL_CENTRES
    return -torch.einsum("bkd,de,bke->bk", d, _BOWL_SHAPE, d).amin(-1)


def cones(x: Tensor) -> Tensor:
    """The lowest of 6 cones of slopes 0.5 … 2, negated: 6 global optima on [−5, 5]²⁰."""
    return -((x[:, None, :] - _CONE_CENTRES).norm(dim=-1) * _CONE_SLOPES).amin(-1)


MORE_FUNCTIONS = (
    NichingFunction("M1 Branin 2D", branin, *_box([-5, 0], [10, 15]), 3,
                    -0.39788735772973816, 0.5),
    NichingFunction("M2 equal maxima 2D", equal_maxima_2d, *_box([0, 0], [1, 1]), 25, 1.0, 0.05),
    NichingFunction("M3 double Himmelblau 4D", double_himmelblau, *_box([-6] * 4, [6] * 4), 16,
                    400.0, 0.5),
    NichingFunction("M4 Cauchy peaks 5D", cauchy_peaks, *_box([-5] * 5, [5] * 5), 7, 1.0, 0.5),
    NichingFunction("M5 rotated bowls 10D", rotated_bowls, *_box([-5] * 10, [5] * 10), 8, 0.0,
                    0.5),
    NichingFunction("M6 cones 20D", cones, *_box([-5] * 20, [5] * 20), 6, 0.0, 0.5),
)  # fmt: skip
SUITES = {"cec2013": FUNCTIONS, "more": MORE_FUNCTIONS}


# ------------------------------------------------------------------------------------ methods
def run_random_search(
    problem: NichingFunction, budgets: Sequence[int], seed: int
) -> peers.Snapshots:
    g = torch.Generator().manual_seed(seed)
    u = torch.rand(budgets[-1], problem.dim, generator=g, dtype=DTYPE)
    theta = problem.lower + (problem.upper - problem.lower) * u
    return {b: (theta[:b], b) for b in budgets}


RUNNERS: dict[str, Callable[[NichingFunction, Sequence[int], int], peers.Snapshots]] = {
    "DIPOLE": peers.run_dipole,
    "DIPOLE (all sweeps)": peers.run_dipole_all_sweeps,
    "DIPOLE (coverage)": peers.run_dipole_coverage,
    "DIPOLE (coverage from 300)": peers.run_dipole_coverage_from,
    "IPOP-CMA-ES": peers.run_ipop_cmaes,
    "NMMSO": peers.run_nmmso,
    "random search": run_random_search,
}


def run_case(
    number: int, seed: int, method: str, budgets: Sequence[int], suite: str = "cec2013"
) -> dict:
    """Run ``method`` on function ``number`` (from 1) of ``suite`` (``SUITES``: F1–F10, or
    the six ``MORE_FUNCTIONS``) with ``seed``, up to the largest budget.

    Returns:
        A JSON-ready dict with, per budget, ``found`` per accuracy level, ``returned``
        (solutions returned) and ``trials`` (trials used), and ``seconds``.
    """
    if suite not in SUITES:
        raise ValueError(f"suite must be one of {sorted(SUITES)}, got {suite!r}")
    functions = SUITES[suite]
    if not 1 <= number <= len(functions):
        raise ValueError(f"function number must lie in 1..{len(functions)}, got {number}")
    budgets = sorted({int(b) for b in budgets})
    if budgets[0] < 1:
        raise ValueError(f"budgets must be positive, got {budgets}")
    problem = functions[number - 1]
    method_seed = 1000 * number + seed
    snapshots, seconds = peers.run_timed(RUNNERS[method], problem, budgets, method_seed, method)
    results = {}
    for b in budgets:
        solutions, trials = snapshots[b]
        inside = (solutions >= problem.lower) & (solutions <= problem.upper)
        if not bool(inside.all()):
            raise AssertionError(f"{method} returned a solution outside the box")
        results[str(b)] = {
            "found": {str(a): problem.found(solutions, a) for a in ACCURACIES},
            "returned": int(solutions.shape[0]),
            "trials": int(trials),
        }
    return {
        "function": number,
        "name": problem.name,
        "optima": problem.optima,
        "seed": seed,
        "method": method,
        "method_seed": method_seed,
        "budgets": results,
        "seconds": round(seconds, 3),
    }


def _progress(i: int, n: int, case: dict) -> str:
    name = case.get("name", f"function {case['function']}")
    tag = f"[{i}/{n}] {name} seed={case['seed']} {case['method']}"
    if "error" in case:
        return f"{tag}: ERROR {case['error']}"
    found = ", ".join(f"{v['found'][str(1e-3)]} @{b}" for b, v in case["budgets"].items())
    return f"{tag}: {found} at 1e-3 ({case['seconds']:.1f} s)"


def _task(args: tuple) -> dict:
    number, seed, method, budgets, suite = args
    try:
        return run_case(number, seed, method, budgets, suite)
    except Exception as error:  # reported in the table and the JSON
        return {"function": number, "seed": seed, "method": method, "error": repr(error)}


# ------------------------------------------------------------------------------------ reports
def summarize(
    cases: list[dict], methods, numbers, budgets, functions=FUNCTIONS
) -> tuple[str, dict]:
    """The printed tables (one per accuracy level) and the JSON summary."""

    def cell(method: str, number: int, budget: int, accuracy: float) -> tuple[int, int, int]:
        runs = [c for c in cases if c["method"] == method and c["function"] == number]
        ok = [c for c in runs if "error" not in c]
        found = sum(c["budgets"][str(budget)]["found"][str(accuracy)] for c in ok)
        return found, functions[number - 1].optima * len(ok), len(runs) - len(ok)

    def text(found: int, total: int, errors: int) -> str:
        return f"{found}/{total}" + (f" ({errors} err)" if errors else "")

    columns = [(m, b) for b in budgets for m in methods]
    lines = []
    for accuracy in ACCURACIES:
        rows = [
            [functions[n - 1].name] + [text(*cell(m, n, b, accuracy)) for m, b in columns]
            for n in numbers
        ]
        totals = [sum(cell(m, n, b, accuracy)[0] for n in numbers) for m, b in columns]
        rows.append(["all (optima found)"] + [str(t) for t in totals])
        header = [f"accuracy {accuracy:g}", *[f"{m} @{b}" for m, b in columns]]
        lines += [peers._table(header, rows), ""]
    seconds = {m: round(sum(c.get("seconds", 0.0) for c in cases if c["method"] == m), 1)
               for m in methods}  # fmt: skip
    lines.append("time s (sum over runs): " + ", ".join(f"{m} {s}" for m, s in seconds.items()))
    summary = {
        m: {
            "seconds": seconds[m],
            "found": {
                str(a): {
                    str(b): {functions[n - 1].name: cell(m, n, b, a)[0] for n in numbers}
                    for b in budgets
                }
                for a in ACCURACIES
            },
        }
        for m in methods
    }
    return "\n".join(lines), summary


def main(argv: Sequence[str] | None = None) -> None:
    from argtypes import Distinct, nonnegative_int, positive_int, report_path

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--suite", choices=list(SUITES), default="cec2013",
        help="CEC 2013's F1-F10, or six functions of other kinds (MORE_FUNCTIONS)",
    )  # fmt: skip
    parser.add_argument(
        "--functions", type=int, nargs="+", action=Distinct, help="numbers from 1 (default: all)"
    )
    parser.add_argument(
        "--seeds", type=positive_int, default=SEEDS, help="seeds 0 … N−1 per function"
    )
    parser.add_argument(
        "--budgets", type=positive_int, nargs="+", action=Distinct, default=list(BUDGETS)
    )
    parser.add_argument(
        "--methods",
        nargs="+",
        action=Distinct,
        default=list(METHODS),
        choices=METHODS + peers.OPT_IN,
    )
    parser.add_argument(
        "--workers", type=nonnegative_int, default=2, help="processes (0: this one)"
    )
    parser.add_argument(
        "--json", type=report_path,
        help="the report (default: docs/figures/niching.json, niching_more.json with --suite more)",
    )  # fmt: skip
    peers.add_keep_others(parser)
    args = parser.parse_args(argv)
    functions = SUITES[args.suite]
    if args.json is None:
        name = "niching.json" if args.suite == "cec2013" else f"niching_{args.suite}.json"
        args.json = ROOT / "docs" / "figures" / name
    budgets = sorted(set(args.budgets))
    methods = [m for m in METHODS + peers.OPT_IN if m in args.methods]
    numbers = sorted(set(args.functions or range(1, len(functions) + 1)))
    for n in numbers:
        if not 1 <= n <= len(functions):
            parser.error(f"--functions takes numbers in 1..{len(functions)}, got {n}")
    # DIPOLE first (the slowest), so the processes finish together.
    tasks = [
        (n, s, m, budgets, args.suite) for m in methods for n in numbers for s in range(args.seeds)
    ]
    grid = {"functions": numbers, "seeds": args.seeds, "budgets": budgets}
    if args.suite != "cec2013":  # (reports of F1-F10 from before the suites say none)
        grid["suite"] = args.suite
    cases, wall, methods = peers.run_keeping_others(
        _task, tasks, args, grid, methods, METHODS + peers.OPT_IN, _progress
    )
    order = {m: i for i, m in enumerate(METHODS + peers.OPT_IN)}
    cases.sort(key=lambda c: (order[c["method"]], c["function"], c["seed"]))
    text, summary = summarize(cases, methods, numbers, budgets, functions)
    print(text)
    print(f"wall time {wall:.1f} s on {max(args.workers, 1)} process(es)")
    config = {
        **({"suite": args.suite} if args.suite != "cec2013" else {}),
        "functions": numbers,
        "seeds": args.seeds,
        "budgets": budgets,
        "methods": methods,
        "accuracies": list(ACCURACIES),
        "workers": args.workers,
    }
    peers.write_report(args.json, config, wall, summary, cases)


if __name__ == "__main__":
    main()

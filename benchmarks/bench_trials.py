"""Where DIPOLE's trials go on the CEC 2013 niching functions, beside NMMSO's count of optima.

    python benchmarks/bench_trials.py [--functions 6 7 9 10] [--seeds 4] [--budget 2000] \\
        [--set refine_share=0.35 ...]

DIPOLE (its defaults told the box, as in ``bench_niching.py``; ``--set key=value`` changes an
option) runs each function and seed up to ``--budget`` trials. Every trial is put in one
class, by what asked for it and, for a policy's sample, by how far that policy's mean lies
below the global optima's value f* when it is asked (the gap f* − f(mean), on the scale of
the competition's accuracies):

* ``gap > 1e-1``: a policy still climbing, or on a local optimum;
* ``1e-1 ≥ gap > 1e-4``: converging on a global optimum within the counted accuracies;
* ``gap ≤ 1e-4``: refining beyond the finest counted accuracy (mostly wakes);
* ``scouts``: samples of no policy, which look for new optima;
* ``probes``: hill-valley probes between candidates and policies.

Printed per function: each class's share of the trials (summed over the seeds), the
policies a run returns, and the global optima found at 1e-1 and 1e-3 by DIPOLE and, in the
same run, by NMMSO (``pynmmso``, its setup in ``bench_multioptima.py``), the peer that finds
most optima at 1e-1 in ``bench_niching.py``. What it answers: whether DIPOLE's trials go to
finding optima or to converging on those found (``pip install -e ".[bench]"``).
"""

from __future__ import annotations

import argparse
import ast
import sys
from collections import Counter
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
import bench_multioptima as peers  # noqa: E402
from bench_niching import ACCURACIES, FUNCTIONS  # noqa: E402

from dipole_torch import Dipole  # noqa: E402
from dipole_torch.archive import PROBE  # noqa: E402

CLASSES = ("gap > 1e-1", "1e-1 >= gap > 1e-4", "gap <= 1e-4", "scouts", "probes")


def classify(owner: Tensor, gaps: Tensor) -> Counter:
    """The classes of one asked batch: ``owner [B]`` (policy index, ``PROBE``, or another
    negative number for a scout) and ``gaps [K]`` the policies' f* − f(mean)."""
    counts: Counter = Counter()
    for o in owner.tolist():
        if o == PROBE:
            counts["probes"] += 1
        elif o < 0:
            counts["scouts"] += 1
        else:
            gap = float(gaps[o])
            counts[CLASSES[0] if gap > 1e-1 else CLASSES[1] if gap > 1e-4 else CLASSES[2]] += 1
    return counts


def run_dipole(
    number: int, seed: int, budget: int, options: dict[str, Any]
) -> tuple[Counter, Tensor]:
    """One DIPOLE run on F``number`` (``bench_niching``'s setup and seed) up to ``budget``
    trials: the trials by class, and ``[K, D]`` the policy means it returns."""
    problem = FUNCTIONS[number - 1]
    theta0, sigma_start, bounds = peers._start(problem)
    generator = torch.Generator().manual_seed(1000 * number + seed)
    opt = Dipole(theta0, sigma_start, bounds=bounds, generator=generator, **options)
    counts: Counter = Counter()
    while True:
        theta = opt.ask()
        if opt.trials + theta.shape[0] > budget:
            break  # not evaluated: it would cross the budget
        means = opt.policy_means
        gaps = problem.f_star - problem(means) if means.shape[0] else means[:, 0]
        counts += classify(opt.asked_owner, gaps)
        opt.tell(theta, problem(theta))
    return counts, opt.policy_means


def parse_options(pairs: Sequence[str]) -> dict[str, Any]:
    """``["key=value", ...]`` as Dipole options (values read as Python literals)."""
    options = {}
    for pair in pairs:
        key, sep, value = pair.partition("=")
        if not sep or not key:
            raise SystemExit(f"--set takes key=value, got {pair!r}")
        try:
            options[key] = ast.literal_eval(value)
        except (ValueError, SyntaxError):
            options[key] = value
    return options


def main(argv: Sequence[str] | None = None) -> None:
    from argtypes import Distinct, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--functions", type=int, nargs="+", action=Distinct, default=[6, 7, 9, 10])
    parser.add_argument("--seeds", type=positive_int, default=4)
    parser.add_argument("--budget", type=positive_int, default=2000)
    parser.add_argument("--set", nargs="*", default=[], metavar="KEY=VALUE",
                        help="DIPOLE options to change")  # fmt: skip
    args = parser.parse_args(argv)
    torch.set_num_threads(1)
    options = parse_options(args.set)
    if any(not 1 <= n <= len(FUNCTIONS) for n in args.functions):
        parser.error(f"--functions must lie in 1..{len(FUNCTIONS)}")
    # An unknown option or a bad value: said now, not as a traceback from the first run.
    theta0, sigma_start, bounds = peers._start(FUNCTIONS[args.functions[0] - 1])
    try:
        Dipole(theta0, sigma_start, bounds=bounds, **options)
    except (TypeError, ValueError) as error:
        parser.error(f"--set: {error}")
    coarse, fine = ACCURACIES[0], ACCURACIES[2]
    header = ["function", *CLASSES, "policies", f"DIPOLE @{coarse:g} / @{fine:g}",
              f"NMMSO @{coarse:g} / @{fine:g}"]  # fmt: skip
    rows, total = [], Counter()
    for number in args.functions:
        problem = FUNCTIONS[number - 1]
        counts, policies = Counter(), 0
        found = {"DIPOLE": [0, 0], "NMMSO": [0, 0]}
        for seed in range(args.seeds):
            run_counts, means = run_dipole(number, seed, args.budget, options)
            counts += run_counts
            policies += means.shape[0]
            nmmso = peers.run_nmmso(problem, [args.budget], 1000 * number + seed)
            for name, solutions in (("DIPOLE", means), ("NMMSO", nmmso[args.budget][0])):
                found[name][0] += problem.found(solutions, coarse)
                found[name][1] += problem.found(solutions, fine)
        total += counts
        trials = sum(counts.values())
        rows.append([
            f"{problem.name} ({problem.optima} × {args.seeds})",
            *[f"{100 * counts[c] / trials:.0f} %" for c in CLASSES],
            f"{policies / args.seeds:.1f}",
            "{} / {}".format(*found["DIPOLE"]),
            "{} / {}".format(*found["NMMSO"]),
        ])  # fmt: skip
    trials = sum(total.values())
    rows.append(["all", *[f"{100 * total[c] / trials:.0f} %" for c in CLASSES], "", "", ""])
    changed = ", ".join(f"{k}={v!r}" for k, v in options.items()) or "defaults"
    print(
        f"DIPOLE ({changed}): trials by class, {args.budget} trials a run, {args.seeds} "
        "seeds; the gap is f* − f(policy mean) when the trial is asked"
    )
    print(peers._table(header, rows))


if __name__ == "__main__":
    main()

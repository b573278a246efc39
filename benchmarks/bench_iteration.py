"""Optimizer time per iteration of DIPOLE against PoWER, its anchor, measured in the same run.

    python benchmarks/bench_iteration.py [--trials 500] [--dims 2 10 50 200] [--seeds 2]

Each optimizer runs whole runs of ``--trials`` reward evaluations on a cheap two-peak reward
(so the rollout costs nothing) with one torch thread; only ``ask()`` and ``tell()`` are timed.
Printed per D: PoWER's, DIPOLE's (default variant) and DIPOLE (paper)'s milliseconds per
iteration, averaged over whole runs (clusterings included; the first tell, which holds the
first clustering of 20 sweeps, is counted in the average and also shown on its own), and
each DIPOLE figure as a ratio to PoWER's. Timings are the median over ``--seeds`` runs.
Runs at D >= 50 are capped at ``--big-trials`` evaluations (their clusterings dominate).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch

from dipole_torch import Dipole, Power

DTYPE = torch.float64


def reward(theta: torch.Tensor) -> torch.Tensor:
    """``[B]`` two Gaussian peaks (heights 1 and 0.8) at ±1 along every axis, in (0, 1]."""
    d = theta.shape[1]
    a = (-0.5 * (theta - 1.0).square().sum(1) / d).exp()
    b = 0.8 * (-0.5 * (theta + 1.0).square().sum(1) / d).exp()
    return torch.maximum(a, b)


def make(name: str, d: int, seed: int):
    theta0 = torch.zeros(d, dtype=DTYPE)
    sigma = 0.25 * torch.eye(d, dtype=DTYPE)
    g = torch.Generator().manual_seed(seed)
    if name == "power":
        return Power(theta0, sigma, n0=10, reward_range=(0.0, 1.0), generator=g)
    if name == "dipole_paper":
        return Dipole.paper(theta0, sigma, n0=10, reward_range=(0.0, 1.0), generator=g)
    return Dipole(theta0, sigma, n0=10, generator=g)


def run(name: str, d: int, trials: int, seed: int) -> tuple[float, float]:
    """One whole run: (seconds per iteration over all tells, seconds of the first tell)."""
    opt = make(name, d, seed)
    total, first, tells = 0.0, 0.0, 0
    while opt.trials < trials:
        start = time.perf_counter()
        theta = opt.ask()
        asked = time.perf_counter() - start
        r = reward(theta)
        start = time.perf_counter()
        opt.tell(theta, r)
        elapsed = asked + time.perf_counter() - start
        if tells == 0:
            first = elapsed
        total += elapsed
        tells += 1
    return total / tells, first


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--trials", type=int, default=500)
    parser.add_argument("--big-trials", type=int, default=60, help="trials at D >= 50")
    parser.add_argument("--dims", type=int, nargs="+", default=[2, 10, 50, 200])
    parser.add_argument("--seeds", type=int, default=2)
    args = parser.parse_args()
    torch.set_num_threads(1)
    names = ("power", "dipole", "dipole_paper")
    header = (
        f"{'D':>4} {'trials':>6} {'PoWER ms':>9} {'DIPOLE ms':>10} {'paper ms':>9} "
        f"{'DIPOLE/PoWER':>13} {'paper/PoWER':>12} {'DIPOLE 1st tell s':>18}"
    )
    for name in names:  # first-call costs (lazy init) out of the table
        run(name, 2, 20, 0)
    print(header)
    print("-" * len(header))
    for d in args.dims:
        trials = args.trials if d < 50 else args.big_trials
        per_iter, first = {}, {}
        for name in names:
            results = [run(name, d, trials, seed) for seed in range(args.seeds)]
            per_iter[name] = 1e3 * statistics.median(r[0] for r in results)
            first[name] = statistics.median(r[1] for r in results)
        base = per_iter["power"]
        print(
            f"{d:>4} {trials:>6} {base:>9.2f} {per_iter['dipole']:>10.2f} "
            f"{per_iter['dipole_paper']:>9.2f} {per_iter['dipole'] / base:>13.2f} "
            f"{per_iter['dipole_paper'] / base:>12.2f} {first['dipole']:>18.3f}",
            flush=True,
        )


if __name__ == "__main__":
    main()

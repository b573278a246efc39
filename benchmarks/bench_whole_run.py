"""Whole-run optimizer CPU at equal trials, evaluations excluded: DIPOLE against IPOP-CMA-ES
and NMMSO, its anchors, on bench_multioptima's landscapes, measured in the same run; and
against the library's PoWER, the same ask/tell with one policy.

    python benchmarks/bench_whole_run.py [--dims 2 10] [--ks 2 4 8] [--seeds 2] \\
        [--trials 2000] [--methods DIPOLE "DIPOLE (paper)" PoWER IPOP-CMA-ES NMMSO]

Each method runs on each case (D, k, seed) of ``benchmarks/bench_multioptima.py`` with the
setup that script gives it (DIPOLE's defaults told the box; pycma's IPOP-CMA-ES with its
restarts; pynmmso's NMMSO with its defaults), up to ``--trials`` evaluations, in this process
with one torch thread, the methods alternated case by case so that a change in the machine's
load falls on all of them alike. Timed: the process CPU time of the whole run
(``time.process_time``), less the CPU time spent inside the landscape's evaluations (each
call timed), so what remains is the optimizer's own work: its ask/tell, its bookkeeping and,
for NMMSO, the Python around each single-point evaluation. First-call costs (imports, lazy
initialisation) are spent in a warm-up run before the table.

Printed per D: each method's optimizer CPU summed over the cases, the trials it used, its
CPU per trial, the Gibbs sweeps its clusterings ran (DIPOLE's variants; counted, so the same
on every machine), and each method's ratio to IPOP-CMA-ES's, NMMSO's and PoWER's summed CPU.
PoWER (``bench_multioptima``'s setup: the paper's global importance sets, a decaying
exploration) runs through the same ``ask``/``tell`` as DIPOLE (the told rows' checks, the
archive, the importance sets, eq. 7, the seeded draws) with one policy and none of DIPOLE's
mechanisms (clusterings, success rule, retirement, scouts, probes): DIPOLE's ratio to it is
what those mechanisms add to a trial, its ratio to IPOP-CMA-ES what the ask/tell itself costs.
The opt-in method "PoWER (bare loop)" is the same algorithm as a dozen lines of eager torch
(one sample, the best M kept, eq. 7, the decay; no checks of the told rows, no archive of
owners, no seeded draws, no undo on error): the floor of a per-trial update in eager torch.
"""

from __future__ import annotations

import argparse
import sys
import time
from pathlib import Path

import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_multioptima import OPT_IN as GRID_OPT_IN  # noqa: E402
from bench_multioptima import RUNNERS as GRID_RUNNERS  # noqa: E402
from bench_multioptima import Snapshots, _start, case_seeds, grid_error, make_landscape  # noqa: E402
from setting import setting_line  # noqa: E402

from dipole_torch.dp.sampler import DPSampler  # noqa: E402

METHODS = ("DIPOLE", "DIPOLE (paper)", "PoWER", "IPOP-CMA-ES", "NMMSO")
ANCHORS = ("IPOP-CMA-ES", "NMMSO", "PoWER")


def run_bare_power(landscape, budgets, seed: int) -> Snapshots:
    """PoWER as ``bench_multioptima`` sets it up (θ0 the box's centre, Σ_start its
    quarter-widths squared, the fixed reward range, ``exploration_decay=0.98``, M = n0 = 5,
    weights floored at 1e-3, the covariance's factor at 1e-2), in a bare eager-torch loop: the
    work of a trial with nothing around it."""
    generator = torch.Generator().manual_seed(seed)
    mean, sigma_start, (lower, upper) = _start(landscape)
    scale = sigma_start.sqrt()  # (diagonal: its Cholesky factor)
    low, high = landscape.reward_range
    top, m = budgets[-1], 5
    noise = torch.randn(m, mean.shape[0], generator=generator, dtype=mean.dtype)
    thetas = (mean + noise @ scale.T).clamp(lower, upper)
    rewards = landscape(thetas)
    for iteration in range(1, top - m + 1):
        best = torch.topk(rewards, min(m, rewards.shape[0]))
        thetas, rewards = thetas[best.indices], best.values
        weights = ((rewards - low) / (high - low)).clamp(1e-3, 1.0)
        mean = mean + (weights[:, None] * (thetas - mean)).sum(0) / weights.sum()
        factor = max(0.98**iteration, 1e-2) ** 0.5
        noise = torch.randn(1, mean.shape[0], generator=generator, dtype=mean.dtype)
        theta = (mean + factor * noise @ scale.T).clamp(lower, upper)
        thetas = torch.cat((thetas, theta))
        rewards = torch.cat((rewards, landscape(theta)))
    return {top: (mean[None], top)}


RUNNERS = {**GRID_RUNNERS, "PoWER (bare loop)": run_bare_power}
OPT_IN = (*GRID_OPT_IN, "PoWER (bare loop)")


class TimedLandscape:
    """A landscape whose evaluations are counted and timed (process CPU seconds); the rest
    of its interface (``dim``, ``lower``, ``upper``, ``reward_range``, ...) passes through."""

    def __init__(self, landscape):
        self.landscape = landscape
        self.seconds = 0.0
        self.trials = 0

    def __getattr__(self, name: str):
        return getattr(self.landscape, name)

    def __call__(self, theta: Tensor) -> Tensor:
        start = time.process_time()
        values = self.landscape(theta)
        self.seconds += time.process_time() - start
        self.trials += int(theta.shape[0]) if theta.dim() > 1 else 1
        return values


class SweepCount:
    """Counts ``DPSampler.sweep`` calls while in use (a counter around the method)."""

    def __init__(self):
        self.sweeps = 0

    def __enter__(self) -> SweepCount:
        sweep = self._sweep = DPSampler.sweep

        def counted(sampler, *args, **kwargs):
            self.sweeps += 1
            return sweep(sampler, *args, **kwargs)

        DPSampler.sweep = counted
        return self

    def __exit__(self, *exc) -> None:
        DPSampler.sweep = self._sweep


def optimizer_cpu(method: str, dim: int, k: int, seed: int, trials: int) -> tuple[float, int, int]:
    """``(optimizer CPU seconds, trials evaluated, Gibbs sweeps)`` of one run of ``method``
    on case (D, k, seed) with a budget of ``trials``."""
    landscape_seed, method_seed = case_seeds(dim, k, seed)
    landscape = TimedLandscape(make_landscape(dim, k, landscape_seed))
    with SweepCount() as count:
        start = time.process_time()
        RUNNERS[method](landscape, [trials], method_seed)
        total = time.process_time() - start
    return total - landscape.seconds, landscape.trials, count.sweeps


def main() -> None:
    from argtypes import Distinct, positive_even_int, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dims", type=positive_int, nargs="+", action=Distinct, default=[2, 10])
    parser.add_argument(
        "--ks", type=positive_even_int, nargs="+", action=Distinct, default=[2, 4, 8]
    )
    parser.add_argument("--seeds", type=positive_int, default=2, help="seeds 0 … N−1 per (D, k)")
    parser.add_argument("--trials", type=positive_int, default=2000)
    parser.add_argument(
        "--methods", nargs="+", action=Distinct, default=list(METHODS), choices=METHODS + OPT_IN
    )
    args = parser.parse_args()
    if (error := grid_error(args.dims, args.ks)) is not None:
        parser.error(f"argument --ks: {error}")
    torch.set_num_threads(1)
    print(setting_line())
    methods = [m for m in METHODS + OPT_IN if m in args.methods]
    for method in methods:  # first-call costs out of the table
        optimizer_cpu(method, 2, 2, 0, 60)
    width = max(len("method"), *map(len, methods))
    header = (
        f"{'D':>3} {'method':<{width}} {'CPU s':>8} {'trials':>7} {'µs/trial':>9} {'sweeps':>7}"
    )
    header += "".join(f" {'/' + anchor:>13}" for anchor in ANCHORS if anchor in methods)
    print(f"optimizer CPU (evaluations excluded), {args.trials} trials a run, "
          f"k in {args.ks}, {args.seeds} seeds")  # fmt: skip
    print(header)
    print("-" * len(header))
    for dim in args.dims:
        seconds = dict.fromkeys(methods, 0.0)
        used = dict.fromkeys(methods, 0)
        sweeps = dict.fromkeys(methods, 0)
        for k in args.ks:
            for seed in range(args.seeds):
                for method in methods:
                    cpu, trials, count = optimizer_cpu(method, dim, k, seed, args.trials)
                    seconds[method] += cpu
                    used[method] += trials
                    sweeps[method] += count
        for method in methods:
            line = (
                f"{dim:>3} {method:<{width}} {seconds[method]:>8.2f} {used[method]:>7} "
                f"{1e6 * seconds[method] / max(used[method], 1):>9.0f} "
                f"{sweeps[method] if method.startswith('DIPOLE') else '-':>7}"
            )
            for anchor in ANCHORS:
                if anchor in methods:
                    ratio = seconds[method] / seconds[anchor]
                    line += f" {ratio:>13.2f}"
            print(line, flush=True)


if __name__ == "__main__":
    main()

"""Optimizer time per iteration of DIPOLE against PoWER, its anchor, measured in the same run.

    python benchmarks/bench_iteration.py [--trials 500] [--dims 2 10 50 200] [--seeds 2]

Each optimizer runs whole runs of ``--trials`` reward evaluations on a cheap two-peak reward
(so the rollout costs nothing) with one torch thread; only ``ask()`` and ``tell()`` are timed.
Printed per D: PoWER's, DIPOLE's (default variant) and DIPOLE (paper)'s milliseconds per
iteration, averaged over whole runs (clusterings included; the first tell, which holds the
first clustering of 20 sweeps, is counted in the average and also shown on its own), and
each DIPOLE figure as a ratio to PoWER's; and the same for DIPOLE with ``settle=None,
scout_sweeps=None`` (every clustering runs all its sweeps; the default ends a warm-started
one after the first sweep that leaves its partition unchanged, and gives a clustering of
scouts alone one sweep).
Timings are the median over ``--seeds`` runs.
Runs at D >= 50 are capped at ``--big-trials`` evaluations (their clusterings dominate).

A second table says where DIPOLE's time goes: the milliseconds per iteration spent in its
clusterings' Gibbs sweeps (``Dipole._fit``) and in the rest of ``ask`` and ``tell``
(PoWER steps, success rule, scouts, hill-valley tests, matching the clusters to policies),
each against PoWER's whole iteration; the trials an iteration evaluates (PoWER one, DIPOLE
one per sampled policy plus scouts and probes) and the time per trial; and, with
``--count-ops``, the torch calls an iteration makes (functions, tensor methods and tensor
property reads such as ``.shape``, which cost far less, so the count bounds the dispatches
from above; counted in one more run per D; the label loop's numpy calls are not counted):
at a few microseconds of dispatch each, they set the floor of an iteration at these sizes.
A third table splits DIPOLE's iterations after the first by kind: those that sample
policies (with their scouts and probes) and restarts (no policy active at the ask: every one
has retired, so the ask is n0 scouts and the tell clusters them), each one's milliseconds
against PoWER's iteration, the trials of a policy iteration and the share of restarts. The
restarts' share follows how soon the policies retire on this reward, so the first ratio is
the one to compare across changes to retirement.
With ``--count-ops`` a fourth table splits DIPOLE's calls by the part of the iteration that
makes them (``PARTS``: each call counted once, in the innermost part it is made in; "the
rest" is ``ask`` and ``tell`` around them: the checks of the told rows, the archive).
"""

from __future__ import annotations

import argparse
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from setting import setting_line  # noqa: E402

from dipole_torch import Dipole, Power  # noqa: E402

DTYPE = torch.float64
NAMES = ("power", "dipole", "dipole_paper", "dipole_all_sweeps")


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
    if name == "dipole_all_sweeps":  # every clustering runs all its sweeps
        return Dipole(theta0, sigma, n0=10, settle=None, scout_sweeps=None, generator=g)
    return Dipole(theta0, sigma, n0=10, generator=g)


class CountCalls(TorchFunctionMode):
    """Counts the torch functions, tensor methods and tensor property reads under it."""

    def __init__(self):
        super().__init__()
        self.calls = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        self.calls += 1
        return func(*args, **(kwargs or {}))


def run(name: str, d: int, trials: int, seed: int) -> dict[str, float]:
    """One whole run. Returns seconds per iteration over all tells (``per_iter``), of the
    first tell (``first``), in DIPOLE's clusterings per iteration (``clustering``; 0 for
    PoWER) and trials per iteration (``trials``)."""
    opt = make(name, d, seed)
    fitting = 0.0
    if isinstance(opt, Dipole):
        fit = opt._fit

        def timed_fit(*args, **kwargs):  # the Gibbs sweeps of one clustering
            nonlocal fitting
            start = time.perf_counter()
            state = fit(*args, **kwargs)
            fitting += time.perf_counter() - start
            return state

        opt._fit = timed_fit
    total, first, tells = 0.0, 0.0, 0
    # After the first tell: iterations that sample policies, and restarts (no policy active at
    # the ask: n0 scouts and a clustering of them).
    kinds = {"policies": [0.0, 0, 0], "restarts": [0.0, 0, 0]}  # seconds, iterations, trials
    while opt.trials < trials:
        restart = isinstance(opt, Dipole) and tells > 0 and not opt.policy_set.any_active()
        before = opt.trials
        start = time.perf_counter()
        theta = opt.ask()
        asked = time.perf_counter() - start
        r = reward(theta)
        start = time.perf_counter()
        opt.tell(theta, r)
        elapsed = asked + time.perf_counter() - start
        if tells == 0:
            first = elapsed
        else:
            kind = kinds["restarts" if restart else "policies"]
            kind[0] += elapsed
            kind[1] += 1
            kind[2] += opt.trials - before
        total += elapsed
        tells += 1
    later = max(tells - 1, 1)
    policies, restarts = kinds["policies"], kinds["restarts"]
    return {
        "per_iter": total / tells,
        "iterations": tells,
        "first": first,
        "clustering": fitting / tells,
        "trials": opt.trials / tells,
        "policy_iter": policies[0] / max(policies[1], 1),
        "policy_trials": policies[2] / max(policies[1], 1),
        "restart_iter": restarts[0] / max(restarts[1], 1),
        "restart_share": restarts[1] / later,
    }


def counted_run(opt, trials: int, counter: CountCalls) -> int:
    """Runs ``opt`` to ``trials`` with ``counter`` on during ``ask`` and ``tell`` only (the
    reward's calls are not the optimizer's); returns the iterations (tells)."""
    tells = 0
    while opt.trials < trials:
        with counter:
            theta = opt.ask()
        r = reward(theta)
        with counter:
            opt.tell(theta, r)
        tells += 1
    return tells


def torch_calls(name: str, d: int, trials: int, seed: int) -> float:
    """Torch calls per iteration of one whole run (``ask`` and ``tell`` only)."""
    counter = CountCalls()
    tells = counted_run(make(name, d, seed), trials, counter)
    return counter.calls / tells


# The parts of a DIPOLE iteration whose torch calls the fourth table counts: (label, the
# object's attribute on the optimizer, or "" for the optimizer itself; the method).
PARTS = (
    ("first clustering", "", "_after_initial_batch"),
    ("clusterings", "", "_cluster"),
    ("observe", "", "_observe"),
    ("eq. 7", "importance", "power_step"),
    ("sampling", "", "_propose"),
    ("straddlers", "retirement", "restart_straddlers"),
    ("retire, merge", "retirement", "retire_and_merge"),
    ("hill-valley", "vetting", "judge"),
    ("hill-valley", "vetting", "queue_probes"),
    ("wake", "retirement", "wake"),
)


def calls_by_part(d: int, trials: int, seed: int) -> dict[str, float]:
    """DIPOLE's torch calls per iteration of one whole run, by part (``PARTS``; each call
    counted once, in the innermost part it is made in; ``"the rest"``: outside them)."""
    opt = make("dipole", d, seed)
    counter = CountCalls()
    totals = dict.fromkeys([label for label, _, _ in PARTS] + ["the rest"], 0)
    inner: list[int] = []  # per running part: the calls its nested parts made

    def counted(label: str, method):
        def part(*args, **kwargs):
            before = counter.calls
            inner.append(0)
            try:
                return method(*args, **kwargs)
            finally:
                made = counter.calls - before
                totals[label] += made - inner.pop()
                if inner:
                    inner[-1] += made

        return part

    for label, path, name in PARTS:
        owner = getattr(opt, path) if path else opt
        setattr(owner, name, counted(label, getattr(owner, name)))  # on the instance only
    tells = counted_run(opt, trials, counter)
    totals["the rest"] = counter.calls - sum(totals.values())
    return {label: calls / tells for label, calls in totals.items()}


def print_header(title: str, header: str) -> None:
    """A blank line, a table's title, its column header and a rule under it."""
    print()
    print(title)
    print(header)
    print("-" * len(header))


def main() -> None:
    from argtypes import Distinct, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--trials", type=positive_int, default=500)
    parser.add_argument("--big-trials", type=positive_int, default=60, help="trials at D >= 50")
    parser.add_argument(
        "--dims", type=positive_int, nargs="+", action=Distinct, default=[2, 10, 50, 200]
    )
    parser.add_argument("--seeds", type=positive_int, default=2)
    parser.add_argument("--count-ops", action="store_true", help="count torch calls (slower)")
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(setting_line())
    for name in NAMES:  # first-call costs (lazy init) out of the table
        run(name, 2, 20, 0)
    header = (
        f"{'D':>4} {'trials':>6} {'PoWER ms':>9} {'DIPOLE ms':>10} {'paper ms':>9} "
        f"{'DIPOLE/PoWER':>13} {'paper/PoWER':>12} {'DIPOLE 1st tell s':>18} "
        f"{'all sweeps ms':>14} {'all sweeps/PoWER':>17}"
    )
    print(header)
    print("-" * len(header))
    breakdown = []
    for d in args.dims:
        trials = args.trials if d < 50 else args.big_trials
        med = {}
        for name in NAMES:
            results = [run(name, d, trials, seed) for seed in range(args.seeds)]
            med[name] = {key: statistics.median(r[key] for r in results) for key in results[0]}
        base = 1e3 * med["power"]["per_iter"]
        dipole, paper = 1e3 * med["dipole"]["per_iter"], 1e3 * med["dipole_paper"]["per_iter"]
        every = 1e3 * med["dipole_all_sweeps"]["per_iter"]
        print(
            f"{d:>4} {trials:>6} {base:>9.2f} {dipole:>10.2f} {paper:>9.2f} "
            f"{dipole / base:>13.2f} {paper / base:>12.2f} {med['dipole']['first']:>18.3f} "
            f"{every:>14.2f} {every / base:>17.2f}",
            flush=True,
        )
        calls = None
        if args.count_ops:
            calls = {name: torch_calls(name, d, trials, 0) for name in ("power", "dipole")}
            calls["parts"] = calls_by_part(d, trials, 0)
        breakdown.append((d, med, calls))
    print_header(
        "where DIPOLE's time goes (ms per iteration; ratios to PoWER's whole iteration):",
        f"{'D':>4} {'clustering ms':>14} {'rest ms':>8} {'clust/PoWER':>12} {'rest/PoWER':>11} "
        f"{'PoWER trials/it':>16} {'DIPOLE trials/it':>17} {'per-trial ratio':>16} "
        f"{'PoWER calls/it':>15} {'DIPOLE calls/it':>16}",
    )
    for d, med, calls in breakdown:
        base = 1e3 * med["power"]["per_iter"]
        clustering = 1e3 * med["dipole"]["clustering"]
        rest = 1e3 * med["dipole"]["per_iter"] - clustering
        per_trial = (med["dipole"]["per_iter"] / med["dipole"]["trials"]) / (
            med["power"]["per_iter"] / med["power"]["trials"]
        )
        counted = (
            f"{calls['power']:>15.0f} {calls['dipole']:>16.0f}" if calls else f"{'-':>15} {'-':>16}"
        )
        print(
            f"{d:>4} {clustering:>14.2f} {rest:>8.2f} {clustering / base:>12.2f} "
            f"{rest / base:>11.2f} {med['power']['trials']:>16.2f} "
            f"{med['dipole']['trials']:>17.2f} {per_trial:>16.2f} {counted}",
            flush=True,
        )
    print_header(
        "DIPOLE's iterations after the first by kind (ms; ratios to PoWER's whole iteration):",
        f"{'D':>4} {'policy it. ms':>14} {'policy it./PoWER':>17} {'trials/policy it.':>18} "
        f"{'restart ms':>11} {'restart/PoWER':>14} {'restarts share':>15}",
    )
    for d, med, _ in breakdown:
        base = 1e3 * med["power"]["per_iter"]
        dipole = med["dipole"]
        policy, restart = 1e3 * dipole["policy_iter"], 1e3 * dipole["restart_iter"]
        print(
            f"{d:>4} {policy:>14.2f} {policy / base:>17.2f} {dipole['policy_trials']:>18.2f} "
            f"{restart:>11.2f} {restart / base:>14.2f} {dipole['restart_share']:>15.3f}",
            flush=True,
        )
    if args.count_ops:
        labels = list(breakdown[0][2]["parts"])
        width = [max(len(label), 6) for label in labels]
        print_header(
            "DIPOLE's torch calls an iteration, by part (one run a D, seed 0):",
            f"{'D':>4} "
            + " ".join(f"{label:>{w}}" for label, w in zip(labels, width, strict=True)),
        )
        for d, _, calls in breakdown:
            row = [
                f"{calls['parts'][label]:>{w}.1f}" for label, w in zip(labels, width, strict=True)
            ]
            print(f"{d:>4} " + " ".join(row))


if __name__ == "__main__":
    main()

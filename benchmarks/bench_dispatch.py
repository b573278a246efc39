"""The dispatch floor of an optimizer made of small tensor calls, against the CPU a trial may
spend to stay within a multiple of IPOP-CMA-ES's, measured in the same run.

    python benchmarks/bench_dispatch.py [--dims 2 10] [--ratio 5] [--repeats 20000]

At DIPOLE's sizes (a few policies, D ≤ 10, M = 5) a tensor call's arithmetic is far below its
dispatch; an iteration costs about its calls times the cost of one. Printed per D, one torch
thread:

* **a call**: µs of a bare elementwise call on ``[K, D]`` float64 (``torch.add``; numpy's
  ``np.add`` beside it), of a batched Cholesky factorisation of K covariances ``[K, p, p]``
  (p = D + 1, a clustering's; ``torch.linalg.cholesky_ex``), and eq. 7
  (``dipole_torch.power.power_update``, the PoWER step on K = 4 policies' importance sets
  of M = 5) per step and per call: in torch as the library
  runs it, under ``torch.jit.script`` (its lines compiled to TorchScript, where the installed
  torch still scripts them) and transcribed to numpy (the same lines, equal to rounding):
  the three engines a rewrite of the bookkeeping could use;
* **the budget**: IPOP-CMA-ES's optimizer CPU a trial on ``bench_multioptima``'s landscape
  (k = 8, seed 0, 2000 trials, evaluations excluded, as ``bench_whole_run.py`` measures it),
  times ``--ratio``: what a DIPOLE trial may spend to be within that ratio; DIPOLE's own
  CPU a trial on the same run's landscape beside it;
* **the calls**: the torch calls a DIPOLE iteration and a PoWER iteration make
  (``bench_iteration.py``'s count, 500 trials, seed 0) and DIPOLE's trials an iteration, so
  the floor of a DIPOLE trial at eager dispatch (calls a trial × eq. 7's µs a call: a lower
  bound, as a factorisation or a triangular solve costs several elementwise calls) beside
  the budget, and the calls a trial the budget allows.
"""

from __future__ import annotations

import argparse
import sys
import time
import warnings
from pathlib import Path

import numpy as np
import torch

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_iteration import make, reward, torch_calls  # noqa: E402
from bench_whole_run import optimizer_cpu  # noqa: E402
from setting import setting_line  # noqa: E402

from dipole_torch.power import power_update  # noqa: E402

K, M = 4, 5  # policies sampled and importance-set size at DIPOLE's defaults
FLOAT64_TINY = float(torch.finfo(torch.float64).tiny)


def per_call_us(fn, args, repeats: int) -> float:
    """µs per call of ``fn(*args)``, after a warm-up."""
    for _ in range(min(repeats, 500)):
        fn(*args)
    start = time.perf_counter()
    for _ in range(repeats):
        fn(*args)
    return (time.perf_counter() - start) / repeats * 1e6


def eq7_numpy(mean: np.ndarray, samples: np.ndarray, weights: np.ndarray) -> np.ndarray:
    """Eq. 7 as ``power_update`` computes it, in numpy (for the floor only)."""
    total = weights.sum(-1, keepdims=True)
    step = (weights[..., None] * (samples - mean[:, None, :])).sum(-2)
    return np.where(total > 0, mean + step / np.maximum(total, FLOAT64_TINY), mean)


def eq7_torch(mean: torch.Tensor, samples: torch.Tensor, weights: torch.Tensor) -> torch.Tensor:
    """Eq. 7 as ``power_update`` computes it (its keyword-only ``validate`` keeps TorchScript
    from compiling the library's function itself: the same lines, for the floor only)."""
    total = weights.sum(-1, keepdim=True)
    step = (weights.unsqueeze(-1) * (samples - mean.unsqueeze(-2))).sum(-2)
    tiny = 2.2250738585072014e-308  # float64's (TorchScript has no finfo or globals)
    return torch.where(total > 0, mean + step / total.clamp_min(tiny), mean)


def scripted_eq7():
    """``eq7_torch`` under ``torch.jit.script``, or ``None`` where scripting fails."""
    try:
        with warnings.catch_warnings():
            warnings.simplefilter("ignore")
            return torch.jit.script(eq7_torch)
    except Exception:  # noqa: BLE001 (any failure: the engine is not available here)
        return None


def eq7_calls(args: tuple) -> int:
    """Torch calls of one ``power_update`` as the library runs it."""
    from bench_iteration import CountCalls

    counter = CountCalls()
    with counter:
        power_update(*args, validate=False)
    return counter.calls


def dipole_trials_per_iteration(d: int, trials: int) -> float:
    opt, tells = make("dipole", d, 0), 0
    while opt.trials < trials:
        theta = opt.ask()
        opt.tell(theta, reward(theta))
        tells += 1
    return opt.trials / tells


def main() -> None:
    from argtypes import Distinct, at_least, positive_float, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dims", type=at_least(2), nargs="+", action=Distinct, default=[2, 10])
    parser.add_argument(
        "--ratio", type=positive_float, default=5.0, help="the target: × IPOP-CMA-ES"
    )
    parser.add_argument("--repeats", type=positive_int, default=20000)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(setting_line())
    scripted = scripted_eq7()
    optimizer_cpu("IPOP-CMA-ES", 2, 8, 0, 200)  # first-call costs out of the table
    rows = []
    for d in args.dims:
        g = torch.Generator().manual_seed(d)
        mean = torch.randn(K, d, generator=g, dtype=torch.float64)
        samples = torch.randn(K, M, d, generator=g, dtype=torch.float64)
        weights = torch.rand(K, M, generator=g, dtype=torch.float64)
        host = (mean.numpy(), samples.numpy(), weights.numpy())
        step = power_update(mean, samples, weights)
        # The engines compute one step (numpy's sums round in another order).
        assert scripted is None or torch.equal(scripted(mean, samples, weights), step)
        assert np.allclose(eq7_numpy(*host), step.numpy(), rtol=1e-12, atol=0.0)
        row = {"D": d, "calls": eq7_calls((mean, samples, weights))}
        row["add"] = per_call_us(torch.add, (mean, mean), args.repeats)
        row["np_add"] = per_call_us(np.add, (host[0], host[0]), args.repeats)
        covs = torch.eye(d + 1, dtype=torch.float64).expand(K, d + 1, d + 1).contiguous()
        row["cholesky"] = per_call_us(torch.linalg.cholesky_ex, (covs,), args.repeats)
        row["eager"] = per_call_us(
            lambda *a: power_update(*a, validate=False), (mean, samples, weights), args.repeats
        )
        row["script"] = (
            per_call_us(scripted, (mean, samples, weights), args.repeats) if scripted else None
        )
        row["numpy"] = per_call_us(eq7_numpy, host, args.repeats)
        ipop_s, ipop_trials, _ = optimizer_cpu("IPOP-CMA-ES", d, 8, 0, 2000)
        dipole_s, dipole_trials, _ = optimizer_cpu("DIPOLE", d, 8, 0, 2000)
        row["ipop"] = ipop_s / ipop_trials * 1e6
        row["dipole"] = dipole_s / dipole_trials * 1e6
        row["dipole_calls"] = torch_calls("dipole", d, 500, 0)
        row["power_calls"] = torch_calls("power", d, 500, 0)
        row["trials_per_it"] = dipole_trials_per_iteration(d, 500)
        rows.append(row)

    print(f"a call at DIPOLE's sizes (K = {K}, M = {M}), µs, one thread:")
    header = (
        f"{'D':>4} {'torch.add':>10} {'np.add':>8} {'cholesky':>9} {'eq.7 torch':>11} {'calls':>6} "
        f"{'µs/call':>8} {'eq.7 script':>12} {'eq.7 numpy':>11}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        script = f"{r['script']:>12.1f}" if r["script"] is not None else f"{'n/a':>12}"
        print(
            f"{r['D']:>4} {r['add']:>10.2f} {r['np_add']:>8.2f} {r['cholesky']:>9.2f} "
            f"{r['eager']:>11.1f} "
            f"{r['calls']:>6d} {r['eager'] / r['calls']:>8.2f} {script} {r['numpy']:>11.1f}"
        )
    print()
    print(f"the budget of a DIPOLE trial at {args.ratio:g}× IPOP-CMA-ES, and its calls:")
    header = (
        f"{'D':>4} {'IPOP µs/trial':>14} {'budget µs':>10} {'DIPOLE µs/trial':>16} "
        f"{'DIPOLE calls/it':>16} {'trials/it':>10} {'calls/trial':>12} "
        f"{'floor µs/trial':>15} {'floor/budget':>13} {'calls allowed':>14} "
        f"{'PoWER calls/it':>15}"
    )
    print(header)
    print("-" * len(header))
    for r in rows:
        budget = args.ratio * r["ipop"]  # µs a DIPOLE trial may spend
        per_call = r["eager"] / r["calls"]
        per_trial = r["dipole_calls"] / r["trials_per_it"]
        floor = per_trial * per_call  # its calls at eager dispatch, nothing around them
        print(
            f"{r['D']:>4} {r['ipop']:>14.1f} {budget:>10.1f} {r['dipole']:>16.0f} "
            f"{r['dipole_calls']:>16.0f} {r['trials_per_it']:>10.2f} {per_trial:>12.0f} "
            f"{floor:>15.0f} {floor / budget:>13.2f} {budget / per_call:>14.0f} "
            f"{r['power_calls']:>15.0f}",
            flush=True,
        )


if __name__ == "__main__":
    main()

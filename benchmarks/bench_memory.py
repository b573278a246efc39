"""Peak memory of one DP Gibbs sweep at N = 10⁴, p = 51, against the same sweep drawing all
its auxiliary components at once, measured in the same run.

    python benchmarks/bench_memory.py [--n 10000] [--dim 51] [--m 10] [--threads 1]

Linux (``/proc`` and ``ru_maxrss``); the data come from ``bench_gibbs.py``, which needs the
``bench`` extra (``pip install -e ".[bench]"``).

Data: N points of 4 unit Gaussians in p dimensions (``bench_gibbs.make_data``), the chain
started from the true partition (``DPMixtureState.from_labels``) under ``bench_gibbs``'s
fixed prior. Each case runs in a fresh Python process, so its peak resident set size
(``ru_maxrss``) is its own; printed per case: the RSS before the sweep (interpreter, torch,
data), the peak during it, the growth (peak − before) and the sweep's seconds. Cases:

* ``neal8``: Algorithm 8 as DIPOLE runs it, the N·m auxiliary draws made in chunks of points
  (at most ``dipole_torch.dp.neal8.AUX_CHUNK_BYTES``, 64 MB, of covariances and factors
  at once);
* ``neal8, unchunked`` (the anchor): the same sweep with one chunk, i.e. all N·m auxiliary
  covariances and their factors at once (``--skip-unchunked`` leaves it out: it needs
  2·N·m·p²·8 bytes, 4.2 GB at the defaults);
* ``reuse``: Favaro & Teh's re-used auxiliary draws (m + slots taken per sweep);
* ``slice``: the slice sampler (no auxiliary components).

The target (issue "Speed"): the chunked sweep stays under 1 GB.
"""

from __future__ import annotations

import argparse
import json
import resource
import subprocess
import sys
import time

import torch
from bench_gibbs import make_data, prior_for

from dipole_torch import DPMixtureState, DPSampler
from dipole_torch.dp import neal8

# The anchor first, so every other row's ratio is to a figure already measured.
CASES = ("neal8, unchunked", "neal8", "reuse", "slice")


def peak_mb() -> float:
    """Peak resident set size of this process so far, in MB (Linux: ``ru_maxrss`` in KB)."""
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def current_mb() -> float:
    """Resident set size of this process now, in MB."""
    with open("/proc/self/statm") as statm:
        pages = int(statm.read().split()[1])
    return pages * resource.getpagesize() / 2**20


def child(case: str, n: int, dim: int, m: int, threads: int) -> dict[str, float]:
    """One sweep of ``case`` in this process; its memory figures."""
    torch.set_num_threads(threads)
    y, labels = make_data(n, dim)
    prior = prior_for(y)
    state = DPMixtureState.from_labels(y, labels, prior)
    g = torch.Generator().manual_seed(0)
    if case == "neal8, unchunked":
        neal8.AUX_CHUNK_BYTES = 2**62
    method = "slice" if case == "slice" else "neal8"
    auxiliary = "reuse" if case == "reuse" else "fresh"
    sampler = DPSampler(prior, m=m, update_prior=False, auxiliary=auxiliary, method=method)
    before = current_mb()
    start = time.perf_counter()
    sampler.sweep(y, sampler.to_chain(state), g)
    seconds = time.perf_counter() - start
    return {"before_mb": before, "peak_mb": peak_mb(), "seconds": seconds}


def main() -> None:
    from argtypes import at_least, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--n", type=at_least(2), default=10_000)
    parser.add_argument("--dim", type=positive_int, default=51, help="p, the dimension of y")
    parser.add_argument("--m", type=positive_int, default=10, help="auxiliary components")
    parser.add_argument("--threads", type=positive_int, default=1)
    parser.add_argument("--skip-unchunked", action="store_true")
    parser.add_argument("--child", choices=CASES, help=argparse.SUPPRESS)
    args = parser.parse_args()
    if args.n <= args.dim:  # the prior's mean covariance is the data's
        parser.error(f"--n {args.n}: N must exceed p = {args.dim} (--dim)")
    if args.child:
        print(json.dumps(child(args.child, args.n, args.dim, args.m, args.threads)))
        return
    all_at_once = 2 * args.n * args.m * args.dim**2 * 8 / 2**20
    chunk = neal8.AUX_CHUNK_BYTES / 2**20
    print(
        f"N = {args.n}, p = {args.dim}, m = {args.m}: all auxiliary covariances and factors "
        f"at once take {all_at_once:.0f} MB; a chunk at most {chunk:.0f} MB"
    )
    header = (
        f"{'case':<18} {'RSS before MB':>14} {'peak MB':>8} {'growth MB':>10} {'sweep s':>8} "
        f"{'peak / unchunked':>17}"
    )
    print(header)
    print("-" * len(header))
    cases = [c for c in CASES if not (args.skip_unchunked and c == "neal8, unchunked")]
    anchor = None
    for case in cases:
        command = [sys.executable, __file__, "--child", case, "--n", str(args.n)]
        command += ["--dim", str(args.dim), "--m", str(args.m), "--threads", str(args.threads)]
        out = subprocess.run(command, check=True, capture_output=True, text=True).stdout
        r = json.loads(out.strip().splitlines()[-1])
        if case == "neal8, unchunked":
            anchor = r["peak_mb"]
        ratio = f"{r['peak_mb'] / anchor:>17.2f}" if anchor else f"{'-':>17}"
        print(
            f"{case:<18} {r['before_mb']:>14.0f} {r['peak_mb']:>8.0f} "
            f"{r['peak_mb'] - r['before_mb']:>10.0f} {r['seconds']:>8.2f} {ratio}",
            flush=True,
        )


if __name__ == "__main__":
    main()

"""Digests of the DIPOLE runs behind the committed figures: run before and after a change on
the same machine, equal digests say the change left every draw of those runs as it was.

    python tests/fingerprint_runs.py > before.txt     # on the parent commit
    python tests/fingerprint_runs.py > after.txt      # on the change
    diff before.txt after.txt && echo "same draws"

Not part of the test suite (about 2 minutes on 2 cores). A change that keeps behaviour
(a refactor, a faster path, a guard that never acts in these runs) must leave the digests
equal; one that changes draws must regenerate the figures and JSON instead. Digests compare
on one machine only: another CPU's floating-point kernels round differently and long runs
diverge (docs/benchmarks/index.md, *Reproducing the numbers*).

The runs, DIPOLE's default options as each benchmark sets them up:

* ``bench_precision.py``: the cone and the spike, D = 2 and 10, seeds 0 and 1 (trials to each
  precision, the final gap);
* ``bench_multioptima.py``: D ∈ {2, 5, 10}, k ∈ {2, 4, 8}, seeds 0 and 1 (the policy means
  at 500 and 2000 trials);
* ``bench_viapoint_qd.py``: viapoint seeds 0–2 (the routes held at 300 and 1000 trials);
* ``bench_niching.py``: F7 and F9 (Vincent 2-D and 3-D), seeds 0 and 1, at 2000 and 10⁴
  trials (the optima found at each accuracy, the solutions returned, the trials used), and
  the same for ``--suite more``'s double Himmelblau function (4-D), seeds 0 and 1.
"""

from __future__ import annotations

import argparse
import hashlib
import json
import sys
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path

import torch

BENCHMARKS = Path(__file__).resolve().parents[1] / "benchmarks"


def _setup() -> None:
    torch.set_num_threads(1)
    if str(BENCHMARKS) not in sys.path:
        sys.path.insert(0, str(BENCHMARKS))


def precision(case: tuple) -> str:
    _setup()
    import bench_precision

    result = bench_precision.run_case(case)
    return json.dumps([result["trials_to"], result["final_gap"], result["trials"]])


def multioptima(case: tuple[int, int, int]) -> str:
    _setup()
    import bench_multioptima

    d, k, seed = case
    landscape_seed, method_seed = bench_multioptima.case_seeds(d, k, seed)
    landscape = bench_multioptima.make_landscape(d, k, landscape_seed)
    return repr(bench_multioptima.RUNNERS["DIPOLE"](landscape, [500, 2000], method_seed))


def viapoint(seed: int) -> str:
    _setup()
    import bench_viapoint_qd

    return repr(bench_viapoint_qd.run_dipole(seed, [300, 1000]))


def niching(case: tuple[int, int] | tuple[int, int, str]) -> str:
    _setup()
    import bench_niching

    number, seed, *suite = case
    result = bench_niching.run_case(number, seed, "DIPOLE", [2000, 10000], *suite)
    return json.dumps(result["budgets"])  # per budget: optima found, solutions, trials


def digest(text: str) -> str:
    return hashlib.sha256(text.encode()).hexdigest()[:16]


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--workers", type=int, default=2)
    args = parser.parse_args()
    jobs = [
        *((precision, ("precision", (p, d, "DIPOLE", s)))
          for p in ("cone", "spike") for d in (2, 10) for s in range(2)),
        *((multioptima, ("multioptima", (d, k, s)))
          for d in (2, 5, 10) for k in (2, 4, 8) for s in range(2)),
        *((viapoint, ("viapoint", s)) for s in range(3)),
        *((niching, ("niching", (n, s))) for n in (7, 9) for s in range(2)),
        *((niching, ("niching", (3, s, "more"))) for s in range(2)),
    ]  # fmt: skip
    with ProcessPoolExecutor(args.workers) as pool:
        futures = [pool.submit(run, case) for run, (_, case) in jobs]
        lines = [f"{name} {case} {digest(f.result())}"
                 for (_, (name, case)), f in zip(jobs, futures, strict=True)]  # fmt: skip
    for line in lines:
        print(line)
    print("DIGEST", digest("\n".join(lines)))


if __name__ == "__main__":
    main()

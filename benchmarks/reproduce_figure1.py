"""Reproduce Figure 1 of Bruno, Calinon & Caldwell (AAAI 2013): DIPOLE vs PoWER on cart-pole
and mountain car, 50 learning runs per curve, mean ± std of the reward against trials (the
std of the runs, NumPy's default ddof=0, as in every table and figure of the project).

For each task and algorithm, ``--runs`` independent learning runs (seeds 0..runs-1), split in
``--chunks`` jobs spread over ``--workers`` processes, advance in lockstep: every iteration,
each run's ``ask()`` is stacked into one batched ``task.evaluate`` call (tasks are
batch-independent, and every row gets its own random start from the task's start
distribution), and the returns are split back for ``tell()``.

After every tell we record, per run,

* **best policy**: the highest return of the batch just evaluated (one sample per policy;
  the initial batch holds ``n0`` draws from N(θ0, Σ_start)),
* **average policy**: the mean return of that batch,

as step functions of the number of trials (one trial = one episode), sampled on a common grid.
PoWER evaluates one policy per iteration, so its two curves coincide (as in the paper).

Tasks, trial budgets and ``n0`` come from ``configs/task/{cartpole,mountain_car}.yaml``; all
algorithms get the same θ0, Σ_start, n0, M = 5 and reward_range (the paper's "same parameters
as PoWER"). Three curves per plot:

* **DIPOLE** (defaults of ``dipole_torch.Dipole``),
* **PoWER** with Σ_start fixed throughout (Algorithm 3 as written),
* **PoWER, decaying exploration**: the paper's PoWER had its exploration covariance "manually
  reduced when the optimum was reached" on cart-pole; there is no principled moment to do
  that by hand, so this curve uses ``dipole_torch.Power``'s reproducible stand-in,
  Σ_t = Σ_start · max(decay^t, min_exploration), with ``DECAY = 0.98`` and the default
  ``min_exploration = 0.01``. The value was fixed once, before looking at any result, and is
  the same for both tasks: the floor (exploration std at 10 % of its start, which is also
  where DIPOLE's default covariance regularisation keeps its exploration) is reached after
  log(0.01)/log(0.98) ≈ 228 iterations, i.e. about mid-budget of the 490 iterations a
  500-trial run has after n0 = 10 — a slower decay would not reach the floor within the
  budget, a faster one would shrink exploration before PoWER has found the optimum.

Writes ``docs/figures/figure1_cartpole.png``, ``figure1_mountain_car.png`` and
``figure1.json`` (trials grid, means, stds, final values). Run::

    python benchmarks/reproduce_figure1.py            # 50 runs, both tasks
    python benchmarks/reproduce_figure1.py --runs 5   # quick look
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from pathlib import Path

import numpy as np
import torch
from lockstep import load_task, on_grid, plot_best_and_average, quartiles, run_in_lockstep

from dipole_torch import Dipole, Power

ROOT = Path(__file__).resolve().parents[1]
TASKS = {"cartpole": "Cart-pole", "mountain_car": "Mountain car"}
DECAY = 0.98  # PoWER's per-iteration exploration decay; see the module docstring
ALGORITHMS = {  # curve label -> (optimizer, extra keyword arguments)
    # The library's default DIPOLE learns the returns' range from its samples; the paper's
    # variant and PoWER are told the task's range.
    "DIPOLE": (Dipole, {"reward_range": None}),
    "DIPOLE (paper)": (Dipole.paper, {}),
    "PoWER": (Power, {}),
    "PoWER, decaying exploration": (Power, {"exploration_decay": DECAY}),
}
COLORS = {
    "DIPOLE": "tab:blue",
    "DIPOLE (paper)": "tab:cyan",
    "PoWER": "tab:red",
    "PoWER, decaying exploration": "tab:orange",
}
LABELS = {
    "DIPOLE": "DIPOLE",
    "DIPOLE (paper)": "DIPOLE (paper)",
    "PoWER": "PoWER (fixed Σ_start)",
    "PoWER, decaying exploration": f"PoWER, decaying exploration (×{DECAY}/iteration)",
}


def learn(job: tuple) -> tuple[tuple, list[np.ndarray], float]:
    """One job: runs ``seeds`` of ``algo`` on task ``name`` in lockstep.

    Returns the job and, per run, an array of rows ``[trials, best, average]``.
    """
    name, algo, seeds, trials, compile, episode_seed = job
    torch.set_num_threads(1)
    start = time.perf_counter()
    task, _, n0 = load_task(name, compile=compile)
    algorithm, options = ALGORITHMS[algo]
    optimizers = [
        algorithm(
            task.theta0,
            task.sigma_start,
            n0=n0,
            generator=torch.Generator().manual_seed(seed),
            **({"reward_range": task.reward_range} | options),
        )
        for seed in seeds
    ]
    episodes = torch.Generator().manual_seed(episode_seed)  # every episode's random start
    history = run_in_lockstep(task, optimizers, trials, episodes)
    return job, history, time.perf_counter() - start


def make_jobs(
    tasks: list[str], runs: int, chunks: int, budgets: dict, compile: bool
) -> list[tuple]:
    """``learn``'s jobs: per task and algorithm, the runs in ``chunks`` parts (none empty:
    ``--chunks`` above ``--runs`` made jobs of no seeds, an IndexError after the runs), each
    with its generator seed."""
    return [
        (name, algo, seeds.tolist(), budgets[name][0], compile, 1000 + 100 * t + 10 * a + c)
        for t, name in enumerate(tasks)
        for a, algo in enumerate(ALGORITHMS)
        for c, seeds in enumerate(np.array_split(np.arange(runs), chunks))
        if len(seeds)
    ]


def main() -> None:
    from argtypes import Distinct, output_dir, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=positive_int, default=50)
    parser.add_argument(
        "--tasks", nargs="+", action=Distinct, default=list(TASKS), choices=list(TASKS)
    )
    parser.add_argument("--out", type=output_dir, default=ROOT / "docs" / "figures")
    parser.add_argument(
        "--grid-step", type=positive_int, default=10, help="trials between grid points"
    )
    parser.add_argument("--workers", type=positive_int, default=2, help="processes (one per core)")
    parser.add_argument(
        "--chunks", type=positive_int, default=2, help="jobs per task and algorithm"
    )
    parser.add_argument(
        "--compile", action="store_true", help="torch.compile the rollouts (pays ~1 min once)"
    )
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    json_path = args.out / "figure1.json"
    summary = json.loads(json_path.read_text()) if json_path.exists() else {}
    budgets = {name: load_task(name)[1:] for name in args.tasks}
    smallest = min(trials for trials, _ in budgets.values())
    if args.grid_step > smallest:
        parser.error(f"--grid-step {args.grid_step} leaves no grid point in {smallest} trials")
    jobs = make_jobs(args.tasks, args.runs, args.chunks, budgets, args.compile)
    jobs.sort(key=lambda job: job[1] != "DIPOLE")  # longest jobs first: better load balance
    histories: dict = {(name, algo): {} for name in args.tasks for algo in ALGORITHMS}
    seconds: dict = {(name, algo): 0.0 for name in args.tasks for algo in ALGORITHMS}
    start = time.perf_counter()
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        for job, history, elapsed in pool.imap_unordered(learn, jobs):
            name, algo, seeds = job[:3]
            histories[name, algo].update(zip(seeds, history, strict=True))
            seconds[name, algo] += elapsed
            print(f"  {name} {algo} runs {seeds[0]}-{seeds[-1]}: {elapsed:.0f} s", flush=True)
    for name in args.tasks:
        trials, n0 = budgets[name]
        grid = np.arange(args.grid_step, trials + 1, args.grid_step)
        curves = {
            algo: np.stack([on_grid(histories[name, algo][s], grid) for s in range(args.runs)])
            for algo in ALGORITHMS
        }
        for algo, values in curves.items():
            final = values[:, :, -1]
            print(
                f"{name:>12} {algo:>27}: final best {final[:, 0].mean():8.1f} ± "
                f"{final[:, 0].std():6.1f}, average {final[:, 1].mean():8.1f} ± "
                f"{final[:, 1].std():6.1f}"
            )
        plot_best_and_average(
            grid,
            {LABELS[algo]: values for algo, values in curves.items()},
            {LABELS[algo]: COLORS[algo] for algo in curves},
            args.out / f"figure1_{name}.png",
            task_title=TASKS[name],
            ylabel=f"return (mean; band: 25-75 % of {args.runs} runs)",
            suptitle=f"Figure 1 reproduction, {TASKS[name].lower()}: DIPOLE vs PoWER",
            bounds=tuple(load_task(name)[0].reward_range),
        )
        task = load_task(name)[0]
        summary[name] = {
            "runs": args.runs,
            "trials": trials,
            "n0": n0,
            "reward_range": list(task.reward_range),
            "power_exploration_decay": DECAY,
            "cpu_seconds": {algo: round(seconds[name, algo], 1) for algo in ALGORITHMS},
            "trials_grid": grid.tolist(),
            **{
                algo: {
                    f"{kind}_{stat}": getattr(np, stat)(values[:, k], axis=0).round(3).tolist()
                    for k, kind in enumerate(("best", "average"))
                    for stat in ("mean", "std")
                }
                | {
                    f"{kind}_q{q}": np.round(band, 3).tolist()
                    for k, kind in enumerate(("best", "average"))
                    for q, band in zip((25, 75), quartiles(values[:, k]), strict=True)
                }
                | {
                    f"final_{kind}": {
                        "mean": float(values[:, k, -1].mean()),
                        "std": float(values[:, k, -1].std()),
                    }
                    for k, kind in enumerate(("best", "average"))
                }
                for algo, values in curves.items()
            },
        }
    json_path.write_text(json.dumps(summary, indent=1))
    print(f"wrote {args.out}/figure1_*.png and {json_path} in {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()

"""Reproduce Figures 2 and 3 of Bruno, Calinon & Caldwell (AAAI 2013): DIPOLE vs PoWER on the
viapoint task with the simulated Barrett WAM, 10 learning runs per algorithm.

Figure 2: best and average policy reward against trials, mean ± std over the runs. After every
``tell`` we record, per run,

* **best policy**: ``max(opt.last_rewards)``, the highest return of the batch just evaluated
  (one exploratory sample per policy; the initial batch holds ``n0`` draws from
  N(θ0, Σ_start)),
* **average policy**: ``mean(opt.last_rewards)``,

as step functions of the number of trials, sampled on a common grid of trials. PoWER evaluates
one policy per iteration, so its two curves coincide (as in the paper).

Figure 3: the distinct routes found over all DIPOLE runs, one end-effector path per route (the
final policy mean of highest reward that takes it), with the viapoints, start and target.

**Routes found** (the paper's "2.5 different policies per run"): a route is the alternative
viapoint nearest to the arm's path at each pass time (``ViapointTask.route``). A run
*finds* a route when one of its **final policy means**, evaluated without exploration noise,
takes it with reward ≥ 0.9 (``--threshold``). A second, looser count is also reported: the
routes of the samples in the final policies' importance sets (the best M = 5 samples of each
policy, all evaluated with exploration noise) whose reward is ≥ 0.9.

**End-point error**: the distance from the end of each final policy mean's arm path to the
target (``ViapointTask.end_point_error``; eq. 9 does not score it), averaged over the
run's final policy means, then mean ± std over runs (printed in cm, in the JSON in m).

Both algorithms get the task's θ0, Σ_start, n0 = 30, M = 5 and reward range (the paper's "same
parameters as PoWER"); DIPOLE uses the paper's α = 1, m = 10 (``configs/algo/dipole.yaml``
defaults); PoWER keeps Σ_start throughout (``configs/algo/power.yaml``). The task comes from
``configs/task/viapoint.yaml``. The runs of all three algorithms advance in lockstep, split
by seed into ``--workers`` processes: every iteration, their ``ask()`` batches are stacked into
one ``task.evaluate`` call (the task is deterministic and batch-independent, bit for bit, so
the grouping changes no number; a rollout of a few policies costs about as much as one of
dozens, its 140 inverse-kinematics steps being bound by per-operation overhead). Writes
``docs/figures/figure2_viapoint.png``, ``docs/figures/figure3_routes.png`` and
``docs/figures/viapoint.json``::

    python benchmarks/reproduce_viapoint.py            # 10 runs per algorithm, 29 s on 2 cores
    python benchmarks/reproduce_viapoint.py --workers 15   # 43 s, idle 16-core host (last release)
    python benchmarks/reproduce_viapoint.py --runs 2   # quick look
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import time
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from lockstep import (  # noqa: E402
    compose_config,
    load_task,
    on_grid,
    plot_best_and_average,
    quartiles,
    run_in_lockstep,
    save_figure,
)

from dipole_torch import Dipole, Power  # noqa: E402
from dipole_torch.training.hydra_compat import instantiate  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
ALGORITHMS = {"DIPOLE": "dipole", "DIPOLE (paper)": "dipole_paper", "PoWER": "power"}
COLORS = {"DIPOLE": "tab:blue", "DIPOLE (paper)": "tab:cyan", "PoWER": "tab:red"}


def make_optimizer(
    algo: str,
    task,
    n0: int,
    seed: int,
    name: str | None = None,
    overrides: tuple[str, ...] = (),
    task_name: str = "viapoint",
):
    """The optimizer of ``configs/algo/<name>.yaml`` (by default ``ALGORITHMS[algo]``; the
    defaults α = 1, m = 10, M = 5) with the config ``overrides``
    (``algo.optimizer.<option>=<value>``), as ``train.py task=<task_name> algo=<name>``
    builds it (with the task's settings for that algorithm, ``configs/task_algo/``)."""
    config = compose_config(
        f"task={task_name}", f"algo={name or ALGORITHMS[algo]}", *overrides
    ).algo
    optimizer = instantiate(
        config.optimizer,
        theta0=task.theta0.double(),
        sigma_start=task.sigma_start.double(),
        n0=n0,
        reward_range=tuple(task.reward_range) if config.use_task_reward_range else None,
        generator=torch.Generator().manual_seed(seed),
    )
    assert isinstance(optimizer, Dipole if algo.startswith("DIPOLE") else Power)
    return optimizer


def learn(job: tuple) -> tuple[tuple, list[dict], float]:
    """Runs the ``(algo, seed)`` pairs of ``job`` in lockstep; per run its algorithm, history
    and final policies."""
    pairs, threshold = job
    torch.set_num_threads(1)
    start = time.perf_counter()
    task, trials, n0 = load_task("viapoint")
    optimizers = [make_optimizer(algo, task, n0, seed) for algo, seed in pairs]
    history = run_in_lockstep(task, optimizers, trials)
    runs = []
    for (algo, seed), opt, h in zip(pairs, optimizers, history, strict=True):
        means = opt.policy_means.to(task.dtype)
        with torch.no_grad():
            paths = task.trajectory(means)  # [K, T+1, 3] arm paths of the final policy means
        mean_rewards = task.reward(paths).double()
        mean_routes = task.viapoint_distances(paths).argmin(-1).tolist()
        end_errors = task.end_point_error(paths).double()
        kept_routes = task.route(opt.thetas.to(task.dtype)).tolist()
        kept_rewards = opt.rewards.tolist()
        routes = {
            tuple(route): float(r)
            for route, r in sorted(
                zip(mean_routes, mean_rewards.tolist(), strict=True), key=lambda x: x[1]
            )
            if r >= threshold
        }
        sample_routes = {
            tuple(route)
            for route, r in zip(kept_routes, kept_rewards, strict=True)
            if r >= threshold
        }
        runs.append(
            {
                "algo": algo,
                "seed": seed,
                "history": h,
                "policy_means": means.double().tolist(),
                "policy_rewards": mean_rewards.tolist(),
                "policy_routes": mean_routes,
                "policy_end_point_errors_m": end_errors.tolist(),
                "end_point_error_m": float(end_errors.mean()),
                "routes_found": {str(route): r for route, r in sorted(routes.items())},
                "routes_in_samples": sorted(str(route) for route in sample_routes),
                "best_reward_so_far": opt.best()[1],
            }
        )
    return job, runs, time.perf_counter() - start


def main() -> None:
    from argtypes import output_dir, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=positive_int, default=10)
    parser.add_argument("--out", type=output_dir, default=ROOT / "docs" / "figures")
    parser.add_argument(
        "--grid-step", type=positive_int, default=5, help="trials between grid points"
    )
    parser.add_argument("--workers", type=positive_int, default=2, help="processes (one per core)")
    parser.add_argument("--threshold", type=float, default=0.9, help="reward of a found route")
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    task, trials, n0 = load_task("viapoint")
    jobs = [
        ([(algo, int(seed)) for algo in ALGORITHMS for seed in seeds], args.threshold)
        for seeds in np.array_split(np.arange(args.runs), max(1, args.workers))
        if len(seeds)
    ]
    start = time.perf_counter()
    results: dict[str, list[dict]] = {algo: [] for algo in ALGORITHMS}
    seconds = 0.0
    with multiprocessing.get_context("spawn").Pool(args.workers) as pool:
        for (pairs, _), runs, elapsed in pool.imap_unordered(learn, jobs):
            for run in runs:
                results[run["algo"]].append(run)
            seconds += elapsed
            print(f"seeds {pairs[0][1]}..{pairs[-1][1]}: {elapsed:.0f} s", flush=True)
    for algo in ALGORITHMS:
        results[algo].sort(key=lambda run: run["seed"])

    grid = np.arange(n0, trials + 1, args.grid_step)
    curves = {
        algo: np.stack([on_grid(run["history"], grid) for run in runs])
        for algo, runs in results.items()
    }
    plot_best_and_average(
        grid,
        curves,
        COLORS,
        args.out / "figure2_viapoint.png",
        task_title="Viapoint task",
        ylabel=f"reward, eq. 9 (mean; band: 25-75 % of {args.runs} runs)",
        xlabel="trials (reward evaluations)",
        bounds=(0.0, 1.0),
    )

    summary: dict = {
        "description": (
            "Viapoint task (configs/task/viapoint.yaml), DIPOLE vs PoWER. Curves: per iteration "
            "best = max and average = mean of the latest batch's returns (opt.last_rewards), "
            "step-interpolated on the trials grid; mean and std over runs. A route is found "
            "when a final policy mean (no exploration noise) takes it with reward >= threshold; "
            "routes_in_samples counts the routes of the final importance-set samples (with "
            "exploration noise) with reward >= threshold. end_point_error_m: distance (m) from "
            "the end of each final policy mean's arm path to the target, averaged over the "
            "run's final policy means; mean and std over runs."
        ),
        "runs": args.runs,
        "trials": trials,
        "n0": n0,
        "threshold": args.threshold,
        "num_routes_in_layout": int(np.prod(task.num_alternatives)),
        "grid": grid.tolist(),
        "wall_time_s": time.perf_counter() - start,
        "cpu_seconds": seconds,  # all processes together, every algorithm
    }
    best_route_policies: dict[tuple, tuple[float, list[float]]] = {}
    for algo, runs in results.items():
        values = curves[algo]
        found = [len(run["routes_found"]) for run in runs]
        in_samples = [len(run["routes_in_samples"]) for run in runs]
        covered = sorted({route for run in runs for route in run["routes_found"]})
        covered_samples = sorted({route for run in runs for route in run["routes_in_samples"]})
        summary[algo] = {
            "best_mean": np.nanmean(values[:, 0], 0).tolist(),
            "best_std": np.nanstd(values[:, 0], 0).tolist(),
            "average_mean": np.nanmean(values[:, 1], 0).tolist(),
            "average_std": np.nanstd(values[:, 1], 0).tolist(),
            **{
                f"{kind}_q{q}": band.tolist()
                for k, kind in enumerate(("best", "average"))
                for q, band in zip((25, 75), quartiles(values[:, k]), strict=True)
            },
            "final_best": [float(np.nanmean(values[:, 0, -1])), float(np.nanstd(values[:, 0, -1]))],
            "final_average": [
                float(np.nanmean(values[:, 1, -1])),
                float(np.nanstd(values[:, 1, -1])),
            ],
            "final_best_policy_mean_reward": [
                float(np.mean([max(run["policy_rewards"]) for run in runs])),
                float(np.std([max(run["policy_rewards"]) for run in runs])),
            ],
            "routes_per_run": [float(np.mean(found)), float(np.std(found))],
            "end_point_error_m": [
                float(np.mean([run["end_point_error_m"] for run in runs])),
                float(np.std([run["end_point_error_m"] for run in runs])),
            ],
            "routes_covered": covered,
            "routes_per_run_in_samples": [float(np.mean(in_samples)), float(np.std(in_samples))],
            "routes_covered_in_samples": covered_samples,
            "per_run": [
                {key: value for key, value in run.items() if key not in ("algo", "history")}
                | {"num_policies_final": int(run["history"][-1, 3])}
                for run in runs
            ],
        }
        for run in runs:
            for route, reward, theta in zip(
                run["policy_routes"], run["policy_rewards"], run["policy_means"], strict=True
            ):
                key = (algo, tuple(route))
                if reward >= args.threshold and reward > best_route_policies.get(key, (-1,))[0]:
                    best_route_policies[key] = (reward, theta)
        print(
            f"{algo}: final best {summary[algo]['final_best'][0]:.3f} ± "
            f"{summary[algo]['final_best'][1]:.3f}, average {summary[algo]['final_average'][0]:.3f}"
            f" ± {summary[algo]['final_average'][1]:.3f}; routes per run {np.mean(found):.2f} "
            f"(samples: {np.mean(in_samples):.2f}); routes covered {len(covered)}/"
            f"{summary['num_routes_in_layout']} (samples: {len(covered_samples)}); end-point "
            f"error {100 * summary[algo]['end_point_error_m'][0]:.2f} ± "
            f"{100 * summary[algo]['end_point_error_m'][1]:.2f} cm"
        )
    (args.out / "viapoint.json").write_text(json.dumps(summary, indent=1, allow_nan=False))

    # Figure 3: one path per distinct route found by DIPOLE over all runs.
    routes = sorted(route for algo, route in best_route_policies if algo == "DIPOLE")
    if routes:
        thetas = torch.tensor([best_route_policies[("DIPOLE", r)][1] for r in routes])
        counts = [
            sum(str(route) in run["routes_found"] for run in results["DIPOLE"]) for route in routes
        ]
        labels = [
            f"{task.route_name(route)}: r = {best_route_policies[('DIPOLE', route)][0]:.3f}, "
            f"{count}/{args.runs} runs"
            for route, count in zip(routes, counts, strict=True)
        ]
        figure = task.plot_policies(
            thetas.to(task.dtype),
            labels=labels,
            title=f"Viapoint task: {len(routes)} routes found by DIPOLE in {args.runs} runs",
        )
        save_figure(figure, args.out / "figure3_routes.png")
        plt.close(figure)
    print(f"wrote {args.out}/figure2_viapoint.png, figure3_routes.png, viapoint.json")
    print(f"total {time.perf_counter() - start:.0f} s")


if __name__ == "__main__":
    main()

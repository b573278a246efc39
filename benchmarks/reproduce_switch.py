"""Switching routes when the world changes: an obstacle blocks the route a run has learned on
the WAM viapoint task (beyond the paper, which leaves this for future work).

Per run (seed s):

1. DIPOLE (``configs/algo/dipole.yaml``) learns 300 trials on the open layout
   (``configs/task/viapoint.yaml``).
2. A sphere (8 cm, ``configs/task/viapoint_blocked.yaml``'s ``block.radius``) appears on the
   route of its best policy mean: on the viapoint that route passes at the pass time where
   the most other good routes (policy means with return >= 0.9) pass the other alternative
   (``dipole_torch.tasks.viapoint.ViapointTask.blocking_obstacle``). A path that enters the
   sphere keeps ``exp(-depth / 2 cm)`` of its eq. 9 reward.
3. DIPOLE evaluates its K stored policy means once each in the blocked world and is told so,
   ``opt.reevaluate(task.evaluate(opt.policy_means))`` (K trials): its best policy mean
   becomes the policy it executes, and it keeps learning for 300 trials from the block.

Comparisons: PoWER (``configs/algo/power.yaml``) learns 300 trials on the open layout, its
route is blocked by the same rule, it re-evaluates its one policy and continues from it for
300 trials; DIPOLE from scratch learns 300 trials on run s's blocked layout (seed s).

Curves against trials on the blocked layout (from the block; the re-evaluation's K trials
count): ``executed`` = the return of the parameters the run would execute, ``opt.best()``
(the best evaluated in the blocked world: right after the re-evaluation the best stored
policy mean; at 0, the policy mean that was best before the block); ``best`` and ``average``
= max and mean of ``opt.last_rewards`` as in ``reproduce_viapoint.py``. All runs advance in
lockstep (``lockstep.run_in_lockstep``), one batched rollout per iteration, each run's rows
scored on its own layout. Rollouts use the task's default engine (on a CPU the float64
numpy rollout of the URDF's chain: the torch rollout's paths to float rounding, 3-8x
faster). Writes ``docs/figures/figure_switch.png`` and ``docs/figures/switch.json``::

    python benchmarks/reproduce_switch.py --workers 1   # 10 runs
    python benchmarks/reproduce_switch.py --runs 2      # quick look
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import re
import time
import warnings
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402
from lockstep import (  # noqa: E402
    compose_config,
    data_limits,
    load_task,
    on_grid,
    quartiles,
    run_in_lockstep,
    save_figure,
)
from reproduce_viapoint import make_optimizer  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
# The optimizers as train.py task=viapoint_blocked builds them (its settings: no coverage).
TASK = "viapoint_blocked"
# Grid points before a run's first return are NaN; their means over runs are NaN (null).
warnings.filterwarnings("ignore", "Mean of empty slice|Degrees of freedom", RuntimeWarning)
LABELS = {
    "DIPOLE": "DIPOLE: re-evaluate, switch, go on",
    "PoWER": "PoWER: re-evaluate, go on",
    "DIPOLE scratch": "DIPOLE from scratch on the blocked layout",
}
COLORS = {"DIPOLE": "tab:blue", "PoWER": "tab:red", "DIPOLE scratch": "tab:gray"}
# Run records' working keys, not written to the JSON (the curve is, as curve_rows/curve).
INTERNAL = ("rows", "reevaluation_row", "best_offset")


class RecordBest:
    """An optimizer that records ``best()``'s return after every ``tell`` (the rows of
    ``run_in_lockstep`` hold the latest batch only); everything else passes through."""

    def __init__(self, optimizer) -> None:
        self.optimizer = optimizer
        self.best_returns: list[float] = []

    def __getattr__(self, name: str):
        return getattr(self.optimizer, name)

    def tell(self, theta: torch.Tensor, rewards: torch.Tensor) -> None:
        self.optimizer.tell(theta, rewards)
        self.best_returns.append(self.optimizer.best()[1])


def routes_of(task, theta: torch.Tensor, threshold: float) -> tuple[list, list, list]:
    """Returns, routes of ``theta: [K, D]`` on ``task`` and the distinct routes with return
    >= ``threshold``."""
    with torch.no_grad():
        path = task.trajectory(theta.to(task.dtype))
        returns = task.reward(path).double().tolist()
        routes = task.viapoint_distances(path).argmin(-1).tolist()
    good = sorted({tuple(r) for r, v in zip(routes, returns, strict=True) if v >= threshold})
    return returns, routes, good


class PerRunLayouts:
    """The task ``lockstep.run_in_lockstep`` sees when each run has its own obstacles:
    the stacked asks' arm paths are rolled out once (obstacles do not move the arm) and each
    run's rows are scored on its own layout. ``run_in_lockstep`` stacks the pending asks of
    the runs below their ``trials`` (one budget per run), in order: their sizes are the
    optimizers' ``asked_owner``.

    The same rollout also scores every active run's policy means (not trials: evaluation
    rollouts for the record): ``policy_mean_returns[i][trials]`` is the best policy mean's
    return of run i when it had made ``trials`` trials."""

    def __init__(self, tasks: list, optimizers: list, trials: list[int]) -> None:
        self.tasks, self.optimizers, self.trials = tasks, optimizers, trials
        self.dtype = tasks[0].dtype
        self.policy_mean_returns: list[dict[int, float]] = [{} for _ in optimizers]

    def evaluate(self, theta: torch.Tensor, generator=None) -> torch.Tensor:
        active = [i for i, opt in enumerate(self.optimizers) if opt.trials < self.trials[i]]
        sizes = [len(self.optimizers[i].asked_owner) for i in active]
        assert sum(sizes) == theta.shape[0], (sizes, theta.shape)
        means = [self.optimizers[i].policy_means.to(theta) for i in active]
        with torch.no_grad():
            paths = self.tasks[0].trajectory(torch.cat([theta, *means]))
        paths = paths.split(sizes + [len(m) for m in means])
        rewards = [self.tasks[i].reward(p) for i, p in zip(active * 2, paths, strict=True)]
        for i, r in zip(active, rewards[len(active) :], strict=True):
            self.policy_mean_returns[i][self.optimizers[i].trials] = float(r.max())
        return torch.cat(rewards[: len(active)])


def block(task, run: dict, radius: float, threshold: float) -> None:
    """Put the run's obstacle on its best route; re-evaluate its stored policies there."""
    opt = run["opt"]
    means = opt.policy_means
    returns, routes, good = routes_of(task, means, threshold)
    obstacle, description = task.blocking_obstacle(means.to(task.dtype), radius, threshold)
    blocked = task.with_obstacles([obstacle])
    block_trial, best_before = opt.trials, opt.best()[1]
    new_returns = blocked.evaluate(means.to(blocked.dtype))
    opt.reevaluate(new_returns)  # K trials: the world changed
    _, new_routes, new_good = routes_of(blocked, means, threshold)
    executed = int(np.argmax(returns))  # before the block: the best policy mean, now blocked
    run.update(
        task=blocked,
        obstacle=obstacle,
        block=description,
        block_trial=block_trial,
        best_return_before_block=best_before,
        num_policies=len(returns),
        returns_before=returns,
        routes_before=routes,
        good_routes_before=[list(r) for r in good],
        returns_after=new_returns.double().tolist(),
        good_routes_after=[list(r) for r in new_good],
        switched_to_route=new_routes[int(new_returns.argmax())],
        blocked_policy_return=float(new_returns[executed]),
        reevaluation_row=(
            opt.trials,
            float(opt.last_rewards.max()),
            float(opt.last_rewards.mean()),
            opt.num_policies,
        ),
        best_offset=len(opt.best_returns),
    )
    opt.best_returns.append(opt.best()[1])


def finish(run: dict, means: dict[int, float], threshold: float) -> None:
    """The run's final policy means on its blocked layout (completing ``means``, the best
    policy mean's return by trials) and its best return."""
    final = run["opt"].policy_means
    run["final_returns"], run["final_routes"], good = routes_of(run["task"], final, threshold)
    run["final_good_routes"] = [list(r) for r in good]
    run["final_best"] = run["opt"].best()[1]
    means[run["opt"].trials] = max(run["final_returns"])


def curves_since(
    history: np.ndarray, best: list[float], means: dict[int, float], start: int, first=None
) -> np.ndarray:
    """Rows ``[trials since start, best, average, policies, executed, policy mean]`` after each
    tell (``first``: a row at 0 with the executed and policy-mean return only)."""
    mean = [means[int(trials)] for trials in history[:, 0]]
    rows = np.column_stack([history[:, 0] - start, history[:, 1:4], best, mean])
    if first is not None:
        rows = np.vstack([[0.0, np.nan, np.nan, np.nan, first, first], rows])
    return rows


def json_list(values: np.ndarray) -> list:
    """``values`` as nested lists with ``None`` for NaN (no data yet at that trial)."""
    return np.where(np.isnan(values), None, values).tolist()


def compact_json(tree) -> str:
    """``tree`` as JSON, floats rounded to 5 decimals (returns in [0, 1]), every innermost
    list on one line (the curves: one line per run)."""

    def rounded(value):
        if isinstance(value, float):
            return round(value, 5)
        if isinstance(value, dict):
            return {key: rounded(item) for key, item in value.items()}
        if isinstance(value, list | tuple):
            return [rounded(item) for item in value]
        return value

    text = json.dumps(rounded(tree), indent=1, allow_nan=False)
    return re.sub(r"\[[^\[\]{}\"]*\]", lambda m: json.dumps(json.loads(m.group(0))), text)


def trials_to(rows: np.ndarray, column: int, threshold: float) -> int | None:
    """Trials (first column) at which ``column`` first reaches ``threshold`` (None: never)."""
    hit = np.nonzero(rows[:, column] >= threshold)[0]
    return int(rows[hit[0], 0]) if len(hit) else None


def trials_said(reached: list[int | None]) -> str:
    """``trials_to``'s values by run, as printed: ``never`` for a run that did not reach the
    threshold within the budget (``None``, null in the JSON)."""
    return "[" + ", ".join("never" if t is None else str(t) for t in reached) + "]"


def run_seeds(job: tuple) -> tuple[list[int], dict[str, list[dict]], float]:
    """Every algorithm's scenario for ``seeds``: per algorithm, one record per run."""
    seeds, after, radius, threshold = job
    torch.set_num_threads(1)
    start = time.perf_counter()
    task, trials, n0 = load_task("viapoint")  # the default engine: numpy on a CPU
    runs = [
        {
            "algo": algo,
            "seed": s,
            "opt": RecordBest(make_optimizer(algo, task, n0, s, task_name=TASK)),
        }
        for algo in ("DIPOLE", "PoWER")
        for s in seeds
    ]
    optimizers = [run["opt"] for run in runs]
    run_in_lockstep(task, optimizers, trials)  # the open layout
    for run in runs:
        block(task, run, radius, threshold)
    # Each run goes on for `after` trials from its own block: a common end (the latest
    # block + after) gave a run more trials when another run in its process overshot 300.
    end = [run["block_trial"] + after for run in runs]
    layouts = PerRunLayouts([run["task"] for run in runs], optimizers, end)
    histories = run_in_lockstep(layouts, optimizers, end)
    for run, history, means in zip(runs, histories, layouts.policy_mean_returns, strict=True):
        finish(run, means, threshold)
        history = np.vstack([run["reevaluation_row"], history.reshape(-1, 4)])
        best = run["opt"].best_returns[run["best_offset"] :]
        first = run["blocked_policy_return"]
        run["rows"] = curves_since(history, best, means, run["block_trial"], first)
    # DIPOLE from scratch on each DIPOLE run's blocked layout.
    scratch = [
        {
            "algo": "DIPOLE scratch",
            "seed": run["seed"],
            "task": run["task"],
            "obstacle": run["obstacle"],
            "opt": RecordBest(make_optimizer("DIPOLE", task, n0, run["seed"], task_name=TASK)),
        }
        for run in runs
        if run["algo"] == "DIPOLE"
    ]
    optimizers = [run["opt"] for run in scratch]
    budgets = [after] * len(scratch)
    layouts = PerRunLayouts([run["task"] for run in scratch], optimizers, budgets)
    histories = run_in_lockstep(layouts, optimizers, budgets)
    for run, history, means in zip(scratch, histories, layouts.policy_mean_returns, strict=True):
        finish(run, means, threshold)
        run["rows"] = curves_since(history, run["opt"].best_returns, means, 0)
    results = {algo: [run for run in runs + scratch if run["algo"] == algo] for algo in LABELS}
    for run in runs + scratch:
        run["trials_to_threshold"] = trials_to(run["rows"], 4, threshold)
        run["trials_to_threshold_policy_mean"] = trials_to(run["rows"], 5, threshold)
        del run["opt"], run["task"]
    return seeds, results, time.perf_counter() - start


# The curves whose quartile bands switch.json holds: (column of a run's rows, name).
BANDS = ((4, "executed"), (5, "policy_mean"), (1, "best"), (2, "average"))


def plot(grid: np.ndarray, curves: dict, k_mean: float, path: Path, runs: int) -> None:
    """Four panels against trials on the blocked layout, each curve's mean over runs with a
    band from its 25 % to its 75 % quantile: the executed return and the best policy mean's
    (each run too), the best and the average return of the latest batch. The y-axis spans
    the data (within the return's range [0, 1]); the legend sits below the panels."""
    fig, axes = plt.subplots(2, 2, figsize=(13, 8.8), sharey=True)
    low, high = np.inf, -np.inf
    panels = (
        (4, "executed: the best parameters evaluated since the block"),
        (5, "the best policy mean (evaluation rollouts, not trials)"),
        (1, "best of the latest batch"),
        (2, "average of the latest batch"),
    )
    for ax, (column, title) in zip(axes.flat, panels, strict=True):
        for algo, values in curves.items():
            series = values[:, column]
            if column in (4, 5):
                for one in series:
                    ax.step(grid, one, where="post", color=COLORS[algo], alpha=0.25, lw=0.7)
            mean, (q25, q75) = np.nanmean(series, 0), quartiles(series)
            ax.plot(grid, mean, color=COLORS[algo], label=LABELS[algo], lw=1.8)
            ax.fill_between(grid, q25, q75, color=COLORS[algo], alpha=0.15, lw=0)
            low = min(low, np.nanmin(q25), np.nanmin(mean))
            high = max(high, np.nanmax(q75))
        ax.axhline(0.9, color="black", lw=0.8, ls=":")
        ax.axvline(k_mean, color="tab:blue", lw=0.8, ls="--")
        ax.set_title(title, fontsize="medium")
        ax.grid(alpha=0.3)
        ax.set_xlim(grid[0], grid[-1])
    axes[0, 0].set_ylim(*data_limits(low, high, (0.0, 1.0)))
    for ax in axes[1]:
        ax.set_xlabel("trials on the blocked layout (since the block)")
    for ax in axes[:, 0]:
        ax.set_ylabel(f"return with the obstacle (band: 25-75 % of {runs} runs)")
    handles, labels = axes[0, 0].get_legend_handles_labels()
    fig.legend(handles, labels, loc="lower center", ncol=len(labels), frameon=False)
    fig.suptitle(
        "Viapoint task: an obstacle blocks the learned route after 300 trials\n"
        f"(dashed: DIPOLE's re-evaluation of its stored policies, K = {k_mean:.1f} trials on "
        "average; dotted: return 0.9)"
    )
    fig.tight_layout(rect=(0, 0.04, 1, 1))
    save_figure(fig, path)
    plt.close(fig)


def summary_of(runs: list[dict]) -> dict:
    """Trials to the threshold (executed and policy mean), how many runs got there, the
    final returns: over runs."""
    out = {}
    for key in ("trials_to_threshold", "trials_to_threshold_policy_mean"):
        reached = [run[key] for run in runs]
        hit = [t for t in reached if t is not None]
        out[key] = reached
        out[f"{key}_reached"] = f"{len(hit)}/{len(runs)}"
        out[f"{key}_mean_std_median"] = (
            [float(np.mean(hit)), float(np.std(hit)), float(np.median(hit))] if hit else None
        )
    for key, values in (
        ("final_executed", [run["final_best"] for run in runs]),
        ("final_best_policy_mean", [max(run["final_returns"]) for run in runs]),
    ):
        out[key] = [float(np.mean(values)), float(np.std(values))]
    return out


def main() -> None:
    from argtypes import output_dir, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--runs", type=positive_int, default=10)
    parser.add_argument("--workers", type=positive_int, default=2, help="processes (one per core)")
    parser.add_argument("--out", type=output_dir, default=ROOT / "docs" / "figures")
    parser.add_argument(
        "--grid-step", type=positive_int, default=1, help="trials between grid points"
    )
    args = parser.parse_args()
    args.out.mkdir(parents=True, exist_ok=True)
    config = compose_config(f"task={TASK}").task.block
    radius, threshold = float(config.radius), float(config.threshold)
    after = 300  # trials on the blocked layout
    chunks = [c.tolist() for c in np.array_split(np.arange(args.runs), max(1, args.workers))]
    jobs = [(seeds, after, radius, threshold) for seeds in chunks if len(seeds)]
    start = time.perf_counter()
    results: dict[str, list[dict]] = {algo: [] for algo in LABELS}
    cpu_seconds = 0.0
    if args.workers > 1:
        pool = multiprocessing.get_context("spawn").Pool(args.workers)
        outcomes = pool.imap_unordered(run_seeds, jobs)
    else:
        pool, outcomes = None, map(run_seeds, jobs)
    for seeds, runs, elapsed in outcomes:
        for algo in LABELS:
            results[algo].extend(runs[algo])
        cpu_seconds += elapsed
        print(f"seeds {seeds[0]}..{seeds[-1]}: {elapsed:.0f} s", flush=True)
    if pool is not None:
        pool.close()
    for algo in LABELS:
        results[algo].sort(key=lambda run: run["seed"])

    grid = np.arange(0, after + 1, args.grid_step)
    curves = {}  # [runs, 6, G]: the rows' columns on the grid (0 and 3 unused)
    for algo, runs in results.items():
        values = np.full((len(runs), 6, len(grid)), np.nan)
        for r, run in enumerate(runs):
            values[r, 1:3] = on_grid(run["rows"][:, :3], grid)
            values[r, 4:6] = on_grid(run["rows"][:, [0, 4, 5]], grid)
        curves[algo] = values
    dipole = results["DIPOLE"]
    k_mean = float(np.mean([run["num_policies"] for run in dipole]))
    plot(grid, curves, k_mean, args.out / "figure_switch.png", args.runs)

    two_routes = [run for run in dipole if len(run["good_routes_before"]) >= 2]
    switched = [run for run in two_routes if max(run["returns_after"]) >= threshold]
    summary: dict = {
        "description": (
            "Viapoint task (configs/task/viapoint_blocked.yaml): after 300 trials on the open "
            "layout a sphere blocks the route of the run's best policy mean "
            "(ViapointTask.blocking_obstacle); DIPOLE and PoWER re-evaluate their stored policy "
            "means there (opt.reevaluate, K trials) and go on; DIPOLE scratch learns the "
            "blocked layout of the DIPOLE run with the same seed from scratch. Curves against "
            "trials on the blocked layout (since the block, the re-evaluation included): "
            "executed = opt.best()'s return (right after the re-evaluation the best stored "
            "policy mean's; at 0 the return of the policy mean that was best before the block), "
            "policy_mean = the return of the best of the run's policy means (evaluation "
            "rollouts, not counted as trials), best / average = max / mean of "
            "opt.last_rewards, step-interpolated on the grid; mean and std over runs. "
            "trials_to_threshold(_policy_mean): trials on the blocked layout until executed "
            f"(the best policy mean) >= threshold (null: not within {after}). Good routes: "
            "distinct routes of policy means with return >= threshold."
        ),
        "runs": args.runs,
        "trials_before_block": 300,
        "trials_after_block": after,
        "obstacle_radius_m": radius,
        "penetration_scale_m": 0.02,
        "threshold": threshold,
        "grid": grid.tolist(),
        "wall_time_s": time.perf_counter() - start,
        "cpu_seconds": cpu_seconds,
        "dipole_runs_with_two_or_more_routes": len(two_routes),
        "dipole_switch_success": f"{len(switched)}/{len(two_routes)}",
        "dipole_switch_success_rate": len(switched) / len(two_routes) if two_routes else None,
        # Trials on the blocked layout to the threshold (null: not within the budget).
        "dipole_trials_to_threshold_two_route_runs": [r["trials_to_threshold"] for r in two_routes],
        "dipole_trials_to_threshold_one_route_runs": [
            r["trials_to_threshold"] for r in dipole if len(r["good_routes_before"]) < 2
        ],
        "dipole_num_policies_reevaluated": [r["num_policies"] for r in dipole],
    }
    for algo, runs in results.items():
        values = curves[algo]
        summary[algo] = summary_of(runs) | {
            "executed_mean": json_list(np.nanmean(values[:, 4], 0)),
            "executed_std": json_list(np.nanstd(values[:, 4], 0)),
            "policy_mean_mean": json_list(np.nanmean(values[:, 5], 0)),
            "policy_mean_std": json_list(np.nanstd(values[:, 5], 0)),
            "best_mean": json_list(np.nanmean(values[:, 1], 0)),
            "best_std": json_list(np.nanstd(values[:, 1], 0)),
            "average_mean": json_list(np.nanmean(values[:, 2], 0)),
            "average_std": json_list(np.nanstd(values[:, 2], 0)),
            **{
                f"{name}_q{q}": json_list(band)
                for column, name in (
                    (4, "executed"),
                    (5, "policy_mean"),
                    (1, "best"),
                    (2, "average"),
                )
                for q, band in zip((25, 75), quartiles(values[:, column]), strict=True)
            },
            "per_run": [
                {key: value for key, value in run.items() if key not in INTERNAL}
                | {
                    "curve_rows": [
                        "trials_since_block",
                        "best",
                        "average",
                        "policies",
                        "executed",
                        "policy_mean",
                    ],
                    "curve": json_list(run["rows"]),
                }
                for run in runs
            ],
        }
    (args.out / "switch.json").write_text(compact_json(summary))
    print(
        f"DIPOLE: {len(two_routes)}/{args.runs} runs had found >= 2 routes; back at >= "
        f"{threshold} within K trials in {len(switched)}/{len(two_routes)}"
    )
    for algo in LABELS:
        s = summary[algo]
        print(
            f"{algo}: executed reaches {threshold} within {after} trials in "
            f"{s['trials_to_threshold_reached']} runs, trials "
            f"{trials_said(s['trials_to_threshold'])}; best policy mean in "
            f"{s['trials_to_threshold_policy_mean_reached']}, trials "
            f"{trials_said(s['trials_to_threshold_policy_mean'])}; final executed "
            f"{s['final_executed'][0]:.3f} ± {s['final_executed'][1]:.3f}, best policy mean "
            f"{s['final_best_policy_mean'][0]:.3f} ± {s['final_best_policy_mean'][1]:.3f}"
        )
    total = time.perf_counter() - start
    print(f"wrote {args.out}/figure_switch.png, switch.json; total {total:.0f} s")


if __name__ == "__main__":
    main()

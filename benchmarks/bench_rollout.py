"""Rollout throughput: the batched torch cart-pole against gymnasium's CartPole-v1, and the
viapoint task's engines and kinematics paths.

Environment steps per second, linear policy included, for B parallel episodes:

* ``torch``: ``dipole_torch.tasks.cartpole.CartPoleTask.evaluate`` with ``engine="torch"`` (one
  batched rollout, 1000 steps), eager and with ``compile=True`` (its one-off compilation, ~1 min on
  CPU the first time, is excluded from the timing: the warm-up call pays it),
* ``python``: the same ``evaluate`` with ``engine="python"``, the CPU default (one episode at a
  time in Python floats; the LQR gain balances, so no episode stops early; at most 1000 episodes
  are timed, the rate being the same for any B),
* ``gym single``: ``gymnasium.make("CartPole-v1")`` stepped B times in a Python loop
  (the policy evaluated per step in numpy),
* ``gym SyncVectorEnv``: ``gymnasium.vector.SyncVectorEnv`` of B CartPole-v1 copies,
* ``gym numpy vector``: gymnasium's own numpy-vectorised ``CartPoleVectorEnv``
  (``make_vec(..., vectorization_mode="vector_entry_point")``).

Gymnasium's CartPole-v1 takes discrete actions: its policy is ``action = θᵀx > 0``; ours is the
continuous ``u = clip(θᵀx)``. The gymnasium environments reset automatically when an
episode ends; ours freezes failed episodes (the work per step is the same either way).

Viapoint (``--task viapoint``): seconds per
``dipole_torch.tasks.viapoint.ViapointTask.evaluate`` (DS-GMR path, 140-step tracking IK on the
WAM, eq. 9) of B policies drawn around θ0 with the task's exploration std, with the torch engine on
the default kinematics (pytorch-kinematics' forward kinematics and ``chain.jacobian`` on the URDF)
and on the WAM's analytic DH fast path (``kinematics=wam_dh``), and with the numpy engine (the
CPU default: float64 arrays, ``dipole_torch.models.numpy_kinematics``), on the same θ in the
same run, best of ``--repeats`` timings; the ratios are pytorch-kinematics' time over the others'.

Run: ``python benchmarks/bench_rollout.py [--task cartpole|viapoint|all] [--threads N]
[--device cuda]``.
"""

from __future__ import annotations

import argparse
import time

import gymnasium as gym
import numpy as np
import torch
from dipole_torch.tasks.cartpole import CartPoleTask
from dipole_torch.tasks.viapoint import KINEMATICS, ViapointTask

THETA = np.array([0.91, 2.14, 30.9, 7.9])  # an LQR gain: long episodes, few resets


def steps_per_second(run, total_steps: int, repeats: int = 3) -> float:
    """Best of ``repeats`` timings of ``run()`` (which performs ``total_steps`` env steps)."""
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        run()
        best = min(best, time.perf_counter() - start)
    return total_steps / best


def bench_ours(
    batch: int, steps: int, device: str, compile: bool = False, engine: str = "torch"
) -> float:
    task = CartPoleTask(steps=steps, device=device, compile=compile, engine=engine)
    theta = torch.as_tensor(THETA, dtype=torch.float32).expand(batch, 4).contiguous()
    generator = torch.Generator().manual_seed(0)
    task.evaluate(theta[:2], generator)  # warm-up (and compilation)

    def run():
        task.evaluate(theta, generator)
        if device.startswith("cuda"):
            torch.cuda.synchronize()

    return steps_per_second(run, batch * steps)


def bench_gym_single(batch: int, steps: int) -> float:
    env = gym.make("CartPole-v1")
    theta = THETA.astype(np.float32)

    def run():
        for b in range(batch):
            obs, _ = env.reset(seed=b)
            for _ in range(steps):
                obs, _, terminated, truncated, _ = env.step(int(obs @ theta > 0))
                if terminated or truncated:
                    obs, _ = env.reset()

    return steps_per_second(run, batch * steps, repeats=1)


def bench_gym_vector(env: gym.vector.VectorEnv, batch: int, steps: int) -> float:
    theta = THETA.astype(np.float32)

    def run():
        obs, _ = env.reset(seed=0)
        for _ in range(steps):
            obs, *_ = env.step((obs @ theta > 0).astype(np.int64))

    return steps_per_second(run, batch * steps)


def bench_viapoint(batches: tuple[int, ...], device: str, repeats: int) -> list[dict]:
    """Seconds per ``evaluate`` of ``B`` policies for each way of rolling out and batch size:
    rows ``{"B", "pytorch_kinematics", "wam_dh", "numpy"}`` (the torch engine with either
    kinematics path, and the numpy engine, CPU only: ``None`` on another device).

    The variants are timed alternately on the same θ (``repeats`` rounds, best of each), so
    that load from other processes affects them alike."""
    tasks = {
        name: ViapointTask(kinematics=name, engine="torch", device=device) for name in KINEMATICS
    }
    if torch.device(device).type == "cpu":
        tasks["numpy"] = ViapointTask(engine="numpy")
    reference = tasks[KINEMATICS[0]]
    generator = torch.Generator().manual_seed(0)
    std = float(reference.sigma_start[0, 0]) ** 0.5
    rows = []
    for batch in batches:
        noise = torch.randn(batch, reference.parameter_dim, generator=generator)
        theta = (reference.theta0.cpu() + std * noise).to(device)
        best = dict.fromkeys(tasks, float("inf"))
        for task in tasks.values():
            task.evaluate(theta[:2])  # warm-up
        for _ in range(repeats):
            for name, task in tasks.items():
                start = time.perf_counter()
                task.evaluate(theta)
                if device.startswith("cuda"):
                    torch.cuda.synchronize()
                best[name] = min(best[name], time.perf_counter() - start)
        rows.append({"B": batch, "numpy": None, **best})
    return rows


def print_viapoint(rows: list[dict], device: str) -> None:
    steps = ViapointTask().dynamics.steps
    print(
        f"viapoint: seconds per evaluate of B policies ({steps} tracking steps, WAM 7-DOF), "
        f"device {device}, {torch.get_num_threads()} torch threads; torch engine with "
        "pytorch-kinematics (pk) or the analytic DH path, numpy engine (CPU)"
    )
    header = (
        f"{'B':>6} | {'torch, pk':>10} | {'torch, DH':>10} | {'numpy':>8} | pk ÷ DH | pk ÷ numpy"
    )
    print(header)
    print("-" * len(header))
    for row in rows:
        pk, dh, numpy_time = row["pytorch_kinematics"], row["wam_dh"], row["numpy"]
        numpy_cells = (
            f"{numpy_time:>7.4f}s" if numpy_time else f"{'-':>8}",
            f"{pk / numpy_time:9.1f}x" if numpy_time else f"{'-':>10}",
        )
        print(
            f"{row['B']:>6} | {pk:>9.4f}s | {dh:>9.4f}s | {numpy_cells[0]} | "
            f"{pk / dh:6.2f}x | {numpy_cells[1]}"
        )


def main() -> None:
    from argtypes import Distinct, device, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--task", choices=("cartpole", "viapoint", "all"), default="all")
    parser.add_argument("--threads", type=positive_int, default=None, help="torch CPU threads")
    parser.add_argument("--device", type=device, default="cpu")
    parser.add_argument(
        "--steps", type=positive_int, default=1000, help="cart-pole steps per episode"
    )
    parser.add_argument("--no-compile", action="store_true", help="skip the torch.compile variant")
    parser.add_argument(
        "--batches",
        type=positive_int,
        nargs="+",
        action=Distinct,
        default=[1, 10, 100, 1000],
        help="viapoint batch sizes",
    )
    parser.add_argument("--repeats", type=positive_int, default=5, help="viapoint timings per case")
    args = parser.parse_args()
    if args.threads:
        torch.set_num_threads(args.threads)
    if args.task in ("cartpole", "all"):
        bench_cartpole(args)
    if args.task in ("viapoint", "all"):
        rows = bench_viapoint(tuple(args.batches), args.device, args.repeats)
        print_viapoint(rows, args.device)


def bench_cartpole(args: argparse.Namespace) -> None:
    """The cart-pole table: env steps per second, ours against gymnasium's."""
    steps = args.steps
    print(
        f"torch {torch.__version__}, gymnasium {gym.__version__}, device {args.device}, "
        f"{torch.get_num_threads()} torch threads, {steps} steps per episode"
    )
    header = (
        f"{'B':>6} | {'implementation':<24} | {'steps':>9} | {'env steps/s':>12} | "
        "torch ÷ it | compiled ÷ it"
    )
    print(header)
    print("-" * len(header))
    for batch in (1, 100, 10000):
        results: list[tuple[str, int, float]] = []
        results.append(("torch (ours)", steps, bench_ours(batch, steps, args.device)))
        if not args.no_compile:
            rate = bench_ours(batch, steps, args.device, compile=True)
            results.append(("torch compiled", steps, rate))
        episodes = min(batch, 1000)  # one at a time: the rate does not depend on B
        rate = bench_ours(episodes, steps, args.device, engine="python")
        results.append((f"python (ours, B={episodes})", steps, rate))
        single_batch = min(batch, 100)  # a Python loop over envs: B=10000 would take minutes
        results.append(
            (
                f"gym single (B={single_batch})",
                steps,
                bench_gym_single(single_batch, steps),
            )
        )
        sync_steps = steps if batch <= 100 else min(steps, 50)  # slow at B=10000
        sync = gym.vector.SyncVectorEnv([lambda: gym.make("CartPole-v1")] * batch)
        results.append(("gym SyncVectorEnv", sync_steps, bench_gym_vector(sync, batch, sync_steps)))
        sync.close()
        numpy_vec = gym.make_vec(
            "CartPole-v1", num_envs=batch, vectorization_mode="vector_entry_point"
        )
        results.append(("gym numpy vector", steps, bench_gym_vector(numpy_vec, batch, steps)))
        numpy_vec.close()
        ours = results[0][2]
        compiled = None if args.no_compile else results[1][2]
        for name, n_steps, rate in results:
            print(
                f"{batch:>6} | {name:<24} | {n_steps:>9} | {rate:>12.3e} | "
                + ratios(ours, compiled, rate)
            )
    print(
        "steps = time steps per episode measured (SyncVectorEnv at B=10000: 50 only; "
        "'gym single' loops over at most 100 envs one after the other, 'python' over at "
        "most 1000 episodes)."
    )


def ratios(ours: float, compiled: float | None, rate: float) -> str:
    """The table's last two cells: the eager torch rate and the compiled one over ``rate``
    (``-`` under ``--no-compile``, which runs no compiled variant)."""
    cell = "-" if compiled is None else f"{compiled / rate:.2f}x"
    return f"{ours / rate:9.2f}x | {cell:>13}"


if __name__ == "__main__":
    main()

"""Long runs of ``Dipole`` with random options on awkward landscapes, checkpointed and
restored three times a run: a search for the failures that only a long, successful run meets.

    python tests/fuzz_long_runs.py --seeds 100 400           # seeds 100 ... 399
    python tests/fuzz_long_runs.py --seeds 703 704 --budget 600   # one case again
    python tests/fuzz_long_runs.py --seeds 2000 3000 --minutes 30 # as many as fit
    python tests/fuzz_long_runs.py --seeds 0 200 --optimizer power  # the PoWER baseline

Not part of the test suite (a case runs 1000-6000 trials; the whole range takes hours): the
cases it found are tests of their own (``tests/test_hardening.py``, ``test_exploration.py``).
Each seed draws, from its own ``random.Random``:

* a dimension D in {1, 2, 3, 5, 9, 12} and a landscape: Gaussian peaks, a plateau, a needle,
  peaks scaled by 1e150 or 1e-150, −1e6 − |θ|², a constant, steps, a sphere, or a narrow
  cone 1 − √|θ − c|;
* half the time, a random value of every option (``DipoleOptions``), and in 15 % of the cases
  the paper's variant instead of the default one; with ``--optimizer power``, the PoWER
  baseline (``Power``) instead, on the same case, with random values of its own arguments;
* 1000, 3000 or 6000 trials, a box (−4, 4) or none, Σ_start = s·I with s in {1e-3, 1, 1e3};
* in a quarter of the cases, crashed rollouts: a return of −1e6 at about 1 % of the θ asked;
  in a quarter, glitches: a return of +1e6 at about 0.5 % of them; in a quarter, noisy
  returns (Gaussian, std 1 % of |return| + 0.01), with ``best_evaluations`` 1, 2 or 4
  (and in a fifth of the others, ``best_evaluations=4`` on deterministic returns);
* checkpoints (``state_dict`` through ``torch.save``) at a quarter, half and three quarters of
  the trials, each loaded into a new ``Dipole`` built with another generator, which goes on.

A case fails when it raises anything but the clear errors for inputs that the options refuse
(``ValueError``/``TypeError`` of an option set, returns that the reward range refuses:
``reward_range="positive"``, or a fixed range they fall outside), asks an empty or non-finite
batch or one of another size than ``batch_size`` said just before, or ends with non-finite
policy means or a non-finite ``best()``. Printed: one line per failure (seed, error, the
case's settings, the traceback's end), cases slower than a minute,
and the counts of cases, failures and cases refused with a clear error.
"""

from __future__ import annotations

import argparse
import io
import math
import random
import time
import traceback

import torch

from dipole_torch import Dipole, Power

LANDSCAPES = ("multi", "plateau", "needle", "huge", "tiny", "negative", "constant", "steps",
              "sphere", "narrow")  # fmt: skip


def landscape(rng: random.Random, d: int):
    """A landscape ``[B, D] -> [B]`` and its name."""
    kind = rng.choice(LANDSCAPES)
    centres = torch.tensor(
        [[rng.uniform(-3, 3) for _ in range(d)] for _ in range(rng.randint(1, 6))],
        dtype=torch.float64,
    )

    def peaks(theta):
        return torch.exp(-0.5 * torch.cdist(theta, centres).square()).amax(-1)

    def distance(theta):
        return torch.cdist(theta, centres[:1]).squeeze(-1)

    return kind, {
        "multi": peaks,
        "plateau": lambda theta: peaks(theta).clamp(max=0.3),
        "needle": lambda theta: torch.exp(-1e3 * distance(theta)),
        "huge": lambda theta: 1e150 * peaks(theta),
        "tiny": lambda theta: 1e-150 * peaks(theta),
        "negative": lambda theta: -1e6 - theta.square().sum(-1),
        "constant": lambda theta: torch.full(theta.shape[:1], 3.0, dtype=theta.dtype),
        "steps": lambda theta: torch.floor(4 * peaks(theta)),
        "sphere": lambda theta: -theta.square().sum(-1),
        "narrow": lambda theta: 1 - distance(theta).sqrt(),
    }[kind]


def crashing(reward):
    """``reward`` with a crashed rollout, a return of −1e6, at about 1 % of the θ asked (a
    fixed function of θ: the same θ crashes again)."""

    def crashed(theta):
        returns = reward(theta)
        crash = torch.frac(1e3 * theta.sum(-1).abs()) < 0.01
        return torch.where(crash, torch.full_like(returns, -1e6), returns)

    return crashed


def glitching(reward):
    """``reward`` with a glitch, a return of +1e6 (a simulation that blew up), at about 0.5 %
    of the θ asked (a fixed function of θ)."""

    def glitched(theta):
        returns = reward(theta)
        glitch = torch.frac(7e2 * theta.sum(-1).abs() + 0.5) < 0.005
        return torch.where(glitch, torch.full_like(returns, 1e6), returns)

    return glitched


def noisy(reward, seed: int):
    """``reward`` with Gaussian noise of std 0.01·(|return| + 1) (its own seeded stream)."""
    generator = torch.Generator().manual_seed(seed)

    def noised(theta):
        returns = reward(theta)
        noise = torch.randn(returns.shape, generator=generator, dtype=returns.dtype)
        return returns + 0.01 * (returns.abs() + 1.0) * noise

    return noised


def options(rng: random.Random) -> tuple[str, dict]:
    """``("default" | "paper", option changes)``."""
    changes = {}
    if rng.random() < 0.5:
        changes = dict(
            importance=rng.choice(["policy", "global"]),
            exploration=rng.choice(["success", "clustering"]),
            explore=rng.choice([0.0, 0.05, 0.5, 1.0]),
            hill_valley=rng.choice([True, False]),
            pair_points=rng.choice([1, 3]),
            max_policies=rng.choice([None, 1, 2, 8]),
            max_sampled=rng.choice([None, 1, 4]),
            retire_std=rng.choice([0.0, 1e-3, 1e-1]),
            retire_spread=rng.choice([0.0, 1e-4, 1e-2, 1.0]),
            refine=rng.choice([0.0, 0.1, 0.9]),
            refine_share=rng.choice([0.01, 0.2, 0.99]),
            merge_radius=rng.choice([0.0, 1.0, 10.0]),
            settle=rng.choice([None, 1, 3]),
            M=rng.choice([1, 5, 10]),
            alpha=rng.choice([0.01, 1.0, 100.0]),
            m=rng.choice([1, 10]),
            regularization=rng.choice([0.0, 1e-2, 1.0]),
            reward_weighted=rng.choice([True, False]),
            restarts=rng.choice(["box", "start"]),
            auxiliary=rng.choice(["fresh", "reuse"]),
        )
    variant = "paper" if rng.random() < 0.15 else "default"
    if changes and changes["hill_valley"]:  # (drawn last: earlier seeds keep their cases)
        changes["accept_unjudged"] = rng.choice([False, True])
        if changes["accept_unjudged"]:
            changes["unjudged_share"] = rng.choice([None, 0.05, 0.5])
        # (Drawn after the rest: earlier seeds keep their other options.)
        changes["coverage_from"] = rng.choice([None, None, 30, 300, 2000])
        if changes["coverage_from"] and not changes["accept_unjudged"]:
            changes["unjudged_share"] = rng.choice([None, 0.5])
    if changes:  # (drawn last, as above)
        changes["refine_gate"] = rng.choice([0.0, 0.05, 1.0])
        changes["wake_while_active"] = rng.choice([True, False])
        changes["start_cap"] = rng.choice([0.0, 1e-3, 0.25, 10.0])
        changes["success_target"] = rng.choice([0.25, 2.0 / 11.0, 0.02, 0.6])
        changes["coverage_max_policies"] = rng.choice([None, None, 1, 10, 40])
    return variant, changes


def power_options(rng: random.Random) -> dict:
    """Random values of ``Power``'s own arguments (its defaults are the first choices)."""
    return dict(
        M=rng.choice([5, 1, 10]),
        n0=rng.choice([None, 1, 20]),
        reward_range=rng.choice([None, None, (-2e6, 2e6), "positive"]),
        reward_floor=rng.choice([1e-3, 1e-9, 0.5]),
        exploration_decay=rng.choice([1.0, 0.98, 0.5]),
        min_exploration=rng.choice([1e-2, 1e-12, 1.0]),
    )


# What ``run_case`` returns for a case refused with a clear error (its options, or returns
# its reward range cannot map): counted apart, neither a failure nor a run that went well.
REFUSED = "refused"


def refused_input(error: Exception) -> bool:
    """The clear errors for returns that a ``reward_range`` refuses (``"positive"``, the
    paper's default, or a fixed range they fall outside): what a user is told to change, not
    a failure of the optimizer."""
    message = str(error)
    return isinstance(error, ValueError) and (
        "reward_range='positive'" in message or "outside reward_range" in message
    )


def run_case(seed: int, budget: int | None = None, optimizer: str = "dipole") -> str | None:
    """Run one case of ``optimizer`` (``"dipole"`` or ``"power"``); ``None`` if it went
    well, ``REFUSED`` if a clear error refused it, else what went wrong."""
    rng = random.Random(seed)
    d = rng.choice([1, 2, 3, 5, 9, 12])
    kind, reward = landscape(rng, d)
    variant, changes = options(rng)
    trials = rng.choice([1000, 3000, 6000]) if budget is None else budget
    box = rng.random() < 0.4
    bounds = (-4.0 * torch.ones(d, dtype=torch.float64), 4.0 * torch.ones(d, dtype=torch.float64))
    sigma = rng.choice([1e-3, 1.0, 1e3]) * torch.eye(d, dtype=torch.float64)
    theta0 = torch.full((d,), rng.uniform(-1, 1), dtype=torch.float64)
    if rng.random() < 0.25:  # (drawn last: earlier seeds keep their cases)
        kind, reward = f"{kind}+crashes", crashing(reward)
    if rng.random() < 0.25:  # (drawn last, as above)
        kind, reward = f"{kind}+glitches", glitching(reward)
    if rng.random() < 0.25:  # (drawn last, as above)
        kind, reward = f"{kind}+noise", noisy(reward, seed)
        changes["best_evaluations"] = rng.choice([1, 2, 4])
    elif rng.random() < 0.2:  # deterministic returns evaluated again (until found so)
        changes["best_evaluations"] = 4
    if variant == "paper":
        kept = ("M", "alpha", "m", "regularization", "settle", "best_evaluations")
        changes = {k: v for k, v in changes.items() if k in kept}
        if kind in ("negative", "sphere", "narrow"):
            changes["reward_range"] = None
    if optimizer == "power":  # (drawn last, as above) the PoWER baseline on the same case
        variant = "power"
        changes = {**power_options(rng), "best_evaluations": changes.get("best_evaluations", 1)}
    case = (f"d={d} landscape={kind} variant={variant} trials={trials} box={box} "
            f"sigma={float(sigma[0, 0]):g} options={changes}")  # fmt: skip

    def build(generator_seed: int) -> Dipole | Power:
        make = {"paper": Dipole.paper, "power": Power}.get(variant, Dipole)
        generator = torch.Generator().manual_seed(generator_seed)
        return make(theta0, sigma, bounds=bounds if box else None, generator=generator, **changes)

    try:
        opt = build(seed)
    except (ValueError, TypeError):
        return REFUSED  # an option set the options refuse, with their message
    checkpoints = [trials // 4, trials // 2, 3 * trials // 4]
    try:
        while opt.trials < trials:
            size = opt.batch_size  # (train.py fits the next batch to its budget by it)
            theta = opt.ask()
            if theta.shape[0] == 0 or not torch.isfinite(theta).all():
                return f"an empty or non-finite ask at {opt.trials} trials | {case}"
            if theta.shape[0] != size:
                return (
                    f"batch_size {size}, an ask of {theta.shape[0]} rows at {opt.trials} | {case}"
                )
            opt.tell(theta, reward(theta))
            if checkpoints and opt.trials >= checkpoints[0]:
                checkpoints.pop(0)
                buffer = io.BytesIO()
                torch.save(opt.state_dict(), buffer)
                buffer.seek(0)
                restored = build(seed + 1)
                restored.load_state_dict(torch.load(buffer, weights_only=False))
                opt = restored
        if opt.policy_means.numel() and not torch.isfinite(opt.policy_means).all():
            return f"non-finite policy means | {case}"
        best_theta, best_reward = opt.best()
        if not (torch.isfinite(best_theta).all() and math.isfinite(best_reward)):
            return f"a non-finite best() | {case}"
        opt.result  # noqa: B018 (its views must build)
    except Exception as error:  # noqa: BLE001 (every other error is a finding)
        if refused_input(error):
            return REFUSED
        return (f"{type(error).__name__}: {str(error)[:300]} | {case}\n"
                + traceback.format_exc()[-1500:])  # fmt: skip
    return None


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--seeds", type=int, nargs=2, default=[0, 20], metavar=("FIRST", "END"))
    parser.add_argument("--budget", type=int, default=None, help="trials a case (default: drawn)")
    parser.add_argument(
        "--optimizer",
        choices=("dipole", "power"),
        default="dipole",
        help="the optimizer each case runs (power: the PoWER baseline, on the same cases)",
    )
    parser.add_argument("--minutes", type=float, default=None, help="start no case after this")
    parser.add_argument(
        "--every", type=int, default=50, help="a line of progress every this many cases"
    )
    args = parser.parse_args()
    torch.set_num_threads(1)
    failures = cases = refused = 0
    began = time.perf_counter()
    for seed in range(*args.seeds):
        if args.minutes is not None and time.perf_counter() - began > 60 * args.minutes:
            break
        cases += 1
        start = time.perf_counter()
        finding = run_case(seed, args.budget, args.optimizer)
        seconds = time.perf_counter() - start
        if seconds > 60:
            print(f"seed {seed}: slow, {seconds:.0f} s", flush=True)
        if finding == REFUSED:
            refused += 1
        elif finding:
            failures += 1
            print(f"seed {seed}: {finding}", flush=True)
        if cases % args.every == 0:  # (a killed run still reports how far it got)
            minutes = (time.perf_counter() - began) / 60
            print(
                f"... {cases} cases to seed {seed}, {failures} failures, {refused} refused, "
                f"{minutes:.0f} min",
                flush=True,
            )
    print(
        f"{cases} cases (seeds {args.seeds[0]}-{args.seeds[0] + cases - 1}), {failures} failures, "
        f"{refused} refused with a clear error (their options, or returns their reward range "
        "cannot map)"
    )


if __name__ == "__main__":
    main()

"""How many of k equally good optima does each method find? DIPOLE against PoWER and two
multi-optima peers (IPOP-CMA-ES, NMMSO) and random search, on generated landscapes.

    python benchmarks/bench_multioptima.py                      # the full grid, 2 processes
    python benchmarks/bench_multioptima.py --dims 2 --ks 2 4 --seeds 3 --workers 1 \\
        --json /tmp/multioptima.json                            # a quick look
    python benchmarks/bench_multioptima.py --methods DIPOLE --keep-others  # DIPOLE's rows anew

**Landscapes** (``make_landscape``, seeded): k peaks of equal height (k even). Centres
c_i are uniform in [−5, 5]^D, the whole set redrawn until every pair is ≥ 2.0 apart;
w_i = a quarter of the distance from c_i to its nearest other centre. Half the peaks are
smooth bumps g_i(θ) = exp(−½ (θ−c_i)ᵀ A_i⁻¹ (θ−c_i)) with a random anisotropic covariance
A_i = R diag(s²) Rᵀ (R a uniformly random rotation, s_j = w_i·U(0.5, 1.5)); the other half are
sharp peaks g_i(θ) = exp(−‖θ−c_i‖ / w_i) (the value falls linearly with distance near the
top). The return is f(θ) = b + h·max_i g_i(θ) with a random scale h = 10^U(−3, 3) and offset
b = h·U(−2, 2) per landscape, so a method that needs to be told the reward scale is told it
(DIPOLE's paper variant and PoWER get the true range (b, b + h)) and the others must do
without. Each peak has a **width**: min_j s_j for a bump, w_i for a sharp peak.

**Found.** Optimum i is found when some returned solution x has ‖x − c_i‖ ≤ 0.1·width_i and
f(x) ≥ b + 0.99·h (evaluated by the benchmark, not charged to the method). A solution can only
find the optimum it is nearest to in width units (the 0.1·width balls are disjoint anyway);
several solutions on one optimum count once. The score of a run is the number of distinct
optima found, out of k.

**Methods.** Every method gets the same trial budget (one trial = one evaluation of f) and
never uses more: a batch that would cross the budget is not evaluated, or, where the method
allows it, only its first points are (CMA-ES's best-so-far, NMMSO, random search). Each starts
from what it would be given on an unknown problem in the box [−5, 5]^D:

* **DIPOLE**: ``Dipole(0, 2.5²·I, bounds=(−5, 5), generator=…)``, the library's defaults
  and no reward range (it must cope with any scale by itself). Returned: the final policy
  means. Like the peers it is told the box: its samples are clipped into it.
* **DIPOLE (paper)**: ``Dipole.paper(0, 2.5²·I, reward_range=(b, b + h), bounds=(−5, 5),
  generator=…)``, the paper's variant, told the true reward range. Returned: the final
  policy means.
* **PoWER**: ``Power(0, 2.5²·I, reward_range=(b, b + h), exploration_decay=0.98,
  bounds=(−5, 5), …)``: one policy, with decaying exploration (fairer than a fixed Σ, which
  could never home in on a peak). Returned: its final mean (one solution).
* **IPOP-CMA-ES**: pycma's ``CMAEvolutionStrategy`` in an ask/tell loop (so the budget is
  exact), bounds [−5, 5], sigma0 = 2.5 (a quarter of the box width, pycma's advice), x0
  uniform in the box at every restart, population 4 + ⌊3 ln D⌋ doubled at each restart, a
  restart whenever pycma's own ``stop()`` says so, with ``tolx`` = 1e-3·sigma0 (the precision
  at which DIPOLE retires a policy; pycma's default 1e-11 spends most of the budget far below
  what "found" needs, about 3 restarts in 2000 trials at D = 2) and no tolerance on f (the
  landscapes' scale spans 10^±3). Returned: every restart's best evaluated
  point (the running restart's best so far included).
* **NMMSO**: pynmmso's ``Nmmso`` with its defaults on [−5, 5]^D, maximising f, halted at the
  budget's evaluation. Returned: its mode locations (one per swarm). Its algorithm never reads
  the budget (``run(n)`` only loops ``iterate()`` until n evaluations have been made), so
  the modes at budget B are snapshotted inside the run that goes on to the larger budget, at
  the moment the (B+1)-th evaluation is requested: exactly the state of a separate run halted
  at B (``tests/test_bench_multioptima.py`` checks this). Two patches, made here and undone
  after each run (site-packages is untouched): pynmmso calls ``random.sample`` on a set, which
  Python ≥ 3.11 refuses, so its module sees a ``sample`` that sorts a set by swarm id first;
  and swarms hash by their id, so that iterating over the set of swarms (and with it the
  draws) is the same in every run.
* **random search**: uniform samples in the box. Returned: in each peak's basin (the points
  where that peak's term h·g_i is the largest; an oracle partition that favours random
  search), the best sample.

Both budgets (500 and 2000 trials) come from one run per (landscape, method): the state at
budget B is the one after the last evaluation with trials ≤ B (for DIPOLE and PoWER the last
``tell`` that stays within B), which for every method here is what a separate run with budget
B would return. Every stochastic method is seeded from the case (D, k, seed); the global
``random`` / ``numpy.random`` state that pycma and pynmmso draw from is seeded per run and
restored afterwards, so reruns give the same numbers.

Work is spread over ``--workers`` processes (spawned, one torch thread each), one task per
(landscape, method). Printed: optima found per method, D and budget, summed over k and seeds
("found/total"), a per-k breakdown, the mean number of returned solutions, and each method's
time summed over its tasks. Everything, with per-case results, goes to ``--json``
(default ``docs/figures/multioptima.json``).
"""

from __future__ import annotations

import argparse
import contextlib
import functools
import importlib
import json
import math
import multiprocessing
import random
import sys
import time
import types
import warnings
from collections.abc import Callable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
import torch
from torch import Tensor

sys.path.insert(0, str(Path(__file__).resolve().parent))
from setting import machine, version  # noqa: E402

from dipole_torch import Dipole, Power  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
DTYPE = torch.float64
BOX = 5.0  # the search box is [-BOX, BOX]^D
MIN_SEPARATION = 2.0  # between any two centres
SIGMA0 = 2.5  # initial exploration std of every method that has one: a quarter of the box
FOUND_RADIUS = 0.1  # in units of the peak's width
FOUND_LEVEL = 0.99  # fraction of the height h above the offset b
METHODS = ("DIPOLE", "DIPOLE (paper)", "PoWER", "IPOP-CMA-ES", "NMMSO", "random search")
# Run when asked for (--methods): DIPOLE with every clustering running all its sweeps
# (``settle=None, scout_sweeps=None``; the default ends one once its partition settles and
# gives a clustering of scouts alone one sweep), and DIPOLE with the
# options for covering alternatives (the preset configs/algo/dipole_coverage.yaml, as
# bench_viapoint_qd.py's "DIPOLE (coverage)"), and the defaults until trial 300 with the
# coverage options from then on (``coverage_from=300, unjudged_share=0.5``), to measure each
# option's effect beside the defaults.
OPT_IN = ("DIPOLE (all sweeps)", "DIPOLE (coverage)", "DIPOLE (coverage from 300)")
DIMS = (2, 5, 10)
KS = (2, 4, 8)
SEEDS = 10
BUDGETS = (500, 2000)


# ---------------------------------------------------------------------------------- landscapes
@dataclass(frozen=True)
class Landscape:
    """f(θ) = b + h·max_i g_i(θ): k peaks of height b + h at the centres.

    Attributes:
        centres: ``[k, D]`` peak locations c_i.
        precisions: ``[k, D, D]`` A_i⁻¹ of the bumps (identity, unused, for sharp peaks).
        sharp: ``[k]`` True for a sharp peak exp(−‖θ−c_i‖ / w_i), False for a bump.
        scales: ``[k]`` w_i, a quarter of the distance to the nearest other centre.
        widths: ``[k]`` the width of the success criterion (min_j s_j, or w_i).
        height: h > 0.
        offset: b.
        seed: the generator seed it was made with.
    """

    centres: Tensor
    precisions: Tensor
    sharp: Tensor
    scales: Tensor
    widths: Tensor
    height: float
    offset: float
    seed: int

    @property
    def dim(self) -> int:
        return int(self.centres.shape[1])

    @property
    def k(self) -> int:
        return int(self.centres.shape[0])

    @property
    def lower(self) -> Tensor:
        """``[D]`` the search box's lower corner (−BOX on every axis)."""
        return torch.full((self.dim,), -BOX, dtype=DTYPE)

    @property
    def upper(self) -> Tensor:
        """``[D]`` the search box's upper corner (+BOX on every axis)."""
        return torch.full((self.dim,), BOX, dtype=DTYPE)

    @property
    def reward_range(self) -> tuple[float, float]:
        """``(b, b + h)``: every value of f lies in it."""
        return self.offset, self.offset + self.height

    def peaks(self, theta: Tensor) -> Tensor:
        """``[B, k]`` every peak's g_i at ``theta: [B, D]``, in [0, 1]."""
        diff = theta.to(DTYPE)[:, None, :] - self.centres  # [B, k, D]
        mahalanobis = torch.einsum("bkd,kde,bke->bk", diff, self.precisions, diff)
        bump = torch.exp(-0.5 * mahalanobis)
        sharp = torch.exp(-diff.norm(dim=-1) / self.scales)
        return torch.where(self.sharp, sharp, bump)

    def __call__(self, theta: Tensor) -> Tensor:
        """``[B]`` float64 returns of ``theta: [B, D]``."""
        return self.offset + self.height * self.peaks(theta).max(dim=-1).values

    def basin(self, theta: Tensor) -> Tensor:
        """``[B]`` index of the peak whose term is the largest at each of ``theta: [B, D]``."""
        return self.peaks(theta).argmax(dim=-1)

    def found(self, solutions: Tensor) -> Tensor:
        """``[k]`` bool: which optima the returned ``solutions: [n, D]`` find.

        A solution x finds the optimum i nearest to it in width units if
        ‖x − c_i‖ ≤ 0.1·width_i and f(x) ≥ b + 0.99·h.
        """
        out = torch.zeros(self.k, dtype=torch.bool)
        x = solutions.to(DTYPE).reshape(-1, self.dim)
        if x.shape[0] == 0:
            return out
        # Explicit differences, not cdist: an exact centre must be at distance exactly 0.
        relative = (x[:, None, :] - self.centres).norm(dim=-1) / self.widths  # [n, k]
        distance, nearest = relative.min(dim=1)
        hit = (distance <= FOUND_RADIUS) & (self(x) >= self.offset + FOUND_LEVEL * self.height)
        out[nearest[hit]] = True
        return out

    def summary(self) -> dict:
        """JSON-ready parameters (no centres: they follow from ``seed``)."""
        separation = torch.cdist(self.centres, self.centres)
        separation.fill_diagonal_(math.inf)
        return {
            "seed": self.seed,
            "height": self.height,
            "offset": self.offset,
            "min_separation": float(separation.min()),
            "sharp": self.sharp.tolist(),
            "widths": [round(w, 6) for w in self.widths.tolist()],
        }


def random_rotation(dim: int, generator: torch.Generator) -> Tensor:
    """``[D, D]`` a uniformly random rotation (QR of a Gaussian matrix, signs fixed)."""
    q, r = torch.linalg.qr(torch.randn(dim, dim, generator=generator, dtype=DTYPE))
    q = q * torch.sign(torch.diagonal(r))
    if torch.det(q) < 0:
        q[:, 0] = -q[:, 0]
    return q


def grid_error(dims: Sequence[int], ks: Sequence[int]) -> str | None:
    """Why a grid of ``--dims`` and ``--ks`` has a case with no landscape, or None.

    On a line, k centres ``MIN_SEPARATION`` apart fill (k − 1)·``MIN_SEPARATION`` of the box's
    width 2·``BOX``: at that width or beyond, the uniform draws of ``make_landscape`` never
    meet the separation (from D = 2 up, k ≤ 8 fits with room)."""
    most = math.ceil(2.0 * BOX / MIN_SEPARATION)  # the largest k with (k − 1)·sep < 2·BOX
    if 1 in dims and max(ks) > most:
        return (
            f"k = {max(ks)} centres {MIN_SEPARATION} apart do not fit in [-{BOX}, {BOX}] "
            f"(D = 1 takes k ≤ {most})"
        )
    return None


def make_landscape(dim: int, k: int, seed: int) -> Landscape:
    """The landscape of the module docstring: k/2 bumps then k/2 sharp peaks, drawn from
    ``torch.Generator().manual_seed(seed)``."""
    if k < 2 or k % 2:
        raise ValueError(f"k must be a positive even number, got {k}")
    if (error := grid_error([dim], [k])) is not None:
        raise ValueError(error)
    g = torch.Generator().manual_seed(seed)
    for _ in range(100_000):
        # Redraw the whole set (not one centre at a time): uniform given the separation.
        centres = BOX * (2.0 * torch.rand(k, dim, generator=g, dtype=DTYPE) - 1.0)
        separation = torch.cdist(centres, centres)
        separation.fill_diagonal_(math.inf)
        if separation.min() >= MIN_SEPARATION:
            break
    else:
        raise RuntimeError(f"no {k} centres {MIN_SEPARATION} apart in [-{BOX}, {BOX}]^{dim}")
    scales = separation.min(dim=1).values / 4.0
    sharp = torch.arange(k) >= k // 2
    precisions = torch.eye(dim, dtype=DTYPE).repeat(k, 1, 1)
    widths = scales.clone()
    for i in range(k // 2):
        rotation = random_rotation(dim, g)
        s = scales[i] * (0.5 + torch.rand(dim, generator=g, dtype=DTYPE))
        precisions[i] = rotation @ torch.diag(s.pow(-2)) @ rotation.T
        widths[i] = s.min()
    u = torch.rand(2, generator=g, dtype=DTYPE).tolist()
    height = 10.0 ** (6.0 * u[0] - 3.0)
    offset = height * (4.0 * u[1] - 2.0)
    return Landscape(centres, precisions, sharp, scales, widths, height, offset, seed)


def case_seeds(dim: int, k: int, seed: int) -> tuple[int, int]:
    """The landscape's and the methods' seeds for case (D, k, seed)."""
    landscape_seed, method_seed = np.random.SeedSequence([dim, k, seed]).generate_state(2)
    return int(landscape_seed), int(method_seed)


# ------------------------------------------------------------------------------------- methods
# A runner takes (landscape, sorted budgets, seed) and returns, per budget, the returned
# solutions [n, D] and the trials used when they were taken. The runners of DIPOLE,
# IPOP-CMA-ES and NMMSO take any problem with ``dim``, ``lower`` and ``upper`` (``[D]`` box
# corners) and ``__call__(theta [B, D]) -> [B]``, so that benchmarks/bench_niching.py runs
# them too.
Snapshots = dict[int, tuple[Tensor, int]]


def _run_ask_tell(opt, landscape: Landscape, budgets: Sequence[int]) -> Snapshots:
    """Ask/tell ``opt`` (a Dipole or Power) until its next batch would cross the largest
    budget; per budget, the policy means after the last tell within it."""
    snapshots = {b: (opt.policy_means.clone(), 0) for b in budgets}
    while True:
        theta = opt.ask()
        if opt.trials + theta.shape[0] > budgets[-1]:
            break  # not evaluated: it would cross the budget
        opt.tell(theta, landscape(theta))
        for b in budgets:
            if opt.trials <= b:
                snapshots[b] = (opt.policy_means.clone(), opt.trials)
    return snapshots


def _start(problem) -> tuple[Tensor, Tensor, tuple[Tensor, Tensor]]:
    """What an ask/tell method is told about a problem's box [l, u]: θ0 = its centre,
    Σ_start = diag(((u − l)/4)²) and ``bounds`` = (l, u). On the landscapes: θ0 = 0,
    Σ_start = 2.5²·I, bounds (−5, 5)."""
    theta0 = 0.5 * (problem.lower + problem.upper)
    sigma_start = torch.diag((0.25 * (problem.upper - problem.lower)).square())
    return theta0, sigma_start, (problem.lower, problem.upper)


def run_dipole(
    landscape: Landscape, budgets: Sequence[int], seed: int, **changes: Any
) -> Snapshots:
    theta0, sigma_start, bounds = _start(landscape)
    generator = torch.Generator().manual_seed(seed)
    opt = Dipole(theta0, sigma_start, bounds=bounds, generator=generator, **changes)
    return _run_ask_tell(opt, landscape, budgets)


def run_dipole_all_sweeps(landscape: Landscape, budgets: Sequence[int], seed: int) -> Snapshots:
    return run_dipole(landscape, budgets, seed, settle=None, scout_sweeps=None)


def coverage_options() -> dict:
    """The options ``configs/algo/dipole_coverage.yaml`` sets (``algo=dipole_coverage``)."""
    from omegaconf import OmegaConf

    preset = OmegaConf.load(Path(__file__).parents[1] / "configs/algo/dipole_coverage.yaml")
    return OmegaConf.to_container(preset.optimizer)


def run_dipole_coverage(landscape: Landscape, budgets: Sequence[int], seed: int) -> Snapshots:
    return run_dipole(landscape, budgets, seed, **coverage_options())


# The options of the opt-in row "DIPOLE (coverage from 300)": the defaults until trial 300,
# the coverage options (their samples held to half) from then on.
COVERAGE_FROM_300 = {"coverage_from": 300, "unjudged_share": 0.5}


def run_dipole_coverage_from(landscape: Landscape, budgets: Sequence[int], seed: int) -> Snapshots:
    return run_dipole(landscape, budgets, seed, **COVERAGE_FROM_300)


def run_dipole_paper(landscape: Landscape, budgets: Sequence[int], seed: int) -> Snapshots:
    theta0, sigma_start, bounds = _start(landscape)
    opt = Dipole.paper(
        theta0,
        sigma_start,
        reward_range=landscape.reward_range,
        bounds=bounds,
        generator=torch.Generator().manual_seed(seed),
    )
    return _run_ask_tell(opt, landscape, budgets)


def run_power(landscape: Landscape, budgets: Sequence[int], seed: int) -> Snapshots:
    theta0, sigma_start, bounds = _start(landscape)
    opt = Power(
        theta0,
        sigma_start,
        reward_range=landscape.reward_range,
        exploration_decay=0.98,
        bounds=bounds,
        generator=torch.Generator().manual_seed(seed),
    )
    return _run_ask_tell(opt, landscape, budgets)


@contextlib.contextmanager
def _global_rngs(seed: int) -> Iterator[None]:
    """Seed ``random`` and ``numpy.random`` (pycma and pynmmso draw from them), then restore."""
    saved = random.getstate(), np.random.get_state()
    random.seed(seed)
    np.random.seed(seed % 2**32)
    try:
        yield
    finally:
        random.setstate(saved[0])
        np.random.set_state(saved[1])


CMA_TOLX = 1e-3  # restart once the step size is below this times sigma0


def _cma_box(problem) -> tuple[list, float, list[float] | None, int]:
    """pycma's view of the problem's box: ``bounds`` (numbers when every axis shares them,
    as on the landscapes), sigma0 (a quarter of the widest side), ``CMA_stds`` (each side's
    quarter relative to sigma0, ``None`` when all sides are equal) and the dimension pycma
    searches. pycma does not support 1-D optimization (it warns that it "may bail or work
    poorly"), so a 1-D problem gets a second coordinate in [−1, 1] that the function
    ignores."""
    lower, upper = problem.lower.tolist(), problem.upper.tolist()
    if problem.dim == 1:
        lower, upper = lower + [-1.0], upper + [1.0]
    widths = [hi - lo for lo, hi in zip(lower, upper, strict=True)]
    sigma0 = max(widths) / 4.0
    same = len(set(lower)) == 1 and len(set(upper)) == 1
    bounds = [lower[0], upper[0]] if same else [lower, upper]
    stds = None if len(set(widths)) == 1 else [w / 4.0 / sigma0 for w in widths]
    return bounds, sigma0, stds, len(lower)


def ipop_restart(problem, restart: int, rng: np.random.Generator):
    """IPOP-CMA-ES's ``restart``-th run (from 0) on ``problem``'s box: pycma's
    ``CMAEvolutionStrategy`` from a point uniform in the box, its population
    4 + ⌊3 ln D⌋ doubled at each restart, its seed and start drawn from ``rng``."""
    import cma

    bounds, sigma0, stds, searched = _cma_box(problem)
    lower, upper = np.array(bounds[0]), np.array(bounds[1])
    options = {
        "bounds": bounds,
        "popsize": (4 + int(3 * math.log(searched))) * 2**restart,  # IPOP: doubled
        "seed": int(rng.integers(1, 2**31 - 1)),
        "verbose": -9,
        "verb_log": 0,
        "verb_disp": 0,
        # Restart once the step size is below what "found" needs (1e-3·sigma0, the
        # precision at which DIPOLE retires a policy), not at pycma's default 1e-11:
        # converging further only spends trials that the next restart could use.
        # No tolerance on f: the landscapes' scale spans 10^±3.
        "tolx": CMA_TOLX * sigma0,
        "tolfun": 0.0,
        "tolfunhist": 0.0,
    }
    if stds is not None:
        options["CMA_stds"] = stds
    return cma.CMAEvolutionStrategy(rng.uniform(lower, upper, searched), sigma0, options)


def run_ipop_cmaes(landscape: Landscape, budgets: Sequence[int], seed: int) -> Snapshots:
    d = landscape.dim
    rng = np.random.default_rng(seed)
    top = budgets[-1]
    used = restarts = 0
    bests: list[tuple[np.ndarray, float]] = []  # finished restarts' best (x, f)
    snapshots: Snapshots = {}

    def returned(current: tuple[np.ndarray, float] | None) -> Tensor:
        points = [x for x, _ in bests] + ([] if current is None else [current[0]])
        return torch.as_tensor(np.array(points), dtype=DTYPE).reshape(-1, d)

    with _global_rngs(seed), warnings.catch_warnings():
        warnings.simplefilter("ignore")  # pycma's notes on flat fitness etc.
        while used < top:
            es = ipop_restart(landscape, restarts, rng)
            restarts += 1
            best: tuple[np.ndarray, float] | None = None
            while used < top and not es.stop():
                asked = es.ask()
                n = min(len(asked), top - used)  # the first n fit the budget
                x = np.array(asked[:n])[:, :d]  # (a 1-D problem's unused coordinate dropped)
                values = landscape(torch.as_tensor(x, dtype=DTYPE)).numpy()
                for b in budgets:
                    if used < b <= used + n:  # best so far after exactly b evaluations
                        i = int(values[: b - used].argmax())
                        prefix = (x[i], float(values[i]))
                        running = prefix if best is None or prefix[1] > best[1] else best
                        snapshots[b] = (returned(running), b)
                i = int(values.argmax())
                if best is None or values[i] > best[1]:
                    best = (x[i].copy(), float(values[i]))
                used += n
                if n < len(asked):
                    break  # a partial batch cannot be told; the budget is spent anyway
                es.tell(asked, (-values).tolist())  # pycma minimises
            if best is not None:
                bests.append(best)
    return snapshots


class _BudgetSpent(Exception):
    pass


class _NmmsoProblem:
    """pynmmso's problem interface on a landscape: counts evaluations, snapshots the modes
    when the (B+1)-th is requested, and halts the run when the largest budget is spent."""

    def __init__(self, landscape: Landscape, budgets: Sequence[int]):
        self.landscape = landscape
        self.budgets = budgets
        self.used = 0
        self.nmmso = None
        self.snapshots: Snapshots = {}

    def get_bounds(self) -> tuple[list[float], list[float]]:
        return self.landscape.lower.tolist(), self.landscape.upper.tolist()

    def modes(self) -> Tensor:
        swarms = sorted(self.nmmso.swarms, key=lambda s: s.id)
        points = np.array([s.mode_location for s in swarms], dtype=float)
        return torch.as_tensor(points, dtype=DTYPE).reshape(-1, self.landscape.dim)

    def fitness(self, x: np.ndarray) -> float:
        if self.used in self.budgets:
            self.snapshots[self.used] = (self.modes(), self.used)
        if self.used >= self.budgets[-1]:
            raise _BudgetSpent
        self.used += 1
        return float(self.landscape(torch.as_tensor(x, dtype=DTYPE).reshape(1, -1)))


def _sample(population, k: int):
    """``random.sample`` that accepts pynmmso's sets of swarms (sorted by id: deterministic)."""
    if isinstance(population, set | frozenset):
        population = sorted(population, key=lambda swarm: swarm.id)
    return random.sample(population, k)


@contextlib.contextmanager
def _patched_pynmmso() -> Iterator[None]:
    """pynmmso with the two patches of the module docstring, undone on exit."""
    import pynmmso.pynmmso as core
    import pynmmso.swarm as swarm_module

    saved_random = core.random
    core.random = types.SimpleNamespace(
        random=random.random, randrange=random.randrange, sample=_sample
    )
    swarm_module.Swarm.__hash__ = lambda swarm: swarm.id
    try:
        yield
    finally:
        core.random = saved_random
        del swarm_module.Swarm.__hash__


def run_nmmso(landscape: Landscape, budgets: Sequence[int], seed: int) -> Snapshots:
    from pynmmso import Nmmso, SequentialFitnessCaller

    problem = _NmmsoProblem(landscape, budgets)
    with _patched_pynmmso(), _global_rngs(seed):
        # A fresh fitness caller: the default argument is one instance shared by all runs.
        problem.nmmso = Nmmso(problem, fitness_caller=SequentialFitnessCaller())
        try:
            while True:
                problem.nmmso.iterate()
        except _BudgetSpent:
            pass
    return problem.snapshots


def run_random_search(landscape: Landscape, budgets: Sequence[int], seed: int) -> Snapshots:
    g = torch.Generator().manual_seed(seed)
    theta = BOX * (2.0 * torch.rand(budgets[-1], landscape.dim, generator=g, dtype=DTYPE) - 1.0)
    values = landscape(theta)
    basins = landscape.basin(theta)
    snapshots: Snapshots = {}
    for b in budgets:
        best = []
        for i in range(landscape.k):
            members = torch.nonzero(basins[:b] == i).flatten()
            if members.numel():
                best.append(theta[members[values[members].argmax()]])
        points = torch.stack(best) if best else theta[:0]
        snapshots[b] = (points, b)
    return snapshots


RUNNERS: dict[str, Callable[[Landscape, Sequence[int], int], Snapshots]] = {
    "DIPOLE": run_dipole,
    "DIPOLE (paper)": run_dipole_paper,
    "DIPOLE (all sweeps)": run_dipole_all_sweeps,
    "DIPOLE (coverage)": run_dipole_coverage,
    "DIPOLE (coverage from 300)": run_dipole_coverage_from,
    "PoWER": run_power,
    "IPOP-CMA-ES": run_ipop_cmaes,
    "NMMSO": run_nmmso,
    "random search": run_random_search,
}


# ----------------------------------------------------------------------------------- one case
def run_timed(runner, problem, budgets: Sequence[int], seed: int, method: str):
    """``(snapshots, seconds)`` of ``runner(problem, budgets, seed)``; raises if a snapshot
    used more trials than its budget."""
    start = time.perf_counter()
    snapshots = runner(problem, budgets, seed)
    seconds = time.perf_counter() - start
    for b in budgets:
        if snapshots[b][1] > b:
            raise AssertionError(f"{method} used {snapshots[b][1]} trials for budget {b}")
    return snapshots, seconds


def run_case(dim: int, k: int, seed: int, method: str, budgets: Sequence[int]) -> dict:
    """Run ``method`` on case (D, k, seed) up to the largest budget.

    Returns:
        A JSON-ready dict: the case, the landscape summary, per budget ``found`` (distinct
        optima found), ``returned`` (number of returned solutions) and ``trials`` (trials
        used), and ``seconds`` (the method's run, landscape evaluations included).
    """
    budgets = sorted({int(b) for b in budgets})
    if budgets[0] < 1:
        raise ValueError(f"budgets must be positive, got {budgets}")
    landscape_seed, method_seed = case_seeds(dim, k, seed)
    landscape = make_landscape(dim, k, landscape_seed)
    snapshots, seconds = run_timed(RUNNERS[method], landscape, budgets, method_seed, method)
    results = {}
    for b in budgets:
        solutions, trials = snapshots[b]
        results[str(b)] = {
            "found": int(landscape.found(solutions).sum()),
            "returned": int(solutions.shape[0]),
            "trials": int(trials),
        }
    return {
        "dim": dim,
        "k": k,
        "seed": seed,
        "method": method,
        "method_seed": method_seed,
        "landscape": landscape.summary(),
        "budgets": results,
        "seconds": round(seconds, 3),
    }


def _init_worker() -> None:
    torch.set_num_threads(1)  # one process per core
    # Import the peers now, so that no task's time includes an import.
    for module in ("cma", "pynmmso"):
        with contextlib.suppress(ImportError):
            importlib.import_module(module)


def _task(args: tuple) -> dict:
    """A pool task: one case, its failure recorded instead of ending the benchmark."""
    dim, k, seed, method, budgets = args
    try:
        return run_case(dim, k, seed, method, budgets)
    except Exception as error:  # reported in the table and the JSON
        return {"dim": dim, "k": k, "seed": seed, "method": method, "error": repr(error)}


# ------------------------------------------------------------------------------------ reports
def _fraction(cases: list[dict], budget: int) -> str:
    ok = [c for c in cases if "error" not in c]
    if not cases:
        return "-"
    found = sum(c["budgets"][str(budget)]["found"] for c in ok)
    total = sum(c["k"] for c in ok)
    errors = len(cases) - len(ok)
    return f"{found}/{total}" + (f" ({errors} err)" if errors else "")


def _table(header: list[str], rows: list[list[str]]) -> str:
    """Plain-text table: first column left-aligned, the others right-aligned."""
    widths = [max(len(r[i]) for r in [header, *rows]) for i in range(len(header))]

    def line(row: list[str]) -> str:
        cells = [c.rjust(w) for c, w in zip(row[1:], widths[1:], strict=True)]
        return "  ".join([row[0].ljust(widths[0]), *cells])

    return "\n".join([line(header), "  ".join("-" * w for w in widths), *map(line, rows)])


def summarize(cases: list[dict], methods, dims, ks, budgets) -> tuple[str, dict]:
    """The printed tables and the JSON summary."""

    def pick(m: str, d: int, k: int | None = None) -> list[dict]:
        return [
            c for c in cases if c["method"] == m and c["dim"] == d and (k is None or c["k"] == k)
        ]

    columns = [(d, b) for d in dims for b in budgets]
    main = [
        [m]
        + [_fraction(pick(m, d), b) for d, b in columns]
        + [f"{sum(c.get('seconds', 0.0) for c in cases if c['method'] == m):.1f}"]
        for m in methods
    ]
    text = [
        "Optima found (summed over k and seeds), per D and budget:",
        _table(["method", *[f"D={d} @{b}" for d, b in columns], "time s"], main),
        "",
        "Per k:",
    ]
    per_k = [(d, k, b) for d in dims for k in ks for b in budgets]
    rows = [[m] + [_fraction(pick(m, d, k), b) for d, k, b in per_k] for m in methods]
    text.append(_table(["method", *[f"D={d} k={k} @{b}" for d, k, b in per_k]], rows))
    text += ["", "Returned solutions (mean per run):"]
    rows = []
    for m in methods:
        row = [m]
        for d, b in columns:
            ok = [c for c in pick(m, d) if "error" not in c]
            mean = np.mean([c["budgets"][str(b)]["returned"] for c in ok]) if ok else math.nan
            row.append(f"{mean:.1f}")
        rows.append(row)
    text.append(_table(["method", *[f"D={d} @{b}" for d, b in columns]], rows))
    summary = {
        m: {
            "seconds": round(sum(c.get("seconds", 0.0) for c in cases if c["method"] == m), 2),
            "found": {
                f"D={d}": {
                    str(b): {
                        "found": sum(
                            c["budgets"][str(b)]["found"] for c in pick(m, d) if "error" not in c
                        ),
                        "total": sum(c["k"] for c in pick(m, d) if "error" not in c),
                        "errors": sum("error" in c for c in pick(m, d)),
                    }
                    for b in budgets
                }
                for d in dims
            },
        }
        for m in methods
    }
    return "\n".join(text), summary


def _progress(i: int, n: int, case: dict) -> str:
    tag = f"[{i}/{n}] D={case['dim']} k={case['k']} seed={case['seed']} {case['method']}"
    if "error" in case:
        return f"{tag}: ERROR {case['error']}"
    found = ", ".join(f"{v['found']}/{case['k']} @{b}" for b, v in case["budgets"].items())
    return f"{tag}: {found} ({case['seconds']:.1f} s)"


def run_tasks(
    task: Callable[[tuple], dict],
    tasks: list[tuple],
    workers: int,
    progress: Callable[[int, int, dict], str],
) -> tuple[list[dict], float]:
    """``task`` on every item of ``tasks`` in ``workers`` spawned processes (one torch
    thread each; 0: in this process, for debugging), a ``progress`` line on stderr as each
    finishes. Returns the results in the order they finished, each with the ``machine`` it
    ran on (a ``--keep-others`` report mixes cases of several runs), and the wall seconds."""
    start = time.perf_counter()
    stamped = functools.partial(_stamped, task)
    if workers == 0:
        _init_worker()
        pool, results = None, map(stamped, tasks)
    else:
        pool = multiprocessing.get_context("spawn").Pool(workers, initializer=_init_worker)
        results = pool.imap_unordered(stamped, tasks)
    cases = []
    for i, case in enumerate(results, 1):
        cases.append(case)
        print(progress(i, len(tasks), case), file=sys.stderr, flush=True)
    if pool is not None:
        pool.close()
        pool.join()
    return cases, time.perf_counter() - start


def _stamped(task: Callable[[tuple], dict], item: tuple) -> dict:
    """``task(item)`` with the ``machine`` that ran it (in the worker: its one thread)."""
    return task(item) | {"machine": machine()}


def write_report(path: Path, config: dict, wall: float, summary: dict, cases: list) -> None:
    """The JSON report: ``config`` (with the peers' versions), wall time, summary, cases."""
    versions = {p: version(p) for p in ("torch", "cma", "pynmmso")}
    report = {
        "config": config | {"versions": versions, "machine": machine()},
        "wall_seconds": round(wall, 1),
        "summary": summary,
        "cases": cases,
    }
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text(json.dumps(report, indent=1) + "\n")
    print(f"wrote {path}")


def add_keep_others(parser: argparse.ArgumentParser) -> None:
    """The ``--keep-others`` flag (see ``run_keeping_others``)."""
    parser.add_argument(
        "--keep-others", action="store_true",
        help="keep the other methods' cases from --json instead of running them",
    )  # fmt: skip


def run_keeping_others(
    task: Callable[[tuple], dict],
    tasks: list[tuple],
    args: argparse.Namespace,
    grid: dict,
    methods: Sequence[str],
    order: Sequence[str],
    progress: Callable[[int, int, dict], str],
) -> tuple[list[dict], float, list[str]]:
    """``run_tasks``, completed with ``--keep-others`` by the other methods' cases of
    ``args.json`` (``kept_cases``, on the keys of ``grid``). Returns the cases, the wall
    seconds and every method among them, in the order of ``order``."""
    kept = kept_cases(args.json, grid, methods) if args.keep_others else []
    cases, wall = run_tasks(task, tasks, args.workers, progress)
    cases += kept
    rank = {m: i for i, m in enumerate(order)}
    return cases, wall, sorted({c["method"] for c in cases} | set(methods), key=rank.__getitem__)


def kept_cases(path: Path, grid: dict, methods: Sequence[str]) -> list:
    """The cases of ``path``'s report for every method not in ``methods``, for
    ``--keep-others``: a run of some methods (DIPOLE's, after a change to it) completed by the
    others' earlier cases rather than by running them again (every method here is seeded from
    its case: a rerun gives the same results; only their timings are the earlier run's).
    The report's config must equal ``grid`` on each of its keys."""
    try:
        report = json.loads(path.read_text())
    except (OSError, ValueError) as error:
        raise SystemExit(
            f"--keep-others: no report to keep cases from at {path}: {error}"
        ) from None
    for key, value in grid.items():
        if report["config"][key] != value:
            raise SystemExit(
                f"--keep-others: {path} has {key}={report['config'][key]}, this run "
                f"{value}: run every method instead"
            )
    return [c for c in report["cases"] if c["method"] not in methods]


def main(argv: Sequence[str] | None = None) -> None:
    from argtypes import Distinct, nonnegative_int, positive_even_int, positive_int, report_path

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dims", type=positive_int, nargs="+", action=Distinct, default=list(DIMS))
    parser.add_argument(
        "--ks", type=positive_even_int, nargs="+", action=Distinct, default=list(KS)
    )
    parser.add_argument(
        "--seeds", type=positive_int, default=SEEDS, help="seeds 0 … N−1 per (D, k)"
    )
    parser.add_argument(
        "--budgets", type=positive_int, nargs="+", action=Distinct, default=list(BUDGETS)
    )
    parser.add_argument(
        "--methods", nargs="+", action=Distinct, default=list(METHODS), choices=METHODS + OPT_IN
    )
    parser.add_argument(
        "--workers", type=nonnegative_int, default=2, help="processes (0: this one)"
    )
    parser.add_argument(
        "--json", type=report_path, default=ROOT / "docs" / "figures" / "multioptima.json"
    )
    add_keep_others(parser)
    args = parser.parse_args(argv)
    if (error := grid_error(args.dims, args.ks)) is not None:
        parser.error(f"argument --ks: {error}")
    budgets = sorted(set(args.budgets))
    methods = [m for m in METHODS + OPT_IN if m in args.methods]
    # Slowest first (DIPOLE clusters, PoWER tells 2000 times; high D costs more), so the last
    # tasks are short and the processes finish together.
    cost = {"DIPOLE": 0, "DIPOLE (paper)": 0, "DIPOLE (all sweeps)": 0, "DIPOLE (coverage)": 0,
            "DIPOLE (coverage from 300)": 0, "PoWER": 1, "NMMSO": 2, "IPOP-CMA-ES": 3}  # fmt: skip
    tasks = sorted(
        (
            (d, k, s, m, budgets)
            for m in methods
            for d in args.dims
            for k in args.ks
            for s in range(args.seeds)
        ),
        key=lambda t: (cost.get(t[3], 4), -t[0], -t[1]),
    )
    grid = {"dims": args.dims, "ks": args.ks, "seeds": args.seeds, "budgets": budgets}
    cases, wall, methods = run_keeping_others(
        _task, tasks, args, grid, methods, METHODS + OPT_IN, _progress
    )
    order = {m: i for i, m in enumerate(METHODS + OPT_IN)}
    cases.sort(key=lambda c: (order[c["method"]], c["dim"], c["k"], c["seed"]))
    text, summary = summarize(cases, methods, args.dims, args.ks, budgets)
    print(text)
    print(f"\nwall time {wall:.1f} s on {max(args.workers, 1)} process(es)")
    config = {
        "dims": args.dims,
        "ks": args.ks,
        "seeds": args.seeds,
        "budgets": budgets,
        "methods": methods,
        "workers": args.workers,
        "sigma0": SIGMA0,
        "box": BOX,
        "found_radius": FOUND_RADIUS,
        "found_level": FOUND_LEVEL,
    }
    write_report(args.json, config, wall, summary, cases)


if __name__ == "__main__":
    main()

"""DPMixtureKernel under pyro.infer.MCMC against the sampler's own sweeps (DPSampler.fit).

DIPOLE's clusterings run a few Gibbs sweeps on a small weighted data set; this times both
paths on the same chains (same generator seed, so the same draws), interleaved and repeated,
and prints the median CPU time per sweep of each (process time, one thread: on a shared
machine it counts this process alone) and their ratio:

    python benchmarks/bench_mcmc_kernel.py [--points 50] [--dim 10] [--sweeps 20] [--repeats 7]

Threads: one (the library's small tensors gain nothing from more).
"""

from __future__ import annotations

import argparse
import statistics
import time

import torch
from pyro.infer import MCMC

from dipole_torch import DPSampler, NormalInverseWishartPrior
from dipole_torch.mcmc import DPMixtureKernel

F64 = torch.float64


def data(points: int, dim: int, seed: int = 0) -> tuple[torch.Tensor, NormalInverseWishartPrior]:
    """``[points, dim]`` y = [θ, w]: θ around 4 optima, w > 0 a reward weight."""
    g = torch.Generator().manual_seed(seed)
    centres = 3.0 * torch.randn(4, dim - 1, generator=g, dtype=F64)
    theta = centres[torch.arange(points) % 4] + 0.3 * torch.randn(
        points, dim - 1, generator=g, dtype=F64
    )
    weight = torch.rand(points, 1, generator=g, dtype=F64) + 0.1
    y = torch.cat([theta, weight], -1)
    prior = NormalInverseWishartPrior.from_exploration(y.mean(0), torch.cov(y.T))
    return y, prior


def main() -> None:
    from argtypes import at_least, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--points", type=at_least(2), default=50)
    parser.add_argument("--dim", type=at_least(2), default=10)
    parser.add_argument("--sweeps", type=positive_int, default=20)
    parser.add_argument("--repeats", type=positive_int, default=7)
    args = parser.parse_args()
    if args.points <= args.dim:  # the prior's covariance is the data's
        parser.error(f"--points {args.points}: N must exceed --dim {args.dim}")
    torch.set_num_threads(1)
    y, prior = data(args.points, args.dim)
    sampler = DPSampler(prior, alpha=1.0, m=10, reward_weighted=True, update_prior=True)

    def direct(seed: int):
        g = torch.Generator().manual_seed(seed)
        return sampler.fit(y, args.sweeps, generator=g)

    def kernel(seed: int, save_params=None):
        g = torch.Generator().manual_seed(seed)
        k = DPMixtureKernel(sampler, generator=g)
        mcmc = MCMC(
            k,
            num_samples=args.sweeps,
            warmup_steps=0,
            disable_progbar=True,
            save_params=save_params,
        )
        mcmc.run(y)
        return k.state

    def kernel_lean(seed: int):  # without the per-sample log joint
        return kernel(seed, save_params=["num_components", "labels", "point_means"])

    paths = (("direct", direct), ("kernel", kernel), ("kernel_lean", kernel_lean))
    for _, run in paths:
        run(0)  # warm up
    times = {name: [] for name, _ in paths}
    for repeat in range(args.repeats):
        labels = {}
        shift = repeat % len(paths)  # rotate the order: no path always runs first
        for name, run in paths[shift:] + paths[:shift]:
            start = time.process_time()
            state = run(repeat)
            times[name].append((time.process_time() - start) / args.sweeps)
            labels[name] = state.labels
        assert all(torch.equal(x, labels["direct"]) for x in labels.values()), "chains differ"
    medians = {name: statistics.median(values) for name, values in times.items()}
    print(f"N={args.points} points, D={args.dim}, {args.sweeps} sweeps, {args.repeats} repeats")
    for name, value in medians.items():
        ratio = value / medians["direct"]
        print(f"  {name:12s} {1e3 * value:7.2f} ms CPU per sweep (median), {ratio:.3f} x direct")


if __name__ == "__main__":
    main()

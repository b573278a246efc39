"""A DP sweep at DIPOLE's sizes against its arithmetic floor, measured in the same run.

    python benchmarks/bench_sweep.py [--dims 2 10] [--trials 500] [--batch 256] [--repeats 5]

The clusterings of one DIPOLE run (default options, the cheap two-peak reward of
``bench_iteration.py``, ``--trials`` trials) are captured (data, warm start, generator
state) and replayed: each clustering's sweeps are timed ``--repeats`` times and the fastest
kept, so a loaded machine inflates the figure less. Printed per D: the sweeps replayed and
their sizes (points N, components K, p = D + 1), the milliseconds per sweep, the torch calls
per sweep (functions and tensor methods, counted with a ``TorchFunctionMode``; property reads
such as ``.shape`` are not counted), and the floor:

**The floor** is the sweep's arithmetic without the per-call overhead: the same operations on
the same sizes (the auxiliary draws from H with their normals and χ², the Cholesky factors
and the triangular solves of the likelihood table, the reward regression, the label draws
point by point, the μ and Σ alternations with their Metropolis-Hastings terms, H's update),
made for ``--batch`` independent copies at once, each call batched over the copies, and the
time divided by the batch. What is left is the cost of the flops and of the batched kernels'
per-matrix work; the ratio sweep / floor says how much of a sweep is the overhead of making
small calls. It is a floor for this implementation's operations, not for the model: a
sampler could choose other ones.
"""

from __future__ import annotations

import argparse
import math
import statistics
import sys
import time
from pathlib import Path

import torch
from torch.overrides import TorchFunctionMode

sys.path.insert(0, str(Path(__file__).resolve().parent))
from bench_iteration import make, reward  # noqa: E402
from setting import setting_line  # noqa: E402

import dipole_torch.dp.sampler as dp_sampler  # noqa: E402
from dipole_torch.dp.conditionals import posterior_point_estimate  # noqa: E402

DTYPE = torch.float64


class CountCalls(TorchFunctionMode):
    """Counts the torch functions and tensor methods under it (property reads excluded)."""

    def __init__(self):
        super().__init__()
        self.calls = 0

    def __torch_function__(self, func, types, args=(), kwargs=None):
        if getattr(func, "__name__", "") != "__get__":
            self.calls += 1
        return func(*args, **(kwargs or {}))


def capture(d: int, trials: int, seed: int = 1) -> tuple[list[dict], object]:
    """The clusterings of one default DIPOLE run: ``y``, sweeps, warm start, generator state."""
    opt = make("dipole", d, seed)
    captured = []
    make_sampler = opt._sampler

    def recording_sampler(prior):
        # Each call of the sampler's fit as Dipole makes it (sweeps, warm start, settle).
        sampler = make_sampler(prior)
        fit = sampler.fit

        def recording_fit(y, sweeps, generator, start=None, **kwargs):
            captured.append(
                dict(y=y.clone(), sweeps=sweeps, start=start, kwargs=kwargs,
                     generator=generator.get_state())
            )  # fmt: skip
            return fit(y, sweeps, generator, start, **kwargs)

        sampler.fit = recording_fit
        return sampler

    opt._sampler = recording_sampler
    while opt.trials < trials:
        theta = opt.ask()
        opt.tell(theta, reward(theta))
    del opt.sampler.fit  # the replays call the sampler's own fit
    return captured, opt


def replay(opt, clustering: dict) -> None:
    """One captured clustering again, from its generator state."""
    opt.generator.set_state(clustering["generator"])
    y, start = clustering["y"], clustering["start"]
    state = opt.sampler.fit(y, clustering["sweeps"], opt.generator, start, **clustering["kwargs"])
    posterior_point_estimate(y, state)


def sweep_sizes(opt, clusterings: list[dict]) -> list[tuple[int, int, int]]:
    """``(N, K at the start, K at the end)`` of every sweep the replays make."""
    sizes = []
    sweep = dp_sampler.neal8_sweep

    def recording_sweep(y, state, sampler, generator):
        new = sweep(y, state, sampler, generator)
        sizes.append((y.shape[0], state.num_components, new.num_components))
        return new

    dp_sampler.neal8_sweep = recording_sweep
    try:
        for clustering in clusterings:
            replay(opt, clustering)
    finally:
        dp_sampler.neal8_sweep = sweep
    return sizes


def floor_seconds(
    batch: int, n: int, k_in: int, k_out: int, p: int, m: int, steps: int, reuse: bool
) -> float:
    """Seconds per copy of one sweep's arithmetic, made for ``batch`` copies at once (see the
    module docstring); K components in the table, K_out after the labels."""
    g = torch.Generator().manual_seed(0)
    b, lower = batch, p * (p - 1) // 2
    eye = torch.eye(p, dtype=DTYPE)
    y = torch.randn(b, n, p, generator=g, dtype=DTYPE)
    scale_tril = eye.expand(b, p, p)
    start = time.perf_counter()
    # The auxiliary draws from H (means, Bartlett normals and χ², the IW product) and the
    # likelihood table of the starting and auxiliary components at every point.
    a = m + n if reuse else n * m
    c = k_in + a
    means = torch.randn(b, c, p, generator=g, dtype=DTYPE)
    normal = torch.randn(b, a, lower, generator=g, dtype=DTYPE)
    chi2 = 2.0 * torch._standard_gamma(torch.full((b, a, p), p + 2.0, dtype=DTYPE), generator=g)
    factor = torch.zeros(b, a, p * p, dtype=DTYPE)
    factor[..., torch.tril_indices(p, p, -1)[0] * p + torch.tril_indices(p, p, -1)[1]] = normal
    factor[..., torch.arange(p) * (p + 1)] = chi2.sqrt()
    factor = factor.view(b, a, p, p)
    root = torch.linalg.solve_triangular(
        factor, scale_tril[:, None].expand(b, a, p, p).mT, upper=False
    )
    covs = torch.cat((eye.expand(b, k_in, p, p), root.mT @ root + 0.01 * eye), 1)
    chol = torch.linalg.cholesky(covs)
    diff = (y[:, None, :, :] - means[:, :, None, :]).mT  # [B, C, p, N]
    z = torch.linalg.solve_triangular(chol, diff, upper=False)
    table = -0.5 * z.square().sum(-2) - chol.diagonal(dim1=-2, dim2=-1).log().sum(-1)[..., None]
    # Eq. 6's reward regression of the K components at the C means.
    theta_tril = chol[:, :k_in, : p - 1, : p - 1]
    q = (means[:, :, None, : p - 1] - means[:, None, :k_in, : p - 1]).movedim(1, -1)  # [B,K,p-1,C]
    zq = torch.linalg.solve_triangular(theta_tril, q, upper=False).square().sum(-2)
    resp = torch.softmax(-0.5 * zq, dim=1)
    table = table + (resp * means[:, None, :, -1]).sum(1).clamp_min(1e-12).log()[:, :, None]
    # The label draws, point by point: K + m logits, their CDF and an inverse-CDF search.
    u = torch.rand(b, n, 1, generator=g, dtype=DTYPE)
    for i in range(n):
        logits = table[:, : k_in + m, i]
        cdf = (logits - logits.amax(-1, keepdim=True)).exp().cumsum(-1)
        torch.searchsorted(cdf, u[:, i] * cdf[:, -1:])
    # The μ and Σ alternations of the K_out components, with the Metropolis-Hastings terms.
    k = k_out
    onehot = (torch.arange(n) % k == torch.arange(k)[:, None]).to(DTYPE).expand(b, k, n)
    counts = onehot.sum(-1)
    cov = torch.eye(p, dtype=DTYPE).expand(b, k, p, p) + 0.0
    normals = torch.randn(b, steps, k, p + lower, generator=g, dtype=DTYPE)
    gammas = torch._standard_gamma(torch.full((b, steps, k, p), p + 3.0, dtype=DTYPE), generator=g)
    logu = torch.rand(b, steps, k, generator=g, dtype=DTYPE).log()
    both = torch.cat((cov + 0.01 * eye, cov), 1)
    lchol = torch.linalg.cholesky(both)
    inverse = torch.cholesky_inverse(lchol)
    for step in range(steps):
        precision = eye + counts[..., None, None] * inverse[:, :k]
        pchol = torch.linalg.cholesky(precision)
        rhs = inverse[:, :k] @ (onehot @ y)[..., None]
        loc = torch.cholesky_solve(rhs, pchol)
        mu = loc + torch.linalg.solve_triangular(
            pchol.mT, normals[:, step, :, :p, None], upper=True
        )
        centred = y[:, None] - mu.mT  # [B, K, N, p]
        scatter = (onehot[..., None] * centred).mT @ centred
        s_tril = torch.linalg.cholesky(eye + scatter)
        bart = torch.zeros(b, k, p * p, dtype=DTYPE)
        bart[..., torch.arange(p) * (p + 1)] = (2.0 * gammas[:, step]).sqrt()
        proot = torch.linalg.solve_triangular(bart.view(b, k, p, p), s_tril.mT, upper=False)
        proposal = proot.mT @ proot
        pchol2, _ = torch.linalg.cholesky_ex(torch.cat((proposal + 0.01 * eye, proposal), 1))
        pinv = torch.cholesky_inverse(pchol2)
        logdet = pchol2.diagonal(dim1=-2, dim2=-1).log().sum(-1)
        weight = ((pinv[:, :k] - pinv[:, k:]) * scatter).sum((-2, -1)) + logdet[:, :k]
        accept = logu[:, step] < weight
        inverse = torch.where(accept[..., None, None].repeat(1, 2, 1, 1), pinv, inverse)
    # H's update: μ0, Σ0 and Ψ0 given the K components.
    hyper = torch.randn(b, p + 2 * lower, generator=g, dtype=DTYPE)
    hchi = torch._standard_gamma(torch.full((b, 2, p), p + 3.0, dtype=DTYPE), generator=g)
    hchol = torch.linalg.cholesky(eye + inverse[:, :k].sum(1))
    torch.cholesky_solve(mu.sum(1), hchol) + hyper[:, :p, None]
    hroot = torch.linalg.solve_triangular(hchol.mT, eye * hchi[:, :1].mT, upper=True)
    hroot @ hroot.mT
    return (time.perf_counter() - start) / batch


def main() -> None:
    from argtypes import Distinct, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--dims", type=positive_int, nargs="+", action=Distinct, default=[2, 10])
    parser.add_argument("--trials", type=positive_int, default=500)
    parser.add_argument(
        "--batch", type=positive_int, default=256, help="copies in the floor's calls"
    )
    parser.add_argument("--repeats", type=positive_int, default=5)
    args = parser.parse_args()
    torch.set_num_threads(1)
    print(setting_line())
    floor_seconds(8, 5, 2, 2, 3, 10, 2, False)  # first-call costs out of the table
    header = (
        f"{'D':>3} {'sweeps':>6} {'N':>7} {'K':>5} {'aux':>6} {'ms/sweep':>9} {'calls/sweep':>11} "
        f"{'floor ms':>9} {'sweep/floor':>11}"
    )
    print(header)
    print("-" * len(header))
    for d in args.dims:
        clusterings, opt = capture(d, args.trials)
        sampler = opt.sampler
        sizes = sweep_sizes(opt, clusterings)
        sweeps = len(sizes)
        total = 0.0
        for clustering in clusterings:
            best = math.inf
            for _ in range(args.repeats):
                start = time.perf_counter()
                replay(opt, clustering)
                best = min(best, time.perf_counter() - start)
            total += best
        counter = CountCalls()
        with counter:
            for clustering in clusterings:
                replay(opt, clustering)
        reuse = sampler.auxiliary == "reuse"
        floors = {}
        for size in set(sizes):
            n, k_in, k_out = size
            floors[size] = min(
                floor_seconds(
                    args.batch, n, k_in, k_out, d + 1, sampler.m, sampler.inner_steps, reuse
                )  # fmt: skip
                for _ in range(3)
            )
        floor = sum(floors[size] for size in sizes)
        n_range = f"{min(s[0] for s in sizes)}-{max(s[0] for s in sizes)}"
        k_mean = statistics.mean(s[1] for s in sizes)
        print(
            f"{d:>3} {sweeps:>6} {n_range:>7} {k_mean:>5.1f} {sampler.auxiliary:>6} "
            f"{1e3 * total / sweeps:>9.3f} {counter.calls / sweeps:>11.0f} "
            f"{1e3 * floor / sweeps:>9.3f} {total / floor:>11.1f}",
            flush=True,
        )


if __name__ == "__main__":
    main()

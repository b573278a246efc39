"""One DP clustering run to convergence (Neal's Algorithm 8) against scikit-learn's
variational Dirichlet-process mixture on the same data, with each one's clustering quality.

    python benchmarks/bench_gibbs.py [--repeats 2] [--sizes 1000 10000] [--dims 2 10]

Data: N points from 4 well-separated unit Gaussians in D dimensions (centres 8·N(0, I)).
Ours: ``DPSampler(prior, update_prior=False).fit(init="sequential")`` with H fixed (means
spread like the data, E[Σ] = 2 I), then sweeps until the partition settles: two consecutive
sweeps whose labels agree with the previous sweep's at ARI ≥ 0.999 (at most
``--max-sweeps``). Timed: the initial pass and every sweep (the convergence check is not). The
anchor, timed in the same run on the same data:
``BayesianGaussianMixture(weight_concentration_prior_type="dirichlet_process",
n_components=10, covariance_type="full")`` fitted to its own convergence (tol 1e-3, max_iter
100). Printed: seconds and ARI against the true labels for both, our sweeps and seconds per
sweep, and the time ratio ours / sklearn; then the same run with Favaro & Teh (2013)'s
re-used auxiliary draws (``auxiliary="reuse"``, CPU), and with the slice sampler
(``method="slice"``: every label drawn at once, from the same sequential start) (best of
``--repeats`` seeds for the time, the ARI of that run).
``--device cuda`` runs Algorithm 8 and the slice sampler on the GPU (Algorithm 8's label
loop never waits for the device within a chunk of points).
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch
from sklearn.exceptions import ConvergenceWarning
from sklearn.metrics import adjusted_rand_score
from sklearn.mixture import BayesianGaussianMixture
from threadpoolctl import threadpool_limits

from dipole_torch import DPSampler, NormalInverseWishartPrior

DTYPE = torch.float64


def make_data(n: int, d: int, seed: int = 0) -> tuple[torch.Tensor, torch.Tensor]:
    """``[N, D]`` points and ``[N]`` true labels of 4 unit Gaussians."""
    g = torch.Generator().manual_seed(seed)
    centres = 8.0 * torch.randn(4, d, generator=g, dtype=DTYPE)
    labels = torch.randint(0, 4, (n,), generator=g)
    return centres[labels] + torch.randn(n, d, generator=g, dtype=DTYPE), labels


def prior_for(y: torch.Tensor) -> NormalInverseWishartPrior:
    d = y.shape[1]
    return NormalInverseWishartPrior(
        mean_loc=y.mean(0),
        mean_covariance=torch.cov(y.T).reshape(d, d),  # (a scalar at D = 1)
        df=d + 6.0,
        scale=10.0 * torch.eye(d, dtype=DTYPE, device=y.device),
        regularization=1e-3 * torch.eye(d, dtype=DTYPE, device=y.device),
    )


def run_gibbs(
    y: torch.Tensor, seed: int, max_sweeps: int, device: str = "cpu", sampler: str = "neal8"
) -> tuple[float, int, torch.Tensor]:
    """(seconds, sweeps, ``[N]`` labels) of one run to convergence, on ``device``; ``sampler``:
    ``"neal8"`` (Algorithm 8), ``"reuse"`` (Favaro & Teh's re-used auxiliary draws instead of
    Algorithm 8's fresh ones) or ``"slice"`` (the slice sampler)."""
    y = y.to(device)
    prior = prior_for(y)
    g = torch.Generator(device).manual_seed(seed)
    start = time.perf_counter()
    method = "slice" if sampler == "slice" else "neal8"
    state = DPSampler(prior, update_prior=False, method=method).fit(
        y, 1, generator=g, init="sequential"
    )  # (the first sweep with fresh auxiliary draws)
    auxiliary = "reuse" if sampler == "reuse" else "fresh"
    dp = DPSampler(prior, update_prior=False, auxiliary=auxiliary, method=method)
    chain = dp.to_chain(state)
    elapsed = time.perf_counter() - start
    sweeps, settled = 1, 0
    while sweeps < max_sweeps and settled < 2:
        previous = chain.labels
        start = time.perf_counter()
        chain = dp.sweep(y, chain, g)
        if device != "cpu":
            torch.cuda.synchronize()
        elapsed += time.perf_counter() - start
        sweeps += 1
        same = adjusted_rand_score(previous.cpu().numpy(), chain.labels.cpu().numpy()) >= 0.999
        settled = settled + 1 if same else 0
    return elapsed, sweeps, chain.labels.cpu()


def run_sklearn(y: torch.Tensor, seed: int, threads: int) -> tuple[float, int, torch.Tensor]:
    """(seconds, EM iterations, ``[N]`` labels) of one variational fit on ``threads`` BLAS
    threads (as many as torch gets)."""
    model = BayesianGaussianMixture(
        n_components=10,
        weight_concentration_prior_type="dirichlet_process",
        covariance_type="full",
        max_iter=100,
        random_state=seed,
    )
    with warnings.catch_warnings(), threadpool_limits(threads):
        warnings.simplefilter("ignore", ConvergenceWarning)
        start = time.perf_counter()
        model.fit(y.numpy())
        elapsed = time.perf_counter() - start
    return elapsed, int(model.n_iter_), torch.as_tensor(model.predict(y.numpy()))


def main() -> None:
    from argtypes import Distinct, at_least, device, positive_int

    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--repeats", type=positive_int, default=2, help="seeds; the best time is kept"
    )
    parser.add_argument(
        "--sizes", type=at_least(2), nargs="+", action=Distinct, default=[1000, 10000]
    )
    parser.add_argument("--dims", type=positive_int, nargs="+", action=Distinct, default=[2, 10])
    parser.add_argument("--max-sweeps", type=positive_int, default=30)
    parser.add_argument("--threads", type=positive_int, default=1, help="torch CPU threads")
    parser.add_argument(
        "--device", type=device, default="cpu", help="where our sampler runs (sklearn: CPU)"
    )
    args = parser.parse_args()
    # The prior's mean covariance is the data's (N > D), sklearn's fit has 10 components.
    if min(args.sizes) < max(max(args.dims) + 1, 10):
        least = max(max(args.dims) + 1, 10)
        parser.error(f"--sizes {min(args.sizes)}: N must be at least {least} (> D, >= 10)")
    torch.set_num_threads(args.threads)
    header = (
        f"{'N':>6} {'D':>3} {'ours s':>8} {'sweeps':>6} {'s/sweep':>8} {'ours ARI':>8} "
        f"{'sklearn s':>9} {'EM its':>6} {'sk ARI':>6} {'ours/sklearn':>12} "
        f"{'reuse s':>8} {'reuse ARI':>9} {'reuse/sklearn':>13} "
        f"{'slice s':>8} {'slice ARI':>9} {'slice/sklearn':>13}"
    )
    warm_up, _ = make_data(200, 2)
    run_gibbs(warm_up, 0, 2, args.device)  # first-call costs (lazy init) out of the table
    run_sklearn(warm_up, 0, args.threads)
    print(header)
    print("-" * len(header))
    for d in args.dims:
        for n in args.sizes:
            y, true = make_data(n, d)
            runs = (run_gibbs(y, s, args.max_sweeps, args.device) for s in range(args.repeats))
            ours = min(runs, key=lambda r: r[0])
            fits = (run_sklearn(y, s, args.threads) for s in range(args.repeats))
            theirs = min(fits, key=lambda r: r[0])
            reruns = (run_gibbs(y, s, args.max_sweeps, "cpu", "reuse") for s in range(args.repeats))
            reuse = min(reruns, key=lambda r: r[0])
            reuse_ari = adjusted_rand_score(true.numpy(), reuse[2].numpy())
            slices = (
                run_gibbs(y, s, args.max_sweeps, args.device, "slice") for s in range(args.repeats)
            )
            slice_run = min(slices, key=lambda r: r[0])
            slice_ari = adjusted_rand_score(true.numpy(), slice_run[2].numpy())
            ours_ari = adjusted_rand_score(true.numpy(), ours[2].numpy())
            their_ari = adjusted_rand_score(true.numpy(), theirs[2].numpy())
            print(
                f"{n:>6} {d:>3} {ours[0]:>8.3f} {ours[1]:>6} {ours[0] / ours[1]:>8.4f} "
                f"{ours_ari:>8.3f} {theirs[0]:>9.3f} {theirs[1]:>6} {their_ari:>6.3f} "
                f"{ours[0] / theirs[0]:>12.2f} {reuse[0]:>8.3f} {reuse_ari:>9.3f} "
                f"{reuse[0] / theirs[0]:>13.2f} {slice_run[0]:>8.3f} {slice_ari:>9.3f} "
                f"{slice_run[0] / theirs[0]:>13.2f}",
                flush=True,
            )


if __name__ == "__main__":
    main()

"""Time one Gibbs sweep of the DP mixture (Neal's Algorithm 8) against scikit-learn's
variational Dirichlet-process mixture on the same data, measured in the same run.

    python benchmarks/bench_gibbs.py [--repeats 3]

For N in {100, 1000, 10000} points and D in {2, 10}: data from 4 well-separated Gaussian
clusters; our sweep starts from the state after 2 warm-up sweeps (so K is realistic); sklearn's
``BayesianGaussianMixture(weight_concentration_prior_type="dirichlet_process")`` is fitted
from scratch (n_components=10, full covariances, max_iter=100). Printed: our seconds per
sweep, sklearn's seconds per fit and per EM iteration, and the ratios.
"""

from __future__ import annotations

import argparse
import time
import warnings

import torch
from sklearn.exceptions import ConvergenceWarning
from sklearn.mixture import BayesianGaussianMixture

from dipole_torch import NormalInverseWishartPrior, fit_dp_mixture, neal8_sweep


def make_data(n: int, d: int, seed: int = 0) -> torch.Tensor:
    g = torch.Generator().manual_seed(seed)
    centres = 8.0 * torch.randn(4, d, generator=g, dtype=torch.float64)
    labels = torch.randint(0, 4, (n,), generator=g)
    return centres[labels] + torch.randn(n, d, generator=g, dtype=torch.float64)


def time_sweep(y: torch.Tensor, repeats: int) -> tuple[float, int]:
    d = y.shape[1]
    prior = NormalInverseWishartPrior(
        mean_loc=y.mean(0),
        mean_covariance=torch.cov(y.T),
        df=d + 6.0,
        scale=10.0 * torch.eye(d, dtype=torch.float64),
        regularization=1e-3 * torch.eye(d, dtype=torch.float64),
    )
    g = torch.Generator().manual_seed(0)
    state = fit_dp_mixture(y, prior, 2, generator=g, init="sequential")
    best = float("inf")
    for _ in range(repeats):
        start = time.perf_counter()
        state = neal8_sweep(y, state, generator=g, initial_prior=prior)
        best = min(best, time.perf_counter() - start)
    return best, state.num_components


def time_sklearn(y: torch.Tensor, repeats: int) -> tuple[float, float]:
    best_fit, per_iter = float("inf"), float("inf")
    for seed in range(repeats):
        model = BayesianGaussianMixture(
            n_components=10,
            weight_concentration_prior_type="dirichlet_process",
            covariance_type="full",
            max_iter=100,
            random_state=seed,
        )
        with warnings.catch_warnings():
            warnings.simplefilter("ignore", ConvergenceWarning)
            start = time.perf_counter()
            model.fit(y.numpy())
            elapsed = time.perf_counter() - start
        best_fit = min(best_fit, elapsed)
        per_iter = min(per_iter, elapsed / model.n_iter_)
    return best_fit, per_iter


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--repeats", type=int, default=3, help="best of this many timings")
    parser.add_argument("--threads", type=int, default=1, help="torch CPU threads")
    args = parser.parse_args()
    torch.set_num_threads(args.threads)
    header = (
        f"{'N':>6} {'D':>3} {'K':>3} {'sweep s':>9} {'sklearn fit s':>14} "
        f"{'sklearn iter s':>15} {'sweep/fit':>10} {'sweep/iter':>11}"
    )
    print(header)
    print("-" * len(header))
    for d in (2, 10):
        for n in (100, 1000, 10000):
            y = make_data(n, d)
            sweep, k = time_sweep(y, args.repeats)
            fit, iteration = time_sklearn(y, args.repeats)
            print(
                f"{n:>6} {d:>3} {k:>3} {sweep:>9.4f} {fit:>14.4f} {iteration:>15.5f} "
                f"{sweep / fit:>10.2f} {sweep / iteration:>11.1f}"
            )


if __name__ == "__main__":
    main()

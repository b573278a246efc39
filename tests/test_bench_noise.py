"""The noisy-returns benchmark's noise and a tiny end-to-end case."""

import pytest
import torch

from benchmarks import bench_multioptima
from benchmarks import bench_noise as bench


def test_the_noise_has_the_std_asked_and_a_mean_of_n_divides_it_by_root_n():
    landscape = bench_multioptima.make_landscape(2, 4, seed=5)
    theta = torch.zeros(20000, 2, dtype=torch.float64)
    clean = landscape(theta)
    for repeats in (1, 4):
        noisy = bench.NoisyLandscape(landscape, 0.03, seed=0, repeats=repeats)(theta)
        std = float((noisy - clean).std())
        assert std == pytest.approx(0.03 * landscape.height / repeats**0.5, rel=0.03)
    silent = bench.NoisyLandscape(landscape, 0.0, seed=0)
    assert torch.equal(silent(theta), clean)


def test_a_case_is_judged_on_the_noise_free_landscape():
    case = bench.run_case(2, 2, 0, 0.01, "DIPOLE (best ×4)", 300)
    assert case["k"] == 2 and 0 <= case["found"] <= 2 and case["returned"] >= 1
    averaged = bench.run_case(2, 2, 0, 0.01, "DIPOLE (mean of 4)", 300)
    assert averaged["returned"] >= 1


def test_the_noise_handling_cma_es_stays_within_the_budget_and_returns_its_means():
    pytest.importorskip("cma")
    landscape = bench_multioptima.make_landscape(2, 2, seed=5)
    calls = []

    def counted(theta):
        calls.append(theta.shape[0])
        return landscape(theta)

    counted.lower, counted.upper, counted.dim = landscape.lower, landscape.upper, 2
    snapshots = bench.run_uh_ipop_cmaes(counted, [400], seed=0)
    means, trials = snapshots[400]
    assert sum(calls) == 400 == trials
    assert means.shape[1] == 2 and means.shape[0] >= 1
    assert bool(((means >= -5) & (means <= 5)).all())


def test_the_best_gap_measures_both_returns_above_the_noise_free_value():
    """On a run with noise, best()'s return and the best told lie above the truth at their
    θ (the luckiest told return most), and the table says so for each level."""
    case = bench.best_gap(2, 2, 0, 0.03, 400)
    assert 0 < case["best"] < case["told"] < 0.3, case
    table = bench.gap_table([case], [2], [0.03])
    assert "D = 2, noise 3 %: best()" in table and "(1 runs)" in table

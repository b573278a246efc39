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

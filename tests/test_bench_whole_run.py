"""The whole-run speed benchmark's measurement: optimizer CPU, trials and Gibbs sweeps."""

import pytest

from benchmarks import bench_whole_run as bench
from dipole_torch.dp.sampler import DPSampler


def test_a_run_reports_its_trials_and_counts_its_sweeps():
    sweep = DPSampler.sweep
    cpu, trials, sweeps = bench.optimizer_cpu("DIPOLE", 2, 2, 0, 60)
    assert cpu > 0 and trials == 60
    assert sweeps >= 20  # the first clustering alone runs 20
    assert DPSampler.sweep is sweep  # the counter is taken off again


def test_the_paper_variant_runs_every_sweep_of_every_clustering():
    _, _, default = bench.optimizer_cpu("DIPOLE", 2, 4, 1, 300)
    _, _, paper = bench.optimizer_cpu("DIPOLE (paper)", 2, 4, 1, 300)
    assert paper > default


def test_the_counter_is_removed_when_a_run_fails():
    sweep = DPSampler.sweep
    with pytest.raises(RuntimeError), bench.SweepCount():
        raise RuntimeError("a failing run")
    assert DPSampler.sweep is sweep

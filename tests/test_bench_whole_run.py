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


def test_the_bare_power_loop_spends_its_budget_and_climbs():
    from bench_multioptima import case_seeds, make_landscape

    cpu, trials, sweeps = bench.optimizer_cpu("PoWER (bare loop)", 2, 2, 0, 300)
    assert cpu > 0 and trials == 300 and sweeps == 0
    landscape = make_landscape(2, 2, case_seeds(2, 2, 0)[0])
    start = landscape(0.5 * (landscape.lower + landscape.upper)[None])
    (mean, used) = bench.run_bare_power(landscape, [300], 0)[300]
    assert used == 300 and float(landscape(mean)) > float(start)


def test_the_setting_line_names_the_cpu_the_threads_and_the_versions():
    import platform

    import torch

    from benchmarks.setting import cpu_model, setting_line

    line = setting_line(("torch", "no-such-distribution"))
    assert line.startswith(f"setting: {cpu_model()} (")
    assert f"Python {platform.python_version()}; torch {torch.__version__}" in line
    assert line.endswith(torch.__version__)  # (a package not installed is left out)
    threads = torch.get_num_threads()
    assert f", {threads} torch thread{'s' if threads != 1 else ''});" in line
    assert "torch thread" not in setting_line(("torch",), threads=False)

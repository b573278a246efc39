"""benchmarks/bench_trials.py: every trial in one class, the classes' boundaries, and a tiny
end-to-end run."""

import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_trials as bench  # noqa: E402

from dipole_torch.archive import PROBE  # noqa: E402


def test_classes_of_a_batch():
    gaps = torch.tensor([0.5, 0.1, 1e-3, 1e-4, 0.0], dtype=torch.float64)
    owner = torch.tensor([0, 1, 2, 3, 4, -1, -1, PROBE])
    counts = bench.classify(owner, gaps)
    assert counts == {
        "gap > 1e-1": 1,
        "1e-1 >= gap > 1e-4": 2,  # 0.1 and 1e-3: the boundaries belong below
        "gap <= 1e-4": 2,
        "scouts": 2,
        "probes": 1,
    }


def test_a_run_puts_every_trial_in_one_class():
    counts, means = bench.run_dipole(7, 0, 300, {})
    assert set(counts) <= set(bench.CLASSES)
    # Stopped before the batch that would cross the budget: close to it, not beyond.
    assert 250 < sum(counts.values()) <= 300
    assert counts["scouts"] > 0 and means.shape[1] == 2
    # Changed options reach the run: without hill-valley vetting no probe is asked.
    counts, _ = bench.run_dipole(7, 0, 300, {"hill_valley": False})
    assert counts["probes"] == 0


def test_options_parse_as_literals():
    assert bench.parse_options(["start_cap=0.25", "restarts=start", "max_policies=None"]) == {
        "start_cap": 0.25,
        "restarts": "start",
        "max_policies": None,
    }
    with pytest.raises(SystemExit, match="key=value"):
        bench.parse_options(["start_cap"])


def test_the_command_line_end_to_end(capsys):
    pytest.importorskip("pynmmso")
    bench.main(["--functions", "2", "--seeds", "1", "--budget", "100"])
    out = capsys.readouterr().out
    assert "F2 equal maxima 1D (5 × 1)" in out and "NMMSO" in out


@pytest.mark.parametrize(
    ("argv", "said"),
    [
        (["--set", "nosuch=1"], "--set: unknown DIPOLE option(s) 'nosuch'"),
        (["--functions", "11"], "--functions must lie in 1..10"),
    ],
)
def test_a_bad_option_is_an_argparse_error_before_any_run(argv, said, capsys):
    # An unknown --set key was a TypeError traceback from inside the first run.
    with pytest.raises(SystemExit) as exit_:
        bench.main(["--seeds", "1", "--budget", "50", *argv])
    assert exit_.value.code == 2
    assert said in capsys.readouterr().err

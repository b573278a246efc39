"""The per-iteration speed benchmark's call counts: by part, they add up to the whole."""

import pytest

from benchmarks import bench_iteration as bench
from dipole_torch import Dipole


def test_the_parts_add_up_to_the_iteration_and_leave_the_class_alone():
    cluster = Dipole._cluster
    bench.torch_calls("dipole", 2, 20, 0)  # first-call costs (lazy init) out, as main does
    parts = bench.calls_by_part(2, 120, 0)
    whole = bench.torch_calls("dipole", 2, 120, 0)  # the same run, counted as one
    assert set(parts) == {label for label, _, _ in bench.PARTS} | {"the rest"}
    assert sum(parts.values()) == pytest.approx(whole)
    assert parts["clusterings"] > 0 and parts["eq. 7"] > 0 and parts["the rest"] > 0
    assert min(parts.values()) >= 0
    assert Dipole._cluster is cluster  # the counters were put on the run's instance


def test_the_iterations_by_kind_add_up_to_the_run():
    # 300 trials at D = 2: every policy retires and the run restarts (seed 0).
    result = bench.run("dipole", 2, 300, 0)
    later = result["iterations"] - 1
    restarts = round(result["restart_share"] * later)
    assert 0 < restarts < later
    total = (
        result["first"]
        + result["policy_iter"] * (later - restarts)
        + result["restart_iter"] * restarts
    )
    assert total == pytest.approx(result["per_iter"] * result["iterations"])
    assert result["policy_trials"] >= 1

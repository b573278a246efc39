"""The multi-optima benchmark's landscapes, success criterion and a tiny end-to-end run."""

import json

import pytest
import torch

from benchmarks import bench_multioptima as bench


@pytest.mark.parametrize(("dim", "k"), [(2, 8), (5, 4), (10, 2)])
def test_every_centre_is_a_local_maximum_of_height_b_plus_h(dim, k):
    landscape = bench.make_landscape(dim, k, seed=3)
    low, high = landscape.reward_range
    assert high - low == pytest.approx(landscape.height)
    top = landscape(landscape.centres)
    assert torch.allclose(top, torch.full((k,), high, dtype=torch.float64), rtol=1e-12)
    g = torch.Generator().manual_seed(0)
    for i in range(k):
        directions = torch.randn(64, dim, generator=g, dtype=torch.float64)
        directions = directions / directions.norm(dim=1, keepdim=True)
        near = landscape.centres[i] + 1e-3 * landscape.widths[i] * directions
        values = landscape(near)
        assert (values < high).all() and (values >= low).all()
    separation = torch.cdist(landscape.centres, landscape.centres) + 1e9 * torch.eye(k)
    assert separation.min() >= bench.MIN_SEPARATION
    assert (landscape.centres.abs() <= bench.BOX).all()
    assert int(landscape.sharp.sum()) == k // 2


def test_found_counts_a_centre_and_rejects_a_point_two_tenths_of_a_width_away():
    landscape = bench.make_landscape(3, 4, seed=11)
    assert landscape.found(landscape.centres).all()
    assert int(landscape.found(landscape.centres[:1].repeat(5, 1)).sum()) == 1  # counted once
    g = torch.Generator().manual_seed(1)
    direction = torch.randn(4, 3, generator=g, dtype=torch.float64)
    direction = direction / direction.norm(dim=1, keepdim=True)
    away = landscape.centres + 0.2 * landscape.widths[:, None] * direction
    assert not landscape.found(away).any()
    assert not landscape.found(torch.empty(0, 3, dtype=torch.float64)).any()


def test_landscapes_are_reproducible_from_their_seed():
    a, b = bench.make_landscape(5, 8, seed=7), bench.make_landscape(5, 8, seed=7)
    c = bench.make_landscape(5, 8, seed=8)
    theta = torch.rand(16, 5, dtype=torch.float64, generator=torch.Generator().manual_seed(2))
    assert torch.equal(a.centres, b.centres) and torch.equal(a(theta), b(theta))
    assert a.height == b.height and a.offset == b.offset
    assert not torch.equal(a.centres, c.centres)


@pytest.mark.parametrize("method", ["random search", "IPOP-CMA-ES"])
def test_one_case_end_to_end(method):
    if method == "IPOP-CMA-ES":
        pytest.importorskip("cma")
    case = bench.run_case(2, 2, 0, method, [60, 150])
    for budget in ("60", "150"):
        result = case["budgets"][budget]
        assert result["trials"] == int(budget)  # both use the budget exactly
        assert 0 <= result["found"] <= 2 and result["returned"] >= 1
    assert bench.run_case(2, 2, 0, method, [60, 150])["budgets"] == case["budgets"]


def test_nmmso_snapshot_equals_a_run_halted_at_the_smaller_budget():
    pytest.importorskip("pynmmso")
    landscape = bench.make_landscape(2, 4, seed=5)
    alone = bench.run_nmmso(landscape, [120], seed=9)
    longer = bench.run_nmmso(landscape, [120, 300], seed=9)
    assert torch.equal(alone[120][0], longer[120][0]) and alone[120][1] == 120
    assert longer[300][1] == 300


def test_keep_others_keeps_each_case_with_the_machine_that_ran_it(tmp_path):
    path = tmp_path / "report.json"
    grid = ["--dims", "2", "--ks", "2", "--seeds", "1", "--budgets", "40", "--workers", "0"]
    bench.main([*grid, "--methods", "random search", "PoWER", "--json", str(path)])
    report = json.loads(path.read_text())
    assert [c["machine"] for c in report["cases"]] == [bench.machine()] * 2  # one thread here
    earlier = {"architecture": "elsewhere", "torch_cpu_capability": "NONE", "torch_threads": 1}
    for case in report["cases"]:
        case["machine"] = earlier  # as if both had run on another machine
    path.write_text(json.dumps(report))
    bench.main([*grid, "--methods", "PoWER", "--keep-others", "--json", str(path)])
    machines = {c["method"]: c["machine"] for c in json.loads(path.read_text())["cases"]}
    assert machines == {"random search": earlier, "PoWER": bench.machine()}

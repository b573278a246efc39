"""The CEC 2013 niching benchmark: its functions' known optima, the competition's count, and
tiny end-to-end runs (pycma on a 1-D function included)."""

import math
import sys
from pathlib import Path

import pytest
import torch

sys.path.insert(0, str(Path(__file__).resolve().parents[1] / "benchmarks"))
import bench_niching as bench  # noqa: E402

DTYPE = torch.float64


def vincent_optima(dim: int) -> torch.Tensor:
    """sin(10 log x) = 1 at x = exp((π/2 + 2πj)/10): 6 such x in [0.25, 10] per axis."""
    xs = [math.exp((math.pi / 2 + 2 * math.pi * j) / 10) for j in range(-2, 4)]
    xs = [x for x in xs if 0.25 <= x <= 10]
    assert len(xs) == 6
    grid = torch.cartesian_prod(*[torch.tensor(xs, dtype=DTYPE)] * dim)
    return grid.reshape(-1, dim)


KNOWN = {
    1: torch.tensor([[0.0], [30.0]], dtype=DTYPE),
    2: torch.tensor([[0.1], [0.3], [0.5], [0.7], [0.9]], dtype=DTYPE),
    3: torch.tensor([[0.15 ** (4 / 3)]], dtype=DTYPE),  # 5π(x^¾ − 0.05) = π/2
    4: torch.tensor(
        [[3.0, 2.0], [-2.805118, 3.131312], [-3.779310, -3.283186], [3.584428, -1.848126]],
        dtype=DTYPE,
    ),
    5: torch.tensor([[0.0898420131, -0.7126564030], [-0.0898420131, 0.7126564030]], dtype=DTYPE),
    7: vincent_optima(2),
    9: vincent_optima(3),
}


@pytest.mark.parametrize("number", sorted(KNOWN))
def test_known_global_optima_are_counted_and_duplicates_once(number):
    problem = bench.FUNCTIONS[number - 1]
    optima = KNOWN[number]
    assert optima.shape == (problem.optima, problem.dim)
    assert ((optima >= problem.lower) & (optima <= problem.upper)).all()
    assert problem.found(optima, 1e-3) == problem.optima
    assert problem.found(optima[:1].repeat(3, 1), 1e-3) == 1
    # A point a radius and a bit away from an optimum is its own seed, but not an optimum.
    shifted = optima[:1] + 1.5 * problem.radius / math.sqrt(problem.dim)
    shifted = torch.minimum(torch.maximum(shifted, problem.lower), problem.upper)
    if not torch.equal(shifted, optima[:1]):
        assert problem.found(torch.cat((shifted, optima[1:])), 1e-3) == problem.optima - 1


def test_the_best_of_a_niche_is_its_seed():
    # Within one radius of the optimum, a worse point before it in the list does not hide it
    # (the count sorts by value first).
    problem = bench.FUNCTIONS[1]  # equal maxima, radius 0.01
    points = torch.tensor([[0.105], [0.1]], dtype=DTYPE)
    assert problem.found(points, 1e-4) == 1
    assert problem.found(points[:1], 1e-4) == 0


def test_shubert_and_rastrigin_reach_their_optimum_values():
    g = torch.Generator().manual_seed(0)
    for number in (6, 8, 10):
        problem = bench.FUNCTIONS[number - 1]
        u = torch.rand(200_000, problem.dim, generator=g, dtype=DTYPE)
        values = problem(problem.lower + (problem.upper - problem.lower) * u)
        assert float(values.max()) <= problem.f_star + 1e-9
        assert float(values.max()) > problem.f_star - 0.1 * abs(problem.f_star)


@pytest.mark.parametrize(
    "method", ["DIPOLE", "DIPOLE (coverage)", "random search", "IPOP-CMA-ES", "NMMSO"]
)
def test_one_run_end_to_end_on_a_1d_function(method):
    if method == "IPOP-CMA-ES":
        pytest.importorskip("cma")
    if method == "NMMSO":
        pytest.importorskip("pynmmso")
    case = bench.run_case(1, 0, method, [100, 250])
    for budget in ("100", "250"):
        result = case["budgets"][budget]
        assert result["trials"] <= int(budget) and result["returned"] >= 1
        assert all(0 <= n <= 2 for n in result["found"].values())
    assert bench.run_case(1, 0, method, [100, 250])["budgets"] == case["budgets"]


def test_every_method_the_command_line_offers_has_a_runner():
    assert set(bench.METHODS + bench.peers.OPT_IN) <= set(bench.RUNNERS)


def test_bad_function_number():
    with pytest.raises(ValueError, match="function number must lie in 1..10"):
        bench.run_case(11, 0, "DIPOLE", [10])


# ------------------------------------------------------------------------- --suite more
def branin_optima() -> torch.Tensor:
    return torch.tensor([[-math.pi, 12.275], [math.pi, 2.275], [3 * math.pi, 2.475]], dtype=DTYPE)


def more_optima(number: int) -> torch.Tensor:
    """The global optima of MORE_FUNCTIONS[number − 1], known in closed form or by design."""
    if number == 1:
        return branin_optima()
    if number == 2:  # sin⁶(5πx) = 1 at 0.1, 0.3, …, 0.9 on each axis
        xs = torch.tensor([0.1, 0.3, 0.5, 0.7, 0.9], dtype=DTYPE)
        return torch.cartesian_prod(xs, xs)
    if number == 3:  # every pair of Himmelblau's four optima
        two = KNOWN[4]
        return torch.cat((two.repeat_interleave(4, 0), two.repeat(4, 1)), dim=1)
    return {4: bench._PEAK_CENTRES, 5: bench._BOWL_CENTRES, 6: bench._CONE_CENTRES}[number]


@pytest.mark.parametrize("number", range(1, len(bench.MORE_FUNCTIONS) + 1))
def test_more_functions_their_optima_are_counted_and_none_is_higher(number):
    problem = bench.MORE_FUNCTIONS[number - 1]
    optima = more_optima(number)
    assert optima.shape == (problem.optima, problem.dim)
    assert ((optima >= problem.lower) & (optima <= problem.upper)).all()
    assert problem(optima).sub(problem.f_star).abs().max() < 1e-5
    assert problem.found(optima, 1e-4) == problem.optima
    # Each optimum its own niche: no two within twice the count's radius.
    distance = torch.cdist(optima, optima) + torch.eye(problem.optima, dtype=DTYPE) * 1e9
    assert float(distance.min()) > 2 * problem.radius
    # No point of the box is higher: random points, and each optimum's neighbourhood.
    g = torch.Generator().manual_seed(number)
    u = torch.rand(20_000, problem.dim, generator=g, dtype=DTYPE)
    near = optima.repeat(50, 1) + 1e-3 * torch.randn(50 * problem.optima, problem.dim,
                                                     generator=g, dtype=DTYPE)  # fmt: skip
    points = torch.cat((problem.lower + (problem.upper - problem.lower) * u, near))
    assert float(problem(points).max()) <= problem.f_star + 1e-9


def test_one_run_of_the_more_suite_end_to_end():
    case = bench.run_case(1, 0, "DIPOLE", [100, 250], suite="more")
    assert case["name"] == "M1 Branin 2D"
    assert all(0 <= n <= 3 for n in case["budgets"]["250"]["found"].values())
    with pytest.raises(ValueError, match="function number must lie in 1..6"):
        bench.run_case(7, 0, "DIPOLE", [10], suite="more")
    with pytest.raises(ValueError, match="suite must be one of"):
        bench.run_case(1, 0, "DIPOLE", [10], suite="cec2017")

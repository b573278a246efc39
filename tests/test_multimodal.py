"""DIPOLE finds several optima of the toy task where PoWER settles on (at most) one."""

import math

import pytest
import torch
from dipole_torch.tasks.multimodal import MultimodalTask

from dipole_torch import Dipole, Power

SEEDS = range(6)
BUDGET = 300  # trials


def distinct_optima(task, opt):
    """Optima that some final policy mean sits on (return of the mean >= 0.8)."""
    means = opt.policy_means.to(task.dtype)
    on_optimum = task.evaluate(means) >= 0.8
    return set(task.nearest_optimum(means)[on_optimum].tolist())


def learn(cls, task, seed):
    opt = cls(
        task.theta0,
        task.sigma_start,
        n0=10,
        reward_range=task.reward_range,
        generator=torch.Generator().manual_seed(seed),
    )
    while opt.trials < BUDGET:
        theta = opt.ask()
        opt.tell(theta, task.evaluate(theta))
    return opt


def test_dipole_keeps_several_optima_power_one():
    task = MultimodalTask(dim=2, num_optima=4)
    dipole = [len(distinct_optima(task, learn(Dipole, task, s))) for s in SEEDS]
    power = [len(distinct_optima(task, learn(Power, task, s))) for s in SEEDS]
    # Measured: DIPOLE [4, 3, 4, 3, 3, 3], PoWER [0, 1, 0, 1, 1, 0] (between optima, its
    # reward-weighted average often stalls). Require >= 2 optima in at least 5 of 6 runs and
    # >= 2.5 on average (margins of one run and of 0.8 optimum per run).
    assert sum(n >= 2 for n in dipole) >= 5, dipole
    assert sum(dipole) / len(dipole) >= 2.5, dipole
    assert max(power) <= 1, power


def test_multimodal_task_basics():
    task = MultimodalTask(dim=3, num_optima=3)
    assert torch.allclose(task.evaluate(task.optima), torch.ones(3))
    assert task.evaluate(torch.zeros(1, 3)).item() < 0.01
    with pytest.raises(ValueError, match=r"theta must have shape \[B, 3\]"):
        task.evaluate(torch.zeros(4, 2))
    with pytest.raises(ValueError, match="dim must be in"):
        MultimodalTask(dim=7)


def test_the_optima_the_policies_find_together():
    """An optimum is found by a policy whose noise-free return is at least 0.99 (within
    0.14 bump widths of it), counted once however many policies sit on it."""
    task = MultimodalTask(dim=2, num_optima=4, noise_std=0.3)  # (noise: not in the count)
    width = task.width
    near = task.optima[[2, 0, 2]] + torch.tensor([[0.1 * width, 0.0], [0.0, 0.0], [0.0, 0.0]])
    beyond = task.optima[[3]] + torch.tensor([[0.2 * width, 0.0]])  # return 0.980
    policies = torch.cat([near, beyond, task.theta0[None]])
    assert task.optima_found(policies) == [0, 2]
    assert task.policy_scalars(policies) == {"optima": 2.0}
    assert task.describe_policy_set(policies) == "2 of the 4 optima at return ≥ 0.99: 0, 2"
    assert task.describe_policy_set(task.theta0[None]) == "0 of the 4 optima at return ≥ 0.99"
    lines = task.describe_policies(policies)
    assert lines[1] == "optimum 0, return 1" and lines[3] == "optimum 3, return 0.9802"
    assert lines[0] == f"optimum 2, return {math.exp(-0.005):.4g}"


def test_the_optima_found_are_listed_in_order_whatever_the_policies_order():
    task = MultimodalTask(dim=2, num_optima=10)
    policies = task.optima[[9, 1]]
    assert task.optima_found(policies) == [1, 9]
    assert task.describe_policy_set(policies) == "2 of the 10 optima at return ≥ 0.99: 1, 9"


def test_the_optima_sit_on_the_circle_of_the_radius_and_returns_in_0_1():
    """The optima are evenly spread on the circle of ``radius`` in the first two coordinates
    (the first at 45° for 4 of them), Σ_start is ``exploration_std``² I, and noisy returns
    are clamped to the reward range [0, 1]."""
    task = MultimodalTask(dim=3, num_optima=4, radius=2.0, exploration_std=0.5)
    root2 = math.sqrt(2.0)
    expected = torch.tensor([[root2, root2, 0.0], [-root2, root2, 0.0]])
    torch.testing.assert_close(task.optima[:2], expected)
    torch.testing.assert_close(task.optima.norm(dim=-1), torch.full((4,), 2.0))
    torch.testing.assert_close(task.sigma_start, 0.25 * torch.eye(3))
    noisy = MultimodalTask(noise_std=10.0)
    theta = torch.cat([noisy.optima, torch.zeros(4, 2)]).repeat(4, 1)
    returns = noisy.evaluate(theta, torch.Generator().manual_seed(0))
    assert float(returns.min()) == 0.0 and float(returns.max()) == 1.0


def test_noisy_returns_without_a_generator_are_the_same_each_time():
    # The base class's promise: generator=None is a fixed default, so equal θ give equal
    # returns (the global RNG made a run's results.json differ between identical runs).
    task = MultimodalTask(noise_std=0.1)
    theta = torch.zeros(5, 2)
    assert torch.equal(task.evaluate(theta), task.evaluate(theta))
    g1, g2 = torch.Generator().manual_seed(1), torch.Generator().manual_seed(1)
    assert torch.equal(task.evaluate(theta, g1), task.evaluate(theta, g2))
    assert not torch.equal(task.evaluate(theta, g1), task.evaluate(theta, g1))
    # The fixed default is the seed default_seed (0).
    seeded = torch.Generator().manual_seed(task.default_seed)
    assert torch.equal(task.evaluate(theta), task.evaluate(theta, seeded))


@pytest.mark.parametrize(
    "kwargs, message",
    [
        ({"dim": 2.5}, "dim must be an integer"),
        ({"num_optima": 2.7}, "num_optima must be an integer"),
        ({"width": math.inf}, "width must be positive and finite"),
        ({"radius": math.nan}, "radius must be positive and finite"),
        ({"optima": [[math.nan, 0.0], [1.0, 1.0], [2.0, 2.0], [3.0, 3.0]]}, "non-finite"),
        ({"optima": [[0.0, 0.0]] * 3}, r"optima must have shape \[4, 2\], got \[3, 2\]"),
        ({"optima": [[0.0, 0.0, 0.0]] * 4}, r"optima must have shape \[4, 2\], got \[4, 3\]"),
        ({"num_optima": 1}, "num_optima must be >= 2, got 1"),
        ({"dim": 6}, r"dim must be in \[2, 5\], got 6"),
        ({"width": 0.0}, "width must be positive and finite, got 0.0"),
        ({"noise_std": math.inf}, "noise_std must be non-negative and finite, got inf"),
    ],
)
def test_bad_task_settings_are_refused_naming_them(kwargs, message):
    with pytest.raises(ValueError, match=message):
        MultimodalTask(**kwargs)

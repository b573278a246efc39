"""DS-GMR: GMR attractor path, critically damped spring-damper, differentiability."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from dipole_torch.models.ds_gmr import DSGMR

F64 = torch.float64


def test_attractor_path_is_time_weighted_average_of_centres():
    ds = DSGMR(3, duration=2.4, dt=0.02, stiffness=100.0, time_std=0.28, dtype=F64)
    theta = torch.randn(4, 9, dtype=F64, generator=torch.Generator().manual_seed(0))
    path = ds.attractor_path(theta)
    centres = torch.tensor([0.0, 0.8, 1.6], dtype=F64)
    log_h = -0.5 * ((ds.times[:, None] - centres) / 0.28) ** 2  # equal weights and σ_t
    h = torch.softmax(log_h, dim=-1)  # [T+1, K]
    expected = torch.einsum("tk,bkd->btd", h, theta.reshape(4, 3, 3))
    assert path.shape == (4, 121, 3)
    torch.testing.assert_close(path, expected)


def test_critically_damped_step_response():
    ds = DSGMR(1, duration=3.0, dt=0.001, stiffness=64.0, dim=1, dtype=F64)
    assert ds.damping == pytest.approx(2 * math.sqrt(64.0))
    path = ds.rollout(torch.ones(1, 1, dtype=F64), torch.zeros(1, dtype=F64))[0, :, 0]
    analytic = 1 - (1 + 8.0 * ds.times) * torch.exp(-8.0 * ds.times)  # x(t) for ζ = 1, ω = 8
    assert float(path.max()) <= 1.0  # no overshoot
    torch.testing.assert_close(path, analytic, atol=5e-3, rtol=0)


def test_straight_line_policy_starts_and_ends_at_rest():
    ds = DSGMR(3, duration=2.4, dt=0.02, stiffness=100.0, time_std=0.28, dtype=F64)
    start = torch.tensor([0.5, -0.35, 0.0], dtype=F64)
    target = torch.tensor([0.5, 0.35, 0.0], dtype=F64)
    theta = torch.stack([start, (start + target) / 2, target]).reshape(1, 9)
    path = ds.rollout(theta, start)[0]
    torch.testing.assert_close(path[0], start)
    assert float((path[1] - path[0]).norm()) < 1e-3  # starts from rest
    assert float((path[-1] - target).norm()) < 1e-3
    assert float((path[-1] - path[-2]).norm() / ds.dt) < 5e-3  # ends (almost) at rest
    # On the straight line throughout.
    torch.testing.assert_close(path[:, [0, 2]], start[[0, 2]].expand(121, 2))


def test_rollout_gradient_matches_finite_differences():
    ds = DSGMR(2, duration=0.5, dt=0.05, stiffness=50.0, dim=2, dtype=F64)
    theta = torch.randn(3, 4, dtype=F64, generator=torch.Generator().manual_seed(1))
    start = torch.tensor([0.1, -0.2], dtype=F64)
    assert torch.autograd.gradcheck(
        lambda th: ds.rollout(th, start)[:, -3:], (theta.requires_grad_(),)
    )


def test_fixed_goal_component_ends_every_path_at_the_goal():
    """goal_time: a fourth, fixed component at the goal (not in θ) after the K learned ones;
    whatever θ, the tip ends at the goal, at rest, once the goal component dominates."""
    ds = DSGMR(3, duration=2.8, dt=0.02, stiffness=100.0, time_std=0.28, goal_time=2.4, dtype=F64)
    assert ds.parameter_dim == 9
    torch.testing.assert_close(ds.time_centres, torch.tensor([0.0, 0.8, 1.6, 2.4], dtype=F64))
    start, goal = torch.zeros(3, dtype=F64), torch.tensor([0.1, 0.2, -0.3], dtype=F64)
    noise = 0.1 * torch.randn(5, 9, dtype=F64, generator=torch.Generator().manual_seed(2))
    theta = goal.repeat(3) + noise  # last attractors ~17 cm from the goal
    attractor = ds.attractor_path(theta, goal)
    log_h = -0.5 * ((ds.times[:, None] - ds.time_centres) / 0.28) ** 2
    h = torch.softmax(log_h, dim=-1)  # [T+1, 4]
    expected = torch.einsum("tk,bkd->btd", h[:, :3], theta.reshape(5, 3, 3)) + h[:, 3:] * goal
    torch.testing.assert_close(attractor, expected)
    path = ds.rollout(theta, start, goal)
    assert float((path[:, -1] - goal).norm(dim=-1).max()) < 5e-3
    # Without it, the tip ends at the last learned attractor instead.
    plain = DSGMR(3, duration=2.8, dt=0.02, stiffness=100.0, time_std=0.28, dtype=F64)
    end = plain.rollout(theta, start)[:, -1]
    assert float((end - theta[:, 6:]).norm(dim=-1).max()) < 5e-3
    assert float((end - goal).norm(dim=-1).min()) > 0.05
    assert ds.gmm(theta, goal).means.shape == (5, 4, 4)
    with pytest.raises(ValueError, match="goal must be a \\[3\\] point"):
        ds.rollout(theta, start)
    with pytest.raises(ValueError, match="no goal component"):
        plain.rollout(theta, start, goal)
    with pytest.raises(ValueError, match="goal_time must lie in"):
        DSGMR(3, duration=2.0, dt=0.02, stiffness=100.0, goal_time=2.4)


def test_bad_inputs_raise():
    with pytest.raises(ValueError, match="multiple of dt"):
        DSGMR(3, duration=1.0, dt=0.3, stiffness=10.0)
    with pytest.raises(ValueError, match="positive"):
        DSGMR(3, duration=1.0, dt=0.1, stiffness=-1.0)
    with pytest.raises(ValueError, match="num_attractors"):
        DSGMR(0, duration=1.0, dt=0.1, stiffness=1.0)
    ds = DSGMR(3, duration=1.0, dt=0.1, stiffness=10.0)
    with pytest.raises(ValueError, match="shape"):
        ds.rollout(torch.zeros(2, 8), torch.zeros(3))


def test_a_duration_a_hair_off_a_multiple_of_dt_is_refused():
    # 1.0 / 0.0999 rounds to 10 steps, 0.999 s: 0.1 % short of the duration asked for.
    with pytest.raises(ValueError, match="multiple of dt"):
        DSGMR(3, duration=1.0, dt=0.0999, stiffness=10.0)
    assert DSGMR(3, duration=0.3, dt=0.1, stiffness=10.0).steps == 3  # float rounding is fine


def test_the_time_std_defaults_to_half_the_spacing_of_the_time_centres():
    assert DSGMR(4, duration=2.0, dt=0.1, stiffness=10.0).time_std == pytest.approx(0.25)
    with_goal = DSGMR(4, duration=2.0, dt=0.1, stiffness=10.0, goal_time=1.6)
    assert with_goal.time_std == pytest.approx(0.2)  # the spacing on [0, goal_time]
    assert DSGMR(4, duration=2.0, dt=0.1, stiffness=10.0, time_std=0.3).time_std == 0.3


def test_one_generator_rolls_out_in_float32_and_float64_in_turn():
    ds = DSGMR(3, duration=1.0, dt=0.1, stiffness=10.0)
    theta = torch.randn(2, 9, dtype=F64, generator=torch.Generator().manual_seed(0))
    start = torch.zeros(3, dtype=F64)
    first = ds.rollout(theta, start)
    narrow = ds.rollout(theta.float(), start.float())
    assert narrow.dtype == torch.float32 and ds.rollout(theta, start).dtype == F64
    torch.testing.assert_close(narrow, first.float())
    torch.testing.assert_close(ds.rollout(theta, start), first, rtol=0, atol=0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_runs_on_cuda():
    ds = DSGMR(3, duration=1.0, dt=0.1, stiffness=10.0, device="cuda")
    path = ds.rollout(torch.zeros(5, 9, device="cuda"), torch.zeros(3, device="cuda"))
    assert path.device.type == "cuda" and path.shape == (5, 11, 3)


@pytest.mark.parametrize("goal_time", [None, 2.6])
def test_numpy_rollout_equals_the_torch_rollout(goal_time):
    """The numpy engine's DS-GMR (float64 arrays, written-out activations) against the
    torch rollout in float64: the same path to rounding."""
    ds = DSGMR(3, duration=2.8, dt=0.02, stiffness=100.0, time_std=0.28, goal_time=goal_time)
    ds64 = DSGMR(
        3, duration=2.8, dt=0.02, stiffness=100.0, time_std=0.28, goal_time=goal_time, dtype=F64
    )
    theta = torch.randn(5, 9, dtype=F64, generator=torch.Generator().manual_seed(5))
    start = torch.tensor([0.5, -0.35, 0.0], dtype=F64)
    goal = None if goal_time is None else torch.tensor([0.5, 0.35, 0.0], dtype=F64)
    expected = ds64.rollout(theta, start, goal).numpy()
    path = ds.rollout_numpy(theta.numpy(), start.numpy(), None if goal is None else goal.numpy())
    assert path.shape == (5, 141, 3) and path.dtype == np.float64
    np.testing.assert_allclose(path, expected, atol=1e-12, rtol=0)


def test_numpy_rollout_rejects_bad_shapes_and_goals():
    ds = DSGMR(3, duration=2.8, dt=0.02, stiffness=100.0, goal_time=2.4)
    with pytest.raises(ValueError, match=r"theta must have shape \[B, 9\]"):
        ds.rollout_numpy(np.zeros((2, 6)), np.zeros(3), np.zeros(3))
    with pytest.raises(ValueError, match="goal must be given exactly"):
        ds.rollout_numpy(np.zeros((2, 9)), np.zeros(3))

"""Viapoint task on the simulated WAM: eq. 9 reward, routes, tracking, gradients, config."""

from __future__ import annotations

import itertools
import math
from pathlib import Path

import pytest
import torch

from tasks.viapoint import ViapointTask

F64 = torch.float64
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "task" / "viapoint.yaml"


@pytest.fixture(scope="module")
def task() -> ViapointTask:
    return ViapointTask(dtype=F64)


def route_policies(task: ViapointTask) -> tuple[torch.Tensor, list[tuple[int, ...]]]:
    """θ for every route, solving the (linear in θ) DS-GMR passes x(t_i) = viapoint."""
    ds = task.dynamics
    k = ds.num_attractors
    response = torch.zeros(k, k, dtype=F64)  # x(t_i) per unit shift of attractor j
    for j in range(k):
        unit = torch.zeros(1, 3 * k, dtype=F64)
        unit[0, 3 * j] = 1.0
        response[:, j] = ds.rollout(unit, torch.zeros(3, dtype=F64))[0, task.pass_indices, 0]
    base = task.pass_positions(task.desired_trajectory(task.theta0[None]))[0]
    routes = list(itertools.product(*(range(n) for n in task.num_alternatives)))
    thetas = []
    for route in routes:
        goal = torch.stack([task.viapoints[i, a] for i, a in enumerate(route)])
        thetas.append(task.theta0 + torch.linalg.solve(response, goal - base).reshape(-1))
    return torch.stack(thetas), routes


def test_spaces_and_straight_line_start(task):
    assert task.theta0.shape == (9,) and task.sigma_start.shape == (9, 9)
    assert task.reward_range == (0.0, 1.0)
    torch.testing.assert_close(task.theta0[:3], task.start)
    torch.testing.assert_close(task.theta0[-3:], task.target)
    start_position = task.kinematics.forward_kinematics(task.q_start[None])[0]
    torch.testing.assert_close(start_position, task.start, atol=1e-8, rtol=0)
    path = task.trajectory(task.theta0[None])[0]
    assert float((path[-1] - task.target).norm()) < 2e-3
    reward = float(task.evaluate(task.theta0[None])[0])
    expected = math.exp(-task.reward_alpha * 0.1)  # 10 cm from every alternative
    assert reward == pytest.approx(expected, abs=0.01)


def test_reward_of_constructed_path_through_a_route(task):
    path = task.desired_trajectory(task.theta0[None]).clone()
    for i, index in enumerate(task.pass_indices):
        path[0, index] = task.viapoints[i, 1] + 1e-3  # ~1.7 mm off
    assert float(task.reward(path)[0]) >= 0.99
    path[0, task.pass_indices[0]] = task.viapoints[0, 0] + torch.tensor([0.0, 0.0, 0.05])
    alpha = task.reward_alpha
    expected = (2 * math.exp(-alpha * 3**0.5 * 1e-3) + math.exp(-alpha * 0.05)) / 3
    assert float(task.reward(path)[0]) == pytest.approx(expected, rel=1e-6)


def test_every_route_is_reachable_and_recognised(task):
    thetas, routes = route_policies(task)
    assert len(routes) == 8
    rewards = task.evaluate(thetas)
    assert bool((rewards >= 0.99).all()), rewards
    assert task.route(thetas).tolist() == [list(r) for r in routes]
    assert task.route(thetas).dtype == torch.long
    # Routes need attractor shifts of at most ~1.5 exploration std from θ0.
    assert float((thetas - task.theta0).abs().max()) < 0.16


def test_rewards_stay_in_range(task):
    generator = torch.Generator().manual_seed(0)
    near = task.theta0 + 0.1 * torch.randn(32, 9, generator=generator, dtype=F64)
    far = task.theta0 + 2.0 * torch.randn(8, 9, generator=generator, dtype=F64)
    rewards = task.evaluate(torch.cat([near, far]))
    assert rewards.shape == (40,)
    assert bool(((rewards >= 0) & (rewards <= 1)).all())
    assert torch.equal(rewards, task.evaluate(torch.cat([near, far])))  # deterministic


def test_unreachable_path_costs_reward(task):
    theta = task.theta0.clone()
    theta[3:6] = torch.tensor([2.0, 0.0, 0.5], dtype=F64)  # middle attractor 2 m out
    desired = task.desired_trajectory(theta[None])[0]
    actual = task.trajectory(theta[None])[0]
    assert float(actual.norm(dim=-1).max()) <= 0.915  # the arm's reach (0.5518 + 0.3628 m)
    assert float((desired - actual).norm(dim=-1).max()) > 0.3
    # The reward is that of the arm's path, not of the desired one.
    torch.testing.assert_close(task.evaluate(theta[None]), task.reward(actual[None]))
    assert not torch.allclose(task.reward(actual[None]), task.reward(desired[None]))


def test_reward_gradient_through_dsgmr_tracking_and_kinematics(task):
    generator = torch.Generator().manual_seed(3)
    theta = task.theta0 + 0.1 * torch.randn(2, 9, generator=generator, dtype=F64)
    theta.requires_grad_(True)
    (gradient,) = torch.autograd.grad(task.evaluate(theta).sum(), theta)
    assert float(gradient.abs().max()) > 1e-2
    # Central differences along random directions (a few rollouts instead of 2·D).
    eps = 1e-6
    directions = torch.randn(3, *theta.shape, generator=generator, dtype=F64)
    with torch.no_grad():
        for direction in directions:
            plus = task.evaluate(theta + eps * direction)
            minus = task.evaluate(theta - eps * direction)
            numeric = (plus - minus) / (2 * eps)  # [B]: rows are independent policies
            analytic = (gradient * direction).sum(-1)
            torch.testing.assert_close(analytic, numeric, atol=1e-7, rtol=1e-5)


def test_another_layout_without_code_changes():
    task = ViapointTask(
        start=[0.45, -0.3, 0.1],
        target=[0.45, 0.3, -0.1],
        pass_times=[0.5, 1.5],
        viapoints=[[[0.45, -0.15, 0.2], [0.45, -0.15, 0.0], [0.3, -0.15, 0.1]], [[0.5, 0.2, 0.0]]],
        duration=2.0,
        dt=0.025,
        time_std=None,
        dtype="float64",
    )
    assert task.theta0.shape == (6,) and task.num_alternatives == [3, 1]
    theta = task.theta0 + 0.05 * torch.randn(5, 6, generator=torch.Generator().manual_seed(0))
    rewards = task.evaluate(theta)
    assert rewards.shape == (5,) and bool(((rewards >= 0) & (rewards <= 1)).all())
    routes = task.route(theta)
    assert routes.shape == (5, 2) and int(routes[:, 1].max()) == 0 and int(routes.max()) <= 2


def test_config_instantiates():
    omegaconf = pytest.importorskip("omegaconf")
    hydra_utils = pytest.importorskip("hydra.utils")
    config = omegaconf.OmegaConf.load(CONFIG)
    config = omegaconf.OmegaConf.merge({"device": "cpu"}, {"task": config})
    assert config.task.trials == 300 and config.task.n0 == 30
    task = hydra_utils.instantiate(config.task.env)
    assert isinstance(task, ViapointTask)
    assert task.parameter_dim == 9 and task.num_alternatives == [2, 2, 2]
    separation = (task.viapoints[:, 0] - task.viapoints[:, 1]).norm(dim=-1)
    assert bool(((separation >= 0.15) & (separation <= 0.25)).all())
    assert task.evaluate(task.theta0[None]).dtype == torch.float32


def test_bad_inputs_raise(task):
    with pytest.raises(ValueError, match="shape"):
        task.evaluate(torch.zeros(2, 8))
    with pytest.raises(ValueError, match="non-finite"):
        task.evaluate(torch.full((1, 9), float("nan")))
    with pytest.raises(TypeError):
        task.evaluate([[0.0] * 9])
    with pytest.raises(ValueError, match="alternatives for each"):
        ViapointTask(pass_times=[0.4, 1.2])
    with pytest.raises(ValueError, match="pass_times"):
        ViapointTask(pass_times=[0.4, 1.2, 3.0])
    with pytest.raises(ValueError, match="start"):
        ViapointTask(start=[0.5, 0.0])
    with pytest.raises(ValueError, match="viapoints\\[1\\]"):
        ViapointTask(viapoints=[[[0.5, 0.0, 0.0]], [[0.5, 0.0]], [[0.5, 0.0, 0.0]]])
    with pytest.raises(ValueError, match="reward_alpha"):
        ViapointTask(reward_alpha=0.0)
    with pytest.raises(ValueError, match="workspace"):
        ViapointTask(start=[1.5, 0.0, 0.0])


def test_dh_kinematics_match_the_urdf_chain(task):
    q = task.kinematics.clamp_to_limits(
        torch.randn(16, 7, generator=torch.Generator().manual_seed(1), dtype=F64)
    )
    position, jacobian = task.kinematics.position_and_jacobian(q)
    reference, pose = task.kinematics.chain.jacobian(q, ret_eef_pose=True)
    torch.testing.assert_close(position, pose[:, :3, 3], atol=1e-7, rtol=0)
    torch.testing.assert_close(jacobian, reference[:, :3], atol=1e-7, rtol=0)


def test_describe_and_plot_policies(task):
    matplotlib = pytest.importorskip("matplotlib")
    thetas, routes = route_policies(task)
    lines = task.describe_policies(thetas[[0, 3]])
    assert lines[0].startswith("route (0, 0, 0): below / near / below, return ")
    assert float(lines[0].split("return ")[1].split(",")[0]) >= 0.99
    assert lines[1].startswith("route (0, 1, 1): below / far / above, return")
    assert lines[1].endswith(" cm")
    figure = task.plot_policies(torch.cat([thetas[:3], task.theta0[None]]))
    assert isinstance(figure, matplotlib.figure.Figure)
    ax = figure.axes[0]
    assert len(ax.lines) == 4 and ax.get_xlabel() == "x [m]"
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "start" in texts and "target" in texts and any("below / near" in t for t in texts)
    figure.canvas.draw()  # renders on Agg, no display
    matplotlib.pyplot.close(figure)
    with pytest.raises(ValueError, match="labels"):
        task.plot_policies(thetas[:2], labels=["one"])


def test_dipole_finds_several_routes():
    """Paper's settings (α = 1, m = 10, M = 5, n0 = 30, 300 trials) on a fixed seed: at least
    two final policy means, evaluated without noise, take distinct routes with reward ≥ 0.9.
    (Measured on seeds 0-3: 4, 3, 2 and 1 routes; seed 0 leaves a margin of two.)"""
    from dipole_torch import Dipole

    torch.set_num_threads(1)
    task = ViapointTask()
    opt = Dipole(
        task.theta0.double(),
        task.sigma_start.double(),
        n0=30,
        reward_range=task.reward_range,
        generator=torch.Generator().manual_seed(0),
    )
    while opt.trials < 300:
        theta = opt.ask()
        rewards = task.evaluate(theta.float())
        assert bool(((rewards >= 0) & (rewards <= 1)).all())
        opt.tell(theta, rewards)
    means = opt.policy_means.float()
    rewards = task.evaluate(means)
    routes = {
        tuple(r)
        for r, v in zip(task.route(means).tolist(), rewards.tolist(), strict=True)
        if v >= 0.9
    }
    assert len(routes) >= 2, (rewards, task.route(means))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_runs_on_cuda():
    task = ViapointTask(device="cuda")
    theta = task.theta0 + 0.1 * torch.randn(30, 9, device="cuda")
    rewards = task.evaluate(theta)
    assert rewards.device.type == "cuda" and rewards.shape == (30,)
    assert bool(((rewards >= 0) & (rewards <= 1)).all())
    assert task.route(theta).shape == (30, 3)
    cpu = ViapointTask().evaluate(theta.cpu())
    torch.testing.assert_close(rewards.cpu(), cpu, atol=1e-3, rtol=0)

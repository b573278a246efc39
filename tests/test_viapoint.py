"""Viapoint task on the simulated WAM: eq. 9 reward, routes, end point, tracking, gradients
on both kinematics paths, config."""

from __future__ import annotations

import copy
import itertools
import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from dipole_torch.models.kinematics import ArmKinematics
from dipole_torch.models.wam import WamKinematics
from dipole_torch.tasks.viapoint import ViapointTask

F64 = torch.float64
CONFIG = Path(__file__).resolve().parents[1] / "configs" / "task" / "viapoint.yaml"


@pytest.fixture(scope="module")
def task() -> ViapointTask:
    return ViapointTask(dtype=F64)


@pytest.fixture(scope="module")
def dh_task() -> ViapointTask:
    return ViapointTask(dtype=F64, kinematics="wam_dh")


def route_policies(task: ViapointTask) -> tuple[torch.Tensor, list[tuple[int, ...]]]:
    """θ for every route, solving the (linear in θ) DS-GMR passes x(t_i) = viapoint."""
    ds = task.dynamics
    k = ds.num_attractors
    response = torch.zeros(k, k, dtype=F64)  # x(t_i) per unit shift of attractor j
    origin = torch.zeros(3, dtype=F64)
    goal = origin if ds.goal_time is not None else None  # the fixed target component at 0
    for j in range(k):
        unit = torch.zeros(1, 3 * k, dtype=F64)
        unit[0, 3 * j] = 1.0
        response[:, j] = ds.rollout(unit, origin, goal)[0, task.pass_indices, 0]
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


def test_paths_end_at_the_target(task):
    """The fixed final DS-GMR component: every exact route ends within 2.5 mm of the target
    (measured 1.9 mm), almost at rest; with the three learned attractors alone (the previous
    task: 2.4 s, no target component) the same routes end ~10 cm short, near the last
    viapoint."""
    assert task.end_at_target and task.dynamics.goal_time == pytest.approx(2.4)
    assert task.dynamics.time_centres.tolist() == pytest.approx([0.0, 0.8, 1.6, 2.4])
    thetas, _ = route_policies(task)
    path = task.trajectory(thetas)
    assert bool((task.reward(path) >= 0.99).all())
    ends = task.end_point_error(path)
    assert float(ends.max()) < 2.5e-3, ends
    speed = (path[:, -1] - path[:, -2]).norm(dim=-1) / task.dynamics.dt
    assert float(speed.max()) < 0.02  # m/s
    old = ViapointTask(dtype=F64, end_at_target=False, duration=2.4)
    old_thetas, _ = route_policies(old)
    old_path = old.trajectory(old_thetas)
    assert bool((old.reward(old_path) >= 0.99).all())
    assert float(old.end_point_error(old_path).min()) > 0.09
    # Same attractor shifts from θ0 either way (the target component costs no reach).
    shift, old_shift = (thetas - task.theta0).abs().max(), (old_thetas - old.theta0).abs().max()
    assert float(shift) == pytest.approx(float(old_shift), abs=0.005)


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


@pytest.mark.parametrize("kinematics", ["pytorch_kinematics", "wam_dh"])
def test_reward_gradient_through_dsgmr_tracking_and_kinematics(kinematics, task, dh_task):
    task = task if kinematics == "pytorch_kinematics" else dh_task
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
    hydra = pytest.importorskip("hydra")
    compat = pytest.importorskip("dipole_torch.training.hydra_compat")
    with hydra.initialize_config_module("dipole_torch.configs", **compat.VERSION_BASE):
        config = hydra.compose("config", overrides=[f"task={CONFIG.stem}"])
    assert config.task.trials == 300 and config.task.n0 == 30
    task = compat.instantiate(config.task.env)
    assert isinstance(task, ViapointTask)
    assert task.parameter_dim == 9 and task.num_alternatives == [2, 2, 2]
    separation = (task.viapoints[:, 0] - task.viapoints[:, 1]).norm(dim=-1)
    assert bool(((separation >= 0.15) & (separation <= 0.25)).all())
    assert task.evaluate(task.theta0[None]).dtype == torch.float32
    # pytorch-kinematics by default; the WAM's analytic path on request, same paths.
    assert type(task.kinematics) is ArmKinematics
    assert task.kinematics.urdf_path.name == "wam7.urdf" and task.kinematics.dof == 7
    fast = compat.instantiate(config.task.env, kinematics="wam_dh")
    assert isinstance(fast.kinematics, WamKinematics)
    theta = task.theta0 + 0.05 * torch.randn(4, 9, generator=torch.Generator().manual_seed(0))
    torch.testing.assert_close(fast.trajectory(theta), task.trajectory(theta), atol=1e-5, rtol=0)


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
    with pytest.raises(ValueError, match="kinematics must be one of pytorch_kinematics, wam_dh"):
        ViapointTask(kinematics="dh")
    with pytest.raises(ValueError, match="fast path of the bundled WAM"):
        ViapointTask(kinematics="wam_dh", end_effector="wam_link7")
    with pytest.raises(ValueError, match="'wam_hand' is not a link.*wam_base, wam_link1"):
        ViapointTask(end_effector="wam_hand")
    with pytest.raises(ValueError, match="initial_joints must give 7 finite values"):
        ViapointTask(initial_joints=[0.0, 0.6, 1.6])
    with pytest.raises(ValueError, match="goal_time"):
        ViapointTask(goal_time=3.0)


DEFAULT_VIAPOINTS = [
    [[0.5, -0.29, -0.1], [0.5, -0.29, 0.1]],
    [[0.4, 0.06, 0.0], [0.6, 0.06, 0.0]],
    [[0.5, 0.34, -0.1], [0.5, 0.34, 0.1]],
]


def test_the_default_layout_is_within_reach_without_a_warning():
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        ViapointTask()


def test_points_beyond_the_arms_stretch_are_errors():
    """The WAM's links reach 0.957 m from its shoulder at full stretch (0.55 m upper arm
    with its 4.5 cm offset, 4.5 cm elbow offset, 0.3 m forearm, 6 cm tool): a point farther
    is out of reach in every posture, and the error says by how much."""
    with pytest.raises(
        ValueError,
        match=r"target \[1\.5, 0, 0\] is out of the arm's reach \(outside its workspace\) by "
        r"54\.3 cm: it is 1\.5 m from the first joint of barrett_wam_7dof .* reach 0\.957 m",
    ):
        ViapointTask(target=[1.5, 0.0, 0.0])
    far = copy.deepcopy(DEFAULT_VIAPOINTS)
    far[2][1] = [0.5, 0.34, 1.2]
    with pytest.raises(ValueError, match=r"viapoints\[2\]\[1\] \[0\.5, 0\.34, 1\.2\] is out of"):
        ViapointTask(viapoints=far)


def test_points_inverse_kinematics_does_not_reach_warn():
    """5 cm above the shoulder is within the links' stretch, but the elbow cannot fold the
    forearm back that far (joint 4 stops at 3.1 rad): a warning naming the point and how far
    from it inverse kinematics from the start posture ends. Not an error: another posture
    might reach a point that IK from this one does not."""
    with pytest.warns(
        UserWarning,
        match=r"target \[0, 0, 0\.05\] may be out of the arm's reach: inverse kinematics from "
        r"the start posture ends \d+\.\d cm from it",
    ):
        ViapointTask(target=[0.0, 0.0, 0.05])


def test_alternatives_on_one_side_are_told_apart_by_their_index(dh_task):
    # At t = 1.2 s, a third alternative near the shoulder: two of three are "near".
    layout = [[list(p) for p in pass_time] for pass_time in dh_task.viapoints.tolist()]
    layout[1].append([0.45, 0.06, 0.0])
    task = ViapointTask(dtype=F64, kinematics="wam_dh", viapoints=layout)
    assert task.alternative_names[1] == ["near0", "far1", "near2"]
    assert task.alternative_names[0] == ["below", "above"]
    assert task.route_name([1, 2, 0]) == "above / near2 / below"


def test_a_route_at_the_threshold_return_exactly_is_found(dh_task):
    thetas, routes = route_policies(dh_task)
    value = float(dh_task.evaluate(thetas[:1])[0])
    assert dh_task.routes_found(thetas[:1], threshold=value) == [routes[0]]


def test_a_pass_time_without_alternatives_is_refused(dh_task):
    with pytest.raises(ValueError, match=r"viapoints\[1\] must be a list of alternatives"):
        ViapointTask(viapoints=[[[0.5, -0.29, 0.1]], [], [[0.5, 0.34, 0.1]]])


def test_the_analytic_wam_takes_its_own_base_link_by_name():
    named = ViapointTask(dtype=F64, kinematics="wam_dh", base_link="wam_base")
    torch.testing.assert_close(named.q_start, ViapointTask(dtype=F64, kinematics="wam_dh").q_start)


def test_a_point_inverse_kinematics_misses_by_millimetres_warns():
    # The warning's bound is 1 mm: 21 cm above the shoulder, IK ends about 5 mm short.
    with pytest.warns(UserWarning, match=r"target \[0, 0, 0\.21\] .* ends 0\.\d cm from it"):
        ViapointTask(dtype=F64, kinematics="wam_dh", target=[0.0, 0.0, 0.21])


def test_input_errors_name_the_argument_and_the_joint():
    ragged = copy.deepcopy(DEFAULT_VIAPOINTS)
    ragged[1][1] = [0.6, 0.06]
    with pytest.raises(
        ValueError, match=r"viapoints\[1\]\[1\] must be a finite \[x, y, z\] point \(m\)"
    ):
        ViapointTask(viapoints=ragged)
    with pytest.raises(ValueError, match=r"viapoints\[0\] must be a list of alternatives"):
        ViapointTask(viapoints=[0.5, [[0.4, 0.06, 0.0]], [[0.5, 0.34, 0.1]]])
    with pytest.raises(ValueError, match=r"start must be a finite \[x, y, z\] point"):
        ViapointTask(start=[0.5, "left", 0.0])
    # The joint out of its limits is named; limits print as the URDF gives them.
    with pytest.raises(
        ValueError,
        match=r"initial_joints lie outside the joint limits .* at wam_j4 = 3\.5 "
        r"\(limits \[-0\.9, 3\.1\]\)$",
    ):
        ViapointTask(start=None, initial_joints=[0.0, 0.6, 0.0, 3.5, 0.0, 0.0, 0.0])
    # With a start point, initial_joints is the start IK's first guess: a posture all the same
    # (one beyond the limits was taken without a word).
    with pytest.raises(ValueError, match=r"initial_joints lie outside .* at wam_j4 = 3\.5 "):
        ViapointTask(initial_joints=[0.0, 0.6, 0.0, 3.5, 0.0, 0.0, 0.0])
    lower = [-2.6, -2.0, -2.8, 3.2, -4.76, -1.6, -3.0]
    with pytest.raises(
        ValueError, match=r"lower exceeds upper for joint\(s\) wam_j4 \[3\.2, 3\.1\] of wam7"
    ):
        ViapointTask(joint_lower=lower)
    with pytest.raises(ValueError, match=r"joint_upper must be 7 numbers"):
        ViapointTask(joint_upper=["a"] * 7)


def test_analytic_fast_path_gives_the_default_paths():
    """kinematics="wam_dh" against the default pytorch-kinematics path (the torch engine's
    kinematics): same start posture (to the start IK's tolerance), same arm paths and rewards
    for policies up to 0.2 m from θ0 (measured: within 1.2e-10 m), same positions and
    Jacobians. Far outside the workspace the DLS steps at the reach boundary amplify rounding
    differences, so the two paths may part there (both stay valid arm paths)."""
    task = ViapointTask(dtype=F64, engine="torch")
    dh_task = ViapointTask(dtype=F64, kinematics="wam_dh", engine="torch")
    assert type(task.kinematics) is ArmKinematics and type(dh_task.kinematics) is WamKinematics
    torch.testing.assert_close(dh_task.q_start, task.q_start, atol=1e-6, rtol=0)
    generator = torch.Generator().manual_seed(2)
    theta = torch.cat(
        [
            task.theta0 + 0.1 * torch.randn(8, 9, generator=generator, dtype=F64),
            task.theta0 + 0.2 * torch.randn(8, 9, generator=generator, dtype=F64),
        ]
    )
    torch.testing.assert_close(dh_task.trajectory(theta), task.trajectory(theta), atol=1e-9, rtol=0)
    torch.testing.assert_close(dh_task.evaluate(theta), task.evaluate(theta), atol=1e-9, rtol=0)
    q = task.kinematics.clamp_to_limits(torch.randn(16, 7, generator=generator, dtype=F64))
    for expected, actual in zip(
        task.kinematics.position_and_jacobian(q),
        dh_task.kinematics.position_and_jacobian(q),
        strict=True,
    ):
        torch.testing.assert_close(actual, expected, atol=1e-7, rtol=0)


def test_describe_and_plot_policies(task):
    matplotlib = pytest.importorskip("matplotlib")
    thetas, routes = route_policies(task)
    lines = task.describe_policies(thetas[[0, 3]])
    assert lines[0].startswith("route (0, 0, 0): below / near / below, return ")
    assert float(lines[0].split("return ")[1].split(",")[0]) >= 0.99
    assert lines[1].startswith("route (0, 1, 1): below / far / above, return")
    assert lines[1].endswith(" cm from the target")
    assert float(lines[1].split("ends ")[1].split(" cm")[0]) <= 0.2
    figure = task.plot_policies(torch.cat([thetas[:3], task.theta0[None]]))
    assert isinstance(figure, matplotlib.figure.Figure)
    ax = figure.axes[0]
    assert len(ax.lines) == 4 and ax.get_xlabel() == "x [m]"
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    assert "start" in texts and "target" in texts and any("below / near" in t for t in texts)
    figure.canvas.draw()  # renders on Agg, no display
    matplotlib.pyplot.close(figure)


def test_the_routes_the_policies_take_together(task):
    """``routes_found`` counts distinct routes at return ≥ 0.9: a route taken twice counts
    once, a policy below 0.9 (θ0, the straight line, ~0.78) none."""
    thetas, routes = route_policies(task)
    chosen = thetas[[3, 0, 3, 5]]  # routes (0, 1, 1), (0, 0, 0), (0, 1, 1), (1, 0, 1)
    with_start = torch.cat([chosen, task.theta0[None]])
    assert task.routes_found(with_start) == [(0, 0, 0), (0, 1, 1), (1, 0, 1)]
    assert task.policy_scalars(with_start) == {"routes": 3.0}
    assert task.routes_found(task.theta0[None]) == []
    straight = tuple(task.route(task.theta0[None])[0].tolist())
    assert task.routes_found(task.theta0[None], threshold=0.5) == [straight]
    assert task.routes_found(thetas) == routes  # all 8
    assert task.describe_policy_set(with_start) == (
        "3 of the 8 routes at return ≥ 0.9: below / near / below; below / far / above; "
        "above / near / above"
    )
    assert task.describe_policy_set(task.theta0[None]) == "0 of the 8 routes at return ≥ 0.9"


def figure_layout_problems(figure, margins: bool = True) -> list[str]:
    """What makes a rendered policy figure hard to read in a TensorBoard card: wider than a
    card, more than 5 ticks on an axis, the legend or the title over an axis' ticks or
    label, the title outside the image, and with ``margins`` wide empty margins (the
    drawing, non-white pixels, spanning less than 90 % of the height or 85 % of the
    width)."""
    figure.canvas.draw()
    width, height = figure.canvas.get_width_height()
    problems = [] if 400 <= width <= 480 else [f"{width} px wide"]  # a card: ~350-420 px
    ax = figure.axes[0]
    renderer = figure.canvas.get_renderer()
    legend = ax.get_legend().get_window_extent(renderer)
    title = ax.title.get_window_extent(renderer)
    if not (title.x0 >= 0 and title.y0 >= 0 and title.x1 <= width and title.y1 <= height):
        problems.append(f"title outside the image: {title}")
    for axis in (ax.xaxis, ax.yaxis, ax.zaxis):
        low, high = sorted(axis.get_view_interval())
        shown = [
            label
            for location, label in zip(axis.get_majorticklocs(), axis.get_ticklabels(), strict=True)
            if low <= location <= high  # (the locator also places ticks beyond the view)
        ]
        if len(shown) > 5:
            problems.append(f"{len(shown)} ticks on {axis.axis_name}")
        for text in [*shown, axis.label]:
            extent = text.get_window_extent(renderer)
            for name, box in (("legend", legend), ("title", title)):
                if box.overlaps(extent):
                    problems.append(f"{name} over {text.get_text()!r}")
    image = np.asarray(figure.canvas.buffer_rgba())[..., :3]
    drawn = (image < 250).any(axis=-1)
    rows, columns = np.flatnonzero(drawn.any(axis=1)), np.flatnonzero(drawn.any(axis=0))
    spans = (rows[-1] - rows[0]) / height, (columns[-1] - columns[0]) / width
    if margins and (spans[0] < 0.9 or spans[1] < 0.85):
        problems.append(f"wide empty margins: the drawing spans {spans[0]:.0%} x {spans[1]:.0%}")
    return problems


def test_policy_figure_legend_colours_title_and_view(dh_task):
    """The legend in two columns, paths left and the points right (one entry for all the
    obstacles), a colour a path, the start and target stars where they are, the title."""
    matplotlib = pytest.importorskip("matplotlib.pyplot")
    thetas, _ = route_policies(dh_task)
    spheres = [
        {"centre": [0.6, 0.06, 0.0], "radius": 0.05},
        {"centre": [0.0, 0.0, 1.5], "radius": 0.1},
    ]
    blocked = dh_task.with_obstacles(spheres)
    figure = blocked.plot_policies(thetas[[0, 3]], labels=["one", "two"])
    ax = figure.axes[0]
    texts = [t.get_text() for t in ax.get_legend().get_texts()]
    points = ["via t = 0.4 s", "via t = 1.2 s", "via t = 2 s", "obstacle", "start", "target"]
    assert texts == ["one", "two", " ", " ", " ", " ", *points]  # 6 rows, 2 columns
    assert ax.lines[0].get_color() != ax.lines[1].get_color()
    assert ax.get_title() == "WAM end-effector paths of 2 policies"
    assert (ax.elev, ax.azim) == (20, -35)
    stars = {c.get_label(): c for c in ax.collections}
    stars = {name: np.ravel(stars[name]._offsets3d) for name in ("start", "target")}
    np.testing.assert_allclose(stars["start"], blocked.start.numpy())
    np.testing.assert_allclose(stars["target"], blocked.target.numpy())
    matplotlib.close(figure)
    one = dh_task.plot_policies(thetas[:1], title="a title")
    assert one.axes[0].get_title() == "a title"
    matplotlib.close(one)
    one = dh_task.plot_policies(thetas[:1])
    assert one.axes[0].get_title() == "WAM end-effector paths of 1 policy"
    matplotlib.close(one)
    with pytest.raises(ValueError, match=r"labels must give one entry per policy \(2\)"):
        dh_task.plot_policies(thetas[:2], labels=["one"])


def test_policy_figure_is_legible_at_tensorboard_card_size(task):
    """As TensorBoard's add_figure renders it (the canvas at the figure's dpi), on the
    default layout with an obstacle and on a layout whose box is tall and narrow (which
    leaves the sides of a landscape figure empty, but must not overlap)."""
    matplotlib = pytest.importorskip("matplotlib.pyplot")
    thetas, _ = route_policies(task)
    blocked = task.with_obstacles([{"centre": [0.6, 0.06, 0.0], "radius": 0.08}])
    figure = blocked.plot_policies(torch.cat([thetas[[0, 3, 5, 6]], task.theta0[None]]))
    assert figure_layout_problems(figure) == []
    matplotlib.close(figure)
    tall = ViapointTask(
        start=[0.5, 0.0, -0.3],
        target=[0.5, 0.0, 0.3],
        pass_times=[0.8, 1.6],
        viapoints=[[[0.5, -0.1, -0.1], [0.5, 0.1, -0.1]], [[0.5, 0.0, 0.15]]],
        duration=2.4,
        time_std=None,
    )
    figure = tall.plot_policies(tall.theta0[None])
    assert figure_layout_problems(figure, margins=False) == []
    matplotlib.close(figure)


def test_dipole_finds_several_routes():
    """The default DIPOLE (n0 = 30, 300 trials) on the default task (pytorch-kinematics, the
    fixed target component), seeds 0-3: the final policy means, evaluated without noise, take
    distinct routes with reward ≥ 0.9, at least 6 in all (measured: 3, 2, 1 and 3; a method
    that kept one policy would have 4 at most)."""
    from dipole_torch import Dipole

    torch.set_num_threads(1)
    task = ViapointTask()
    found = []
    for seed in range(4):
        opt = Dipole(
            task.theta0.double(),
            task.sigma_start.double(),
            n0=30,
            reward_range=task.reward_range,
            generator=torch.Generator().manual_seed(seed),
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
        found.append(len(routes))
    assert sum(found) >= 6, found


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


def test_numpy_engine_follows_the_torch_engine(task):
    """The default engine on a CPU (numpy, float64) against the torch rollout: the same
    paths to rounding, in float64 (measured: 3e-10 m) and in the default float32 (the torch
    rollout's rounding, for policies 0.1 m from θ0: measured 2.4e-7 m, rewards 1.8e-7)."""
    assert task.engine == "auto"
    torch_task = ViapointTask(dtype=F64, engine="torch")
    generator = torch.Generator().manual_seed(6)
    theta = torch.cat(
        [
            task.theta0 + 0.1 * torch.randn(16, 9, generator=generator, dtype=F64),
            task.theta0 + 0.3 * torch.randn(16, 9, generator=generator, dtype=F64),
        ]
    )
    torch.testing.assert_close(
        task.trajectory(theta), torch_task.trajectory(theta), atol=1e-8, rtol=0
    )
    torch.testing.assert_close(task.evaluate(theta), torch_task.evaluate(theta), atol=1e-8, rtol=0)
    # In float32 only near θ0: far outside the workspace the DLS steps at the reach boundary
    # amplify float32 rounding (as between the kinematics paths), and paths may part.
    task32, torch_task32 = ViapointTask(engine="numpy"), ViapointTask(engine="torch")
    theta32 = theta[:16].float()
    path = task32.trajectory(theta32)
    assert path.dtype == torch.float32
    torch.testing.assert_close(path, torch_task32.trajectory(theta32), atol=1e-5, rtol=0)
    torch.testing.assert_close(
        task32.evaluate(theta32), torch_task32.evaluate(theta32), atol=1e-5, rtol=0
    )


def test_engine_choice_and_its_errors(task):
    theta = task.theta0[None].clone()
    assert task._runs_numpy(theta)  # auto on the CPU
    assert not task._runs_numpy(theta.requires_grad_(True))  # a gradient needs torch
    with torch.no_grad():
        assert task._runs_numpy(theta)
    numpy_task = ViapointTask(dtype=F64, engine="numpy")
    with pytest.raises(ValueError, match="engine='numpy' is not differentiable"):
        numpy_task.evaluate(theta)
    with pytest.raises(ValueError, match="engine must be one of 'auto', 'numpy', 'torch'"):
        ViapointTask(engine="jax")
    with pytest.raises(ValueError, match="engine='numpy' runs on the CPU"):
        ViapointTask(engine="numpy", device="cuda")


@pytest.mark.parametrize("engine", ["numpy", "torch"])
def test_a_policys_path_does_not_depend_on_its_batch(engine):
    """Bit for bit: the lockstep benchmarks stack the batches of many runs into one rollout.
    (numpy's matmul picks its kernel by the operands' strides: a Jacobian returned as a view
    whose strides depend on B gave 4e-16 differences in float64.)"""
    task = ViapointTask(dtype=F64, engine=engine)
    generator = torch.Generator().manual_seed(7)
    theta = task.theta0 + 0.1 * torch.randn(12, 9, generator=generator, dtype=F64)
    whole = task.trajectory(theta)
    assert torch.equal(whole, torch.cat([task.trajectory(theta[:5]), task.trajectory(theta[5:])]))
    assert torch.equal(whole, torch.cat([task.trajectory(row[None]) for row in theta]))


@pytest.mark.parametrize("engine", ["torch", "numpy"])
def test_attractors_far_beyond_reach_give_the_returns_of_the_limit_not_nan(engine):
    # A float32 rollout from 3e38 m overflowed into NaN; far attractors are taken at
    # ATTRACTOR_LIMIT (1000 m): the arm's path, and the return, are the same.
    from dipole_torch.tasks.viapoint import ATTRACTOR_LIMIT

    task = ViapointTask(engine=engine)
    far = task.evaluate(torch.full((2, 9), 3e38))
    at_limit = task.evaluate(torch.full((2, 9), ATTRACTOR_LIMIT))
    assert torch.isfinite(far).all() and torch.equal(far, at_limit)


def test_half_precision_and_an_empty_policy_set_are_refused_clearly():
    for dtype in (torch.float16, torch.bfloat16):
        with pytest.raises(ValueError, match="too narrow for this task"):
            ViapointTask(dtype=dtype)
    task = ViapointTask()
    with pytest.raises(ValueError, match="theta holds no policy"):
        task.blocking_obstacle(torch.zeros(0, 9))


def test_the_layout_and_reward_constants_are_the_documented_ones():
    # Pass times 0.4 / 1.2 / 2.0 s on the 0.02 s grid, eq. 9's α = 2.5, the first pass time's
    # two alternatives 20 cm apart in z; a pass time may be the motion's last instant.
    task = ViapointTask()
    assert task.pass_indices == [20, 60, 100] and task.reward_alpha == 2.5
    first = task.viapoints[0, :2].double()
    assert torch.allclose(first, torch.tensor([[0.5, -0.29, -0.1], [0.5, -0.29, 0.1]],
                                              dtype=torch.float64), atol=1e-7)  # fmt: skip
    assert ViapointTask(pass_times=(0.4, 1.2, 2.8)).pass_indices[-1] == 140

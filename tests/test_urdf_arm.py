"""A second arm from config, no code change: a 4-joint URDF written here, through
pytorch-kinematics, in the viapoint task, learned by DIPOLE."""

from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from dipole_torch.models.kinematics import ArmKinematics
from dipole_torch.models.numpy_kinematics import NumpyChain
from dipole_torch.models.tracking import solve_position_ik, track_path
from dipole_torch.tasks.viapoint import ViapointTask

F64 = torch.float64

# Base yaw (continuous: no limits) and three pitch joints; a fixed tool flange 0.1 m past the
# wrist, and a fixed camera link on the base (a branch that is not on the chain).
URDF = """<?xml version="1.0"?>
<robot name="four_joint_arm">
  <link name="base"/> <link name="shoulder"/> <link name="upper_arm"/> <link name="forearm"/>
  <link name="hand"/> <link name="tool"/> <link name="camera"/>
  <joint name="camera_mount" type="fixed">
    <parent link="base"/> <child link="camera"/> <origin xyz="0.1 0 0.2" rpy="0 0 0"/>
  </joint>
  <joint name="yaw" type="continuous">
    <parent link="base"/> <child link="shoulder"/> <origin xyz="0 0 0.3" rpy="0 0 0"/>
    <axis xyz="0 0 1"/>
  </joint>
  <joint name="shoulder_pitch" type="revolute">
    <parent link="shoulder"/> <child link="upper_arm"/> <origin xyz="0 0 0" rpy="0 0 0"/>
    <axis xyz="0 1 0"/> <limit lower="-1.8" upper="1.8" effort="10" velocity="2"/>
  </joint>
  <joint name="elbow" type="revolute">
    <parent link="upper_arm"/> <child link="forearm"/> <origin xyz="0 0 0.4" rpy="0 0 0"/>
    <axis xyz="0 1 0"/> <limit lower="0" upper="2.6" effort="10" velocity="2"/>
  </joint>
  <joint name="wrist" type="revolute">
    <parent link="forearm"/> <child link="hand"/> <origin xyz="0 0 0.35" rpy="0 0 0"/>
    <axis xyz="0 1 0"/> <limit lower="-1.5" upper="1.5" effort="10" velocity="2"/>
  </joint>
  <joint name="tool_mount" type="fixed">
    <parent link="hand"/> <child link="tool"/> <origin xyz="0 0 0.1" rpy="0 0 0"/>
  </joint>
</robot>
"""

# The task config for this arm, as a user writes it (docs/guide/urdf.md): only keys of
# configs/task/viapoint.yaml, no code. Start and target 50 cm apart at shoulder height, 55 cm
# in front of the base; two alternatives 20 cm apart (below / above) at 0.5 s, one viapoint
# at 1.3 s.
CONFIG = """
name: viapoint
trials: 250
n0: 20
env:
  _target_: dipole_torch.tasks.viapoint.ViapointTask
  device: cpu
  urdf: {urdf}
  end_effector: tool
  initial_joints: [0.0, 0.6, 1.2, 0.3]
  start: [0.5, -0.25, 0.35]
  target: [0.5, 0.25, 0.35]
  pass_times: [0.5, 1.3]
  viapoints:
    - [[0.5, -0.1, 0.25], [0.5, -0.1, 0.45]]
    - [[0.5, 0.15, 0.35]]
  dt: 0.04
  duration: 2.2
  time_std: null
"""


@pytest.fixture(scope="module")
def urdf_path(tmp_path_factory):
    path = tmp_path_factory.mktemp("arm") / "four_joint_arm.urdf"
    path.write_text(URDF)
    return path


def numpy_forward_kinematics(q: np.ndarray) -> np.ndarray:
    """Tool position of the arm above, written out by hand (yaw about z, pitches about y)."""
    yaw, pitch, elbow, wrist = q
    reach = (
        0.4 * math.sin(pitch)
        + 0.35 * math.sin(pitch + elbow)
        + 0.1 * math.sin(pitch + elbow + wrist)
    )
    height = (
        0.3
        + 0.4 * math.cos(pitch)
        + 0.35 * math.cos(pitch + elbow)
        + 0.1 * math.cos(pitch + elbow + wrist)
    )
    return np.array([reach * math.cos(yaw), reach * math.sin(yaw), height])


def make_task(urdf_path, **overrides) -> ViapointTask:
    """The task of :data:`CONFIG`, instantiated by Hydra as ``train.py`` does."""
    omegaconf = pytest.importorskip("omegaconf")
    compat = pytest.importorskip("dipole_torch.training.hydra_compat")
    config = omegaconf.OmegaConf.create(CONFIG.format(urdf=urdf_path))
    return compat.instantiate(config.env, **overrides)


def task_arguments(urdf_path, **overrides) -> dict:
    """:data:`CONFIG`'s constructor arguments (to see the task's own exceptions, which Hydra
    would wrap)."""
    omegaconf = pytest.importorskip("omegaconf")
    config = omegaconf.OmegaConf.create(CONFIG.format(urdf=urdf_path))
    arguments = omegaconf.OmegaConf.to_container(config.env)
    del arguments["_target_"]
    return arguments | overrides


def test_kinematics_match_hand_written_forward_kinematics(urdf_path):
    arm = ArmKinematics(urdf_path, "tool", dtype=F64)
    assert arm.dof == 4 and arm.joint_names == ["yaw", "shoulder_pitch", "elbow", "wrist"]
    assert arm.robot_name == "four_joint_arm"
    # Limits from the URDF; the continuous joint is unlimited.
    assert math.isinf(arm.joint_lower[0]) and math.isinf(arm.joint_upper[0])
    torch.testing.assert_close(arm.joint_upper[1:], torch.tensor([1.8, 2.6, 1.5], dtype=F64))
    rng = np.random.default_rng(0)
    q = rng.uniform([-3.0, -1.8, 0.0, -1.5], [3.0, 1.8, 2.6, 1.5], size=(32, 4))
    positions, jacobian = arm.position_and_jacobian(torch.from_numpy(q))
    expected = np.stack([numpy_forward_kinematics(row) for row in q])
    np.testing.assert_allclose(positions.numpy(), expected, atol=1e-6, rtol=0)
    # Position Jacobian against central differences of the hand-written FK.
    eps = 1e-6
    for b in range(3):
        columns = [
            (numpy_forward_kinematics(q[b] + eps * e) - numpy_forward_kinematics(q[b] - eps * e))
            / (2 * eps)
            for e in np.eye(4)
        ]
        np.testing.assert_allclose(jacobian[b].numpy(), np.stack(columns, -1), atol=1e-6)
    assert arm.jacobian(torch.from_numpy(q)).shape == (32, 6, 4)


def test_limits_from_config_override_the_urdf(urdf_path):
    arm = ArmKinematics(urdf_path, "tool", joint_lower=[-1, -1, 0, -1], joint_upper=[1, 1, 2, 1])
    assert arm.joint_lower.tolist() == [-1, -1, 0, -1]
    clamped = arm.clamp_to_limits(torch.full((1, 4), 5.0))
    assert clamped.tolist() == [[1.0, 1.0, 2.0, 1.0]]
    with pytest.raises(ValueError, match="joint_lower must give 4 values"):
        ArmKinematics(urdf_path, "tool", joint_lower=[0.0] * 7)


def test_clear_errors_for_links_and_files(urdf_path, tmp_path):
    with pytest.raises(
        ValueError, match="'gripper' is not a link.*links are base, camera, shoulder, upper_arm"
    ):
        ArmKinematics(urdf_path, "gripper")
    with pytest.raises(ValueError, match="not below base_link 'camera'"):
        ArmKinematics(urdf_path, "tool", base_link="camera")
    with pytest.raises(FileNotFoundError, match="no_such_arm.urdf"):
        ArmKinematics(tmp_path / "no_such_arm.urdf", "tool")
    floating = tmp_path / "floating.urdf"
    floating.write_text(URDF.replace('"continuous"', '"floating"'))
    with pytest.raises(ValueError, match="unsupported joint type"):
        ArmKinematics(floating, "tool")
    with pytest.raises(ValueError, match="initial_joints must give 4 finite values"):
        ViapointTask(**task_arguments(urdf_path, initial_joints=[0.0] * 7))
    with pytest.raises(ValueError, match="fast path of the bundled WAM"):
        ViapointTask(**task_arguments(urdf_path, kinematics="wam_dh"))
    with pytest.raises(ValueError, match="workspace"):  # 1.2 m out: beyond the 0.85 m reach
        ViapointTask(**task_arguments(urdf_path, start=[1.2, 0.0, 0.3]))


@pytest.mark.parametrize("origin", ['xyz="0 0 nan"', 'xyz="0 0 0.4" rpy="0 inf 0"'])
def test_a_non_finite_origin_stops_the_task_not_its_rewards(tmp_path, origin):
    """A NaN or inf origin made every position NaN: the task's reach check passed (NaN
    comparisons are False) and ``evaluate`` returned NaN rewards. Now the task is not built,
    and the error names the file and the joint."""
    path = tmp_path / "nan_arm.urdf"
    path.write_text(URDF.replace('xyz="0 0 0.4" rpy="0 0 0"', origin))
    with pytest.raises(ValueError, match=r"urdf .*nan_arm\.urdf: joint 'elbow' has <origin "):
        ViapointTask(**task_arguments(path))


def test_start_posture_from_config(urdf_path):
    task = make_task(urdf_path, start=None, dtype="float64")
    q = [0.0, 0.6, 1.2, 0.3]
    torch.testing.assert_close(task.q_start, torch.tensor(q, dtype=F64))
    torch.testing.assert_close(task.start.numpy(), numpy_forward_kinematics(np.array(q)))
    torch.testing.assert_close(task.theta0[:3], task.start)
    # Without initial_joints: the middle of the limits (0 for the unlimited yaw) as the guess.
    middle = ViapointTask(**task_arguments(urdf_path, initial_joints=None))
    assert middle.kinematics.middle_posture().tolist() == pytest.approx([0.0, 0.0, 1.3, 0.0])
    reached = middle.kinematics.forward_kinematics(middle.q_start[None])[0]
    assert float((reached - middle.start).norm()) < 1e-4
    with pytest.raises(ValueError, match="outside the joint limits"):
        ViapointTask(**task_arguments(urdf_path, start=None, initial_joints=[0, 0.6, -1, 0.3]))


def test_reward_gradient_on_the_second_arm(urdf_path):
    task = make_task(urdf_path, dtype="float64")
    generator = torch.Generator().manual_seed(0)
    theta = task.theta0 + 0.05 * torch.randn(2, 6, generator=generator, dtype=F64)
    theta.requires_grad_(True)
    (gradient,) = torch.autograd.grad(task.evaluate(theta).sum(), theta)
    direction = torch.randn(2, 6, generator=generator, dtype=F64)
    eps = 1e-6
    with torch.no_grad():
        numeric = task.evaluate(theta + eps * direction) - task.evaluate(theta - eps * direction)
    torch.testing.assert_close(
        (gradient * direction).sum(-1), numeric / (2 * eps), rtol=1e-5, atol=1e-7
    )


def test_dipole_learns_a_route_on_the_second_arm(urdf_path):
    """DIPOLE (default variant) on the config above, 250 trials, seed 0: at least one final
    policy mean takes a route with reward >= 0.9 and every final policy's path ends within
    1 cm of the target. (Measured on seeds 0-3: best route returns 0.936, 0.937, 0.949 and
    0.984; paths end 0.4-0.7 cm from the target; about 10 s a seed on one shared core.)"""
    from dipole_torch import Dipole

    torch.set_num_threads(1)
    task = make_task(urdf_path)
    assert task.kinematics.robot_name == "four_joint_arm" and task.parameter_dim == 6
    opt = Dipole(
        task.theta0.double(),
        task.sigma_start.double(),
        n0=20,
        reward_range=task.reward_range,
        generator=torch.Generator().manual_seed(0),
    )
    while opt.trials < 250:
        theta = opt.ask()
        opt.tell(theta, task.evaluate(theta.float()))
    means = opt.policy_means.float()
    with torch.no_grad():
        path = task.trajectory(means)
    rewards = task.reward(path)
    routes = {
        tuple(r)
        for r, v in zip(task.route(means).tolist(), rewards.tolist(), strict=True)
        if v >= 0.9
    }
    assert len(routes) >= 1, (rewards, task.describe_policies(means))
    assert float(task.end_point_error(path).max()) < 0.01
    lines = task.describe_policies(means)
    assert all("from the target" in line for line in lines)
    figure = task.plot_policies(means)
    assert "four_joint_arm" in figure.axes[0].get_title()


def test_readme_example_config_composes(urdf_path, tmp_path):
    """The docs' "Your own arm" config file, with this test's URDF and end-effector link,
    composes with Hydra as ``task=viapoint_myarm`` and builds the task on that arm."""
    import shutil
    from pathlib import Path

    hydra = pytest.importorskip("hydra")
    compat = pytest.importorskip("dipole_torch.training.hydra_compat")
    import dipole_torch.configs  # noqa: F401 (registers the schemas the configs extend)

    root = Path(__file__).resolve().parents[1]
    readme = (root / "docs" / "guide" / "urdf.md").read_text()
    marker = "# file: my_configs/task/viapoint_myarm.yaml"
    assert marker in readme
    example = readme.split(marker, 1)[1].split("\n", 1)[1].split("```", 1)[0]
    example = example.replace("my_arm.urdf", str(urdf_path))
    example = example.replace("tool_link", "tool")
    configs = tmp_path / "configs"
    shutil.copytree(root / "configs", configs)
    (configs / "task" / "viapoint_myarm.yaml").write_text(example)
    with hydra.initialize_config_dir(config_dir=str(configs), **compat.VERSION_BASE):
        config = hydra.compose(config_name="config", overrides=["task=viapoint_myarm"])
    assert config.task.name == "viapoint_myarm" and config.task.trials == 300
    task = compat.instantiate(config.task.env)
    assert task.kinematics.robot_name == "four_joint_arm" and task.parameter_dim == 6
    assert task.num_alternatives == [2, 1]
    assert (
        float((task.kinematics.forward_kinematics(task.q_start[None])[0] - task.start).norm())
        < 1e-4
    )


# Every kind of chain element the numpy engine folds: a revolute joint with a tilted,
# non-unit axis and rpy origin, a prismatic joint, a fixed frame between movable joints, a
# continuous joint, a branch off the chain, and a tool frame with its own rotation.
MIXED_URDF = """<?xml version="1.0"?>
<robot name="mixed">
  <link name="base"/> <link name="a"/> <link name="b"/> <link name="c"/> <link name="d"/>
  <link name="e"/> <link name="tip"/> <link name="side"/>
  <joint name="j0" type="revolute">
    <parent link="base"/> <child link="a"/> <origin xyz="0.1 -0.2 0.3" rpy="0.3 -0.2 0.5"/>
    <axis xyz="0 0.6 0.8"/> <limit lower="-3" upper="3" effort="1" velocity="1"/>
  </joint>
  <joint name="j1" type="prismatic">
    <parent link="a"/> <child link="b"/> <origin xyz="0 0.1 0.2" rpy="-0.4 0.1 0"/>
    <axis xyz="1 1 0"/> <limit lower="-0.5" upper="0.5" effort="1" velocity="1"/>
  </joint>
  <joint name="f" type="fixed">
    <parent link="b"/> <child link="c"/> <origin xyz="0.05 0 0.1" rpy="0 0.7 0"/>
  </joint>
  <joint name="side_mount" type="fixed">
    <parent link="b"/> <child link="side"/> <origin xyz="1 0 0" rpy="0 0 0"/>
  </joint>
  <joint name="j2" type="continuous">
    <parent link="c"/> <child link="d"/> <origin xyz="0 0 0.25" rpy="0 0 0.2"/>
    <axis xyz="0 0 2"/>
  </joint>
  <joint name="j3" type="revolute">
    <parent link="d"/> <child link="e"/> <origin xyz="0.2 0 0" rpy="1.0 0 0"/>
    <axis xyz="0 1 0"/> <limit lower="-2" upper="2" effort="1" velocity="1"/>
  </joint>
  <joint name="tool" type="fixed">
    <parent link="e"/> <child link="tip"/> <origin xyz="0 0.05 0.15" rpy="0.1 0.2 0.3"/>
  </joint>
</robot>
"""


@pytest.mark.parametrize("base_link", [None, "a"])
def test_numpy_chain_matches_pytorch_kinematics(tmp_path, base_link):
    """The numpy engine's chain against pytorch-kinematics' forward pass and Jacobian, in
    float64. They differ only by the float32 rounding of the URDF's axes and origins inside
    pytorch-kinematics (measured: 5e-8); a wrong fold, axis or joint type is off by > 1e-2."""
    path = tmp_path / "mixed.urdf"
    path.write_text(MIXED_URDF)
    arm = ArmKinematics(path, "tip", base_link=base_link, dtype=F64)
    chain = NumpyChain(arm.chain, arm.base_link)
    assert chain.dof == arm.dof == (4 if base_link is None else 3)
    expected_revolute = [True, False, True, True][4 - chain.dof :]
    assert chain.revolute.tolist() == expected_revolute
    q = np.random.default_rng(1).uniform(-1.0, 1.0, size=(64, arm.dof))
    positions, jacobian = arm.position_and_jacobian(torch.from_numpy(q))
    numpy_positions, numpy_jacobian = chain.position_and_jacobian(q)
    assert numpy_positions.shape == (64, 3) and numpy_jacobian.shape == (64, 3, arm.dof)
    np.testing.assert_allclose(numpy_positions, positions.numpy(), atol=1e-6, rtol=0)
    np.testing.assert_allclose(numpy_jacobian, jacobian.numpy(), atol=1e-6, rtol=0)
    np.testing.assert_allclose(chain.forward_kinematics(q), numpy_positions, atol=0, rtol=0)


def test_numpy_engine_tracks_like_the_torch_engine_on_another_arm(urdf_path):
    """The four-joint arm's paths agree between the engines, also where the DLS steps run
    into joint limits (3 of these 12 policies do; measured: within 4e-13 m)."""
    task = ViapointTask(**task_arguments(urdf_path, dtype="float64", engine="numpy"))
    torch_task = ViapointTask(**task_arguments(urdf_path, dtype="float64", engine="torch"))
    generator = torch.Generator().manual_seed(4)
    theta = task.theta0 + 0.3 * torch.randn(12, task.parameter_dim, generator=generator, dtype=F64)
    joints, _ = track_path(
        torch_task.kinematics, torch_task.q_start, task.desired_trajectory(theta), task.ik_damping
    )
    kinematics = torch_task.kinematics
    at_limit = (joints == kinematics.joint_lower) | (joints == kinematics.joint_upper)
    assert int(at_limit.any(-1).any(-1).sum()) >= 2
    torch.testing.assert_close(
        task.trajectory(theta), torch_task.trajectory(theta), atol=1e-9, rtol=0
    )


def test_reach_bounds_every_posture_and_is_the_full_stretch(tmp_path, urdf_path):
    """NumpyChain.reach: no posture within the limits puts the end effector outside the
    ball (the mixed chain's prismatic travel included), and on the four-joint arm, whose
    links can line up, the radius is their summed lengths (0.4 + 0.35 + 0.1 m) around the
    shoulder (0.3 m above the base), reached when the arm is straight."""
    path = tmp_path / "mixed.urdf"
    path.write_text(MIXED_URDF)
    arm = ArmKinematics(path, "tip", dtype=F64)
    lower, upper = arm.joint_lower.numpy(), arm.joint_upper.numpy()
    chain = NumpyChain(arm.chain, arm.base_link)
    centre, radius = chain.reach(lower, upper)
    q = np.random.default_rng(2).uniform(np.maximum(lower, -4), np.minimum(upper, 4), (512, 4))
    distances = np.linalg.norm(chain.forward_kinematics(q) - centre, axis=-1)
    assert distances.max() <= radius and distances.max() > 0.5 * radius
    four = ArmKinematics(urdf_path, "tool", dtype=F64)
    chain = NumpyChain(four.chain, four.base_link)
    centre, radius = chain.reach(four.joint_lower.numpy(), four.joint_upper.numpy())
    np.testing.assert_allclose(centre, [0.0, 0.0, 0.3], atol=1e-7)
    assert radius == pytest.approx(0.85, abs=1e-7)
    straight = chain.forward_kinematics(np.zeros((1, 4)))[0]
    assert np.linalg.norm(straight - centre) == pytest.approx(radius, abs=1e-7)


def test_numpy_inverse_kinematics_reaches_reachable_points(urdf_path):
    """From one guess, to the end-effector positions of postures within the limits: within
    1e-6 m (the joint values it finds stay within the limits); to a point beyond the reach,
    it ends at least that far away."""
    arm = ArmKinematics(urdf_path, "tool", dtype=F64)
    lower, upper = arm.joint_lower.numpy(), arm.joint_upper.numpy()
    chain = NumpyChain(arm.chain, arm.base_link)
    rng = np.random.default_rng(3)
    postures = rng.uniform([-3.0, -1.0, 0.3, -1.0], [3.0, 1.0, 2.0, 1.0], size=(8, 4))
    points = np.concatenate([chain.forward_kinematics(postures), [[1.5, 0.0, 0.3]]])
    q, distances = chain.inverse_kinematics(points, np.array([0.0, 0.6, 1.2, 0.3]), lower, upper)
    assert distances[:-1].max() < 1e-6 and distances[-1] >= 1.5 - 0.85 - 1e-9
    assert bool(((q >= lower) & (q <= upper)).all())
    np.testing.assert_allclose(chain.forward_kinematics(q)[:-1], points[:-1], atol=1e-6)


def test_position_ik_keeps_to_the_joint_limits_and_to_its_tolerance():
    from dipole_torch.models.wam import WamKinematics

    wam = WamKinematics(dtype=F64)
    guess = torch.tensor([0.0, 0.6, 0.0, 1.6, 0.0, 0.0, 0.0], dtype=F64)
    # A point the arm reaches with its base joint at 0.8 rad, beyond a ±0.05 rad limit.
    beyond = guess.clone()
    beyond[0] = 0.8
    target = wam.forward_kinematics(beyond[None])[0]
    lower, upper = wam.joint_lower.tolist(), wam.joint_upper.tolist()
    lower[0], upper[0] = -0.05, 0.05
    narrow = WamKinematics(joint_lower=lower, joint_upper=upper, dtype=F64)
    with pytest.raises(ValueError, match="inverse kinematics did not reach"):
        solve_position_ik(narrow, target, guess)
    # One iteration towards a point 1 mm away leaves 2.4e-6 m: within 5e-6, not 1.5e-6.
    near = wam.forward_kinematics(guess[None])[0] + torch.tensor([1e-3, 0.0, 0.0], dtype=F64)
    with pytest.raises(ValueError, match=r"residual 2\.36e-06 m"):
        solve_position_ik(wam, near, guess, iterations=1, tolerance=1.5e-6)
    q = solve_position_ik(wam, near, guess, iterations=1, tolerance=5e-6)
    assert float((wam.forward_kinematics(q[None])[0] - near).norm()) < 5e-6


def test_reach_counts_a_prismatic_joints_longest_travel_either_way(tmp_path):
    path = tmp_path / "mixed.urdf"
    path.write_text(MIXED_URDF)
    arm = ArmKinematics(path, "tip", dtype=F64)
    chain = NumpyChain(arm.chain, arm.base_link)
    lower, upper = arm.joint_lower.numpy().copy(), arm.joint_upper.numpy().copy()
    assert (lower[1], upper[1]) == (-0.5, 0.5)  # j1, the prismatic joint
    _, radius = chain.reach(lower, upper)
    upper[1] = 0.2  # 0.5 m of travel on the negative side only
    assert chain.reach(lower, upper)[1] == pytest.approx(radius, abs=1e-12)
    lower[1], upper[1] = -0.1, 0.2
    assert chain.reach(lower, upper)[1] == pytest.approx(radius - 0.3, abs=1e-12)


def test_a_numpy_chain_from_a_link_not_in_the_chain_is_refused(urdf_path):
    arm = ArmKinematics(urdf_path, "tool", dtype=F64)
    with pytest.raises(ValueError, match="base_link 'nowhere' is not a frame of the chain"):
        NumpyChain(arm.chain, "nowhere")


def test_editing_the_centre_reach_returns_leaves_the_chain_be(urdf_path):
    arm = ArmKinematics(urdf_path, "tool", dtype=F64)
    chain = NumpyChain(arm.chain, arm.base_link)
    limits = arm.joint_lower.numpy(), arm.joint_upper.numpy()
    centre, _ = chain.reach(*limits)
    centre += 1.0
    np.testing.assert_allclose(chain.reach(*limits)[0], [0.0, 0.0, 0.3], atol=1e-7)


def test_numpy_inverse_kinematics_starts_from_the_guess_within_the_limits(urdf_path):
    arm = ArmKinematics(urdf_path, "tool", dtype=F64)
    lower, upper = arm.joint_lower.numpy(), arm.joint_upper.numpy()
    chain = NumpyChain(arm.chain, arm.base_link)
    points = chain.forward_kinematics(np.array([[0.5, 0.3, 1.0, 0.2]]))
    beyond = upper + 1.0  # every limited joint 1 past its upper limit
    beyond[~np.isfinite(beyond)] = 0.0  # (the unlimited yaw at 0)
    clipped = np.clip(beyond, lower, upper)
    for iterations in (0, 1, 5):
        from_beyond = chain.inverse_kinematics(points, beyond, lower, upper, iterations=iterations)
        from_clipped = chain.inverse_kinematics(
            points, clipped, lower, upper, iterations=iterations
        )
        np.testing.assert_array_equal(from_beyond[0], from_clipped[0])

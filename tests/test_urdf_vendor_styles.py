"""Arms from URDF files written as vendors write them (tests/urdf/: KUKA iiwa, Franka Panda,
Kinova Gen3 and UFactory xArm6 styles): each loads without noise, the right joints are free
with the right limits, and the viapoint task rolls out on it. Then the loader's answers to
what such files hold: continuous joints with limit tags, transmissions pytorch-kinematics
cannot parse, materials, gripper branches with mimic joints, broken trees."""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np
import pytest
import torch
from dipole_torch.models.kinematics import ArmKinematics
from dipole_torch.models.numpy_kinematics import NumpyChain
from dipole_torch.tasks.viapoint import ViapointTask

F64 = torch.float64
URDF_DIR = Path(__file__).resolve().parent / "urdf"
INF = math.inf

# file, end effector, free joints, their (lower, upper) limits, a start posture (rad)
ARMS = {
    "iiwa": (
        "iiwa_style.urdf",
        "lbr_iiwa_link_ee",
        [f"lbr_iiwa_joint_{i}" for i in range(1, 8)],
        [(-2.96705972839, 2.96705972839), (-2.09439510239, 2.09439510239)] * 3
        + [(-3.05432619099, 3.05432619099)],
        [0.0, 0.5, 0.0, -1.2, 0.0, 0.6, 0.0],
    ),
    "panda": (
        "panda_style.urdf",
        "panda_hand_tcp",  # past the hand, whose finger joints branch off the chain
        [f"panda_joint{i}" for i in range(1, 8)],
        [(-2.8973, 2.8973), (-1.7628, 1.7628), (-2.8973, 2.8973), (-3.0718, -0.0698)]
        + [(-2.8973, 2.8973), (-0.0175, 3.7525), (-2.8973, 2.8973)],
        [0.0, -0.3, 0.0, -2.0, 0.0, 1.8, 0.785],
    ),
    "gen3": (
        "gen3_style.urdf",
        "tool_frame",
        [f"joint_{i}" for i in range(1, 8)],
        [(-INF, INF), (-2.41, 2.41), (-INF, INF), (-2.66, 2.66)]
        + [(-INF, INF), (-2.23, 2.23), (-INF, INF)],
        [0.0, 0.4, 0.0, 1.6, 0.0, 1.0, 0.0],
    ),
    "xarm6": (
        "xarm6_style.urdf",
        "link_eef",
        [f"joint{i}" for i in range(1, 7)],
        [(-2 * math.pi, 2 * math.pi), (-2.059, 2.0944), (-3.927, 0.19198)]
        + [(-2 * math.pi, 2 * math.pi), (-1.69297, 3.14159265359), (-2 * math.pi, 2 * math.pi)],
        [0.0, -0.5, -0.8, 0.0, 1.3, 0.0],
    ),
}


def load_quietly(capsys, *args, **kwargs) -> ArmKinematics:
    """``ArmKinematics(*args, **kwargs)``, failing on any warning or stderr output."""
    with warnings.catch_warnings():
        warnings.simplefilter("error")
        arm = ArmKinematics(*args, **kwargs)
    assert capsys.readouterr().err == ""
    return arm


def variant(tmp_path, file: str, old: str, new: str) -> Path:
    """A copy of ``tests/urdf/<file>`` with ``old`` (which it must hold) replaced by ``new``."""
    text = (URDF_DIR / file).read_text()
    assert old in text
    path = tmp_path / file
    path.write_text(text.replace(old, new))
    return path


@pytest.mark.parametrize("name", ARMS)
def test_vendor_style_arm_loads_with_its_free_joints_and_limits(name, capsys):
    file, end_effector, joints, limits, _ = ARMS[name]
    arm = load_quietly(capsys, URDF_DIR / file, end_effector, dtype=F64)
    assert arm.joint_names == joints
    expected = torch.tensor(limits, dtype=F64).T
    # float32 inside pytorch-kinematics does not touch the limits: read from the file here.
    assert arm.joint_lower.tolist() == expected[0].tolist()
    assert arm.joint_upper.tolist() == expected[1].tolist()
    low, high = arm.chain.get_joint_limits()  # the chain carries the same limits
    assert (low, high) == (expected[0].tolist(), expected[1].tolist())
    # The numpy engine's chain folds the same fixed frames (flanges, rotated hands, tools).
    q = np.random.default_rng(0).uniform(-1.0, 1.0, size=(16, arm.dof))
    positions, jacobians = arm.position_and_jacobian(torch.from_numpy(q))
    numpy_positions, numpy_jacobians = NumpyChain(arm.chain, arm.base_link).position_and_jacobian(q)
    np.testing.assert_allclose(numpy_positions, positions.numpy(), atol=1e-6, rtol=0)
    np.testing.assert_allclose(numpy_jacobians, jacobians.numpy(), atol=1e-6, rtol=0)


@pytest.mark.parametrize("name", ARMS)
def test_short_viapoint_rollout_on_a_vendor_style_arm(name, capsys):
    """Start at the posture's end effector; target and viapoint where the end effector is at
    postures a few tenths of a radian away (reachable by construction). Both engines give
    the same paths, which end at the target."""
    file, end_effector, _, _, posture = ARMS[name]
    arm = load_quietly(capsys, URDF_DIR / file, end_effector, dtype=F64)
    q0 = torch.tensor(posture, dtype=F64)
    shift = torch.zeros_like(q0)
    shift[0], shift[1] = 0.4, 0.15
    target, via = arm.forward_kinematics(torch.stack([q0 + shift, q0 + 0.5 * shift.flip(0)]))
    arguments = dict(
        urdf=str(URDF_DIR / file),
        end_effector=end_effector,
        initial_joints=posture,
        start=None,
        target=target.tolist(),
        pass_times=[0.5],
        viapoints=[[via.tolist()]],
        duration=1.2,
        dt=0.04,
        time_std=None,
        dtype="float64",
    )
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # no reach warning: every point is reachable
        task = ViapointTask(**arguments)
    assert capsys.readouterr().err == ""
    theta = task.theta0 + 0.03 * torch.randn(3, 3, generator=torch.Generator().manual_seed(0))
    path = task.trajectory(theta)
    torch_path = ViapointTask(**arguments, engine="torch").trajectory(theta)
    torch.testing.assert_close(path, torch_path, atol=1e-8, rtol=0)
    rewards = task.evaluate(theta)
    assert rewards.shape == (3,) and bool(((rewards > 0) & (rewards <= 1)).all())
    assert float(task.end_point_error(path).max()) < 0.01


def test_continuous_joints_are_unlimited_whatever_their_limit_tag(capsys):
    """Gen3 style: ``<limit effort=... velocity=.../>`` on a continuous joint gives no
    position limits (pytorch-kinematics reads it as [0, 0], which locks the joint)."""
    arm = load_quietly(capsys, URDF_DIR / "gen3_style.urdf", "tool_frame")
    continuous = [0, 2, 4, 6]
    assert arm.joint_lower[continuous].tolist() == [-INF] * 4
    assert arm.joint_upper[continuous].tolist() == [INF] * 4
    moved = arm.clamp_to_limits(torch.full((1, 7), 1.0))[0]
    assert moved[continuous].tolist() == [1.0] * 4  # free to move


def test_continuous_joint_with_lower_and_upper_stays_unlimited(tmp_path):
    """URDF gives continuous joints no position limits: lower/upper in the tag are ignored."""
    path = variant(
        tmp_path,
        "gen3_style.urdf",
        '<limit effort="39" velocity="1.3963"/>',
        '<limit lower="-1" upper="1" effort="39" velocity="1.3963"/>',
    )
    arm = ArmKinematics(path, "tool_frame")
    assert arm.joint_lower[[0, 2]].tolist() == [-INF, -INF]
    assert arm.joint_upper[[0, 2]].tolist() == [INF, INF]


def test_revolute_limit_tag_without_lower_and_upper(tmp_path):
    """Neither given: an error naming the joint (URDF's defaults would lock it at [0, 0]),
    unless both overrides are given; one missing is 0, URDF's default."""
    neither = variant(
        tmp_path,
        "gen3_style.urdf",
        '<limit lower="-2.41" upper="2.41" effort="39" velocity="1.3963"/>',
        '<limit effort="39" velocity="1.3963"/>',
    )
    with pytest.raises(ValueError, match=r"gen3_style.urdf: joint 'joint_2' is revolute but its"):
        ArmKinematics(neither, "tool_frame")
    with pytest.raises(ValueError, match="would lock it at"):
        ArmKinematics(neither, "tool_frame", joint_lower=[-1.0] * 7)
    overridden = ArmKinematics(neither, "tool_frame", joint_lower=[-1] * 7, joint_upper=[1] * 7)
    assert overridden.joint_upper.tolist() == [1.0] * 7
    one_sided = variant(
        tmp_path,
        "gen3_style.urdf",
        '<limit lower="-2.41" upper="2.41" effort="39" velocity="1.3963"/>',
        '<limit upper="2.41" effort="39" velocity="1.3963"/>',
    )
    arm = ArmKinematics(one_sided, "tool_frame")
    assert (arm.joint_lower[1].item(), arm.joint_upper[1].item()) == (0.0, pytest.approx(2.41))


def test_transmissions_and_plugins_kinematics_does_not_read_do_not_stop_loading(capsys):
    """xArm6 style: a transmission whose mechanicalReduction is not a number (pytorch-
    kinematics' parser raises on it), a <mujoco> block, ros2_control, materials."""
    arm = load_quietly(capsys, URDF_DIR / "xarm6_style.urdf", "link_eef")
    assert arm.robot_name == "UF_ROBOT" and arm.dof == 6


def test_parse_errors_that_remain_name_the_file(tmp_path):
    path = variant(tmp_path, "xarm6_style.urdf", 'xyz="0.0535 -0.2845 0"', 'xyz="0.0535 a 0"')
    with pytest.raises(ValueError, match=r"urdf .*xarm6_style\.urdf: .*joint3"):
        ArmKinematics(path, "link_eef")
    broken = tmp_path / "broken.urdf"
    broken.write_text((URDF_DIR / "xarm6_style.urdf").read_text()[:-20])
    with pytest.raises(ValueError, match=r"broken\.urdf is not valid XML"):
        ArmKinematics(broken, "link_eef")


def test_unknown_tags_in_a_joint_warn_naming_the_file(tmp_path, capsys):
    """What pytorch-kinematics still reports (here a misspelt tag in a joint) is a warning
    naming the file, not a line on stderr."""
    path = variant(
        tmp_path,
        "xarm6_style.urdf",
        '<dynamics damping="1.0" friction="1.0"/>\n  </joint>\n  <joint name="joint2"',
        '<limt lower="-1" upper="1"/>\n  </joint>\n  <joint name="joint2"',
    )
    with pytest.warns(UserWarning, match=r'xarm6_style\.urdf: Unknown tag "limt" in .*joint1'):
        ArmKinematics(path, "link_eef")
    assert "Unknown tag" not in capsys.readouterr().err


def test_materials_print_nothing(capsys):
    """Panda style: <material> inside links and collisions, which pytorch-kinematics
    reports as unknown tags, one stderr line each."""
    load_quietly(capsys, URDF_DIR / "panda_style.urdf", "panda_hand_tcp")


def test_gripper_branches_and_mimic_joints(capsys):
    """Panda style: a finger on the chain is a free prismatic joint with its limits; the
    finger whose joint mimics the other's cannot end a chain (it would move on its own)."""
    finger = load_quietly(capsys, URDF_DIR / "panda_style.urdf", "panda_leftfinger", dtype=F64)
    assert finger.joint_names[-1] == "panda_finger_joint1" and finger.dof == 8
    assert (finger.joint_lower[-1].item(), finger.joint_upper[-1].item()) == (0.0, 0.04)
    with pytest.raises(ValueError, match=r"joint 'panda_finger_joint2' .* mimics joint "):
        ArmKinematics(URDF_DIR / "panda_style.urdf", "panda_rightfinger")


def test_a_joint_naming_a_missing_link_is_named(tmp_path):
    """iiwa style, a link name mistyped in a joint: the error names the joint and the link
    (not the end effector, which exists but was cut off from the tree)."""
    path = variant(
        tmp_path,
        "iiwa_style.urdf",
        '<parent link="lbr_iiwa_link_6"/>',
        '<parent link="lbr_iiwa_link6"/>',
    )
    with pytest.raises(
        ValueError,
        match=r"iiwa_style\.urdf: joint 'lbr_iiwa_joint_7' names parent link 'lbr_iiwa_link6', "
        r"which is not a link of iiwa_style\.urdf \(did you mean 'lbr_iiwa_link_6'\?\)",
    ):
        ArmKinematics(path, "lbr_iiwa_link_7")
    path = variant(
        tmp_path, "iiwa_style.urdf", '<child link="lbr_iiwa_link_ee"/>', '<child link="tool0"/>'
    )
    with pytest.raises(ValueError, match=r"joint 'lbr_iiwa_joint_ee' names child link 'tool0'"):
        ArmKinematics(path, "lbr_iiwa_link_7")


def test_trees_that_are_not_one_tree_are_named(tmp_path):
    two_parents = variant(
        tmp_path,
        "iiwa_style.urdf",
        '<child link="lbr_iiwa_link_ee"/>',
        '<child link="lbr_iiwa_link_7"/>',
    )
    with pytest.raises(
        ValueError,
        match=r"link 'lbr_iiwa_link_7' is the child of two joints, 'lbr_iiwa_joint_7' and "
        r"'lbr_iiwa_joint_ee'",
    ):
        ArmKinematics(two_parents, "lbr_iiwa_link_7")
    two_roots = variant(
        tmp_path,
        "iiwa_style.urdf",
        '<link name="world"/>',
        '<link name="world"/><link name="table"/>',
    )
    with pytest.raises(ValueError, match=r"2 root links .*: world, table"):
        ArmKinematics(two_roots, "lbr_iiwa_link_7")


def test_joint_types_off_the_chain_that_pytorch_kinematics_lacks_are_fixed(tmp_path):
    """A floating object in the file (here a camera) does not stop loading the arm; on the
    chain it is an error naming the joint."""
    path = variant(
        tmp_path,
        "xarm6_style.urdf",
        '<link name="link_eef"/>',
        '<link name="link_eef"/> <link name="camera"/> <joint name="camera_joint" type="floating">'
        '<parent link="link_base"/> <child link="camera"/> </joint>',
    )
    arm = ArmKinematics(path, "link_eef")
    assert arm.dof == 6
    with pytest.raises(
        ValueError, match=r"unsupported joint type 'floating' of joint 'camera_joint'"
    ):
        ArmKinematics(path, "camera")


def test_a_movable_joint_without_axis_turns_about_x(tmp_path):
    """URDF's default axis is x (pytorch-kinematics alone would take z)."""
    path = tmp_path / "no_axis.urdf"
    path.write_text(
        '<robot name="no_axis"><link name="base"/><link name="arm"/><link name="tip"/>'
        '<joint name="hinge" type="revolute"><parent link="base"/><child link="arm"/>'
        '<limit lower="-2" upper="2" effort="1" velocity="1"/></joint>'
        '<joint name="tool" type="fixed"><parent link="arm"/><child link="tip"/>'
        '<origin xyz="0 0.5 0"/></joint></robot>'
    )
    arm = ArmKinematics(path, "tip", dtype=F64)
    tip = arm.forward_kinematics(torch.tensor([[math.pi / 2]], dtype=F64))[0]
    torch.testing.assert_close(tip, torch.tensor([0.0, 0.0, 0.5], dtype=F64), atol=1e-6, rtol=0)


def hinge_arm(tmp_path, tip_link: str) -> Path:
    """A hinge about z at the base, the tip 0.5 along the arm's x, the tip's ``<link>``
    element as given."""
    path = tmp_path / "hinge.urdf"
    path.write_text(
        f'<robot name="hinge"><link name="base"/><link name="arm"/>{tip_link}'
        '<joint name="hinge" type="revolute"><parent link="base"/><child link="arm"/>'
        '<axis xyz="0 0 1"/><limit lower="-2" upper="2" effort="1" velocity="1"/></joint>'
        '<joint name="tool" type="fixed"><parent link="arm"/><child link="tip"/>'
        '<origin xyz="0.5 0 0"/></joint></robot>'
    )
    return path


def test_a_links_origin_moves_its_frame_as_pytorch_kinematics_reads_it(tmp_path):
    """The copy pytorch-kinematics loads keeps a link's ``<origin>`` (it applies it): the
    tip's origin 0.1 along x and 0.25 along z moves the tip there, in the arm's frame."""
    quarter = torch.tensor([[math.pi / 2]], dtype=F64)
    plain = ArmKinematics(hinge_arm(tmp_path, '<link name="tip"/>'), "tip", dtype=F64)
    torch.testing.assert_close(
        plain.forward_kinematics(quarter)[0], torch.tensor([0.0, 0.5, 0.0], dtype=F64)
    )
    moved = hinge_arm(tmp_path, '<link name="tip"><origin xyz="0.1 0 0.25"/></link>')
    tip = ArmKinematics(moved, "tip", dtype=F64).forward_kinematics(quarter)[0]
    torch.testing.assert_close(tip, torch.tensor([0.0, 0.6, 0.25], dtype=F64))


def test_equal_limits_pin_a_joint():
    """joint_lower = joint_upper is a joint held at one value, not crossed limits."""
    arm = ArmKinematics(
        URDF_DIR / "xarm6_style.urdf", "link_eef", joint_lower=[0.3] * 6, joint_upper=[0.3] * 6
    )
    assert arm.clamp_to_limits(torch.full((1, 6), 1.0)).tolist() == [[pytest.approx(0.3)] * 6]


def test_an_unexpanded_xacro_file_says_so(tmp_path):
    path = tmp_path / "arm.urdf.xacro"
    path.write_text(
        '<robot name="arm" xmlns:xacro="http://www.ros.org/wiki/xacro">'
        '<xacro:property name="length" value="0.3"/><link name="base"/></robot>'
    )
    with pytest.raises(
        ValueError, match=r"is a xacro file .* `xacro arm\.urdf\.xacro > arm\.urdf`"
    ):
        ArmKinematics(path, "base")


@pytest.mark.parametrize("axis", ["0 0 0", "1 0"])
def test_a_movable_joint_needs_a_non_zero_axis(tmp_path, axis):
    path = variant(tmp_path, "xarm6_style.urdf", '<axis xyz="0 0 1"/>', f'<axis xyz="{axis}"/>')
    with pytest.raises(ValueError, match=r"joint 'joint1' has <axis xyz='.*'>; a movable joint"):
        ArmKinematics(path, "link_eef")


@pytest.mark.parametrize(
    ("old", "new", "named"),
    [
        (
            '<axis xyz="0 0 1"/>',
            '<axis xyz="0 nan 1"/>',
            r"joint 'joint1' has <axis xyz='0 nan 1'>",
        ),
        (
            '<axis xyz="0 0 1"/>',
            '<axis xyz="0 inf 1"/>',
            r"joint 'joint1' has <axis xyz='0 inf 1'>",
        ),
        (
            'xyz="0.0535 -0.2845 0"',
            'xyz="0.0535 nan 0"',
            r"joint 'joint3' has <origin xyz='0.0535 nan 0'>; an origin's xyz is three finite",
        ),
        (
            'xyz="0.0535 -0.2845 0" rpy="0 0 0"',
            'xyz="0.0535 -0.2845 0" rpy="0 inf 0"',
            r"joint 'joint3' has <origin rpy='0 inf 0'>; an origin's rpy is three finite",
        ),
        (
            '<link name="link_eef"/>',
            '<link name="link_eef"><origin xyz="0 0 -inf"/></link>',
            r"link 'link_eef' has <origin xyz='0 0 -inf'>",
        ),
    ],
    ids=["axis-nan", "axis-inf", "origin-xyz-nan", "origin-rpy-inf", "link-origin-inf"],
)
def test_non_finite_axes_and_origins_on_the_chain_are_named(tmp_path, old, new, named):
    """NaN or inf in an axis or an origin made every position NaN, which the task's reach
    check let through (comparisons with NaN are False) and ``evaluate`` returned; now the
    file does not load, naming the file and the joint or link."""
    path = variant(tmp_path, "xarm6_style.urdf", old, new)
    with pytest.raises(ValueError, match=r"urdf .*xarm6_style\.urdf: " + named):
        ArmKinematics(path, "link_eef")


def test_a_file_without_joints_has_no_movable_joint(tmp_path):
    """pytorch-kinematics fails on a file without joints (UnboundLocalError); the chain is
    rejected first, as a chain of fixed joints is."""
    path = tmp_path / "no_joints.urdf"
    path.write_text('<robot name="r"><link name="base"/></robot>')
    with pytest.raises(ValueError, match=r"no movable joint between 'base' and 'base' in no_j"):
        ArmKinematics(path, "base")
    fixed = variant(
        tmp_path,
        "xarm6_style.urdf",
        '<link name="link_eef"/>',
        '<link name="link_eef"/> <link name="camera"/> <joint name="camera_joint" type="fixed">'
        '<parent link="link_base"/> <child link="camera"/> </joint>',
    )
    with pytest.raises(ValueError, match=r"no movable joint between 'link_base' and 'camera'"):
        ArmKinematics(fixed, "camera")


@pytest.mark.parametrize(
    ("limit", "message"),
    [
        ('lower="nan" upper="2.0944"', r"<limit lower='nan'>, not a number"),
        ('lower="-2.059" upper="NaN"', r"<limit upper='NaN'>, not a number"),
        ('lower="inf" upper="inf"', r"<limit lower='inf'>, which leaves the joint no value"),
    ],
    ids=["lower-nan", "upper-nan", "lower-inf"],
)
def test_non_finite_joint_limits_are_named_not_crossed(tmp_path, limit, message):
    """NaN limits were reported as 'lower exceeds upper' (and lower = upper = +inf loaded)."""
    path = variant(tmp_path, "xarm6_style.urdf", 'lower="-2.059" upper="2.0944"', limit)
    with pytest.raises(
        ValueError, match=r"urdf .*xarm6_style\.urdf: joint 'joint2' has " + message
    ):
        ArmKinematics(path, "link_eef")


def test_nan_limit_overrides_are_named_not_crossed():
    """A NaN in joint_lower / joint_upper was reported as 'lower exceeds upper'."""
    nan = [0.0, math.nan, 0.0, 0.0, 0.0, 0.0]
    with pytest.raises(ValueError, match=r"not numbers \(NaN\) .* joint2 \[nan, 2.094\] of xarm6"):
        ArmKinematics(URDF_DIR / "xarm6_style.urdf", "link_eef", joint_lower=nan)

"""Barrett WAM model: both kinematics paths (pytorch-kinematics on the URDF, the default;
the analytic DH fast path) against an independent numpy DH implementation and each other."""

from __future__ import annotations

import numpy as np
import pytest
import torch
from dipole_torch.models.kinematics import ArmKinematics
from dipole_torch.models.wam import END_EFFECTOR_LINK, URDF_PATH, WamKinematics

# Standard DH table of the WAM 7-DOF (Barrett WAM Arm User's Manual): a, alpha, d per joint.
DH_A = np.array([0.0, 0.0, 0.045, -0.045, 0.0, 0.0, 0.0])
DH_ALPHA = np.array([-1, 1, -1, 1, -1, 1, 0]) * np.pi / 2
DH_D = np.array([0.0, 0.0, 0.55, 0.0, 0.3, 0.0, 0.06])
LOWER = np.array([-2.6, -2.0, -2.8, -0.9, -4.76, -1.6, -3.0])
UPPER = np.array([2.6, 2.0, 2.8, 3.1, 1.24, 1.6, 3.0])


def dh_forward_kinematics(q: np.ndarray) -> np.ndarray:
    """Tool position of one configuration with standard DH: Rz(q) Tz(d) Tx(a) Rx(alpha)."""
    transform = np.eye(4)
    for theta, a, alpha, d in zip(q, DH_A, DH_ALPHA, DH_D, strict=True):
        ct, st, ca, sa = np.cos(theta), np.sin(theta), np.cos(alpha), np.sin(alpha)
        link = np.array(
            [
                [ct, -st * ca, st * sa, a * ct],
                [st, ct * ca, -ct * sa, a * st],
                [0.0, sa, ca, d],
                [0.0, 0.0, 0.0, 1.0],
            ]
        )
        transform = transform @ link
    return transform[:3, 3]


def both_paths(dtype=torch.float64):
    """The WAM through pytorch-kinematics (the default) and through its DH fast path."""
    return ArmKinematics(URDF_PATH, END_EFFECTOR_LINK, dtype=dtype), WamKinematics(dtype=dtype)


@pytest.mark.parametrize("path", ["pytorch_kinematics", "wam_dh"])
def test_forward_kinematics_matches_dh_table(path):
    rng = np.random.default_rng(0)
    q = rng.uniform(LOWER, UPPER, size=(64, 7))
    wam = both_paths()[path == "wam_dh"]
    positions = wam.forward_kinematics(torch.from_numpy(q)).numpy()
    expected = np.stack([dh_forward_kinematics(row) for row in q])
    np.testing.assert_allclose(positions, expected, atol=1e-6, rtol=0)


def test_fast_path_matches_pytorch_kinematics():
    urdf, fast = both_paths()
    q = fast.clamp_to_limits(
        torch.randn(32, 7, generator=torch.Generator().manual_seed(1), dtype=torch.float64)
    )
    for expected, actual in zip(
        urdf.position_and_jacobian(q), fast.position_and_jacobian(q), strict=True
    ):
        torch.testing.assert_close(actual, expected, atol=1e-7, rtol=0)
    torch.testing.assert_close(fast.jacobian(q), urdf.jacobian(q))  # both pytorch-kinematics'
    assert urdf.joint_names == fast.joint_names == [f"wam_j{i}" for i in range(1, 8)]


@pytest.mark.parametrize("path", ["pytorch_kinematics", "wam_dh"])
def test_zero_configuration_points_straight_up(path):
    wam = both_paths()[path == "wam_dh"]
    position = wam.forward_kinematics(torch.zeros(1, 7))
    torch.testing.assert_close(position, torch.tensor([[0.0, 0.0, 0.91]], dtype=torch.float64))


def test_joint_limits_and_clamp():
    wam = WamKinematics(dtype=torch.float64)
    np.testing.assert_allclose(both_paths()[0].joint_lower.numpy(), LOWER)
    np.testing.assert_allclose(wam.joint_lower.numpy(), LOWER)
    np.testing.assert_allclose(wam.joint_upper.numpy(), UPPER)
    clamped = wam.clamp_to_limits(torch.full((2, 7), 10.0, dtype=torch.float64))
    torch.testing.assert_close(clamped[0], wam.joint_upper)
    assert URDF_PATH.exists()


@pytest.mark.parametrize("path", ["pytorch_kinematics", "wam_dh"])
def test_position_jacobian_matches_finite_differences(path):
    wam = both_paths()[path == "wam_dh"]
    q = torch.tensor([[0.3, 0.7, -0.4, 1.5, 0.2, -0.5, 0.1]], dtype=torch.float64)
    position, jacobian = wam.position_and_jacobian(q)
    torch.testing.assert_close(position, wam.forward_kinematics(q))
    eps = 1e-6
    columns = []
    for j in range(7):
        step = torch.zeros_like(q)
        step[0, j] = eps
        difference = wam.forward_kinematics(q + step) - wam.forward_kinematics(q - step)
        columns.append(difference[0] / (2 * eps))
    torch.testing.assert_close(jacobian[0], torch.stack(columns, dim=-1), atol=1e-8, rtol=0)
    assert wam.jacobian(q).shape == (1, 6, 7)


@pytest.mark.parametrize("path", ["pytorch_kinematics", "wam_dh"])
def test_bad_joint_shape_raises(path):
    wam = both_paths(torch.float32)[path == "wam_dh"]
    with pytest.raises(ValueError, match="shape \\[B, 7\\] \\(joints wam_j1, wam_j2"):
        wam.forward_kinematics(torch.zeros(3, 6))
    with pytest.raises(TypeError):
        wam.forward_kinematics(np.zeros((3, 7)))
    with pytest.raises(ValueError, match="'wam_hand' is not a link of wam7.urdf"):
        ArmKinematics(URDF_PATH, "wam_hand")


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_runs_on_cuda():
    for wam in (
        ArmKinematics(URDF_PATH, END_EFFECTOR_LINK, device="cuda"),
        WamKinematics(device="cuda"),
    ):
        position, jacobian = wam.position_and_jacobian(torch.zeros(4, 7, device="cuda"))
        assert position.device.type == "cuda" and jacobian.shape == (4, 3, 7)

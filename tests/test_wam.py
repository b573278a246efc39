"""Barrett WAM model: URDF forward kinematics against an independent DH implementation."""

from __future__ import annotations

import numpy as np
import pytest
import torch

from models.wam import URDF_PATH, WamKinematics

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


def test_forward_kinematics_matches_dh_table():
    rng = np.random.default_rng(0)
    q = rng.uniform(LOWER, UPPER, size=(64, 7))
    wam = WamKinematics(dtype=torch.float64)
    positions = wam.forward_kinematics(torch.from_numpy(q)).numpy()
    expected = np.stack([dh_forward_kinematics(row) for row in q])
    np.testing.assert_allclose(positions, expected, atol=1e-6, rtol=0)


def test_zero_configuration_points_straight_up():
    wam = WamKinematics(dtype=torch.float64)
    position = wam.forward_kinematics(torch.zeros(1, 7))
    torch.testing.assert_close(position, torch.tensor([[0.0, 0.0, 0.91]], dtype=torch.float64))


def test_joint_limits_and_clamp():
    wam = WamKinematics(dtype=torch.float64)
    np.testing.assert_allclose(wam.joint_lower.numpy(), LOWER)
    np.testing.assert_allclose(wam.joint_upper.numpy(), UPPER)
    clamped = wam.clamp_to_limits(torch.full((2, 7), 10.0, dtype=torch.float64))
    torch.testing.assert_close(clamped[0], wam.joint_upper)
    assert URDF_PATH.exists()


def test_position_jacobian_matches_finite_differences():
    wam = WamKinematics(dtype=torch.float64)
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


def test_bad_joint_shape_raises():
    wam = WamKinematics()
    with pytest.raises(ValueError, match="shape"):
        wam.forward_kinematics(torch.zeros(3, 6))
    with pytest.raises(TypeError):
        wam.forward_kinematics(np.zeros((3, 7)))


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs a CUDA GPU")
def test_runs_on_cuda():
    wam = WamKinematics(device="cuda")
    position, jacobian = wam.position_and_jacobian(torch.zeros(4, 7, device="cuda"))
    assert position.device.type == "cuda" and jacobian.shape == (4, 3, 7)

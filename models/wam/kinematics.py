"""Batched kinematics of the Barrett WAM 7-DOF arm with pytorch-kinematics.

The URDF ``wam7.urdf`` next to this file encodes the WAM's standard Denavit-Hartenberg table
(Barrett Technology, *WAM Arm User's Manual*, kinematics chapter; the same numbers are used by
the Robotics Toolbox and DQ Robotics WAM models):

=====  ========  ===========  ========
joint  a [m]     alpha [rad]  d [m]
=====  ========  ===========  ========
1       0         -pi/2        0
2       0         +pi/2        0
3       0.045     -pi/2        0.55
4      -0.045     +pi/2        0
5       0         -pi/2        0.3
6       0         +pi/2        0
7       0          0           0.06
=====  ========  ===========  ========

with joint limits (Barrett's, as in the ROS ``wam_description``) lower
``(-2.6, -2.0, -2.8, -0.9, -4.76, -1.6, -3.0)`` and upper ``(2.6, 2.0, 2.8, 3.1, 1.24, 1.6, 3.0)``
rad. The base frame is the DH frame 0 (at the shoulder, z up); the end effector ``wam_tool`` is
the tool flange, 0.06 m past the wrist centre. Kinematics only: no masses, no geometry.
"""

from __future__ import annotations

from pathlib import Path

import pytorch_kinematics as pk
import torch
from torch import Tensor

URDF_PATH = Path(__file__).with_name("wam7.urdf")
END_EFFECTOR_LINK = "wam_tool"


class WamKinematics:
    """Forward kinematics and position Jacobians of the WAM, batched over configurations.

    Args:
        device: device of the chain and of every returned tensor.
        dtype: floating dtype of the chain (``torch.float64`` for gradient checks).

    Attributes:
        chain: the ``pytorch_kinematics.SerialChain`` from ``wam_base`` to ``wam_tool``.
        joint_lower, joint_upper: ``[7]`` joint limits in rad.
    """

    dof = 7

    def __init__(self, device: torch.device | str = "cpu", dtype: torch.dtype = torch.float32):
        self.device = torch.device(device)
        self.dtype = dtype
        chain = pk.build_serial_chain_from_urdf(URDF_PATH.read_bytes(), END_EFFECTOR_LINK)
        self.chain = chain.to(device=self.device, dtype=dtype)
        lower, upper = self.chain.get_joint_limits()
        self.joint_lower = torch.as_tensor(lower, device=self.device, dtype=dtype)
        self.joint_upper = torch.as_tensor(upper, device=self.device, dtype=dtype)

    def _check_joints(self, q: Tensor) -> Tensor:
        if not isinstance(q, Tensor):
            raise TypeError(f"q must be a torch.Tensor, got {type(q).__name__}")
        if q.dim() != 2 or q.shape[-1] != self.dof:
            raise ValueError(f"q must have shape [B, {self.dof}], got {list(q.shape)}")
        return q.to(device=self.device, dtype=self.dtype)

    def forward_kinematics(self, q: Tensor) -> Tensor:
        """End-effector positions ``[B, 3]`` (m, base frame) of joint angles ``q: [B, 7]``."""
        q = self._check_joints(q)
        return self.chain.forward_kinematics(q).get_matrix()[:, :3, 3]

    def jacobian(self, q: Tensor) -> Tensor:
        """Geometric Jacobians ``[B, 6, 7]`` (linear rows first) in the base frame."""
        return self.chain.jacobian(self._check_joints(q))

    def position_and_jacobian(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Positions ``[B, 3]`` and position Jacobians ``[B, 3, 7]`` from one FK pass."""
        jacobian, pose = self.chain.jacobian(self._check_joints(q), ret_eef_pose=True)
        return pose[:, :3, 3], jacobian[:, :3, :]

    def clamp_to_limits(self, q: Tensor) -> Tensor:
        """``q: [..., 7]`` clamped into the joint limits."""
        return torch.maximum(torch.minimum(q, self.joint_upper), self.joint_lower)

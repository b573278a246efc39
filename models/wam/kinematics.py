"""The Barrett WAM 7-DOF arm: its URDF and an analytic (DH) fast path for its kinematics.

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

The viapoint task runs any URDF through pytorch-kinematics (``dipole_torch.models.
kinematics.ArmKinematics``), the WAM included (``kinematics: pytorch_kinematics``, the default).
``WamKinematics`` is the opt-in fast path for this arm (``kinematics: wam_dh``): the same
interface, with positions and position Jacobians computed from the DH table directly
(``tests/test_wam.py`` checks it against the pytorch-kinematics chain to 1e-7 m). Its speed-up
is measured by ``benchmarks/bench_rollout.py`` (numbers in the docs' benchmark pages).
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from pathlib import Path

import torch
from dipole_torch.models.kinematics import ArmKinematics
from torch import Tensor

URDF_PATH = Path(__file__).with_name("wam7.urdf")
END_EFFECTOR_LINK = "wam_tool"
# The standard DH table of the module docstring (the URDF encodes the same numbers): rows i=1..7.
DH_A = (0.0, 0.0, 0.045, -0.045, 0.0, 0.0, 0.0)  # m
DH_ALPHA = (-math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, -math.pi / 2, math.pi / 2, 0.0)
DH_D = (0.0, 0.0, 0.55, 0.0, 0.3, 0.0, 0.06)  # m


class WamKinematics(ArmKinematics):
    """The WAM's kinematics with the analytic DH fast path, batched over configurations.

    An ``ArmKinematics`` of ``wam7.urdf`` (base ``wam_base``,
    end effector ``wam_tool``) whose ``forward_kinematics`` and ``position_and_jacobian``
    use the DH table instead of the pytorch-kinematics chain; ``jacobian`` (6 rows) and
    ``chain`` stay pytorch-kinematics'.

    Args:
        device: device of the chain and of every returned tensor.
        dtype: floating dtype (``torch.float64`` for gradient checks).
        joint_lower, joint_upper: ``[7]`` limits overriding Barrett's (rad), or ``None``.

    Attributes:
        chain: the ``pytorch_kinematics.SerialChain`` from ``wam_base`` to ``wam_tool``.
        joint_lower, joint_upper: ``[7]`` joint limits in rad.
    """

    def __init__(
        self,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
        joint_lower: Sequence[float] | None = None,
        joint_upper: Sequence[float] | None = None,
    ):
        super().__init__(
            URDF_PATH, END_EFFECTOR_LINK, None, joint_lower, joint_upper, device, dtype
        )
        factory = {"device": self.device, "dtype": dtype}
        self._dh_a = torch.tensor(DH_A, **factory)
        self._dh_d = torch.tensor(DH_D, **factory)
        self._dh_cos_alpha = torch.tensor(DH_ALPHA, **factory).cos()
        self._dh_sin_alpha = torch.tensor(DH_ALPHA, **factory).sin()

    def forward_kinematics(self, q: Tensor) -> Tensor:
        """End-effector positions ``[B, 3]`` (m, base frame) of joint angles ``q: [B, 7]``,
        from the DH table."""
        return self._frames(self.check_joints(q))[:, -1, :3, 3]

    def position_and_jacobian(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Positions ``[B, 3]`` and position Jacobians ``[B, 3, 7]`` of ``q: [B, 7]`` from one
        DH forward pass: ``J_i = z_{i-1} × (p_e − p_{i-1})``."""
        frames = self._frames(self.check_joints(q))  # [B, 7, 4, 4]: frames 1..7
        position = frames[:, -1, :3, 3]
        # Axes z_{i-1} and origins p_{i-1} of frames 0..6 (frame 0 is the base).
        base_axis = torch.zeros_like(position)
        base_axis[:, 2] = 1.0
        axes = torch.cat((base_axis[:, None], frames[:, :-1, :3, 2]), 1)  # [B, 7, 3]
        origins = torch.cat((torch.zeros_like(position)[:, None], frames[:, :-1, :3, 3]), 1)
        jacobian = torch.linalg.cross(axes, position[:, None] - origins, dim=-1)
        return position, jacobian.transpose(-1, -2)

    def _frames(self, q: Tensor) -> Tensor:
        """``[B, 7, 4, 4]`` poses of DH frames 1..7 in the base frame, for ``q: [B, 7]``."""
        cos_q, sin_q = q.cos(), q.sin()
        ca, sa = self._dh_cos_alpha.expand_as(q), self._dh_sin_alpha.expand_as(q)
        a, d = self._dh_a.expand_as(q), self._dh_d.expand_as(q)
        zero, one = torch.zeros_like(q), torch.ones_like(q)
        # A_i = Rz(q_i) Tz(d_i) Tx(a_i) Rx(alpha_i): [B, 7, 4, 4]
        links = torch.stack(
            (
                torch.stack((cos_q, -sin_q * ca, sin_q * sa, a * cos_q), -1),
                torch.stack((sin_q, cos_q * ca, -cos_q * sa, a * sin_q), -1),
                torch.stack((zero, sa, ca, d), -1),
                torch.stack((zero, zero, zero, one), -1),
            ),
            -2,
        )
        frames = [links[:, 0]]
        for i in range(1, self.dof):
            frames.append(frames[-1] @ links[:, i])
        return torch.stack(frames, 1)

"""The Barrett WAM 7-DOF arm: URDF (from its public DH table) and batched kinematics."""

from models.wam.kinematics import URDF_PATH, WamKinematics

__all__ = ["URDF_PATH", "WamKinematics"]

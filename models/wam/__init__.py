"""The Barrett WAM 7-DOF arm: URDF (from its public DH table) and its analytic DH fast path."""

from dipole_torch.models.wam.kinematics import END_EFFECTOR_LINK, URDF_PATH, WamKinematics

__all__ = ["END_EFFECTOR_LINK", "URDF_PATH", "WamKinematics"]

"""Batched kinematics of any serial-chain arm from its URDF, with pytorch-kinematics.

:class:`ArmKinematics` loads a URDF, extracts the serial chain from a base link to an
end-effector link (``pytorch_kinematics.SerialChain``; branches elsewhere in the tree, e.g.
gripper fingers, are ignored) and gives, batched over configurations ``q: [B, n]``:

* the end-effector position ``[B, 3]`` (m, in the base link's frame),
* the geometric Jacobian ``[B, 6, n]`` (``chain.jacobian``: linear rows first),
* both from one forward-kinematics pass (:meth:`ArmKinematics.position_and_jacobian`), the
  call the tracking IK (:mod:`dipole_torch.models.tracking`) makes at every time step.

Everything is differentiable in ``q`` (pytorch-kinematics attaches an analytical backward to
its forward kinematics; the Jacobian is built from those poses with torch ops), so rewards of
tracked paths can be differentiated back to the policy parameters.

Joints on the chain may be revolute, continuous (unlimited revolute) or prismatic. Joint
limits come from the URDF (``±inf`` for continuous joints) unless overridden.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from xml.etree import ElementTree

import pytorch_kinematics as pk
import torch
from torch import Tensor

# The repository root; in a wheel, the installed dipole_torch/ folder, which holds models/ there
# too (pyproject.toml), so models/wam/wam7.urdf resolves either way.
PROJECT_ROOT = Path(__file__).resolve().parents[1]


def resolve_urdf_path(urdf: str | Path) -> Path:
    """The URDF file ``urdf`` names: an absolute path, or a path relative to the current
    directory or else to the project root (so ``models/wam/wam7.urdf`` works from anywhere).
    Raises ``FileNotFoundError`` naming the places tried."""
    path = Path(urdf).expanduser()
    candidates = [path] if path.is_absolute() else [Path.cwd() / path, PROJECT_ROOT / path]
    for candidate in candidates:
        if candidate.is_file():
            return candidate.resolve()
    tried = ", ".join(str(c) for c in candidates)
    raise FileNotFoundError(f"urdf: no file {str(urdf)!r} (tried {tried})")


class ArmKinematics:
    """Forward kinematics and Jacobians of a serial-chain arm, batched over configurations.

    Args:
        urdf: path of the URDF file (see :func:`resolve_urdf_path`).
        end_effector: name of the end-effector link (the point the task moves).
        base_link: name of the link whose frame positions are expressed in (default: the
            URDF's root link). It must be an ancestor of ``end_effector``.
        joint_lower, joint_upper: ``[n]`` joint limits (rad, or m for prismatic joints)
            overriding the URDF's; ``None`` keeps the URDF's.
        device: device of the chain and of every returned tensor.
        dtype: floating dtype of the chain (``torch.float64`` for gradient checks).

    Attributes:
        chain: the ``pytorch_kinematics.SerialChain`` from ``base_link`` to ``end_effector``.
        dof: n, the number of movable joints on the chain.
        joint_names: their names, in the order of the columns of ``q``.
        joint_lower, joint_upper: ``[n]`` joint limits.
        urdf_path: the resolved URDF file.
        robot_name: the ``<robot name=...>`` of the URDF.
    """

    def __init__(
        self,
        urdf: str | Path,
        end_effector: str,
        base_link: str | None = None,
        joint_lower: Sequence[float] | None = None,
        joint_upper: Sequence[float] | None = None,
        device: torch.device | str = "cpu",
        dtype: torch.dtype = torch.float32,
    ):
        self.device = torch.device(device)
        self.dtype = dtype
        self.urdf_path = resolve_urdf_path(urdf)
        text = self.urdf_path.read_bytes()
        try:
            self.robot_name = ElementTree.fromstring(text).get("name") or self.urdf_path.stem
        except ElementTree.ParseError as error:
            raise ValueError(f"urdf {self.urdf_path} is not valid XML: {error}") from None
        try:
            full_chain = pk.build_chain_from_urdf(text)
        except KeyError as error:  # pytorch-kinematics maps joint types through a dict
            raise ValueError(
                f"urdf {self.urdf_path}: unsupported joint type {error} (serial chains of "
                "revolute, continuous, prismatic and fixed joints are supported)"
            ) from None
        links = full_chain.get_link_names()
        for name, value in (("end_effector", end_effector), ("base_link", base_link)):
            if value is not None and value not in links:
                raise ValueError(
                    f"{name} {value!r} is not a link of {self.urdf_path.name}; its links are "
                    f"{', '.join(links)}"
                )
        root = full_chain._root.name if base_link is None else base_link
        base = full_chain.find_frame(root)
        below_base = base is not None and end_effector in _frame_names_below(base)
        if not below_base:
            raise ValueError(
                f"end_effector {end_effector!r} is not below base_link {root!r} in "
                f"{self.urdf_path.name}: pick a base link on the path from the root to it"
            )
        self.base_link = root
        self.end_effector = end_effector
        chain = pk.SerialChain(full_chain, end_effector, "" if base_link is None else base_link)
        self.chain = chain.to(device=self.device, dtype=dtype)
        self.joint_names = list(self.chain.get_joint_parameter_names())
        self.dof = len(self.joint_names)
        if self.dof == 0:
            raise ValueError(
                f"no movable joint between {root!r} and {end_effector!r} in {self.urdf_path.name}"
            )
        lower, upper = self.chain.get_joint_limits()
        factory = {"device": self.device, "dtype": dtype}
        self.joint_lower = self._limit(joint_lower, lower, "joint_lower", factory)
        self.joint_upper = self._limit(joint_upper, upper, "joint_upper", factory)
        if not bool((self.joint_lower <= self.joint_upper).all()):
            raise ValueError(
                f"joint limits: lower {self.joint_lower.tolist()} exceeds upper "
                f"{self.joint_upper.tolist()} for some joint of {self.joint_names}"
            )

    def _limit(self, given, from_urdf, name: str, factory: dict) -> Tensor:
        values = from_urdf if given is None else [float(v) for v in given]
        if len(values) != self.dof:
            raise ValueError(
                f"{name} must give {self.dof} values (joints {', '.join(self.joint_names)}), "
                f"got {len(values)}"
            )
        return torch.as_tensor(values, **factory)

    def check_joints(self, q: Tensor) -> Tensor:
        """Validate ``q: [B, n]`` and move it to the chain's device and dtype."""
        if not isinstance(q, Tensor):
            raise TypeError(f"q must be a torch.Tensor, got {type(q).__name__}")
        if q.dim() != 2 or q.shape[-1] != self.dof:
            raise ValueError(
                f"q must have shape [B, {self.dof}] (joints {', '.join(self.joint_names)}), "
                f"got {list(q.shape)}"
            )
        return q.to(device=self.device, dtype=self.dtype)

    def forward_kinematics(self, q: Tensor) -> Tensor:
        """End-effector positions ``[B, 3]`` (m, base frame) of joint values ``q: [B, n]``."""
        return self.position_and_jacobian(q)[0]

    def jacobian(self, q: Tensor) -> Tensor:
        """Geometric Jacobians ``[B, 6, n]`` (linear rows first) in the base frame."""
        return self.chain.jacobian(self.check_joints(q))

    def position_and_jacobian(self, q: Tensor) -> tuple[Tensor, Tensor]:
        """Positions ``[B, 3]`` and position Jacobians ``[B, 3, n]`` of ``q: [B, n]`` from one
        pytorch-kinematics forward pass (``chain.jacobian(q, ret_eef_pose=True)``)."""
        jacobian, pose = self.chain.jacobian(self.check_joints(q), ret_eef_pose=True)
        return pose[:, :3, 3], jacobian[:, :3]

    def clamp_to_limits(self, q: Tensor) -> Tensor:
        """``q: [..., n]`` clamped into the joint limits."""
        return torch.maximum(torch.minimum(q, self.joint_upper), self.joint_lower)

    def middle_posture(self) -> Tensor:
        """``[n]`` joint values halfway between the limits (0 for an unlimited joint)."""
        middle = 0.5 * (self.joint_lower + self.joint_upper)
        return torch.where(torch.isfinite(middle), middle, torch.zeros_like(middle))


def _frame_names_below(frame) -> set[str]:
    names = {frame.name}
    for child in frame.children:
        names |= _frame_names_below(child)
    return names

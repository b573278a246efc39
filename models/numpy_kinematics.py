"""A serial chain's kinematics in float64 numpy arrays: the viapoint task's CPU engine.

``NumpyChain`` takes the structure of a pytorch-kinematics serial chain (any URDF loaded
by ``dipole_torch.models.kinematics.ArmKinematics``) once, and then computes
end-effector positions and position Jacobians of a batch of configurations with a few dozen
numpy operations a call.

Why: a learning run rolls out a handful of policies at a time, and an inverse-kinematics
step (one forward pass and Jacobian) through pytorch-kinematics' eager torch is nearly all
per-operation overhead (a couple of hundred ops), whatever the batch; here a whole tracking
step (this and the DLS solve) is a few dozen numpy calls (``benchmarks/bench_rollout.py
--task viapoint`` measures both). It is the same maths as
pytorch-kinematics' ``_fk_impl`` and ``jacobian_tensor``, in double precision:

* every frame's local transform is ``link_offset @ joint_offset @ M(q)`` (pytorch-kinematics'
  static offset, then the joint's motion ``M``: a rotation about the unit axis by q for a
  revolute joint, a translation along it by q for a prismatic one, nothing for a fixed one);
* fixed frames are folded into the next movable joint's static transform (and the last ones
  into the tool transform), so the loop runs over the n movable joints only;
* the geometric Jacobian's linear rows are ``z_i × (p_e − p_i)`` for a revolute joint and
  ``z_i`` for a prismatic one, with ``z_i`` the joint's axis and ``p_i`` its origin in the
  base frame.

Nothing here is differentiable (numpy); the torch path (``ArmKinematics``) is.
"""

from __future__ import annotations

import numpy as np
from numpy.typing import NDArray


def _matrix(transform) -> NDArray[np.float64]:
    """A pytorch-kinematics ``Transform3d`` (or ``None``, the identity) as a float64 [4, 4]."""
    if transform is None:
        return np.eye(4)
    return transform.get_matrix().detach().cpu().double().numpy().reshape(4, 4)


def _cross_matrix(axis: NDArray[np.float64]) -> NDArray[np.float64]:
    """[3, 3] K with K v = axis × v."""
    x, y, z = axis
    return np.array([[0.0, -z, y], [z, 0.0, -x], [-y, x, 0.0]])


class NumpyChain:
    """Positions and position Jacobians of a serial chain, batched, in float64 numpy.

    Args:
        chain: a ``pytorch_kinematics.SerialChain`` (``ArmKinematics.chain``).
        base_link: name of its first frame (``ArmKinematics.base_link``).

    Attributes:
        dof: n, the number of movable joints (the columns of ``q``).
        revolute: ``[n]`` bool, True for a revolute joint, False for a prismatic one.
    """

    def __init__(self, chain, base_link: str):
        frame = chain.find_frame(base_link)
        if frame is None:
            raise ValueError(f"base_link {base_link!r} is not a frame of the chain")
        static = np.eye(4)  # fixed transform accumulated since the last movable joint's motion
        rotations, translations, axes, revolute = [], [], [], []
        while True:
            joint = frame.joint
            static = static @ (_matrix(frame.link.offset) @ _matrix(joint.offset))
            if joint.joint_type != "fixed":
                axis = joint.axis.detach().cpu().double().numpy()
                rotations.append(static[:3, :3])
                translations.append(static[:3, 3])
                axes.append(axis / np.linalg.norm(axis))
                revolute.append(joint.joint_type == "revolute")
                static = np.eye(4)
            if not frame.children:
                break
            if len(frame.children) != 1:
                raise ValueError(f"frame {frame.name!r} branches: not a serial chain")
            frame = frame.children[0]
        self.dof = len(axes)
        self.revolute = np.array(revolute, dtype=bool)
        self._all_revolute = bool(self.revolute.all())  # (asked at every call)
        self._rotation = np.array(rotations).reshape(self.dof, 3, 3)  # S_i, fixed part of frame i
        self._translation = np.array(translations).reshape(self.dof, 3)
        axes = np.array(axes).reshape(self.dof, 3)
        cross = np.array([_cross_matrix(a) for a in axes]).reshape(self.dof, 3, 3)
        # Rodrigues: S_i R(a_i, q) = S_i + sin q (S_i K_i) + (1 − cos q) (S_i K_i²); a prismatic
        # joint does not rotate, so its two terms are zero.
        rotating = self.revolute[:, None, None]
        self._sine_term = np.where(rotating, self._rotation @ cross, 0.0)
        self._cosine_term = np.where(rotating, self._rotation @ cross @ cross, 0.0)
        # [n, 1, 3, 2]: S_i a_i (the axis in the frame before joint i's static transform, so
        # that z_i = R_before_i S_i a_i) beside the static translation t_i.
        self._axis_and_offset = np.stack(
            [np.einsum("nij,nj->ni", self._rotation, axes), self._translation], axis=-1
        )[:, None]
        self._tool_translation = static[:3, 3]
        self._first_joint_origin = self._translation[0].copy()
        # Lengths of the fixed offsets after the first joint's motion, up to the end effector.
        self._offset_lengths = np.linalg.norm(
            np.concatenate([self._translation[1:], self._tool_translation[None]]), axis=-1
        )

    def position_and_jacobian(
        self, q: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Positions ``[B, 3]`` and position Jacobians ``[B, 3, n]`` of ``q: [B, n]``."""
        batch, n = q.shape[0], self.dof
        sine, one_minus_cosine = np.sin(q), 1.0 - np.cos(q)
        # [B, n, 3, 3]: each joint's static rotation times its motion, all joints at once.
        local = (
            self._rotation
            + sine[:, :, None, None] * self._sine_term
            + one_minus_cosine[:, :, None, None] * self._cosine_term
        )
        # rotations[i + 1] = local_0 ⋯ local_i, the base-frame rotation after joint i (and
        # rotations[i] the one before it): an inclusive scan by doubling (Hillis & Steele
        # 1986), log₂ n batched products instead of n small ones.
        rotations = np.empty((n + 1, batch, 3, 3))
        rotations[0] = np.eye(3)
        rotations[1:] = local.transpose(1, 0, 2, 3)
        shift = 1
        while shift < n:
            rotations[1 + shift :] = rotations[1:-shift] @ rotations[1 + shift :]
            shift *= 2
        axis_and_offset = rotations[:n] @ self._axis_and_offset  # [n, B, 3, 2]
        axes = axis_and_offset[..., 0]  # z_i, [n, B, 3]
        origins = np.cumsum(axis_and_offset[..., 1], axis=0)  # p_i before joint i's motion
        end = origins[-1] + rotations[n] @ self._tool_translation
        if not self._all_revolute:  # a prismatic joint moves everything after it by q z
            slide = np.where(self.revolute[:, None, None], 0.0, axes * q.T[:, :, None])
            moved = np.cumsum(slide, axis=0)
            origins = origins + moved - slide
            end = end + moved[-1]
        arm = end - origins  # p_e − p_i
        linear = np.stack(  # z_i × (p_e − p_i)
            [
                axes[..., 1] * arm[..., 2] - axes[..., 2] * arm[..., 1],
                axes[..., 2] * arm[..., 0] - axes[..., 0] * arm[..., 2],
                axes[..., 0] * arm[..., 1] - axes[..., 1] * arm[..., 0],
            ],
            axis=1,
        )  # [n, 3, B]
        if not self._all_revolute:
            linear = np.where(self.revolute[:, None, None], linear, axes.transpose(0, 2, 1))
        # A contiguous [B, 3, n]: numpy's matmul picks its kernel (BLAS or its own loop, whose
        # roundings differ) by the operands' strides, and a view's strides depend on B; each
        # policy's numbers must not depend on the batch it is rolled out in.
        return end, np.ascontiguousarray(linear.transpose(2, 1, 0))

    def forward_kinematics(self, q: NDArray[np.float64]) -> NDArray[np.float64]:
        """End-effector positions ``[B, 3]`` of ``q: [B, n]``."""
        return self.position_and_jacobian(q)[0]

    def reach(
        self, lower: NDArray[np.float64], upper: NDArray[np.float64]
    ) -> tuple[NDArray[np.float64], float]:
        """A ball every end-effector position lies in, whatever the joint values within
        ``[lower, upper]: [n]``: its centre ``[3]`` (the first movable joint's origin, which no
        joint moves) and radius (m).

        The radius is the sum of the lengths of the chain's fixed offsets after that joint,
        the tool offset included, plus each prismatic joint's largest travel: rotations keep
        lengths, so the end effector is never farther from the centre (the triangle
        inequality). It is reached only where the arm can stretch every offset along one
        line, so a point inside may still be out of reach; one outside never is. ``inf`` for
        an unlimited prismatic joint.
        """
        travel = np.maximum(np.abs(lower), np.abs(upper))[~self.revolute]
        return self._first_joint_origin.copy(), float(self._offset_lengths.sum() + travel.sum())

    def inverse_kinematics(
        self,
        points: NDArray[np.float64],
        q_guess: NDArray[np.float64],
        lower: NDArray[np.float64],
        upper: NDArray[np.float64],
        damping: float = 1e-2,
        iterations: int = 300,
    ) -> tuple[NDArray[np.float64], NDArray[np.float64]]:
        """Joint values ``[P, n]`` that bring the end effector towards each of ``points:
        [P, 3]``, by iterated damped least squares from ``q_guess: [n]`` within ``[lower,
        upper]: [n]`` (``damping`` λ in m), and the distance ``[P]`` (m) at which each ends.

        A distance well above 0 says that from this guess the point was not reached: it may
        be out of the arm's reach, or behind a joint limit from this posture.
        """
        q = np.clip(np.broadcast_to(q_guess, (points.shape[0], self.dof)), lower, upper)
        damping_term = damping**2 * np.eye(3)
        for _ in range(iterations):
            position, jacobian = self.position_and_jacobian(q)
            error = points - position
            jacobian_t = jacobian.transpose(0, 2, 1)
            gram = jacobian @ jacobian_t + damping_term
            step = (jacobian_t @ np.linalg.solve(gram, error[:, :, None]))[:, :, 0]
            q = np.clip(q + step, lower, upper)
        distance = np.linalg.norm(points - self.forward_kinematics(q), axis=-1)
        return q, distance

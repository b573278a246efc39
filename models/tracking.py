"""Differential inverse kinematics: an arm's end effector tracking a task-space path.

Damped least squares (Wampler 1986; Nakamura & Hanafusa 1986) on the position rows of the
arm's geometric Jacobian, batched over paths:

    q_{k+1} = clip(q_k + Jᵀ (J Jᵀ + λ² I)⁻¹ (x*_{k+1} − f(q_k)),  q_min, q_max),

where f is the forward kinematics and x* the desired path. The error term is the distance to
the next desired point from where the arm *is*, so tracking errors are corrected at the next
step; clipping at the joint limits and the damping near singularities make paths outside the
arm's reach come out different from the desired ones. Only the end-effector position is
controlled; on a redundant arm (n > 3 joints, e.g. the WAM's 7) the redundant degrees of
freedom take the minimum-norm joint step.

``kinematics`` is any object with ``dof``, ``joint_lower``/``joint_upper`` ``[n]``,
``position_and_jacobian(q[B, n]) -> ([B, 3], [B, 3, n])``, ``forward_kinematics(q) -> [B, 3]``
and ``clamp_to_limits``: ``dipole_torch.models.kinematics.ArmKinematics``
(pytorch-kinematics, any URDF: ``chain.jacobian``) or
``dipole_torch.models.wam.WamKinematics`` (the WAM's analytic DH path).
``track_path_numpy`` is the same tracking in float64 numpy on a
``dipole_torch.models.numpy_kinematics.NumpyChain`` (the viapoint task's CPU engine).
"""

from __future__ import annotations

import numpy as np
import torch
from dipole_torch.models.kinematics import ArmKinematics
from dipole_torch.models.numpy_kinematics import NumpyChain
from numpy.typing import NDArray
from torch import Tensor


def damped_least_squares_step(jacobian: Tensor, error: Tensor, damping: float) -> Tensor:
    """Joint step ``[B, n]`` = Jᵀ (J Jᵀ + λ² I)⁻¹ e of ``jacobian: [B, m, n]``, ``error: [B, m]``.

    ``damping`` is λ, in the units of ``error`` (m).
    """
    m = jacobian.shape[-2]
    eye = torch.eye(m, device=jacobian.device, dtype=jacobian.dtype)
    gram = jacobian @ jacobian.transpose(-1, -2) + damping**2 * eye
    return (jacobian.transpose(-1, -2) @ torch.linalg.solve(gram, error.unsqueeze(-1))).squeeze(-1)


def solve_position_ik(
    kinematics: ArmKinematics,
    target: Tensor,
    q_guess: Tensor,
    damping: float = 1e-2,
    iterations: int = 300,
    tolerance: float = 1e-7,
) -> Tensor:
    """Joint values ``[n]`` whose end effector is at ``target: [3]``, by iterated DLS from
    ``q_guess: [n]``. Raises ``ValueError`` if the target is not reached within ``tolerance``
    metres (unreachable, outside the joint limits, or a guess in the wrong basin)."""
    q = kinematics.clamp_to_limits(q_guess.to(kinematics.joint_lower).reshape(1, -1))
    target = target.to(q).reshape(1, 3)
    for _ in range(iterations):
        position, jacobian = kinematics.position_and_jacobian(q)
        error = target - position
        if float(error.norm()) < tolerance:
            break
        q = kinematics.clamp_to_limits(q + damped_least_squares_step(jacobian, error, damping))
    error = float((kinematics.forward_kinematics(q) - target).norm())
    if error > tolerance:
        raise ValueError(
            f"inverse kinematics did not reach {target[0].tolist()} (residual {error:.3g} m) "
            f"from the joint guess {q_guess.tolist()}: the point may be outside the arm's "
            "workspace (or try another initial_joints)"
        )
    return q[0]


def track_path(
    kinematics: ArmKinematics, q_start: Tensor, desired: Tensor, damping: float
) -> tuple[Tensor, Tensor]:
    """Follow ``desired: [B, T+1, 3]`` from joint values ``q_start: [n]`` (whose end effector
    is ``desired[:, 0]``) with DLS differential IK, one ``position_and_jacobian`` call a step.

    Returns:
        ``joints: [B, T+1, n]`` and the end-effector path ``positions: [B, T+1, 3]`` the arm
        actually makes (``positions[:, k] = f(joints[:, k])``).
    """
    batch, horizon = desired.shape[0], desired.shape[1]
    q = q_start.to(desired).expand(batch, -1)
    joints, positions = [], []
    for step in range(horizon - 1):
        position, jacobian = kinematics.position_and_jacobian(q)
        joints.append(q)
        positions.append(position)
        step_q = damped_least_squares_step(jacobian, desired[:, step + 1] - position, damping)
        q = kinematics.clamp_to_limits(q + step_q)
    joints.append(q)
    positions.append(kinematics.forward_kinematics(q))
    return torch.stack(joints, dim=1), torch.stack(positions, dim=1)


def track_path_numpy(
    chain: NumpyChain,
    q_start: NDArray[np.float64],
    desired: NDArray[np.float64],
    damping: float,
    lower: NDArray[np.float64],
    upper: NDArray[np.float64],
) -> NDArray[np.float64]:
    """``track_path`` in float64 numpy (the viapoint task's CPU engine): the same DLS
    steps and clipping to ``[lower, upper]: [n]``, on a ``NumpyChain``.

    Returns the end-effector path ``[B, T+1, 3]`` the arm makes for ``desired: [B, T+1, 3]``
    from ``q_start: [n]``.
    """
    batch, horizon = desired.shape[0], desired.shape[1]
    q = np.broadcast_to(q_start, (batch, chain.dof))
    positions = np.empty_like(desired)
    damping_term = damping**2 * np.eye(3)
    for step in range(horizon - 1):
        position, jacobian = chain.position_and_jacobian(q)
        positions[:, step] = position
        jacobian_t = jacobian.transpose(0, 2, 1)
        gram = jacobian @ jacobian_t + damping_term
        error = desired[:, step + 1] - position
        step_q = (jacobian_t @ np.linalg.solve(gram, error[:, :, None]))[:, :, 0]
        q = np.minimum(np.maximum(q + step_q, lower), upper)
    positions[:, -1] = chain.forward_kinematics(q)
    return positions

"""Viapoint task on a simulated Barrett WAM 7-DOF arm (Bruno, Calinon & Caldwell 2013, Fig. 2-3)."""

from __future__ import annotations

import copy
import math
import warnings
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import TypedDict

import numpy as np
import torch
from dipole_torch.models.ds_gmr import DSGMR
from dipole_torch.models.kinematics import ArmKinematics, format_value, resolve_urdf_path
from dipole_torch.models.numpy_kinematics import NumpyChain
from dipole_torch.models.tracking import solve_position_ik, track_path, track_path_numpy
from dipole_torch.models.wam import END_EFFECTOR_LINK, URDF_PATH, WamKinematics
from dipole_torch.tasks.base import EpisodicTask, floating_dtype
from torch import Tensor

__all__ = ["ENGINES", "FOUND_RETURN", "KINEMATICS", "Obstacle", "ViapointTask"]

KINEMATICS = ("pytorch_kinematics", "wam_dh")  # the choices of ViapointTask(kinematics=...)
ENGINES = ("auto", "numpy", "torch")  # the choices of ViapointTask(engine=...)
WAM_START_POSTURE = (0.0, 0.6, 0.0, 1.6, 0.0, 0.0, 0.0)  # rad, elbow bent, tool in front
# m: a target or viapoint that inverse kinematics from the start posture ends farther from
# than this gets a warning at construction.
UNREACHED_DISTANCE = 1e-3
FOUND_RETURN = 0.9  # the return at which a policy's route counts as found (Figure 3)


class Obstacle(TypedDict):
    """A sphere the end effector's path must not enter.

    Attributes:
        centre: ``[x, y, z]`` in m, in the arm's base frame.
        radius: in m.
    """

    centre: Sequence[float]
    radius: float


class ViapointTask(EpisodicTask):
    r"""Move an arm's end effector from a start to a target point through one of several
    alternative viapoints at each of a few pass times.

    ## Description

    The paper's section "Simulation of a viapoint task" (Bruno, Calinon & Caldwell, AAAI 2013):
    the tip of a Barrett WAM 7-DOF arm moves between two points; at each pass time several
    alternative viapoints are defined, so that several distinct routes are optimal (with the
    default layout, 2 alternatives at each of 3 pass times: 2³ = 8 routes, all with reward 1).
    Any serial-chain arm given as a URDF can take the WAM's place (``urdf``, ``end_effector``,
    ``initial_joints`` and a layout it can reach; see the docs' "Your own arm").

    A policy is a DS-GMR trajectory (``dipole_torch.models.ds_gmr.DSGMR``, Calinon et al.
    2012): a critically damped virtual spring-damper ``ẍ = K_P (x̂(t) − x) − K_V ẋ`` pulls the
    tip towards the attractor path ``x̂(t)`` that Gaussian mixture regression retrieves from a
    GMM over ``[t, x]`` with ``K = len(pass_times)`` learned components and, with
    ``end_at_target`` (default), one fixed final component at the target. The policy
    parameters are the learned components' spatial centres, ``θ = [μ_1^x, ..., μ_K^x]``
    (``D = 3K = 9``). The desired task-space path is then tracked by the simulated arm
    (``dipole_torch.models.tracking.track_path``: damped-least-squares differential IK on
    the arm's position Jacobian, joint limits enforced), and the reward is computed on the
    end-effector path the arm actually makes. The kinematics (forward kinematics and Jacobian,
    batched over rollouts) are pytorch-kinematics'
    (``dipole_torch.models.kinematics.ArmKinematics``, ``chain.jacobian``) by default; for
    the bundled WAM, ``kinematics="wam_dh"`` selects the analytic DH fast path
    (``dipole_torch.models.wam.WamKinematics``), which gives the same paths to float
    rounding.

    ``evaluate`` rolls out ``theta: [B, 9]`` batched over the policies (loops over time
    only), in one of two engines (``engine``):

    * ``"torch"``: torch operations on the task's device and dtype, differentiable in
      ``theta`` on either kinematics path;
    * ``"numpy"``: the same DS-GMR integration and DLS tracking in float64 numpy on the CPU
      (``dipole_torch.models.numpy_kinematics.NumpyChain``, built from the same
      pytorch-kinematics chain), returned in the task's dtype; not differentiable. A
      learning run rolls out a few policies at a time, where eager torch pays its
      per-operation overhead whatever the batch and numpy a fraction of it
      (``benchmarks/bench_rollout.py --task viapoint`` measures both). The two give the
      same paths to float rounding (``tests/test_viapoint.py``);
    * ``"auto"`` (default): numpy on the CPU, unless ``theta`` requires a gradient (and
      gradients are enabled); torch on an accelerator.

    ``kinematics`` chooses the torch engine's kinematics; the numpy engine reads the chain of
    either.

    ## Action Space

    ``θ: [3K]`` (metres, the arm's base frame; for the WAM: origin at the shoulder, z up): the
    attractor centres μ_i^x, component-major (``θ[3i:3i+3] = μ_i^x``). The arm's joint
    velocities are not actions: the differential IK derives them from the DS-GMR path.

    ## Observation Space

    None is given to the policy (open-loop trajectory). ``trajectory`` returns the
    end-effector path ``[B, T+1, 3]`` (m), ``route`` which alternative is nearest at each
    pass time and ``end_point_error`` how far the path ends from the target.

    ## Rewards

    Eq. 9 with the Euclidean norm:
    ``r = (1/N_v) Σ_i exp(−α ‖x(t_i) − x_i^v‖)``, where ``x(t_i)`` is the end effector at pass
    time ``t_i``, ``x_i^v`` the alternative viapoint nearest to it and ``N_v`` the number of
    pass times. ``reward_range = (0, 1)``; 1 is reached when one viapoint is passed exactly at
    every pass time. ``α = reward_alpha = 2.5`` 1/m: ``exp(−α d) ≥ 0.9`` for ``d ≤ 4.2`` cm
    (a route is "found" at reward ≥ 0.9: within 4.2 cm on average of viapoints 20 cm from
    their alternatives), ``≈ 0.78`` at 10 cm (the straight-line policy θ0), ``≈ 0.61`` at 20 cm.
    The end point is not scored (eq. 9 as in the paper): the fixed final component makes the
    path end at the target whatever θ is.

    Obstacles (``obstacles``, none by default): spheres the end effector must not enter,
    checked on the path the arm actually makes (after tracking, every step of it). A path
    that enters has its eq. 9 reward multiplied by ``exp(−p / penetration_scale)``, where
    ``p`` is its penetration depth (m): how far the path goes inside the obstacles at its
    deepest point, ``max_t max_j (ρ_j − ‖x(t) − c_j‖)⁺`` for spheres of centre ``c_j`` and
    radius ``ρ_j``. With ``penetration_scale = 0.02`` m, a path 2 cm deep keeps 37 % of its
    reward and one through the centre of an 8 cm sphere 1.8 %; one that only grazes a
    sphere keeps almost all of it. The factor is continuous (and differentiable almost
    everywhere) in θ, so that among samples that all enter an obstacle the shallower ones
    rank higher and a reward-weighted update (PoWER) climbs out; a reward of 0 inside would
    give it no direction. ``set_obstacles`` / ``with_obstacles`` change them at run
    time (the world changes), ``blocking_obstacle`` places one on a learned route.

    ## Starting State

    Deterministic: the arm at rest at ``q_start``. With a ``start`` point, ``q_start`` is the
    joint configuration whose end effector is ``start``, found once by iterated DLS inverse
    kinematics from ``initial_joints`` (for the WAM an elbow-bent posture); with
    ``start=None``, ``q_start = initial_joints`` and ``start`` is its end-effector position.
    ``generator`` is ignored (nothing is random).

    ## Episode End

    After ``duration = 2.8`` s, i.e. ``duration / dt = 140`` steps of ``dt = 0.02`` s.

    ## Arguments

    Each constructor argument has one entry under Args below. Pass times are rounded to the
    ``dt`` grid; the number of alternatives may differ between pass times. Without
    ``initial_joints`` the start posture (with ``start``, the guess of the start IK) is the
    WAM's ``(0, 0.6, 0, 1.6, 0, 0, 0)`` rad for the bundled WAM, else the middle of the joint
    limits (0 for an unlimited joint). ``kinematics="wam_dh"`` needs the bundled WAM URDF and
    ``wam_tool``. ``start`` and ``target`` must lie outside every obstacle. Every point must
    be within the arm's reach (see "Choices where the paper is silent").

    The default layout (``configs/task/viapoint.yaml``): start ``(0.5, −0.35, 0)``, target
    ``(0.5, 0.35, 0)`` (a 70 cm straight line in front of the shoulder, 0.61 m from it at its
    ends), pass times 0.4, 1.2, 2.0 s, viapoints 10 cm either side of where the straight-line
    policy passes at each pass time: below/above at 0.4 s and 2.0 s (``z = ∓0.1``),
    near/far at 1.2 s (``x = 0.4 / 0.6``). Alternatives are 20 cm apart.

    Args:
        start: ``[3]`` start point in m (base frame); None: the end effector at initial_joints.
        target: ``[3]`` target point in m (base frame), where paths end with end_at_target.
        pass_times: ``[N_v]`` times in s, in ``(0, duration]``, one learned attractor each.
        viapoints: per pass time, a list of >= 1 alternative ``[x, y, z]`` points in m.
        reward_alpha: α of eq. 9 in 1/m: how steeply the reward falls with the miss distance.
        stiffness: K_P of the spring-damper in 1/s²; the damping is K_V = 2 √K_P in 1/s.
        dt: integration step in s.
        duration: length of the motion in s.
        time_std: σ_t of the GMM components' time marginals in s; None: half their spacing.
        end_at_target: add a fixed final DS-GMR component at target, so that paths end there.
        goal_time: time centre in s of that component; None: (last pass time + duration) / 2.
        exploration_std: std in m of the initial exploration of each attractor coordinate.
        ik_damping: λ of the damped-least-squares tracking IK in m.
        obstacles: spheres ``[{"centre": [x, y, z], "radius": ρ}, ...]`` in m to keep out of.
        penetration_scale: penetration depth in m at which an obstacle divides the reward by e.
        urdf: the arm's URDF file; a relative path: from the current directory, else the project.
        end_effector: name of the link the task moves through the viapoints.
        base_link: name of the link whose frame all points are in; None: the URDF's root link.
        joint_lower: ``[n]`` lower joint limits in rad (m for prismatic); None: the URDF's.
        joint_upper: ``[n]`` upper joint limits in rad (m for prismatic); None: the URDF's.
        initial_joints: ``[n]`` start posture in rad (the start IK's guess); None: see above.
        kinematics: "pytorch_kinematics" (any URDF) or "wam_dh" (the bundled WAM's DH path).
        engine: "auto", "numpy" or "torch": how rollouts run (see Description).
        device: torch device the rollouts run on ("cpu", "cuda", ...).
        dtype: floating dtype of the rollouts, a torch.dtype or its name ("float64").

    ## Deviations from the paper

    * Eq. 9 as printed lacks the norm; we use the Euclidean distance ``‖x(t_i) − x_i^v‖``.
    * The paper simulates the arm with the MATLAB Robotics Toolbox; we use a kinematic URDF of the
      WAM built from its public DH table (``dipole_torch.models.wam``) and pytorch-kinematics.
      Only kinematics is simulated (no dynamics or torque limits): the arm follows the desired path
      unless joint limits, singularities or the workspace boundary prevent it.
    * The paper learns "the position and the activation weights of the attractors" but counts
      only the 9 attractor coordinates as policy parameters; the activation weights (the GMM's
      time centres, σ_t and mixing weights) are fixed here.
    * The paper's task moves "between two points" and its initial policy has "zero velocity"
      at both, but with its 3 attractors alone a learned path ends wherever the last
      attractor sits: pulled towards the last viapoint, the exact routes of the default
      layout end 10.2 cm from the target, and the final policy means of the previous
      release's 10 DIPOLE runs 9.2 ± 1.0 cm. A fourth, fixed component at the target (θ
      stays the 9 coordinates, eq. 9 is unchanged) and a motion 0.4 s longer (2.8 s instead
      of 2.4 s) make every path end at the target: the exact routes end 1.9 mm from it, at
      1.3 cm/s, with the same attractor shifts from θ0 (at most 14.6 cm), and the final
      policy means of 10 DIPOLE runs 0.17 ± 0.01 cm. Keeping the 2.4 s end (target
      component at 2.2 s) they would end 1.4 cm short, still moving at 9 cm/s, and need
      shifts of up to 19 cm.

    ## Choices where the paper is silent

    * Layout (start, target, pass times, viapoints): see Arguments; every route needs
      attractor shifts of at most about 15 cm (3 ``exploration_std``) from θ0.
    * ``reward_alpha = 2.5`` 1/m and ``exploration_std = 0.05`` m were chosen by measurement
      (``benchmarks/reproduce_viapoint.py``, 6 DIPOLE runs of 300 trials each, paper's
      α = 1, m = 10, M = 5, before the fixed final component): with α = 5 and a 0.1 m std, no
      final policy mean reached reward 0.9 (mean final best sample 0.72); α = 5 with 0.05 m:
      0.80, still no route ≥ 0.9; α = 10 with 0.05 m: 0.67. DIPOLE's exploration std shrinks
      slowly (0.1 → ~0.06 m in 300 trials with a 0.1 m start: the inverse-Wishart prior
      dominates 5-point clusters in 10 dimensions), so the sample rewards stay limited by
      exploration noise; a smaller α makes eq. 9 less steep at that noise level. With
      α = 2.5 and 0.05 m, runs found 1.7 routes on average and all 8 over 6 runs.
    * Time centres of the GMM: the K learned components and the target component evenly
      spaced on ``[0, goal_time]`` (0, 0.8, 1.6 s and the target at 2.4 s), the first active
      at the start; θ0 puts the K attractors evenly on the straight line from start to
      target (start, midpoint, target for K = 3), so the tip moves along that line and ends
      at the target at rest. Without the target component (``end_at_target=False``) the
      centres are ``i · duration / K``.
    * The GMM covariances do not couple t and x, so GMR gives ``x̂(t) = Σ_i h_i(t) μ_i^x``
      (+ ``h_g(t)`` times the target).
    * ``K_P = 100`` 1/s² (time constant 0.1 s: the tip lags the attractor by about 0.2 s),
      critically damped ``K_V = 2 √K_P``; semi-implicit Euler at ``dt = 0.02`` s.
    * ``exploration_std = 0.05`` m: the attractors of ±3σ draws stay within 0.15 m of the
      straight line, well inside the WAM's 0.91 m reach (the paper: "the initial covariance
      is set so that the trajectory stays within the workspace of the robot").
    * Reachability, checked at construction. A start, target or viapoint beyond the arm's
      full stretch (farther from its first joint than the summed lengths of the chain's
      link offsets, plus the travel of its prismatic joints; ``NumpyChain.reach``) is a
      ``ValueError`` naming the point and by how much it is out of reach: no posture
      reaches it, and a run would only end far from it. A target or viapoint within that
      stretch which inverse kinematics from the start posture does not reach (within
      ``UNREACHED_DISTANCE``) gets a warning naming it, not an error: joint limits or a
      fold the arm cannot make may keep it out of reach, but another posture might reach
      a point this one does not.
    * Differential IK: DLS on the 3 position rows of the Jacobian with damping λ = 0.05 m,
      error feedback to the next desired point, joint positions clamped to the joint limits
      (Barrett's for the WAM); the redundant degrees of freedom take the minimum-norm step
      (no null-space posture task).

    Example:
        >>> task = ViapointTask()
        >>> round(float(task.evaluate(task.theta0[None])[0]), 2)
        0.78
    """

    def __init__(
        self,
        start: Sequence[float] | None = (0.5, -0.35, 0.0),
        target: Sequence[float] = (0.5, 0.35, 0.0),
        pass_times: Sequence[float] = (0.4, 1.2, 2.0),
        viapoints: Sequence[Sequence[Sequence[float]]] = (
            ((0.5, -0.29, -0.1), (0.5, -0.29, 0.1)),
            ((0.4, 0.06, 0.0), (0.6, 0.06, 0.0)),
            ((0.5, 0.34, -0.1), (0.5, 0.34, 0.1)),
        ),
        reward_alpha: float = 2.5,
        stiffness: float = 100.0,
        dt: float = 0.02,
        duration: float = 2.8,
        time_std: float | None = 0.28,
        end_at_target: bool = True,
        goal_time: float | None = None,
        exploration_std: float = 0.05,
        ik_damping: float = 0.05,
        obstacles: Sequence[Obstacle] = (),
        penetration_scale: float = 0.02,
        urdf: str | Path = "models/wam/wam7.urdf",
        end_effector: str = END_EFFECTOR_LINK,
        base_link: str | None = None,
        joint_lower: Sequence[float] | None = None,
        joint_upper: Sequence[float] | None = None,
        initial_joints: Sequence[float] | None = None,
        kinematics: str = "pytorch_kinematics",
        engine: str = "auto",
        device: str | torch.device = "cpu",
        dtype: torch.dtype | str = torch.float32,
    ) -> None:
        self.device = torch.device(device)
        if engine not in ENGINES:
            raise ValueError(
                f"engine must be one of {', '.join(map(repr, ENGINES))}, got {engine!r}"
            )
        if engine == "numpy" and self.device.type != "cpu":
            raise ValueError(
                f"engine='numpy' runs on the CPU; device {str(self.device)!r} needs engine "
                "'torch' (or 'auto', which picks it there)"
            )
        self.engine = engine
        self.dtype = floating_dtype(dtype, half=False)
        factory = {"device": self.device, "dtype": self.dtype}
        start, target, pass_times, viapoints, initial_joints, joint_lower, joint_upper = map(
            _plain, (start, target, pass_times, viapoints, initial_joints, joint_lower, joint_upper)
        )
        self.target = _point(target, "target", factory)
        for name, value in (
            ("reward_alpha", reward_alpha),
            ("exploration_std", exploration_std),
            ("ik_damping", ik_damping),
            ("penetration_scale", penetration_scale),
        ):
            if not (math.isfinite(value) and value > 0):
                raise ValueError(f"{name} must be a positive finite number, got {value!r}")
        self.reward_alpha = float(reward_alpha)  # α of eq. 9, 1/m
        self.ik_damping = float(ik_damping)  # λ of the damped least squares, m
        self.penetration_scale = float(penetration_scale)  # m: depth that divides reward by e
        self.pass_times = [float(t) for t in pass_times]  # seconds
        if len(self.pass_times) == 0:
            raise ValueError("pass_times must name at least one pass time")
        if len(viapoints) != len(self.pass_times):
            raise ValueError(
                f"viapoints must give a list of alternatives for each of the "
                f"{len(self.pass_times)} pass times, got {len(viapoints)} lists"
            )
        for t in self.pass_times:
            if not (0 < t <= duration):
                raise ValueError(f"pass_times must lie in (0, duration={duration}], got {t}")
        self.end_at_target = bool(end_at_target)
        if self.end_at_target and goal_time is None:
            goal_time = 0.5 * (max(self.pass_times) + duration)
        elif not self.end_at_target:
            goal_time = None
        self.dynamics = DSGMR(
            num_attractors=len(self.pass_times),
            duration=duration,
            dt=dt,
            stiffness=stiffness,
            dim=3,
            time_std=time_std,
            goal_time=goal_time,
            device=self.device,
            dtype=self.dtype,
        )
        self.pass_indices = [round(t / self.dynamics.dt) for t in self.pass_times]
        self._pass_index = torch.tensor(self.pass_indices, device=self.device)
        # Alternatives padded to [N_v, A_max, 3] by repeating the first one (a duplicate never
        # changes the nearest distance, and argmin returns the first of equal entries).
        alternatives = [_alternatives(v, i, factory) for i, v in enumerate(viapoints)]
        most = max(a.shape[0] for a in alternatives)
        self.num_alternatives = [a.shape[0] for a in alternatives]
        self.viapoints = torch.stack(
            [torch.cat([a, a[:1].expand(most - a.shape[0], 3)]) for a in alternatives]
        )
        self.kinematics = _make_kinematics(
            kinematics, urdf, end_effector, base_link, joint_lower, joint_upper, factory
        )
        is_wam = self.kinematics.urdf_path == URDF_PATH.resolve()
        if initial_joints is None:
            if is_wam and end_effector == END_EFFECTOR_LINK and base_link in (None, "wam_base"):
                initial_joints = WAM_START_POSTURE
            else:
                initial_joints = self.kinematics.middle_posture().tolist()
        guess = torch.as_tensor(initial_joints, **factory)
        if guess.shape != (self.kinematics.dof,) or not torch.isfinite(guess).all():
            raise ValueError(
                f"initial_joints must give {self.kinematics.dof} finite values (joints "
                f"{', '.join(self.kinematics.joint_names)}), got {initial_joints!r}"
            )
        self._numpy_chain = NumpyChain(self.kinematics.chain, self.kinematics.base_link)
        # Points beyond the chain's full stretch are errors before any IK runs.
        named_points = [("target", self.target)] + [
            (f"viapoints[{i}][{a}]", point)
            for i, points in enumerate(alternatives)
            for a, point in enumerate(points)
        ]
        if start is not None:
            named_points.insert(0, ("start", _point(start, "start", factory)))
        self._check_within_reach(named_points)
        # The start posture, or with a start point the IK's first guess: a posture all the same.
        outside = [
            f"{name} = {format_value(q)} (limits [{format_value(low)}, {format_value(high)}])"
            for name, q, low, high in zip(
                self.kinematics.joint_names,
                guess.tolist(),
                self.kinematics.joint_lower.tolist(),
                self.kinematics.joint_upper.tolist(),
                strict=True,
            )
            if not low <= q <= high
        ]
        if outside:
            raise ValueError(
                f"initial_joints lie outside the joint limits (rad, or m for prismatic "
                f"joints) at {', '.join(outside)}"
            )
        if start is None:
            self.q_start = guess
            self.start = self.kinematics.forward_kinematics(guess[None])[0].detach()
        else:
            self.start = named_points[0][1]
            tolerance = 1e-8 if self.dtype == torch.float64 else 1e-5  # m
            self.q_start = solve_position_ik(
                self.kinematics, self.start, guess, tolerance=tolerance
            )
        self._warn_if_not_reached(named_points[1:] if start is not None else named_points)
        k = self.dynamics.num_attractors
        fractions = torch.linspace(0.0, 1.0, k, **factory) if k > 1 else torch.ones(1, **factory)
        self.theta0 = (self.start + fractions[:, None] * (self.target - self.start)).reshape(-1)
        self.sigma_start = exploration_std**2 * torch.eye(3 * k, **factory)
        self.reward_range = (0.0, 1.0)
        self.set_obstacles(obstacles)

    # ------------------------------------------------------------------ reach checks
    def _check_within_reach(self, named_points: Sequence[tuple[str, Tensor]]) -> None:
        """Raise ``ValueError`` for a point (``[3]`` m, named) that no joint values reach:
        outside the ball around the first joint whose radius is the chain's full stretch
        (``NumpyChain.reach``)."""
        lower, upper = _array(self.kinematics.joint_lower), _array(self.kinematics.joint_upper)
        centre, radius = self._numpy_chain.reach(lower, upper)
        for name, point in named_points:
            distance = float(np.linalg.norm(_array(point) - centre))
            if distance > radius:
                raise ValueError(
                    f"{name} {_format_point(point)} is out of the arm's reach (outside its "
                    f"workspace) by {100 * (distance - radius):.1f} cm: it is "
                    f"{distance:.3g} m from the first joint of {self.kinematics.robot_name} "
                    f"(at {_format_point(centre)} in the frame of "
                    f"{self.kinematics.base_link!r}), and the links from there to "
                    f"{self.kinematics.end_effector!r} reach {radius:.3g} m at full stretch"
                )

    def _warn_if_not_reached(self, named_points: Sequence[tuple[str, Tensor]]) -> None:
        """Warn for each point (``[3]`` m, named) that inverse kinematics from ``q_start``
        (``NumpyChain.inverse_kinematics``) ends more than ``UNREACHED_DISTANCE`` from."""
        lower, upper = _array(self.kinematics.joint_lower), _array(self.kinematics.joint_upper)
        points = np.stack([_array(point) for _, point in named_points])
        _, distances = self._numpy_chain.inverse_kinematics(
            points, _array(self.q_start), lower, upper
        )
        for (name, point), distance in zip(named_points, distances.tolist(), strict=True):
            if distance > UNREACHED_DISTANCE:
                warnings.warn(
                    f"{name} {_format_point(point)} may be out of the arm's reach: inverse "
                    f"kinematics from the start posture ends {100 * distance:.1f} cm from it "
                    "(joint limits, or a point inside the chain's stretch that no posture "
                    "reaches); paths through it are likely to miss it",
                    stacklevel=3,
                )

    # ------------------------------------------------------------------ obstacles
    def set_obstacles(self, obstacles: Sequence[Mapping]) -> None:
        """Replace the obstacles by the spheres ``[{"centre": [x, y, z], "radius": ρ}, ...]``
        (m); ``[]`` clears them. Raises ``ValueError`` naming the entry for a bad sphere or one
        that holds the start or the target (every path would enter it)."""
        obstacles = _plain(obstacles)
        if isinstance(obstacles, Mapping):
            raise ValueError(f"obstacles must be a list of spheres, got one mapping {obstacles!r}")
        factory = {"device": self.device, "dtype": self.dtype}
        centres, radii = [], []
        for j, sphere in enumerate(obstacles):
            if not isinstance(sphere, Mapping) or set(sphere) != {"centre", "radius"}:
                raise ValueError(
                    f"obstacles[{j}] must be {{'centre': [x, y, z], 'radius': r}}, got {sphere!r}"
                )
            centre = _point(sphere["centre"], f"obstacles[{j}].centre", factory)
            radius = _radius(sphere["radius"], f"obstacles[{j}].radius")
            for name, point in (("start", self.start), ("target", self.target)):
                if float(torch.linalg.vector_norm(point - centre)) <= radius:
                    raise ValueError(
                        f"obstacles[{j}] (centre {centre.tolist()}, radius {radius}) holds the "
                        f"{name} point {point.tolist()}: every path would enter it"
                    )
            centres.append(centre)
            radii.append(float(radius))
        # As given (full precision, plain floats: JSON, checkpoints, configs).
        self._obstacles = [
            {"centre": [float(x) for x in sphere["centre"]], "radius": radius}
            for sphere, radius in zip(obstacles, radii, strict=True)
        ]
        self.obstacle_centres = torch.stack(centres) if centres else torch.zeros(0, 3, **factory)
        self.obstacle_radii = torch.tensor(radii, **factory)  # [J] m

    def with_obstacles(self, obstacles: Sequence[Mapping]) -> ViapointTask:
        """A copy of this task with other obstacles (see ``set_obstacles``); it shares
        the arm and the layout, so making it costs no inverse kinematics."""
        task = copy.copy(self)
        task.set_obstacles(obstacles)
        return task

    @property
    def obstacles(self) -> list[dict]:
        """The obstacles as ``[{"centre": [x, y, z], "radius": ρ}, ...]`` (m), as given."""
        return copy.deepcopy(self._obstacles)

    def penetration(self, path: Tensor) -> Tensor:
        """``[B]`` penetration depth (m) of ``path: [B, T+1, 3]`` into the obstacles: how far
        inside a sphere it goes at its deepest point (0 for a path that stays outside)."""
        if self.obstacle_radii.numel() == 0:
            return path.new_zeros(path.shape[0])
        offsets = path.unsqueeze(-2) - self.obstacle_centres  # [B, T+1, J, 3]
        depth = self.obstacle_radii - torch.linalg.vector_norm(offsets, dim=-1)  # [B, T+1, J]
        return depth.clamp_min(0.0).flatten(1).amax(dim=-1)

    def blocking_obstacle(
        self, theta: Tensor, radius: float = 0.08, threshold: float = 0.9
    ) -> tuple[dict, str]:
        """A sphere that blocks the route of the best of the policies ``theta: [K, D]``.

        The sphere of ``radius`` (m) is centred on a viapoint the best policy's path passes
        (its route's alternative at one pass time). The pass time is the one where most of the
        other routes taken by good policies (return ≥ ``threshold`` on the current layout)
        pass the other alternative, so they stay open; ties go to the earliest pass time (with
        no other good route: the first). The default 8 cm keeps the start and the target
        (11.7 and 10.0 cm from the first and last viapoints of the default layout) outside,
        and the paths of the routes through the other alternatives (19 cm away at the middle
        pass time, about 10 cm from the first and last viapoints near the start and target).

        Returns:
            The obstacle (``{"centre": [3], "radius": radius}``, for ``set_obstacles``)
            and a description, e.g. ``"a sphere of radius 8 cm on the far viapoint at
            t = 1.2 s (route below / far / above)"``.
        """
        if theta.dim() == 2 and theta.shape[0] == 0:
            raise ValueError("theta holds no policy: a blocking obstacle needs a route to block")
        with torch.no_grad():
            path = self.trajectory(theta)
            returns = self.reward(path)
            routes = self.viapoint_distances(path).argmin(dim=-1)  # [K, N_v]
        best = int(returns.argmax())
        others = routes[(returns >= threshold) & (routes != routes[best]).any(dim=-1)]
        others = torch.unique(others, dim=0)  # distinct good routes but the best's
        kept_open = (others != routes[best]).sum(dim=0)  # [N_v] routes avoiding each viapoint
        i = int(kept_open.argmax())  # the first of equal counts
        alternative = int(routes[best, i])
        centre = [round(x, 6) for x in self.viapoints[i, alternative].tolist()]  # float32 noise
        obstacle = {"centre": centre, "radius": float(radius)}
        name = self.alternative_names[i][alternative]
        description = (
            f"a sphere of radius {100 * radius:g} cm on the {name} viapoint at "
            f"t = {self.pass_times[i]:g} s (route {self.route_name(routes[best].tolist())})"
        )
        return obstacle, description

    # ------------------------------------------------------------------ rollouts
    def desired_trajectory(self, theta: Tensor) -> Tensor:
        """The DS-GMR task-space path ``[B, T+1, 3]`` the arm is asked to follow."""
        return self._desired(self.check_theta(theta))

    def _desired(self, theta: Tensor) -> Tensor:
        goal = self.target if self.end_at_target else None
        return self.dynamics.rollout(_within_reach(theta), self.start, goal)

    def trajectory(self, theta: Tensor) -> Tensor:
        """The end-effector path ``[B, T+1, 3]`` (m) the arm actually makes for ``theta``."""
        theta = self.check_theta(theta)
        if self._runs_numpy(theta):
            return self._trajectory_numpy(theta)
        desired = self._desired(theta)  # (theta checked above)
        _, positions = track_path(self.kinematics, self.q_start, desired, self.ik_damping)
        return positions

    def _runs_numpy(self, theta: Tensor) -> bool:
        """Whether this rollout of ``theta`` runs in the numpy engine (see ``engine``)."""
        if self.engine == "torch":
            return False
        needs_gradient = torch.is_grad_enabled() and theta.requires_grad
        if self.engine == "numpy" and needs_gradient:
            raise ValueError(
                "engine='numpy' is not differentiable, and theta requires a gradient: use "
                "engine='torch' (or 'auto', which picks it for such a theta)"
            )
        return self.engine == "numpy" or (self.device.type == "cpu" and not needs_gradient)

    def _trajectory_numpy(self, theta: Tensor) -> Tensor:
        """``trajectory`` in the numpy engine (float64), returned in the task's dtype."""
        goal = _array(self.target) if self.end_at_target else None
        theta = _array(_within_reach(theta))
        desired = self.dynamics.rollout_numpy(theta, _array(self.start), goal)
        path = track_path_numpy(
            self._numpy_chain,
            _array(self.q_start),
            desired,
            self.ik_damping,
            _array(self.kinematics.joint_lower),
            _array(self.kinematics.joint_upper),
        )
        return torch.from_numpy(path).to(dtype=self.dtype)

    def pass_positions(self, path: Tensor) -> Tensor:
        """``[B, N_v, 3]`` end-effector positions at the pass times of ``path: [B, T+1, 3]``."""
        return path[:, self._pass_index]

    def viapoint_distances(self, path: Tensor) -> Tensor:
        """``[B, N_v, A]`` distances (m) from the path at each pass time to each alternative."""
        difference = self.pass_positions(path).unsqueeze(-2) - self.viapoints
        return torch.linalg.vector_norm(difference, dim=-1)

    def end_point_error(self, path: Tensor) -> Tensor:
        """``[B]`` distance (m) from the end of ``path: [B, T+1, 3]`` to the target."""
        return torch.linalg.vector_norm(path[:, -1] - self.target, dim=-1)

    def reward(self, path: Tensor) -> Tensor:
        """Eq. 9 of an end-effector path ``[B, T+1, 3]``: ``[B]`` in ``[0, 1]``, times
        ``exp(−penetration / penetration_scale)`` where there are obstacles."""
        nearest = self.viapoint_distances(path).amin(dim=-1)  # [B, N_v]
        reward = torch.exp(-self.reward_alpha * nearest).mean(dim=-1)
        if self.obstacle_radii.numel() == 0:
            return reward  # the open layout: eq. 9 exactly
        return reward * torch.exp(-self.penetration(path) / self.penetration_scale)

    def route(self, theta: Tensor) -> Tensor:
        """``LongTensor [B, N_v]``: index of the nearest alternative at each pass time."""
        with torch.no_grad():
            return self.viapoint_distances(self.trajectory(theta)).argmin(dim=-1)

    def evaluate(self, theta: Tensor, generator: torch.Generator | None = None) -> Tensor:
        """Eq. 9 reward ``[B]`` of the arm's path for each policy ``theta: [B, 3K]``.

        ``generator`` is ignored: the task is deterministic. Differentiable in ``theta``.
        """
        return self.reward(self.trajectory(theta))

    # ------------------------------------------------------------------ reporting
    @property
    def alternative_names(self) -> list[list[str]]:
        """Per pass time, a name for each alternative viapoint, from where it lies relative
        to the centroid of that pass time's alternatives along the axis that separates them
        most: ``near``/``far`` (x, away from the shoulder), ``right``/``left`` (y),
        ``below``/``above`` (z); ``via`` for a single alternative. Duplicate names get the
        alternative's index appended."""
        words = (("near", "far"), ("right", "left"), ("below", "above"))
        names = []
        for i, count in enumerate(self.num_alternatives):
            points = self.viapoints[i, :count].double().cpu()
            if count == 1:
                names.append(["via"])
                continue
            offsets = points - points.mean(0)
            axis = int(offsets.abs().amax(0).argmax())
            row = [words[axis][int(offset[axis] > 0)] for offset in offsets]
            if len(set(row)) < count:
                row = [f"{name}{a}" for a, name in enumerate(row)]
            names.append(row)
        return names

    def route_name(self, route: Sequence[int]) -> str:
        """``"below / far / above"`` for ``route = (0, 1, 1)`` with the default layout."""
        names = self.alternative_names
        return " / ".join(names[i][int(a)] for i, a in enumerate(route))

    def describe_policies(self, theta: Tensor) -> list[str]:
        """One line per policy ``theta: [K, 3K']``: its route (nearest alternative at each pass
        time), the reward of the arm's path, the distance (cm) to the nearest viapoint at each
        pass time and the distance (cm) of the path's end from the target, e.g.
        ``route (0, 1, 1): below / far / above, return 0.972, misses 0.3 / 0.9 / 0.5 cm,
        ends 0.2 cm from the target`` (and ``, 3.1 cm deep in an obstacle`` for a path that
        enters one)."""
        with torch.no_grad():
            path = self.trajectory(theta)
            rewards = self.reward(path)
            distances = self.viapoint_distances(path)
            ends = (100.0 * self.end_point_error(path)).tolist()  # cm
            depths = (100.0 * self.penetration(path)).tolist()  # cm
        routes = distances.argmin(-1).tolist()
        nearest = (100.0 * distances.amin(-1)).tolist()  # cm
        return [
            f"route {tuple(route)}: {self.route_name(route)}, return {reward:.3f}, misses "
            + " / ".join(f"{d:.1f}" for d in misses)
            + f" cm, ends {end:.1f} cm from the target"
            + (f", {depth:.1f} cm deep in an obstacle" if depth > 0 else "")
            for route, reward, misses, end, depth in zip(
                routes, rewards.tolist(), nearest, ends, depths, strict=True
            )
        ]

    def routes_found(self, theta: Tensor, threshold: float = FOUND_RETURN) -> list[tuple[int, ...]]:
        """The distinct routes, sorted, taken by the rows of ``theta: [K, 3K']`` whose path
        returns at least ``threshold`` (a route is "found" at return ≥ 0.9, as
        ``benchmarks/reproduce_viapoint.py`` counts them)."""
        with torch.no_grad():
            path = self.trajectory(theta)
            returns = self.reward(path).tolist()
            routes = self.viapoint_distances(path).argmin(-1).tolist()
        return sorted(
            {tuple(r) for r, value in zip(routes, returns, strict=True) if value >= threshold}
        )

    def policy_scalars(self, theta: Tensor) -> dict[str, float]:
        """``{"routes": n}``: the number of distinct routes the policies ``theta: [K, 3K']``
        take at return ≥ 0.9 (``routes_found``), the measure of the paper's Figure 3."""
        return {"routes": float(len(self.routes_found(theta)))}

    def describe_policy_set(self, theta: Tensor) -> str:
        """E.g. ``3 of the 8 routes at return ≥ 0.9: below / near / above; …`` for the
        policies ``theta: [K, 3K']``."""
        found = self.routes_found(theta)
        total = math.prod(self.num_alternatives)
        names = "; ".join(self.route_name(route) for route in found)
        return f"{len(found)} of the {total} routes at return ≥ {FOUND_RETURN:g}" + (
            f": {names}" if found else ""
        )

    def plot_policies(self, theta: Tensor, labels: Sequence[str] | None = None, title=None):
        """A 3-D matplotlib figure of the end-effector paths the arm makes for the policies
        ``theta: [K, 3K']``, with the viapoints (one colour per pass time), start and target.

        ``labels`` (one per policy) replace the default legend entries (route and return);
        ``title`` replaces the default title (the arm and the number of policies).

        The figure is sized for a TensorBoard image card, which scales an image down to the
        card's width: 440 px wide (4.4 in at 100 dpi), the 3-D box zoomed to fill the axes,
        a few ticks per axis, and the legend below the axes (paths in the left column,
        viapoints, obstacle, start and target in the right one), the figure growing
        downwards with the number of entries. It is a bare
        ``matplotlib.figure.Figure`` on the Agg canvas (no pyplot state, no display):
        TensorBoard's ``add_figure`` renders and closes it, or call ``plt.close(figure)`` /
        drop the reference.
        """
        from dipole_torch.tasks.viapoint_figure import paths_figure

        return paths_figure(self, theta, labels, title)


def _make_kinematics(
    name: str,
    urdf: str | Path,
    end_effector: str,
    base_link: str | None,
    joint_lower: Sequence[float] | None,
    joint_upper: Sequence[float] | None,
    factory: dict,
) -> ArmKinematics:
    """The arm's kinematics: ``"pytorch_kinematics"`` (any URDF) or ``"wam_dh"`` (the WAM's
    analytic fast path, which needs the bundled WAM URDF, ``wam_tool`` and ``wam_base``)."""
    if name == "pytorch_kinematics":
        return ArmKinematics(urdf, end_effector, base_link, joint_lower, joint_upper, **factory)
    if name == "wam_dh":
        if (
            resolve_urdf_path(urdf) != URDF_PATH.resolve()
            or end_effector != END_EFFECTOR_LINK
            or base_link not in (None, "wam_base")
        ):
            raise ValueError(
                f"kinematics='wam_dh' is the analytic fast path of the bundled WAM only "
                f"(urdf {URDF_PATH}, end_effector {END_EFFECTOR_LINK!r}); got urdf {urdf!r}, "
                f"end_effector {end_effector!r}, base_link {base_link!r}: use "
                "kinematics='pytorch_kinematics' for other arms"
            )
        return WamKinematics(joint_lower=joint_lower, joint_upper=joint_upper, **factory)
    raise ValueError(f"kinematics must be one of {', '.join(KINEMATICS)}, got {name!r}")


def _plain(value):
    """Nested sequences and mappings (e.g. Hydra's ``ListConfig``, ``DictConfig``) as nested
    Python lists and dicts."""
    if isinstance(value, Mapping):
        return {key: _plain(item) for key, item in value.items()}
    if isinstance(value, (str, bytes, Tensor, np.ndarray)) or not hasattr(value, "__iter__"):
        return value
    return [_plain(item) for item in value]


# Attractor coordinates beyond this many metres from the origin are taken at it: far beyond
# any arm's reach, and the spring of a rollout from 1e36 m overflows float32 (and from
# 1e300 m float64) into NaN returns.
ATTRACTOR_LIMIT = 1e3


def _within_reach(theta: Tensor) -> Tensor:
    """``theta: [B, 3K]`` with every attractor coordinate within ±``ATTRACTOR_LIMIT``."""
    return theta.clamp(-ATTRACTOR_LIMIT, ATTRACTOR_LIMIT)


def _array(tensor: Tensor) -> np.ndarray:
    """A tensor as a float64 numpy array on the CPU."""
    return tensor.detach().cpu().double().numpy()


def _format_point(point: Tensor | np.ndarray) -> str:
    """``[0.5, -0.35, 0]``: a point for a message, 4 significant digits (no float32 noise)."""
    return "[" + ", ".join(format_value(x) for x in point.tolist()) + "]"


def _point(value: Sequence[float], name: str, factory: dict) -> Tensor:
    try:
        point = torch.as_tensor(value, **factory)
    except (TypeError, ValueError, RuntimeError):
        point = None  # ragged or not numbers
    if point is None or point.shape != (3,) or not torch.isfinite(point).all():
        raise ValueError(f"{name} must be a finite [x, y, z] point (m), got {value!r}")
    return point


def _radius(value: float, name: str) -> float:
    """A finite positive real scalar as a float: a Python number, a NumPy scalar or a 0-d
    tensor or array, as a point's coordinates may be tensors (a bool is refused: a mistake,
    not 1 m)."""
    try:
        scalar = torch.as_tensor(value)  # its kind and shape; float(value) keeps a float64
    except (TypeError, ValueError, RuntimeError):
        scalar = None  # not a number
    if (
        scalar is None
        or scalar.shape != ()
        or scalar.dtype == torch.bool
        or scalar.is_complex()
        or not (math.isfinite(float(value)) and float(value) > 0)
    ):
        raise ValueError(f"{name} must be a finite positive number (m), got {value!r}")
    return float(value)


def _alternatives(value: Sequence[Sequence[float]], index: int, factory: dict) -> Tensor:
    """``[A, 3]``: the alternatives ``viapoints[index]``, checked one point at a time so that
    an error names the point."""
    layout = "(viapoints: per pass time, a list of >= 1 alternative [x, y, z] points)"
    if isinstance(value, str) or not hasattr(value, "__len__") or len(value) == 0:
        raise ValueError(
            f"viapoints[{index}] must be a list of alternatives, got {value!r} {layout}"
        )
    points = [_point(point, f"viapoints[{index}][{a}]", factory) for a, point in enumerate(value)]
    return torch.stack(points)

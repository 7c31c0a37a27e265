"""What a robot reports and the contract it passes (the common part of ``activetouch.protocol``, whose docstring is
the overview): :class:`SensorFrame` and its parts (:class:`ArmState`, :class:`MotionLog`: the grasp tasks;
:class:`DepthView`: the clutter tasks), the ``semantics`` / ``source`` constants, :class:`ProtocolError`, the
rummaging tasks' :class:`EeDeltaCommand`, the :class:`Robot` protocol, :func:`check_frame` and :func:`check_robot`,
and the helpers the task parts share (command validation, poses, the end-effector state of a frame).

Conventions (docs/INTERFACES.md): metres, radians, world frame = the robot base frame with z up; poses are
``(4, 4)`` homogeneous object/end-effector -> world transforms.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Protocol, runtime_checkable

import numpy as np

#: ``SensorFrame.semantics`` values (chsel.SemanticsClass, ``activetouch.observations.Semantics``).
SURFACE, FREE, OCCUPIED = 0, 1, 2
#: ``SensorFrame.source`` values: a camera / depth sensor; touch (tactile pads, and the free space the robot's
#: own body swept); prior knowledge of the scene (e.g. free points under the table top, the box tasks).
CAMERA, TOUCH, PRIOR = 0, 1, 2


class ProtocolError(ValueError):
    """A robot broke the protocol (a frame with a wrong shape, a non-finite value, a non-rigid pose, ...)."""


@dataclasses.dataclass(frozen=True)
class ArmState:
    """The arm's state beyond ``SensorFrame.joint_positions`` at the frame's instant: what a model (a simulator used
    as one) needs to start a prediction where the arm is (the grasp tasks' particle rollouts of the next motion,
    touch paper Sec. V-A, and its plan, ``GraspEnv.plan_poke``). ``n`` arm joints, ``g`` gripper fingers.

    Attributes:
        joint_velocities: ``(n,)`` arm joint velocities (rad/s).
        gripper_positions: ``(g,)`` finger positions (m, each finger's slide from closed).
        gripper_velocities: ``(g,)`` finger velocities (m/s).
        command: ``(n + g,)`` the position setpoints the controllers hold (arm joints, then fingers).
        solver_warmstart: ``(n + g,)`` simulation only: the physics solver's warm start of the arm's and fingers'
            dofs, so the model replays the simulated arm bit for bit; a real arm leaves None (the model's solver
            then starts cold).
    """

    joint_velocities: np.ndarray
    gripper_positions: np.ndarray
    gripper_velocities: np.ndarray
    command: np.ndarray
    solver_warmstart: np.ndarray | None = None


@dataclasses.dataclass(frozen=True)
class MotionLog:
    """What the arm logged at its control rate during one guarded motion (a :class:`GuardedMoveCommand`): ``S``
    control periods, ``K'`` observations (touch paper App. D-a, D-b). The motion starts where the previous frame
    left the arm.

    Attributes:
        command: ``(S, n + g)`` the position setpoints sent each period (arm joints, then fingers): what a model
            replays for the particles.
        contact: ``(S,)`` bool, the binary contact signal of each period (App. D-a): the norm of the external
            torques of joints 1-5 above the robot's contact threshold (false positives from sensor noise, false
            negatives on light contacts included).
        contact_torque: ``(S,)`` that norm (N m).
        ee_force: ``(S,)`` the end-effector contact force estimated from the external torques (N), the guard's input.
        observed: ``(K',)`` int, strictly increasing: the periods at which the arm took an observation (each
            via-point reached; on a guarded stop the trigger's period and the end of the hold after it).
        joint_positions: ``(K'+1, n)`` measured arm joints at the start and at each observation.
        ee: ``(K'+1, 4)`` measured end effector ``[x, y, z, yaw]`` (gripper pointing down) at the same instants.
        stopped: the guard stopped the motion (App. D-b).
        true_contact: ``(S,)`` bool, simulation only: whether the robot touched anything in each period (for
            measuring the signal's error rates); None on a real arm.
    """

    command: np.ndarray
    contact: np.ndarray
    contact_torque: np.ndarray
    ee_force: np.ndarray
    observed: np.ndarray
    joint_positions: np.ndarray
    ee: np.ndarray
    stopped: bool
    true_contact: np.ndarray | None = None

    @property
    def num_observations(self) -> int:
        return int(len(self.observed))


@dataclasses.dataclass(frozen=True)
class DepthView:
    """One segmented depth image: what a :class:`ViewCommand` returns (the clutter tasks; visuo-tactile paper
    Sec. II-D-1; Sec. II-B's declutter graph is built on its segmentation). ``H x W`` pixels, row-major.

    Attributes:
        camera_pose: ``(4, 4)`` camera -> world pose of the image taken, OpenCV axes (x right, y down, z forward:
            the optical axis).
        intrinsics: ``(3, 3)`` pinhole ``K = [[fx, 0, cx], [0, fy, cy], [0, 0, 1]]`` (pixels).
        points: ``(H, W, 3)`` world point of each pixel's depth return (the depth image back-projected with
            ``intrinsics`` and ``camera_pose``), NaN where the ray returned nothing.
        labels: ``(H, W)`` int object label of each pixel from the robot's segmenter (the simulator: MuJoCo's geom
            ids), ``-1`` = no object (table, robot, background). A label names one object for the whole episode
            (instance tracking across views): :class:`PushCommand` and :class:`PickCommand` name their object by it.
        target_label: the label of the target object.
        max_depth: the sensor's range (m): a ray without a return is free up to it (the occupancy grid, Eq. 22).
    """

    camera_pose: np.ndarray
    intrinsics: np.ndarray
    points: np.ndarray
    labels: np.ndarray
    target_label: int
    max_depth: float

    @property
    def shape(self) -> tuple[int, int]:
        """``(H, W)``."""
        return tuple(np.shape(self.labels))

    @property
    def target_points(self) -> np.ndarray:
        """``(N, 3)`` the returns of the target's pixels (row-major, NaN pixels left out)."""
        pts = np.asarray(self.points)[np.asarray(self.labels) == self.target_label]
        return pts[np.isfinite(pts).all(1)]


@dataclasses.dataclass(frozen=True)
class SensorFrame:
    """What a robot reports at one instant: after ``reset()``, an ``act()`` or an ``observe()``.

    Attributes:
        stamp: time of the frame (s, the robot's clock; strictly increasing over an episode).
        ee_pose: ``(4, 4)`` end-effector (tool centre point) pose.
        joint_positions: ``(n,)`` arm joint angles (rad).
        joint_torques: ``(n,)`` external joint torques (N m): the torque the environment exerts on each joint
            (a real arm's estimate from its torque sensors minus its dynamics model; the simulator's contact
            constraint forces). The touch paper's contact signal is thresholded from joints 1-5.
        points: ``(N, 3)`` labelled points new since the previous frame (camera and touch), world frame.
        semantics: ``(N,)`` int: SURFACE (on the object), FREE (not in the object), OCCUPIED (inside it).
        source: ``(N,)`` int: CAMERA, TOUCH or PRIOR.
        in_contact: the tactile sensors touched the object since the previous frame (or touch it now).
        object_motion: ``(4, 4)`` world-frame object motion since the previous frame (``T_new = dT @ T_old``)
            when the robot can measure it (simulation, motion capture), else None (methods then estimate it:
            RUMI's ObjMove, ``--estimate-dT``).
        object_pose: ``(4, 4)`` ground-truth object pose for evaluation only (simulation, motion capture, the
            paper's overhead camera), never read by an estimator or planner; None when unknown.
        arm: the rest of the arm's state (:class:`ArmState`); the grasp tasks need it, None elsewhere.
        motion: the control-rate log of the :class:`GuardedMoveCommand` this frame ends (:class:`MotionLog`); None
            for other frames.
        grasp_success: the outcome of the :class:`GraspCommand` this frame ends (the object came up with the
            gripper) or of the :class:`PickCommand` (the object was grasped, verified by contact, and set down
            outside the workspace); None for other frames.
        view: the segmented depth image of the :class:`ViewCommand` this frame ends (:class:`DepthView`); None for
            other frames. ``points`` then holds the target's returns (``view.target_points``: SURFACE, CAMERA).
        contact_label: the label (``view.labels``' numbering) of the object a :class:`TouchCommand` or
            :class:`PushCommand` touched first, or that a :class:`PickCommand` held; ``-1``: none; None for other
            frames. A touch that ended on the target reports its contact points in ``points`` (SURFACE, TOUCH) and
            ``in_contact``.
        push_success: the outcome of the :class:`PushCommand` this frame ends (the object moved away from the
            target); None for other frames.
    """

    stamp: float
    ee_pose: np.ndarray
    joint_positions: np.ndarray
    joint_torques: np.ndarray
    points: np.ndarray
    semantics: np.ndarray
    source: np.ndarray
    in_contact: bool
    object_motion: np.ndarray | None = None
    object_pose: np.ndarray | None = None
    arm: ArmState | None = None
    motion: MotionLog | None = None
    grasp_success: bool | None = None
    view: DepthView | None = None
    contact_label: int | None = None
    push_success: bool | None = None

    @property
    def contacts(self) -> np.ndarray:
        """``(K, 3)`` surface points sensed by touch (the tactile contact points)."""
        return self.points[(self.semantics == SURFACE) & (self.source == TOUCH)]


@dataclasses.dataclass(frozen=True)
class EeDeltaCommand:
    """An end-effector motion (the rummaging tasks' action, RUMI Table I): ``u`` in ``[-1, 1]^Nu``, planar
    ``[dx, dy, dyaw]`` or 3-D ``[dx, dy, dz, dyaw]``, one unit = the task's ``translation_scale`` (m) /
    ``rotation_scale`` (rad). The robot moves the end effector there (quasi-statically, in small increments),
    lets the scene settle and reports what it sensed on the way."""

    u: np.ndarray


def _command_array(x, shape: tuple, name: str) -> np.ndarray:
    """``x`` as a read-only float64 copy of ``shape`` (``-1``: any length >= 1), finite; ProtocolError otherwise."""
    try:
        a = np.array(x, dtype=np.float64)
    except (TypeError, ValueError):
        raise ProtocolError(f"{name} must be a numeric array, got {type(x).__name__}") from None
    if a.ndim != len(shape) or any(w != -1 and w != d for w, d in zip(shape, a.shape)) or a.size == 0:
        want = "(" + ", ".join("K" if w == -1 else str(w) for w in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ProtocolError(f"{name} must have shape {want}{' with K >= 1' if -1 in shape else ''}, got {a.shape}")
    if not np.isfinite(a).all():
        raise ProtocolError(f"{name} must be finite")
    a.flags.writeable = False
    return a


@runtime_checkable
class Robot(Protocol):
    """A robot the episode loop can drive (simulated or real). Every call blocks until its frame is ready."""

    def reset(self) -> SensorFrame:
        """Go to the start configuration and take the first look (camera points, tactile reading)."""

    def observe(self) -> SensorFrame:
        """Read the sensors now without moving: pose, joints, torques, contact (new points may be empty)."""

    def act(self, command) -> SensorFrame:
        """Execute ``command`` and return what was sensed during and after it: an :class:`EeDeltaCommand` (the
        rummaging tasks), a :class:`GuardedMoveCommand` / :class:`GraspCommand` (the grasp tasks) or a
        :class:`ViewCommand` / :class:`TouchCommand` / :class:`PushCommand` / :class:`PickCommand` (the clutter
        tasks); a command the robot does not execute raises :class:`ProtocolError`."""


def _pose(x, name: str) -> np.ndarray:
    T = np.asarray(x, dtype=np.float64)
    if T.shape != (4, 4) or not np.isfinite(T).all():
        raise ProtocolError(f"{name} must be a finite (4, 4) pose, got shape {T.shape}")
    R = T[:3, :3]
    if not np.allclose(R @ R.T, np.eye(3), atol=1e-4) or abs(np.linalg.det(R) - 1.0) > 1e-4 \
            or not np.allclose(T[3], [0, 0, 0, 1]):
        raise ProtocolError(f"{name} is not a rigid transform")
    return T


def check_frame(frame: SensorFrame, n_joints: int | None = None) -> SensorFrame:
    """Raise :class:`ProtocolError` naming the first problem of ``frame``; return it."""
    if not isinstance(frame, SensorFrame):
        raise ProtocolError(f"a robot must return a SensorFrame, got {type(frame).__name__}")
    if not math.isfinite(float(frame.stamp)):
        raise ProtocolError(f"stamp must be finite, got {frame.stamp!r}")
    _pose(frame.ee_pose, "ee_pose")
    q, tau = np.asarray(frame.joint_positions), np.asarray(frame.joint_torques)
    if q.ndim != 1 or tau.shape != q.shape or not (np.isfinite(q).all() and np.isfinite(tau).all()):
        raise ProtocolError(f"joint_positions and joint_torques must be finite (n,) arrays of one n, got "
                            f"{q.shape} and {tau.shape}")
    if n_joints is not None and q.shape[0] != n_joints:
        raise ProtocolError(f"the robot reported {q.shape[0]} joints, earlier {n_joints}")
    p, s, src = np.asarray(frame.points), np.asarray(frame.semantics), np.asarray(frame.source)
    if p.ndim != 2 or p.shape[1] != 3 or not np.isfinite(p).all():
        raise ProtocolError(f"points must be a finite (N, 3) array, got shape {p.shape}")
    if s.shape != (p.shape[0],) or src.shape != (p.shape[0],):
        raise ProtocolError(f"semantics and source must be (N,) = ({p.shape[0]},), got {s.shape} and {src.shape}")
    if len(s) and not np.isin(s, (SURFACE, FREE, OCCUPIED)).all():
        raise ProtocolError("semantics must be SURFACE (0), FREE (1) or OCCUPIED (2)")
    if len(src) and not np.isin(src, (CAMERA, TOUCH, PRIOR)).all():
        raise ProtocolError("source must be CAMERA (0), TOUCH (1) or PRIOR (2)")
    if frame.object_motion is not None:
        _pose(frame.object_motion, "object_motion")
    if frame.object_pose is not None:
        _pose(frame.object_pose, "object_pose")
    n = q.shape[0]
    width = None  # n + g: the arm's and the gripper's setpoints
    if frame.arm is not None:
        width = _check_arm(frame.arm, n)
    if frame.motion is not None:
        _check_motion(frame.motion, n, width)
    if frame.grasp_success is not None and not isinstance(frame.grasp_success, (bool, np.bool_)):
        raise ProtocolError(f"grasp_success must be a bool or None, got {frame.grasp_success!r}")
    if frame.push_success is not None and not isinstance(frame.push_success, (bool, np.bool_)):
        raise ProtocolError(f"push_success must be a bool or None, got {frame.push_success!r}")
    c = frame.contact_label
    if c is not None and (isinstance(c, (bool, np.bool_)) or not isinstance(c, (int, np.integer)) or c < -1):
        raise ProtocolError(f"contact_label must be an object label >= 0, -1 (none) or None, got {c!r}")
    if frame.view is not None:
        _check_view(frame.view)
    return frame


def _check_view(view: DepthView) -> None:
    """Validate a :class:`DepthView` (shapes, a rigid camera pose, a pinhole K, labels >= -1, returns finite or NaN)."""
    if not isinstance(view, DepthView):
        raise ProtocolError(f"view must be a DepthView, got {type(view).__name__}")
    _pose(view.camera_pose, "view.camera_pose")
    K = np.asarray(view.intrinsics)
    if K.shape != (3, 3) or not (np.issubdtype(K.dtype, np.number) and np.isfinite(K).all()) \
            or K[0, 1] != 0 or K[1, 0] != 0 or (K[2] != (0, 0, 1)).any() or not (K[0, 0] > 0 and K[1, 1] > 0):
        raise ProtocolError("view.intrinsics must be a finite [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0")
    lab = np.asarray(view.labels)
    if lab.ndim != 2 or lab.size == 0 or not np.issubdtype(lab.dtype, np.integer):
        raise ProtocolError(f"view.labels must be a non-empty (H, W) int array, got shape {lab.shape} "
                            f"dtype {lab.dtype}")
    if (lab < -1).any():
        raise ProtocolError("view.labels must be object labels >= 0 or -1 (no object)")
    H, W = lab.shape
    _finite(view.points, (H, W, 3), "view.points", dtype=None)
    pts = np.asarray(view.points)
    if not np.issubdtype(pts.dtype, np.floating) or np.isinf(pts).any():
        raise ProtocolError("view.points must be float, finite or NaN (no return)")
    t = view.target_label
    if isinstance(t, (bool, np.bool_)) or not isinstance(t, (int, np.integer)) or t < 0:
        raise ProtocolError(f"view.target_label must be an object label (an int >= 0), got {t!r}")
    d = view.max_depth
    if isinstance(d, bool) or not isinstance(d, (int, float, np.floating, np.integer)) \
            or not (math.isfinite(float(d)) and float(d) > 0):
        raise ProtocolError(f"view.max_depth must be a finite range > 0 (m), got {d!r}")


def _finite(x, shape: tuple, name: str, dtype=np.float64) -> np.ndarray:
    """``x`` as an array of exactly ``shape`` (None entries: any size), finite; ProtocolError otherwise."""
    a = np.asarray(x)
    if a.ndim != len(shape) or any(w is not None and w != d for w, d in zip(shape, a.shape)):
        want = "(" + ", ".join("?" if w is None else str(w) for w in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ProtocolError(f"{name} must have shape {want}, got {a.shape}")
    if dtype is None:  # shape only (the caller checks the values)
        pass
    elif dtype is bool:
        if a.size and a.dtype != np.bool_:
            raise ProtocolError(f"{name} must be a bool array, got dtype {a.dtype}")
    elif dtype is int:
        if a.size and not np.issubdtype(a.dtype, np.integer):
            raise ProtocolError(f"{name} must be an int array, got dtype {a.dtype}")
    elif not (np.issubdtype(a.dtype, np.number) and np.isfinite(a).all()):
        raise ProtocolError(f"{name} must be finite numbers")
    return a


def _check_arm(arm: ArmState, n: int) -> int:
    """Validate an :class:`ArmState` of an ``n``-joint arm; returns ``n + g``."""
    if not isinstance(arm, ArmState):
        raise ProtocolError(f"arm must be an ArmState, got {type(arm).__name__}")
    _finite(arm.joint_velocities, (n,), "arm.joint_velocities")
    g = _finite(arm.gripper_positions, (None,), "arm.gripper_positions").shape[0]
    _finite(arm.gripper_velocities, (g,), "arm.gripper_velocities")
    _finite(arm.command, (n + g,), "arm.command")
    if arm.solver_warmstart is not None:
        _finite(arm.solver_warmstart, (n + g,), "arm.solver_warmstart")
    return n + g


def _check_motion(log: MotionLog, n: int, width: int | None) -> None:
    """Validate a :class:`MotionLog` of an ``n``-joint arm (``width`` = n + g when the frame's arm says it)."""
    if not isinstance(log, MotionLog):
        raise ProtocolError(f"motion must be a MotionLog, got {type(log).__name__}")
    S = _finite(log.command, (None, width), "motion.command").shape[0]
    if S < 1:
        raise ProtocolError("motion.command is empty: a motion has at least one control period")
    _finite(log.contact, (S,), "motion.contact", dtype=bool)
    _finite(log.contact_torque, (S,), "motion.contact_torque")
    _finite(log.ee_force, (S,), "motion.ee_force")
    obs = _finite(log.observed, (None,), "motion.observed", dtype=int)
    if len(obs) and (obs[0] < 0 or obs[-1] >= S or (np.diff(obs) <= 0).any()):
        raise ProtocolError(f"motion.observed must increase strictly within [0, {S}), got {obs.tolist()}")
    _finite(log.joint_positions, (len(obs) + 1, n), "motion.joint_positions")
    _finite(log.ee, (len(obs) + 1, 4), "motion.ee")
    if not isinstance(log.stopped, (bool, np.bool_)):
        raise ProtocolError(f"motion.stopped must be a bool, got {log.stopped!r}")
    if log.true_contact is not None:
        _finite(log.true_contact, (S,), "motion.true_contact", dtype=bool)


def _check_answer(command, frame: SensorFrame) -> SensorFrame:
    """Raise :class:`ProtocolError` when ``frame`` (valid) lacks what ``command`` reports; return it."""
    # the task parts' commands, imported here: .grasp and .clutter import this module
    from .clutter import PickCommand, PushCommand, TouchCommand, ViewCommand
    from .grasp import GraspCommand, GuardedMoveCommand

    name = type(command).__name__
    if isinstance(command, GuardedMoveCommand) and frame.motion is None:
        raise ProtocolError("the frame of a GuardedMoveCommand must carry its MotionLog (motion)")
    if isinstance(command, ViewCommand) and frame.view is None:
        raise ProtocolError("the frame of a ViewCommand must carry its DepthView (view)")
    if isinstance(command, (TouchCommand, PushCommand, PickCommand)) and frame.contact_label is None:
        raise ProtocolError(f"the frame of a {name} must report contact_label (-1: no contact)")
    if isinstance(command, PushCommand) and frame.push_success is None:
        raise ProtocolError("the frame of a PushCommand must report push_success")
    if isinstance(command, (GraspCommand, PickCommand)) and frame.grasp_success is None:
        raise ProtocolError(f"the frame of a {name} must report grasp_success")
    return frame


def check_robot(robot, command_dim: int | None = None, steps: int = 2, command=None) -> list[SensorFrame]:
    """The contract every :class:`Robot` passes: ``reset``, ``observe`` and ``steps`` "do nothing" ``act`` calls
    return valid frames with strictly increasing stamps and a fixed joint count; an ``observe`` does not move the
    end effector. Returns the frames (reset first). Raises :class:`ProtocolError`.

    The "do nothing" command is a zero :class:`EeDeltaCommand` of ``command_dim`` (the rummaging tasks), or
    ``command(last_frame)`` (the grasp tasks: ``command=GuardedMoveCommand.stay``; the clutter tasks: a
    :class:`ViewCommand`, which moves only the camera). A frame answering a command carries what that command
    reports (:func:`_check_answer`: a :class:`GuardedMoveCommand` its :class:`MotionLog`, a :class:`ViewCommand` its
    :class:`DepthView`, ...), and every frame of a robot whose reset frame carries an :class:`ArmState` must carry
    one."""
    if command is None and command_dim is None:
        raise ValueError("check_robot needs command_dim (an EeDeltaCommand robot) or command (frame -> command)")
    if not isinstance(robot, Robot):
        raise ProtocolError(f"{type(robot).__name__} lacks reset(), observe() or act()")
    frames = [check_frame(robot.reset())]
    n = len(frames[0].joint_positions)
    has_arm = frames[0].arm is not None
    seen = check_frame(robot.observe(), n)
    if not np.allclose(seen.ee_pose, frames[0].ee_pose, atol=1e-3):
        raise ProtocolError("observe() moved the end effector by more than 1 mm")
    frames.append(seen)
    for _ in range(steps):
        cmd = EeDeltaCommand(np.zeros(command_dim)) if command is None else command(frames[-1])
        frame = _check_answer(cmd, check_frame(robot.act(cmd), n))
        frames.append(frame)
    if has_arm and any(f.arm is None for f in frames):
        raise ProtocolError("the reset frame carries an ArmState: every frame must")
    stamps = [f.stamp for f in frames]
    if any(b <= a for a, b in zip(stamps, stamps[1:])):
        raise ProtocolError(f"stamps must increase strictly, got {stamps}")
    return frames


def _ee_state(frame: SensorFrame) -> np.ndarray:
    """``[x, y, z, yaw] (4,)`` of ``frame.ee_pose`` (the grasp tasks' end-effector parameterisation)."""
    from activetouch.sim.robot import ee_state_from_pose

    T = np.asarray(frame.ee_pose, dtype=np.float64)
    return ee_state_from_pose(T[:3, 3], T[:3, :3])

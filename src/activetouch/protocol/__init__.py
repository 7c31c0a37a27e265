"""The robot / sensor protocol: what a robot (simulated or real) gives the episode loop, and what it takes.

A robot implements :class:`Robot`: ``reset()``, ``observe()`` and ``act(command)``, each returning a
:class:`SensorFrame`. :class:`activetouch.sim.sim_robot.SimRobot` implements it on the MuJoCo rummaging tasks;
a real arm implements the same three methods on its drivers (docs/ROBOT.md walks through it).
:class:`RobotEnv` turns any :class:`Robot` back into the environment the one episode loop runs
(``reset() -> (obs, info)``, ``step(u) -> (obs, r, terminated, truncated, info)`` and the task geometry the
planners read), so every method registered for the rummaging tasks (RUMI, its ablations, GPVR, Slide,
tiqf-slide) runs on it unchanged; :func:`check_robot` is the contract a robot must pass (as gymnasium's
``check_env`` is for environments).

The touch-only grasp tasks (``grasp-box-*``, the touch paper) run through the same three calls with two more
commands, :class:`GuardedMoveCommand` (a guarded poke through end-effector via-points) and :class:`GraspCommand`
(the grasp primitive), and frames that carry the arm's full state (:class:`ArmState`), the control-rate log of the
motion (:class:`MotionLog`: the binary contact signal, the guard) and the grasp's outcome. :class:`GraspRobotEnv`
turns such a robot back into the grasp environment the loop runs; its estimator and planner still predict with a
*model* (a ``GraspEnv`` used only for particle rollouts, IK, grasp simulation, robot surface points and reach),
whose own object is never read. :class:`activetouch.sim.sim_grasp_robot.SimGraspRobot` implements it.

The visuo-tactile clutter tasks (``clutter-*``, the visuo-tactile paper) run through the same three calls with four
more commands: :class:`ViewCommand` (move the depth camera to a view pose, Sec. II-D-1), :class:`PushCommand` and
:class:`PickCommand` (the declutter actions, Sec. II-B) and :class:`TouchCommand` (a guarded touch, Sec. II-D-2);
a view's frame carries the segmented depth image (:class:`DepthView`: the organised point cloud, per-pixel object
labels from the robot's segmenter and which label is the target), a touch's frame the contact points and the label
of the object touched, a push's or pick's frame its outcome. :class:`ClutterRobotEnv` turns such a robot back into
the clutter environment the loop runs; the clutter planners make no model queries (they predict on their own
occupancy grid and on the target's mesh), so it needs no model environment, only the task knowledge (the task spec's
camera model and view hemisphere, the target's mesh, the gripper's size). :func:`detection_prior` is the tasks'
prior around the robot's coarse detection of the target instead of the simulator's truth.
:class:`activetouch.sim.sim_clutter_robot.SimClutterRobot` implements it.

The episode log (``episode.h5``) records the observations the loop saw, so
a real robot's episodes replay offline with ``activetouch replay`` like simulated ones.

Conventions (docs/INTERFACES.md): metres, radians, world frame = the robot base frame with z up; poses are
``(4, 4)`` homogeneous object/end-effector -> world transforms.
"""
from __future__ import annotations

import dataclasses
import math
from typing import Any, Protocol, runtime_checkable

import numpy as np
import torch

from activetouch.sim.camera import PinholeCamera
from activetouch.sim.env import TaskGeometry

__all__ = ["SensorFrame", "EeDeltaCommand", "GuardedMoveCommand", "GraspCommand", "ViewCommand", "TouchCommand",
           "PushCommand", "PickCommand", "ArmState", "MotionLog", "DepthView", "PosedCamera", "Robot", "RobotEnv",
           "GraspRobotEnv", "ClutterRobotEnv", "detection_prior", "check_frame", "check_robot", "ProtocolError",
           "CAMERA", "TOUCH", "PRIOR", "SURFACE", "FREE", "OCCUPIED"]

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


def _guard(x, name: str) -> float | None:
    if x is None:
        return None
    if isinstance(x, bool) or not isinstance(x, (int, float, np.floating, np.integer)) \
            or not (math.isfinite(float(x)) and float(x) > 0):
        raise ProtocolError(f"{name} must be a finite force > 0 (N) or None, got {x!r}")
    return float(x)


@dataclasses.dataclass(frozen=True)
class GuardedMoveCommand:
    """A guarded motion through end-effector via-points (the grasp tasks' poke; touch paper App. C, D-b).

    ``waypoints (K, 4)`` = ``[x, y, z, yaw]`` end-effector targets (world frame, metres / radians, gripper pointing
    down). The arm follows the straight path from via-point to via-point at its control rate (the simulator: at
    most 4 mm and 0.05 rad per 20 ms period, IK per period), reads the binary contact signal every period (App.
    D-a) and takes an observation at each via-point. Guarded motion (App. D-b): when the end-effector force
    estimated from the external joint torques rises by more than ``guard_force`` (N) above its lowest value in
    this motion, the arm stops, holds still for a moment, takes a last observation and the motion ends.
    ``guard_force`` None: the robot's own threshold (the simulator's ``GraspTaskSpec.guard_force``, 2.5 N).
    Via-points below the robot's lowest poke height are raised to it (the fingers stay clear of the table). The
    frame that ends it carries the :class:`MotionLog`."""

    waypoints: np.ndarray
    guard_force: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "waypoints", _command_array(self.waypoints, (-1, 4), "waypoints"))
        object.__setattr__(self, "guard_force", _guard(self.guard_force, "guard_force"))

    @classmethod
    def stay(cls, frame: SensorFrame) -> "GuardedMoveCommand":
        """One via-point where the end effector is in ``frame``: the grasp robots' "do nothing" command
        (``check_robot(robot, command=GuardedMoveCommand.stay)``)."""
        return cls(_ee_state(check_frame(frame))[None])


@dataclasses.dataclass(frozen=True)
class GraspCommand:
    """Grasp the object assumed at the SE(2) pose ``state (3,)`` = ``(x, y, yaw)`` (world, metres / radians) with
    the arm's grasp primitive (touch paper App. D-d): lift clear of the table, move above the object with the
    fingers across its narrow axis, open, descend (guarded: a contact force above ``guard_force`` N means a finger
    landed on the object and aborts the grasp; None: the robot's threshold), close, lift and hold. The frame that
    ends it reports ``grasp_success``; the episode ends with it."""

    state: np.ndarray
    guard_force: float | None = None

    def __post_init__(self):
        object.__setattr__(self, "state", _command_array(self.state, (3,), "grasp state"))
        object.__setattr__(self, "guard_force", _guard(self.guard_force, "guard_force"))


def _unit_vector(x, name: str) -> np.ndarray:
    """``x`` as a read-only finite ``(3,)`` float64 copy of norm 1 (within 1e-3, the clutter env's tolerance)."""
    a = _command_array(x, (3,), name)
    n = float(np.linalg.norm(a))
    if abs(n - 1.0) > 1e-3:
        raise ProtocolError(f"{name} must be a unit vector, got norm {n:.4f}")
    return a


def _positive(x, name: str) -> float:
    if isinstance(x, bool) or not isinstance(x, (int, float, np.floating, np.integer)) \
            or not (math.isfinite(float(x)) and float(x) > 0):
        raise ProtocolError(f"{name} must be a finite number > 0, got {x!r}")
    return float(x)


def _label(x, name: str) -> int:
    if isinstance(x, (bool, np.bool_)) or not isinstance(x, (int, np.integer)) or int(x) < 0:
        raise ProtocolError(f"{name} must be an object label (an int >= 0), got {x!r}")
    return int(x)


@dataclasses.dataclass(frozen=True)
class ViewCommand:
    """Move the depth camera so its optical centre is at ``position (3,)`` looking at ``look_at (3,)`` (world, m),
    take one depth image and segment it (visuo-tactile paper Sec. II-D-1; the declutter phase's overhead views,
    Sec. II-B). The image's roll is the look-at convention of ``sim.camera.PinholeCamera`` (image x horizontal,
    world z up): the full camera pose is :attr:`camera_pose`, what a real arm's IK or camera mount reaches for.
    The frame that ends it carries the :class:`DepthView` of the image taken (at the pose reached).

    SIMPLIFICATION (the simulator): the camera is a free-flying sensor on the view hemisphere and the arm parks out
    of view before each image; the paper's camera rides on a second arm."""

    position: np.ndarray
    look_at: np.ndarray

    def __post_init__(self):
        from activetouch.sim.camera import look_at

        p = _command_array(self.position, (3,), "ViewCommand.position")
        t = _command_array(self.look_at, (3,), "ViewCommand.look_at")
        object.__setattr__(self, "position", p)
        object.__setattr__(self, "look_at", t)
        if np.linalg.norm(p - t) < 1e-6:
            raise ProtocolError("ViewCommand.position and look_at coincide")
        try:
            look_at(p, t)
        except ValueError:
            raise ProtocolError("ViewCommand looks straight up or down: the image's roll is undefined") from None

    @property
    def camera_pose(self) -> np.ndarray:
        """``(4, 4)`` camera -> world pose to reach, OpenCV axes (x right, y down, z forward)."""
        from activetouch.sim.camera import look_at

        T = np.eye(4)
        T[:3, :3] = look_at(self.position, self.look_at)
        T[:3, 3] = self.position
        return T


@dataclasses.dataclass(frozen=True)
class TouchCommand:
    """A guarded touch (visuo-tactile paper Sec. II-D-2): bring the closed gripper to ``start (3,)`` (world, m;
    through a safe height above the pile, the pads' narrow edges leading along ``direction``), then move straight
    along the unit ``direction (3,)`` at touch speed for at most ``max_length`` m and stop at the first contact of
    the gripper with anything; retreat. The frame that ends it reports ``contact_label`` (the object touched first,
    ``-1``: none) and, when that is the target, ``in_contact`` and the tactile contact points on it (``points``:
    SURFACE, TOUCH; the paper's taxel positions). A contact on the way to ``start`` ends the touch too."""

    start: np.ndarray
    direction: np.ndarray
    max_length: float = 0.15

    def __post_init__(self):
        object.__setattr__(self, "start", _command_array(self.start, (3,), "TouchCommand.start"))
        object.__setattr__(self, "direction", _unit_vector(self.direction, "TouchCommand.direction"))
        object.__setattr__(self, "max_length", _positive(self.max_length, "TouchCommand.max_length"))


@dataclasses.dataclass(frozen=True)
class PushCommand:
    """Push object ``label`` (a label of the views' segmentation, not the target's) with the closed gripper
    (visuo-tactile paper Sec. II-B-1): from ``start (3,)`` straight along the unit ``direction (3,)`` by ``length``
    m, monitoring the contact with the object; a loss of contact stops the push. The frame that ends it reports
    ``push_success`` (the object moved away from the target) and ``contact_label`` (``label`` if the gripper
    touched it, else ``-1``)."""

    label: int
    start: np.ndarray
    direction: np.ndarray
    length: float = 0.10

    def __post_init__(self):
        object.__setattr__(self, "label", _label(self.label, "PushCommand.label"))
        object.__setattr__(self, "start", _command_array(self.start, (3,), "PushCommand.start"))
        object.__setattr__(self, "direction", _unit_vector(self.direction, "PushCommand.direction"))
        object.__setattr__(self, "length", _positive(self.length, "PushCommand.length"))


@dataclasses.dataclass(frozen=True)
class PickCommand:
    """Pick object ``label`` (a label of the views' segmentation, not the target's) and place it outside the
    workspace (visuo-tactile paper Sec. II-B-2): open to ``width`` m plus clearance, descend top-down (guarded:
    touching another object aborts) until the pads' tips are at ``position (3,)`` (world, m), close along the
    horizontal direction at ``closing_angle`` (rad, world x-y), verify the grasp by contact (both pads on the
    object), lift, set the object down outside the workspace. The frame that ends it reports ``grasp_success``
    (grasped and set down outside) and ``contact_label`` (``label`` if grasped, else ``-1``)."""

    label: int
    position: np.ndarray
    closing_angle: float
    width: float

    def __post_init__(self):
        object.__setattr__(self, "label", _label(self.label, "PickCommand.label"))
        object.__setattr__(self, "position", _command_array(self.position, (3,), "PickCommand.position"))
        a = self.closing_angle
        if isinstance(a, bool) or not isinstance(a, (int, float, np.floating, np.integer)) or not math.isfinite(a):
            raise ProtocolError(f"PickCommand.closing_angle must be a finite angle (rad), got {a!r}")
        object.__setattr__(self, "closing_angle", float(a))
        object.__setattr__(self, "width", _positive(self.width, "PickCommand.width"))


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


class RobotEnv(TaskGeometry):
    """The rummaging environment interface (``activetouch.sim.env.RummageEnv``'s) on top of any :class:`Robot`.

    Args:
        robot: a :class:`Robot`.
        spec: the task geometry the planners read (``activetouch.sim.tasks.TaskSpec``: action space, workspace,
            action scales, end-effector bounds, ``se2``, ``r_w``, ``max_steps``, ``nll_threshold``).
        obj: the known object (``activetouch.objects.KnownObject``).
        gripper_points: ``() -> (h (M, 3) ee frame, h_I mask (M,))`` (default: the simulated gripper's).

    Observations carry the frame's points as ``Features`` and ``info["true_pose"]`` = the frame's
    ``object_pose`` (the loop's metrics need it: a real robot without ground truth still runs the estimator and
    planner, but NLL, APC against the truth and the success criterion are then not defined).
    """

    def __init__(self, robot, spec, obj, gripper_points=None):
        if not isinstance(robot, Robot):
            raise ProtocolError(f"{type(robot).__name__} lacks reset(), observe() or act()")
        self.robot, self.spec, self.object = robot, spec, obj
        self._gripper_points = gripper_points
        self._step = 0
        self._frame: SensorFrame | None = None
        self._n_joints: int | None = None

    # action_scale, action_dim, gripper_points, target_ee, reachability: TaskGeometry (from self.spec)
    def gripper_points(self, spacing: float = 0.01):
        if self._gripper_points is not None:
            return self._gripper_points()
        return super().gripper_points(spacing)

    def ee_pose(self) -> np.ndarray:
        return np.asarray(self._frame.ee_pose, dtype=np.float64)

    def ee_state(self) -> np.ndarray:
        from activetouch.sim.robot import ee_state_from_pose

        T = self.ee_pose()
        return ee_state_from_pose(T[:3, 3], T[:3, :3])

    def true_pose(self) -> np.ndarray | None:
        return None if self._frame.object_pose is None else np.asarray(self._frame.object_pose)

    # -- the loop's calls
    def _obs(self, frame: SensorFrame):
        from activetouch.observations import Features
        from activetouch.sim.env import Observation

        check_frame(frame, self._n_joints)
        self._n_joints = len(frame.joint_positions)
        self._frame = frame
        feats = Features(torch.as_tensor(np.asarray(frame.points), dtype=torch.float32),
                         torch.as_tensor(np.asarray(frame.semantics), dtype=torch.long))
        dT = None if frame.object_motion is None else torch.as_tensor(np.asarray(frame.object_motion),
                                                                      dtype=torch.float32)
        obs = Observation(features=feats, ee_pose=torch.as_tensor(np.asarray(frame.ee_pose), dtype=torch.float32),
                          in_contact=bool(frame.in_contact), dT=dT)
        info: dict[str, Any] = {"step": self._step, "ee_state": self.ee_state(), "stamp": float(frame.stamp)}
        if frame.object_pose is not None:
            info["true_pose"] = torch.as_tensor(np.asarray(frame.object_pose), dtype=torch.float32)
        return obs, info

    def reset(self, seed: int | None = None):
        self._step = 0
        self._n_joints = None
        obs, info = self._obs(self.robot.reset())
        info["camera_surface_points"] = int(((self._frame.semantics == SURFACE) & (self._frame.source == CAMERA)).sum())
        return obs, info

    def step(self, action):
        if self._frame is None:
            raise RuntimeError("call reset() before step()")
        u = np.asarray(action, dtype=np.float64).reshape(-1)
        if u.shape != (self.action_dim,) or not np.isfinite(u).all():
            raise ValueError(f"action must be a finite ({self.action_dim},) array, got {np.shape(action)}")
        u = np.clip(u, -1.0, 1.0)
        target = self.target_ee(self.ee_state(), u)
        self._step += 1
        obs, info = self._obs(self.robot.act(EeDeltaCommand(u)))
        info["target_ee"] = target
        return obs, 0.0, False, self._step >= self.spec.max_steps, info


def _ee_state(frame: SensorFrame) -> np.ndarray:
    """``[x, y, z, yaw] (4,)`` of ``frame.ee_pose`` (the grasp tasks' end-effector parameterisation)."""
    from activetouch.sim.robot import ee_state_from_pose

    T = np.asarray(frame.ee_pose, dtype=np.float64)
    return ee_state_from_pose(T[:3, 3], T[:3, :3])


class GraspRobotEnv:
    """The blind-grasping environment interface (``activetouch.sim.grasp_env.GraspEnv``'s: the touch paper's
    ``grasp-box-*`` tasks) on top of any :class:`Robot`, with a *model* ``GraspEnv`` for the predictions.

    The loop's ``reset`` / ``step`` go to the robot: a ``PokeAction`` becomes a :class:`GuardedMoveCommand`, a
    ``GraspAction`` a :class:`GraspCommand`, and the frames become the ``TouchObservation`` the touch belief reads
    (the binary contact signal and the arm's joints at each observation, the executed setpoints for the rollouts).
    The model answers what the estimator and the planner compute rather than sense: the MuJoCo rollouts of the
    particles under an executed or planned motion (``rollout``), the IK chain of a planned poke (``plan_poke``,
    started from the robot's last frame), the grasp simulated on hypotheses (``grasp_success``), the robot's surface
    points (``robot_points``) and its reach (``reachable``). Each takes the particles' states or the robot's
    measured state as input: the model's own object (its ``MjData``'s box) is never read, and the model is never
    reset or stepped. A real arm needs the model as much as the simulator does: the touch belief's prediction and
    likelihood (Sec. V-A, Eq. 10) and the planner's expected information gain are computed on it.

    Args:
        robot: a :class:`Robot` that executes :class:`GuardedMoveCommand` and :class:`GraspCommand` and reports an
            :class:`ArmState` in every frame (``activetouch.sim.sim_grasp_robot.SimGraspRobot``; a real arm's driver).
        model: a ``GraspEnv`` of the robot's scene (arm, gripper, object, task spec) used only as a model; its spec
            gives the guard thresholds sent with the commands and the episode length.
        prior_means: ``(M, 3)`` SE(2) means of the prior mixture (App. D-c: where the object may stand), or a
            callable ``seed -> (M, 3)``; None: the simulated task's means for the reset's seed
            (``grasp_tasks.sample_task_instance`` on ``model.spec``).
        seed: default seed of ``reset`` (only the default prior uses it: the robot draws nothing).

    ``info["true_pose"]`` / ``info["true_state"]`` come from the frames' ``object_pose`` (evaluation only: the
    loop's metrics need them, no estimator or planner reads them); ``info`` has no ``true_mode``,
    ``object_states`` or ``object_height`` (the simulator's ground truth beyond the pose).
    """

    def __init__(self, robot, model, prior_means=None, seed: int = 0):
        if not isinstance(robot, Robot):
            raise ProtocolError(f"{type(robot).__name__} lacks reset(), observe() or act()")
        self.robot, self.model = robot, model
        self.spec, self.object, self.gripper = model.spec, model.object, model.gripper
        self.seed = int(seed)
        self._prior_means = prior_means
        self._frame: SensorFrame | None = None
        self._n_joints: int | None = None
        self._n_actions = 0
        self._terminated = False
        self._means = None

    @property
    def max_steps(self) -> int:
        """Episode length T for the episode loop: ``max_actions`` pokes and the grasp."""
        return self.model.max_steps

    # -- the model's answers (forwarded: each takes the states / motion it predicts for as input)
    def rollout(self, states, motion):
        """The model's object states ``(P, K, 3)`` after each waypoint of ``motion`` (an executed
        ``TouchObservation`` or a planned ``MotionPlan``) for particles ``states (P, 3)`` (``GraspEnv.rollout``)."""
        return self.model.rollout(states, motion)

    def rollout_detailed(self, states, motion):
        """``GraspEnv.rollout_detailed`` on the model: states ``(P, K, 3)``, simulated ``(P,)``, stop ``(P,)``."""
        return self.model.rollout_detailed(states, motion)

    def grasp_success(self, states, grasp_state):
        """``(P,)`` bool: the model's grasp planned for ``grasp_state (3,)`` lifts the box at ``states (P, 3)``."""
        return self.model.grasp_success(states, grasp_state)

    def grasp_plan(self, grasp_state):
        """The model's grasp primitive ``MotionPlan`` for the SE(2) pose ``grasp_state (3,)``."""
        return self.model.grasp_plan(grasp_state)

    def grasp_yaw(self, box_yaw: float) -> float:
        """End-effector yaw of the grasp of a box at ``box_yaw``."""
        return self.model.grasp_yaw(box_yaw)

    def robot_points(self, q, spacing: float = 0.01, opening=None):
        """The robot's surface points ``(K, M, 3)`` at arm joints ``q (K, 7)`` (the model's kinematics)."""
        return self.model.robot_points(q, spacing, opening)

    def reachable(self, points):
        """``(N,)`` bool: ee tip positions ``points (N, 3)`` in the arm's reach (the model's spec)."""
        return self.model.reachable(points)

    def ik_to_point(self, p, yaw: float, q0=None, restarts: int = 10):
        """Arm joints ``(7,)`` putting the ee tip at ``p (3,)`` with ``yaw`` (the model's IK)."""
        return self.model.ik_to_point(p, yaw, q0, restarts)

    def ik_error(self, q, p, yaw: float):
        """Position (m) and rotation (rad) error of ``q (7,)`` w.r.t. the ee goal ``(p (3,), yaw)``."""
        return self.model.ik_error(q, p, yaw)

    def fk(self, q):
        """ee ``[x, y, z, yaw] (4,)`` of arm joints ``q (7,)`` (the model's kinematics)."""
        return self.model.fk(q)

    def plan_from_joints(self, q_plan, opening: float | None = None):
        """A guarded ``MotionPlan`` through arm configurations ``q_plan (K+1, 7)`` from rest (the model's)."""
        return self.model.plan_from_joints(q_plan, opening)

    def plan_poke(self, waypoints, q0=None):
        """The motion the robot executes for ``GuardedMoveCommand(waypoints)`` from where its last frame left it
        (the model's IK chain; ``q0 (7,)``: from rest at ``q0`` instead), as a guarded ``MotionPlan``."""
        if q0 is not None:
            return self.model.plan_poke(waypoints, q0)
        f = self._require_frame()
        init, warm = self._physics_state(f)
        return self.model.plan_poke_at(waypoints, f.joint_positions, self.ee_state(), init, warm, f.arm.command)

    @property
    def rollout_stats(self) -> dict:
        """The model's counters of its last rollout."""
        return self.model.rollout_stats

    # -- the robot's state (its last frame)
    def current_q(self) -> np.ndarray:
        """Measured arm joints ``(n,)``."""
        return np.array(self._require_frame().joint_positions, dtype=np.float64)

    def ee_state(self) -> np.ndarray:
        """Measured end effector ``[x, y, z, yaw] (4,)`` of the last frame."""
        return _ee_state(self._require_frame())

    def true_pose(self) -> np.ndarray | None:
        """Ground-truth object pose ``(4, 4)`` of the last frame (evaluation only), None when unknown."""
        f = self._require_frame()
        return None if f.object_pose is None else np.asarray(f.object_pose, dtype=np.float64)

    def true_state(self) -> np.ndarray | None:
        """Ground-truth SE(2) state ``(x, y, yaw) (3,)`` of the last frame's ``object_pose`` (evaluation only)."""
        T = self.true_pose()
        return None if T is None else np.array([T[0, 3], T[1, 3], math.atan2(T[1, 0], T[0, 0])])

    def close(self) -> None:
        self.model.close()
        if hasattr(self.robot, "close"):
            self.robot.close()

    # -- the loop's calls
    def _require_frame(self) -> SensorFrame:
        if self._frame is None:
            raise RuntimeError("call reset() before step()")
        return self._frame

    def _accept(self, frame: SensorFrame) -> SensorFrame:
        check_frame(frame, self._n_joints)
        if frame.arm is None:
            raise ProtocolError("a grasp robot's frames must carry arm (ArmState): the model's predictions start there")
        self._n_joints = len(frame.joint_positions)
        return frame

    def _physics_state(self, f: SensorFrame):
        """The model's physics state and solver warm start of the arm in frame ``f`` (the object parked)."""
        a = f.arm
        return self.model.robot_physics_state(f.joint_positions, a.joint_velocities, a.gripper_positions,
                                              a.gripper_velocities, time=float(f.stamp), warmstart=a.solver_warmstart)

    def _observation(self, start: SensorFrame, log: MotionLog | None = None):
        """The ``TouchObservation`` of ``log`` (the motion that started at frame ``start``), or of no motion at
        ``start`` (reset, grasp: ``K' = 0``)."""
        from activetouch.sim.grasp_env import TouchObservation

        init, warm = self._physics_state(start)
        ctrl0 = np.array(start.arm.command, dtype=np.float64)
        if log is None:
            q = np.asarray(start.joint_positions, dtype=np.float64)[None].copy()
            return TouchObservation(
                z=np.zeros(0, bool), q=q, ee=_ee_state(start)[None], stopped_early=False, contact_force=0.0,
                tau_norm=np.zeros(0), ctrl=np.zeros((0, len(ctrl0))), seg_end=np.zeros(0, np.int64), init_state=init,
                warmstart=warm, ctrl0=ctrl0, z_period=np.zeros(0, np.int64), z_samples=np.zeros(0, bool),
                tau_samples=np.zeros(0), force_samples=np.zeros(0), true_contact_samples=np.zeros(0, bool))
        k = np.array(log.observed, dtype=np.int64)
        z = np.array(log.contact, dtype=bool)
        tau = np.array(log.contact_torque, dtype=np.float64)
        force = np.array(log.ee_force, dtype=np.float64)
        # a real arm does not know when it truly touched: all False (only benchmarks of the signal read it)
        true = np.zeros(len(z), bool) if log.true_contact is None else np.array(log.true_contact, dtype=bool)
        return TouchObservation(
            z=z[k], q=np.array(log.joint_positions, dtype=np.float64), ee=np.array(log.ee, dtype=np.float64),
            stopped_early=bool(log.stopped), contact_force=float(force.max()), tau_norm=tau[k],
            ctrl=np.array(log.command, dtype=np.float64), seg_end=k, init_state=init, warmstart=warm, ctrl0=ctrl0,
            z_period=k.copy(), z_samples=z, tau_samples=tau, force_samples=force, true_contact_samples=true)

    def _info(self, **extra) -> dict:
        f = self._require_frame()
        info: dict[str, Any] = {"prior_means": np.array(self._means, dtype=np.float64), "num_actions": self._n_actions,
                                "stamp": float(f.stamp)}
        if f.object_pose is not None:
            info["true_pose"] = torch.as_tensor(np.asarray(f.object_pose, dtype=np.float64)).to(torch.float32)
            info["true_state"] = self.true_state()
        info.update(extra)
        return info

    def reset(self, seed: int | None = None):
        """Reset the robot; returns an empty ``TouchObservation`` (``K' = 0``) and ``info`` with ``prior_means``
        and, when the robot reports ``object_pose``, ``true_pose (4, 4)`` float32 torch and ``true_state (3,)``."""
        seed = self.seed if seed is None else int(seed)
        if self._prior_means is None:
            from activetouch.sim.grasp_tasks import sample_task_instance

            means = sample_task_instance(self.spec, seed)[0]  # the task's prior; its truth is not kept
        else:
            means = self._prior_means(seed) if callable(self._prior_means) else self._prior_means
        means = np.asarray(means, dtype=np.float64)
        if means.ndim != 2 or means.shape[1] != 3 or len(means) == 0 or not np.isfinite(means).all():
            raise ValueError(f"prior_means must be a finite (M, 3) array of SE(2) means, got shape {means.shape}")
        self._means = means
        self._n_joints = None
        self._frame = self._accept(self.robot.reset())
        self._n_actions = 0
        self._terminated = False
        return self._observation(self._frame), self._info()

    def step(self, action):
        """Execute a ``PokeAction`` (as a :class:`GuardedMoveCommand` with the model's ``guard_force``) or a
        ``GraspAction`` (a :class:`GraspCommand` with its ``grasp_guard_force``); returns ``(obs, reward,
        terminated, truncated, info)`` as ``GraspEnv.step`` does."""
        from activetouch.sim.grasp_env import GraspAction, PokeAction

        start = self._require_frame()
        if self._terminated:
            raise RuntimeError("the episode has terminated (grasp done); call reset()")
        if isinstance(action, PokeAction):
            if self._n_actions >= self.spec.max_actions:
                raise RuntimeError(f"max_actions = {self.spec.max_actions} pokes made; only a GraspAction is allowed")
            frame = self._accept(self.robot.act(GuardedMoveCommand(action.waypoints, self.spec.guard_force)))
            if frame.motion is None:
                raise ProtocolError("the frame of a GuardedMoveCommand must carry its MotionLog (motion)")
            self._frame = frame
            self._n_actions += 1
            obs = self._observation(start, frame.motion)
            return obs, 0.0, False, False, self._info(target_waypoints=len(action.waypoints))
        if isinstance(action, GraspAction):
            frame = self._accept(self.robot.act(GraspCommand(action.state, self.spec.grasp_guard_force)))
            if frame.grasp_success is None:
                raise ProtocolError("the frame of a GraspCommand must report grasp_success")
            self._frame = frame
            self._n_actions += 1
            self._terminated = True
            success = bool(frame.grasp_success)
            return self._observation(frame), float(success), True, False, self._info(grasp_success=success)
        raise ValueError(f"action must be a PokeAction or GraspAction, got {type(action).__name__}")


# ---------------------------------------------------------------------------------------------------- clutter tasks
@dataclasses.dataclass(frozen=True)
class PosedCamera(PinholeCamera):
    """The camera of a :class:`DepthView` as the clutter planners use it (``sim.camera.PinholeCamera``'s interface:
    ``pos``, ``intrinsics()``, ``rotation()``, ``ray_directions() (H*W, 3)``, ``max_depth``), at the pose the robot
    reported rather than a look-at: ``orientation`` is the camera -> world rotation (9 floats, row-major, OpenCV
    axes), so a camera that rolled or looks straight down keeps its pixels' rays; ``target`` is 1 m along the
    optical axis (for viewers); ``fx, fy, cx, cy`` are the view's intrinsics."""

    orientation: tuple = ()

    def __post_init__(self):
        if self.width < 1 or self.height < 1:
            raise ValueError(f"camera image size must be positive, got {self.width}x{self.height}")
        if len(self.orientation) != 9:
            raise ValueError(f"PosedCamera.orientation must be 9 floats (a row-major 3x3 rotation), got "
                             f"{len(self.orientation)}")

    def rotation(self) -> np.ndarray:
        """Camera-to-world rotation ``(3, 3)`` (the reported one)."""
        return np.array(self.orientation, dtype=np.float64).reshape(3, 3)

    @classmethod
    def of(cls, view: DepthView) -> "PosedCamera":
        """The camera of ``view`` (valid: :func:`check_frame`)."""
        T = np.asarray(view.camera_pose, dtype=np.float64)
        K = np.asarray(view.intrinsics, dtype=np.float64)
        H, W = view.shape
        return cls(pos=tuple(float(v) for v in T[:3, 3]), target=tuple(float(v) for v in T[:3, 3] + T[:3, 2]),
                   width=int(W), height=int(H), fov_y_deg=math.degrees(2 * math.atan(0.5 * H / K[1, 1])),
                   fx=float(K[0, 0]), fy=float(K[1, 1]), cx=float(K[0, 2]), cy=float(K[1, 2]),
                   max_depth=float(view.max_depth), orientation=tuple(float(v) for v in T[:3, :3].reshape(-1)))


def _swap_label(label: int, target: int) -> int:
    """The planners' numbering (target = 0) <-> the robot's (target = ``target``): 0 and ``target`` trade places,
    every other label (and -1, no object) stays. Its own inverse."""
    label = int(label)
    return 0 if label == target else target if label == 0 else label


class ClutterRobotEnv:
    """The dense-clutter environment interface (``activetouch.sim.clutter_env.ClutterEnv``'s: the visuo-tactile
    paper's ``clutter-*`` tasks) on top of any :class:`Robot` that executes :class:`ViewCommand`,
    :class:`TouchCommand`, :class:`PushCommand` and :class:`PickCommand`.

    The loop's ``step`` goes to the robot: a ``ViewAction`` becomes a :class:`ViewCommand` (Sec. II-D-1), a
    ``TouchAction`` a :class:`TouchCommand` (II-D-2), a ``PushAction`` / ``PickAction`` a :class:`PushCommand` /
    :class:`PickCommand` (the declutter actions, II-B); a ``StopAction`` ends the episode without moving the robot.
    The frames become the ``ClutterObservation`` the TIQF estimator and the clutter planner read: a view's target
    points (``frame.points``' SURFACE / CAMERA rows), segmentation ``seg (H, W)``, organised cloud ``cloud (H, W,
    3)`` and camera (a :class:`PosedCamera` at the reported pose); a touch's contact points on the target; a push's
    or pick's outcome; the label of the object touched. Labels: the planners call the target 0; a robot whose
    segmenter gives the target another label ``t`` has 0 and ``t`` swapped both ways (into ``seg`` and
    ``contact_label``, back into the commands' labels); every other label passes unchanged.

    No model queries: the clutter planners predict on their own occupancy grid (Eq. 19-24) and on the target's mesh
    (Eq. 25), so unlike :class:`GraspRobotEnv` no model environment is needed, only task knowledge: ``spec`` (the view
    hemisphere, the camera model the next best views are predicted with, the budget, the prior's spread), the
    target's mesh ``obj`` and the ``gripper`` (its opening and pad size, for grasp and push planning).

    Args:
        robot: a :class:`Robot` of the clutter tasks (``activetouch.sim.sim_clutter_robot.SimClutterRobot``; a real
            arm's driver with a depth camera and a segmenter).
        spec: the task (``sim.clutter_env.ClutterTaskSpec``): ``view_radius``, ``min_view_elevation_deg``,
            ``camera_*`` (set them to the real camera's), ``max_actions``, ``prior_sigma_*``, ``target``.
        obj: the target (``activetouch.objects.KnownObject``); None: ``objects.load(spec.target)``.
        gripper: the gripper's geometry (``sim.grasp_scene.GripperSpec``); None: the simulated ``CLUTTER_GRIPPER``.
        prior_pose: the coarse target pose ``(4, 4)`` the episode starts from (the paper's approximate centroid from
            its segmentation network, an upright target of unknown heading; Sec. II-D-1), or a callable
            ``seed -> (4, 4)`` called after the robot's reset; reported as ``info["prior_pose"]`` for
            :func:`detection_prior`. None: no ``prior_pose`` (the task's prior must come from elsewhere).
        names: object names by label for figures (default: ``(spec.target,)``: a robot does not know the clutter).
        seed: default seed of ``reset`` (only a callable ``prior_pose`` reads it: the robot draws nothing).

    ``info["true_pose"]`` (float32 torch ``(4, 4)``) comes from the frames' ``object_pose`` (evaluation only: the
    loop's metrics read it, no estimator or planner does); ``info`` has no ``object_poses``, ``object_names`` or
    ``pile_centre`` (the simulator's ground truth beyond the target's pose).
    """

    def __init__(self, robot, spec, obj=None, gripper=None, prior_pose=None, names=None, seed: int = 0):
        if not isinstance(robot, Robot):
            raise ProtocolError(f"{type(robot).__name__} lacks reset(), observe() or act()")
        from activetouch import objects
        from activetouch.sim.clutter_env import CLUTTER_GRIPPER

        self.robot, self.spec = robot, spec
        self.object = objects.load(spec.target) if obj is None else obj
        self.gripper = CLUTTER_GRIPPER if gripper is None else gripper
        self.names = (spec.target,) if names is None else tuple(names)
        self.seed = int(seed)
        self._prior_pose = prior_pose
        self._frame: SensorFrame | None = None
        self._n_joints: int | None = None
        self._n_actions = 0
        self._terminated = False
        self._target = 0  # the robot's label of the target (the last view's)

    @property
    def max_steps(self) -> int:
        """Episode budget T: ``spec.max_actions``."""
        return self.spec.max_actions

    # -- the robot's state (its last frame)
    def _require_frame(self) -> SensorFrame:
        if self._frame is None:
            raise RuntimeError("call reset() before step()")
        return self._frame

    def ee_state(self) -> np.ndarray:
        """Measured end effector ``[x, y, z, yaw] (4,)`` of the last frame."""
        return _ee_state(self._require_frame())

    def current_q(self) -> np.ndarray:
        """Measured arm joints ``(n,)`` of the last frame."""
        return np.array(self._require_frame().joint_positions, dtype=np.float64)

    def true_pose(self) -> np.ndarray | None:
        """Ground-truth target pose ``(4, 4)`` of the last frame (evaluation only), None when unknown."""
        f = self._require_frame()
        return None if f.object_pose is None else np.asarray(f.object_pose, dtype=np.float64)

    def object_poses(self) -> np.ndarray:
        """``(1, 4, 4)``: the target's ground-truth pose (figures only; the clutter's poses are not reported)."""
        T = self.true_pose()
        if T is None:
            raise RuntimeError("the robot reports no object_pose: no ground truth to draw")
        return T[None].copy()

    def close(self) -> None:
        if hasattr(self.robot, "close"):
            self.robot.close()

    # -- the loop's calls
    def _accept(self, frame: SensorFrame, command=None) -> SensorFrame:
        check_frame(frame, self._n_joints)
        if command is not None:
            _check_answer(command, frame)
        self._n_joints = len(frame.joint_positions)
        return frame

    def _observation(self, command, frame: SensorFrame):
        """The ``ClutterObservation`` of ``frame``, the answer to ``command``."""
        from activetouch.sim.clutter_env import ClutterObservation

        none = np.zeros((0, 3))
        if isinstance(command, ViewCommand):
            v = frame.view
            t = int(v.target_label)
            self._target = t
            lab = np.asarray(v.labels)
            seg = lab.copy() if t == 0 else np.where(lab == t, 0, np.where(lab == 0, t, lab)).astype(lab.dtype)
            pts = np.asarray(frame.points, dtype=np.float64)
            pts = pts[(np.asarray(frame.semantics) == SURFACE) & (np.asarray(frame.source) == CAMERA)]
            return ClutterObservation("view", pts, seg=seg, cloud=np.array(v.points), camera=PosedCamera.of(v),
                                      success=bool((lab == t).any()))
        label = _swap_label(frame.contact_label, self._target)
        if isinstance(command, TouchCommand):
            contacts = np.asarray(frame.contacts, dtype=np.float64)
            ok = bool(frame.in_contact) and len(contacts) > 0
            return ClutterObservation("touch", contacts if ok else none, in_contact=ok, success=ok,
                                      contact_label=label)
        if isinstance(command, PushCommand):
            return ClutterObservation("push", none, success=bool(frame.push_success), contact_label=label)
        return ClutterObservation("pick", none, success=bool(frame.grasp_success), contact_label=label)

    def _info(self, **extra) -> dict[str, Any]:
        f = self._require_frame()
        info: dict[str, Any] = {"num_actions": self._n_actions, "stamp": float(f.stamp)}
        if f.object_pose is not None:
            info["true_pose"] = torch.as_tensor(np.asarray(f.object_pose, dtype=np.float64), dtype=torch.float32)
        info.update(extra)
        return info

    def reset(self, seed: int | None = None):
        """Reset the robot; returns ``ClutterObservation("reset")`` and ``info`` with ``num_actions``, ``stamp``,
        ``prior_pose (4, 4)`` float32 torch (when given) and, when the robot reports ``object_pose``, ``true_pose``."""
        from activetouch.sim.clutter_env import ClutterObservation

        seed = self.seed if seed is None else int(seed)
        self._n_joints = None
        self._frame = self._accept(self.robot.reset())
        self._n_actions = 0
        self._terminated = False
        self._target = 0
        extra: dict[str, Any] = {}
        if self._prior_pose is not None:
            P = self._prior_pose(seed) if callable(self._prior_pose) else self._prior_pose
            extra["prior_pose"] = torch.as_tensor(_pose(P, "prior_pose"), dtype=torch.float32)
        return ClutterObservation("reset", np.zeros((0, 3))), self._info(**extra)

    def step(self, action):
        """Execute a ``ViewAction`` / ``TouchAction`` / ``PushAction`` / ``PickAction`` on the robot (a
        ``StopAction`` ends the episode); returns ``(obs, reward, terminated, truncated, info)`` as
        ``ClutterEnv.step`` does (``info``: ``action``, ``action_success``, ``num_actions``, ``stamp``,
        ``true_pose``; a stop's ``stop_reason``)."""
        from activetouch.sim.clutter_env import (ClutterObservation, PickAction, PushAction, StopAction, TouchAction,
                                                 ViewAction)

        self._require_frame()
        if self._terminated:
            raise RuntimeError("the episode has ended (StopAction); call reset()")
        if isinstance(action, StopAction):
            self._terminated = True
            return (ClutterObservation("stop", np.zeros((0, 3))), 0.0, True, False,
                    self._info(action="stop", action_success=True, stop_reason=action.reason))
        if self._n_actions >= self.spec.max_actions:
            raise RuntimeError(f"max_actions = {self.spec.max_actions} actions made; call reset()")
        if isinstance(action, ViewAction):
            cmd = ViewCommand(action.position, action.look_at)
        elif isinstance(action, TouchAction):
            cmd = TouchCommand(action.start, action.direction, action.max_length)
        elif isinstance(action, PushAction):
            cmd = PushCommand(_swap_label(action.label, self._target), action.start, action.direction, action.length)
        elif isinstance(action, PickAction):
            cmd = PickCommand(_swap_label(action.label, self._target), action.position, action.closing_angle,
                              action.width)
        else:
            raise ValueError(f"action must be a ViewAction, TouchAction, PushAction, PickAction or StopAction, "
                             f"got {type(action).__name__}")
        self._n_actions += 1
        self._frame = self._accept(self.robot.act(cmd), cmd)
        obs = self._observation(cmd, self._frame)
        truncated = self._n_actions >= self.spec.max_actions
        return obs, 0.0, False, truncated, self._info(action=obs.kind, action_success=obs.success)


def detection_prior(env, n: int, generator: torch.Generator, device="cpu", *, info=None, **_) -> torch.Tensor:
    """The clutter tasks' prior around the robot's detection of the target: ``n`` poses ``(n, 4, 4)``, the coarse
    pose ``info["prior_pose"]`` (:class:`ClutterRobotEnv`'s ``prior_pose``) perturbed exactly as
    ``activetouch.tasks.clutter_prior`` perturbs the simulator's truth (N(0, ``spec.prior_sigma_t``) in x, y and
    N(0, ``spec.prior_sigma_yaw_deg``) about z). Register a clutter task on a robot with ``prior=detection_prior``:
    the registered tasks' ``clutter_prior`` reads ``info["true_pose"]``, the simulator's stand-in for the paper's
    approximate centroid (Sec. II-D-1)."""
    from activetouch.tasks import clutter_prior

    if info is None or "prior_pose" not in info:
        raise ValueError("detection_prior needs info['prior_pose'] from ClutterRobotEnv.reset() (its prior_pose)")
    return clutter_prior(env, n, generator, device, info={"true_pose": info["prior_pose"]})

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

from activetouch.sim.env import TaskGeometry

__all__ = ["SensorFrame", "EeDeltaCommand", "GuardedMoveCommand", "GraspCommand", "ArmState", "MotionLog", "Robot",
           "RobotEnv", "GraspRobotEnv", "check_frame", "check_robot", "ProtocolError", "CAMERA", "TOUCH", "PRIOR",
           "SURFACE", "FREE", "OCCUPIED"]

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
            gripper); None for other frames.
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


@runtime_checkable
class Robot(Protocol):
    """A robot the episode loop can drive (simulated or real). Every call blocks until its frame is ready."""

    def reset(self) -> SensorFrame:
        """Go to the start configuration and take the first look (camera points, tactile reading)."""

    def observe(self) -> SensorFrame:
        """Read the sensors now without moving: pose, joints, torques, contact (new points may be empty)."""

    def act(self, command) -> SensorFrame:
        """Execute ``command`` and return what was sensed during and after it: an :class:`EeDeltaCommand` (the
        rummaging tasks) or a :class:`GuardedMoveCommand` / :class:`GraspCommand` (the grasp tasks); a command the
        robot does not execute raises :class:`ProtocolError`."""


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
    return frame


def _finite(x, shape: tuple, name: str, dtype=np.float64) -> np.ndarray:
    """``x`` as an array of exactly ``shape`` (None entries: any size), finite; ProtocolError otherwise."""
    a = np.asarray(x)
    if a.ndim != len(shape) or any(w is not None and w != d for w, d in zip(shape, a.shape)):
        want = "(" + ", ".join("?" if w is None else str(w) for w in shape) + ("," if len(shape) == 1 else "") + ")"
        raise ProtocolError(f"{name} must have shape {want}, got {a.shape}")
    if dtype is bool:
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


def check_robot(robot, command_dim: int | None = None, steps: int = 2, command=None) -> list[SensorFrame]:
    """The contract every :class:`Robot` passes: ``reset``, ``observe`` and ``steps`` "do nothing" ``act`` calls
    return valid frames with strictly increasing stamps and a fixed joint count; an ``observe`` does not move the
    end effector. Returns the frames (reset first). Raises :class:`ProtocolError`.

    The "do nothing" command is a zero :class:`EeDeltaCommand` of ``command_dim`` (the rummaging tasks), or
    ``command(last_frame)`` (the grasp tasks: ``command=GuardedMoveCommand.stay``). A frame answering a
    :class:`GuardedMoveCommand` must carry its :class:`MotionLog`, and every frame of a robot whose reset frame
    carries an :class:`ArmState` must carry one."""
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
        frame = check_frame(robot.act(cmd), n)
        if isinstance(cmd, GuardedMoveCommand) and frame.motion is None:
            raise ProtocolError("the frame of a GuardedMoveCommand must carry its MotionLog (motion)")
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

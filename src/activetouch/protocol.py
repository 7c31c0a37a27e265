"""The robot / sensor protocol: what a robot (simulated or real) gives the episode loop, and what it takes.

A robot implements :class:`Robot`: ``reset()``, ``observe()`` and ``act(command)``, each returning a
:class:`SensorFrame`. :class:`activetouch.sim.sim_robot.SimRobot` implements it on the MuJoCo rummaging tasks;
a real arm implements the same three methods on its drivers (docs/ROBOT.md walks through it).
:class:`RobotEnv` turns any :class:`Robot` back into the environment the one episode loop runs
(``reset() -> (obs, info)``, ``step(u) -> (obs, r, terminated, truncated, info)`` and the task geometry the
planners read), so every method registered for the rummaging tasks (RUMI, its ablations, GPVR, Slide,
tiqf-slide) runs on it unchanged; :func:`check_robot` is the contract a robot must pass (as gymnasium's
``check_env`` is for environments). The episode log (``episode.h5``) records the observations the loop saw, so
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

__all__ = ["SensorFrame", "EeDeltaCommand", "Robot", "RobotEnv", "check_robot", "ProtocolError", "CAMERA", "TOUCH", "PRIOR",
           "SURFACE", "FREE", "OCCUPIED"]

#: ``SensorFrame.semantics`` values (chsel.SemanticsClass, ``activetouch.observations.Semantics``).
SURFACE, FREE, OCCUPIED = 0, 1, 2
#: ``SensorFrame.source`` values: a camera / depth sensor; touch (tactile pads, and the free space the robot's
#: own body swept); prior knowledge of the scene (e.g. free points under the table top, the box tasks).
CAMERA, TOUCH, PRIOR = 0, 1, 2


class ProtocolError(ValueError):
    """A robot broke the protocol (a frame with a wrong shape, a non-finite value, a non-rigid pose, ...)."""


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


@runtime_checkable
class Robot(Protocol):
    """A robot the episode loop can drive (simulated or real). Every call blocks until its frame is ready."""

    def reset(self) -> SensorFrame:
        """Go to the start configuration and take the first look (camera points, tactile reading)."""

    def observe(self) -> SensorFrame:
        """Read the sensors now without moving: pose, joints, torques, contact (new points may be empty)."""

    def act(self, command: EeDeltaCommand) -> SensorFrame:
        """Execute ``command`` and return what was sensed during and after it."""


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
    return frame


def check_robot(robot, command_dim: int, steps: int = 2) -> list[SensorFrame]:
    """The contract every :class:`Robot` passes: ``reset``, ``observe`` and ``steps`` zero ``act`` calls return
    valid frames with strictly increasing stamps and a fixed joint count; an ``observe`` does not move the end
    effector. Returns the frames (reset first). Raises :class:`ProtocolError`."""
    if not isinstance(robot, Robot):
        raise ProtocolError(f"{type(robot).__name__} lacks reset(), observe() or act()")
    frames = [check_frame(robot.reset())]
    n = len(frames[0].joint_positions)
    seen = check_frame(robot.observe(), n)
    if not np.allclose(seen.ee_pose, frames[0].ee_pose, atol=1e-3):
        raise ProtocolError("observe() moved the end effector by more than 1 mm")
    frames.append(seen)
    for _ in range(steps):
        frames.append(check_frame(robot.act(EeDeltaCommand(np.zeros(command_dim))), n))
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

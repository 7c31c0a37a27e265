"""The touch-only grasp tasks (``grasp-box-*``, the touch paper) on a robot: the commands
:class:`GuardedMoveCommand` and :class:`GraspCommand`, and :class:`GraspRobotEnv`, such a robot as the grasp
environment the episode loop runs (``activetouch.sim.sim_grasp_robot.SimGraspRobot`` is one). The frames' parts these
commands report (:class:`~activetouch.protocol.frames.ArmState`, :class:`~activetouch.protocol.frames.MotionLog`)
are in :mod:`activetouch.protocol.frames`; ``activetouch.protocol``'s docstring is the overview."""
from __future__ import annotations

import dataclasses
import math
from typing import Any

import numpy as np
import torch

from .frames import MotionLog, ProtocolError, Robot, SensorFrame, _command_array, _ee_state, check_frame


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

"""The rummaging tasks on a robot: :class:`RobotEnv`, any :class:`~activetouch.protocol.frames.Robot` that executes
:class:`~activetouch.protocol.frames.EeDeltaCommand` as the environment the episode loop runs
(``activetouch.sim.sim_robot.SimRobot`` is such a robot; ``activetouch.protocol``'s docstring is the overview)."""
from __future__ import annotations

from typing import Any

import numpy as np
import torch

from activetouch.sim.env import TaskGeometry

from .frames import CAMERA, SURFACE, EeDeltaCommand, ProtocolError, Robot, SensorFrame, check_frame


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

"""The simulator as a clutter-task :class:`activetouch.protocol.Robot`: the visuo-tactile paper's dense-clutter scene
(``ClutterEnv``, clutter-*) behind ``reset`` / ``observe`` / ``act``, so the protocol a real arm implements for the
clutter tasks is exercised by every test that drives it.

``ClutterRobotEnv(SimClutterRobot(env), env.spec, env.object, env.gripper, prior_pose=...)`` gives the episode loop
the same observations and the same per-step results as ``env`` itself (tests/test_protocol.py): the robot side
reports what an arm with a depth camera, a segmenter and tactile pads senses (segmented depth images, contact points,
the outcome of pushes and grasps), and the planners keep only task knowledge (the spec, the target's mesh, the
gripper).
"""
from __future__ import annotations

import numpy as np

from activetouch.protocol import (CAMERA, SURFACE, TOUCH, DepthView, PickCommand, ProtocolError, PushCommand,
                                  SensorFrame, TouchCommand, ViewCommand)

__all__ = ["SimClutterRobot", "sim_clutter_robot_env"]


class SimClutterRobot:
    """A :class:`~activetouch.protocol.Robot` on a :class:`~activetouch.sim.clutter_env.ClutterEnv`; it executes
    :class:`~activetouch.protocol.ViewCommand` (``ClutterEnv.step(ViewAction)``, Sec. II-D-1),
    :class:`~activetouch.protocol.TouchCommand` (``TouchAction``, II-D-2), :class:`~activetouch.protocol.PushCommand`
    (``PushAction``, II-B-1) and :class:`~activetouch.protocol.PickCommand` (``PickAction``, II-B-2).

    Frames: the stamp is MuJoCo's simulated time plus ``view_time`` per view taken (the simulated camera is a
    free-flying sensor whose images take no physics time: ``clutter_env``'s SIMPLIFICATION; a real exposure does);
    ``ee_pose`` the ee site's pose as ``ClutterEnv.ee_state`` reads it; ``joint_positions`` the 7 arm joints;
    ``joint_torques`` the arm's contact constraint torques (``qfrc_constraint``); ``view``: the environment's image
    (``cloud (H, W, 3)`` as ``points``, the geom-id segmentation ``seg (H, W)`` as ``labels``, with the task's
    boundary label noise and depth noise; object label = MuJoCo body index, the target 0) with the camera's pose
    and intrinsics; ``points``: a view's target returns (SURFACE, CAMERA) or a touch's contact points on the target
    (SURFACE, TOUCH); ``in_contact``: a touch that ended on the target; ``contact_label``, ``push_success``,
    ``grasp_success`` (a pick): the environment's ``contact_label`` and ``success``, which it decides from MuJoCo's
    contacts and the objects' poses; ``object_pose``: the target's ground truth (evaluation only).

    :meth:`detection` is the simulated detector behind the tasks' prior: the target's true pose, which the prior
    perturbs (``tasks.clutter_prior``); a real robot's comes from its segmenter (the target segment's centroid).
    """

    def __init__(self, env, view_time: float = 0.05):
        if not (view_time > 0):
            raise ValueError(f"view_time must be > 0 s, got {view_time!r}")
        self.env = env
        self.view_time = float(view_time)
        self._clock = 0.0  # the views' exposure time so far (s)

    def _frame(self, points=None, source: int = CAMERA, in_contact: bool = False, **fields) -> SensorFrame:
        env, d = self.env, self.env.data
        ee = np.eye(4)
        ee[:3, :3] = d.site_xmat[env._site].reshape(3, 3)  # what ClutterEnv.ee_state reads
        ee[:3, 3] = d.site_xpos[env._site]
        pts = np.zeros((0, 3)) if points is None else np.asarray(points, dtype=np.float64).reshape(-1, 3).copy()
        return SensorFrame(
            stamp=float(d.time) + self._clock, ee_pose=ee, joint_positions=env.current_q(),
            joint_torques=d.qfrc_constraint[env._vadr].copy(), points=pts,
            semantics=np.full(len(pts), SURFACE, np.int64), source=np.full(len(pts), source, np.int64),
            in_contact=bool(in_contact), object_pose=env.true_pose(), **fields)

    def detection(self) -> np.ndarray:
        """The simulated coarse detection of the target ``(4, 4)``: its true pose now (the prior's centre)."""
        return self.env.true_pose()

    def reset(self) -> SensorFrame:
        self.env.reset()
        self._clock = 0.0
        return self._frame()

    def observe(self) -> SensorFrame:
        import mujoco

        env = self.env
        if not env._reset_done:
            raise ProtocolError("call reset() before observe()")
        env.data.ctrl[:] = env._target_ctrl  # a sensor read takes time: one 2 ms physics step, the setpoints held
        mujoco.mj_step(env.model, env.data)
        return self._frame()

    def _label(self, command) -> int:
        n = len(self.env.names)
        if not 0 < command.label < n:
            raise ProtocolError(f"{type(command).__name__}.label must name a clutter object 1..{n - 1} (0 is the "
                                f"target), got {command.label}")
        return int(command.label)

    def act(self, command) -> SensorFrame:
        from activetouch.sim.clutter_env import PickAction, PushAction, TouchAction, ViewAction

        env = self.env
        if not env._reset_done:
            raise ProtocolError("call reset() before act()")
        if env._n_actions >= env.spec.max_actions:
            raise ProtocolError(f"{env.spec.max_actions} actions made (max_actions): call reset()")
        try:
            if isinstance(command, ViewCommand):
                action = ViewAction(tuple(command.position), tuple(command.look_at))
            elif isinstance(command, TouchCommand):
                action = TouchAction(tuple(command.start), tuple(command.direction), command.max_length)
            elif isinstance(command, PushCommand):
                action = PushAction(self._label(command), tuple(command.start), tuple(command.direction),
                                    command.length)
            elif isinstance(command, PickCommand):
                action = PickAction(self._label(command), tuple(command.position), command.closing_angle,
                                    command.width)
            else:
                raise ProtocolError(f"SimClutterRobot executes ViewCommand, TouchCommand, PushCommand and "
                                    f"PickCommand, got {type(command).__name__}")
        except ProtocolError:
            raise
        except ValueError as e:  # beyond the simulated arm's limits (ClutterEnv's action checks)
            raise ProtocolError(str(e)) from None
        obs, _, _, _, _ = env.step(action)
        if obs.kind == "view":
            cam = obs.camera
            T = np.eye(4)
            T[:3, :3] = cam.rotation()
            T[:3, 3] = cam.pos
            self._clock += self.view_time
            view = DepthView(camera_pose=T, intrinsics=cam.intrinsics(), points=obs.cloud, labels=obs.seg,
                             target_label=0, max_depth=float(cam.max_depth))
            return self._frame(obs.points, CAMERA, view=view)
        if obs.kind == "touch":
            return self._frame(obs.points, TOUCH, in_contact=obs.in_contact, contact_label=int(obs.contact_label))
        if obs.kind == "push":
            return self._frame(contact_label=int(obs.contact_label), push_success=bool(obs.success))
        return self._frame(contact_label=int(obs.contact_label), grasp_success=bool(obs.success))

    def close(self) -> None:
        self.env.close()


def sim_clutter_robot_env(task: str, seed: int = 0, **overrides):
    """``ClutterRobotEnv(SimClutterRobot(make_clutter_env(task)), spec, object, gripper, prior_pose=the simulated
    detection)``: a registered clutter task driven through the robot protocol (``overrides`` replace
    ``ClutterTaskSpec`` fields). Register it with ``prior=protocol.detection_prior``."""
    from activetouch.protocol import ClutterRobotEnv
    from activetouch.sim.clutter_tasks import make_clutter_env

    env = make_clutter_env(task, seed=seed, **overrides)
    robot = SimClutterRobot(env)
    return ClutterRobotEnv(robot, env.spec, env.object, env.gripper, prior_pose=lambda _seed: robot.detection(),
                           seed=seed)

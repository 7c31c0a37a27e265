"""The simulator as a :class:`activetouch.protocol.Robot`: the MuJoCo rummaging tasks behind ``reset`` /
``observe`` / ``act``, so the protocol a real arm implements is exercised by every test that drives it.

``RobotEnv(SimRobot(make(task)), spec, obj)`` gives the episode loop exactly the observations of
``make(task)`` itself (tests/test_protocol.py): the protocol loses nothing the methods use.
"""
from __future__ import annotations

import numpy as np

from activetouch.protocol import CAMERA, PRIOR, TOUCH, EeDeltaCommand, SensorFrame

__all__ = ["SimRobot", "sim_robot_env"]


class SimRobot:
    """A :class:`~activetouch.protocol.Robot` on a :class:`~activetouch.sim.env.RummageEnv`.

    Frames: the stamp is MuJoCo's simulated time; joint torques are the arm's contact constraint torques
    (``qfrc_constraint``, what joint torque sensors would read beyond the arm's own dynamics); points are the
    environment's new features, labelled by source from the counts ``RummageEnv.reset`` reports (camera, the
    box tasks' floor points as PRIOR, touch); with ``camera_every_step`` the later frames' camera points are
    labelled TOUCH (the environment does not report the split: a simplification, no method reads ``source``);
    ``object_motion`` and ``object_pose`` are the simulator's ground truth.
    """

    def __init__(self, env):
        self.env = env

    def _frame(self, features, in_contact: bool, dT=None, info: dict | None = None) -> SensorFrame:
        env, d = self.env, self.env.data
        pts = features.positions.detach().cpu().numpy().astype(np.float64)
        sem = features.semantics.detach().cpu().numpy().astype(np.int64)
        source = np.full(len(pts), TOUCH, dtype=np.int64)
        if info is not None and "camera_surface_points" in info:  # reset: RummageEnv lists, per semantics,
            f0 = int((sem == 0).sum())  # the camera's points first, then (free) the floor's, then touch
            source[:int(info["camera_surface_points"])] = CAMERA
            cf, fl = int(info.get("camera_free_points", 0)), int(info.get("floor_free_points", 0))
            source[f0:f0 + cf] = CAMERA
            source[f0 + cf:f0 + cf + fl] = PRIOR
        return SensorFrame(
            stamp=float(d.time), ee_pose=env.ee_pose(), joint_positions=d.qpos[env._qadr].copy(),
            joint_torques=d.qfrc_constraint[env._vadr].copy(), points=pts, semantics=sem, source=source,
            in_contact=bool(in_contact),
            object_motion=None if dT is None else dT.detach().cpu().numpy().astype(np.float64),
            object_pose=env.true_pose())

    def reset(self) -> SensorFrame:
        obs, info = self.env.reset()
        return self._frame(obs.features, obs.in_contact, obs.dT, info)

    def observe(self) -> SensorFrame:
        import mujoco

        from activetouch.observations import Features

        env = self.env
        mujoco.mj_step(env.model, env.data)  # a sensor read takes time: one 2 ms physics step, joints held
        return self._frame(Features.empty(), env._touching())

    def act(self, command: EeDeltaCommand) -> SensorFrame:
        obs, _, _, _, _ = self.env.step(np.asarray(command.u, dtype=np.float64))
        return self._frame(obs.features, obs.in_contact, obs.dT)


def sim_robot_env(task: str, seed: int = 0, **overrides):
    """``RobotEnv(SimRobot(sim.make(task)))``: a registered rummaging task driven through the robot protocol."""
    from activetouch import sim
    from activetouch.protocol import RobotEnv

    env = sim.make(task, seed=seed, **overrides)
    return RobotEnv(SimRobot(env), env.spec, env.object)

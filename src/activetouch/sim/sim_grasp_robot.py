"""The simulator as a grasp-task :class:`activetouch.protocol.Robot`: the touch paper's blind-grasping scene
(``GraspEnv``, grasp-box-*) behind ``reset`` / ``observe`` / ``act``, so the protocol a real arm implements for the
grasp tasks is exercised by every test that drives it.

``GraspRobotEnv(SimGraspRobot(make_grasp_env(task)), make_grasp_env(task))`` gives the episode loop the same
observations and the same per-step results as ``make_grasp_env(task)`` itself (tests/test_protocol.py): the robot
side reports only what an arm senses (joints, torques, the binary contact signal, the guard, the grasp outcome) and
the second environment serves as the model, whose own object is never read.
"""
from __future__ import annotations

import contextlib
import dataclasses

import numpy as np
import torch

from activetouch.protocol import (ArmState, GraspCommand, GuardedMoveCommand, MotionLog, ProtocolError,
                                  SensorFrame)

__all__ = ["SimGraspRobot", "sim_grasp_robot_env"]


class SimGraspRobot:
    """A :class:`~activetouch.protocol.Robot` on a :class:`~activetouch.sim.grasp_env.GraspEnv`; it executes
    :class:`~activetouch.protocol.GuardedMoveCommand` (``GraspEnv.step(PokeAction)``) and
    :class:`~activetouch.protocol.GraspCommand` (``GraspEnv.step(GraspAction)``).

    Frames: the stamp is MuJoCo's simulated time; ``ee_pose`` is the ee site's pose as ``GraspEnv.ee_state``
    reads it; ``joint_positions`` the 7 arm joints; ``joint_torques`` the arm's contact constraint torques now
    (``qfrc_constraint``, noise-free: the noisy sensor of App. D-a is sampled once per control period inside a
    motion, and its norms and the contact signal are in ``motion``; drawing more noise here would shift the
    environment's seeded noise stream); no points (no camera, no tactile array: the touch paper senses contact
    only through the joint torques); ``in_contact``: the contact signal at one of the last motion's observations;
    ``arm``: joint and pad velocities, pad positions, the actuator setpoints and the solver's warm start (the
    simulation-only part); ``motion``: the poke's control-rate log (``TouchObservation``'s setpoints, signal, torque
    norms, force estimates, observation periods, joints and ee, true contacts); ``grasp_success``: the grasp's
    outcome; ``object_pose``: the box's SE(2) ground truth on the table (z = 0: the table top, the box's bottom
    centre) as ``GraspEnv``'s ``info["true_pose"]`` reports it. A command's ``guard_force`` other than the task's
    runs that one command with it (the environment reads its thresholds from its spec).
    """

    def __init__(self, env):
        self.env = env
        self._in_contact = False

    def _frame(self, motion: MotionLog | None = None, grasp_success: bool | None = None) -> SensorFrame:
        from activetouch.geometry.transforms import pose_from_xyz_yaw

        env, d = self.env, self.env.data
        ee = np.eye(4)
        ee[:3, :3] = d.site_xmat[env._site].reshape(3, 3)  # what GraspEnv.ee_state reads
        ee[:3, 3] = d.site_xpos[env._site]
        st = env.true_state()
        obj = pose_from_xyz_yaw(torch.tensor([st[0], st[1], 0.0], dtype=torch.float64), torch.tensor(st[2]))
        warm = np.concatenate([d.qacc_warmstart[env._vadr], d.qacc_warmstart[env._pad_vadr]])
        arm = ArmState(joint_velocities=d.qvel[env._vadr].copy(), gripper_positions=d.qpos[env._pad_qadr].copy(),
                       gripper_velocities=d.qvel[env._pad_vadr].copy(), command=env._target.copy(),
                       solver_warmstart=warm)
        return SensorFrame(
            stamp=float(d.time), ee_pose=ee, joint_positions=env.current_q(),
            joint_torques=d.qfrc_constraint[env._vadr].copy(), points=np.zeros((0, 3)),
            semantics=np.zeros(0, np.int64), source=np.zeros(0, np.int64), in_contact=self._in_contact,
            object_pose=obj.numpy(), arm=arm, motion=motion, grasp_success=grasp_success)

    @contextlib.contextmanager
    def _thresholds(self, **fields):
        """Run one command with the spec's ``fields`` (the command's guard forces) where they differ."""
        spec = self.env.spec
        changed = {k: v for k, v in fields.items() if v is not None and v != getattr(spec, k)}
        if changed:
            self.env.spec = dataclasses.replace(spec, **changed)
        try:
            yield
        finally:
            self.env.spec = spec

    def reset(self) -> SensorFrame:
        self.env.reset()
        self._in_contact = False
        return self._frame()

    def observe(self) -> SensorFrame:
        import mujoco

        env = self.env
        env._require_reset()
        env.data.ctrl[:] = env._target  # a sensor read takes time: one 2 ms physics step, the setpoints held
        mujoco.mj_step(env.model, env.data)
        return self._frame()

    def act(self, command) -> SensorFrame:
        from activetouch.sim.grasp_env import GraspAction, PokeAction

        env = self.env
        if not env._reset_done:
            raise ProtocolError("call reset() before act()")
        if env._terminated:
            raise ProtocolError("the episode has ended with the grasp: call reset()")
        if isinstance(command, GuardedMoveCommand):
            if env._n_actions >= env.spec.max_actions:
                raise ProtocolError(f"{env.spec.max_actions} pokes made (max_actions): only a GraspCommand is allowed")
            if len(command.waypoints) > env.spec.max_waypoints:
                raise ProtocolError(f"a motion has at most {env.spec.max_waypoints} via-points, got "
                                    f"{len(command.waypoints)}")
            with self._thresholds(guard_force=command.guard_force):
                obs, _, _, _, _ = env.step(PokeAction(np.array(command.waypoints)))
            if not np.array_equal(obs.z_period, obs.seg_end):  # GraspEnv records z, q and ee at one instant
                raise RuntimeError("GraspEnv's contact periods and observation periods differ")
            self._in_contact = bool(obs.z.any())
            log = MotionLog(command=obs.ctrl.copy(), contact=obs.z_samples.copy(),
                            contact_torque=obs.tau_samples.copy(), ee_force=obs.force_samples.copy(),
                            observed=obs.seg_end.copy(), joint_positions=obs.q.copy(), ee=obs.ee.copy(),
                            stopped=bool(obs.stopped_early), true_contact=obs.true_contact_samples.copy())
            return self._frame(motion=log)
        if isinstance(command, GraspCommand):
            with self._thresholds(grasp_guard_force=command.guard_force):
                _, _, _, _, info = env.step(GraspAction(np.array(command.state)))
            self._in_contact = False
            return self._frame(grasp_success=bool(info["grasp_success"]))
        raise ProtocolError(f"SimGraspRobot executes GuardedMoveCommand and GraspCommand, got {type(command).__name__}")

    def close(self) -> None:
        self.env.close()


def sim_grasp_robot_env(task: str, seed: int = 0, **overrides):
    """``GraspRobotEnv(SimGraspRobot(make_grasp_env(task)), model=make_grasp_env(task))``: a registered grasp task
    driven through the robot protocol, a second ``GraspEnv`` of the same task as the estimator's and planner's model
    (``overrides`` replace ``GraspTaskSpec`` fields of both)."""
    from activetouch.protocol import GraspRobotEnv
    from activetouch.sim.grasp_env import make_grasp_env

    robot = SimGraspRobot(make_grasp_env(task, seed=seed, **overrides))
    return GraspRobotEnv(robot, make_grasp_env(task, seed=seed, **overrides), seed=seed)

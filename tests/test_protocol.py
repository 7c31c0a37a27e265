"""The robot / sensor protocol (activetouch.protocol) and the simulator's implementations of it (sim.sim_robot,
sim.sim_grasp_robot)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from activetouch import sim
from activetouch.protocol import (CAMERA, PRIOR, SURFACE, TOUCH, ArmState, EeDeltaCommand, GraspCommand,
                                  GuardedMoveCommand, MotionLog, ProtocolError, RobotEnv, SensorFrame, check_frame,
                                  check_robot)
from activetouch.sim.sim_robot import SimRobot

# toward the mug (mug-0: the mug at (0.5, 0), the gripper starts at (0.25, 0.22)): contact from the second action on
ACTIONS = [[1.0, -1.0, 0.0], [1.0, -1.0, 0.0], [1.0, -0.74, 0.0]]


def test_the_simulator_passes_the_robot_contract():
    env = sim.make("mug-0")
    frames = check_robot(SimRobot(env), command_dim=env.action_dim)
    reset = frames[0]
    n_cam = int(((reset.semantics == SURFACE) & (reset.source == CAMERA)).sum())
    assert n_cam > 100  # mug-0's camera sees the mug
    assert reset.object_pose is not None and reset.joint_positions.shape == (7,)
    assert len(reset.contacts) == 0  # the gripper starts away from the mug
    box = SimRobot(sim.make("box-0")).reset()
    assert int((box.source == PRIOR).sum()) > 100  # the box tasks' floor free points are prior knowledge
    assert int(((box.semantics == SURFACE) & (box.source == CAMERA)).sum()) == 0  # occluded camera


def test_the_loop_sees_the_same_observations_through_the_protocol():
    """RobotEnv(SimRobot(env)) gives the episode loop exactly what the environment gives it directly."""
    direct = sim.make("mug-0")
    proto = RobotEnv(SimRobot(sim.make("mug-0")), direct.spec, direct.object)
    pairs = [(direct.reset(), proto.reset())]
    for u in ACTIONS:
        a, b = direct.step(u), proto.step(u)
        pairs.append(((a[0], a[4]), (b[0], b[4])))
    touched = False
    for (oa, ia), (ob, ib) in pairs:
        assert torch.equal(oa.features.positions, ob.features.positions)
        assert torch.equal(oa.features.semantics, ob.features.semantics)
        assert torch.equal(oa.ee_pose, ob.ee_pose) and oa.in_contact == ob.in_contact
        assert (oa.dT is None) == (ob.dT is None) and (oa.dT is None or torch.allclose(oa.dT, ob.dT, atol=1e-6))
        assert torch.equal(ia["true_pose"], ib["true_pose"])
        np.testing.assert_allclose(ia["ee_state"], ib["ee_state"], atol=1e-9)
        touched = touched or oa.in_contact
    assert touched, "the scripted actions were meant to touch the mug"
    ee = direct.ee_state()
    np.testing.assert_array_equal(direct.target_ee(ee, np.array([0.5, -1.0, 0.2])),
                                  proto.target_ee(ee, np.array([0.5, -1.0, 0.2])))
    assert proto.action_dim == direct.action_dim and proto.action_scale == direct.action_scale


def _frame(**changes) -> SensorFrame:
    base = SensorFrame(stamp=1.0, ee_pose=np.eye(4), joint_positions=np.zeros(7), joint_torques=np.zeros(7),
                       points=np.zeros((2, 3)), semantics=np.array([0, 1]), source=np.array([TOUCH, CAMERA]),
                       in_contact=True)
    return dataclasses.replace(base, **changes)


@pytest.mark.parametrize("changes, message", [
    ({"ee_pose": 2 * np.eye(4)}, "ee_pose is not a rigid transform"),
    ({"points": np.array([[0.0, np.nan, 0.0], [0, 0, 0]])}, "points must be a finite"),
    ({"semantics": np.array([0, 5])}, "semantics must be SURFACE"),
    ({"source": np.array([0])}, "semantics and source must be"),
    ({"joint_torques": np.zeros(6)}, "joint_positions and joint_torques"),
    ({"stamp": float("inf")}, "stamp must be finite"),
    ({"object_pose": np.zeros((4, 4))}, "object_pose is not a rigid transform"),
])
def test_bad_frames_are_named(changes, message):
    check_frame(_frame())  # the base frame is valid
    with pytest.raises(ProtocolError, match=message):
        check_frame(_frame(**changes))


def test_a_robot_must_have_the_three_calls_and_increasing_stamps():
    class NoAct:
        def reset(self):
            return _frame()

        def observe(self):
            return _frame()

    with pytest.raises(ProtocolError, match="lacks"):
        check_robot(NoAct(), 3)

    class Frozen(NoAct):
        def act(self, command):
            assert isinstance(command, EeDeltaCommand)
            return _frame()

    with pytest.raises(ProtocolError, match="stamps must increase"):
        check_robot(Frozen(), 3)
    assert _frame().contacts.shape == (1, 3)  # the touch surface point only


def test_a_method_runs_through_the_protocol_with_the_same_numbers(tmp_path, monkeypatch):
    """A task whose environment is RobotEnv(SimRobot(...)), registered as a user would register a real arm,
    runs RUMI through the one episode loop and gives the same steps as the simulated task itself."""
    import dataclasses as dc

    from activetouch import registry
    from activetouch.experiments.records import read_steps
    from activetouch.experiments.runner import EpisodeConfig, run_episode
    from activetouch.methods import QUICK_KMPPI
    from activetouch.sim.sim_robot import sim_robot_env

    entry = dc.replace(registry.get_task("mug-0"), name="mug-0-protocol",
                       make_env=lambda seed=0, **kw: sim_robot_env("mug-0", seed=seed, **kw))
    monkeypatch.setitem(registry._TASKS, "mug-0-protocol", entry)
    cfg = dict(method="rumi", seed=0, steps=2, particles=20, use_chsel=False, planner=dict(QUICK_KMPPI),
               figures=False, progress=False)
    run_episode(EpisodeConfig(task="mug-0", **cfg), tmp_path / "direct")
    run_episode(EpisodeConfig(task="mug-0-protocol", **cfg), tmp_path / "protocol")
    a, b = read_steps(tmp_path / "direct" / "steps.csv"), read_steps(tmp_path / "protocol" / "steps.csv")
    keep = ("nll", "apc", "n_features", "n_surface", "n_free", "in_contact", "trans_err", "rot_err_deg")
    assert len(a) == len(b) == 3
    assert [[r[k] for k in keep] for r in a] == [[r[k] for k in keep] for r in b]


# ------------------------------------------------------------------------------------------------ grasp tasks
# grasp-box-0 seed 0: the box at (0.44, -0.156, yaw 0.67); the first poke sweeps -y into it (contact, guarded stop),
# the second backs off from the stopped gripper (a motion that starts in contact)
POKES = [[[0.44, 0.05, 0.10, 0.0], [0.44, -0.10, 0.08, 0.0]], [[0.44, 0.0, 0.09, 0.0]]]


def test_the_simulated_grasp_arm_passes_the_robot_contract():
    from activetouch.protocol import GraspCommand, GuardedMoveCommand
    from activetouch.sim.grasp_env import make_grasp_env
    from activetouch.sim.sim_grasp_robot import SimGraspRobot

    robot = SimGraspRobot(make_grasp_env("grasp-box-0"))
    frames = check_robot(robot, command=GuardedMoveCommand.stay)
    reset = frames[0]
    assert reset.joint_positions.shape == (7,) and reset.arm.gripper_positions.shape == (2,)
    assert reset.arm.command.shape == (9,) and reset.motion is None and reset.grasp_success is None
    assert len(reset.points) == 0 and reset.object_pose is not None  # touch only: no points, truth for metrics
    log = frames[2].motion
    assert log.num_observations >= 1 and log.joint_positions.shape == (log.num_observations + 1, 7)
    assert log.command.shape[1] == 9 and log.contact.dtype == bool
    spec = robot.env.spec
    stay = GuardedMoveCommand.stay(frames[-1])
    robot.act(GuardedMoveCommand(stay.waypoints, guard_force=50.0))  # one command under its own guard threshold
    assert robot.env.spec is spec  # the task's thresholds are back
    with pytest.raises(ProtocolError, match="executes GuardedMoveCommand and GraspCommand"):
        robot.act(EeDeltaCommand(np.zeros(3)))
    with pytest.raises(ProtocolError, match="at most 200 via-points"):
        robot.act(GuardedMoveCommand(np.tile(frames[-1].motion.ee[-1], (201, 1))))
    done = robot.act(GraspCommand(robot.env.true_state()))
    assert isinstance(done.grasp_success, bool) and done.stamp > frames[-1].stamp
    with pytest.raises(ProtocolError, match="ended with the grasp"):
        robot.act(GuardedMoveCommand.stay(done))
    robot.close()


def test_the_grasp_loop_sees_the_same_observations_through_the_protocol():
    """GraspRobotEnv(SimGraspRobot(env), model) gives the loop exactly GraspEnv's observations and plans."""
    from activetouch.sim.grasp_env import GraspAction, PokeAction, TouchObservation, make_grasp_env
    from activetouch.sim.sim_grasp_robot import sim_grasp_robot_env

    direct, proto = make_grasp_env("grasp-box-0"), sim_grasp_robot_env("grasp-box-0")
    (oa, ia), (ob, ib) = direct.reset(), proto.reset()
    pairs = [(oa, ia, ob, ib)]
    for k, w in enumerate(POKES):
        pa, pb = direct.plan_poke(w), proto.plan_poke(w)  # the planner's IK chain from the robot's last frame
        for f in ("ctrl", "seg_end", "init_state", "warmstart", "q", "ctrl0"):
            np.testing.assert_array_equal(getattr(pa, f), getattr(pb, f), err_msg=f"poke {k}: plan {f}")
        np.testing.assert_array_equal(direct.ee_state(), proto.ee_state())
        a, b = direct.step(PokeAction(w)), proto.step(PokeAction(w))
        pairs.append((a[0], a[4], b[0], b[4]))
    g = direct.true_state()
    a, b = direct.step(GraspAction(g)), proto.step(GraspAction(g))
    pairs.append((a[0], a[4], b[0], b[4]))
    assert a[1:4] == b[1:4] and a[4]["grasp_success"] == b[4]["grasp_success"]
    for oa, ia, ob, ib in pairs:
        for f in dataclasses.fields(TouchObservation):
            x, y = getattr(oa, f.name), getattr(ob, f.name)
            assert (x is None) == (y is None) and (x is None or np.array_equal(x, y)), f.name
        assert torch.equal(ia["true_pose"], ib["true_pose"])
        np.testing.assert_array_equal(ia["prior_means"], ib["prior_means"])
        np.testing.assert_allclose(ib["true_state"][2], ia["true_state"][2], atol=1e-12)  # yaw from the pose matrix
    assert pairs[1][0].stopped_early and pairs[1][0].z.any(), "the first poke was meant to touch the box"
    assert not proto.model._reset_done  # the model was never reset: its own box was never where the truth is
    direct.close()
    proto.close()


def test_a_touch_method_runs_through_the_grasp_protocol_with_the_same_numbers(tmp_path, monkeypatch):
    """A grasp task whose environment is GraspRobotEnv(SimGraspRobot(...), model), registered as a user would
    register a real arm, runs the touch belief through the one episode loop (two pokes, the grasp) and gives the
    same steps and summary as the simulated task itself."""
    import dataclasses as dc

    from activetouch import registry
    from activetouch.experiments.records import read_steps
    from activetouch.experiments.runner import EpisodeConfig, run_episode
    from activetouch.sim.sim_grasp_robot import sim_grasp_robot_env

    entry = dc.replace(registry.get_task("grasp-box-0"), name="grasp-box-0-protocol",
                       make_env=lambda seed=0, **kw: sim_grasp_robot_env("grasp-box-0", seed=seed, **kw))
    monkeypatch.setitem(registry._TASKS, "grasp-box-0-protocol", entry)
    cfg = dict(method="scripted-poke", seed=0, particles=20, planner={"pokes": POKES}, figures=False, progress=False)
    sa = run_episode(EpisodeConfig(task="grasp-box-0", **cfg), tmp_path / "direct")
    sb = run_episode(EpisodeConfig(task="grasp-box-0-protocol", **cfg), tmp_path / "protocol")
    a, b = read_steps(tmp_path / "direct" / "steps.csv"), read_steps(tmp_path / "protocol" / "steps.csv")
    assert len(a) == len(b) == 4  # the reset, two pokes, the grasp
    assert int(a[1]["n_contacts"]) >= 1 and a[1]["stopped_early"] == "1"  # the first poke touched the box
    same = lambda r: {k: v for k, v in r.items() if not k.endswith("_s")}  # noqa: E731 (timings differ)
    assert [same(r) for r in a] == [same(r) for r in b]
    assert sa["grasped"] and sb["grasped"]
    skip = {"task", "config", "platform", "wall_s", "median_plan_s"}
    assert {k: v for k, v in sa.items() if k not in skip} == {k: v for k, v in sb.items() if k not in skip}


@pytest.mark.parametrize("make, message", [
    (lambda: GuardedMoveCommand(np.zeros((2, 3))), r"waypoints must have shape \(K, 4\)"),
    (lambda: GuardedMoveCommand(np.zeros((0, 4))), r"waypoints must have shape \(K, 4\) with K >= 1"),
    (lambda: GuardedMoveCommand([[0.4, 0.0, np.nan, 0.0]]), "waypoints must be finite"),
    (lambda: GuardedMoveCommand("up"), "waypoints must be a numeric array"),
    (lambda: GuardedMoveCommand([[0.4, 0.0, 0.1, 0.0]], guard_force=-1.0), "guard_force must be a finite force > 0"),
    (lambda: GuardedMoveCommand([[0.4, 0.0, 0.1, 0.0]], guard_force=True), "guard_force must be a finite force > 0"),
    (lambda: GraspCommand(np.zeros(2)), r"grasp state must have shape \(3,\)"),
    (lambda: GraspCommand([0.4, 0.0, np.inf]), "grasp state must be finite"),
    (lambda: GraspCommand([0.4, 0.0, 0.0], guard_force=float("nan")), "guard_force must be a finite force > 0"),
])
def test_bad_grasp_commands_are_named(make, message):
    with pytest.raises(ProtocolError, match=message):
        make()
    cmd = GuardedMoveCommand([[0.4, 0.0, 0.1, 0.0]], guard_force=2)
    assert cmd.waypoints.dtype == np.float64 and not cmd.waypoints.flags.writeable and cmd.guard_force == 2.0


def _grasp_frame(arm=None, **motion) -> SensorFrame:
    log = MotionLog(command=np.zeros((3, 9)), contact=np.array([False, True, False]), contact_torque=np.zeros(3),
                    ee_force=np.zeros(3), observed=np.array([1, 2]), joint_positions=np.zeros((3, 7)),
                    ee=np.zeros((3, 4)), stopped=True)
    base = ArmState(joint_velocities=np.zeros(7), gripper_positions=np.zeros(2), gripper_velocities=np.zeros(2),
                    command=np.zeros(9))
    return _frame(points=np.zeros((0, 3)), semantics=np.zeros(0, int), source=np.zeros(0, int),
                  arm=dataclasses.replace(base, **(arm or {})), motion=dataclasses.replace(log, **motion))


@pytest.mark.parametrize("arm, motion, message", [
    ({"command": np.zeros(8)}, {}, r"arm.command must have shape \(9,\)"),
    ({"joint_velocities": np.full(7, np.inf)}, {}, "arm.joint_velocities must be finite"),
    ({}, {"command": np.zeros((3, 8))}, r"motion.command must have shape \(\?, 9\)"),
    ({}, {"contact": np.zeros(3)}, "motion.contact must be a bool array"),
    ({}, {"observed": np.array([2, 1])}, "motion.observed must increase strictly"),
    ({}, {"observed": np.array([1, 3])}, "motion.observed must increase strictly"),
    ({}, {"joint_positions": np.zeros((2, 7))}, r"motion.joint_positions must have shape \(3, 7\)"),
    ({}, {"stopped": "yes"}, "motion.stopped must be a bool"),
])
def test_bad_grasp_frames_are_named(arm, motion, message):
    check_frame(_grasp_frame())  # the base frame is valid
    with pytest.raises(ProtocolError, match=message):
        check_frame(_grasp_frame(arm, **motion))


def test_the_grasp_wrapper_refuses_a_robot_without_arm_state():
    from types import SimpleNamespace

    from activetouch.protocol import GraspRobotEnv
    from activetouch.sim.grasp_tasks import get_grasp_spec

    class Rummager:  # the rummaging frames: no ArmState
        def reset(self):
            return _frame()

        def observe(self):
            return _frame()

        def act(self, command):
            return _frame()

    model = SimpleNamespace(spec=get_grasp_spec("grasp-box-0"), object=None, gripper=None)  # reset reads the spec only
    with pytest.raises(ProtocolError, match="must carry arm"):
        GraspRobotEnv(Rummager(), model).reset()
    with pytest.raises(ValueError, match="prior_means must be a finite"):
        GraspRobotEnv(Rummager(), model, prior_means=np.zeros((2, 2))).reset()

"""The robot / sensor protocol (activetouch.protocol) and the simulator's implementations of it (sim.sim_robot,
sim.sim_grasp_robot, sim.sim_clutter_robot)."""
from __future__ import annotations

import dataclasses
import math

import numpy as np
import pytest
import torch

from activetouch import sim
from activetouch.protocol import (CAMERA, PRIOR, SURFACE, TOUCH, ArmState, EeDeltaCommand, GraspCommand,
                                  GuardedMoveCommand, MotionLog, PickCommand, ProtocolError, PushCommand, RobotEnv,
                                  SensorFrame, TouchCommand, ViewCommand, check_frame, check_robot)
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


# ---------------------------------------------------------------------------------------------------- clutter tasks
# clutter-mustard seed 0: the mustard bottle at (0.328, 0.003) among a sugar box (1), a potted meat can (2, at
# (0.504, 0.032)), a foam brick (3, at (0.429, -0.010)) and a bleach bottle (4)
OVERHEAD = ([0.14, 0.0, 0.62], [0.33, 0.0, 0.10])  # the declutter phase's 70 deg view of the pile


def _clutter_script():
    """A view, a touch at the target's -x side, a push of the foam brick away along +y, a pick of the potted meat
    can, a second view, the stop."""
    from activetouch.sim.clutter_env import PickAction, PushAction, StopAction, TouchAction, ViewAction

    return [ViewAction(*OVERHEAD), TouchAction((0.20, 0.003, 0.10), (1.0, 0.0, 0.0), 0.2),
            PushAction(3, (0.429, -0.10, 0.025), (0.0, 1.0, 0.0), 0.12),
            PickAction(2, (0.504, 0.032, 0.02), math.pi / 2, 0.10), ViewAction((0.33, -0.5, 0.35), (0.33, 0.0, 0.08)),
            StopAction("scripted")]


def test_the_simulated_clutter_robot_passes_the_robot_contract():
    from activetouch.protocol import PushCommand, TouchCommand, ViewCommand
    from activetouch.sim.clutter_tasks import make_clutter_env
    from activetouch.sim.sim_clutter_robot import SimClutterRobot

    robot = SimClutterRobot(make_clutter_env("clutter-mustard"))
    frames = check_robot(robot, command=lambda f: ViewCommand(*OVERHEAD))  # a view moves the camera only
    reset, view = frames[0], frames[2]
    assert reset.view is None and len(reset.points) == 0 and reset.object_pose is not None
    assert reset.joint_positions.shape == (7,) and reset.contact_label is None
    v = view.view
    assert v.shape == (72, 96) and v.points.shape == (72, 96, 3) and v.target_label == 0
    assert int((v.labels == 0).sum()) > 30 and int((v.labels > 0).sum()) > 30  # the target and the clutter
    np.testing.assert_array_equal(view.points, v.target_points)  # the target's returns, from the camera
    assert (view.source == CAMERA).all() and (view.semantics == SURFACE).all()
    np.testing.assert_allclose(v.camera_pose, ViewCommand(*OVERHEAD).camera_pose, atol=1e-12)
    assert frames[3].stamp > view.stamp  # a view takes no physics time; the robot's clock counts its exposure
    with pytest.raises(ProtocolError, match="executes ViewCommand, TouchCommand, PushCommand and PickCommand"):
        robot.act(EeDeltaCommand(np.zeros(3)))
    with pytest.raises(ProtocolError, match=r"PushCommand.label must name a clutter object 1..4 \(0 is the target"):
        robot.act(PushCommand(0, [0.3, 0.0, 0.05], [1.0, 0.0, 0.0]))
    with pytest.raises(ProtocolError, match="max_length must be in"):  # beyond the simulated arm's reach
        robot.act(TouchCommand([0.2, 0.0, 0.1], [1.0, 0.0, 0.0], max_length=0.6))
    robot.close()


def test_the_clutter_loop_sees_the_same_observations_through_the_protocol():
    """ClutterRobotEnv(SimClutterRobot(env)) gives the loop exactly ClutterEnv's observations: views (target
    points, segmentation, organised cloud, the camera's rays), a touch, a push, a pick and the stop."""
    from activetouch.protocol import ClutterRobotEnv
    from activetouch.sim.clutter_env import ClutterObservation
    from activetouch.sim.clutter_tasks import make_clutter_env
    from activetouch.sim.sim_clutter_robot import sim_clutter_robot_env

    direct, proto = make_clutter_env("clutter-mustard"), sim_clutter_robot_env("clutter-mustard")
    assert isinstance(proto, ClutterRobotEnv)
    (oa, ia), (ob, ib) = direct.reset(seed=0), proto.reset(seed=0)
    pairs = [(oa, ia, ob, ib)]
    torch.testing.assert_close(ib["prior_pose"], ia["true_pose"], rtol=0, atol=0)  # the simulated detection
    for action in _clutter_script():
        np.testing.assert_array_equal(direct.ee_state(), proto.ee_state())
        a, b = direct.step(action), proto.step(action)
        assert a[1:4] == b[1:4]
        pairs.append((a[0], a[4], b[0], b[4]))
    for oa, ia, ob, ib in pairs:
        for f in dataclasses.fields(ClutterObservation):
            x, y = getattr(oa, f.name), getattr(ob, f.name)
            if f.name == "camera":
                assert (x is None) == (y is None)
                if x is not None:
                    assert x.pos == y.pos and x.max_depth == y.max_depth
                    np.testing.assert_array_equal(x.ray_directions(), y.ray_directions())
                    np.testing.assert_array_equal(x.intrinsics(), y.intrinsics())
                continue
            assert (x is None) == (y is None), f.name
            if isinstance(x, np.ndarray):
                assert x.dtype == y.dtype and np.array_equal(x, y, equal_nan=True), f.name
            else:
                assert x == y, f.name
        assert torch.equal(ia["true_pose"], ib["true_pose"])
        for k in ("action", "action_success", "num_actions", "stop_reason"):
            assert ia.get(k) == ib.get(k), k
        assert "object_poses" not in ib  # the clutter's poses stay in the simulator
    kinds = [p[0].kind for p in pairs]
    assert kinds == ["reset", "view", "touch", "push", "pick", "view", "stop"]
    assert pairs[2][0].success and len(pairs[2][0].points) >= 1, "the touch was meant to reach the target"
    assert pairs[3][0].success and pairs[4][0].success, "the push and the pick were meant to succeed"
    with pytest.raises(RuntimeError, match="ended"):
        proto.step(_clutter_script()[0])
    direct.close()
    proto.close()


def test_a_clutter_method_runs_through_the_protocol_with_the_same_numbers(tmp_path, monkeypatch):
    """A clutter task whose environment is ClutterRobotEnv(SimClutterRobot(...)), registered as a user would register
    a real arm (its prior around the robot's detection), runs the paper's method (views, a declutter push, views, a
    touch, the stop) through the one episode loop and gives the same steps and summary as the simulated task itself,
    while the estimator and the planner see no ground truth: ``info`` reaches them without ``true_pose`` and the
    wrapper's truth accessors raise (only the loop's metrics read ``info["true_pose"]``)."""
    import dataclasses as dc

    from activetouch import registry
    from activetouch.experiments.estimators import TiqfEstimator
    from activetouch.experiments.records import read_steps
    from activetouch.experiments.runner import EpisodeConfig, run_episode
    from activetouch.methods import QUICK_CLUTTER
    from activetouch.protocol import ClutterRobotEnv, detection_prior
    from activetouch.sim.sim_clutter_robot import sim_clutter_robot_env

    entry = dc.replace(registry.get_task("clutter-mustard"), name="clutter-mustard-protocol", prior=detection_prior,
                       make_env=lambda seed=0, **kw: sim_clutter_robot_env("clutter-mustard", seed=seed, **kw))
    monkeypatch.setitem(registry._TASKS, "clutter-mustard-protocol", entry)
    cfg = dict(method="tiqf-visuo-tactile", seed=0, planner=dict(QUICK_CLUTTER), figures=False, progress=False)
    sa = run_episode(EpisodeConfig(task="clutter-mustard", **cfg), tmp_path / "direct")

    blind = lambda info: {k: v for k, v in info.items() if k != "true_pose"}  # noqa: E731
    init, observe = TiqfEstimator.initialise, TiqfEstimator.observe
    monkeypatch.setattr(TiqfEstimator, "initialise", lambda self, task, obs, info, gen: init(self, task, obs,
                                                                                            blind(info), gen))
    monkeypatch.setattr(TiqfEstimator, "observe", lambda self, obs, info, ee, gen: observe(self, obs, blind(info),
                                                                                         ee, gen))

    def no_truth(self):
        raise AssertionError("an estimator or planner read the ground truth")

    monkeypatch.setattr(ClutterRobotEnv, "true_pose", no_truth)
    monkeypatch.setattr(ClutterRobotEnv, "object_poses", no_truth)
    sb = run_episode(EpisodeConfig(task="clutter-mustard-protocol", **cfg), tmp_path / "protocol")

    a, b = read_steps(tmp_path / "direct" / "steps.csv"), read_steps(tmp_path / "protocol" / "steps.csv")
    acts = [r["action"] for r in a]
    assert acts[0] == "reset" and acts[-1] == "stop" and "view" in acts and "touch" in acts
    assert {"push", "pick"} & set(acts), "the episode was meant to declutter"
    same = lambda r: {k: v for k, v in r.items() if not k.endswith("_s")}  # noqa: E731 (timings differ)
    assert len(a) == len(b) and [same(r) for r in a] == [same(r) for r in b]
    skip = {"task", "config", "platform", "wall_s", "median_plan_s"}
    assert {k: v for k, v in sa.items() if k not in skip} == {k: v for k, v in sb.items() if k not in skip}


@pytest.mark.parametrize("make, message", [
    (lambda: ViewCommand([0.1, 0.0], OVERHEAD[1]), r"ViewCommand.position must have shape \(3,\)"),
    (lambda: ViewCommand([0.1, np.nan, 0.5], OVERHEAD[1]), "ViewCommand.position must be finite"),
    (lambda: ViewCommand(OVERHEAD[1], OVERHEAD[1]), "ViewCommand.position and look_at coincide"),
    (lambda: ViewCommand([0.3, 0.0, 0.6], [0.3, 0.0, 0.0]), "ViewCommand looks straight up or down"),
    (lambda: TouchCommand([0.2, 0.0, 0.1], [1.0, 1.0, 0.0]), "TouchCommand.direction must be a unit vector"),
    (lambda: TouchCommand("here", [1.0, 0.0, 0.0]), "TouchCommand.start must be a numeric array"),
    (lambda: TouchCommand([0.2, 0.0, 0.1], [1.0, 0.0, 0.0], 0.0), "TouchCommand.max_length must be a finite"),
    (lambda: PushCommand(-1, [0.4, 0.0, 0.03], [1.0, 0.0, 0.0]), "PushCommand.label must be an object label"),
    (lambda: PushCommand(True, [0.4, 0.0, 0.03], [1.0, 0.0, 0.0]), "PushCommand.label must be an object label"),
    (lambda: PushCommand(1, [0.4, 0.0, 0.03], [0.0, 0.0, 2.0]), "PushCommand.direction must be a unit vector"),
    (lambda: PushCommand(1, [0.4, 0.0, 0.03], [1.0, 0.0, 0.0], np.inf), "PushCommand.length must be a finite"),
    (lambda: PickCommand(1.5, [0.5, 0.0, 0.02], 0.0, 0.06), "PickCommand.label must be an object label"),
    (lambda: PickCommand(2, [0.5, 0.0], 0.0, 0.06), r"PickCommand.position must have shape \(3,\)"),
    (lambda: PickCommand(2, [0.5, 0.0, 0.02], np.nan, 0.06), "PickCommand.closing_angle must be a finite angle"),
    (lambda: PickCommand(2, [0.5, 0.0, 0.02], 0.0, -0.1), "PickCommand.width must be a finite number > 0"),
])
def test_bad_clutter_commands_are_named(make, message):
    with pytest.raises(ProtocolError, match=message):
        make()
    cmd = PushCommand(np.int64(2), (0.4, 0.0, 0.03), (1.0, 0.0, 0.0), 1)
    assert type(cmd.label) is int and cmd.length == 1.0 and not cmd.start.flags.writeable
    T = ViewCommand(*OVERHEAD).camera_pose  # OpenCV axes: z (forward) toward the look-at point
    fwd = np.subtract(OVERHEAD[1], OVERHEAD[0])
    np.testing.assert_allclose(T[:3, 2], fwd / np.linalg.norm(fwd), atol=1e-12)
    assert T[2, 0] == 0.0  # the image's x axis horizontal


K_TEST = np.array([[80.0, 0.0, 2.0], [0.0, 80.0, 1.5], [0.0, 0.0, 1.0]])
R_DOWN = np.diag([1.0, -1.0, -1.0])  # a camera looking straight down (a real mount may; ViewCommand cannot)


def _view(**changes):
    from activetouch.protocol import DepthView

    T = np.eye(4)
    T[:3, :3], T[:3, 3] = R_DOWN, (0.33, 0.0, 0.6)
    pts = np.full((4, 5, 3), 0.1)
    pts[0, 0] = np.nan  # no return
    labels = np.zeros((4, 5), np.int64)
    labels[0] = -1
    labels[3, 4] = 2
    base = DepthView(camera_pose=T, intrinsics=K_TEST, points=pts, labels=labels, target_label=0, max_depth=1.5)
    return dataclasses.replace(base, **changes)


@pytest.mark.parametrize("view, frame, message", [
    ({"camera_pose": 2 * np.eye(4)}, {}, "view.camera_pose is not a rigid transform"),
    ({"intrinsics": K_TEST + np.array([[0, 1.0, 0], [0, 0, 0], [0, 0, 0]])}, {}, r"view.intrinsics must be a finite"),
    ({"intrinsics": np.eye(2)}, {}, "view.intrinsics must be a finite"),
    ({"labels": np.zeros((4, 5))}, {}, r"view.labels must be a non-empty \(H, W\) int array"),
    ({"labels": np.full((4, 5), -2)}, {}, "view.labels must be object labels >= 0 or -1"),
    ({"points": np.zeros((4, 4, 3))}, {}, r"view.points must have shape \(4, 5, 3\)"),
    ({"points": np.full((4, 5, 3), np.inf)}, {}, "view.points must be float, finite or NaN"),
    ({"target_label": -1}, {}, "view.target_label must be an object label"),
    ({"max_depth": 0.0}, {}, "view.max_depth must be a finite range > 0"),
    ({}, {"contact_label": -2}, "contact_label must be an object label >= 0, -1"),
    ({}, {"contact_label": True}, "contact_label must be an object label >= 0, -1"),
    ({}, {"push_success": "yes"}, "push_success must be a bool"),
    ({}, {"view": "image"}, "view must be a DepthView"),
])
def test_bad_clutter_frames_are_named(view, frame, message):
    check_frame(_frame(view=_view(), contact_label=-1, push_success=False))  # the base frame is valid
    with pytest.raises(ProtocolError, match=message):
        check_frame(_frame(**{"view": _view(**view), **frame}))


class _ScriptedClutterRobot:
    """Answers every command with the frame fields ``answers[type(command)]`` (a robot whose segmenter calls the
    target 3) and keeps the commands."""

    def __init__(self, answers):
        self.answers, self.commands = answers, []

    def reset(self):
        return _frame(points=np.zeros((0, 3)), semantics=np.zeros(0, int), source=np.zeros(0, int))

    def observe(self):
        return self.reset()

    def act(self, command):
        self.commands.append(command)
        return _frame(**self.answers.get(type(command), {}))


def test_the_clutter_wrapper_numbers_the_target_0_for_the_planners():
    from activetouch.protocol import ClutterRobotEnv, PosedCamera
    from activetouch.sim.camera import PinholeCamera
    from activetouch.sim.clutter_env import PushAction, StopAction, TouchAction, ViewAction
    from activetouch.sim.clutter_tasks import get_clutter_spec

    v = _view(labels=np.array([[3, 0, -1, 1, 3], [3, 3, 2, 2, -1], [0, 0, 0, 3, 3], [-1, -1, -1, -1, 3]]),
              target_label=3)
    n = len(v.target_points)  # the target's 7 pixels but (0, 0), which returned nothing
    answers = {ViewCommand: dict(view=v, points=v.target_points, semantics=np.zeros(n, int),
                                 source=np.full(n, CAMERA)),
               PushCommand: dict(points=np.zeros((0, 3)), semantics=np.zeros(0, int), source=np.zeros(0, int),
                                 contact_label=0, push_success=True),
               TouchCommand: dict(contact_label=3)}  # _frame's one TOUCH point on the target, in_contact
    robot = _ScriptedClutterRobot(answers)
    env = ClutterRobotEnv(robot, get_clutter_spec("clutter-mustard"), prior_pose=np.eye(4))
    obs, info = env.reset()
    assert "true_pose" not in info and torch.equal(info["prior_pose"], torch.eye(4))
    obs = env.step(ViewAction(*OVERHEAD))[0]
    assert obs.seg.tolist() == [[0, 3, -1, 1, 0], [0, 0, 2, 2, -1], [3, 3, 3, 0, 0], [-1, -1, -1, -1, 0]]
    assert obs.success and n == int((v.labels == 3).sum()) - 1 and len(obs.points) == n
    assert isinstance(obs.camera, PosedCamera) and isinstance(obs.camera, PinholeCamera)
    np.testing.assert_allclose(obs.camera.ray_directions()[7], [0.0, 0.0, -1.0], atol=0.02)  # looking down
    obs = env.step(PushAction(3, (0.4, 0.0, 0.03), (1.0, 0.0, 0.0), 0.1))[0]
    assert robot.commands[-1].label == 0  # the planners' 3 is the robot's 0
    assert obs.kind == "push" and obs.success and obs.contact_label == 3
    obs = env.step(TouchAction((0.2, 0.0, 0.1), (1.0, 0.0, 0.0)))[0]
    assert obs.success and obs.contact_label == 0 and obs.points.shape == (1, 3)
    obs, _, terminated, _, info = env.step(StopAction("done"))
    assert terminated and obs.kind == "stop" and info["stop_reason"] == "done" and len(robot.commands) == 3
    with pytest.raises(RuntimeError, match="no ground truth"):
        env.object_poses()


def test_the_clutter_wrapper_refuses_frames_without_their_answers():
    from activetouch.protocol import ClutterRobotEnv, detection_prior
    from activetouch.sim.clutter_env import PickAction, TouchAction, ViewAction
    from activetouch.sim.clutter_tasks import get_clutter_spec

    spec = get_clutter_spec("clutter-mustard")
    env = ClutterRobotEnv(_ScriptedClutterRobot({}), spec)
    env.reset()
    with pytest.raises(ProtocolError, match="the frame of a ViewCommand must carry its DepthView"):
        env.step(ViewAction(*OVERHEAD))
    with pytest.raises(ProtocolError, match="the frame of a TouchCommand must report contact_label"):
        env.step(TouchAction((0.2, 0.0, 0.1), (1.0, 0.0, 0.0)))
    picked = ClutterRobotEnv(_ScriptedClutterRobot({PickCommand: dict(contact_label=-1)}), spec)
    picked.reset()
    with pytest.raises(ProtocolError, match="the frame of a PickCommand must report grasp_success"):
        picked.step(PickAction(1, (0.5, 0.0, 0.02), 0.0, 0.06))
    with pytest.raises(ProtocolError, match="lacks reset"):
        ClutterRobotEnv(object(), spec)
    with pytest.raises(ValueError, match=r"detection_prior needs info\['prior_pose'\]"):
        detection_prior(env, 1, torch.Generator(), info={})
    with pytest.raises(ProtocolError, match="prior_pose is not a rigid transform"):
        ClutterRobotEnv(_ScriptedClutterRobot({}), spec, prior_pose=lambda seed: np.zeros((4, 4))).reset()
    with pytest.raises(ProtocolError, match="the frame of a ViewCommand must carry its DepthView"):
        check_robot(_ScriptedClutterRobot({}), command=lambda f: ViewCommand(*OVERHEAD))

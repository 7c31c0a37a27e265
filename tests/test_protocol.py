"""The robot / sensor protocol (activetouch.protocol) and the simulator's implementation of it (sim.sim_robot)."""
from __future__ import annotations

import dataclasses

import numpy as np
import pytest
import torch

from activetouch import sim
from activetouch.protocol import (CAMERA, PRIOR, SURFACE, TOUCH, EeDeltaCommand, ProtocolError, RobotEnv,
                                  SensorFrame, check_frame, check_robot)
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

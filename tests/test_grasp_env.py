"""Tests of the blind-grasping task (activetouch.sim.grasp_env / grasp_tasks / grasp_scene): real MuJoCo physics."""
from __future__ import annotations

import math

import mujoco
import numpy as np
import pytest
import torch

from activetouch.sim.grasp_env import GraspAction, MotionPlan, PokeAction, make_grasp_env
from activetouch.sim.grasp_tasks import get_grasp_spec, registered_grasp_tasks, sample_task_instance

TOP = 0.2134  # cracker box height


@pytest.fixture(scope="module")
def env():
    e = make_grasp_env("grasp-box-1", seed=0)
    yield e
    e.close()


@pytest.fixture(scope="module")
def quiet_env():
    """Noise-free torque sensor."""
    e = make_grasp_env("grasp-box-1", seed=0, torque_noise_std=0.0)
    yield e
    e.close()


def _axes(yaw):
    return np.array([math.cos(yaw), math.sin(yaw)]), np.array([-math.sin(yaw), math.cos(yaw)])


def side_poke(state, height=0.10, standoff=0.13, n_across=10, overshoot=0.02):
    """ee waypoints: down beside the box (along its narrow object-x axis), then horizontally into its face."""
    ax, _ = _axes(state[2])
    p0 = state[:2] - standoff * ax
    p1 = state[:2] + overshoot * ax
    down = np.linspace(np.r_[p0, 0.26], np.r_[p0, height], 4)
    across = np.linspace(np.r_[p0, height], np.r_[p1, height], n_across + 1)[1:]
    xyz = np.concatenate([down, across])
    return np.concatenate([xyz, np.full((len(xyz), 1), state[2] + math.pi / 2)], axis=1)


# ------------------------------------------------------------------ tasks
def test_registry_and_specs():
    assert registered_grasp_tasks() == ["grasp-box-0", "grasp-box-1", "grasp-box-2"]
    seps = [get_grasp_spec(n).mode_separation for n in registered_grasp_tasks()]
    assert seps == [0.2, 0.3, 0.4]
    s = get_grasp_spec("grasp-box-0")
    assert (s.sigma_pos, s.sigma_yaw, s.max_actions) == (0.06, 0.5, 15)
    assert get_grasp_spec("grasp-box-0", gripper_opening=0.1).gripper_opening == 0.1
    with pytest.raises(ValueError, match="unknown grasp task"):
        get_grasp_spec("grasp-mug-0")
    with pytest.raises(ValueError, match="unknown GraspTaskSpec fields"):
        get_grasp_spec("grasp-box-0", teapot=1)
    with pytest.raises(ValueError, match="sigma_pos"):
        get_grasp_spec("grasp-box-0", sigma_pos=float("nan"))
    with pytest.raises(ValueError, match="does not fit"):
        get_grasp_spec("grasp-box-0", mode_separation=5.0)


@pytest.mark.parametrize("name", ["grasp-box-0", "grasp-box-2"])
def test_task_instances(name):
    spec = get_grasp_spec(name)
    lo, up = np.array(spec.workspace_lower), np.array(spec.workspace_upper)
    modes = set()
    for seed in range(40):
        means, k, x = sample_task_instance(spec, seed)
        assert means.shape == (2, 3) and x.shape == (3,)
        assert abs(np.linalg.norm(means[0, :2] - means[1, :2]) - spec.mode_separation) < 1e-9
        assert (means[:, :2] >= lo - 1e-12).all() and (means[:, :2] <= up + 1e-12).all()
        assert (x[:2] >= lo).all() and (x[:2] <= up).all() and -math.pi <= x[2] < math.pi
        modes.add(k)
    assert modes == {0, 1}
    a, b = sample_task_instance(spec, 7), sample_task_instance(spec, 7)
    assert np.array_equal(a[0], b[0]) and a[1] == b[1] and np.array_equal(a[2], b[2])


# ------------------------------------------------------------------ reset
def test_reset_deterministic_and_box_rests_upright(env):
    obs1, info1 = env.reset(seed=3)
    q1, state1 = env.data.qpos.copy(), info1["true_state"]
    obs2, info2 = env.reset(seed=3)
    assert np.array_equal(env.data.qpos, q1) and np.array_equal(info2["true_state"], state1)
    assert np.array_equal(info1["prior_means"], info2["prior_means"])
    _, info3 = env.reset(seed=4)
    assert not np.allclose(info3["true_state"], state1)
    env.reset(seed=3)
    assert info1["true_pose"].shape == (4, 4) and info1["true_pose"].dtype == torch.float32
    assert obs1.q.shape == (1, 7) and obs1.ee.shape == (1, 4) and obs1.z.shape == (0,)
    o = env._state_obj_q  # observations carry the robot's state only, never the true box pose
    assert np.linalg.norm(obs1.init_state[o:o + 2] - state1[:2]) > 0.3
    # the box rests: still, on the table, upright (its joints keep it upright by construction)
    T = env.true_pose()
    assert abs(T[2, 3]) < 2e-3 and T[2, 2] > 1 - 1e-9
    assert np.abs(env.data.qvel[env._obj_vadr:env._obj_vadr + 4]).max() < 1e-2
    xy = np.asarray(state1[:2])
    assert np.allclose(T[:2, 3], xy, atol=1e-4)
    # the arm starts clear of the box
    assert all(not (int(c.geom1) in env._robot_geom_set or int(c.geom2) in env._robot_geom_set)
               for c in env.data.contact[:env.data.ncon])


# ------------------------------------------------------------------ pokes and the contact signal
def test_poke_down_onto_box_contacts_and_stops(env):
    _, info = env.reset(seed=0)
    x = info["true_state"]
    W = np.array([[x[0], x[1], TOP + 0.08, 0.0], [x[0], x[1], TOP + 0.03, 0.0], [x[0], x[1], TOP - 0.03, 0.0]])
    obs, reward, term, trunc, info = env.step(PokeAction(W))
    # a guarded stop adds an observation: the trigger (z = 1) and the end of the hold (still pressing the lid)
    assert obs.stopped_early and obs.z[-2] and obs.contact_force > env.spec.guard_force
    assert obs.num_waypoints == 4 and not obs.z[:2].any() and obs.z[-1]
    assert obs.true_contact_samples[obs.z_period[-2]] and obs.z_period[-1] - obs.z_period[-2] == env.spec.stop_hold
    assert obs.ee[-1, 2] > TOP - 0.01  # stopped on the lid, not through it
    assert obs.q.shape == (5, 7) and obs.ee.shape == (5, 4) and obs.tau_norm.shape == (4,)
    assert (reward, term, trunc) == (0.0, False, False)
    # the arm stopped on the lid: the next poke can move away (up), and stops again if it presses down
    up = np.array([[x[0], x[1], TOP + 0.10, 0.0]])
    obs2, *_ = env.step(PokeAction(up))
    assert not obs2.stopped_early and abs(obs2.ee[-1, 2] - (TOP + 0.10)) < 5e-3
    obs3, *_ = env.step(PokeAction(np.array([[x[0], x[1], TOP - 0.03, 0.0], [x[0], x[1], TOP + 0.1, 0.0]])))
    assert obs3.stopped_early and obs3.num_waypoints == 2 and obs3.z[0]


def test_side_poke_into_box_contacts_and_stops(env):
    _, info = env.reset(seed=1)
    x = info["true_state"]
    obs, *_, info = env.step(PokeAction(side_poke(x)))
    assert obs.stopped_early and obs.z[:-1].any()  # the trigger; the box may have slid off by the hold's end
    assert obs.num_waypoints <= len(side_poke(x))
    moved = np.linalg.norm(info["object_states"][-1, :2] - x[:2])
    assert moved < 0.02  # the guarded stop ends the push early


def test_free_space_poke_no_contact_and_tracks_waypoints(quiet_env):
    env = quiet_env
    _, info = env.reset(seed=0)
    x = info["true_state"]
    ax, _ = _axes(x[2])
    far = x.copy()
    far[:2] = x[:2] - 0.25 * ax  # a poke next to where the box is not
    far[:2] = np.clip(far[:2], [0.2, -0.35], [0.5, 0.35])
    if np.linalg.norm(far[:2] - x[:2]) < 0.2:
        far[:2] = x[:2] + 0.25 * ax
    W = np.array([[far[0], far[1], 0.25, 0.3], [far[0], far[1], 0.15, 0.3], [far[0] + 0.03, far[1], 0.08, 0.0],
                  [far[0] + 0.03, far[1] + 0.04, 0.05, -0.4]])
    obs, *_, info = env.step(PokeAction(W))
    assert not obs.true_contact_samples.any()
    assert not obs.z.any() and not obs.z_samples.any() and not obs.stopped_early
    assert obs.num_waypoints == len(W)
    err = np.linalg.norm(obs.ee[1:, :3] - W[:, :3], axis=1)
    assert err.max() < 0.005, err
    assert np.abs(np.angle(np.exp(1j * (obs.ee[1:, 3] - W[:, 3])))).max() < 0.02
    # nobody touched the box: it stays put up to MuJoCo's soft-contact creep (~3 um/s)
    assert np.abs(info["object_states"][-1] - info["object_states"][0]).max() < 1e-4


def test_noise_gives_seeded_false_positives(env):
    rates, zs = [], []
    for rep in range(2):
        _, info = env.reset(seed=5)
        x = info["true_state"]
        W = np.array([[0.3, -0.3 if x[1] > 0 else 0.3, 0.3, 0.0], [0.3, 0.0, 0.3, 0.0], [0.35, 0.0, 0.3, 1.0]])
        obs, *_ = env.step(PokeAction(W))
        assert not obs.true_contact_samples.any()
        zs.append(obs.z_samples.copy())
        rates.append(obs.z_samples.mean())
    assert np.array_equal(zs[0], zs[1])  # the sensor noise is seeded by the reset seed
    assert len(zs[0]) > 100
    assert 0.005 < rates[0] < 0.15  # ~5 % expected (chi distribution tail at the threshold)


def test_plan_poke_is_what_step_executes(quiet_env):
    env = quiet_env
    env.reset(seed=2)
    W = np.array([[0.3, 0.1, 0.28, 0.0], [0.32, 0.12, 0.26, 0.2]])
    plan = env.plan_poke(W)
    obs, *_ = env.step(PokeAction(W))
    assert not obs.stopped_early
    assert np.array_equal(plan.ctrl, obs.ctrl) and np.array_equal(plan.seg_end, obs.seg_end)
    assert isinstance(plan, MotionPlan) and plan.guarded and not obs.motion().guarded


def test_max_actions_then_only_grasp():
    e = make_grasp_env("grasp-box-0", seed=0, max_actions=1)
    try:
        _, info = e.reset()
        W = np.array([[0.3, 0.0, 0.3, 0.0]])
        *_, trunc, _ = e.step(PokeAction(W))
        assert not trunc and e.max_steps == 2  # the last poke does not end the episode: the grasp does
        with pytest.raises(RuntimeError, match="max_actions"):
            e.step(PokeAction(W))
        _, r, term, _, info = e.step(GraspAction(info["true_state"]))
        assert term
        with pytest.raises(RuntimeError, match="terminated"):
            e.step(PokeAction(W))
    finally:
        e.close()


# ------------------------------------------------------------------ robot points
def test_robot_points_cover_the_whole_robot(env):
    env.reset(seed=0)
    q = np.stack([env.current_q(), env.ik_to_point([0.4, 0.1, 0.1], 0.5)])
    pts = env.robot_points(q, spacing=0.01)
    assert pts.shape[0] == 2 and pts.shape[2] == 3 and pts.dtype == torch.float32
    assert not torch.equal(pts[0], pts[1])
    d = env._kin
    m = env.model
    for k in range(2):
        d.qpos[env._qadr] = q[k]
        d.qpos[env._pad_qadr] = env.spec.poke_opening / 2
        mujoco.mj_kinematics(m, d)
        P = pts[k].double().numpy()
        for i in range(1, 8):  # every link has surface points close to its frame origin (on the joint axis)
            b = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_BODY, f"lbr_iiwa_link_{i}")
            assert np.linalg.norm(P - d.xpos[b], axis=1).min() < 0.08, i
        for name in ("pad_0", "pad_1", "palm"):  # and the gripper parts: points on each box's faces
            g = mujoco.mj_name2id(m, mujoco.mjtObj.mjOBJ_GEOM, name)
            local = (P - d.geom_xpos[g]) @ d.geom_xmat[g].reshape(3, 3)
            inside = (np.abs(local) <= m.geom_size[g] + 1e-6).all(axis=1)
            on_face = np.isclose(np.abs(local), m.geom_size[g], atol=1e-6).any(axis=1)
            assert (inside & on_face).sum() >= 20, name
        # the ee tip (between the pads' lower ends) is on the surface sample
        tip = d.site_xpos[env._site]
        assert np.linalg.norm(P - tip, axis=1).min() < 0.01
    coarse = env.robot_points(q[:1], spacing=0.03)
    assert coarse.shape[1] < pts.shape[1]
    opened = env.robot_points(q[:1], spacing=0.01, opening=0.09)
    assert opened.shape == pts[:1].shape and not torch.equal(opened, pts[:1])


# ------------------------------------------------------------------ rollouts
def test_rollout_reproduces_true_motion_and_keeps_far_particles(env):
    _, info = env.reset(seed=1)
    x = info["true_state"]
    obs, *_, info = env.step(PokeAction(side_poke(x, overshoot=0.03)))
    truth = info["object_states"]
    assert np.linalg.norm(truth[-1, :2] - truth[0, :2]) > 1e-4  # the poke moved the box a little
    far = truth[0] + np.array([0.0, 0.0, 0.0])
    far[:2] = truth[0, :2] + 0.35 * _axes(x[2])[1]
    states = torch.tensor(np.stack([truth[0], far]), dtype=torch.float32)
    res = env.rollout_detailed(states, obs)
    assert res.states.shape == (2, obs.num_waypoints, 3) and res.states.dtype == torch.float32
    assert res.simulated.tolist() == [True, False] and res.stop_waypoint.tolist() == [-1, -1]
    err = (res.states[0].double() - torch.as_tensor(truth[1:])).abs()
    assert err[:, :2].max() < 3e-3 and err[:, 2].max() < 0.03
    assert torch.equal(res.states[1], states[1].expand(obs.num_waypoints, 3))
    # numpy in -> float64 out; plain rollout returns the states only
    out = env.rollout(np.stack([truth[0], far]), obs)
    assert out.dtype == torch.float64 and torch.allclose(out.float(), res.states, atol=1e-6)


def test_settle_ends_each_poke_with_the_box_at_rest_and_replays_it():
    # spec.settle_time: after a poke the arm holds while the box still moves, so the next poke (and every
    # particle's rollout of it, which starts boxes at rest) begins from a resting box; the replay includes the hold.
    # Fast pokes (0.4 m/s) with a one-period hold kick the box so that it is still sliding when the poke ends.
    fast = dict(max_ee_step=0.008, stop_hold=1)
    moving_without = []
    for settle in (0.0, 1.0):
        e = make_grasp_env("grasp-box-1", seed=0, settle_time=settle, **fast)
        n_settle = int(round(settle / e.spec.control_dt))
        try:
            e.reset(seed=1)
            for overshoot in (0.03, 0.05, 0.05):
                x = e.true_state().copy()
                obs, *_, info = e.step(PokeAction(side_poke(x, overshoot=overshoot)))
                if settle == 0.0:
                    moving_without.append(e._object_moving())
                    continue
                held_out = len(obs.ctrl) > n_settle and np.allclose(obs.ctrl[-n_settle:], obs.ctrl[-1])
                assert not e._object_moving() or held_out  # at rest, or the whole settle time spent holding
                replay = e.rollout(np.asarray([x]), obs)[0].numpy()
                assert np.abs(replay[:, :2] - info["object_states"][1:, :2]).max() < 3e-3
        finally:
            e.close()
    assert any(moving_without), "the fast pokes no longer leave the box moving: the test shows nothing"


def test_rollout_skips_only_untouchable_particles(env):
    """Brute force (every particle simulated from the start) against the engine's skipping: particles it skips
    do not move in the brute-force run, simulated ones agree while the contact is short."""
    _, info = env.reset(seed=2)
    x = info["true_state"]
    rng = np.random.default_rng(0)
    P = x + rng.normal(size=(24, 3)) * np.array([0.06, 0.06, 0.5])
    plan = env.plan_poke(side_poke(x, n_across=6, overshoot=-0.02))
    plan.guarded = False
    res = env.rollout_detailed(P, plan)
    o, v, sub = env._state_obj_q, env._state_obj_v, env.spec.substeps
    init = np.tile(plan.init_state, (len(P), 1))
    init[:, o], init[:, o + 1], init[:, o + 2], init[:, o + 3] = P[:, 0], P[:, 1], env.z_rest, P[:, 2]
    init[:, v:v + 4] = 0
    state, _ = env._pool_rollout(init, env.expand_ctrl(plan.ctrl, plan.ctrl0)[None], plan.warmstart[None])
    brute = state[:, (plan.seg_end + 1) * sub - 1][..., [o, o + 1, o + 3]]
    sim = res.simulated.numpy()
    moved = np.abs(brute - P[:, None]).max(axis=(1, 2))
    assert (~sim).any() and sim.any()
    assert moved[~sim].max() < 1e-4  # only the resting jitter of a box nobody touches
    assert np.array_equal(res.states.numpy()[~sim], np.repeat(P[~sim, None], plan.num_waypoints, axis=1))
    assert (moved > 1e-3).sum() >= 1  # the poke does push some particles' boxes


def test_rollout_of_planned_joint_path_and_guard(env):
    _, info = env.reset(seed=1)
    x = info["true_state"]
    plan = env.plan_poke(side_poke(x, overshoot=0.03))
    q_plan = plan.q
    P = np.stack([x, x + np.array([0.0, 0.0, 0.0])])
    P[1, :2] += 0.4 * _axes(x[2])[1]
    guarded = env.rollout_detailed(P, plan)
    assert guarded.stop_waypoint[0] >= 0 and guarded.stop_waypoint[1] == -1
    k = int(guarded.stop_waypoint[0])
    assert torch.equal(guarded.states[0, k:], guarded.states[0, k].expand_as(guarded.states[0, k:]))
    joint = env.rollout(P, q_plan)  # (K+1, 7) joint path, interpolated in joint space
    assert joint.shape == (2, len(q_plan) - 1, 3)
    assert torch.equal(joint[1], torch.as_tensor(P[1]).expand(len(q_plan) - 1, 3))
    assert (joint[0] - torch.as_tensor(x)).abs().max() > 1e-4  # the path pushes the box at the truth


# ------------------------------------------------------------------ grasp
def test_grasp_true_pose_lifts_and_offset_fails(env):
    _, info = env.reset(seed=0)
    x = info["true_state"]
    obs, reward, term, trunc, info = env.step(GraspAction(x))
    assert term and info["grasp_success"] and reward == 1.0 and info["object_height"] > 0.05
    _, info = env.reset(seed=0)
    ax, _ = _axes(x[2])
    off = x.copy()
    off[:2] += 0.10 * ax
    *_, info = env.step(GraspAction(off))
    assert not info["grasp_success"]


def test_grasp_success_batch(env):
    _, info = env.reset(seed=2)
    x = info["true_state"]
    ax, ay = _axes(x[2])
    P = np.stack([x, x.copy(), x.copy(), x.copy()])
    P[1, :2] += 0.10 * ax  # 10 cm off across the pads: the pads land on the lid
    P[2, :2] += 0.40 * ay  # far: fails without simulation
    P[3, 2] += 0.01  # small yaw error: still fits between the pads
    ok = env.grasp_success(torch.as_tensor(P), x)
    assert ok.dtype == torch.bool and ok.tolist() == [True, False, False, True]


# ------------------------------------------------------------------ ik, reach, bad input
def test_ik_and_reach(env):
    spec = env.spec
    lo, up = np.array(spec.workspace_lower), np.array(spec.workspace_upper)
    for xy in (lo, up, [lo[0], up[1]], [up[0], lo[1]]):
        for z in (0.03, TOP + 0.06):
            p = np.array([xy[0], xy[1], z])
            assert env.reachable(p[None])[0]
            q = env.ik_to_point(p, 0.7)
            e_p, e_r = env.ik_error(q, p, 0.7)
            assert e_p < 2e-3 and e_r < 1e-2
    assert not env.reachable(np.array([[1.0, 0.0, 0.1], [-0.2, 0.0, 0.1], [0.4, 0.0, 0.6]])).any()


def test_bad_input_raises(env):
    env.reset(seed=0)
    with pytest.raises(ValueError, match="NaN"):
        PokeAction(np.array([[0.3, 0.0, np.nan, 0.0]]))
    with pytest.raises(ValueError, match="shape"):
        PokeAction(np.zeros((3, 3)))
    with pytest.raises(ValueError, match="empty"):
        PokeAction(np.zeros((0, 4)))
    with pytest.raises(ValueError, match="shape"):
        GraspAction(np.zeros(4))
    with pytest.raises(ValueError, match="NaN"):
        GraspAction(np.array([0.3, np.inf, 0.0]))
    with pytest.raises(ValueError, match="PokeAction or GraspAction"):
        env.step(np.zeros(4))
    with pytest.raises(ValueError, match="at most"):
        env.plan_poke(np.tile([0.3, 0.0, 0.3, 0.0], (env.spec.max_waypoints + 1, 1)))
    q = env.current_q()[None]
    with pytest.raises(ValueError, match="NaN"):
        env.robot_points(np.full((1, 7), np.nan))
    with pytest.raises(ValueError, match="shape"):
        env.robot_points(np.zeros((2, 6)))
    with pytest.raises(ValueError, match="spacing"):
        env.robot_points(q, spacing=0.0)
    plan = env.plan_poke(np.array([[0.3, 0.0, 0.3, 0.0]]))
    with pytest.raises(ValueError, match="NaN"):
        env.rollout(torch.tensor([[0.3, float("nan"), 0.0]]), plan)
    with pytest.raises(ValueError, match="shape"):
        env.rollout(np.zeros((5, 2)), plan)
    with pytest.raises(ValueError, match="empty"):
        env.rollout(np.zeros((0, 3)), plan)
    with pytest.raises(ValueError, match="motion must be"):
        env.rollout(np.zeros((1, 3)), "poke")
    with pytest.raises(ValueError, match="q_plan"):
        env.rollout(np.zeros((1, 3)), np.zeros((1, 7)))
    with pytest.raises(ValueError, match="grasp state"):
        env.grasp_success(np.zeros((1, 3)), np.zeros(2))
    fresh = make_grasp_env("grasp-box-0")
    try:
        with pytest.raises(RuntimeError, match="reset"):
            fresh.step(PokeAction(np.zeros((1, 4))))
    finally:
        fresh.close()

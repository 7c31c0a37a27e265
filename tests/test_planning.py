"""RUMI planning: stochastic dynamics (Alg. 7), C_I (Eq. 29), C_R (Alg. 8) and the KMPPI planner."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from activetouch import objects
from activetouch.geometry import VoxelGrid, pose_from_xyz_yaw
from activetouch.information import compute_field
from activetouch.planning import (
    GripperModel,
    InformationCost,
    ReachabilityCost,
    RumiPlanner,
    RumiPlannerConfig,
    StochasticDynamics,
)

from synthetic import paddle, toy_field

BODY_OFFSET = torch.tensor([-0.012, 0.0, 0.0])  # mug body axis in the object frame (handle along +x)
CENTRE = torch.tensor([0.40, 0.0, 0.0])
BODY_R = 0.0466
Z = 0.04  # planar ee height (the handle's height)


def mug_particles(yaws):
    P = len(yaws)
    R = pose_from_xyz_yaw(torch.zeros(P, 3), yaws)[:, :3, :3]
    t = CENTRE - torch.einsum("pij,j->pi", R, BODY_OFFSET)
    return pose_from_xyz_yaw(t, yaws), torch.full((P,), 1.0 / P)


@pytest.fixture(scope="module")
def mug():
    return objects.load("mug")


@pytest.fixture(scope="module")
def workspace():
    return VoxelGrid([0.1, -0.3, 0.0], [0.7, 0.3, 0.1], 0.01)


@pytest.fixture(scope="module")
def field(mug, workspace):
    poses, w = mug_particles(torch.linspace(-math.pi / 3, math.pi / 3, 36))
    return compute_field(mug, poses, w, workspace, lam=2.0, free_scale=10.0, alpha=-0.004)


@pytest.fixture(scope="module")
def gripper():
    h, m = paddle()
    return GripperModel(h, m)


def make_dynamics(field, gripper, workspace, seed=0):
    return StochasticDynamics(field, gripper, "planar", workspace.lower, workspace.upper,
                              generator=torch.Generator().manual_seed(seed))


def rollout(dyn, ee, u, steps, n=200):
    s = torch.tensor([*ee, 0.0, 0.0, 0.0]).expand(n, 7).clone()
    uu = torch.tensor(u, dtype=torch.float32).expand(n, 3)
    for _ in range(steps):
        s = dyn(s, uu)
    return s


# ---------------------------------------------------------------------------------------------- dynamics
def test_free_space_motion_far_from_object(field, gripper, workspace):
    dyn = make_dynamics(field, gripper, workspace)
    s = rollout(dyn, [0.15, -0.25, Z, 0.0], [0.5, 1.0, 0.2], 2)
    assert torch.allclose(s[:, 4:], torch.zeros(200, 3))
    expected = torch.tensor([0.15 + 2 * 0.04, -0.25 + 2 * 0.08, Z, 0.2])
    assert torch.allclose(s[:, :4], expected.expand(200, 4), atol=1e-5)
    # clipped to the workspace
    s = rollout(dyn, [0.15, -0.25, Z, 0.0], [-1.0, 0.0, 0.0], 3)
    assert torch.allclose(s[:, 0], torch.full((200,), 0.1))
    # (4,) bounds also clip the yaw (the sim's ee_lower / ee_upper)
    lo4 = torch.tensor([0.1, -0.3, 0.0, -0.6])
    up4 = torch.tensor([0.7, 0.3, 0.1, 0.6])
    dyn4 = StochasticDynamics(field, gripper, "planar", lo4, up4, generator=torch.Generator().manual_seed(0))
    s = rollout(dyn4, [0.15, -0.25, Z, 0.0], [0.0, 0.0, 1.0], 2)
    assert torch.allclose(s[:, 3], torch.full((200,), 0.6))


def test_no_displacement_in_known_free_space_near_object(field, gripper, workspace):
    # 6 cm in front of the mug body, sliding sideways: free space all particles agree on
    dyn = make_dynamics(field, gripper, workspace)
    x0 = float(CENTRE[0]) - BODY_R - 0.06 - 0.01
    s = rollout(dyn, [x0, -0.1, Z, 0.0], [0.0, 1.0, 0.0], 3)
    assert torch.equal(s[:, 4:], torch.zeros(200, 3))
    moved = (s[:, 1] - (-0.1 + 3 * 0.08)).abs() < 1e-5
    assert float(moved.float().mean()) > 0.95


def test_head_on_drive_pushes_object(field, gripper, workspace):
    # Half-speed actions (1 cm mini steps): at full speed the 2 cm mini steps can jump past the mug's 3.5 mm
    # wall (1 cm field cells) and the contact point's normal then faces the robot -> Alg. 7 holds the robot.
    dyn = make_dynamics(field, gripper, workspace)
    x0 = float(CENTRE[0]) - BODY_R - 0.01 - 0.03  # plate front 3 cm from the body
    s = rollout(dyn, [x0, 0.0, Z, 0.0], [0.5, 0.0, 0.0], 3)
    d = s[:, 4:]
    pushed = d[:, 0] > 0.01
    assert float(pushed.float().mean()) > 0.6
    assert float(d[:, 0].mean()) > 0.03
    assert float(d[:, 1].abs().mean()) < 0.2 * float(d[:, 0].mean())  # along the motion
    assert torch.equal(d[:, 2], torch.zeros(200))  # planar motion, planar push
    # the displacement never exceeds the robot's own travel
    assert torch.all(d[:, 0] <= s[:, 0] - x0 + 1e-5)
    # d keeps growing along the motion
    s5 = rollout(dyn, [x0, 0.0, Z, 0.0], [0.5, 0.0, 0.0], 5)
    assert float(s5[:, 4].mean()) > float(d[:, 0].mean()) + 0.01


def test_tangential_contact_holds_robot(field, gripper, workspace):
    # plate front touching the body's front, moving sideways: normal ~ -x, motion ~ +y -> not pushing
    dyn = make_dynamics(field, gripper, workspace)
    x0 = float(CENTRE[0]) - BODY_R - 0.01 - 0.002
    s = rollout(dyn, [x0, 0.0, Z, 0.0], [0.0, 0.5, 0.0], 1)
    assert torch.equal(s[:, 4:], torch.zeros(200, 3))
    held = (s[:, 1] - 0.04).abs() > 1e-4
    assert float(held.float().mean()) > 0.5
    assert dyn.contacts > 0


@pytest.mark.parametrize("action_space", ["3d", "planar"])
def test_lazy_free_lookup_is_exact(field, gripper, workspace, action_space, monkeypatch):
    """Skipping p(free) look-ups by lower bounds (rollout and point level) changes nothing, bit for bit."""
    def run(screen):
        monkeypatch.setattr(StochasticDynamics, "screen", screen)
        dyn = StochasticDynamics(field, gripper, action_space, workspace.lower, workspace.upper,
                                 generator=torch.Generator().manual_seed(7))
        gen = torch.Generator().manual_seed(8)
        s = torch.zeros(300, 7)
        s[:, 0] = 0.30 + 0.06 * torch.rand(300, generator=gen)
        s[:, 1] = -0.05 + 0.1 * torch.rand(300, generator=gen)
        s[:, 2] = 0.02 + 0.1 * torch.rand(300, generator=gen) if action_space == "3d" else Z
        nu = 4 if action_space == "3d" else 3
        u = torch.rand(300, nu, generator=gen) * torch.tensor([1.0, 0.3, -0.5, 0.2][:nu])
        for _ in range(3):
            s = dyn(s, u)
        return s, dyn.contacts

    (a, ca), (b, cb) = run(True), run(False)
    assert ca > 20 and ca == cb
    assert torch.equal(a, b)
    assert float((a[:, 4:].norm(dim=-1) > 0).float().mean()) > 0.05  # some rollouts pushed the object


def test_free_lower_bounds_are_valid(field, gripper):
    """The level-1 / level-2 bounds never exceed the trilinear p(free) they bound (random poses, yaws)."""
    from activetouch.planning.dynamics import _FreeBounds

    bounds = _FreeBounds(field, gripper.points)
    gen = torch.Generator().manual_seed(3)
    n = 400
    pos = torch.stack([0.25 + 0.3 * torch.rand(n, generator=gen), -0.15 + 0.3 * torch.rand(n, generator=gen),
                       -0.01 + 0.12 * torch.rand(n, generator=gen)], -1)
    yaw = 2 * math.pi * torch.rand(n, generator=gen)
    tx, ty, tz = bounds.index_coords(gripper.points, yaw, pos)
    exact = bounds.exact(tx, ty, tz, planar_layer=False)  # (n, M)
    ee = torch.cat([pos, yaw[:, None]], -1)
    assert torch.allclose(exact, field.free_probability(GripperModel.transform(gripper.points, ee)), atol=1e-5)
    assert float(exact.min()) < 0.5  # the sample reaches the object
    point_lb = bounds.point_lower_bound(tx, ty, tz)
    assert bool((point_lb <= exact + bounds.tol).all())
    rollout_lb = bounds.rollout_lower_bound(pos)
    assert bool((rollout_lb <= exact.min(dim=1).values + bounds.tol).all())
    assert bool((rollout_lb <= point_lb.min(dim=1).values).all())
    # not vacuous: far from the mug both bounds are 1
    far = bounds.rollout_lower_bound(torch.tensor([[0.12, -0.28, 0.05]]))
    assert float(far) == 1.0


def test_dynamics_seeded_and_validated(field, gripper, workspace):
    a = rollout(make_dynamics(field, gripper, workspace, 3), [0.3, 0.0, Z, 0.0], [1.0, 0.2, 0.0], 2)
    b = rollout(make_dynamics(field, gripper, workspace, 3), [0.3, 0.0, Z, 0.0], [1.0, 0.2, 0.0], 2)
    assert torch.equal(a, b)
    dyn = make_dynamics(field, gripper, workspace)
    with pytest.raises(ValueError, match="state"):
        dyn(torch.zeros(4, 6), torch.zeros(4, 3))
    with pytest.raises(ValueError, match="u must"):
        dyn(torch.zeros(4, 7), torch.zeros(4, 4))
    with pytest.raises(ValueError, match="action_space"):
        StochasticDynamics(field, gripper, "2d", workspace.lower, workspace.upper)


# ---------------------------------------------------------------------------------------------- C_I
def brute_force_ci(field, gripper, states, r_d):
    out = []
    origin = field.grid.lower.float()
    for traj in states:
        cells = set()
        for st in traj:
            pts = GripperModel.transform(gripper.info_points, st[:4]) - st[4:]
            for c in torch.floor((pts - origin) / r_d).long().tolist():
                if all(0 <= c[k] < n for k, n in enumerate(field.grid.shape)):
                    cells.add(tuple(c))
        if not cells:
            out.append(0.0)
            continue
        centres = origin + (torch.tensor(sorted(cells), dtype=torch.float32) + 0.5) * r_d
        out.append(-float(field.information(centres).sum()))
    return torch.tensor(out)


def test_information_cost_matches_brute_force(field, gripper):
    gen = torch.Generator().manual_seed(1)
    S, H = 6, 5
    states = torch.zeros(S, H, 7)
    states[..., 0] = 0.30 + 0.1 * torch.rand(S, H, generator=gen)
    states[..., 1] = -0.08 + 0.16 * torch.rand(S, H, generator=gen)
    states[..., 2] = Z
    states[..., 3] = 3.0 * torch.rand(S, H, generator=gen)
    states[..., 4] = 0.03 * torch.rand(S, H, generator=gen)
    cost = InformationCost(field, gripper, r_d=0.01)
    got = cost(states)
    ref = brute_force_ci(field, gripper, states, 0.01)
    assert torch.allclose(got, ref, rtol=1e-4, atol=1e-7)
    assert float(got.max()) < 0  # every trajectory passes informative cells
    # chunking does not change the result
    assert torch.allclose(InformationCost(field, gripper, 0.01, chunk_points=500)(states), got, rtol=1e-5)


def test_information_cost_object_frame(field, gripper):
    """Eq. 29: moving with the object (sticking contact) collects nothing new; moving relative to it does."""
    H = 6
    base = torch.tensor([0.4237, 0.0513, Z, math.pi])  # off the cell faces (float round-off)
    steps = torch.arange(H, dtype=torch.float32) * 0.01
    stick = torch.zeros(1, H, 7)
    stick[0, :, :4] = base
    stick[0, :, 0] += steps
    stick[0, :, 4] = steps  # d_t follows the robot
    still = torch.zeros(1, H, 7)
    still[0, :, :4] = base
    slide = stick.clone()
    slide[0, :, 4] = 0.0
    cost = InformationCost(field, gripper, r_d=0.01)
    c_stick, c_still, c_slide = cost(stick), cost(still), cost(slide)
    assert torch.allclose(c_stick, c_still)
    assert float(c_slide) < float(c_still) - 1e-4


# ---------------------------------------------------------------------------------------------- C_R
def reach_frontier(grid, x_max):
    pts = grid.points()
    return (pts[:, 0] < x_max).float().reshape(grid.shape)


def brute_force_cr(field, reach, d_traj):
    W = field.grid.points()
    avg = torch.stack([field.information(W - d) for d in d_traj]).mean(0)
    return -float((avg * reach.reshape(-1)).sum() / field.info.sum())


def test_reachability_cost_matches_algorithm8(field, workspace):
    noise = torch.rand(workspace.shape, generator=torch.Generator().manual_seed(0))
    reach = 0.5 * reach_frontier(workspace, 0.38) + 0.5 * noise
    cost = ReachabilityCost(field, reach)
    gen = torch.Generator().manual_seed(2)
    d = (torch.rand(3, 4, 3, generator=gen) - 0.5) * torch.tensor([0.2, 0.2, 0.0])
    d[0, :, :] = torch.tensor([0.02, -0.03, 0.0])  # whole-cell shifts
    states = torch.zeros(3, 4, 7)
    states[..., 4:] = d
    got = cost(states)
    for k in range(3):
        ref = brute_force_cr(field, reach, d[k])
        assert abs(float(got[k]) - ref) < 2e-3 * abs(ref) + 1e-6, (k, float(got[k]), ref)
    assert torch.all(got <= 0) and torch.all(got >= -1)


def test_reachability_cost_prefers_pulling_info_into_reach(field, workspace):
    cost = ReachabilityCost(field, reach_frontier(workspace, 0.40))  # the hidden handle side is out of reach

    def c(dx):
        s = torch.zeros(1, 3, 7)
        s[0, :, 4] = torch.tensor([0.0, dx / 2, dx])
        return float(cost(s))

    assert c(-0.1) < c(0.0) < c(0.1)
    assert c(-0.1) < c(0.0) - 0.05


# ---------------------------------------------------------------------------------------------- planner
@pytest.fixture(scope="module")
def slab_ws():
    return VoxelGrid([0.0, -0.4, Z - 0.005], [0.8, 0.4, Z + 0.005], 0.01)


def test_kmppi_moves_toward_information(slab_ws, gripper):
    blob = (0.55, 0.2)
    # paper KMPPI parameters; one rollout per sample suffices here: the toy field has no contacts (f^ = f_f)
    planner = RumiPlanner(None, slab_ws, gripper.points, gripper.info_mask,
                          config=RumiPlannerConfig.info_only(rollout_samples=1), seed=0)
    planner.set_field(toy_field(slab_ws, blob))
    ee = np.array([0.25, -0.1, Z, 0.0], dtype=np.float32)
    u, timing = planner.plan(None, None, ee)
    assert u.shape == (3,) and np.all(np.abs(u) <= 1.0)
    to_blob = np.array(blob) - ee[:2]
    assert float(u[:2] @ to_blob) > 0.3 * np.linalg.norm(to_blob)
    # executing the plan with free-space motion brings the plate onto the blob
    U = torch.as_tensor(planner.planned_actions)
    q = torch.as_tensor(ee)[None]
    dists = []
    for a in U:
        q = planner._dynamics.free_space(q, a[None])
        dists.append(float((q[0, :2] - torch.tensor(blob)).norm()))
    assert min(dists) < 0.05 < np.linalg.norm(to_blob)
    for k in ("field_s", "dynamics_s", "cost_s"):
        assert timing[k] >= 0
    assert timing["plan_iters"] == planner.config.warmstart_iters + planner.config.iterations_per_plan


SMALL = dict(num_samples=64, rollout_samples=2, warmstart_iters=1)


def test_next_action_replanning_policy(slab_ws, gripper):
    planner = RumiPlanner(None, slab_ws, gripper.points, gripper.info_mask,
                          config=RumiPlannerConfig.info_only(**SMALL), seed=0)
    planner.set_field(toy_field(slab_ws, (0.5, 0.0)))
    ee = np.array([0.3, 0.0, Z, 0.0])
    flags, actions = [], []
    for contact in (False, False, False, False, True, False):
        u, t = planner.next_action(None, ee, contact)
        flags.append(t["replanned"])
        actions.append(u)
        if t["replanned"]:
            plan = planner.planned_actions.copy()
            k = 0
        else:
            k += 1
            assert np.allclose(u, plan[k])  # the remaining nominal sequence is executed as planned
    assert flags == [1.0, 0.0, 0.0, 1.0, 1.0, 0.0]  # replan after 3 actions and on contact


def test_planner_seeded(slab_ws, gripper):
    def first(seed):
        p = RumiPlanner(None, slab_ws, gripper.points, gripper.info_mask,
                        config=RumiPlannerConfig.info_only(**SMALL), seed=seed)
        p.set_field(toy_field(slab_ws, (0.5, 0.1)))
        return p.plan(None, None, [0.3, 0.0, Z, 0.0])[0]

    assert np.array_equal(first(4), first(4))
    assert not np.array_equal(first(4), first(5))


def test_planner_on_mug_belief_with_reachability(mug, slab_ws, gripper):
    """Full cost (Eq. 31) on a real field: runs, reuses its cache, reports timings, stays in bounds."""
    poses, w = mug_particles(torch.linspace(-math.pi / 3, math.pi / 3, 20))
    reach = (slab_ws, reach_frontier(slab_ws, 0.42))
    planner = RumiPlanner(mug, slab_ws, gripper.points, gripper.info_mask, reachability=reach,
                          config=RumiPlannerConfig(num_samples=100, rollout_samples=2, warmstart_iters=1), seed=0)
    ee = [0.3, 0.0, Z, 0.0]
    u, t = planner.plan(poses, w, ee)
    assert u.shape == (3,) and np.all(np.abs(u) <= 1) and np.all(np.isfinite(u))
    assert t["field_s"] > 0 and t["dynamics_s"] > 0 and t["cost_s"] > 0
    assert planner.update_field(poses, w) is False  # unchanged belief: cached field reused
    grid, values = planner.last_field
    assert values.shape == slab_ws.shape and float(values.max()) > 0


def test_config_and_validation(slab_ws, gripper):
    assert RumiPlannerConfig().beta_R == 200 and RumiPlannerConfig().horizon == 15
    assert RumiPlannerConfig.info_only().beta_R == 0 and RumiPlannerConfig.reach_only().beta_I == 0
    with pytest.raises(ValueError, match="num_support_pts"):
        RumiPlannerConfig(num_support_pts=20)
    with pytest.raises(ValueError, match="beta"):
        RumiPlannerConfig(beta_I=0.0, beta_R=0.0)
    with pytest.raises(ValueError, match="unknown"):
        RumiPlannerConfig().with_overrides(horizn=3)
    with pytest.raises(ValueError, match="reachability"):
        RumiPlanner(None, slab_ws, gripper.points, gripper.info_mask)  # beta_R = 200 needs r(x)
    with pytest.raises(ValueError, match="info_mask"):
        GripperModel(gripper.points, torch.zeros(len(gripper.points), dtype=torch.bool))
    planner = RumiPlanner(None, slab_ws, gripper.points, gripper.info_mask, config=RumiPlannerConfig.info_only(**SMALL))
    with pytest.raises(ValueError, match="poses"):
        planner.plan(None, None, [0.3, 0.0, Z, 0.0])
    planner.set_field(toy_field(slab_ws, (0.5, 0.0)))
    with pytest.raises(ValueError, match="ee_state"):
        planner.plan(None, None, [0.3, 0.0, Z])
    with pytest.raises(ValueError, match="NaN"):
        planner.plan(None, None, [0.3, float("nan"), Z, 0.0])


def test_from_env_wiring():
    """The planner builds from a sim task (workspace, gripper points, action scale, ee bounds) and plans."""
    from activetouch import sim
    from activetouch.belief import BeliefConfig

    env = sim.make("mug-0", seed=0)
    _, info = env.reset(seed=0)
    planner = RumiPlanner.from_env(env, BeliefConfig(), seed=0, beta_R=0.0, num_samples=32, rollout_samples=1,
                                   warmstart_iters=0)
    assert planner.workspace.shape[2] == 1 and planner.nu == env.action_dim
    assert planner.alpha == -BeliefConfig().violation_tolerance and planner.free_scale == BeliefConfig().free_scale
    T = torch.as_tensor(np.asarray(info["true_pose"]), dtype=torch.float32)
    poses = T.expand(4, 4, 4).clone()
    poses[:, :3, :3] = pose_from_xyz_yaw(torch.zeros(4, 3), torch.tensor([0.0, 0.5, 1.0, 1.5]))[:, :3, :3] @ T[:3, :3]

    class Belief:
        pass

    b = Belief()
    b.poses, b.weights = poses, torch.full((4,), 0.25)
    u, t = planner.next_action(b, env.ee_state(), False)
    assert u.shape == (env.action_dim,) and np.all(np.abs(u) <= 1)
    assert set(t) >= {"field_s", "dynamics_s", "cost_s"}

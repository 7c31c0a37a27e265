"""Baselines of RUMI section V-H: GPVR (GP implicit surface variance, Eq. 37) and Slide."""
from __future__ import annotations

import inspect
import math

import numpy as np
import pytest
import torch

from activetouch import objects
from activetouch.geometry import VoxelGrid, pose_from_xyz_yaw
from activetouch.information import FREE, InformationField
from activetouch.observations import Features, Semantics
from activetouch.planning import (
    GPImplicitSurface,
    GpvrConfig,
    GpvrPlanner,
    GPVarianceCost,
    GripperModel,
    RumiPlanner,
    RumiPlannerConfig,
    SlideConfig,
    SlidePlanner,
    gp_training_data,
)

from synthetic import paddle
from synthetic import toy_field as info_blob_field

Z = 0.04  # planar ee height of the synthetic tasks
SMALL = dict(num_samples=64, rollout_samples=2, warmstart_iters=1)  # KMPPI kept small: these are wiring tests


@pytest.fixture(scope="module", autouse=True)
def one_thread():
    """One torch thread, as the sweep's workers run (on a shared 2-core machine, two OpenMP threads per process
    made the GP fits several times slower); restored afterwards."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def gripper():
    return GripperModel(*paddle())


@pytest.fixture(scope="module")
def slab():
    return VoxelGrid([0.0, -0.4, Z - 0.005], [0.8, 0.4, Z + 0.005], 0.01)


@pytest.fixture(scope="module")
def mug():
    return objects.load("mug")


def disc_field(grid, centre=(0.5, 0.0), radius=0.08):
    """Hand-made field: p(free) = 0.5 inside a disc (where the object may be), 1 elsewhere; no information."""
    pts = grid.points()
    inside = ((pts[:, :2] - torch.tensor(centre)) ** 2).sum(-1) < radius**2
    probs = torch.zeros(pts.shape[0], 3)
    probs[:, FREE] = torch.where(inside, 0.5, 1.0)
    probs[:, Semantics.SURFACE] = 1.0 - probs[:, FREE]
    lo = grid.lower.float()
    return InformationField(grid, probs.reshape(*grid.shape, 3), torch.zeros(grid.shape),
                            torch.zeros(*grid.shape, 3), lo, lo)


def ring_features(centre=(0.5, 0.0), r=0.05, n=24, z=Z):
    """Surface points on a circle (a round object seen all around) and free points outside it."""
    a = torch.linspace(0, 2 * math.pi, n + 1)[:-1]
    surf = torch.stack([centre[0] + r * torch.cos(a), centre[1] + r * torch.sin(a), torch.full_like(a, z)], -1)
    free = torch.stack([centre[0] + 2.5 * r * torch.cos(a), centre[1] + 2.5 * r * torch.sin(a),
                        torch.full_like(a, z)], -1)
    return Features(torch.cat([surf, free]), torch.cat([torch.full((n,), 0), torch.full((n,), 1)]))


# ---------------------------------------------------------------------------------------------- the GP
def test_gp_fits_surface_and_free_labels():
    g = torch.Generator().manual_seed(0)
    d = torch.randn(60, 3, generator=g, dtype=torch.float64)
    d = d / d.norm(dim=1, keepdim=True)
    c = torch.tensor([0.4, 0.0, 0.05], dtype=torch.float64)
    surf = c + 0.05 * d  # a sphere of radius 5 cm
    free = c + 0.12 * d  # a shell outside it
    gp = GPImplicitSurface(GpvrConfig(), lengthscale=0.07)
    loss = gp.fit(torch.cat([surf, free]), torch.cat([torch.zeros(60), torch.ones(60)]))
    assert math.isfinite(loss) and gp.num_data == 120
    assert bool((gp.mean(surf) < 0.5).all()) and bool((gp.mean(free) > 0.5).all())
    near = gp.variance(surf)
    far = gp.variance(torch.tensor([[0.9, 0.5, 0.05], [0.0, -0.5, 0.3]], dtype=torch.float64))
    assert float(near.max()) < float(far.min())
    # the cached posterior equals gpytorch's own exact prediction
    q = torch.cat([surf[:5], free[:5], torch.tensor([[0.9, 0.5, 0.05]], dtype=torch.float64)])
    with torch.no_grad():
        post = gp.model(q)
    assert torch.allclose(gp.mean(q, chunk=4), post.mean, atol=1e-9)
    assert torch.allclose(gp.variance(q, chunk=4), post.variance, atol=1e-9)
    hp = gp.hyperparameters()
    assert hp["lengthscale"] <= 0.07 + 1e-9  # capped at the free-point spacing (max_lengthscale = 1)
    # warm start: a refit starts from the fitted hyperparameters; reset forgets them
    gp.fit(torch.cat([surf, free]), torch.cat([torch.zeros(60), torch.ones(60)]), steps=0)
    assert gp.hyperparameters() == pytest.approx(hp)
    gp.reset()
    assert gp.num_data == 0 and gp.hyperparameters() == {}
    with pytest.raises(ValueError, match="fit the GP"):
        gp.variance(surf)
    with pytest.raises(ValueError, match="shape"):
        gp.fit(surf[:, :2], torch.zeros(60))
    with pytest.raises(ValueError, match="at least one"):
        gp.fit(torch.zeros(0, 3), torch.zeros(0))


def test_training_data_augments_and_downsamples(slab):
    field = disc_field(slab)
    occ = Features(torch.tensor([[0.5, 0.0, Z]]), Semantics.OCCUPIED)
    X = Features.concat([ring_features(), occ])
    r = 7 * slab.resolution
    x, y = gp_training_data(X, field, r)
    assert x.shape == (len(y), 3) and x.dtype == torch.float64
    n_surf = int((y == 0).sum())
    assert n_surf == 24 and bool((y[:n_surf] == 0).all()) and bool((y[n_surf:] == 1).all())
    free = x[n_surf:]
    # one free point per 7 r_w cell (world-anchored), none in the disc where p(free) = 0.5 unless observed
    cells = torch.floor(free / r).long()
    assert len(torch.unique(cells, dim=0)) == len(free)
    observed = X.free.positions.double()
    in_disc = ((free[:, :2] - torch.tensor([0.5, 0.0], dtype=torch.float64)) ** 2).sum(-1) < 0.08**2
    for p in free[in_disc]:
        assert float((observed - p).norm(dim=1).min()) < 1e-6  # only observed free points inside the disc
    assert not bool(((x - torch.tensor([0.5, 0.0, Z], dtype=torch.float64)).norm(dim=1) < 1e-6).any())  # no occ.
    # bounded size: farthest-point subsets
    x2, y2 = gp_training_data(X, field, r, max_surface_points=5, max_free_points=7)
    assert int((y2 == 0).sum()) == 5 and int((y2 == 1).sum()) == 7
    with pytest.raises(ValueError, match="Features"):
        gp_training_data(torch.zeros(3, 3), field, r)
    with pytest.raises(ValueError, match="p_free"):
        gp_training_data(X, field, r, p_free=1.5)


def test_planner_caches_normalised_variance(slab, gripper):
    planner = GpvrPlanner(None, slab, gripper.points, gripper.info_mask, config=RumiPlannerConfig.info_only(**SMALL),
                          gp_config=GpvrConfig(fit_steps=30), seed=0)
    planner.set_field(disc_field(slab))
    X = ring_features()
    u, t = planner.plan(None, None, [0.3, 0.0, Z, 0.0], features=X)
    assert u.shape == (3,) and u.dtype == np.float32 and np.all(np.abs(u) <= 1)
    var = planner.variance
    assert var.shape == slab.shape and float(var.max()) == pytest.approx(1.0) and float(var.min()) >= 0
    grid, values = planner.last_field
    assert torch.equal(values, var)
    at_data = slab.interpolate(var, X.surface.positions)
    assert float(at_data.max()) < float(var.median())  # low next to data ...
    assert float(var[0, 0, 0]) > 2 * float(at_data.max())  # ... high in a corner far from it
    for k in ("field_s", "dynamics_s", "cost_s", "mppi_s", "gp_fit_s"):
        assert t[k] >= 0
    assert t["gp_fit_s"] > 0 and t["cost_s"] > 0 and t["dynamics_s"] > 0
    assert planner.describe()["gp_points"] > 24


def test_gpvr_next_action_refits_every_step_and_is_seeded(slab, gripper):
    def run(seed):
        p = GpvrPlanner(None, slab, gripper.points, gripper.info_mask, config=RumiPlannerConfig.info_only(**SMALL),
                        gp_config=GpvrConfig(fit_steps=10), seed=seed)
        p.set_field(disc_field(slab))
        out = []
        for contact in (False, False):
            out.append(p.next_action(None, [0.3, 0.0, Z, 0.0], contact, features=ring_features()))
        return p, out

    p, out = run(3)
    (u1, t1), (u2, t2) = out
    assert t1["replanned"] == 1.0 and t2["replanned"] == 0.0
    assert t1["gp_fit_s"] > 0 and t2["gp_fit_s"] > 0  # refit after every execution step
    assert set(t1) == set(t2)  # same columns on every step
    assert np.allclose(u2, p.planned_actions[1])
    _, again = run(3)
    assert np.array_equal(u1, again[0][0]) and np.array_equal(u2, again[1][0])
    with pytest.raises(ValueError, match="features"):
        p.next_action(None, [0.3, 0.0, Z, 0.0], False)
    p.reset()
    with pytest.raises(ValueError, match="features"):
        p.plan(None, None, [0.3, 0.0, Z, 0.0])


def test_gpvr_config_validation():
    assert GpvrConfig().discount == 0.99 and GpvrConfig().fit_steps == 50 and GpvrConfig().free_downsample == 7.0
    assert GpvrConfig().p_free == 0.99 and GpvrConfig().matern_nu == 1.5
    for bad in (dict(discount=0.0), dict(discount=1.5), dict(fit_steps=-1), dict(matern_nu=2.0),
                dict(p_free=1.0), dict(free_downsample=0.0), dict(max_lengthscale=0.1),
                dict(max_surface_points=0), dict(learning_rate=float("nan"))):
        with pytest.raises(ValueError):
            GpvrConfig(**bad)
    with pytest.raises(ValueError, match="unknown"):
        GpvrConfig().with_overrides(discout=0.9)


# ---------------------------------------------------------------------------------------------- Eq. 37
def brute_force_step(cost: GPVarianceCost, state: torch.Tensor) -> float:
    """sum over the distinct D cells hit by h_I at one state of var at the cell centre (0 outside W)."""
    h = cost._points_for(state[None, None])
    pts = GripperModel.transform(h, state[:4]) - state[4:7]
    cells = {tuple(int(v) for v in torch.floor((p - cost.origin) / cost.r_d)) for p in pts}
    n = cost.n_cells
    total = 0.0
    for c in cells:
        if all(0 <= c[k] < n[k] for k in range(3)):
            centre = cost.origin + (torch.tensor(c, dtype=torch.float32) + 0.5) * cost.r_d
            total += float(cost.grid.interpolate(cost.variance, centre[None], outside=0.0)[0])
    return total


def state(x, y, yaw=0.0, z=Z, d=(0.0, 0.0, 0.0)):
    return torch.tensor([x, y, z, yaw, *d])


def test_eq37_cost_prefers_high_variance_and_discounts(slab, gripper):
    pts = slab.points()
    var = torch.where(pts[:, 0] > 0.5, 1.0, 0.1).reshape(slab.shape)
    cost = GPVarianceCost(slab, var, gripper, r_d=0.01, discount=0.99)
    H = 15
    high = torch.stack([state(0.6, -0.2 + 0.02 * t) for t in range(H)])[None]
    low = torch.stack([state(0.3, -0.2 + 0.02 * t) for t in range(H)])[None]
    assert float(cost(high)) < float(cost(low)) < 0
    # discounting: the same high-variance cells count less later in the trajectory
    early = torch.stack([state(0.6, 0.0)] + [state(0.3, -0.2 + 0.02 * t) for t in range(1, H)])[None]
    late = torch.stack([state(0.3, -0.2 + 0.02 * t) for t in range(1, H)] + [state(0.6, 0.0)])[None]
    assert float(cost(early)) < float(cost(late))
    # per-step de-duplication: staying on one state counts its cells at every step (Eq. 29 would count them once)
    still = state(0.6, 0.0).expand(1, H, 7)
    v0 = float(cost.step_values(still[:, :1])[0, 0])
    assert float(cost(still)) == pytest.approx(-v0 * sum(0.99**t for t in range(H)), rel=1e-5)
    # the cost is exactly Eq. 37: -sum_t beta^(t-1) sum over distinct cells (brute force), rotated and displaced
    g = torch.Generator().manual_seed(0)
    S = torch.stack([state(float(torch.rand(1, generator=g)) * 0.8, float(torch.rand(1, generator=g)) * 0.8 - 0.4,
                           yaw=float(torch.rand(1, generator=g)) * 6.0, d=(0.01, -0.02, 0.0)) for _ in range(H)])
    ref = [brute_force_step(cost, s) for s in S]
    got = cost.step_values(S[None])[0]
    assert got.tolist() == pytest.approx(ref, rel=1e-5, abs=1e-6)
    assert float(cost(S[None])) == pytest.approx(-sum(r * 0.99**t for t, r in enumerate(ref)), rel=1e-5)
    # both exact de-duplication paths (close pairs / sort) agree
    h = cost._points_for(S[None])
    assert torch.allclose(cost._chunk(S, h, cost.close_pairs(h)), cost._chunk(S, h, None))
    with pytest.raises(ValueError, match="shape"):
        GPVarianceCost(slab, var[:, :, 0], gripper, r_d=0.01)
    with pytest.raises(ValueError, match="discount"):
        GPVarianceCost(slab, var, gripper, r_d=0.01, discount=0.0)


# ---------------------------------------------------------------------------------------------- Slide
class _Belief:
    def __init__(self, poses, weights):
        self.poses, self.weights = poses, weights


def mug_belief(xy=(0.45, 0.0), n=6):
    yaws = torch.linspace(-0.3, 0.3, n)
    t = torch.tensor([[xy[0], xy[1], 0.0]]).expand(n, 3)
    return _Belief(pose_from_xyz_yaw(t, yaws), torch.full((n,), 1.0 / n))


def slide_planner(mug, seed=0, action_space="planar"):
    from activetouch.sim.robot import gripper_points

    h, m = gripper_points(0.01)
    return SlidePlanner(mug, h, m, action_space=action_space, seed=seed)


def test_slide_moves_toward_weighted_centre(mug):
    near, far = mug_belief((0.45, 0.0)), mug_belief((0.45, 0.3))
    b = _Belief(torch.cat([near.poses, far.poses]), torch.cat([torch.full((6,), 0.8 / 6), torch.full((6,), 0.2 / 6)]))
    planner = slide_planner(mug)
    centre = planner.centre(b.poses, b.weights)
    assert centre.tolist() == pytest.approx([0.45, 0.06, 0.0407], abs=1e-3)  # bbox centre, weighted 0.8 / 0.2
    ee = np.array([0.2, -0.1, 0.02, 0.0], dtype=np.float32)
    u, t = planner.next_action(b, ee, False)
    assert u.shape == (3,) and u.dtype == np.float32 and u[2] == 0 and planner.last_mode == "approach"
    to_c = centre[:2].numpy() - ee[:2]
    assert float(u[:2] @ to_c) / (np.linalg.norm(u[:2]) * np.linalg.norm(to_c)) > 0.999
    assert np.linalg.norm(u[:2]) * 0.08 == pytest.approx(SlideConfig().approach_step, rel=1e-5)
    assert t["replanned"] == 1.0 and t["slide_s"] >= 0
    # 3-d action space: dz toward the centre height too
    p3 = slide_planner(mug, action_space="3d")
    ee3 = np.array([0.2, -0.1, 0.15, 0.0], dtype=np.float32)
    u3, _ = p3.next_action(b, ee3, False)
    to_c3 = centre.numpy() - ee3[:3]
    assert u3.shape == (4,) and u3[3] == 0
    assert float(u3[:3] @ to_c3) / (np.linalg.norm(u3[:3]) * np.linalg.norm(to_c3)) > 0.999


def test_slide_in_contact_is_tangential_with_seeded_direction(mug):
    b = mug_belief()
    T = b.poses[0]
    # an observed contact on the -x side of the mug body at the pad height
    surf = (T[:3, :3] @ torch.as_tensor(mug.sample_surface(4000, seed=0), dtype=torch.float32).T).T + T[:3, 3]
    band = surf[(surf[:, 2] - 0.03).abs() < 0.004]
    contact = band[torch.argmin(band[:, 0])]
    X = Features(contact[None], Semantics.SURFACE)
    ee = np.array([float(contact[0]) - 0.038, float(contact[1]), 0.02, math.pi / 2], dtype=np.float32)  # pad face

    dirs = set()
    for seed in range(8):
        planner = slide_planner(mug, seed=seed)
        u, _ = planner.next_action(b, ee, True, features=X)
        assert planner.last_mode == "slide" and torch.allclose(planner.last_contact, contact)
        n = planner.last_normal.numpy()
        assert n @ np.array([-1.0, 0.0]) > 0.95  # the estimated normal points out of the body (-x)
        v = u[:2] / np.linalg.norm(u[:2])
        cos = float(v @ n)
        assert -0.25 < cos < 0  # nearly tangential, slightly inward (inward = 0.2: cos = -0.196)
        assert np.sign(n[0] * v[1] - n[1] * v[0]) == planner.direction  # +1: counter-clockwise around the object
        assert u[2] == 0 and np.linalg.norm(u[:2]) * 0.08 == pytest.approx(SlideConfig().slide_step, rel=1e-5)
        again = slide_planner(mug, seed=seed)
        assert again.direction == planner.direction  # drawn once per run from the seed
        planner.reset()
        assert planner.direction == again.direction
        dirs.add(planner.direction)
    assert dirs == {1, -1}
    # without features (or far from the observed points) the contact is the pad point deepest in the belief
    planner = slide_planner(mug, seed=0)
    u, _ = planner.next_action(b, ee, True)
    assert planner.last_mode == "slide" and abs(float(u[:2] @ planner.last_normal.numpy())) < 0.25 * np.linalg.norm(
        u[:2])


def test_slide_validation(mug):
    for bad in (dict(slide_step=0.0), dict(approach_step=0.5), dict(inward=-1.0), dict(min_horizontal_normal=1.0)):
        with pytest.raises(ValueError):
            SlideConfig(**bad)
    with pytest.raises(ValueError, match="action_space"):
        slide_planner(mug, action_space="6d")
    planner = slide_planner(mug)
    with pytest.raises(ValueError, match="ee_state"):
        planner.next_action(mug_belief(), [0.2, 0.0, 0.02], False)
    with pytest.raises(ValueError, match="belief"):
        planner.next_action(None, [0.2, 0.0, 0.02, 0.0], False)
    with pytest.raises(ValueError, match="weights"):
        planner.next_action(_Belief(mug_belief().poses, torch.zeros(6)), [0.2, 0.0, 0.02, 0.0], False)


# ---------------------------------------------------------------------------------------------- wiring
def test_rumi_takes_features_and_is_unchanged(slab, gripper):
    def first(**kw):
        p = RumiPlanner(None, slab, gripper.points, gripper.info_mask, config=RumiPlannerConfig.info_only(**SMALL),
                        seed=4)
        p.set_field(info_blob_field(slab, (0.5, 0.1)))
        return p.next_action(None, [0.3, 0.0, Z, 0.0], False, **kw)[0]

    assert np.array_equal(first(), first(features=ring_features()))


def test_methods_registered():
    from activetouch.registry import get_method, methods

    assert {"gpvr", "slide"} <= set(methods())
    assert "Eq. 37" in get_method("gpvr").description and "Slide" in get_method("slide").description


def _two_steps_direct(method, tmp_path, planner_overrides):
    """Two steps of Algorithm 1 built as the runner builds them, passing features=X to the planner."""
    from activetouch import sim
    from activetouch.belief import BeliefConfig, ParticleBelief
    from activetouch.experiments.runner import build_prior
    from activetouch.observations import merge_obs, voxel_downsample
    from activetouch.registry import get_method

    env = sim.make("mug-0", seed=0)
    bcfg = BeliefConfig(num_particles=20, se2=env.spec.se2)
    obs, _ = env.reset(seed=0)
    X = voxel_downsample(obs.features, r_free=bcfg.r_free, r_surface=bcfg.r_surface)
    gen = torch.Generator().manual_seed(0)
    belief = ParticleBelief.from_prior(env.object, build_prior(env, X, 20, gen), X, bcfg, use_chsel=False,
                                       generator=gen)
    planner = get_method(method).make_planner(env, bcfg, 0, **planner_overrides)
    planner.reset()
    in_contact, rows = False, []
    for _ in range(2):
        u, timings = planner.next_action(belief, env.ee_state(), in_contact, features=X)
        assert u.shape == (env.action_dim,) and np.all(np.abs(u) <= 1) and np.isfinite(u).all()
        obs, *_ = env.step(u)
        in_contact = bool(obs.in_contact)
        X = merge_obs(X, obs.features, belief.poses, env.object, obs.dT, r_free=bcfg.r_free,
                      r_surface=bcfg.r_surface)
        belief.update(X, generator=gen)
        rows.append(timings)
    return rows


@pytest.mark.parametrize("method,overrides", [
    ("slide", {}),
    ("gpvr", {"num_samples": 100, "rollout_samples": 2, "warmstart_iters": 1, "fit_steps": 10,
              "max_surface_points": 100, "max_free_points": 100}),
])
def test_two_steps_of_a_real_episode(method, overrides, tmp_path):
    from activetouch.experiments import runner
    from activetouch.experiments.records import read_steps

    cfg = runner.EpisodeConfig(task="mug-0", method=method, steps=2, particles=20, figures=False, progress=False,
                               use_chsel=False, planner=overrides)
    passes_features = "features=" in inspect.getsource(runner.run_episode)
    try:
        summary = runner.run_episode(cfg, tmp_path)
    except ValueError as e:
        # The runner passes features=X only after its pending change and GPVR cannot plan without X: then run the
        # same two steps directly. Any other failure is a real one.
        if passes_features or "features" not in str(e):
            raise
        rows = _two_steps_direct(method, tmp_path, overrides)
        assert len(rows) == 2 and all(r["replanned"] in (0.0, 1.0) for r in rows)
        if method == "gpvr":
            assert all(r["gp_fit_s"] > 0 for r in rows)
        return
    assert summary["steps"] == 2 and len(read_steps(tmp_path / "steps.csv")) == 3

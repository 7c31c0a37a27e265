"""Tests of activetouch.belief: RUMI discrepancy (Eq. 3-9), particle belief (Algorithms 1-5), priors, CHSEL init.

The mug scenario builds observations as a side camera would give them: mesh surface points that face the
camera and are not occluded (ray cast against the posed mesh), the handle left out (it points away from the
camera), and free points along the camera rays in front of each surface point; both voxel-downsampled at
the paper's resolutions (r_d,s = 2 mm, r_d,f = 10 mm).
"""
from __future__ import annotations

import logging
import math

import numpy as np
import pytest
import torch
import trimesh

from activetouch import objects
from activetouch.belief import (
    MIN_PARTICLES,
    BeliefConfig,
    ParticleBelief,
    boltzmann_weights,
    chsel_min_batch,
    discrepancy,
    discrepancy_and_objective,
    gaussian_yaw_prior,
    mug_prior,
    optimisation_objective,
    point_costs,
    systematic_resample,
)
from activetouch.belief.optimise import local_poses
from activetouch.experiments import metrics
from activetouch.geometry import invert, pose_from_xyz_yaw, transform_points, yaw_of
from activetouch.observations import Features, merge_obs, voxel_downsample

CAMERA = np.array([0.40, 0.0, 0.06])
TRUE_XYZ = (0.80, 0.0, 0.0)
TRUE_YAW = 0.3  # the handle (+x of the mug frame) points away from the camera (camera at smaller x)


# ---------------------------------------------------------------------------------------------- fixtures
@pytest.fixture(scope="module")
def mug():
    return objects.load("mug")


@pytest.fixture(scope="module")
def body_axis(mug):
    """Object-frame point on the mug body's axis (the mesh origin is the bounding-box centre incl. handle)."""
    lo, hi = mug.bounds
    radius = float(hi[1] - lo[1]) / 2.0  # the body spans y; the handle sticks out along +x
    return torch.tensor([float(lo[0]) + radius, 0.0, 0.0])


@pytest.fixture(scope="module")
def T_true():
    return pose_from_xyz_yaw(torch.tensor(TRUE_XYZ), torch.tensor(TRUE_YAW))


def side_camera_features(obj, T, n=8000, seed=0) -> Features:
    import open3d as o3d

    pts, fi = trimesh.sample.sample_surface(obj.mesh, n, seed=seed)
    Tn = T.double().numpy()
    pw = pts @ Tn[:3, :3].T + Tn[:3, 3]
    nw = obj.mesh.face_normals[fi] @ Tn[:3, :3].T
    d = CAMERA - pw
    dist = np.linalg.norm(d, axis=1)
    d /= dist[:, None]
    scene = o3d.t.geometry.RaycastingScene()
    V = obj.mesh.vertices @ Tn[:3, :3].T + Tn[:3, 3]
    scene.add_triangles(o3d.core.Tensor(V.astype(np.float32)), o3d.core.Tensor(obj.mesh.faces.astype(np.uint32)))
    rays = np.concatenate([np.repeat(CAMERA[None], len(pw), 0), -d], 1).astype(np.float32)
    t_hit = scene.cast_rays(o3d.core.Tensor(rays))["t_hit"].numpy()
    facing = (nw * d).sum(1) > 0.1
    not_handle = pts[:, 0] < 0.035
    visible = facing & (np.abs(t_hit - dist) < 1e-3) & not_handle
    surf = pw[visible]
    free = np.concatenate([surf + d[visible] * k for k in np.arange(0.005, 0.12, 0.01)])
    free = free[free[:, 2] > 0.003]  # above the table
    f = Features(torch.tensor(np.concatenate([surf, free]), dtype=torch.float32),
                 torch.tensor([0] * len(surf) + [1] * len(free)))
    return voxel_downsample(f, r_free=0.010, r_surface=0.002)


def handle_features(obj, T, n=20000, seed=1) -> Features:
    """Surface points on the handle (as repeated touches would give them), downsampled at 2 mm."""
    pts, _ = trimesh.sample.sample_surface(obj.mesh, n, seed=seed)
    h = torch.tensor(pts[pts[:, 0] > 0.042], dtype=torch.float32)
    return voxel_downsample(Features(transform_points(T, h), 0), r_surface=0.002)


def weighted_yaw_stats(poses, w, T) -> tuple[float, float]:
    """(|weighted circular mean yaw error|, weighted circular std), degrees."""
    d = yaw_of(poses) - yaw_of(T)
    c, s = (w * torch.cos(d)).sum(), (w * torch.sin(d)).sum()
    R = float(torch.hypot(c, s))
    return math.degrees(abs(math.atan2(float(s), float(c)))), math.degrees(math.sqrt(-2 * math.log(max(R, 1e-12))))


@pytest.fixture(scope="module")
def camera_X(mug, T_true):
    return side_camera_features(mug, T_true)


@pytest.fixture(scope="module")
def handle_X(mug, T_true):
    return handle_features(mug, T_true)


# ---------------------------------------------------------------------------------------------- config
def test_config_has_table_iv_defaults():
    c = BeliefConfig()
    assert (c.num_particles, c.lam, c.resample_threshold, c.free_scale) == (100, 2.0, 5.0, 10.0)
    assert (c.sigma_t, c.sigma_R, c.n_opt, c.r_free, c.r_surface, c.beta_t) == (0.010, 0.0, 10, 0.010, 0.002, 0.03)
    with pytest.raises(ValueError, match="lam"):
        BeliefConfig(lam=-1.0)
    with pytest.raises(ValueError, match="resample_percentile"):
        BeliefConfig(resample_percentile=150.0)
    with pytest.raises(Exception):
        c.lam = 3.0  # frozen


# ---------------------------------------------------------------------------------------------- Eq. 3-9
def test_point_costs_follow_eq_4_to_6(mug, T_true):
    # object-frame probes with known exact SDF: one on the surface, points inside the thick lower wall
    # (x ~ -0.044, z = 0.03: sdf ~ -8 mm) and outside the mug
    probes = torch.tensor([[-0.044, 0.0, 0.03], [-0.044, 0.0, 0.03], [-0.090, 0.0, 0.03], [-0.044, 0.0, 0.03],
                           [-0.090, 0.0, 0.03]])
    v_exact, _ = mug.sdf(probes)
    assert float(v_exact[0]) < -0.006 and float(v_exact[2]) > 0.02
    sem = torch.tensor([1, 2, 1, 0, 2])  # free inside, occupied inside, free outside, surface inside, occ outside
    X = Features(transform_points(T_true, probes), sem)
    c = point_costs(mug, X, T_true[None], free_scale=10.0, violation_tolerance=0.004, exact=True)[0]
    v = v_exact
    expected = torch.stack([10 * torch.clamp(-0.004 - v[0], min=0), 10 * torch.clamp(v[1] - 0.004, min=0),
                            10 * torch.clamp(-0.004 - v[2], min=0), v[3].abs(), 10 * torch.clamp(v[4] - 0.004, min=0)])
    torch.testing.assert_close(c, expected, atol=1e-6, rtol=1e-5)
    assert float(c[0]) > 0.02 and float(c[1]) == 0.0 and float(c[2]) == 0.0 and float(c[4]) > 0.2
    # Eq. 3 sums over features
    total = discrepancy(mug, X, T_true[None].expand(3, 4, 4), exact=True)
    torch.testing.assert_close(total, c.sum().expand(3), rtol=1e-5, atol=1e-6)


@pytest.mark.parametrize("se2", [True, False])
def test_discrepancy_gradient_matches_finite_differences(mug, T_true, se2):
    g = torch.Generator().manual_seed(3)
    # surface points 3-6 mm off the surface (no |.| kink), free points 6-9 mm inside the thick lower wall
    # (kept only where the offset point's SDF equals the offset, i.e. away from SDF kinks / medial axes)
    surf = mug.sample_surface(80, seed=5)
    _, n = mug.sdf(surf)
    off = 0.003 + 0.003 * torch.rand(80, 1, generator=g)
    surf = surf + n * off
    v, _ = mug.sdf(surf)
    surf = surf[(v - off[:, 0]).abs() < 2e-4][:30]
    assert len(surf) == 30
    free = torch.tensor([[-0.048, 0.0, 0.03], [0.0, -0.0445, 0.028], [0.0, 0.0445, 0.032]])
    pts = torch.cat([surf, free])
    X = Features(transform_points(T_true, pts), torch.tensor([0] * 30 + [1] * 3))
    base = T_true[None].repeat(2, 1, 1).double()
    nr, nt = (1, 2) if se2 else (3, 3)
    params = torch.zeros(2, nr + nt, dtype=torch.float64)
    params[1] = torch.randn(nr + nt, generator=g, dtype=torch.float64) * 1e-3

    def f(p):
        rot = p[:, 0] if se2 else p[:, :3]
        T = local_poses(base, rot, p[:, nr:], se2)
        return discrepancy(mug, X, T, exact=True, violation_tolerance=0.001).double()

    p = params.clone().requires_grad_(True)
    f(p).sum().backward()
    analytic = p.grad
    h = 2e-5
    fd = torch.zeros_like(params)
    for k in range(params.shape[1]):
        e = torch.zeros_like(params)
        e[:, k] = h
        fd[:, k] = (f(params + e) - f(params - e)) / (2 * h)
    assert analytic.abs().max() > 1.0  # a real, non-trivial gradient
    torch.testing.assert_close(analytic, fd, rtol=0.03, atol=0.03 * float(fd.abs().max()))


def test_discrepancy_is_lowest_near_the_truth(mug, T_true, camera_X):
    offsets = [(0, 0, 0), (0.005, 0, 0), (0, 0.01, 0), (0.02, 0, 0)]
    poses = torch.stack([pose_from_xyz_yaw(torch.tensor(TRUE_XYZ) + torch.tensor(o, dtype=torch.float32),
                                           torch.tensor(TRUE_YAW)) for o in offsets])
    l = discrepancy(mug, camera_X, poses)
    assert int(torch.argmin(l)) == 0
    assert float(l[0]) < 2.0 < float(l[1]) < float(l[3])


# ---------------------------------------------------------------------------------------------- robustness
def test_empty_features_give_uniform_weights_and_no_resample(mug, T_true):
    poses = T_true[None].repeat(5, 1, 1)
    poses[:, 0, 3] += torch.linspace(0, 0.05, 5)
    b = ParticleBelief(mug, poses, torch.tensor([0.6, 0.1, 0.1, 0.1, 0.1]))
    empty = Features.empty()
    assert discrepancy(mug, empty, poses).tolist() == [0.0] * 5
    assert b.update(empty) is False
    torch.testing.assert_close(b.weights, torch.full((5,), 0.2))


def test_nan_or_inf_positions_raise(mug, T_true):
    for bad in (float("nan"), float("inf")):
        with pytest.raises(ValueError, match="NaN or inf"):
            Features(torch.tensor([[0.8, 0.0, bad]]), torch.tensor([0]))
    # a Features mutated after validation is still caught by the discrepancy
    f = Features(torch.tensor([[0.8, 0.0, 0.02]]), torch.tensor([0]))
    f.positions[0, 0] = float("nan")
    with pytest.raises(ValueError, match="NaN or inf"):
        discrepancy(mug, f, T_true[None])
    with pytest.raises(ValueError, match="NaN or inf"):
        ParticleBelief(mug, torch.full((2, 4, 4), float("nan")))


def test_weights_recover_from_non_finite_discrepancies(caplog):
    l = torch.tensor([1.0, float("inf"), 2.0, float("nan")])
    w = boltzmann_weights(l, 2.0)
    assert w[1] == 0 and w[3] == 0
    torch.testing.assert_close(w[0] / w[2], torch.tensor(math.exp(2.0)))
    torch.testing.assert_close(w.sum(), torch.tensor(1.0))
    with caplog.at_level(logging.WARNING, logger="activetouch.belief.particle_filter"):
        w = boltzmann_weights(torch.full((4,), float("inf")), 2.0)
    torch.testing.assert_close(w, torch.full((4,), 0.25))
    assert "uniform" in caplog.text
    # huge discrepancy differences underflow exp(); the minimum keeps weight, so there is no 0/0
    w = boltzmann_weights(torch.tensor([1e6, 0.0, 5e5]), 2.0)
    assert w.tolist() == [0.0, 1.0, 0.0]


def test_update_with_infinite_discrepancies_never_holds_nan(mug, T_true):
    # a surface point 1e36 m away overflows float32 in Eq. 3: every particle's discrepancy is +inf
    X = Features(torch.tensor([[1e36, 0.0, 0.0], [0.8, 0.0, 0.02]]), torch.tensor([0, 0]))
    b = ParticleBelief(mug, T_true[None].repeat(4, 1, 1), config=BeliefConfig(num_particles=4))
    assert bool(torch.isinf(b.discrepancy(X)).all())
    g = torch.Generator().manual_seed(0)
    assert b.update(X, g) is True  # inf > l_r: resampled from uniform fallback weights
    assert bool(torch.isfinite(b.poses).all()) and bool(torch.isfinite(b.weights).all())
    torch.testing.assert_close(b.weights, torch.full((4,), 0.25))


def test_bad_weights_and_poses_raise(mug, T_true):
    with pytest.raises(ValueError, match="weights"):
        ParticleBelief(mug, T_true[None].repeat(3, 1, 1), torch.zeros(3))
    with pytest.raises(ValueError, match="weights"):
        ParticleBelief(mug, T_true[None].repeat(3, 1, 1), torch.tensor([1.0, float("nan"), 1.0]))
    with pytest.raises(ValueError, match="shape"):
        ParticleBelief(mug, torch.eye(4))
    b = ParticleBelief(mug, T_true[None].repeat(3, 1, 1))
    with pytest.raises(ValueError, match="NaN or inf"):
        b.predict(torch.full((4, 4), float("nan")))
    with pytest.raises(ValueError, match="weights"):
        systematic_resample(torch.zeros(3))


# ---------------------------------------------------------------------------------------------- Alg. 3, 4
def test_systematic_resample_counts_and_seed():
    w = torch.tensor([0.5, 0.25, 0.25, 0.0])
    for seed in range(5):
        idx = systematic_resample(w, generator=torch.Generator().manual_seed(seed))
        assert torch.bincount(idx, minlength=4).tolist() == [2, 1, 1, 0]
    w = torch.rand(50, generator=torch.Generator().manual_seed(1))
    a = systematic_resample(w, generator=torch.Generator().manual_seed(7))
    b = systematic_resample(w, generator=torch.Generator().manual_seed(7))
    assert torch.equal(a, b)
    counts = torch.bincount(a, minlength=50).double()
    assert bool(((counts - 50 * w / w.sum()).abs() < 1.0 + 1e-9).all())  # floor or ceil of P w_i


def test_predict_applies_world_motion_and_keeps_se2(mug, T_true):
    g = torch.Generator().manual_seed(0)
    poses = mug_prior(torch.tensor([0.8, 0.0, 0.01]), 20, g)
    dT = pose_from_xyz_yaw(torch.tensor([0.02, -0.01, 0.0]), torch.tensor(0.2))
    b = ParticleBelief(mug, poses, config=BeliefConfig(num_particles=20, sigma_t=0.0))
    b.predict(dT)
    torch.testing.assert_close(b.poses, dT @ poses)
    b = ParticleBelief(mug, poses, config=BeliefConfig(num_particles=20))  # sigma_t = 10 mm
    b.predict(dT, generator=torch.Generator().manual_seed(1))
    assert float((b.poses[:, 2, 3] - 0.01).abs().max()) < 1e-6  # height kept
    assert float((b.poses[:, 2, 2] - 1).abs().max()) < 1e-6  # upright
    moved = (dT @ poses)[:, :2, 3]
    spread = (b.poses[:, :2, 3] - moved).norm(dim=1)
    assert 0.004 < float(spread.mean()) < 0.025  # ~ sigma_t * sqrt(pi/2) = 12.5 mm for 2D noise
    b2 = ParticleBelief(mug, poses, config=BeliefConfig(num_particles=20))
    b2.predict(dT, generator=torch.Generator().manual_seed(1))
    assert torch.equal(b.poses, b2.poses)
    # noise=False (observed settling below the motion tolerance): the default sigma_t is not applied
    b3 = ParticleBelief(mug, poses, config=BeliefConfig(num_particles=20))
    b3.predict(dT, generator=torch.Generator().manual_seed(1), noise=False)
    torch.testing.assert_close(b3.poses, dT @ poses)


# ---------------------------------------------------------------------------------------------- priors
def test_priors(body_axis):
    g = torch.Generator().manual_seed(0)
    c = torch.tensor([0.8, 0.1, 0.0])
    p = mug_prior(c, 2000, g)
    assert p.shape == (2000, 4, 4)
    torch.testing.assert_close(p[:, :3, 3], c.expand(2000, 3))
    yaw = yaw_of(p)
    assert float(yaw.min()) < -3.0 and float(yaw.max()) > 3.0 and abs(float(yaw.mean())) < 0.15
    p = mug_prior(c, 50, g, axis_offset=body_axis)
    torch.testing.assert_close(transform_points(p, body_axis[None])[:, 0], c.expand(50, 3), atol=1e-6, rtol=0)
    q = gaussian_yaw_prior(c, sigma=0.05, n=4000, generator=torch.Generator().manual_seed(2))
    std = q[:, :2, 3].std(dim=0)
    assert bool(((std - 0.05).abs() < 0.004).all())
    assert float((q[:, 2, 3] - c[2]).abs().max()) == 0.0
    r = gaussian_yaw_prior(c, sigma=0.05, n=4000, generator=torch.Generator().manual_seed(2))
    assert torch.equal(q, r)
    with pytest.raises(ValueError):
        mug_prior(torch.tensor([0.0, float("nan"), 0.0]), 10)
    with pytest.raises(ValueError):
        gaussian_yaw_prior(c, n=0)


# ---------------------------------------------------------------------------------------------- the mug
@pytest.fixture(scope="module")
def mug_run(mug, T_true, camera_X, handle_X, body_axis):
    """Algorithm 1 on the side-camera mug: init (no CHSEL), update, then touch the handle and update."""
    g = torch.Generator().manual_seed(0)
    centre = transform_points(T_true, body_axis[None])[0] + torch.tensor([0.002, -0.002, 0.0])
    prior = mug_prior(centre, 100, g, axis_offset=body_axis)
    b = ParticleBelief.from_prior(mug, prior, camera_X, BeliefConfig(), use_chsel=False, generator=g)
    out = {"resampled_before": b.update(camera_X, g)}
    out["before"] = (b.poses.clone(), b.weights.clone(), b.active_share())
    X = Features.concat([camera_X, handle_X])
    out["resampled_after"] = []
    for _ in range(3):
        out["resampled_after"].append(b.update(X, g))
    out["after"] = (b.poses.clone(), b.weights.clone(), b.active_share())
    return out


def test_mug_yaw_stays_spread_while_the_handle_is_hidden(mug_run, T_true):
    poses, w, active = mug_run["before"]
    _, circ_std = weighted_yaw_stats(poses, w, T_true)
    assert circ_std > 60.0 and active > 0.3, (circ_std, active)


def test_mug_handle_contact_localises_the_yaw(mug, mug_run, T_true):
    assert mug_run["resampled_after"][0] is True  # the handle points contradict most particles (l > l_r)
    poses, w, _ = mug_run["after"]
    err, _ = weighted_yaw_stats(poses, w, T_true)
    assert err < 10.0, err
    nll = metrics.nll(mug, poses, w, T_true)
    assert nll < 20.0, nll  # Table III success threshold for the mug
    assert bool(torch.isfinite(poses).all())
    assert float((poses[:, 2, 3] - T_true[2, 3]).abs().max()) < 1e-6  # SE(2): z fixed
    assert float((poses[:, 2, 2] - 1).abs().max()) < 1e-6  # upright


def test_update_is_reproducible(mug, T_true, camera_X, handle_X, body_axis):
    X = Features.concat([camera_X, handle_X])
    res = []
    for _ in range(2):
        g = torch.Generator().manual_seed(5)
        prior = mug_prior(transform_points(T_true, body_axis[None])[0], 20, g, axis_offset=body_axis)
        b = ParticleBelief(mug, prior, config=BeliefConfig(num_particles=20, n_opt=3))
        b.update(X, g)
        res.append(b.poses)
    assert torch.equal(res[0], res[1])


def test_resample_percentile_ignores_outlier_particles(mug, T_true, camera_X):
    poses = T_true[None].repeat(10, 1, 1)
    poses[0, 0, 3] += 0.05  # one outlier
    cfg = BeliefConfig(num_particles=10, resample_percentile=50.0)
    b = ParticleBelief(mug, poses, config=cfg)
    assert b.update(camera_X) is False  # median discrepancy is below l_r
    assert float(b.weights[0]) < 1e-6
    b = ParticleBelief(mug, poses, config=BeliefConfig(num_particles=10, n_opt=2))
    assert b.update(camera_X, torch.Generator().manual_seed(0)) is True  # max discrepancy is above l_r


# ---------------------------------------------------------------------------------------------- Alg. 5
def test_obj_move_recovers_a_planar_push(mug, T_true, camera_X, handle_X):
    # the mug is pushed: 15 mm, -10 mm and 0.15 rad about its own origin
    T_new = pose_from_xyz_yaw(torch.tensor(TRUE_XYZ) + torch.tensor([0.015, -0.010, 0.0]),
                              torch.tensor(TRUE_YAW + 0.15))
    X_new = Features.concat([side_camera_features(mug, T_new, n=4000), handle_features(mug, T_new, n=8000)])
    X_prev = Features.concat([camera_X, handle_X])
    g = torch.Generator().manual_seed(0)
    poses = T_true[None].repeat(8, 1, 1)
    poses[1:, :2, 3] += torch.randn(7, 2, generator=g) * 0.01  # particle 0 is the truth: lowest discrepancy
    b = ParticleBelief(mug, poses, config=BeliefConfig(num_particles=8))
    # sticking-contact prior: the end effector moved 5 mm and 0.05 rad (the object slipped): 14 mm, 5.7 deg off
    T_r = pose_from_xyz_yaw(torch.tensor(TRUE_XYZ) + torch.tensor([0.005, 0.0, 0.0]), torch.tensor(TRUE_YAW + 0.05))
    dT_r = T_r @ invert(T_true)  # world frame
    assert float(metrics.translation_error(dT_r @ T_true, T_new)) > 0.013
    dT, dT_w = b.obj_move(X_prev, X_new, dT_r)
    est = dT_w @ T_true
    assert float(metrics.translation_error(est, T_new)) < 0.004
    assert math.degrees(float(metrics.rotation_error(est, T_new))) < 2.0
    # frame algebra: dT is the body-frame motion of the chosen particle (T_i = T_true), T_i dT = dT_w T_i
    torch.testing.assert_close(T_true @ dT, dT_w @ T_true, atol=1e-5, rtol=0)
    assert abs(float(dT_w[2, 3])) < 1e-6 and abs(float(dT_w[2, 2]) - 1) < 1e-6  # planar


# ---------------------------------------------------------------------------------------------- CHSEL
@pytest.mark.slow
def test_chsel_initialisation_fits_the_body_and_keeps_yaw_diversity(mug, T_true, camera_X, body_axis):
    """One small CHSEL run (the full one takes minutes on 2 CPU cores): 8 particles, 1 round, 5 QD steps."""
    g = torch.Generator().manual_seed(0)
    axis_true = transform_points(T_true, body_axis[None])[0]
    centre = axis_true + torch.tensor([0.004, -0.003, 0.0])
    prior = mug_prior(centre, 8, g)  # origin (not body axis) at the centre: 12 mm yaw-dependent offset
    cfg = BeliefConfig(num_particles=8, chsel_iterations=1, chsel_qd_iterations=5)
    prior_l = discrepancy(mug, camera_X, prior)
    b = ParticleBelief.from_prior(mug, prior, camera_X, cfg, use_chsel=True, generator=torch.Generator().manual_seed(1))
    axis_err = (transform_points(b.poses, body_axis[None])[:, 0, :2] - axis_true[:2]).norm(dim=1)
    assert float(axis_err.median()) < 0.003, axis_err
    assert float(b.last_discrepancy.median()) < 0.5 * float(prior_l.median())
    assert float((b.poses[:, 2, 3] - T_true[2, 3]).abs().max()) < 1e-6
    assert float((b.poses[:, 2, 2] - 1).abs().max()) < 1e-6
    _, circ_std = weighted_yaw_stats(b.poses, torch.full((8,), 1 / 8), T_true)
    assert circ_std > 40.0  # the yaw stays diverse (quality diversity over the yaw measure)


def test_se3_resample_optimises_full_poses(mug, T_true, camera_X, handle_X):
    """SE(3) particles (the box task's setting): Resample moves roll/pitch too and keeps rotations orthonormal."""
    from activetouch.geometry import axis_angle_to_matrix, make_pose

    g = torch.Generator().manual_seed(4)
    tilt = make_pose(axis_angle_to_matrix(torch.randn(10, 3, generator=g) * 0.08), torch.zeros(10, 3))
    poses = T_true[None] @ tilt  # tilted ~5 deg about the mug origin
    poses[:, :3, 3] += torch.randn(10, 3, generator=g) * 0.004
    X = Features.concat([camera_X, handle_X])
    cfg = BeliefConfig(num_particles=10, se2=False, sigma_t=0.0, n_opt=10)
    b = ParticleBelief(mug, poses, config=cfg)
    l0 = b.discrepancy(X)
    assert b.update(X, torch.Generator().manual_seed(0)) is True
    l1 = b.discrepancy(X)
    assert float(l1.median()) < 0.6 * float(l0.median())
    R = b.poses[:, :3, :3]
    torch.testing.assert_close(R @ R.transpose(-1, -2), torch.eye(3).expand(10, 3, 3), atol=1e-5, rtol=0)
    assert float(metrics.rotation_error(b.poses, T_true).median()) < float(metrics.rotation_error(poses, T_true).median())


def test_resting_face_prior_covers_the_six_faces_on_the_table():
    from activetouch.belief import resting_face_prior

    box = objects.load("cracker_box")
    v = torch.as_tensor(box.mesh.vertices, dtype=torch.float32)
    P = resting_face_prior(torch.tensor([0.4, 0.1, 0.0]), box.mesh.vertices, n=600,
                           generator=torch.Generator().manual_seed(0))
    world = transform_points(P, v)
    assert torch.allclose(world[..., 2].min(dim=1).values, torch.zeros(600), atol=1e-5)  # resting on z = 0
    down = P[:, :3, :3].transpose(1, 2) @ torch.tensor([0.0, 0.0, -1.0])  # object-frame axis pointing down
    faces = {tuple(torch.round(d).int().tolist()) for d in down}
    assert len(faces) == 6  # every face drawn
    assert torch.allclose(P[:, :3, :3].det(), torch.ones(600), atol=1e-5)
    assert abs(float(P[:, 0, 3].mean()) - 0.4) < 0.01 and 0.04 < float(P[:, 1, 3].std()) < 0.06


# ---------------------------------------------------------------------------------------------- weighing fast path
def test_fast_weighing_equals_the_gradient_path(mug, T_true, camera_X, handle_X):
    """weigh() runs under no_grad and takes the values-only SDF lookup; its discrepancies and weights equal those
    of the differentiable path (poses that require grad -> KnownObject.sdf_world) within float rounding."""
    X = Features.concat([camera_X, handle_X])
    g = torch.Generator().manual_seed(0)
    poses = mug_prior(T_true[:3, 3] + torch.tensor([0.003, -0.002, 0.0]), 100, g)
    poses[:, :2, 3] += torch.randn(100, 2, generator=g) * 0.003
    b = ParticleBelief(mug, poses)
    w_fast = b.weigh(X).clone()
    l_fast = b.last_discrepancy.clone()
    l_grad = discrepancy(mug, X, poses.clone().requires_grad_(True)).detach()
    assert 1.0 < float(l_grad.min()) < float(l_grad.max())  # a real spread of weights
    torch.testing.assert_close(l_fast, l_grad, rtol=1e-5, atol=2e-4)
    torch.testing.assert_close(w_fast, boltzmann_weights(l_grad, 2.0), rtol=0, atol=1e-5)
    assert torch.equal(b.weigh(X), w_fast)  # deterministic


# ---------------------------------------------------------------------------------------------- Eq. 7-9
@pytest.mark.parametrize("exact", [True, False])
def test_optimisation_objective_gradient_is_eq_7_to_9(mug, T_true, exact):
    """The autograd gradient of the squared-hinge objective J = sum k r^2 / 2 is the paper's Eq. 7-9 written out by
    hand: per point e = C max(0, alpha - sdf) (-grad sdf) (free), C max(0, alpha + sdf) grad sdf (occupied),
    (sdf - 0) grad sdf (surface), chained through x_obj = R^T (x - t): dJ/dR = sum (x - t) e^T, dJ/dt = -R sum e."""
    C, tol = 10.0, 0.004
    alpha = -tol  # chsel's sign convention (module docstring of activetouch.belief.discrepancy)
    g = torch.Generator().manual_seed(8)
    surf = mug.sample_surface(40, seed=9)
    _, n = mug.sdf(surf)
    surf = surf + n * ((torch.rand(40, 1, generator=g) - 0.5) * 0.01)  # +-5 mm off the surface, both sides
    probes = torch.tensor([[-0.044, 0.0, 0.03], [0.0, -0.0445, 0.028], [-0.090, 0.0, 0.03],  # free: in, in, out
                           [-0.044, 0.0, 0.03], [-0.090, 0.0, 0.03], [0.0, -0.080, 0.02]])  # occupied: in, out, out
    pts = torch.cat([surf, probes]).double()
    sem = torch.tensor([0] * 40 + [1, 1, 1, 2, 2, 2])
    X = Features(transform_points(T_true.double(), pts).float(), sem)
    off = pose_from_xyz_yaw(torch.tensor([0.003, -0.002, 0.0]), torch.tensor(0.05))
    poses = torch.stack([T_true, off @ T_true]).double()
    T = poses.clone().requires_grad_(True)
    J = optimisation_objective(mug, X, T, free_scale=C, violation_tolerance=tol, exact=exact)
    J.sum().backward()
    # by hand
    x = X.positions.double()
    R, t = poses[:, :3, :3], poses[:, :3, 3]
    x_obj = (x[None] - t[:, None]) @ R  # R^T (x - t), (P, N, 3)
    v, gr = mug.sdf(x_obj) if exact else mug.cached_sdf(x_obj)
    free, occ, surface = (sem == 1), (sem == 2), (sem == 0)
    r_f = torch.clamp(alpha - v, min=0)
    r_o = torch.clamp(alpha + v, min=0)
    e = torch.where(free[None, :, None], C * r_f[..., None] * -gr,
                    torch.where(occ[None, :, None], C * r_o[..., None] * gr, (v - 0.0)[..., None] * gr))  # Eq. 7-9
    assert float(r_f[:, free].max()) > 0.002 and float(r_o[:, occ].max()) > 0.01  # violations of both kinds
    assert float((r_f[:, free] == 0).sum()) > 0 and float((r_o[:, occ] == 0).sum()) > 0  # and non-violations
    dR = (x[None] - t[:, None]).transpose(1, 2) @ e  # sum_n (x_n - t) e_n^T
    dt = -(R @ e.sum(1).unsqueeze(-1)).squeeze(-1)
    assert float(dt.abs().max()) > 1e-3
    torch.testing.assert_close(T.grad[:, :3, :3], dR, rtol=1e-4, atol=1e-7)
    torch.testing.assert_close(T.grad[:, :3, 3], dt, rtol=1e-4, atol=1e-7)
    assert float(T.grad[:, 3].abs().max()) == 0.0
    # J is the squared hinge of the same residuals whose linear sum is the discrepancy of Eq. 3
    J_hand = (0.5 * C * r_f ** 2 * free + 0.5 * C * r_o ** 2 * occ + 0.5 * v ** 2 * surface).sum(1)
    torch.testing.assert_close(J.detach(), J_hand, rtol=1e-5, atol=1e-9)
    c, J2 = discrepancy_and_objective(mug, X, poses, free_scale=C, violation_tolerance=tol, exact=exact)
    torch.testing.assert_close(c, discrepancy(mug, X, poses, free_scale=C, violation_tolerance=tol, exact=exact))
    torch.testing.assert_close(J2, J.detach())


def test_resample_and_obj_move_descend_the_eq_7_to_9_objective(mug, T_true, camera_X):
    """Algorithms 4 and 5 get (C^, J) from the belief: Adam descends J, each particle keeps its lowest C^."""
    b = ParticleBelief(mug, T_true[None].repeat(4, 1, 1), config=BeliefConfig(num_particles=4))
    c, J = b._cost_fn(camera_X)(b.poses)
    torch.testing.assert_close(c, b.discrepancy(camera_X))
    torch.testing.assert_close(J, optimisation_objective(mug, camera_X, b.poses))
    # a 5 mm offset particle is pulled back; the returned cost is its C^ (never worse than at the start)
    from activetouch.belief.optimise import optimise_poses

    start = pose_from_xyz_yaw(torch.tensor(TRUE_XYZ) + torch.tensor([0.005, 0.0, 0.0]), torch.tensor(TRUE_YAW))[None]
    best, cost = optimise_poses(b._cost_fn(camera_X), start, 10, 0.003, 0.03, True)
    assert float(metrics.translation_error(best[0], T_true)) < 0.003
    torch.testing.assert_close(cost, b.discrepancy(camera_X, best))
    assert float(cost[0]) < float(b.discrepancy(camera_X, start)[0])
    # the pre-Eq.-7-9 behaviour on request: descend C^ itself
    lin = ParticleBelief(mug, b.poses, config=BeliefConfig(num_particles=4, opt_objective="linear_hinge"))
    torch.testing.assert_close(lin._cost_fn(camera_X)(b.poses), b.discrepancy(camera_X))
    with pytest.raises(ValueError, match="opt_objective"):
        BeliefConfig(opt_objective="huber")


# ---------------------------------------------------------------------------------------------- input checks
def test_chsel_minimum_particle_count_is_checked_before_any_work(mug, T_true, camera_X):
    assert MIN_PARTICLES == chsel_min_batch(BeliefConfig().chsel_iterations) == 10
    assert chsel_min_batch(1) == 3
    g = torch.Generator().manual_seed(0)
    for P in (1, 2, MIN_PARTICLES - 1):
        prior = mug_prior(T_true[:3, 3], P, g)
        cfg = BeliefConfig(num_particles=P)
        with pytest.raises(ValueError, match=rf"CHSEL .* needs at least 10 particles, got {P}"):
            ParticleBelief.from_prior(mug, prior, camera_X, cfg, use_chsel=True, generator=g)
        # without CHSEL any P works, and the belief never holds NaN
        b = ParticleBelief.from_prior(mug, prior, camera_X, cfg, use_chsel=False, generator=g)
        b.update(camera_X, g)
        assert bool(torch.isfinite(b.poses).all()) and bool(torch.isfinite(b.weights).all())
    with pytest.raises(ValueError, match="needs at least 3 particles, got 2"):
        ParticleBelief.from_prior(mug, mug_prior(T_true[:3, 3], 2, g), camera_X, BeliefConfig(num_particles=2),
                                  use_chsel=True, chsel_iterations=1)
    with pytest.raises(ValueError, match="chsel_batch must be None or an int >= 10"):
        BeliefConfig(chsel_batch=5)
    with pytest.raises(ValueError, match="got 9"):  # chsel_register itself checks too
        from activetouch.belief.chsel_init import chsel_register

        chsel_register(mug, mug_prior(T_true[:3, 3], 9, g), camera_X, BeliefConfig(num_particles=9))


@pytest.mark.slow
def test_chsel_at_the_minimum_particle_count_gives_finite_poses(mug, T_true, camera_X):
    """With MIN_PARTICLES particles CHSEL re-initialises between rounds from 2 elites (fewer: NaN poses)."""
    g = torch.Generator().manual_seed(0)
    prior = mug_prior(T_true[:3, 3] + torch.tensor([0.004, -0.003, 0.0]), MIN_PARTICLES, g)
    cfg = BeliefConfig(num_particles=MIN_PARTICLES, chsel_iterations=2, chsel_qd_iterations=5, chsel_max_points=100)
    b = ParticleBelief.from_prior(mug, prior, camera_X, cfg, use_chsel=True, generator=torch.Generator().manual_seed(1))
    assert bool(torch.isfinite(b.poses).all()) and b.num_particles == MIN_PARTICLES


def test_boltzmann_weights_reject_bad_lambda():
    l = torch.tensor([1.0, 2.0, 4.0])
    for lam in (float("nan"), -1.0, -1e-9, float("inf"), "two", None):
        with pytest.raises(ValueError, match="lam must be a finite number >= 0"):
            boltzmann_weights(l, lam)
    # lam = 0: uniform over the particles with a finite discrepancy
    torch.testing.assert_close(boltzmann_weights(torch.tensor([1.0, 5.0, float("inf")]), 0.0),
                               torch.tensor([0.5, 0.5, 0.0]))
    torch.testing.assert_close(boltzmann_weights(l, torch.tensor(2.0)), boltzmann_weights(l, 2.0))


def test_non_rigid_poses_are_rejected_where_poses_enter_the_belief(mug, T_true, camera_X):
    bad = 2 * torch.eye(4)
    with pytest.raises(ValueError, match=r"^poses must be rigid transforms \(pose 0 of 3\).*det R = 8"):
        ParticleBelief(mug, bad.expand(3, 4, 4))
    with pytest.raises(ValueError, match="prior_poses must be rigid"):
        ParticleBelief.from_prior(mug, bad.expand(3, 4, 4), camera_X, BeliefConfig(num_particles=3), use_chsel=False)
    reflected = T_true.clone()
    reflected[:3, 0] *= -1.0
    with pytest.raises(ValueError, match="det R = -1"):
        ParticleBelief(mug, reflected[None])
    b = ParticleBelief(mug, T_true[None].repeat(3, 1, 1), config=BeliefConfig(num_particles=3))
    with pytest.raises(ValueError, match="dT must be rigid"):
        b.predict(bad)
    with pytest.raises(ValueError, match="dT_r must be rigid"):
        b.obj_move(camera_X, camera_X, bad)
    with pytest.raises(ValueError, match="dT_w must be rigid"):
        merge_obs(camera_X, camera_X, b.poses, mug, bad, r_free=0.010, r_surface=0.002)
    with pytest.raises(ValueError, match="poses must be rigid"):
        discrepancy(mug, camera_X, bad[None])
    # float32 poses composed over many steps stay rigid within the tolerance
    dT = pose_from_xyz_yaw(torch.tensor([0.001, 0.0005, 0.0]), torch.tensor(0.013))
    for _ in range(200):
        b.predict(dT, noise=False)
    assert bool(torch.isfinite(b.poses).all())


def test_from_prior_rejects_a_prior_of_the_wrong_size(mug, T_true, camera_X):
    prior = mug_prior(T_true[:3, 3], 20, torch.Generator().manual_seed(0))
    with pytest.raises(ValueError, match="prior_poses holds 20 poses but config.num_particles is 50"):
        ParticleBelief.from_prior(mug, prior, camera_X, BeliefConfig(num_particles=50), use_chsel=False)
    with pytest.raises(ValueError, match="holds 20 poses but config.num_particles is 100"):  # the default P
        ParticleBelief.from_prior(mug, prior, camera_X, use_chsel=False)
    b = ParticleBelief.from_prior(mug, prior, camera_X, use_chsel=False, num_particles=20)
    assert b.num_particles == 20

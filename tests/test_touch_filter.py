"""Tests of the touch-only particle filter: contact model (Eq. 10), robot-object distance, TouchBelief
(Sec. V, App. B) and the GMM prior (App. D-c).

The scenes use the cracker box resting on the table (the scanned YCB mesh: about 0.072 x 0.164 x 0.213 m, its
+x face bulging in by ~6 mm at mid-height) and a "finger": a 2 cm cube of grid points (4 mm spacing), standing
in for the robot's collision geometry.
"""
from __future__ import annotations

import math
from dataclasses import replace

import numpy as np
import pytest
import torch
import trimesh

from activetouch import objects
from activetouch.belief.contact_model import (
    ContactModelConfig,
    contact_likelihood,
    contact_log_likelihood,
    pose_to_se2,
    robot_object_distance,
    se2_to_pose,
    signed_robot_object_distance,
)
from activetouch.belief.touch_filter import TouchBelief, TouchFilterConfig, gmm_prior
from activetouch.geometry import invert, transform_points



@pytest.fixture(autouse=True)
def one_thread():
    """One torch thread: the updates are small tensor ops, where 2 OpenMP threads on this loaded 2-core machine
    spin (measured: 120 ms instead of 5 ms per update)."""
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def box():
    return objects.load("cracker_box")


def _face_x(mesh, y: float, z: float) -> float:
    """x of the mesh's +x face at (y, z) (ray cast from +x)."""
    loc, _, _ = mesh.ray.intersects_location(np.array([[1.0, y, z]]), np.array([[-1.0, 0.0, 0.0]]))
    return float(loc[:, 0].max())


_FACE_X: dict[float, float] = {}


def finger(centre, half: float = 0.01, spacing: float = 0.004) -> torch.Tensor:
    """Grid points ``(M, 3)`` filling a cube of half size ``half`` about ``centre`` (boundary included)."""
    ax = torch.linspace(-half, half, int(round(2 * half / spacing)) + 1)
    pts = torch.stack(torch.meshgrid(ax, ax, ax, indexing="ij"), -1).reshape(-1, 3)
    return pts + torch.as_tensor(centre, dtype=torch.float32)


def touching_finger(z: float = 0.1) -> torch.Tensor:
    """Finger whose -x face centre lies on the box's +x face at state (0, 0, 0)."""
    if z not in _FACE_X:
        _FACE_X[z] = _face_x(objects.load("cracker_box").mesh, 0.0, z)
    return finger([_FACE_X[z] + 0.01, 0.0, z])


# ---------------------------------------------------------------------------------------------- Eq. 10
def test_eq10_values_at_zero_and_infinity():
    cfg = ContactModelConfig()
    assert (cfg.alpha_tp, cfg.alpha_fp, cfg.gamma) == (0.5, 0.1, 1000.0)  # App. D-e
    d = torch.tensor([[0.0, float("inf"), 1.0, 0.001, -0.01]])
    p1 = contact_likelihood(torch.tensor([True]), d, cfg)[0]
    p0 = contact_likelihood(torch.tensor([False]), d, cfg)[0]
    assert p1[0] == pytest.approx(0.5) and p0[0] == pytest.approx(0.5)
    assert p1[1] == pytest.approx(0.1) and p0[1] == pytest.approx(0.9)
    assert p1[2] == pytest.approx(0.1, abs=1e-9)  # 1 m away: exp(-1000) underflows to alpha_fp
    assert p1[3] == pytest.approx(0.1 + 0.4 * math.exp(-1.0), rel=1e-5)
    assert p1[4] == pytest.approx(0.5)  # penetration counts as d = 0


def test_likelihoods_in_unit_interval_and_complementary():
    g = torch.Generator().manual_seed(0)
    d = torch.randn(6, 200, generator=g).abs() * 0.01 - 0.002
    d[0, :10] = float("inf")
    z = torch.rand(6, generator=g) > 0.5
    for kind in ("smooth", "binary"):
        cfg = ContactModelConfig(kind=kind)
        p = contact_likelihood(z, d, cfg)
        assert p.shape == (6, 200)
        assert bool(((p >= 0) & (p <= 1)).all())
        q = contact_likelihood(~z, d, cfg)
        assert torch.allclose(p + q, torch.ones_like(p))
        lp = contact_log_likelihood(z, d, cfg)
        assert torch.allclose(lp, torch.log(p), atol=1e-6)


def test_binary_model_is_a_step():
    cfg = ContactModelConfig(kind="binary", binary_tolerance=0.002)
    d = torch.linspace(-0.005, 0.01, 301)[None]
    p = contact_likelihood(torch.tensor([True]), d, cfg)[0]
    inside = d[0] <= 0.002
    assert bool((p[inside] == 0.5).all()) and bool((p[~inside] == 0.1).all())
    assert inside.any() and (~inside).any()
    smooth = contact_likelihood(torch.tensor([True]), d, ContactModelConfig())[0]
    assert len(torch.unique(smooth)) > 100  # the smooth model is not a step


# ---------------------------------------------------------------------------------------------- distance
def test_se2_pose_roundtrip():
    s = torch.tensor([[0.1, -0.2, 0.3], [0.0, 0.5, -3.0]])
    T = se2_to_pose(s, z=0.0)
    assert T.shape == (2, 4, 4)
    assert torch.allclose(pose_to_se2(T), s, atol=1e-6)
    assert torch.allclose(se2_to_pose(s[None].expand(4, 2, 3)), T.expand(4, 2, 4, 4))


def test_distance_matches_trimesh_exact(box):
    g = torch.Generator().manual_seed(1)
    states = torch.tensor([[0.0, 0.0, 0.0], [0.02, -0.01, 0.4], [-0.03, 0.05, -1.2]])
    # each waypoint: 5 points 3-12 mm outside the surface of the posed box (from surface samples + normals)
    surf, fi = trimesh.sample.sample_surface(box.mesh, 400, seed=3)
    normals = box.mesh.face_normals[fi]
    K, M = 4, 5
    rp = []
    for k in range(K):
        sel = torch.randint(400, (M,), generator=g).numpy()
        off = (0.003 + 0.009 * torch.rand(M, 1, generator=g)).numpy()
        rp.append(surf[sel] + off * normals[sel])
    rp = torch.tensor(np.stack(rp), dtype=torch.float32)  # object-frame points of the first state (identity)
    poses = se2_to_pose(states)
    # world points: the object-frame offsets posed with state 0 = identity; distances differ per particle
    d = robot_object_distance(box, states, rp, far_inf=False)
    assert d.shape == (3, K)
    for i in range(3):
        for k in range(K):
            x_obj = transform_points(invert(poses[i]), rp[k]).numpy()
            exact = trimesh.proximity.closest_point(box.mesh, x_obj)[1]
            inside = box.mesh.contains(x_obj)
            true = 0.0 if inside.any() else float(exact.min())
            assert float(d[i, k]) == pytest.approx(true, abs=box.sdf_resolution), (i, k)
    # the (P, K, 3) path agrees with the static path
    d2 = robot_object_distance(box, states[:, None].expand(3, K, 3), rp, far_inf=False)
    assert torch.allclose(d, d2, atol=1e-6)


def test_distance_is_zero_for_penetrating_points(box):
    inside = finger([0.0, 0.0, 0.1], half=0.01)  # well inside the box
    states = torch.zeros(2, 3)
    d = robot_object_distance(box, states, inside[None])
    assert bool((d == 0).all())
    sd = signed_robot_object_distance(box, states, inside[None])
    assert bool((sd < -0.01).all())  # signed: about minus the depth (>= 26 mm at the box centre line)
    d_touch = robot_object_distance(box, states, touching_finger()[None])
    assert float(d_touch.max()) < box.sdf_resolution


def test_distance_far_is_inf_or_large(box):
    far = finger([0.5, 0.5, 0.1])
    d = robot_object_distance(box, torch.zeros(1, 3), far[None])
    assert float(d) == float("inf")
    d = robot_object_distance(box, torch.zeros(1, 3), far[None], far_inf=False)
    assert 0.5 < float(d) < 1.0


def test_distance_of_a_full_batch(box):
    """P = 100, K = 30, M ~ 3,000 in one batched call, finite (its speed, ~0.11 s, is a benchmark: bench touch-ig)."""
    from activetouch.sim.robot import gripper_points

    h, _ = gripper_points(0.0085)
    assert 2500 < h.shape[0] < 3500
    g = torch.Generator().manual_seed(0)
    rp = torch.stack([h + torch.tensor([-0.15 + 0.01 * k, 0.0, 0.05]) for k in range(30)])
    st = torch.randn(100, 3, generator=g) * torch.tensor([0.05, 0.05, 0.5])
    d = robot_object_distance(box, st, rp)
    assert d.shape == (100, 30) and not bool(torch.isnan(d).any())
    # the batch equals per-particle calls
    for i in (0, 57):
        assert torch.allclose(d[i], robot_object_distance(box, st[i:i + 1], rp)[0])


# ---------------------------------------------------------------------------------------------- updates
def _two_groups() -> torch.Tensor:
    """10 particles at the box's origin (the finger touches them), 10 shifted 0.3 m away (untouched)."""
    near = torch.zeros(10, 3)
    far = torch.tensor([[-0.3, 0.0, 0.0]]).repeat(10, 1)
    return torch.cat([near, far])


def test_contact_raises_touched_weights_no_contact_lowers_them(box):
    rp = touching_finger()[None]
    for z, sign in ((True, 1), (False, -1)):
        b = TouchBelief.from_prior(box, _two_groups(), TouchFilterConfig(num_particles=20, resample=False))
        out = b.update(torch.tensor([z]), rp)
        w = b.weights
        assert sign * (float(w[:10].mean()) - 0.05) > 0.01
        assert sign * (float(w[10:].mean()) - 0.05) < -0.01
        assert out["resampled"] is None and not out["fallback"]
        assert float(out["distances"][:10].max()) < 0.002
        assert torch.allclose(b.states, _two_groups())  # static: particles unchanged


def test_update_moves_particles_to_predicted_states(box):
    st = _two_groups()
    traj = st[:, None].repeat(1, 3, 1)
    traj[:, 1:, 0] += 0.01
    traj[:, 2, 2] += 0.1
    b = TouchBelief.from_prior(box, st, TouchFilterConfig(num_particles=20, resample=False))
    out = b.update(torch.tensor([False, False, False]), finger([0.5, 0.5, 0.1])[None].repeat(3, 1, 1), traj)
    assert torch.allclose(b.states, traj[:, -1])
    assert torch.allclose(b.weights, torch.full((20,), 0.05), atol=1e-6)  # far robot: no information
    assert out["distances"].shape == (20, 3)


def test_weights_stay_normalised_and_finite_after_random_updates(box):
    g = torch.Generator().manual_seed(5)
    st = gmm_prior(torch.tensor([[0.0, 0.0, 0.0], [0.1, 0.05, 1.0]]), 100, generator=g)
    for kind in ("smooth", "binary"):
        b = TouchBelief.from_prior(box, st, TouchFilterConfig(contact=ContactModelConfig(kind=kind)))
        kinds = set()
        for _ in range(20):
            K = 3
            z = torch.rand(K, generator=g) > 0.4
            c = (torch.rand(K, 3, generator=g) - 0.5) * torch.tensor([0.2, 0.3, 0.0]) + torch.tensor([0, 0, 0.1])
            rp = torch.stack([finger(ci.tolist()) for ci in c])
            traj = b.states[:, None] + torch.randn(100, K, 3, generator=g) * 0.002
            out = b.update(z, rp, traj, generator=g)
            kinds.add(out["resampled"])
            w = b.weights
            assert bool(torch.isfinite(w).all()) and not bool(torch.isnan(b.states).any())
            assert float(w.sum()) == pytest.approx(1.0, abs=1e-6)
            assert 1.0 <= out["ess"] <= 100.0 * (1 + 1e-5)  # float32 weights: ESS may round above P
        assert kinds & {"contact", "systematic"}  # some resampling happened along the way


def test_all_zero_likelihood_falls_back_to_previous_weights(box, caplog):
    cfg = TouchFilterConfig(num_particles=20, resample=False, contact=ContactModelConfig(alpha_fp=0.0))
    w0 = torch.linspace(1.0, 2.0, 20)
    b = TouchBelief(box, _two_groups() + torch.tensor([0.0, 0.5, 0.0]), w0, cfg)  # all far from the finger
    out = b.update(torch.tensor([True]), touching_finger()[None])
    assert out["fallback"]
    assert torch.allclose(b.weights, w0 / w0.sum())
    assert "zero likelihood" in caplog.text


def test_contact_resampling_places_particles_at_the_contact(box):
    """Starvation: a broad prior, the finger touches the truth; after contact-aware resampling the replaced
    particles touch the robot (distance ~0, no deep penetration), and after a second contact the belief keeps
    more active particles than without resampling."""
    g = torch.Generator().manual_seed(2)
    st = gmm_prior(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.2, 0.0]]), 100, 0.06, 0.5, generator=g)
    rp = touching_finger()[None].repeat(5, 1, 1)
    z = torch.ones(5, dtype=torch.bool)
    res = TouchBelief.from_prior(box, st)
    plain = TouchBelief.from_prior(box, st, TouchFilterConfig(resample=False))
    out = res.update(z, rp, None, generator=torch.Generator().manual_seed(0))
    plain.update(z, rp)
    assert out["resampled"] == "contact"
    assert out["n_replaced"] >= 20
    rep = out["replaced"]
    sd = signed_robot_object_distance(box, res.states[rep], rp[:1])[:, 0]
    assert float(sd.max()) < 0.002  # at the contact
    assert float(sd.min()) > -0.002 - box.sdf_resolution  # not deep inside
    before = robot_object_distance(box, st, rp[:1])[:, 0]
    assert float((before < 0.002).float().mean()) < 0.4  # few particles touched the robot before
    res.update(z, rp, None, generator=torch.Generator().manual_seed(1), resample=False)
    plain.update(z, rp)
    assert res.active_share() > plain.active_share() + 0.2


def test_resampling_is_seeded(box):
    st = gmm_prior(torch.tensor([[0.0, 0.0, 0.0], [0.0, 0.2, 0.0]]), 100, generator=torch.Generator().manual_seed(0))
    rp = touching_finger()[None].repeat(5, 1, 1)
    runs = []
    for _ in range(2):
        b = TouchBelief.from_prior(box, st)
        b.update(torch.ones(5, dtype=torch.bool), rp, None, generator=torch.Generator().manual_seed(7))
        runs.append(b.states)
    assert torch.equal(runs[0], runs[1])


# ---------------------------------------------------------------------------------------------- prior
def test_gmm_prior_component_means_and_stds():
    cfg = TouchFilterConfig()
    assert (cfg.prior_sigma_pos, cfg.prior_sigma_yaw, cfg.prior_components, cfg.num_particles) == (0.06, 0.5, 2, 100)
    means = torch.tensor([[0.3, 0.2, 0.5], [-0.3, -0.2, -1.0]], dtype=torch.float64)
    n = 20000
    x = gmm_prior(means, n, cfg.prior_sigma_pos, cfg.prior_sigma_yaw, torch.Generator().manual_seed(0))
    assert x.shape == (n, 3) and x.dtype == torch.float64
    comp = (x[:, :2, None] - means[:, :2].T[None]).norm(dim=1).argmin(1)  # modes 0.72 m apart, sigma 6 cm
    for c in range(2):
        xc = x[comp == c]
        assert abs(xc.shape[0] / n - 0.5) < 0.02  # equal weights
        assert torch.allclose(xc.mean(0), means[c], atol=0.02)
        assert torch.allclose(xc[:, :2].std(0), torch.tensor([0.06, 0.06], dtype=torch.float64), rtol=0.05)
        assert float(xc[:, 2].std()) == pytest.approx(0.5, rel=0.05)
    assert float(x[:, 2].abs().max()) <= math.pi


# ---------------------------------------------------------------------------------------------- bad input
def test_bad_input_raises(box):
    z1 = torch.tensor([True])
    with pytest.raises(ValueError, match="NaN"):
        contact_likelihood(z1, torch.tensor([[float("nan")]]))
    with pytest.raises(ValueError, match="shape"):
        contact_likelihood(z1, torch.zeros(2, 3))
    with pytest.raises(ValueError, match="bool"):
        contact_likelihood(torch.tensor([0.5]), torch.zeros(1, 3))
    with pytest.raises(ValueError, match="no particles"):
        contact_likelihood(z1, torch.zeros(1, 0))
    with pytest.raises(ValueError, match="alpha"):
        ContactModelConfig(alpha_tp=0.1, alpha_fp=0.5)
    with pytest.raises(ValueError, match="kind"):
        ContactModelConfig(kind="sigmoid")
    with pytest.raises(ValueError, match="empty"):
        TouchBelief.from_prior(box, torch.zeros(0, 3))
    with pytest.raises(ValueError, match="NaN"):
        TouchBelief.from_prior(box, torch.tensor([[0.0, float("nan"), 0.0]]))
    with pytest.raises(ValueError, match="shape"):
        TouchBelief.from_prior(box, torch.zeros(5, 4))
    with pytest.raises(ValueError, match="num_particles"):
        TouchBelief.from_prior(box, torch.zeros(5, 3), TouchFilterConfig())
    with pytest.raises(ValueError, match="no mass"):
        TouchBelief(box, torch.zeros(3, 3), torch.zeros(3))
    with pytest.raises(ValueError, match="non-negative"):
        TouchBelief(box, torch.zeros(3, 3), torch.tensor([1.0, -1.0, 1.0]))
    b = TouchBelief.from_prior(box, torch.zeros(3, 3))
    rp = touching_finger()[None]
    with pytest.raises(ValueError, match="robot_points"):
        b.update(z1, torch.zeros(1, 5, 2))
    with pytest.raises(ValueError, match="NaN"):
        b.update(z1, torch.full((1, 5, 3), float("nan")))
    with pytest.raises(ValueError, match="waypoints"):
        b.update(torch.tensor([True, False]), rp)
    with pytest.raises(ValueError, match="states_traj"):
        b.update(z1, rp, torch.zeros(3, 2, 3))
    with pytest.raises(ValueError, match="NaN"):
        b.update(z1, rp, torch.full((3, 1, 3), float("nan")))
    with pytest.raises(ValueError, match="z must"):
        b.update(torch.zeros(0, dtype=torch.bool), rp)
    with pytest.raises(ValueError, match="n must"):
        gmm_prior(torch.zeros(2, 3), 0)
    with pytest.raises(ValueError, match="means"):
        gmm_prior(torch.zeros(2, 2), 10)
    with pytest.raises(ValueError, match="ess_threshold"):
        TouchFilterConfig(ess_threshold=1.5)


# ---------------------------------------------------------------------------------------------- history check
def _free_fingers() -> torch.Tensor:
    """``(4, M, 3)`` fingers in free space around the box at state (0, 0, 0) (none touches it): where a box
    turned by a quarter turn and touching ``touching_finger`` would lie, and beside the narrow faces."""
    return torch.stack([finger(c) for c in ([-0.09, 0.0, 0.1], [-0.07, 0.03, 0.1], [0.0, 0.13, 0.1],
                                            [0.0, -0.13, 0.1])])


def test_history_log_likelihood_sums_eq10_over_the_kept_segments(box):
    cfg = TouchFilterConfig(num_particles=20, resample=False, history_check=True, history_segments=2)
    b = TouchBelief.from_prior(box, _two_groups(), cfg)
    segs = [(torch.tensor([False, False, False, False]), _free_fingers()),
            (torch.tensor([True]), touching_finger()[None]),
            (torch.tensor([False, True]), torch.stack([finger([0.5, 0.5, 0.1]), touching_finger()]))]
    for z, rp in segs:
        b.update(z, rp)
    probe = torch.tensor([[0.0, 0.0, 0.0], [-0.046, 0.0, math.pi / 2], [0.3, 0.3, 1.0]], dtype=b.states.dtype)
    want = sum(contact_log_likelihood(z, robot_object_distance(box, probe, rp).T, cfg.contact).sum(0)
               for z, rp in segs[1:])  # only the last two segments are kept
    assert torch.allclose(b.history_log_likelihood(probe), want.to(probe), atol=1e-6)
    assert float(b.history_log_likelihood(probe)[0]) > float(b.history_log_likelihood(probe)[2]) + 1.0
    plain = TouchBelief.from_prior(box, _two_groups(), TouchFilterConfig(num_particles=20, resample=False))
    plain.update(*segs[0])
    assert torch.equal(plain.history_log_likelihood(probe), torch.zeros(3, dtype=probe.dtype))  # nothing kept


def test_history_check_keeps_candidates_that_earlier_pokes_ruled_out_away(box):
    """Free space seen first, then a contact on the +x face that no particle explains (the prior lies 30 cm away):
    App. B's candidates (half of them at any yaw near the contact) may sit where the free-space fingers were; with
    ``history_check`` they are ranked by the whole history, every replacement explains it better than the particle
    it replaces, and far fewer replacements contradict the free space."""
    st = gmm_prior(torch.tensor([[0.0, 0.3, 0.0], [0.0, -0.3, math.pi / 2]]), 100, 0.02, 0.5,
                   generator=torch.Generator().manual_seed(3))
    free_z, free = torch.zeros(4, dtype=torch.bool), _free_fingers()
    touch_z, touch = torch.ones(3, dtype=torch.bool), touching_finger()[None].repeat(3, 1, 1)
    contradicting = {}
    for check in (False, True):
        b = TouchBelief.from_prior(box, st, TouchFilterConfig(history_check=check))
        b.update(free_z, free, None, generator=torch.Generator().manual_seed(0), resample=False)
        before = b.states.clone()
        out = b.update(touch_z, touch, None, generator=torch.Generator().manual_seed(1))
        assert out["resampled"] == "contact" and out["n_replaced"] >= 10
        rep = out["replaced"]
        d_free = robot_object_distance(box, b.states[rep], free).amin(1)  # (R,) nearest free-space finger
        contradicting[check] = float((d_free < 0.002).double().mean())
        if check:
            # the acceptance rule, slot by slot, over both segments (states static: no rollout here)
            assert bool((b.history_log_likelihood(b.states[rep]) > b.history_log_likelihood(before[rep])).all())
    assert contradicting[False] >= 0.15, contradicting  # App. B as published brings such states back (0.40)
    assert contradicting[True] <= 0.05, contradicting  # the check keeps them out (0.02)


def test_history_check_does_not_dilute_a_belief_that_explains_the_contact(box):
    """Half the prior lies at the truth, which the contact confirms: App. B as published still swaps half the
    belief for contact candidates (uniform weights afterwards); with ``history_check`` a candidate must also beat
    the belief's weighted median particle on the whole history, so few or none come in."""
    st = gmm_prior(torch.tensor([[0.0, 0.0, 0.0], [-0.04, 0.0, math.pi / 2]]), 100, 0.04, 0.8,
                   generator=torch.Generator().manual_seed(3))
    replaced = {}
    for check in (False, True):
        b = TouchBelief.from_prior(box, st, TouchFilterConfig(history_check=check))
        b.update(torch.zeros(4, dtype=torch.bool), _free_fingers(), None, generator=torch.Generator().manual_seed(0),
                 resample=False)
        out = b.update(torch.ones(3, dtype=torch.bool), touching_finger()[None].repeat(3, 1, 1), None,
                       generator=torch.Generator().manual_seed(1))
        assert out["resampled"] == "contact"
        replaced[check] = out["n_replaced"]
    assert replaced[False] >= 30 and replaced[True] <= 10, replaced  # 50 and 0 here


def test_history_motion_judges_a_pushed_box_where_it_was(box):
    """``history_motion``: a contact on the +x face, then a poke that pushes every particle 3 cm along -x. Held
    still (the default check), the present states lie 3 cm from the old contact; on their own paths they touched
    it. Resampled copies (roughened) and contact candidates inherit paths that end at their present state and
    keep their parent's displacement."""
    cfg = TouchFilterConfig(num_particles=20, resample=False, history_check=True, history_motion=True)
    st = torch.cat([torch.zeros(10, 3), torch.tensor([[0.0, 0.3, 0.0]]).repeat(10, 1)]).double()
    b = TouchBelief.from_prior(box, st, cfg)
    b.update(torch.ones(1, dtype=torch.bool), touching_finger()[None])  # the box at rest, touched
    traj = st[:, None, :].repeat(1, 3, 1)
    traj[..., 0] += torch.tensor([-0.01, -0.02, -0.03], dtype=traj.dtype)  # the poke pushes it 3 cm along -x
    b.update(torch.zeros(3, dtype=torch.bool), finger([0.5, 0.5, 0.1])[None].repeat(3, 1, 1), traj)
    assert [tuple(p.shape) for p in b.history_paths] == [(20, 1, 3), (20, 3, 3)]
    own = b.history_log_likelihood(b.states, b.history_paths)
    still = b.history_log_likelihood(b.states)
    assert bool((own[:10] > still[:10] + 1.0).all()), (own, still)  # log(0.5 / 0.1) = 1.6 at the contact
    assert torch.allclose(own[10:], still[10:], atol=1e-6)  # the far group never came near the finger
    plain = TouchBelief.from_prior(box, st, replace(cfg, history_motion=False))
    plain.update(torch.ones(1, dtype=torch.bool), touching_finger()[None])
    plain.update(torch.zeros(3, dtype=torch.bool), finger([0.5, 0.5, 0.1])[None].repeat(3, 1, 1), traj)
    assert plain.history_paths == [] and torch.allclose(plain.history_log_likelihood(plain.states), still)

    b.resample_systematic(torch.Generator().manual_seed(0))  # mostly copies of the touched group, roughened
    p0, p1 = b.history_paths
    assert torch.allclose(p1[:, -1], b.states, atol=1e-9)  # every path ends where its particle is now
    assert torch.allclose(p0[:, 0] - b.states, torch.tensor([0.03, 0.0, 0.0], dtype=p0.dtype).expand(20, 3),
                          atol=1e-9)  # and keeps the parent's 3 cm push
    # a contact 15 cm from every particle: contact-aware resampling brings in candidates
    out = b.update(torch.ones(1, dtype=torch.bool), touching_finger()[None] + torch.tensor([0.0, -0.15, 0.0]),
                   generator=torch.Generator().manual_seed(1), resample=True)
    assert out["resampled"] == "contact" and out["n_replaced"] > 0, out
    assert all(torch.allclose(p[:, -1], b.states, atol=1e-9) for p in b.history_paths[-1:])  # theirs end there too
    assert len(b.history_paths) == 3 and all(bool(torch.isfinite(p).all()) for p in b.history_paths)

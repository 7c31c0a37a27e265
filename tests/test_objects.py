"""Tests for activetouch.objects: loading, exact SDF vs trimesh, cached SDF accuracy, pose gradients."""
import numpy as np
import pytest
import torch
import trimesh

from activetouch import objects
from activetouch.geometry import transforms as tf


@pytest.fixture(scope="module")
def mug():
    return objects.load("mug")


@pytest.fixture(scope="module")
def box():
    return objects.load("cracker_box")


@pytest.fixture()
def box_file(tmp_path):
    """A 4 x 6 x 8 cm analytic box, base-centred, written as an OBJ."""
    m = trimesh.creation.box(extents=[0.04, 0.06, 0.08])
    m.apply_translation([0, 0, 0.04])
    p = tmp_path / "testbox.obj"
    m.export(p)
    return p


def _near_surface_points(obj, n, seed, band):
    g = torch.Generator().manual_seed(seed)
    s = obj.sample_surface(n, seed=seed)
    _, normal = obj.sdf(s)
    off = (torch.rand(n, 1, generator=g) * 2 - 1) * band
    return s + normal * off


def test_available_and_unknown_name():
    assert objects.available() == ["mug", "drill", "cracker_box", "mustard_bottle", "bleach_cleanser", "tomato_soup_can",
                                   "sugar_box", "potted_meat_can", "foam_brick"]
    with pytest.raises(ValueError, match="mug, drill, cracker_box"):
        objects.load("teapot")


def test_packaged_frames_and_units(mug, box):
    # metres, base-centred: z from 0, x/y centred (assets/objects/README.md)
    b = mug.bounds
    assert b.shape == (2, 3)
    assert torch.allclose(b, torch.tensor([[-0.0585, -0.0466, 0.0], [0.0585, 0.0466, 0.0813]]), atol=2e-4)
    assert abs(mug.diagonal - float(np.linalg.norm([0.117, 0.0931, 0.0813]))) < 1e-3
    assert torch.allclose(box.bounds[1] - box.bounds[0], torch.tensor([0.0718, 0.164, 0.2134]), atol=5e-4)
    drill = objects.load("drill")
    assert drill.mesh.is_watertight and abs(drill.bounds[0, 2].item()) < 1e-6


@pytest.mark.parametrize("name", ["mug", "cracker_box"])
def test_exact_sdf_matches_trimesh(name, mug, box):
    pytest.importorskip("rtree")  # trimesh.proximity needs it
    obj = mug if name == "mug" else box
    g = torch.Generator().manual_seed(0)
    lo, hi = obj.bounds[0] - 0.02, obj.bounds[1] + 0.02
    pts = torch.cat([lo + (hi - lo) * torch.rand(120, 3, generator=g), _near_surface_points(obj, 80, 1, 0.005)])
    v, grad = obj.sdf(pts)
    ref = -trimesh.proximity.signed_distance(obj.mesh, pts.double().numpy())  # trimesh: positive inside
    assert np.abs(v.numpy() - ref).max() < 1e-3
    assert np.abs(v.numpy() - ref).mean() < 1e-4
    assert ((v.numpy() < 0) == (ref < 0))[np.abs(ref) > 1e-4].all()
    assert torch.allclose(grad.norm(dim=-1), torch.ones(len(pts)), atol=1e-5)


def test_sdf_at_known_points_of_the_box(box):
    # The scanned box is 71.8 mm thick (AABB) but slightly tilted and bulged: its centre is 28-36 mm deep.
    # 5 cm above the top face / 2 cm beside the +x face are 5 / 2 cm outside (within the scan's wobble).
    c = torch.tensor([[0.0, 0.0, 0.1067], [0.0, 0.0, 0.2134 + 0.05], [0.0359 + 0.02, 0.0, 0.1]])
    v, g = box.sdf(c)
    assert -0.0359 - 1e-4 < v[0].item() < -0.025
    assert v[1].item() == pytest.approx(0.05, abs=4e-3)
    assert 0.015 < v[2].item() < 0.03
    assert g[1] @ torch.tensor([0.0, 0, 1]) > 0.99  # outward normal of the top
    assert g[2] @ torch.tensor([1.0, 0, 0]) > 0.99


def test_sdf_sign_at_known_points_of_the_mug(mug):
    # inside the (partly filled) bottom of the cup body, in the air of the cup, far above
    pts = torch.tensor([[-0.012 + 0.035, 0.0, 0.02], [-0.012, 0.0, 0.07], [-0.012, 0.0, 0.3]])
    v, _ = mug.sdf(pts)
    vc, _ = mug.cached_sdf(pts)
    assert v[0] < 0 and vc[0] < 0
    assert v[1] > 0.02 and vc[1] > 0.02  # ~40 mm inner radius, >= 20 mm from any wall near the axis
    assert v[2] == pytest.approx(0.3 - 0.0813, abs=5e-3) and vc[2] == pytest.approx(v[2].item(), abs=2e-3)


@pytest.mark.parametrize("method,max_tol,p99_tol", [("taylor", 1.5e-3, 0.7e-3), ("linear", 0.8e-3, 0.6e-3)])
def test_cached_sdf_matches_exact_near_surface(mug, method, max_tol, p99_tol):
    """Stated accuracy of the default 1 mm mug cache within +-3 mm of the surface."""
    q = _near_surface_points(mug, 3000, 7, 0.003)
    ve, ge = mug.sdf(q)
    vc, gc = mug.cached_sdf(q, method=method)
    err = (ve - vc).abs()
    assert err.max().item() < max_tol
    assert err.quantile(0.99).item() < p99_tol
    assert torch.allclose(gc.norm(dim=-1), torch.ones(len(q)), atol=1e-4)


def test_cached_sdf_far_points_positive_and_gradients_agree(mug):
    g = torch.Generator().manual_seed(2)
    d = torch.randn(500, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    centre = torch.tensor([0.0, 0.0, 0.04])
    for r in (0.08, 0.3, 2.0):  # inside and far outside the 15 mm padded box
        x = centre + r * d
        ve, ge = mug.sdf(x)
        vc, gc = mug.cached_sdf(x)
        assert (vc > 0).all()
        assert (vc >= ve - 1.5e-3).all()  # outside the box: an upper bound
        assert ((vc - ve) / ve).abs().max() < 0.15  # loose far away: free space, sign is what matters
        assert (ge * gc).sum(-1).min() > 0.9
        assert torch.allclose(gc.norm(dim=-1), torch.ones(500), atol=1e-4)


def test_sdf_world_equals_object_frame_and_is_differentiable(mug):
    g = torch.Generator().manual_seed(4)
    P, N = 6, 40
    poses = tf.pose_from_xyz_yaw(torch.randn(P, 3, generator=g) * 0.02, torch.rand(P, generator=g) * 6.28)
    x = mug.sample_surface(N, seed=3) + torch.tensor([0.0, 0.0, 0.02]) + 0.03 * torch.randn(N, 3, generator=g)
    for exact in (False, True):
        v, gr = mug.sdf_world(poses, x, exact=exact)
        assert v.shape == (P, N) and gr.shape == (P, N, 3)
        xo = tf.transform_points(tf.invert(poses), x)
        ref_v, _ = mug.sdf(xo) if exact else mug.cached_sdf(xo)
        assert torch.allclose(v, ref_v, atol=1e-6)
    # pose gradient: x_obj = R^T (x - t) => d v / d t = -R grad
    T = poses.clone().requires_grad_(True)
    v, gr = mug.sdf_world(T, x, exact=True)
    v.sum().backward()
    expected_dt = -(poses[:, :3, :3] @ gr.transpose(1, 2)).sum(-1)  # (P, 3)
    assert torch.allclose(T.grad[:, :3, 3], expected_dt, atol=1e-5)
    # ... which matches finite differences of the exact SDF for points >= 5 mm from the surface
    far = v.detach().abs() > 0.005
    h = 1e-4
    for k in range(3):
        Tp = poses.clone()
        Tp[:, k, 3] += h
        Tm = poses.clone()
        Tm[:, k, 3] -= h
        fd = (mug.sdf_world(Tp, x, exact=True)[0] - mug.sdf_world(Tm, x, exact=True)[0]) / (2 * h)
        an = -(poses[:, k, :3].unsqueeze(1) * gr).sum(-1)
        assert (fd - an)[far].abs().quantile(0.95) < 0.02
    # the cached path gives pose gradients too
    T2 = poses.clone().requires_grad_(True)
    mug.sdf_world(T2, x)[0].sum().backward()
    assert torch.isfinite(T2.grad).all() and T2.grad.abs().sum() > 0


def test_bad_inputs_raise(mug):
    with pytest.raises(ValueError, match="NaN"):
        mug.cached_sdf(torch.tensor([[0.0, float("nan"), 0.0]]))
    with pytest.raises(ValueError, match="NaN"):
        mug.sdf(torch.tensor([[0.0, float("inf"), 0.0]]))
    with pytest.raises(ValueError, match="shape"):
        mug.sdf(torch.zeros(4, 2))
    bad = torch.eye(4).expand(2, 4, 4).clone()
    bad[1, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        mug.sdf_world(bad, torch.zeros(3, 3))


def test_sample_surface_seeded_and_on_surface(mug):
    a = mug.sample_surface(300, seed=5)
    b = mug.sample_surface(300, seed=5)
    c = mug.sample_surface(300, seed=6)
    assert a.shape == (300, 3) and torch.equal(a, b) and not torch.equal(a, c)
    v, _ = mug.sdf(a)
    assert v.abs().max() < 1e-4


def test_user_mesh_cache_location_and_reuse(box_file, tmp_path, monkeypatch):
    cache = tmp_path / "cache"
    monkeypatch.setenv("ACTIVETOUCH_CACHE_DIR", str(cache))
    obj = objects.load(str(box_file), sdf_resolution=0.004)
    assert obj.name == "testbox"
    v, g = obj.cached_sdf(torch.tensor([[0.0, 0.0, 0.04], [0.0, 0.0, 0.1]]))
    assert v[0].item() == pytest.approx(-0.02, abs=1e-3)  # 2 cm to the nearest (x) face
    assert v[1].item() == pytest.approx(0.02, abs=1e-3)
    files = list((cache / "sdf").glob("testbox-*.npz"))
    assert len(files) == 1 and "r4000um" in files[0].name
    # a second load reads the file instead of rebuilding
    monkeypatch.setattr(objects.VoxelSDF, "build", classmethod(lambda *a, **k: pytest.fail("rebuilt")))
    obj2 = objects.load(str(box_file), sdf_resolution=0.004)
    v2, _ = obj2.cached_sdf(torch.tensor([[0.0, 0.0, 0.04]]))
    assert v2[0].item() == pytest.approx(v[0].item())
    assert obj2.collision_hulls[0].is_convex


def test_non_watertight_mesh_rejected(tmp_path):
    m = trimesh.creation.box(extents=[0.05, 0.05, 0.05])
    m.update_faces(np.arange(len(m.faces)) != 0)  # drop one triangle: a hole
    p = tmp_path / "holey.obj"
    m.export(p)
    with pytest.raises(ValueError, match="not watertight"):
        objects.load(str(p))
    with pytest.raises(ValueError, match="no such mesh file"):
        objects.load(str(tmp_path / "missing.obj"))


# ---------------------------------------------------------------------------------------------- values-only fast path
def _poses_and_world_points(mug, P=8, seed=11):
    """``P`` upright and tilted poses, and world points near the posed surface, in the padded box and far away."""
    g = torch.Generator().manual_seed(seed)
    yaw = torch.rand(P, generator=g) * 6.28
    poses = tf.pose_from_xyz_yaw(torch.tensor([0.8, 0.0, 0.0]) + torch.randn(P, 3, generator=g) * 0.01, yaw)
    poses[P // 2:] = poses[P // 2:] @ tf.make_pose(tf.axis_angle_to_matrix(torch.randn(P - P // 2, 3, generator=g)
                                                                          * 0.3), torch.zeros(3))
    near = _near_surface_points(mug, 600, 21, 0.003)  # object frame, +-3 mm
    d = torch.randn(600, 3, generator=g)
    d = d / d.norm(dim=-1, keepdim=True)
    far = torch.cat([torch.tensor([0.0, 0.0, 0.04]) + r * d[i::3] for i, r in enumerate((0.08, 0.3, 2.0))])
    return poses, near, far


def test_values_fast_path_agrees_with_exact_sdf(mug):
    """sdf_world_values (VoxelSDF.posed_values, used for weighing) has the stated accuracy of the Taylor cache
    against the exact mesh SDF: near the surface max 1.5 mm / p99 0.7 mm (as the taylor row of
    test_cached_sdf_matches_exact_near_surface), far away positive upper bounds within 15 %."""
    poses, near, far = _poses_and_world_points(mug)
    for pts_obj, is_near in ((near, True), (far, False)):
        # the same object-frame points seen through every pose: world x = T_i p
        x = tf.transform_points(poses, pts_obj)  # (P, N, 3)
        v = mug.sdf_world_values(poses, x)
        assert v.shape == (len(poses), len(pts_obj)) and not v.requires_grad
        ve, _ = mug.sdf(pts_obj)
        err = (v - ve).abs()
        if is_near:
            assert err.max().item() < 1.5e-3
            assert err.quantile(0.99).item() < 0.7e-3
        else:
            assert (v > 0).all()
            assert (v >= ve - 1.5e-3).all()  # outside the box: an upper bound
            assert ((v - ve) / ve).abs().max() < 0.15


def test_values_fast_path_equals_the_gradient_path(mug):
    """Same values as sdf_world (the differentiable Taylor lookup) up to float rounding: the nearest cell may
    differ for points within ~1e-7 cells of a cell face, where the Taylor value jumps by its second-order error."""
    poses, near, far = _poses_and_world_points(mug, P=16, seed=12)
    g = torch.Generator().manual_seed(13)
    x = torch.cat([tf.transform_points(poses[0], torch.cat([near, far])),
                   torch.tensor([0.8, 0.0, 0.04]) + (torch.rand(3000, 3, generator=g) - 0.5) * 0.3])  # (N, 3)
    v_fast = mug.sdf_world_values(poses, x)
    v_grad, _ = mug.sdf_world(poses.clone().requires_grad_(True), x)
    diff = (v_fast - v_grad.detach()).abs()
    assert diff.quantile(0.999).item() < 1e-6
    assert diff.max().item() < 3e-4
    # one pose -> (N,); one point set per pose -> (P, N)
    v1 = mug.sdf_world_values(poses[3], x)
    assert v1.shape == (len(x),)
    torch.testing.assert_close(v1, v_fast[3], atol=1e-6, rtol=0)
    xp = x[:500].expand(len(poses), 500, 3) + 0.002 * torch.randn(len(poses), 500, 3, generator=g)
    vp = mug.sdf_world_values(poses, xp)
    ref, _ = mug.sdf_world(poses, xp)
    assert vp.shape == (len(poses), 500) and (vp - ref).abs().quantile(0.999).item() < 1e-6
    # the exact SDF through the values path is the exact SDF
    ve = mug.sdf_world_values(poses[:2], x[:200], exact=True)
    torch.testing.assert_close(ve, mug.sdf_world(poses[:2], x[:200], exact=True)[0])
    # deterministic
    assert torch.equal(mug.sdf_world_values(poses, x), v_fast)


def test_values_fast_path_far_points_and_bad_inputs(mug):
    T = tf.pose_from_xyz_yaw(torch.tensor([0.8, 0.0, 0.0]), torch.tensor(0.3))[None]
    # float32 overflow far away: +inf, like the gradient path
    x = torch.tensor([[1e36, 0.0, 0.0], [0.8, 0.0, 0.02]])
    v = mug.sdf_world_values(T, x)
    assert v[0, 0] == float("inf") and torch.isfinite(v[0, 1])
    assert v[0, 0] == mug.sdf_world(T, x)[0][0, 0]
    with pytest.raises(ValueError, match="NaN"):
        mug.sdf_world_values(T, torch.tensor([[0.0, float("nan"), 0.0]]))
    with pytest.raises(ValueError, match="rigid"):
        mug.sdf_world_values(2 * torch.eye(4)[None], torch.zeros(3, 3))

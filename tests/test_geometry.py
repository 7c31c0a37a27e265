"""Tests for activetouch.geometry: batched transforms, PerturbTransform (RUMI Alg. 3), VoxelGrid."""
import math

import pytest
import torch

from activetouch.geometry import VoxelGrid
from activetouch.geometry import transforms as tf


def _random_poses(P, seed=0, dtype=torch.float64):
    g = torch.Generator().manual_seed(seed)
    aa = torch.randn(P, 3, generator=g, dtype=dtype)
    t = torch.randn(P, 3, generator=g, dtype=dtype)
    return tf.make_pose(tf.axis_angle_to_matrix(aa), t)


def test_invert_and_compose_identity():
    T = _random_poses(50)
    I = T @ tf.invert(T)
    assert torch.allclose(I, torch.eye(4, dtype=T.dtype).expand(50, 4, 4), atol=1e-12)
    assert torch.allclose(tf.invert(tf.invert(T)), T, atol=1e-12)


def test_transform_points_broadcasting_matches_homogeneous_product():
    T = _random_poses(7)
    x = torch.randn(11, 3, dtype=T.dtype)
    y = tf.transform_points(T, x)
    assert y.shape == (7, 11, 3)
    xh = torch.cat([x, torch.ones(11, 1, dtype=x.dtype)], -1)  # (N, 4)
    ref = torch.einsum("pij,nj->pni", T, xh)[..., :3]
    assert torch.allclose(y, ref, atol=1e-12)
    # single pose, and per-pose point sets
    assert tf.transform_points(T[0], x).shape == (11, 3)
    xp = torch.randn(7, 11, 3, dtype=T.dtype)
    assert torch.allclose(tf.transform_points(T, xp)[3], tf.transform_points(T[3], xp[3]))
    # inverse maps back
    assert torch.allclose(tf.transform_points(tf.invert(T), y), x.expand(7, 11, 3), atol=1e-12)


def test_bad_shapes_raise():
    with pytest.raises(ValueError, match="4, 4"):
        tf.transform_points(torch.eye(3), torch.zeros(2, 3))
    with pytest.raises(ValueError, match="N, 3"):
        tf.transform_points(torch.eye(4), torch.zeros(2, 2))
    with pytest.raises(ValueError, match="NaN"):
        tf.check_poses(torch.full((4, 4), float("nan")))


def test_yaw_roundtrip_and_matrix():
    yaw = torch.linspace(-3.1, 3.1, 25, dtype=torch.float64)
    xyz = torch.randn(25, 3, dtype=torch.float64)
    T = tf.pose_from_xyz_yaw(xyz, yaw)
    assert torch.allclose(tf.yaw_of(T), yaw, atol=1e-12)
    assert torch.allclose(T[:, :3, 3], xyz)
    R = tf.yaw_matrix(torch.tensor(math.pi / 2, dtype=torch.float64))
    assert torch.allclose(R @ torch.tensor([1.0, 0, 0], dtype=torch.float64), torch.tensor([0.0, 1, 0], dtype=torch.float64))


def test_axis_angle_is_rotation_about_axis():
    g = torch.Generator().manual_seed(1)
    aa = torch.randn(100, 3, generator=g, dtype=torch.float64)
    R = tf.axis_angle_to_matrix(aa)
    assert torch.allclose(R @ R.transpose(-1, -2), torch.eye(3, dtype=R.dtype).expand(100, 3, 3), atol=1e-10)
    assert torch.allclose(torch.linalg.det(R), torch.ones(100, dtype=R.dtype), atol=1e-10)
    # the axis is fixed and the angle is |aa| (mod 2 pi)
    assert torch.allclose((R @ aa.unsqueeze(-1)).squeeze(-1), aa, atol=1e-10)
    ang = torch.acos(((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    ref = torch.remainder(aa.norm(dim=-1), 2 * math.pi)
    ref = torch.where(ref > math.pi, 2 * math.pi - ref, ref)
    assert torch.allclose(ang, ref, atol=1e-6)
    # zero rotation is exactly the identity
    assert torch.allclose(tf.axis_angle_to_matrix(torch.zeros(3)), torch.eye(3))


def test_perturb_transform_se2_statistics():
    n, st, sr = 20000, 0.01, 0.2
    T = tf.perturb_transform(n, st, sr, se2=True, generator=torch.Generator().manual_seed(0), dtype=torch.float64)
    assert T.shape == (n, 4, 4)
    # z axis kept, no z translation, bottom row
    assert torch.allclose(T[:, 2, :3], torch.tensor([0.0, 0, 1], dtype=T.dtype).expand(n, 3))
    assert torch.allclose(T[:, :3, 2], torch.tensor([0.0, 0, 1], dtype=T.dtype).expand(n, 3))
    assert torch.all(T[:, 2, 3] == 0)
    assert torch.allclose(T[:, 3], torch.tensor([0.0, 0, 0, 1], dtype=T.dtype).expand(n, 4))
    std_t = T[:, :2, 3].std(dim=0)
    assert torch.allclose(std_t, torch.full((2,), st, dtype=T.dtype), rtol=0.03)
    assert abs(T[:, :2, 3].mean().item()) < 3 * st / math.sqrt(n) * 2
    yaw = tf.yaw_of(T)
    assert abs(yaw.std().item() - sr) < 0.03 * sr


def test_perturb_transform_se3_statistics_and_seed():
    n, st, sr = 20000, 0.02, 0.1
    g = torch.Generator().manual_seed(3)
    T = tf.perturb_transform(n, st, sr, se2=False, generator=g, dtype=torch.float64)
    std_t = T[:, :3, 3].std(dim=0)
    assert torch.allclose(std_t, torch.full((3,), st, dtype=T.dtype), rtol=0.03)
    R = T[:, :3, :3]
    ang = torch.acos(((R.diagonal(dim1=-2, dim2=-1).sum(-1) - 1) / 2).clamp(-1, 1))
    # |theta| with theta ~ N(0, sr^2): E[theta^2] = sr^2
    assert abs(ang.pow(2).mean().sqrt().item() - sr) < 0.03 * sr
    # axis uniform on the sphere: each rotated basis vector tilts equally on average
    tilt = 1 - R.diagonal(dim1=-2, dim2=-1).mean(0)
    assert tilt.max() / tilt.min() < 1.1
    T2 = tf.perturb_transform(n, st, sr, se2=False, generator=torch.Generator().manual_seed(3), dtype=torch.float64)
    assert torch.equal(T, T2)
    T0 = tf.perturb_transform(10, st, 0.0, se2=False, generator=g)
    assert torch.allclose(T0[:, :3, :3], torch.eye(3).expand(10, 3, 3))


def test_perturb_transform_rejects_bad_args():
    with pytest.raises(ValueError):
        tf.perturb_transform(5, -0.1, 0.0, se2=True)
    with pytest.raises(ValueError):
        tf.perturb_transform(5, 0.1, float("nan"), se2=True)


def test_voxel_grid_shape_points_and_linear_interpolation():
    grid = VoxelGrid([0.0, -0.1, 0.2], [0.1, 0.1, 0.25], 0.01)
    assert grid.shape == (10, 20, 5)
    pts = grid.points(dtype=torch.float64)
    assert pts.shape == (1000, 3)
    assert torch.allclose(pts[0], torch.tensor([0.005, -0.095, 0.205], dtype=torch.float64))
    # trilinear interpolation reproduces affine functions exactly between cell centres
    a = torch.tensor([1.0, -2.0, 3.0], dtype=torch.float64)
    vals = (pts @ a + 0.5).reshape(grid.shape)
    g = torch.Generator().manual_seed(0)
    x = torch.rand(500, 3, generator=g, dtype=torch.float64) * torch.tensor([0.09, 0.19, 0.04], dtype=torch.float64)
    x = x + torch.tensor([0.005, -0.095, 0.205], dtype=torch.float64)
    x.requires_grad_(True)
    v = grid.interpolate(vals, x)
    assert torch.allclose(v, x @ a + 0.5, atol=1e-9)
    v.sum().backward()
    assert torch.allclose(x.grad, a.expand(500, 3), atol=1e-6)
    # outside value, and multi-channel
    out = grid.interpolate(vals, torch.tensor([[1.0, 0, 0]], dtype=torch.float64), outside=-7.0)
    assert out.item() == -7.0
    v2 = grid.interpolate(torch.stack([vals, 2 * vals], -1), x.detach())
    assert v2.shape == (500, 2) and torch.allclose(v2[:, 1], 2 * v2[:, 0])
    with pytest.raises(ValueError, match="shape"):
        grid.interpolate(torch.zeros(3, 3, 3), x)
    with pytest.raises(ValueError):
        VoxelGrid([0, 0, 0], [0, 1, 1], 0.1)


def test_check_poses_rejects_non_rigid_transforms():
    good = _random_poses(5, seed=3).float()
    assert tf.check_poses(good) is good
    # float32 round-off (and drift of composed poses) is well inside the 1e-3 tolerance
    noisy = good.clone()
    noisy[:, :3, :3] += 1e-5 * torch.randn(5, 3, 3, generator=torch.Generator().manual_seed(0))
    tf.check_poses(noisy)
    scaled = good.clone()
    scaled[2, :3, :3] *= 2.0
    reflected = good.clone()
    reflected[1, :3, 0] *= -1.0  # orthonormal, det -1
    sheared = good.clone()
    sheared[4, 0, 1] += 0.05
    bottom = good.clone()
    bottom[0, 3, 0] = 0.5
    for bad, i in ((scaled, 2), (reflected, 1), (sheared, 4), (bottom, 0)):
        with pytest.raises(ValueError, match=rf"rigid transforms \(pose {i} of 5\)"):
            tf.check_poses(bad, "poses")
    with pytest.raises(ValueError, match="dT must be rigid.*det R = 8"):
        tf.check_poses(2 * torch.eye(4), "dT")
    # general 4 x 4 matrices on request; NaN is reported as NaN first
    tf.check_poses(2 * torch.eye(4), rigid=False)
    with pytest.raises(ValueError, match="NaN"):
        tf.check_poses(torch.full((4, 4), float("nan")))
    # message is one line
    with pytest.raises(ValueError) as e:
        tf.check_poses(2 * torch.eye(4))
    assert "\n" not in str(e.value)

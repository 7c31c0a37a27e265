"""Next best view (visuo-tactile clutter paper Sec. II-D-1, Eq. 20-24) and the NBV/NBT stop rule (Sec. II-D-2):
activetouch.planning.nbv."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from activetouch.information.occupancy import OccupancyConfig, OccupancyGrid, region_around
from activetouch.planning.nbv import (
    NBVConfig,
    cameras_for,
    hemisphere_views,
    pose_change_below,
    select_next_best_view,
    view_ray_directions,
    view_rotations,
)
from activetouch.sim.camera import PinholeCamera

CENTROID = torch.tensor([0.5, 0.0, 0.05], dtype=torch.float64)


def _angle(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Angles (rad) between rows of ``a`` and ``b``, accurate near 0."""
    return torch.atan2(torch.linalg.cross(a, b).norm(dim=-1), (a * b).sum(-1))


def _check_rotations(R):
    eye = torch.eye(3, dtype=R.dtype)
    assert torch.allclose(R.transpose(-1, -2) @ R, eye.expand_as(R), atol=1e-12)
    assert torch.allclose(torch.linalg.det(R), torch.ones(R.shape[0], dtype=R.dtype), atol=1e-12)


# ---- config ----------------------------------------------------------------------------------------------------

def test_config_defaults():
    c = NBVConfig()
    assert (c.num_views, c.radius, c.min_elevation_deg, c.width, c.height, c.fov_y_deg, c.max_depth) == (
        50, 0.45, 20.0, 64, 48, 55.0, 1.5)
    assert (c.stop_translation, c.stop_rotation_deg) == (0.005, 2.0)


@pytest.mark.parametrize("field, value", [
    ("num_views", 0), ("num_views", 2.5), ("radius", 0.0), ("min_elevation_deg", 90.0),
    ("min_elevation_deg", -1.0), ("width", 0), ("height", True), ("fov_y_deg", 180.0), ("max_depth", -1.0),
    ("stop_translation", 0.0), ("stop_rotation_deg", float("nan")), ("radius", float("inf")),
])
def test_config_rejects_bad_fields_naming_them(field, value):
    with pytest.raises(ValueError, match=field):
        NBVConfig(**{field: value})


# ---- views (Eq. 20-21) -----------------------------------------------------------------------------------------

@pytest.mark.parametrize("gen", [lambda: torch.Generator().manual_seed(0), lambda: np.random.default_rng(0)])
def test_hemisphere_views_look_at_the_centroid(gen):
    cfg = NBVConfig(num_views=200)
    p, R = hemisphere_views(CENTROID, cfg, gen())
    assert p.shape == (200, 3) and R.shape == (200, 3, 3) and p.dtype == torch.float64
    off = p - CENTROID
    assert torch.allclose(off.norm(dim=1), torch.full((200,), 0.45, dtype=torch.float64), atol=1e-12)
    elev = torch.rad2deg(torch.asin(off[:, 2] / 0.45))
    assert float(elev.min()) >= 20.0 - 1e-9 and float(elev.max()) <= 90.0
    _check_rotations(R)
    assert float(_angle(R[:, :, 2], -off).max()) < 1e-6  # optical (forward) axis at the centroid
    # the cap is covered: views on every side
    az = torch.atan2(off[:, 1], off[:, 0])
    assert torch.histc(az, bins=4, min=-math.pi, max=math.pi).min() > 20
    # same seed, same views
    p2, R2 = hemisphere_views(CENTROID, cfg, gen())
    assert torch.equal(p, p2) and torch.equal(R, R2)


def test_view_rotation_is_eq21_applied_to_the_straight_down_camera():
    p = CENTROID + torch.tensor([[0.3, -0.2, 0.25]], dtype=torch.float64)
    R = view_rotations(p, CENTROID)[0]
    h = (p[0] - CENTROID) / (p[0] - CENTROID).norm()
    Z = torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64)
    theta = math.acos(float(h @ Z))
    e = torch.linalg.cross(h, Z)
    e = e / e.norm()
    K = torch.tensor([[0, -e[2], e[1]], [e[2], 0, -e[0]], [-e[1], e[0], 0]], dtype=torch.float64)
    rot = torch.eye(3, dtype=torch.float64) + math.sin(theta) * K + (1 - math.cos(theta)) * K @ K  # Rot(e, theta)
    assert torch.allclose(rot @ h, Z, atol=1e-12)  # Eq. 21's rotation turns h onto Z ...
    R_down = torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64))
    assert torch.allclose(R, rot.T @ R_down, atol=1e-12)  # ... so its inverse turns the down camera onto -h
    assert torch.allclose(R[:, 2], -h, atol=1e-12)


def test_degenerate_straight_above_and_below():
    up = CENTROID + torch.tensor([[0.0, 0.0, 0.45]], dtype=torch.float64)
    down = CENTROID - torch.tensor([[0.0, 0.0, 0.45]], dtype=torch.float64)
    R = view_rotations(torch.cat([up, down]), CENTROID)
    _check_rotations(R)
    assert torch.allclose(R[0], torch.diag(torch.tensor([1.0, -1.0, -1.0], dtype=torch.float64)))
    assert torch.allclose(R[0, :, 2], torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64))
    assert torch.allclose(R[1, :, 2], torch.tensor([0.0, 0.0, 1.0], dtype=torch.float64), atol=1e-12)
    cam = cameras_for(up, R[:1])[0]  # look_at cannot look along its up axis: nudged by 1e-6 m
    assert float(_angle(torch.as_tensor(cam.rotation()[:, 2]), R[0, :, 2])) < 1e-5
    with pytest.raises(ValueError, match="centroid"):
        view_rotations(CENTROID[None], CENTROID)


def test_reachable_filters_views():
    def reachable(x):
        return x[:, 1] > 0.0  # only the +y half

    p, R = hemisphere_views(CENTROID, NBVConfig(num_views=30), torch.Generator().manual_seed(1), reachable)
    assert p.shape == (30, 3) and bool((p[:, 1] > 0).all())
    assert float(_angle(R[:, :, 2], CENTROID - p).max()) < 1e-6
    p_np, _ = hemisphere_views(CENTROID, NBVConfig(num_views=5), np.random.default_rng(0),
                               lambda x: np.asarray(x[:, 0] < 0.5))
    assert bool((p_np[:, 0] < 0.5).all())
    with pytest.raises(ValueError, match="reachable"):
        hemisphere_views(CENTROID, NBVConfig(num_views=5), np.random.default_rng(0),
                         lambda x: torch.zeros(len(x), dtype=torch.bool), max_rounds=3)
    with pytest.raises(ValueError, match="reachable"):
        hemisphere_views(CENTROID, NBVConfig(num_views=5), np.random.default_rng(0), lambda x: x[:, 0])
    with pytest.raises(ValueError, match="centroid"):
        hemisphere_views([0.0, 0.0], NBVConfig(), np.random.default_rng(0))
    with pytest.raises(ValueError, match="generator"):
        hemisphere_views(CENTROID, NBVConfig(), 0)


def test_ray_directions_follow_the_pinhole_camera_convention():
    cfg = NBVConfig(width=16, height=12)
    p, R = hemisphere_views(CENTROID, NBVConfig(num_views=4), torch.Generator().manual_seed(2))
    D = view_ray_directions(R, cfg)
    assert D.shape == (4, 16 * 12, 3)
    assert torch.allclose(D.norm(dim=-1), torch.ones(4, 192, dtype=torch.float64))
    for k, cam in enumerate(cameras_for(p, R, cfg)):
        assert isinstance(cam, PinholeCamera) and (cam.width, cam.height, cam.max_depth) == (16, 12, 1.5)
        Rc = torch.as_tensor(cam.rotation())
        assert float(_angle(Rc[:, 2], R[k, :, 2])) < 1e-9  # same optical axis (roll may differ)
        assert torch.allclose(view_ray_directions(Rc[None], cfg)[0], torch.as_tensor(cam.ray_directions()),
                              atol=1e-12)
    # the principal ray (image centre) is the forward axis
    centre = view_ray_directions(R, NBVConfig(width=3, height=3))[:, 4]
    assert torch.allclose(centre, R[:, :, 2], atol=1e-12)
    with pytest.raises(ValueError, match="rotations"):
        view_ray_directions(torch.eye(3), cfg)


# ---- selection (Eq. 24) on a synthetic scene -------------------------------------------------------------------

def _ray_box(o, d, lo, hi):
    """Distances (R,) to an axis-aligned box (``inf`` where missed) of rays ``o (3,)``, ``d (R, 3)``."""
    with np.errstate(divide="ignore", invalid="ignore"):
        t1, t2 = (lo - o) / d, (hi - o) / d
    tmin, tmax = np.nanmax(np.minimum(t1, t2), 1), np.nanmin(np.maximum(t1, t2), 1)
    return np.where((tmin > 0) & (tmin <= tmax), tmin, np.inf)


def test_next_best_view_looks_at_the_unobserved_side():
    c = CENTROID.numpy()
    half = np.array([0.04, 0.04, 0.05])
    box_lo, box_hi = c - half, c + half
    lower, upper = region_around(torch.tensor(np.stack([box_lo, box_hi])), 0.1)
    grid = OccupancyGrid(lower, upper, OccupancyConfig(resolution=0.01))
    # the +x side observed by six depth images from cameras on the +x side
    for off in ([0.4, 0, 0.2], [0.38, 0.1, 0.2], [0.38, -0.1, 0.2], [0.4, 0, 0.1], [0.35, 0, 0.3], [0.4, 0.05, 0.15]):
        cam = PinholeCamera(pos=tuple(c + off), target=tuple(c), width=64, height=48, max_depth=1.5)
        o, d = np.asarray(cam.pos), cam.ray_directions()
        t = _ray_box(o, d, box_lo, box_hi)
        hit = np.isfinite(t)
        grid.integrate(o, o + d * np.where(hit, t, 1.5)[:, None], hit)
    before = grid.log_odds.clone()
    cfg = NBVConfig(num_views=40, width=32, height=24)
    p, R = hemisphere_views(CENTROID, cfg, torch.Generator().manual_seed(0))
    assert int((p[:, 0] < c[0]).sum()) >= 10 and int((p[:, 0] > c[0]).sum()) >= 10  # both sides offered
    idx, gains = select_next_best_view(grid, p, view_ray_directions(R, cfg), cfg.max_depth)
    assert gains.shape == (40,) and bool((gains >= 0).all()) and idx == int(torch.argmax(gains))
    assert float(p[idx, 0]) < c[0] - 0.1  # the chosen view looks from the unobserved -x side
    # views from the observed side gain clearly less than those from the unobserved side
    seen, unseen = gains[p[:, 0] > c[0] + 0.2], gains[p[:, 0] < c[0] - 0.2]
    assert float(seen.mean()) < 0.8 * float(unseen.mean())
    assert torch.equal(grid.log_odds, before)  # selection does not modify the grid
    with pytest.raises(ValueError, match="positions"):
        select_next_best_view(grid, p[:0], view_ray_directions(R, cfg)[:0], 1.5)


# ---- stop rule (Sec. II-D-2) -----------------------------------------------------------------------------------

def _pose(angle_deg=0.0, t=(0.0, 0.0, 0.0)):
    a = math.radians(angle_deg)
    T = torch.eye(4, dtype=torch.float64)
    T[:3, :3] = torch.tensor([[math.cos(a), -math.sin(a), 0], [math.sin(a), math.cos(a), 0], [0, 0, 1]])
    T[:3, 3] = torch.tensor(t)
    return T


def test_pose_change_below():
    A = _pose(10.0, (0.3, 0.1, 0.05))
    assert pose_change_below(A, A)
    assert pose_change_below(A, _pose(11.9, (0.303, 0.103, 0.05)))  # 4.2 mm, 1.9 deg
    assert not pose_change_below(A, _pose(10.0, (0.306, 0.1, 0.05)))  # 6 mm
    assert not pose_change_below(A, _pose(12.1, (0.3, 0.1, 0.05)))  # 2.1 deg
    assert pose_change_below(A.numpy(), _pose(10.5).numpy() @ np.eye(4), translation=1.0, rotation_deg=1.0) is True
    assert not pose_change_below(A, _pose(190.0, (0.3, 0.1, 0.05)), rotation_deg=179.0)
    with pytest.raises(ValueError, match="prev_pose"):
        pose_change_below(torch.eye(3), A)
    with pytest.raises(ValueError, match="pose"):
        pose_change_below(A, torch.eye(4)[:3])
    with pytest.raises(ValueError, match="translation"):
        pose_change_below(A, A, translation=0.0)
    with pytest.raises(ValueError, match="rotation_deg"):
        pose_change_below(A, A, rotation_deg=-2.0)

"""RUMI information gain field (Eq. 23) and semantics field (Eq. 27) on the mug."""
from __future__ import annotations

import math

import pytest
import torch

from activetouch import objects
from activetouch.geometry import VoxelGrid, pose_from_xyz_yaw
from activetouch.information import (
    FREE,
    OCCUPIED,
    SURFACE,
    compute_field,
    field_margin,
    information_gain,
    per_semantics_costs,
    semantics_probabilities,
)
from activetouch.observations import SemanticSensorModel

BODY_OFFSET = torch.tensor([-0.012, 0.0, 0.0])  # mug body axis in the object frame (handle along +x)
CENTRE = torch.tensor([0.40, 0.0, 0.0])  # world position of the body axis
LAM, C, ALPHA = 2.0, 10.0, -0.004  # Table IV lambda, C; the belief's alpha = -violation_tolerance


def mug_particles(yaws: torch.Tensor):
    """Particles sharing the mug body axis at CENTRE, differing in yaw (the handle direction)."""
    P = len(yaws)
    R = pose_from_xyz_yaw(torch.zeros(P, 3), yaws)[:, :3, :3]
    t = CENTRE - torch.einsum("pij,j->pi", R, BODY_OFFSET)
    return pose_from_xyz_yaw(t, yaws), torch.full((P,), 1.0 / P)


@pytest.fixture(scope="module")
def mug():
    return objects.load("mug")


@pytest.fixture(scope="module")
def slab():
    # 5 mm grid, one layer at the handle's height
    return VoxelGrid([0.15, -0.25, 0.035], [0.65, 0.25, 0.045], 0.005)


@pytest.fixture(scope="module")
def hidden_field(mug, slab):
    """Camera at -x saw the front of the mug: the handle (36 yaws) can only be in the hidden back half."""
    poses, w = mug_particles(torch.linspace(-math.pi / 3, math.pi / 3, 36))
    return compute_field(mug, poses, w, slab, lam=LAM, free_scale=C, alpha=ALPHA), poses, w


def _polar(grid):
    pts = grid.points().reshape(*grid.shape, 3)[..., 0, :]
    rel = pts[..., :2] - CENTRE[:2]
    return pts, rel.norm(dim=-1), torch.atan2(rel[..., 1], rel[..., 0])


def test_info_largest_where_handle_could_be(hidden_field, slab):
    field, _, _ = hidden_field
    info = field.info[..., 0]
    _, dist, ang = _polar(slab)
    imax = float(info.max())
    k = int(info.argmax())
    # argmax in the handle ring (body radius 47 mm, handle reaches ~71 mm) on the hidden side
    assert 0.047 <= float(dist.reshape(-1)[k]) <= 0.08
    assert abs(float(ang.reshape(-1)[k])) < math.radians(65)
    ring = (dist >= 0.06) & (dist < 0.08)
    back = info[ring & (ang.abs() < math.pi / 4)].mean()
    front = info[ring & (ang.abs() > 3 * math.pi / 4)].mean()
    assert back > 2.0 * front
    # far from the mug: nothing to learn
    assert float(info[dist > 0.18].max()) < 1e-3 * imax
    # observed free space in front of the mug (camera side), away from the surface band
    front_free = (dist > 0.09) & (dist < 0.13) & (ang.abs() > 3 * math.pi / 4)
    assert float(info[front_free].mean()) < 0.05 * imax


def test_full_yaw_ring_is_rotationally_symmetric(mug, slab):
    poses, w = mug_particles(torch.arange(36) * 2 * math.pi / 36)
    info = compute_field(mug, poses, w, slab, lam=LAM, free_scale=C, alpha=ALPHA).info[..., 0]
    _, dist, ang = _polar(slab)
    ring = (dist >= 0.06) & (dist < 0.08)
    back = info[ring & (ang.abs() < math.pi / 4)].mean()
    front = info[ring & (ang.abs() > 3 * math.pi / 4)].mean()
    assert abs(float(back - front)) < 0.15 * float(back)


def test_probabilities_eq27(mug, hidden_field, slab):
    field, poses, w = hidden_field
    assert torch.allclose(field.probs.sum(-1), torch.ones(slab.shape), atol=1e-5)
    # cell centres: the cached grid equals the direct (ungridded) Eq. 27 / Eq. 23 evaluation
    pts = slab.points()[::37]
    direct = semantics_probabilities(mug, poses, w, pts)
    assert torch.allclose(field.semantics(pts), direct, atol=1e-5)
    gain = information_gain(mug, poses, w, pts, lam=LAM, free_scale=C, alpha=ALPHA)
    assert torch.allclose(field.information(pts), gain, atol=1e-3 * float(field.info.max()))
    # one particle: Eq. 27 is the sensor model at sdf(T^-1 x)
    x = torch.tensor([[0.40, 0.0, 0.04], [0.45, 0.0, 0.04], [0.30, 0.1, 0.04]])
    v, _ = mug.sdf_world(poses[:1], x)
    p1 = semantics_probabilities(mug, poses[:1], torch.ones(1), x)
    assert torch.allclose(p1, SemanticSensorModel().probs(v[0]), atol=1e-6)


def test_outside_workspace_is_free_and_uninformative(hidden_field):
    field, _, _ = hidden_field
    x = torch.tensor([[1.5, 0.0, 0.04], [0.4, 0.0, 0.5], [-1.0, -1.0, -1.0]])
    p = field.semantics(x)
    assert torch.equal(p, torch.tensor([[0.0, 1.0, 0.0]] * 3))
    assert torch.equal(field.information(x), torch.zeros(3))
    assert torch.equal(field.free_probability(x), torch.ones(3))
    g = field.grid_coords(x)
    assert torch.equal(field.sample_free(g), torch.ones(3))


def test_fast_free_lookup_matches_trilinear(hidden_field, slab):
    field, _, _ = hidden_field
    gen = torch.Generator().manual_seed(0)
    lo, up = slab.lower.float(), slab.upper.float()
    x = lo + (up - lo + 0.04) * torch.rand(5000, 3, generator=gen) - 0.02  # includes points outside
    x[:, 2] = 0.03 + 0.02 * torch.rand(5000, generator=gen)  # around and off the single z layer
    assert torch.allclose(field.sample_free(field.grid_coords(x)), field.free_probability(x), atol=1e-5)


def test_far_points_skipped_exactly(mug, hidden_field):
    field, poses, w = hidden_field
    m = field_margin(SemanticSensorModel())
    assert 0.09 < m < 0.1
    # a point just outside the culled region: its exact field value is negligible
    x = torch.tensor([[float(field.active_upper[0]) + 0.01, 0.0, 0.04]])
    p = semantics_probabilities(mug, poses, w, x)
    assert float(p[0, FREE]) > 1 - 1e-4


def test_per_semantics_costs_match_belief_discrepancy(mug):
    from activetouch.belief.discrepancy import point_costs
    from activetouch.observations import Features

    poses, _ = mug_particles(torch.tensor([0.0, 1.0, 2.5]))
    x = torch.tensor([[0.40, 0.0, 0.04], [0.452, 0.0, 0.04], [0.46, 0.02, 0.01], [0.30, 0.1, 0.04]])
    v, _ = mug.sdf_world(poses, x)
    mine = per_semantics_costs(v, C, ALPHA)  # (P, N, 3)
    for s in (SURFACE, FREE, OCCUPIED):
        feats = Features(x, torch.full((4,), s, dtype=torch.long))
        ref = point_costs(mug, feats, poses, free_scale=C, violation_tolerance=-ALPHA)
        assert torch.allclose(mine[..., s], ref, atol=1e-6), s


def test_bad_inputs(mug, slab):
    poses, w = mug_particles(torch.zeros(3))
    with pytest.raises(ValueError, match="weights"):
        compute_field(mug, poses, w[:2], slab, lam=LAM, free_scale=C, alpha=ALPHA)
    with pytest.raises(ValueError, match="weights"):
        compute_field(mug, poses, -w, slab, lam=LAM, free_scale=C, alpha=ALPHA)
    with pytest.raises(ValueError, match="poses"):
        compute_field(mug, poses[:, :3], w, slab, lam=LAM, free_scale=C, alpha=ALPHA)
    bad = poses.clone()
    bad[0, 0, 3] = float("nan")
    with pytest.raises(ValueError, match="NaN"):
        compute_field(mug, bad, w, slab, lam=LAM, free_scale=C, alpha=ALPHA)
    with pytest.raises(ValueError, match="VoxelGrid"):
        compute_field(mug, poses, w, "grid", lam=LAM, free_scale=C, alpha=ALPHA)
    with pytest.raises(ValueError, match="x"):
        semantics_probabilities(mug, poses, w, torch.zeros(4, 2))

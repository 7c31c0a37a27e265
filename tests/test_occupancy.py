"""Occupancy grid (Eq. 19, 22) and the expected information gain of a view (Eq. 23), visuo-tactile clutter paper
Sec. II-D-1: activetouch.information.occupancy."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from activetouch.information.occupancy import (
    OccupancyConfig,
    OccupancyGrid,
    bernoulli_entropy,
    expected_information_gain,
    region_around,
)

LN2 = math.log(2.0)


def _logit(p):
    return math.log(p / (1 - p))


def _grid(n=10, res=0.01, dtype=torch.float64, **kw):
    return OccupancyGrid([0.0, 0.0, 0.0], [n * res] * 3, OccupancyConfig(resolution=res, **kw), dtype=dtype)


def _cells_by_sampling(grid, o, e, steps=200_001):
    """Reference: the cells a segment passes through, by very fine sampling (set of linear indices)."""
    o, e = torch.as_tensor(o, dtype=torch.float64), torch.as_tensor(e, dtype=torch.float64)
    s = torch.linspace(0, 1, steps, dtype=torch.float64)[:, None]
    idx = torch.floor((o + (e - o) * s - grid.lower.double()) / grid.resolution).long()
    idx = idx[((idx >= 0) & (idx < torch.tensor(grid.shape))).all(1)]
    X, Y, Z = grid.shape
    return set(torch.unique((idx[:, 0] * Y + idx[:, 1]) * Z + idx[:, 2]).tolist())


# ---- config ----------------------------------------------------------------------------------------------------

def test_config_defaults_are_the_paper_and_octomap_values():
    c = OccupancyConfig()
    assert (c.p_hit, c.p_miss, c.p_prior, c.p_min, c.p_max, c.resolution) == (0.7, 0.4, 0.5, 0.12, 0.97, 0.01)
    assert c.l_hit == pytest.approx(math.log(0.7 / 0.3)) and c.l_miss == pytest.approx(math.log(0.4 / 0.6))


@pytest.mark.parametrize("field, value", [
    ("resolution", 0.0), ("resolution", float("nan")), ("p_hit", 0.5), ("p_hit", 1.0), ("p_miss", 0.5),
    ("p_miss", 0.0), ("p_min", 0.6), ("p_max", 0.4), ("p_max", 1.0), ("p_prior", 0.05), ("max_range", -1.0),
    ("max_range", float("inf")), ("p_hit", True),
])
def test_config_rejects_bad_fields_naming_them(field, value):
    with pytest.raises(ValueError, match=field):
        OccupancyConfig(**{field: value})


# ---- grid ------------------------------------------------------------------------------------------------------

def test_fresh_grid_entropy_is_n_cells_ln2_and_box_is_rounded_up():
    g = OccupancyGrid([0.0, 0.0, 0.0], [0.1, 0.205, 0.3], OccupancyConfig(resolution=0.01))
    assert g.shape == (10, 21, 30)
    assert torch.allclose(g.upper.double(), torch.tensor([0.1, 0.21, 0.3], dtype=torch.float64), atol=1e-6)
    assert float(g.entropy()) == pytest.approx(g.n_cells * LN2, rel=1e-6)
    assert torch.allclose(g.prob(), torch.full(g.shape, 0.5))
    assert torch.allclose(g.cell_entropy(), torch.full(g.shape, LN2))
    centres = g.cell_centers()
    assert centres.shape == (10, 21, 30, 3)
    ijk = torch.stack(torch.meshgrid(*[torch.arange(n) for n in g.shape], indexing="ij"), -1).reshape(-1, 3)
    assert torch.equal(g.index_of(centres.reshape(-1, 3)), ijk)
    assert g.index_of([[-0.001, 0.0, 0.0], [0.05, 0.05, 0.31]]).tolist() == [[-1, -1, -1]] * 2


def test_bernoulli_entropy_matches_definition_and_is_finite_at_extremes():
    p = torch.tensor([0.12, 0.4, 0.5, 0.7, 0.97], dtype=torch.float64)
    ref = -(p * p.log() + (1 - p) * (1 - p).log())
    assert torch.allclose(bernoulli_entropy(torch.log(p / (1 - p))), ref, atol=1e-12)
    assert torch.isfinite(bernoulli_entropy(torch.tensor([-1e4, 1e4]))).all()


def test_ray_through_empty_space_frees_traversed_cells_and_marks_end_cell():
    g = _grid()
    # along x at the centre of row (y, z) = (5, 5), from outside the grid to the centre of cell x = 7
    g.integrate([-0.05, 0.055, 0.055], [[0.075, 0.055, 0.055]], torch.tensor([True]))
    p = g.prob()
    assert torch.allclose(p[:7, 5, 5], torch.full((7,), 0.4, dtype=torch.float64), atol=1e-12)
    assert float(p[7, 5, 5]) == pytest.approx(0.7, abs=1e-12)
    untouched = torch.ones(g.shape, dtype=torch.bool)
    untouched[:8, 5, 5] = False
    assert torch.all(p[untouched] == 0.5)
    # a miss ray (hit=False) frees its end cell too
    g2 = _grid()
    g2.integrate([-0.05, 0.055, 0.055], [[0.075, 0.055, 0.055]], [False])
    assert torch.allclose(g2.prob()[:8, 5, 5], torch.full((8,), 0.4, dtype=torch.float64))


def test_traversal_is_exact_against_fine_sampling():
    g = OccupancyGrid([0.0, 0.0, 0.0], [0.07, 0.05, 0.06], OccupancyConfig(resolution=0.01), dtype=torch.float64)
    rng = np.random.default_rng(3)
    for _ in range(40):
        o, e = rng.uniform(-0.03, 0.1, 3), rng.uniform(-0.03, 0.1, 3)
        gg = g.clone().integrate(o, e[None], [False])
        changed = (gg.log_odds != 0).reshape(-1).nonzero()[:, 0].tolist()
        assert set(changed) == _cells_by_sampling(g, o, e)
        assert torch.allclose(gg.prob()[gg.log_odds != 0], torch.tensor(0.4, dtype=torch.float64))


def test_cell_updated_once_per_ray_through_corners_and_end_not_also_a_miss():
    g = _grid()
    # the diagonal through the exact corners of cells (k, k, k): three planes are crossed at once at each corner
    g.integrate([0.005, 0.005, 0.005], [[0.095, 0.095, 0.095]], [True])
    l = g.log_odds
    changed = (l != 0).nonzero()
    diag = [(k, k, k) for k in range(10)]
    assert {tuple(r) for r in changed.tolist()} >= set(diag)
    for k in range(9):
        assert float(l[k, k, k]) == pytest.approx(_logit(0.4), abs=1e-12)  # one miss, not three
    assert float(l[9, 9, 9]) == pytest.approx(_logit(0.7), abs=1e-12)  # hit only
    # a zero-length ray: only the hit
    g2 = _grid()
    g2.integrate([0.055, 0.055, 0.055], [[0.055, 0.055, 0.055]], [True])
    assert int((g2.log_odds != 0).sum()) == 1 and float(g2.prob()[5, 5, 5]) == pytest.approx(0.7)


def test_repeated_hits_and_misses_saturate_at_clamp():
    g = _grid()
    for _ in range(30):
        g.integrate([-0.05, 0.055, 0.055], [[0.075, 0.055, 0.055]], [True])
    p = g.prob()
    assert float(p[7, 5, 5]) == pytest.approx(0.97, abs=1e-12)
    assert torch.allclose(p[:7, 5, 5], torch.full((7,), 0.12, dtype=torch.float64), atol=1e-12)
    assert float(p.max()) <= 0.97 + 1e-12 and float(p.min()) >= 0.12 - 1e-12
    # one call with 30 identical rays: summed, then clamped once (same result)
    g2 = _grid()
    g2.integrate([-0.05, 0.055, 0.055], torch.tensor([[0.075, 0.055, 0.055]]).repeat(30, 1), torch.ones(30, dtype=bool))
    assert torch.allclose(g2.log_odds, g.log_odds)


def test_integrate_is_order_independent():
    rng = np.random.default_rng(0)
    o = np.array([-0.1, 0.05, 0.15])
    ends = rng.uniform(0.0, 0.1, (200, 3))
    hit = rng.random(200) < 0.5
    a = _grid(dtype=torch.float32).integrate(o, ends, hit)
    perm = rng.permutation(200)
    b = _grid(dtype=torch.float32).integrate(o, ends[perm], hit[perm])
    assert torch.allclose(a.log_odds, b.log_odds, atol=1e-5)
    # two small unclamped ray sets integrated in either order
    e1, e2 = rng.uniform(0.0, 0.1, (3, 3)), rng.uniform(0.0, 0.1, (3, 3))
    c = _grid().integrate(o, e1, [True] * 3).integrate([0.2, 0.2, 0.2], e2, [True, False, True])
    d = _grid().integrate([0.2, 0.2, 0.2], e2, [True, False, True]).integrate(o, e1, [True] * 3)
    assert torch.allclose(c.log_odds, d.log_odds, atol=1e-12)


def test_rays_from_outside_are_clipped_to_the_grid():
    g = _grid()
    # origin 10 cm outside on -x, endpoint beyond the grid on +x (a hit outside): only misses inside, no hit
    g.integrate([-0.1, 0.035, 0.065], [[0.2, 0.035, 0.065]], [True])
    p = g.prob()
    assert torch.allclose(p[:, 3, 6], torch.full((10,), 0.4, dtype=torch.float64))
    assert int((g.log_odds != 0).sum()) == 10
    # a ray that passes beside the grid changes nothing
    g2 = _grid()
    g2.integrate([-0.1, -0.05, 0.05], [[0.2, -0.01, 0.05]], [True])
    assert torch.all(g2.log_odds == 0)
    # an oblique ray entering through a face: the clipped cells equal the sampled ones
    g3 = _grid()
    o, e = np.array([-0.08, -0.03, 0.2]), np.array([0.043, 0.061, 0.017])
    g3.integrate(o, e[None], [True])
    changed = set((g3.log_odds != 0).reshape(-1).nonzero()[:, 0].tolist())
    assert changed == _cells_by_sampling(g3, o, e)
    assert float(g3.prob()[4, 6, 1]) == pytest.approx(0.7)
    # a ray from outside ending exactly on the grid's face: only its end cell, a hit
    g4 = _grid()
    g4.integrate([-0.05, 0.055, 0.055], [[0.0, 0.055, 0.055]], [True])
    assert (g4.log_odds != 0).nonzero().tolist() == [[0, 5, 5]] and float(g4.prob()[0, 5, 5]) == pytest.approx(0.7)


def test_max_range_cuts_rays_and_drops_their_hit():
    g = _grid(max_range=0.1)
    g.integrate([-0.05, 0.055, 0.055], [[0.085, 0.055, 0.055]], [True])  # 13.5 cm > 10 cm
    p = g.prob()
    assert torch.allclose(p[:5, 5, 5], torch.full((5,), 0.4, dtype=torch.float64))
    assert torch.all(p[5:, 5, 5] == 0.5)


def test_region_around_and_bad_inputs():
    pts = torch.tensor([[0.1, 0.2, 0.0], [0.3, 0.1, 0.2]])
    lo, hi = region_around(pts, 0.05)
    assert torch.allclose(lo, torch.tensor([0.05, 0.05, -0.05], dtype=torch.float64))
    assert torch.allclose(hi, torch.tensor([0.35, 0.25, 0.25], dtype=torch.float64))
    with pytest.raises(ValueError, match="points"):
        region_around(np.zeros((0, 3)), 0.05)
    with pytest.raises(ValueError, match="points"):
        region_around(np.zeros((4, 2)), 0.05)
    with pytest.raises(ValueError, match="margin"):
        region_around(pts, -0.1)
    with pytest.raises(ValueError, match="upper"):
        OccupancyGrid([0, 0, 0], [0.1, 0.0, 0.1])
    with pytest.raises(ValueError, match="lower"):
        OccupancyGrid([0, 0], [0.1, 0.1, 0.1])
    g = _grid()
    with pytest.raises(ValueError, match="origin"):
        g.integrate([0, 0], [[0.01, 0.01, 0.01]], [True])
    with pytest.raises(ValueError, match="endpoints"):
        g.integrate([0, 0, 0], [0.01, 0.01, 0.01], [True])
    with pytest.raises(ValueError, match="endpoints"):
        g.integrate([0, 0, 0], [[float("nan"), 0.01, 0.01]], [True])
    with pytest.raises(ValueError, match="hit"):
        g.integrate([0, 0, 0], [[0.01, 0.01, 0.01]], [1])
    with pytest.raises(ValueError, match="hit"):
        g.integrate([0, 0, 0], [[0.01, 0.01, 0.01]], [True, False])


# ---- expected information gain (Eq. 23) ------------------------------------------------------------------------

def _fan(n=5, spread=0.15):
    """Ray directions ``(n*n, 3)`` around +x."""
    a = torch.linspace(-spread, spread, n, dtype=torch.float64)
    yy, zz = torch.meshgrid(a, a, indexing="ij")
    d = torch.stack([torch.ones_like(yy), yy, zz], -1).reshape(-1, 3)
    return d / d.norm(dim=1, keepdim=True)


def test_ig_unknown_space_beats_space_already_observed_free():
    g = OccupancyGrid([0, 0, 0], [0.2, 0.1, 0.1], OccupancyConfig(resolution=0.01), dtype=torch.float64)
    # observe the lower half (y < 0.05) as free: 6 parallel miss rays along x through every (y, z) cell row
    for y in np.arange(0.005, 0.05, 0.01):
        for z in np.arange(0.005, 0.1, 0.01):
            g.integrate([-0.001, y, z], np.tile([0.2, y, z], (6, 1)), np.zeros(6, bool))
    assert float(g.prob()[:, :5].max()) == pytest.approx(0.12) and bool((g.prob()[:, 5:] == 0.5).all())
    d = torch.tensor([[1.0, 0.0, 0.0], [1.0, 0.0, 0.02], [1.0, 0.0, -0.02]], dtype=torch.float64)
    origins = torch.tensor([[-0.05, 0.025, 0.05], [-0.05, 0.075, 0.05]], dtype=torch.float64)
    gains = expected_information_gain(g, origins, d, 1.0)
    assert float(gains[0]) == pytest.approx(0.0, abs=1e-9)  # only saturated free cells
    cell_gain = LN2 - float(bernoulli_entropy(torch.tensor(_logit(0.4), dtype=torch.float64)))
    assert float(gains[1]) >= 20 * cell_gain - 1e-9  # the central ray alone crosses 20 unknown cells


def test_ig_stops_at_a_known_occupied_wall():
    g = OccupancyGrid([0, 0, 0], [0.2, 0.1, 0.1], OccupancyConfig(resolution=0.01), dtype=torch.float64)
    lmin, lmax = g.config.l_min, g.config.l_max
    g.log_odds[:10] = lmin  # known free in front (x < 0.10)
    g.log_odds[10] = lmax  # a known occupied (saturated) wall at x in [0.10, 0.11); unknown behind it
    origin, dirs = torch.tensor([-0.05, 0.05, 0.05], dtype=torch.float64), _fan(7, 0.2)
    blocked = float(expected_information_gain(g, origin, dirs, 1.0))
    assert blocked == pytest.approx(0.0, abs=1e-9)  # nothing beyond the wall counts
    # without the wall, the same view reaches the unknown region
    open_ = g.clone()
    open_.log_odds[10] = lmin
    assert float(expected_information_gain(open_, origin, dirs, 1.0)) > 10 * (LN2 - 0.673)
    # the unknown region seen from behind the wall
    behind = expected_information_gain(g, torch.tensor([0.25, 0.05, 0.05], dtype=torch.float64), -dirs, 1.0)
    assert float(behind) > 10 * (LN2 - 0.673)
    # with an uncertain front region, the gain is that of the cells up to the wall: whatever lies beyond it
    # (unknown, known free or occupied) gives the same gain
    h = g.clone()
    h.log_odds[:10] = 0.0
    ref = float(expected_information_gain(h, origin, dirs, 1.0))
    assert ref > 0
    for value in (lmin, 1.0, -1.0):
        hh = h.clone()
        hh.log_odds[11:] = value
        assert float(expected_information_gain(hh, origin, dirs, 1.0)) == pytest.approx(ref, rel=1e-12)


def test_ig_is_nonnegative_and_batched_equals_loop():
    torch.manual_seed(0)
    g = OccupancyGrid([0, 0, 0], [0.15, 0.12, 0.1], OccupancyConfig(resolution=0.01), dtype=torch.float64)
    g.log_odds = torch.empty(g.shape, dtype=torch.float64).uniform_(g.config.l_min, g.config.l_max)
    V, R = 6, 40
    origins = torch.randn(V, 3, dtype=torch.float64) * 0.1 + torch.tensor([0.075, 0.06, 0.3], dtype=torch.float64)
    dirs = torch.randn(V, R, 3, dtype=torch.float64) * 0.3 + torch.tensor([0.0, 0.0, -1.0], dtype=torch.float64)
    gains = expected_information_gain(g, origins, dirs, 1.0)
    assert gains.shape == (V,) and bool((gains >= 0).all()) and float(gains.max()) > 0
    loop = torch.stack([expected_information_gain(g, origins[v], dirs[v][None], 1.0)[0] for v in range(V)])
    assert torch.allclose(gains, loop, atol=1e-10)
    chunked = expected_information_gain(g, origins, dirs, 1.0, max_rays_per_chunk=50)
    assert torch.allclose(gains, chunked, atol=1e-10)
    # shared directions (R, 3) broadcast over origins (V, 3)
    shared = expected_information_gain(g, origins, dirs[0], 1.0)
    loop2 = torch.stack([expected_information_gain(g, origins[v], dirs[0], 1.0)[0] for v in range(V)])
    assert torch.allclose(shared, loop2, atol=1e-10)
    # the grid is not modified
    assert torch.equal(g.log_odds, g.clone().log_odds)


def test_ig_counts_each_cell_once_per_view_and_respects_max_range():
    g = _grid()
    origin = torch.tensor([-0.05, 0.055, 0.055], dtype=torch.float64)
    one = expected_information_gain(g, origin, torch.tensor([[1.0, 0.0, 0.0]]), 1.0)
    many = expected_information_gain(g, origin, torch.tensor([[1.0, 0.0, 0.0]]).repeat(20, 1), 1.0)
    cell_gain = LN2 - float(bernoulli_entropy(torch.tensor(_logit(0.4), dtype=torch.float64)))
    assert float(one) == pytest.approx(10 * cell_gain) and float(many) == pytest.approx(float(one))
    short = expected_information_gain(g, origin, torch.tensor([[1.0, 0.0, 0.0]]), 0.085)  # reaches x = 0.035
    assert float(short) == pytest.approx(4 * cell_gain)


def test_ig_bad_inputs():
    g = _grid()
    d = torch.tensor([[1.0, 0.0, 0.0]])
    with pytest.raises(ValueError, match="grid"):
        expected_information_gain(object(), [0, 0, 0], d, 1.0)
    with pytest.raises(ValueError, match="max_range"):
        expected_information_gain(g, [0, 0, 0], d, 0.0)
    with pytest.raises(ValueError, match="origin"):
        expected_information_gain(g, [0, 0], d, 1.0)
    with pytest.raises(ValueError, match="directions"):
        expected_information_gain(g, [0, 0, 0], torch.zeros(1, 3), 1.0)
    with pytest.raises(ValueError, match="directions"):
        expected_information_gain(g, torch.zeros(2, 3), torch.ones(3, 4, 3), 1.0)


@pytest.mark.skipif(not torch.cuda.is_available(), reason="needs CUDA")
def test_cuda_matches_cpu():
    rng = np.random.default_rng(1)
    o = np.array([-0.1, 0.05, 0.15])
    ends, hit = rng.uniform(0.0, 0.1, (500, 3)), rng.random(500) < 0.5
    cpu = _grid(dtype=torch.float32).integrate(o, ends, hit)
    gpu = OccupancyGrid(torch.zeros(3, device="cuda"), torch.full((3,), 0.1, device="cuda"),
                        OccupancyConfig(resolution=0.01)).integrate(o, ends, hit)
    assert gpu.log_odds.is_cuda and torch.allclose(gpu.log_odds.cpu(), cpu.log_odds, atol=1e-5)
    dirs = torch.randn(4, 100, 3)
    a = expected_information_gain(cpu, torch.tensor([0.05, 0.05, 0.3]), dirs, 1.0)
    b = expected_information_gain(gpu, torch.tensor([0.05, 0.05, 0.3]), dirs, 1.0)
    assert b.is_cuda and torch.allclose(a, b.cpu(), rtol=1e-4)


def test_float32_corners_give_the_float64_grid():
    # 0.1f = 0.1000000015: ceil((upper - lower) / res) must not add a cell for the corners' float32 rounding
    # (a CUDA test built its grid from float32 tensors and got 11 cells where the float64 box has 10)
    a = OccupancyGrid(torch.zeros(3), torch.full((3,), 0.1), OccupancyConfig(resolution=0.01))
    b = _grid(n=10, res=0.01)
    assert a.shape == b.shape == (10, 10, 10)
    c = OccupancyGrid([0.0] * 3, [0.1005] * 3, OccupancyConfig(resolution=0.01))  # half a mm more: one more cell
    assert c.shape == (11, 11, 11)

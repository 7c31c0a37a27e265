"""Spatially-aware entropy and expected information gain (touch-only localisation Sec. IV-A/B, Eq. 5-9, Alg. 1,
App. A): activetouch.information.entropy.

The estimator is checked against exact differential entropies (Gaussians: 0.5 log det(2 pi e Sigma);
uniform boxes and disjoint mixtures of equal boxes: log of the covered volume) by rank and slope, not by
absolute value: its offset is a constant that cancels in the information gain.
"""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch
from scipy import stats

from activetouch.information.entropy import (
    DEFAULT_MIN_SIDE,
    SE2_PERIODIC,
    IGResult,
    expected_information_gain,
    expected_weight_entropy,
    expected_weight_entropy_binary,
    log_support_volume,
    se2_scale,
    shared_support,
    spatial_entropy,
    weight_entropy,
)

F64 = torch.float64
ALPHA_TP, ALPHA_FP = 0.5, 0.1  # Eq. 10, App. D e)


def uniform_w(n: int) -> torch.Tensor:
    return torch.full((n,), 1.0 / n, dtype=F64)


def gaussian(n, sigmas, g):
    return torch.randn(n, len(sigmas), generator=g, dtype=F64) * torch.tensor(sigmas, dtype=F64)


def uniform_boxes(n, k, side, d, g, gap=2.0):
    """``n`` samples of an equal mixture of ``k`` disjoint cubes of side ``side``, ``gap * side`` apart in x."""
    comp = torch.randint(0, k, (n,), generator=g)
    centres = torch.zeros(k, d, dtype=F64)
    centres[:, 0] = torch.arange(k, dtype=F64) * side * (1 + gap)
    return centres[comp] + (torch.rand(n, d, generator=g, dtype=F64) - 0.5) * side


def gaussian_exact(sigmas) -> float:
    return sum(0.5 * math.log(2 * math.pi * math.e * s * s) for s in sigmas)


def slope_and_rank(exact, est) -> tuple[float, float]:
    return float(np.polyfit(exact, est, 1)[0]), float(stats.spearmanr(exact, est)[0])


def literal_expected_entropy(w0, p, z):
    """Eq. 7-8 literally, O(P^2): hypothesis j produces z^j; all particles re-weighted from w0."""
    w0 = w0 / w0.sum()
    total = torch.zeros(p.shape[:-1], dtype=p.dtype)
    for j in range(w0.shape[0]):
        lik = torch.where(z[..., j:j + 1], p, 1 - p)
        post = w0 * lik
        post = post / post.sum(-1, keepdim=True)
        h = -(torch.special.xlogy(post, post)).sum(-1)
        total = total + w0[j] * h
    return total


# --------------------------------------------------------------------------------------------- weight entropy

def test_weight_entropy_uniform_and_one_hot():
    for P in (1, 7, 100):
        assert float(weight_entropy(uniform_w(P))) == pytest.approx(math.log(P), abs=1e-12)
    one_hot = torch.zeros(100, dtype=F64)
    one_hot[17] = 1.0
    assert float(weight_entropy(one_hot)) == 0.0
    # normalised inside, batched over leading dims
    w = torch.rand(3, 4, 50, generator=torch.Generator().manual_seed(0), dtype=F64)
    h = weight_entropy(w * 7.5)
    assert h.shape == (3, 4)
    assert torch.allclose(h, weight_entropy(w / w.sum(-1, keepdim=True)))
    assert bool((h > 0).all()) and bool((h < math.log(50)).all())


# ----------------------------------------------------------------------------------------- estimator vs exact

@pytest.mark.parametrize("d", [2, 3])
@pytest.mark.parametrize("n", [100, 300])
def test_spatial_entropy_tracks_gaussian_entropy(d, n):
    """Isotropic and anisotropic Gaussians of 6 widths over 1.5 decades: same ranking as the exact entropy
    and a slope near 1 (scale changes shift H_Omega by exactly d log s; anisotropy changes the neighbours)."""
    widths = np.geomspace(0.01, 0.3, 6)
    for seed in range(3):
        g = torch.Generator().manual_seed(seed)
        for kind in ("iso", "aniso"):
            exact, est = [], []
            for s in widths:
                sig = [s] * d if kind == "iso" else [s] + [0.05] * (d - 1)
                est.append(float(spatial_entropy(gaussian(n, sig, g), uniform_w(n))))
                exact.append(gaussian_exact(sig))
            slope, rank = slope_and_rank(exact, est)
            assert rank == 1.0, (kind, seed, est)
            assert 0.85 < slope < 1.15, (kind, seed, slope)
            # a constant offset below the exact entropy (documented: ~0.7 nats in 2-D, ~1.2 in 3-D)
            bias = np.array(est) - np.array(exact)
            assert -2.0 < bias.mean() < 0.0 and bias.std() < 0.3, (kind, seed, bias)


@pytest.mark.parametrize("d", [2, 3])
def test_spatial_entropy_tracks_uniform_mixtures(d):
    """Single boxes of 6 sides and equal mixtures of 1, 2, 4, 8 disjoint boxes (exact: log covered volume)."""
    n = 400
    for seed in range(3):
        g = torch.Generator().manual_seed(10 + seed)
        exact = [d * math.log(s) for s in np.geomspace(0.02, 0.5, 6)]
        est = [float(spatial_entropy(uniform_boxes(n, 1, math.exp(e / d), d, g), uniform_w(n))) for e in exact]
        slope, rank = slope_and_rank(exact, est)
        assert rank == 1.0 and 0.9 < slope < 1.1, (seed, slope, est)

        ks = (1, 2, 4, 8)
        exact = [math.log(k * 0.1 ** d) for k in ks]
        est = [float(spatial_entropy(uniform_boxes(n, k, 0.1, d, g), uniform_w(n))) for k in ks]
        slope, rank = slope_and_rank(exact, est)
        assert rank == 1.0 and 0.85 < slope < 1.2, (seed, slope, est)


def test_spatial_entropy_ignores_gap_between_modes():
    """Two disjoint boxes moved apart: the exact entropy (log 2 V) stays put and so does the estimator
    (local neighbourhoods), while a Gaussian fit of the same particles grows by ~3 nats."""
    g = torch.Generator().manual_seed(3)
    n, d = 300, 2
    est, fit = [], []
    for gap in (0.5, 2.0, 8.0, 32.0):
        x = uniform_boxes(n, 2, 0.1, d, g, gap)
        est.append(float(spatial_entropy(x, uniform_w(n))))
        fit.append(0.5 * float(torch.logdet(2 * math.pi * math.e * torch.cov(x.T))))
    assert max(est) - min(est) < 0.3, est
    assert fit[-1] - fit[0] > 2.0, fit


def test_spatial_entropy_separates_spread_from_clustered():
    """Equal weights: H_w cannot tell a spread set from a clustered one; H_Omega can (by ~d log 10)."""
    g = torch.Generator().manual_seed(4)
    P = 100
    spread = gaussian(P, [0.06, 0.06, 0.5], g)
    clustered = 0.1 * spread
    w = uniform_w(P)
    assert float(weight_entropy(w)) == float(weight_entropy(w))
    h_spread = float(spatial_entropy(spread, w, periodic=SE2_PERIODIC, scale=se2_scale(0.1)))
    h_clust = float(spatial_entropy(clustered, w, periodic=SE2_PERIODIC, scale=se2_scale(0.1)))
    assert h_spread - h_clust > 0.8 * 3 * math.log(10), (h_spread, h_clust)


# -------------------------------------------------------------------------------------- shared support itself

def test_shared_support_equivariance_and_batching():
    g = torch.Generator().manual_seed(5)
    x = gaussian(60, [0.05, 0.02, 0.3], g)
    sides = shared_support(x)
    assert sides.shape == (3,) and bool((sides > DEFAULT_MIN_SIDE).all())
    # translation invariant, scale equivariant, a uniform metric scale changes nothing
    shift = torch.tensor([0.5, -0.3, 0.1], dtype=F64)
    assert torch.allclose(shared_support(x + shift), sides, rtol=1e-9)
    assert torch.allclose(shared_support(3.0 * x), 3.0 * sides, rtol=1e-9)
    assert torch.allclose(shared_support(x, scale=(2.0, 2.0, 2.0)), sides, rtol=1e-9)
    # log volume = sum of log sides; batching over leading dims equals a loop
    assert float(log_support_volume(x)) == pytest.approx(float(sides.log().sum()), rel=1e-12)
    xb = gaussian(2 * 3 * 60, [0.05, 0.02, 0.3], g).reshape(2, 3, 60, 3)
    sb = shared_support(xb, periodic=SE2_PERIODIC, scale=se2_scale(0.1))
    assert sb.shape == (2, 3, 3)
    for i in range(2):
        for j in range(3):
            assert torch.allclose(sb[i, j], shared_support(xb[i, j], periodic=SE2_PERIODIC, scale=se2_scale(0.1)))


def test_shared_support_float32_tight_belief_far_from_origin():
    """A 1 mm / 0.6 deg belief 0.6 m from the origin: float32 picks the same neighbours as float64."""
    g = torch.Generator().manual_seed(12)
    x = torch.tensor([0.5, -0.4, 2.0], dtype=F64) + gaussian(100, [1e-3, 1e-3, 1e-2], g)
    kw = dict(periodic=SE2_PERIODIC, scale=se2_scale(0.1))
    s64, s32 = shared_support(x, **kw), shared_support(x.float(), **kw)
    assert s32.dtype == torch.float32
    assert torch.allclose(s32.double(), s64, rtol=1e-3)


def test_shared_support_wraps_yaw():
    """A yaw cluster straddling +-pi has the support of the same cluster around 0 (not a 2 pi wide box)."""
    g = torch.Generator().manual_seed(6)
    x = gaussian(100, [0.03, 0.03, 0.1], g)
    seam = x.clone()
    seam[:, 2] = torch.remainder(seam[:, 2], 2 * math.pi) - math.pi  # shifted by pi: now near +-pi
    assert float(seam[:, 2].abs().min()) > 2.5
    kw = dict(periodic=SE2_PERIODIC, scale=se2_scale(0.1))
    assert torch.allclose(shared_support(seam, **kw), shared_support(x, **kw), rtol=1e-6)
    assert float(shared_support(seam, **kw)[2]) < 0.2
    # three particles on either side of the seam: each one's 5 neighbours include the other side, which is
    # <= 0.06 rad away wrapped but ~2 pi away unwrapped
    yaw = torch.tensor([math.pi - 0.01 * k for k in range(1, 4)] + [-math.pi + 0.01 * k for k in range(1, 4)],
                       dtype=F64)
    few = torch.stack([torch.zeros(6, dtype=F64), torch.zeros(6, dtype=F64), yaw], -1)
    assert float(shared_support(few, **kw)[2]) < 0.1
    assert float(shared_support(few, scale=se2_scale(0.1))[2]) > 1.0


def test_shared_support_scale_changes_neighbours_only():
    """Yaw scale picks different neighbours (a different support) but the result stays in rad, and a huge
    yaw scale makes neighbours nearest in yaw, so the yaw side shrinks."""
    g = torch.Generator().manual_seed(7)
    x = gaussian(100, [0.05, 0.05, 0.5], g)
    small = shared_support(x, periodic=SE2_PERIODIC, scale=(1.0, 1.0, 1e-3))
    large = shared_support(x, periodic=SE2_PERIODIC, scale=(1.0, 1.0, 1e3))
    assert float(large[2]) < 0.5 * float(small[2])
    assert float(large[0]) > float(small[0])


def test_shared_support_floor_against_collapse():
    """Identical particles (resampling duplicates) or a collapsed dimension stay finite: sides >= min_side."""
    x = torch.tensor([[0.4, 0.1, 0.2]], dtype=F64).expand(50, 3)
    assert torch.equal(shared_support(x), torch.full((3,), DEFAULT_MIN_SIDE, dtype=F64))
    assert float(log_support_volume(x)) == pytest.approx(3 * math.log(DEFAULT_MIN_SIDE))
    g = torch.Generator().manual_seed(8)
    flat = gaussian(50, [0.05, 0.05, 0.0], g)
    sides = shared_support(flat, min_side=(1e-4, 1e-4, 1e-3))
    assert float(sides[2]) == pytest.approx(1e-3) and float(sides[0]) > 1e-3
    h = spatial_entropy(x.float(), torch.ones(50))
    assert bool(torch.isfinite(h))


# --------------------------------------------------------------------------------- expected weight entropy

def test_binary_expected_entropy_equals_literal_formula():
    g = torch.Generator().manual_seed(9)
    P = 40
    w0 = torch.rand(P, generator=g, dtype=F64) + 0.05
    p = ALPHA_FP + (ALPHA_TP - ALPHA_FP) * torch.rand(3, 5, P, generator=g, dtype=F64)
    z = torch.rand(3, 5, P, generator=g) < 0.4
    z[0, 0] = False  # all hypotheses agree (no contact)
    z[0, 1] = True
    fast = expected_weight_entropy_binary(w0, p, z)
    assert fast.shape == (3, 5)
    assert torch.allclose(fast, literal_expected_entropy(w0, p, z), rtol=1e-10, atol=1e-12)
    # general form with Z = P hypotheses weighted by w0 (Eq. 7 as written)
    lik = torch.where(z[..., :, None], p[..., None, :], 1 - p[..., None, :])  # (3, 5, Z=P, P)
    general = expected_weight_entropy(w0, lik, (w0 / w0.sum()).expand(3, 5, P))
    assert torch.allclose(general, fast, rtol=1e-10, atol=1e-12)


def test_half_split_gains_log_2_and_no_touch_gains_nothing():
    P, C, T = 100, 1, 1
    w0 = uniform_w(P)
    x0 = gaussian(P, [0.06, 0.06, 0.5], torch.Generator().manual_seed(10))
    x_traj = x0.expand(C, T, P, 3)
    z = torch.zeros(C, T, P, dtype=torch.bool)
    z[..., : P // 2] = True
    # a near-perfect sensor that splits the particles in half: one bit
    p = torch.where(z, 1 - 1e-9, 1e-9).to(F64)
    r = expected_information_gain(w0, x0, x_traj, p, z)
    assert float(r.weight_term[0, 0]) == pytest.approx(math.log(2), abs=1e-6)
    assert float(r.spatial_term[0, 0]) == 0.0
    # the paper's noisy sensor (alpha_tp = 0.5, alpha_fp = 0.1) gains less, but something
    p = torch.where(z, ALPHA_TP, ALPHA_FP).to(F64)
    r = expected_information_gain(w0, x0, x_traj, p, z)
    assert 0.05 < float(r.weight_term[0, 0]) < math.log(2) - 0.1
    # a trajectory touching no particle's region: p = alpha_fp everywhere, every hypothesis says no contact
    p = torch.full((C, T, P), ALPHA_FP, dtype=F64)
    r = expected_information_gain(w0, x0, x_traj, p, torch.zeros(C, T, P, dtype=torch.bool))
    assert abs(float(r.weight_term[0, 0])) < 1e-12 and float(r.gain[0]) == pytest.approx(0.0, abs=1e-12)


def setup_candidates(C=4, T=6, P=100, seed=11):
    g = torch.Generator().manual_seed(seed)
    x0 = gaussian(P, [0.06, 0.06, 0.5], g)
    w0 = torch.rand(P, generator=g, dtype=F64) + 0.1
    drift = 0.01 * torch.randn(C, T, P, 3, generator=g, dtype=F64)
    x_traj = x0 + drift.cumsum(1)
    p = ALPHA_FP + (ALPHA_TP - ALPHA_FP) * torch.rand(C, T, P, generator=g, dtype=F64)
    z = torch.rand(C, T, P, generator=g) < 0.3
    return w0, x0, x_traj, p, z


KW = dict(periodic=SE2_PERIODIC, scale=se2_scale(0.1))


def test_information_gain_terms_and_t_star():
    w0, x0, x_traj, p, z = setup_candidates()
    C, T, P = p.shape
    # candidate 0: the particles contract most after step 3 and the only informative observation is at step 5
    x_traj[0] = x0
    x_traj[0, 1] = x0 * torch.tensor([0.7, 0.7, 1.0], dtype=F64)
    x_traj[0, 2] = x0 * torch.tensor([0.3, 0.3, 1.0], dtype=F64)
    x_traj[0, 3:] = x0 * torch.tensor([0.9, 0.9, 1.0], dtype=F64)
    p[0], z[0] = ALPHA_FP, False
    z[0, 4, : P // 2] = True
    p[0, 4, : P // 2] = ALPHA_TP
    r = expected_information_gain(w0, x0, x_traj, p, z, **KW)
    assert isinstance(r, IGResult)
    assert r.gain.shape == (C,) and r.t_star.shape == (C,) and r.t_star.dtype == torch.long
    assert r.per_step.shape == r.weight_term.shape == r.spatial_term.shape == (C, T)
    assert torch.allclose(r.per_step, r.weight_term + r.spatial_term)
    assert torch.equal(r.gain, r.per_step.max(-1).values)
    assert torch.equal(r.t_star, r.per_step.argmax(-1) + 1)
    assert bool(((r.t_star >= 1) & (r.t_star <= T)).all())
    # candidate 0 in detail: weight term only at step 5, spatial term largest at step 3 (2 log(1/0.3))
    wt, st = r.weight_term[0], r.spatial_term[0]
    assert float(wt[[0, 1, 2, 3, 5]].abs().max()) < 1e-12 and float(wt[4]) > 0.05
    assert float(st[0]) == 0.0
    assert float(st[2]) == pytest.approx(2 * math.log(1 / 0.3), rel=0.05)
    assert int(r.t_star[0]) == 3
    # each term agrees with the standalone functions
    h0 = float(log_support_volume(x0, **KW))
    assert torch.allclose(r.spatial_term, h0 - log_support_volume(x_traj, **KW), atol=1e-12)
    assert torch.allclose(r.weight_term, weight_entropy(w0) - expected_weight_entropy_binary(w0, p, z))


def test_information_gain_batched_equals_loop():
    w0, x0, x_traj, p, z = setup_candidates(C=5, T=4)
    x_traj[2, 1:3] = x_traj[2, 0]  # static steps take the carried-forward path
    x_traj[3, 0] = x0
    r = expected_information_gain(w0, x0, x_traj, p, z, **KW)
    for c in range(5):
        rc = expected_information_gain(w0, x0, x_traj[c:c + 1], p[c:c + 1], z[c:c + 1], **KW)
        for a, b in zip(r, rc):
            assert torch.allclose(a[c:c + 1], b, rtol=1e-10, atol=1e-12)
    assert float(r.spatial_term[3, 0]) == 0.0
    assert float(r.spatial_term[2, 1]) == float(r.spatial_term[2, 0]) == float(r.spatial_term[2, 2])


# ---------------------------------------------------------------------------------------------- bad input

def test_bad_input_raises_value_error():
    w0, x0, x_traj, p, z = setup_candidates(C=2, T=3, P=20)
    nan_x = x0.clone()
    nan_x[3, 1] = float("nan")
    nan_traj = x_traj.clone()
    nan_traj[1, 2, 0, 0] = float("nan")
    cases = [
        (lambda: shared_support(nan_x), "NaN"),
        (lambda: spatial_entropy(nan_x, w0), "NaN"),
        (lambda: expected_information_gain(w0, x0, nan_traj, p, z), "NaN"),
        (lambda: expected_information_gain(w0, nan_x, x_traj, p, z), "NaN"),
        (lambda: shared_support(x0, rho=20), "rho"),
        (lambda: shared_support(x0, rho=0), "rho"),
        (lambda: expected_information_gain(w0, x0, x_traj, p, z, rho=25), "rho"),
        (lambda: shared_support(x0[:0]), "P > 0"),
        (lambda: weight_entropy(torch.tensor([0.5, -0.1, 0.6])), "non-negative"),
        (lambda: weight_entropy(torch.zeros(10)), "no mass"),
        (lambda: weight_entropy(torch.tensor([[1.0, 0.0], [0.0, 0.0]])), "no mass"),
        (lambda: weight_entropy(torch.tensor([0.5, float("nan")])), "NaN"),
        (lambda: weight_entropy(torch.zeros(0)), "P > 0"),
        (lambda: expected_information_gain(torch.zeros(20), x0, x_traj, p, z), "no mass"),
        (lambda: expected_information_gain(-w0, x0, x_traj, p, z), "non-negative"),
        (lambda: spatial_entropy(x0, torch.ones(19)), "P = 20"),
        (lambda: expected_information_gain(w0, x0, x_traj, p, z.double()), "bool"),
        (lambda: expected_information_gain(w0, x0, x_traj, p * 3, z), r"\[0, 1\]"),
        (lambda: expected_information_gain(w0, x0, x_traj[:, :, :10], p, z), "x_traj"),
        (lambda: expected_information_gain(w0, x0, x_traj[:, :0], p[:, :0], z[:, :0]), "C, T > 0"),
        (lambda: expected_information_gain(w0, x0, x_traj, p[:, :2], z[:, :2]), "p_contact"),
        (lambda: shared_support(x0, periodic=(False, True)), "periodic"),
        (lambda: shared_support(x0, scale=(1.0, -1.0, 1.0)), "scale"),
        (lambda: shared_support(x0, min_side=0.0), "min_side"),
        (lambda: expected_weight_entropy_binary(w0, torch.zeros(20, dtype=F64), torch.ones(20, dtype=torch.bool)),
         "zero likelihood"),
        (lambda: expected_weight_entropy(w0, torch.ones(3, 20), torch.ones(4)), "p_z"),
        (lambda: expected_weight_entropy(w0, torch.zeros(2, 20), torch.ones(2)), "zero likelihood"),
        (lambda: se2_scale(0.0), "se2_scale"),
    ]
    for fn, msg in cases:
        with pytest.raises(ValueError, match=msg):
            fn()

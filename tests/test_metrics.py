"""Tests of activetouch.experiments.metrics: nll (RUMI Eq. 36), APC (Eq. 33), TIQF errors and ADI, Wilson."""
from __future__ import annotations

import math

import pytest
import torch

from activetouch import objects
from activetouch.experiments import metrics
from activetouch.geometry import make_pose, pose_from_xyz_yaw
from activetouch.observations import SemanticSensorModel


@pytest.fixture(scope="module")
def mug():
    return objects.load("mug")


@pytest.fixture(scope="module")
def T_true():
    return pose_from_xyz_yaw(torch.tensor([0.8, 0.1, 0.0]), torch.tensor(0.4))


def _around(T, n, sigma_t, sigma_yaw, seed=0):
    g = torch.Generator().manual_seed(seed)
    xyz = T[:3, 3] + torch.randn(n, 3, generator=g) * sigma_t * torch.tensor([1.0, 1.0, 0.0])
    yaw = math.atan2(float(T[1, 0]), float(T[0, 0])) + torch.randn(n, generator=g) * sigma_yaw
    return pose_from_xyz_yaw(xyz, yaw)


def test_nll_small_for_a_belief_on_the_truth_and_large_for_a_wrong_one(mug, T_true):
    w = torch.full((20,), 1 / 20)
    good = metrics.nll(mug, T_true[None].repeat(20, 1, 1), w, T_true)
    assert 0.0 <= good < 2.0  # every surface sample is within the sensor's 3 mm surface band
    near = metrics.nll(mug, _around(T_true, 20, 0.001, 0.01), w, T_true)
    wrong = metrics.nll(mug, _around(T_true, 20, 0.001, 0.01) @ pose_from_xyz_yaw(
        torch.tensor([0.03, 0.0, 0.0]), torch.tensor(0.0)), w, T_true)
    assert near < 20.0 < 200.0 < wrong  # Table III mug threshold between them
    # weights matter: most weight on a wrong particle raises the nll
    poses = torch.stack([T_true, pose_from_xyz_yaw(T_true[:3, 3] + torch.tensor([0.03, 0, 0]), torch.tensor(0.4))])
    a = metrics.nll(mug, poses, torch.tensor([0.9, 0.1]), T_true)
    b = metrics.nll(mug, poses, torch.tensor([0.1, 0.9]), T_true)
    assert a < 500 * -math.log(0.9) + 2.0 and b > a + 300
    # finite even when every particle is far away (log-space evaluation)
    far = metrics.nll(mug, T_true[None] @ pose_from_xyz_yaw(torch.tensor([5.0, 0, 0]), torch.tensor(0.0))[None],
                      torch.ones(1), T_true)
    assert math.isfinite(far) and far > 1e5
    # same seed, same value; the sensor model's zeta widens the surface band
    assert metrics.nll(mug, _around(T_true, 20, 0.002, 0.02), w, T_true) == \
        metrics.nll(mug, _around(T_true, 20, 0.002, 0.02), w, T_true)
    wide = metrics.nll(mug, _around(T_true, 20, 0.002, 0.02), w, T_true, sensor=SemanticSensorModel(zeta=0.02))
    assert wide < metrics.nll(mug, _around(T_true, 20, 0.002, 0.02), w, T_true)


def test_nll_rejects_bad_input(mug, T_true):
    with pytest.raises(ValueError, match="weights"):
        metrics.nll(mug, T_true[None].repeat(2, 1, 1), torch.tensor([1.0, float("nan")]), T_true)
    with pytest.raises(ValueError, match="NaN or inf"):
        metrics.nll(mug, torch.full((2, 4, 4), float("nan")), torch.ones(2), T_true)


def test_apc_is_zero_for_identical_particles_and_grows_with_spread(mug, T_true):
    same = T_true[None].repeat(5, 1, 1)
    assert metrics.apc(mug, same, n=200, exact=True) < 1e-5  # exact SDF: surface samples have sdf ~ 0
    assert metrics.apc(mug, same, n=200) < 5e-4  # voxel cache: its interpolation error only
    a = metrics.apc(mug, _around(T_true, 10, 0.002, 0.0), n=200)
    b = metrics.apc(mug, _around(T_true, 10, 0.010, 0.0), n=200)
    assert 5e-4 < a < b < 0.02
    # a pure 1 cm x shift between two particles: APC is about the mean |sdf| of the shifted surface
    two = torch.stack([T_true, pose_from_xyz_yaw(T_true[:3, 3] + torch.tensor([0.01, 0, 0]), torch.tensor(0.4))])
    val = metrics.apc(mug, two, n=300)
    assert 0.001 < val < 0.005  # 2 of the 4 pairs are offset by at most 10 mm


def test_translation_and_rotation_errors():
    T = pose_from_xyz_yaw(torch.tensor([0.1, 0.2, 0.3]), torch.tensor(0.25))
    U = pose_from_xyz_yaw(torch.tensor([0.1, 0.23, 0.34]), torch.tensor(0.25 + 0.3))
    assert float(metrics.translation_error(U, T)) == pytest.approx(0.05, abs=1e-6)
    assert float(metrics.rotation_error(U, T)) == pytest.approx(0.3, abs=1e-6)
    assert float(metrics.rotation_error(T, U)) == pytest.approx(0.3, abs=1e-6)
    assert float(metrics.rotation_error(T, T)) == pytest.approx(0.0, abs=1e-6)
    # a known rotation about an arbitrary axis, and near pi
    from activetouch.geometry import axis_angle_to_matrix

    axis = torch.tensor([1.0, -2.0, 0.5])
    axis = axis / axis.norm()
    for angle in (1e-4, 0.7, 2.0, math.pi - 1e-3):
        R = axis_angle_to_matrix(axis.double() * angle).float()
        A = make_pose(R, torch.zeros(3)) @ T
        assert float(metrics.rotation_error(A, T)) == pytest.approx(angle, abs=2e-4)
    batch = metrics.rotation_error(torch.stack([T, U]), T)
    assert batch.shape == (2,)


def test_adi(mug, T_true):
    assert metrics.adi(mug, T_true, T_true, n=500) == pytest.approx(0.0, abs=1e-7)
    shifted = pose_from_xyz_yaw(T_true[:3, 3] + torch.tensor([0.0, 0.01, 0.0]), torch.tensor(0.4))
    d = metrics.adi(mug, shifted, T_true, n=500)
    assert 0.002 < d <= 0.0101  # never more than the shift; less where surfaces slide along themselves
    # a larger shift gives a larger ADI
    big = pose_from_xyz_yaw(T_true[:3, 3] + torch.tensor([0.05, 0.0, 0.0]), torch.tensor(0.4))
    assert metrics.adi(mug, big, T_true, n=500) > d


def test_active_share():
    w = torch.tensor([0.5, 0.49995, 0.00005, 0.0])
    assert metrics.active_share(w) == 0.5
    assert metrics.active_share(torch.full((10,), 0.1)) == 1.0
    assert metrics.active_share(torch.tensor([2.0, 2.0])) == 1.0  # normalised first
    with pytest.raises(ValueError):
        metrics.active_share(torch.tensor([0.0, 0.0]))


def test_wilson_interval_known_values():
    lo, hi = metrics.wilson_interval(9, 10)
    assert lo == pytest.approx(0.5958, abs=1e-4) and hi == pytest.approx(0.9821, abs=1e-4)
    lo, hi = metrics.wilson_interval(0, 10)
    assert lo == 0.0 and hi == pytest.approx(0.2775, abs=1e-4)
    lo, hi = metrics.wilson_interval(10, 10)
    assert hi == 1.0 and lo == pytest.approx(0.7225, abs=1e-4)
    lo, hi = metrics.wilson_interval(5, 10)
    assert lo == pytest.approx(0.2366, abs=1e-4) and hi == pytest.approx(0.7634, abs=1e-4)
    for bad in ((11, 10), (-1, 10), (0, 0)):
        with pytest.raises(ValueError):
            metrics.wilson_interval(*bad)

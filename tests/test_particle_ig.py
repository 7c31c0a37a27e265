"""The mixed planner rumi-touch-ig (planning.particle_ig): the touch paper's expected IG over RUMI's particles."""
from __future__ import annotations

import math
from types import SimpleNamespace

import numpy as np
import pytest
import torch

from activetouch import objects
from activetouch.geometry import pose_from_xyz_yaw
from activetouch.planning.particle_ig import ParticleIGConfig, ParticleIGPlanner
from activetouch.sim.robot import gripper_points

EE = np.array([0.36, 0.0, 0.02, 0.0])


@pytest.fixture(scope="module")
def mug():
    return objects.load("mug")


def _planner(mug, seed=0, **cfg):
    h, _ = gripper_points(0.02)
    return ParticleIGPlanner(mug, h, action_space="planar", config=ParticleIGConfig(**cfg), seed=seed)


def _belief(yaws, xy=(0.5, 0.0)):
    n = len(yaws)
    t = torch.tensor([[xy[0], xy[1], 0.0]] * n, dtype=torch.float64)
    return SimpleNamespace(poses=pose_from_xyz_yaw(t, torch.as_tensor(yaws, dtype=torch.float64)),
                           weights=torch.full((n,), 1.0 / n, dtype=torch.float64))


def test_a_belief_with_nothing_to_learn_has_zero_gain(mug):
    """All particles the same pose: every hypothetical contact re-weighs them equally, so Alg. 1's gain is 0."""
    pl = _planner(mug)
    pl.next_action(_belief([0.3] * 30), EE, False)
    assert torch.allclose(pl.last["gains"], torch.zeros_like(pl.last["gains"]), atol=1e-9)


def test_a_spread_belief_gets_an_informative_move_toward_the_particles(mug):
    yaws = np.linspace(-math.pi, math.pi, 40, endpoint=False)  # where is the handle?
    pl = _planner(mug, seed=3)
    u, timing = pl.next_action(_belief(yaws), EE, False)
    gains = pl.last["gains"]
    assert float(gains.max()) > 0.05 and pl.last["gain"] == float(gains.max())
    assert u.shape == (3,) and float(np.abs(u).max()) <= 1.0 and u[0] > 0  # toward the mug, ahead of the gripper
    assert timing["replanned"] == 1.0 and timing["ig_s"] > 0
    u2, _ = _planner(mug, seed=3).next_action(_belief(yaws), EE, False)
    np.testing.assert_array_equal(u, u2)  # same seed, same move


def test_moves_are_at_most_one_unit_and_planar_moves_keep_the_height(mug):
    pl = _planner(mug, seed=1)
    b = _belief(np.linspace(0, 2 * math.pi, 20, endpoint=False), xy=(0.9, 0.4))  # far away
    moves = pl.candidates(b.poses.float(), b.weights.float(), torch.as_tensor(EE, dtype=torch.float32))
    assert moves.shape == (20, 3)
    assert float(moves.norm(dim=-1).max()) <= 0.08 + 1e-6 and float(moves[:, 2].abs().max()) == 0.0


@pytest.mark.parametrize("bad", [{"num_candidates": 0}, {"waypoints": 1.5}, {"contact_tol": -1.0},
                                 {"gripper_spacing": 0.0}])
def test_bad_settings_are_named(bad):
    with pytest.raises(ValueError, match=next(iter(bad))):
        ParticleIGConfig(**bad)
    with pytest.raises(ValueError, match="unknown ParticleIGConfig fields"):
        ParticleIGConfig().with_overrides(horizon_typo=3)

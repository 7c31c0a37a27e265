"""The touch paper's controller: spline candidates (App. C), the robot-point cull, the sparse distance, the grasp
decision (App. D-d, e) and Alg. 1's selection, on the real grasp-box scene."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from activetouch.planning.splines import spline_waypoints, via_point_spline


def test_spline_passes_via_points_with_zero_end_velocity():
    u0 = np.array([0.3, 0.0, 0.3, 0.0])
    via = np.array([[0.4, 0.1, 0.1, 0.5], [0.45, 0.05, 0.05, 0.6]])
    sp = via_point_spline(u0, via)
    assert np.allclose(sp(0.0), u0) and np.allclose(sp(0.5), via[0]) and np.allclose(sp(1.0), via[1])
    d = sp.derivative()
    assert np.abs(d(0.0)).max() < 1e-12 and np.abs(d(1.0)).max() < 1e-12
    assert np.abs(d(0.5)).max() > 0.05  # it does move in between
    w = spline_waypoints(u0, via, 8)
    assert w.shape == (8, 4) and np.allclose(w[-1], via[-1]) and np.allclose(w[3], via[0])


@pytest.mark.parametrize("u0,via,n", [([0, 0, 0, 0], [[1, 1, 1]], 4), ([0, 0, 0, 0], [[np.nan, 0, 0, 0]], 4),
                                      ([0, 0, 0, 0], [[1, 0, 0, 0]], 0)])
def test_spline_bad_input(u0, via, n):
    with pytest.raises(ValueError):
        spline_waypoints(u0, via, n)


@pytest.fixture(scope="module")
def env():
    from activetouch.sim.grasp_env import make_grasp_env

    e = make_grasp_env("grasp-box-0", seed=3)
    e.reset(seed=3)
    yield e
    e.close()


def _belief_at(env, states, weights=None):
    from activetouch.belief.touch_filter import TouchBelief

    return TouchBelief(env.object, torch.as_tensor(states, dtype=torch.float64), weights)


def test_sparse_distance_equals_dense_below_the_padding(env):
    """The pair-culled distance (far_inf) is the dense lookup's wherever the dense one is below the padding."""
    from activetouch.belief.contact_model import signed_robot_object_distance

    true = env.true_state()
    g = torch.Generator().manual_seed(0)
    states = torch.as_tensor(true) + torch.randn(40, 3, generator=g, dtype=torch.float64) * torch.tensor([0.05, 0.05, 0.5])
    plan = env.plan_poke(np.array([[true[0] - 0.15, true[1], 0.08, 0.0], [true[0], true[1], 0.08, 0.0]]))
    pts = env.robot_points(plan.q[1:]).double()
    sparse = signed_robot_object_distance(env.object, states, pts, far_inf=True)
    dense = signed_robot_object_distance(env.object, states, pts, far_inf=False)
    near = dense < 0.015
    assert near.sum() > 10 and (~near).sum() > 10  # both kinds of pair occur
    assert torch.allclose(sparse[near], dense[near], atol=1e-5)
    assert (sparse[~near] > 0.0149).all()  # far pairs: +inf or beyond the padding, never a false contact


def test_point_cull_keeps_every_near_point(env):
    from activetouch.belief.contact_model import robot_object_distance
    from activetouch.planning.touch_ig import near_robot_points

    true = env.true_state()
    states = torch.as_tensor(np.stack([true, true + [0.05, -0.03, 0.3]]), dtype=torch.float64)
    plan = env.plan_poke(np.array([[true[0] - 0.12, true[1], 0.06, 0.0], [true[0] + 0.02, true[1], 0.06, 0.0]]))
    pts = env.robot_points(plan.q[1:]).double()
    kept = near_robot_points(env.object, pts, states)
    assert kept.shape[1] < 0.5 * pts.shape[1]  # most of the arm is culled
    full = robot_object_distance(env.object, states, pts)
    cull = robot_object_distance(env.object, states, kept)
    fin = torch.isfinite(full) & (full < 0.015)
    assert fin.any() and torch.allclose(full[fin], cull[fin])


def test_concentrated_belief_grasps_and_a_spread_one_pokes(env):
    from activetouch.planning.touch_ig import TouchIGPlanner, TouchPlannerConfig
    from activetouch.sim.grasp_env import GraspAction, PokeAction

    planner = TouchIGPlanner(env, None, TouchPlannerConfig(num_samples=4, waypoints=6), seed=0)
    true = env.true_state()
    g = torch.Generator().manual_seed(1)
    tight = torch.as_tensor(true) + torch.randn(20, 3, generator=g, dtype=torch.float64) * torch.tensor([0.002, 0.002, 0.01])
    p, best = planner.grasp_probability(_belief_at(env, tight))
    assert p >= 0.8
    a, timings = planner.next_action(_belief_at(env, tight), env.ee_state(), False)
    assert isinstance(a, GraspAction) and np.allclose(a.state, best)
    spread = torch.as_tensor(true) + torch.randn(30, 3, generator=g, dtype=torch.float64) * torch.tensor([0.06, 0.06, 0.5])
    planner.reset()
    a, timings = planner.next_action(_belief_at(env, spread), env.ee_state(), False)
    assert isinstance(a, PokeAction)
    assert 1 <= len(a.waypoints) <= 6 and np.isfinite(a.waypoints).all()
    last = planner.last
    assert last["t_star"] == len(a.waypoints) and math.isfinite(last["gain"])
    assert env.reachable(a.waypoints[-1:, :3]).all() or len(a.waypoints) < 6


def test_selection_follows_the_criterion(env):
    """IG picks the candidate of largest expected gain; MaxContact the one touching most particles."""
    from activetouch.planning.touch_ig import TouchIGPlanner, TouchPlannerConfig

    true = env.true_state()
    g = torch.Generator().manual_seed(2)
    spread = torch.as_tensor(true) + torch.randn(30, 3, generator=g, dtype=torch.float64) * torch.tensor([0.06, 0.06, 0.5])
    belief = _belief_at(env, spread)
    for criterion in ("ig", "max-contact"):
        planner = TouchIGPlanner(env, None, TouchPlannerConfig(num_samples=4, waypoints=6, criterion=criterion,
                                                               predict="static"), seed=5)
        cands = planner.sample_candidates(belief, env.ee_state())
        planner.reset()  # same rng: the call below draws the same candidates
        planner.next_action(belief, env.ee_state(), False)
        assert all(np.allclose(a, b) for a, b in zip(cands, planner.last["candidates"]))
        ev = planner._evaluate(belief, [env.plan_poke(c) for c in cands])
        if criterion == "max-contact":
            counts = [int(z.any(0).sum()) for z in ev["z"]]
            assert counts[planner.last["chosen"]] == max(counts)
        else:
            from activetouch.information import entropy

            res = entropy.expected_information_gain(belief.weights.double(), belief.states.double(),
                                                    torch.stack(ev["x"]), torch.stack(ev["p"]), torch.stack(ev["z"]),
                                                    scale=planner.se2_scale,
                                                    periodic=entropy.SE2_PERIODIC)
            assert planner.last["chosen"] == int(torch.argmax(res.gain))
            assert planner.last["t_star"] == int(res.t_star[planner.last["chosen"]])


def test_planner_config_errors():
    from activetouch.planning.touch_ig import TouchPlannerConfig

    for bad in ({"num_samples": 0}, {"grasp_threshold": 1.5}, {"predict": "magic"}, {"criterion": "x"},
                {"approach_distance": float("nan")}):
        with pytest.raises(ValueError):
            TouchPlannerConfig(**bad)

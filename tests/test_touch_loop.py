"""The touch belief in the one episode loop, driven by scripted pokes (properties that hold on any machine)."""
from __future__ import annotations

import math

import numpy as np
import pytest
import torch

from activetouch.experiments.records import read_steps
from activetouch.experiments.runner import EpisodeConfig, run_episode


def _truth(task: str, seed: int):
    from activetouch.sim.grasp_env import make_grasp_env

    env = make_grasp_env(task, seed=seed)
    _, info = env.reset(seed=seed)
    env.close()
    return np.asarray(info["true_state"]), np.asarray(info["prior_means"])


def _side_poke(state, height: float = 0.08) -> list[list[float]]:
    """A poke from 15 cm on the robot's side of the box straight at its centre, at ``height``."""
    x, y, _ = state
    d = np.array([x + 0.25, y])  # from the robot base (-0.25, 0) towards the box
    d /= np.linalg.norm(d)
    start = np.array([x, y]) - 0.15 * d
    return [[*start, 0.15, 0.0], [*start, height, 0.0], [x, y, height, 0.0]]


def _mass_near(states, weights, truth, radius=0.03):
    near = np.hypot(states[:, 0] - truth[0], states[:, 1] - truth[1]) < radius
    return float(weights[near].sum())


def _explaining_mass(est, states, weights, tol=0.015) -> float:
    """Weighted share of particles whose object lies within ``tol`` of the robot where the last poke ended (a box
    pushed at the guarded stop slides on by up to ~1 cm during the hold, so ``tol`` is 15 mm)."""
    from activetouch.belief.contact_model import robot_object_distance

    pts = est.env.robot_points(est.last_obs.q[-1:])
    d = robot_object_distance(est.obj, torch.as_tensor(states, dtype=torch.float64), pts.double())[:, 0]
    return float(weights[(d <= tol).numpy()].sum())


@pytest.mark.parametrize("seed", [0, 1, 2])
def test_a_contact_moves_belief_mass_onto_hypotheses_that_explain_it(seed, tmp_path):
    """Poking the true box: the guard stops the arm at contact, and afterwards most of the belief's mass lies on
    boxes that touch the robot there (Eq. 10 + contact-aware resampling, App. B); before the poke almost none."""
    truth, _ = _truth("grasp-box-1", seed)
    seen = {}

    def on_step(t, est, row):
        seen[t] = (est, est.belief.states.numpy().copy(), est.belief.weights.numpy().copy(), row)

    cfg = EpisodeConfig(task="grasp-box-1", method="scripted-poke", seed=seed, particles=60, steps=2,
                        planner={"pokes": [_side_poke(truth)]}, figures=False, progress=False)
    summary = run_episode(cfg, tmp_path, on_step=on_step)
    est, s0, w0, _ = seen[0]
    _, s1, w1, row1 = seen[1]
    assert row1["n_contacts"] >= 1 and row1["stopped_early"]  # the poke hit the box and the guard stopped it
    # before: the prior particles (at their pre-poke states); after: the updated belief
    before, after = _explaining_mass(est, s0, w0), _explaining_mass(est, s1, w1)
    assert after > 0.25 and after >= 2 * before, (before, after)
    assert summary["grasped"] and summary["iterations"] == 1  # step 2: the grasp ends the episode
    rows = read_steps(tmp_path / "steps.csv")
    assert len(rows) == 3 and float(rows[1]["xy_err"]) >= 0 and rows[2]["n_waypoints"] in ("0", 0)


def test_a_poke_far_from_every_particle_leaves_the_belief_unchanged(tmp_path):
    truth, means = _truth("grasp-box-0", 4)
    seen = {}

    def on_step(t, est, row):
        seen[t] = (est.belief.states.numpy().copy(), est.belief.weights.numpy().copy())

    # near the robot base, low: no particle (all within ~0.5 m of the modes, >= 0.28 m in x) comes near
    far = [[0.05, -0.35, 0.25, 0.0], [0.05, -0.35, 0.20, 0.0]]
    cfg = EpisodeConfig(task="grasp-box-0", method="scripted-poke", seed=4, particles=40, steps=1,
                        planner={"pokes": [far]}, figures=False, progress=False)
    run_episode(cfg, tmp_path, on_step=on_step)
    (s0, w0), (s1, w1) = seen[0], seen[1]
    assert np.min(np.hypot(s0[:, 0] - 0.05, s0[:, 1] + 0.35)) > 0.2
    assert np.allclose(s0, s1) and np.allclose(w0, w1, atol=1e-6)


def test_scripted_poke_bad_input(tmp_path):
    cfg = EpisodeConfig(task="grasp-box-0", method="scripted-poke", planner={"pokes": [[[0.3, 0.0, math.nan, 0.0]]]},
                        figures=False, progress=False)
    with pytest.raises(ValueError, match="NaN"):
        run_episode(cfg, tmp_path)
    with pytest.raises(ValueError, match="pokes"):
        run_episode(EpisodeConfig(task="grasp-box-0", method="scripted-poke", progress=False), tmp_path)
    assert not (tmp_path / "steps.csv").exists()  # refused before any work


def test_touch_belief_settings_are_checked(tmp_path):
    with pytest.raises(ValueError, match="belief settings"):
        run_episode(EpisodeConfig(task="grasp-box-0", method="touch-ig", belief={"no_such": 1}, progress=False),
                    tmp_path)
    with pytest.raises(ValueError, match="cannot run"):
        run_episode(EpisodeConfig(task="mug-0", method="touch-ig", progress=False), tmp_path)
    with pytest.raises(ValueError, match="cannot run"):
        run_episode(EpisodeConfig(task="grasp-box-0", method="rumi", progress=False), tmp_path)


def test_grasp_tasks_check_contact_candidates_against_the_history():
    """The grasp tasks run with ``history_check`` (beyond App. B, TouchFilterConfig) unless ``--belief`` says
    otherwise; the setting reaches the filter and is recorded as a task default."""
    from activetouch.experiments.estimators import TouchEstimator
    from activetouch.experiments.runner import task_belief_defaults
    from activetouch.sim.grasp_env import make_grasp_env

    assert task_belief_defaults("grasp-box-0", "touch-ig") == {"history_check": True}
    env = make_grasp_env("grasp-box-0", seed=0)
    try:
        on = TouchEstimator(env, EpisodeConfig(task="grasp-box-0", method="touch-ig", progress=False), "cpu")
        off = TouchEstimator(env, EpisodeConfig(task="grasp-box-0", method="touch-ig", progress=False,
                                                belief={"history_check": False}), "cpu")
    finally:
        env.close()
    assert on.config.history_check and not off.config.history_check
    with pytest.raises(ValueError, match="history_check"):
        from activetouch.belief.touch_filter import TouchFilterConfig

        TouchFilterConfig(history_check="yes")

"""The what-if APC stop (RUMI Eq. 33, section J) replayed from --no-terminate episodes: the pure rule, its
refusals, and the property that makes the replay exact: a terminated episode is the prefix of the
--no-terminate episode of the same seed."""
import math

import pytest

from activetouch.experiments.records import read_steps
from activetouch.experiments.runner import EpisodeConfig, run_episode
from activetouch.experiments.stop_rule import (object_diagonal, replay_stop, stop_rule_markdown, stop_rule_rows,
                                               stop_step)


def test_stop_step_is_the_first_step_below_the_bound():
    assert stop_step([0.05, 0.02, 0.009, 0.004, 0.001], 0.01) == (2, True)
    assert stop_step([0.05, 0.02, 0.011], 0.01) == (2, False)  # never below: runs to its last step
    assert stop_step([0.005, 0.02], 0.01) == (0, True)  # the check before step 1 reads step 0's APC
    assert stop_step([None, math.nan, 0.002], 0.01) == (2, True)  # missing values never stop an episode


def test_a_prior_already_below_the_bound_disables_the_stop():
    # the estimator turns APC termination off when the prior's APC is already below beta_t l_c (the mug)
    assert stop_step([0.002, 0.001], 0.005, prior_apc=0.001) == (1, False)
    assert stop_step([0.002, 0.001], 0.005, prior_apc=0.05) == (0, True)


def test_a_success_after_the_stop_does_not_count():
    rows = [{"step": k, "nll": n, "apc": a} for k, (n, a) in enumerate([(900, 0.1), (400, 0.006), (100, 0.004)])]
    assert replay_stop(rows, 150.0, 0.008) == (1, False, True)
    assert replay_stop(rows, 150.0, 0.005) == (2, True, True)
    assert replay_stop(rows, 150.0, 0.001) == (2, True, False)


def _summary(**kw):
    s = {"task": "box-0", "method": "rumi", "seed": 0, "nll_threshold": 150.0, "prior_apc": 0.08,
         "apc_termination": False, "config": {"terminate_on_convergence": False}}
    s.update(kw)
    return s


def test_refuses_terminated_or_non_rumi_episodes_and_bad_betas():
    rows = [{"step": 0, "nll": 1000.0, "apc": 0.05}]
    with pytest.raises(ValueError, match="--no-terminate"):
        stop_rule_rows([(_summary(config={"terminate_on_convergence": True}), rows)], [0.03])
    with pytest.raises(ValueError, match="not a RUMI-task episode"):
        stop_rule_rows([(_summary(nll_threshold=None), rows)], [0.03])
    no_apc = _summary(method="contact-slide")
    del no_apc["apc_termination"]
    with pytest.raises(ValueError, match="does not stop on APC"):
        stop_rule_rows([(no_apc, rows)], [0.03])
    with pytest.raises(ValueError, match="beta_t must be in"):
        stop_rule_rows([(_summary(), rows)], [0.0])
    with pytest.raises(ValueError, match="apc_stop"):
        stop_step([0.1], -1.0)


def test_table_counts_per_beta_and_totals_over_tasks():
    lc = object_diagonal("box-0")
    assert 0.2 < lc < 0.35  # the cracker box's bounding-box diagonal (0.03 l_c = 8.4 mm)
    slow = [{"step": k, "nll": n, "apc": a * lc} for k, (n, a) in enumerate([(900, 0.5), (200, 0.025), (120, 0.01)])]
    fast = [{"step": k, "nll": n, "apc": a * lc} for k, (n, a) in enumerate([(900, 0.5), (140, 0.025), (100, 0.01)])]
    eps = [(_summary(seed=0), slow), (_summary(seed=1), fast), (_summary(task="box-1", seed=0), slow)]
    rows = stop_rule_rows(eps, [0.03, 0.02])
    got = {(r["beta_t"], r["task"]): (r["successes"], r["runs"], r["median_steps"]) for r in rows}
    assert got == {(0.03, "box-0"): (1, 2, 1.0), (0.03, "box-1"): (0, 1, 1.0),
                   (0.02, "box-0"): (2, 2, 2.0), (0.02, "box-1"): (1, 1, 2.0)}
    md = stop_rule_markdown(rows)
    assert "| 0.03 | all 2 tasks | rumi | **1/3** |" in md and "| 0.02 | all 2 tasks | rumi | **3/3** |" in md


def test_a_terminated_episode_is_the_prefix_of_the_no_terminate_one(tmp_path):
    # RUMI on box-0 (the prior's APC is far above the bound, so termination is live; resampling moves APC from
    # the first step on). The bound is taken from the --no-terminate run itself, just above its first new APC
    # minimum: whatever trajectory this machine's floating point gives, the terminated run must stop where the
    # replay says and hold the same rows up to there.
    cfg = dict(task="box-0", method="rumi", seed=0, steps=4, use_chsel=False, progress=False, figures=False,
               planner={"num_samples": 100, "rollout_samples": 2})
    free = run_episode(EpisodeConfig(**cfg, terminate_on_convergence=False), tmp_path / "free")
    rows = read_steps(tmp_path / "free" / "steps.csv")
    apc = [float(r["apc"]) for r in rows]
    lc = object_diagonal("box-0")
    drops = [k for k in range(1, len(apc) - 1) if apc[k] < min(apc[:k]) * (1 - 1e-4)]
    # a new minimum before the last step: stop there; none (APC only grew): a bound below every step, no stop
    bound = apc[drops[0]] * (1 + 1e-5) if drops else min(apc) * 0.999
    predicted = replay_stop(rows, free["nll_threshold"], bound, free["prior_apc"])
    assert predicted.converged == bool(drops)
    assert predicted.stop_step == (drops[0] if drops else len(apc) - 1)
    stopped = run_episode(EpisodeConfig(**cfg, beta_t=bound / lc), tmp_path / "stopped")
    assert (stopped["steps"], stopped["converged"]) == (predicted.stop_step, predicted.converged)
    assert stopped["success"] == predicted.success
    got = [float(r["nll"]) for r in read_steps(tmp_path / "stopped" / "steps.csv")]
    assert got == [float(r["nll"]) for r in rows[:predicted.stop_step + 1]]

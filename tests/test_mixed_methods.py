"""Mixed methods (issue 11): a belief of one paper with a planner of another, on the one episode loop."""
import math

import numpy as np
import torch

from activetouch import registry
from activetouch.belief.tiqf import initial_state
from activetouch.experiments.estimators import move_state
from activetouch.experiments.runner import EpisodeConfig, run_episode
from activetouch.geometry import make_pose


def _rot(axis, angle):
    a = torch.as_tensor(axis, dtype=torch.float64)
    a = a / a.norm()
    K = torch.tensor([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]], dtype=torch.float64)
    return torch.eye(3, dtype=torch.float64) + math.sin(angle) * K + (1 - math.cos(angle)) * K @ K


def test_moving_the_tiqf_posterior_moves_its_pose_and_keeps_its_covariance_spectrum():
    T = make_pose(_rot([0.2, 0.5, 1.0], 0.7), torch.tensor([0.3, -0.1, 0.05], dtype=torch.float64))
    s = initial_state(T)
    s = s.__class__(x=s.x, Sigma=s.Sigma + 1e-3 * torch.diag(torch.tensor([1.0, 2.0, 3.0, 4.0], dtype=torch.float64)),
                    t=s.t)
    dT = make_pose(_rot([0.0, 0.0, 1.0], 0.3), torch.tensor([0.02, 0.01, 0.0], dtype=torch.float64))
    s2 = move_state(s, dT)
    np.testing.assert_allclose(s2.pose.numpy(), (dT @ T).numpy(), atol=1e-9)
    np.testing.assert_allclose(torch.linalg.eigvalsh(s2.Sigma).numpy(), torch.linalg.eigvalsh(s.Sigma).numpy(),
                               rtol=1e-9, atol=1e-15)
    assert torch.allclose(s2.Sigma, s2.Sigma.T)


def test_tiqf_slide_runs_on_the_rummaging_tasks_and_reports_their_metrics(tmp_path):
    assert registry.compatible("mug-0", "tiqf-slide") and not registry.compatible("clutter-mustard", "tiqf-slide")
    s = run_episode(EpisodeConfig(task="mug-0", method="tiqf-slide", seed=0, steps=3, figures=False, progress=False),
                    tmp_path)
    assert s["steps"] == 3 and math.isfinite(s["min_nll"]) and "success" in s
    import csv

    rows = list(csv.DictReader(open(tmp_path / "steps.csv")))
    assert int(rows[0]["n_visual"]) > 50  # the first view's surface points
    assert all(math.isfinite(float(r["adi_mm"])) and math.isfinite(float(r["nll"])) for r in rows)

"""Tests of the Table II ablation (Sec. VI-B, Fig. 4): planar push scene, batched rollouts, the three filter
variants' metrics, determinism, and the table / figure outputs."""
from __future__ import annotations

import csv
import math

import numpy as np
import pytest
import torch
import trimesh

from activetouch.belief.contact_model import se2_to_pose
from activetouch.experiments.touch_ablation import (
    PAPER_TABLE_II,
    VARIANTS,
    AblationConfig,
    PlanarBox,
    PlanarPushSim,
    _run_seed,
    plot_run,
    run_ablation,
    simulate_run,
    table_markdown,
    write_table,
)


@pytest.fixture(autouse=True)
def one_thread():
    n = torch.get_num_threads()
    torch.set_num_threads(1)
    yield
    torch.set_num_threads(n)


@pytest.fixture(scope="module")
def sim():
    return PlanarPushSim(AblationConfig())


@pytest.fixture(scope="module")
def records(sim):
    """Six runs (seed 0): ~0.6 s each on this CPU."""
    torch.set_num_threads(1)
    return [simulate_run(_run_seed(0, i), sim.cfg, sim, keep=(i == 0)) for i in range(6)]


def test_planar_box_sdf_is_exact(sim):
    box = sim.box
    mesh = trimesh.creation.box(extents=[0.072, 0.164, 0.05])
    mesh.apply_translation([0, 0, 0.025])
    g = torch.Generator().manual_seed(0)
    x = (torch.rand(500, 3, generator=g, dtype=torch.float64) - 0.5) * torch.tensor([0.2, 0.3, 0.1],
                                                                                   dtype=torch.float64)
    x[:, 2] += 0.025
    v, grad = box.sdf_world(se2_to_pose(torch.zeros(1, 3, dtype=torch.float64)), x)
    ref = -trimesh.proximity.signed_distance(mesh, x.numpy())  # trimesh: positive inside
    assert np.allclose(v[0].numpy(), ref, atol=1e-6)
    assert torch.allclose(grad.norm(dim=-1), torch.ones(1, 500, dtype=torch.float64))
    # the gradient is the SDF's: a small step along it raises the value by the step (away from kinks)
    v2, _ = box.sdf_world(se2_to_pose(torch.zeros(1, 3, dtype=torch.float64)), x + 1e-5 * grad[0])
    assert float(((v2 - v) / 1e-5 - 1).abs().median()) < 1e-3


def test_rollout_reproduces_the_true_run(sim):
    """A particle at the true state predicts the true trajectory exactly (same model, same steps), and the
    batched rollout's qpos slots are the object's."""
    cfg = sim.cfg
    truth = np.array([0.01, -0.015, 0.3])
    traj, contact = sim.simulate_truth(truth)
    assert contact.any() and not contact.all()
    states = np.stack([truth, truth + [0.0, 0.3, 0.0]])
    out = sim.rollout(sim.initial_states(states), 0, cfg.num_steps)
    q = sim.qpos(out[:, cfg.steps_per_waypoint - 1::cfg.steps_per_waypoint])
    assert np.allclose(q[0], traj, atol=1e-9)
    assert np.allclose(q[1], states[1], atol=1e-9)  # 0.3 m to the side: never touched, never moves
    # pushed by the robot: the truth ends far along the push direction
    assert traj[-1, 0] - truth[0] > 0.1


def test_scene_is_quasi_static(sim):
    """The object moves only while touched: between two contact-free waypoints it stays within 0.5 mm."""
    cfg = sim.cfg
    for truth in ([0.0, 0.0, 0.0], [0.0, 0.06, 0.5], [0.02, -0.04, -0.8]):
        traj, contact = sim.simulate_truth(np.array(truth))
        free = ~contact[1:] & ~contact[:-1]
        step = np.linalg.norm(np.diff(traj[:, :2], axis=0), axis=1)
        assert contact.any()
        if free.any():
            assert float(step[free].max()) < 5e-4
        # never faster than the robot (0.1 m/s = 5 mm per waypoint) by more than a little
        assert float(step.max()) < 1.5 * 0.4 / cfg.num_waypoints


def test_metrics_finite_and_in_range(records):
    for rec in records:
        assert rec["n_contacts"] >= 0
        for key in VARIANTS:
            m = rec[key]
            assert 0.0 <= m["mse_pos"] < 0.5 and math.isfinite(m["mse_pos"])
            assert 0.0 <= m["mse_yaw"] <= (math.pi / 2) ** 2 + 1e-9
            assert 1 / 100 <= m["active_share"] <= 1.0
    assert sum(r["n_contacts"] > 0 for r in records) >= 5  # the push meets the truth in (nearly) every run


def test_same_seed_same_numbers(sim, records):
    again = simulate_run(_run_seed(0, 1), sim.cfg, sim)
    for key in VARIANTS:
        assert again[key] == records[1][key]
    a = run_ablation(2, seed=3, progress=False)
    b = run_ablation(2, seed=3, progress=False)
    assert a["summary"] == b["summary"]
    c = run_ablation(2, seed=4, progress=False)
    assert c["summary"] != a["summary"]


def test_resampled_keeps_more_active_particles_than_binary(records):
    res = np.array([r["smooth_resampled"]["active_share"] for r in records])
    binary = np.array([r["binary"]["active_share"] for r in records])
    assert float(res.mean()) > float(binary.mean()) + 0.15
    assert int((res > binary).sum()) >= 5
    assert sum(r["smooth_resampled"]["n_resamples"] for r in records) >= len(records)  # it did resample


def test_table_and_figure(records, tmp_path):
    from activetouch.experiments.touch_ablation import summarise

    summary = summarise(records)
    csv_path, md_path = write_table(summary, tmp_path, runs=len(records))
    rows = list(csv.DictReader(open(csv_path)))
    assert [r["method"] for r in rows] == list(VARIANTS.values())
    assert float(rows[2]["active_share_paper_mean"]) == PAPER_TABLE_II["smooth_resampled"]["active_share"][0]
    assert float(rows[0]["mse_pos_mean"]) == pytest.approx(summary["binary"]["mse_pos"]["mean"])
    md = md_path.read_text()
    assert "Smooth & Resampled" in md and "0.511 ± 0.140" in md
    assert md == table_markdown(summary, len(records))
    png = plot_run(records[0], tmp_path / "fig4.png")
    assert png.stat().st_size > 20_000
    with pytest.raises(ValueError, match="keep=True"):
        plot_run(records[1], tmp_path / "x.png")


def test_bad_input():
    with pytest.raises(ValueError, match="multiple"):
        AblationConfig(num_waypoints=81)
    with pytest.raises(ValueError, match="top_k"):
        AblationConfig(num_particles=5)
    with pytest.raises(ValueError, match="flip_rate"):
        AblationConfig(flip_rate=1.5)
    with pytest.raises(ValueError, match="runs"):
        run_ablation(0, progress=False)
    with pytest.raises(ValueError, match="half"):
        PlanarBox([0.1, -0.1, 0.1])

"""A short closed loop of Algorithm 1 (RUMI on mug-0): it runs, writes its files as it goes, and learns."""
import json

import pytest

from activetouch.experiments.records import read_steps
from activetouch.experiments.runner import EpisodeConfig, run_episode


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("mug0")
    # Few KMPPI samples and no CHSEL keep this under a minute; everything else is the paper's configuration.
    cfg = EpisodeConfig(task="mug-0", method="rumi", seed=0, steps=12, use_chsel=False, progress=False,
                        planner={"num_samples": 200, "rollout_samples": 3})
    summary = run_episode(cfg, out)
    return out, summary


def test_closed_loop_writes_results(short_run):
    out, summary = short_run
    rows = read_steps(out / "steps.csv")
    assert [int(r["step"]) for r in rows] == list(range(len(rows)))
    assert len(rows) == summary["steps"] + 1 >= 2
    for name in ("summary.json", "curves.png", "belief.png"):
        assert (out / name).stat().st_size > 0
    on_disk = json.loads((out / "summary.json").read_text())
    assert on_disk["min_nll"] == pytest.approx(min(float(r["nll"]) for r in rows), rel=1e-4)
    assert on_disk["success"] == (on_disk["min_nll"] < 20.0)
    replans = [r for r in rows[1:] if float(r["replanned"]) == 1.0]
    assert replans and all(float(r["plan_s"]) >= float(r["dynamics_s"]) > 0 for r in replans)


def test_closed_loop_nll_falls(short_run):
    out, summary = short_run
    rows = read_steps(out / "steps.csv")
    first, last = float(rows[0]["nll"]), float(rows[-1]["nll"])
    assert last < first, f"nll did not fall: {first:.1f} -> {last:.1f}"
    assert any(int(r["in_contact"]) for r in rows), "the robot never touched the mug"


def test_closed_loop_with_estimated_object_motion(tmp_path):
    # observe_dT=False: the object's motion comes from ObjMove (Algorithm 5) seeded with the gripper's motion
    cfg = EpisodeConfig(task="mug-0", method="rumi", seed=0, steps=7, use_chsel=False, progress=False, figures=False,
                        observe_dT=False, planner={"num_samples": 200, "rollout_samples": 3})
    summary = run_episode(cfg, tmp_path)
    rows = read_steps(tmp_path / "steps.csv")
    assert summary["config"]["observe_dT"] is False and len(rows) == 8
    assert any(int(r["in_contact"]) for r in rows), "no contact: ObjMove was never exercised"
    nll = [float(r["nll"]) for r in rows]
    assert all(v == v and v < 1e4 for v in nll)  # finite, no lost belief
    assert float(rows[-1]["trans_err"]) < 0.03  # the belief followed the pushed mug to within 3 cm

"""A short closed loop of Algorithm 1 (RUMI on mug-0): it runs, writes its files as it goes, and learns."""
import json

import pytest

from activetouch.experiments.records import read_steps
from activetouch.experiments.runner import EpisodeConfig, run_episode


# Few KMPPI samples and no CHSEL keep a run under half a minute; everything else is the paper's configuration.
SHORT = dict(task="mug-0", method="rumi", seed=0, steps=6, use_chsel=False, progress=False,
             planner={"num_samples": 200, "rollout_samples": 3})


@pytest.fixture(scope="module")
def short_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("mug0")
    summary = run_episode(EpisodeConfig(**SHORT), out)
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


# A scripted push of the mug-0 mug: from the start (0.25, 0.22) to y = 0, then +x into the mug at (0.5, 0).
# Scripted actions make the same contact on any machine; the closed loop's trajectory depends on floating point.
PUSH = [[0, -1, 0], [0, -1, 0], [0, -0.75, 0], [1, 0, 0], [1, 0, 0], [1, 0, 0], [0.5, 0, 0], [-0.5, 0, 0]]
SCRIPTED = dict(task="mug-0", method="scripted", seed=0, particles=30, use_chsel=False, progress=False, figures=False)


def _col(rows, name):
    return [float(r[name]) for r in rows]


def test_zero_actions_keep_every_free_point(tmp_path):
    # MuJoCo settles the resting box by ~1e-6 m per step; Algorithm 6 must not take that for a move that covers
    # free space (it deleted the free points inside any particle: box-0 lost its evidence against particles)
    run_episode(EpisodeConfig(**{**SCRIPTED, "task": "box-0", "steps": 3, "planner": {"actions": [[0, 0, 0, 0]] * 3}}),
                tmp_path)
    rows = read_steps(tmp_path / "steps.csv")
    free, nll = _col(rows, "n_free"), _col(rows, "nll")
    assert len(rows) == 4 and free[0] > 1000
    assert all(f >= free[0] for f in free), f"free points lost during zero actions: {free}"
    assert max(nll) - min(nll) < 1e-3 * max(nll), f"the belief changed without new evidence: {nll}"


# observed dT (the paper's sim setting): the features follow the mug exactly, so the true pose stays far below
# the resample threshold l_r = 5; estimated dT (ObjMove, Algorithm 5): its errors add up over the pushes (here
# about 3 after 3 pushes), a looser bound
@pytest.mark.parametrize("observe_dT, max_true_l, max_err", [(True, 2.0, 0.05), (False, 15.0, 0.06)])
def test_scripted_push_keeps_evidence_consistent_with_the_truth(tmp_path, observe_dT, max_true_l, max_err):
    # While the gripper pushes the mug, the object-fixed features must move with it: the true pose stays
    # consistent with the evidence and the belief stays on the mug.
    cfg = EpisodeConfig(**{**SCRIPTED, "steps": len(PUSH), "observe_dT": observe_dT, "planner": {"actions": PUSH}})
    summary = run_episode(cfg, tmp_path)
    rows = read_steps(tmp_path / "steps.csv")
    contact = [int(r["in_contact"]) for r in rows]
    assert summary["config"]["observe_dT"] is observe_dT
    assert sum(contact) >= 2, f"the scripted push never touched the mug: {contact}"
    first = contact.index(1)
    assert _col(rows, "n_surface")[first] > _col(rows, "n_surface")[0]  # the touch added surface points
    assert max(_col(rows, "true_discrepancy")) < max_true_l, _col(rows, "true_discrepancy")
    assert max(_col(rows, "trans_err")) < max_err, _col(rows, "trans_err")
    assert all(v == v and v < 1e4 for v in _col(rows, "nll"))  # finite, no lost belief


def test_same_seed_same_result(tmp_path):
    # one machine, one seed: identical per-step numbers (timings aside)
    cfg = EpisodeConfig(**{**SHORT, "steps": 3, "figures": False})
    run_episode(cfg, tmp_path / "a")
    run_episode(cfg, tmp_path / "b")
    a, b = read_steps(tmp_path / "a" / "steps.csv"), read_steps(tmp_path / "b" / "steps.csv")
    keys = ("nll", "apc", "n_features", "n_free", "in_contact", "trans_err", "mean_rot_err_deg")
    assert [[r[k] for k in keys] for r in a] == [[r[k] for k in keys] for r in b]


def test_rerun_into_a_folder_replaces_its_figures_and_records_the_platform(tmp_path):
    cfg = EpisodeConfig(**{**SCRIPTED, "steps": 1, "figures": True, "planner": {"actions": [[0, 0, 0]]}})
    run_episode(cfg, tmp_path)
    assert (tmp_path / "curves.png").exists() and (tmp_path / "belief.png").exists()
    summary = run_episode(EpisodeConfig(**{**SCRIPTED, "steps": 1, "planner": {"actions": [[0, 0, 0]]}}), tmp_path)
    assert not any((tmp_path / f).exists() for f in ("curves.png", "belief.png", "contact.png")), \
        "figures of the earlier run were left in the folder"
    p = summary["platform"]
    assert p["torch"] and p["mujoco"] and p["numpy"] and p["cpu"] and p["torch_threads"] >= 1


def test_platform_records_the_code_that_ran():
    # results kept across sessions (benchmarks/results) must say which code made them
    import subprocess
    from pathlib import Path

    import activetouch
    from activetouch.experiments.runner import platform_info

    p = platform_info()
    assert p["activetouch"] == activetouch.__version__
    pkg = Path(activetouch.__file__).resolve().parent
    try:
        head = subprocess.run(["git", "-C", str(pkg), "rev-parse", "HEAD"], capture_output=True, text=True, timeout=10)
    except OSError:  # no git on this machine: nothing to compare against
        head = None
    if head is not None and head.returncode == 0:  # imported from a git checkout (CI's clean clone is one)
        assert p["commit"] == head.stdout.strip() and isinstance(p["modified"], bool)
    else:
        assert p["commit"] is None and p["modified"] is None


def test_first_view_of_mug2_leaves_the_yaw_open(tmp_path):
    # the demo's premise (activetouch demo runs mug-2): the handle faces away from the camera, so the camera-only
    # belief (CHSEL on X_0, Alg. 1 lines 1-3) cannot tell the yaw; measured 42-110 deg over seeds 0-4. One seed
    # here: CHSEL on mug-2's first view takes ~45 s on 2 cores (seed 1 is in benchmarks/bench_first_view.py)
    s = run_episode(EpisodeConfig(task="mug-2", method="scripted", seed=0, steps=1, progress=False,
                                  figures=False, planner={"actions": [[0, 0, 0]]}), tmp_path)
    assert s["initial_mean_rot_err_deg"] > 30.0, s["initial_mean_rot_err_deg"]


# Every family on CUDA (skipped without one). Found on an H200: the SE(3) prior, Algorithm 6's move test and the
# TIQF estimator's weights mixed CPU and CUDA tensors, so no rummaging method ran with the default device there.
@pytest.mark.skipif(not __import__("torch").cuda.is_available(), reason="needs CUDA")
@pytest.mark.parametrize("task, method", [("box-0", "rumi"), ("box-0", "gpvr"), ("box-0", "slide"),
                                          ("box-0", "tiqf-slide"), ("clutter-mustard", "tiqf-visuo-tactile")])
def test_methods_run_on_cuda(tmp_path, task, method):
    s = run_episode(EpisodeConfig(task=task, method=method, seed=0, steps=4, device="cuda", use_chsel=False,
                                  progress=False, figures=False), tmp_path)
    rows = read_steps(tmp_path / "steps.csv")
    assert s["steps"] == len(rows) - 1 >= 1
    assert all(r.get("nll", "") in ("", None) or float(r["nll"]) == float(r["nll"]) for r in rows)  # no NaN
    assert s["platform"]["cuda"]

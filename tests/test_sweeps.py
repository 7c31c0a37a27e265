"""Sweeps beyond one process: every compatible pair (``sweep --grid``) and Ray (``--backend ray`` /
``--ray-address``): a local Ray instance gives the same summaries as the process pool."""
import json
import subprocess
import sys

import pytest

from activetouch import registry
from activetouch.experiments.runner import EpisodeConfig, run_sweep

_VOLATILE = {"wall_s", "platform", "median_plan_s", "_dir"}  # timings and the folder


def _stable(s: dict) -> dict:
    return {k: v for k, v in s.items() if k not in _VOLATILE}


def test_grid_runs_only_compatible_pairs_and_writes_one_table(tmp_path):
    out = tmp_path / "grid"
    r = subprocess.run([sys.executable, "-m", "activetouch.cli", "sweep", "--grid", "--tasks", "clutter-mustard",
                        "grasp-box-0", "--methods", "tiqf-static", "touch-uninformed", "--seeds", "1", "--steps", "1",
                        "--no-figures", "--out", str(out)], capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, r.stderr[-2000:]
    grid = (out / "grid.md").read_text()
    rows = [ln for ln in grid.splitlines() if ln.startswith("| clutter") or ln.startswith("| grasp")]
    # 2 of the 4 task x method combinations are compatible; the others were not run
    assert len(rows) == 2, grid
    assert any("tiqf-static" in ln and "clutter" in ln for ln in rows)
    assert any("touch-uninformed" in ln and "grasp" in ln for ln in rows)
    assert not (out / "clutter-mustard" / "touch-uninformed").exists()
    assert not (out / "grasp-box-0" / "tiqf-static").exists()


def test_grid_with_no_compatible_pair_is_refused():
    r = subprocess.run([sys.executable, "-m", "activetouch.cli", "sweep", "--grid", "--tasks", "mug-0",
                        "--methods", "tiqf-static", "--seeds", "1"], capture_output=True, text=True, timeout=120)
    assert r.returncode != 0 and "no compatible" in r.stderr


def test_ray_local_instance_gives_the_process_pool_summaries(tmp_path):
    pytest.importorskip("ray")
    base = EpisodeConfig(figures=False, progress=False)
    # one episode per backend: what is compared is the summary, not the load balancing
    pool = run_sweep(["clutter-mustard"], ["tiqf-static"], [1], tmp_path / "pool", base=base, workers=2)
    on_ray = run_sweep(["clutter-mustard"], ["tiqf-static"], [1], tmp_path / "ray", base=base, workers=1,
                       backend="ray")
    assert len(on_ray) == 1 and on_ray[0]["seed"] == 1
    assert [_stable(s) for s in on_ray] == [_stable(s) for s in pool]
    # resume: a second call finds every episode finished and runs nothing
    again = run_sweep(["clutter-mustard"], ["tiqf-static"], [1], tmp_path / "ray", base=base, workers=1,
                      backend="ray")
    assert [s["wall_s"] for s in again] == [s["wall_s"] for s in on_ray]


def test_ray_address_needs_the_ray_backend(tmp_path):
    with pytest.raises(ValueError, match="ray_address needs"):
        run_sweep(["clutter-mustard"], ["tiqf-static"], [0], tmp_path, ray_address="auto")
    with pytest.raises(ValueError, match="retries"):
        run_sweep(["clutter-mustard"], ["tiqf-static"], [0], tmp_path, backend="ray", retries=-1)
    assert registry.compatible("clutter-mustard", "tiqf-static")

"""How much of the pose the first camera view alone pins down (RUMI Alg. 1 lines 1-3: CHSEL on X_0).

Usage: ``.venv/bin/python benchmarks/bench_first_view.py [--tasks mug-2] [--seeds 5]`` (or ``activetouch bench
first-view -- ...``).

Per task and seed, one episode of the ``scripted`` method with a single zero action (the belief after the camera
view and one settle step, no contact), at the paper's 100 particles with CHSEL: prints the weighted mean rotation
error of the initial belief (``initial_mean_rot_err_deg``). The demo's premise is that
mug-2's handle faces away from the camera, so this error stays large (the yaw is open until a touch); the suite
checks one seed (tests/test_runner.py), this script the spread over seeds. Measured on this 2-core CPU
(mug-2, seeds 0-4, ~45 s each): 42-110 deg.
"""
from __future__ import annotations

import argparse
import tempfile
import time

from activetouch.experiments.runner import EpisodeConfig, run_episode
from activetouch.registry import compatible_pairs


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--tasks", nargs="+", default=["mug-2"])
    ap.add_argument("--seeds", type=int, default=5)
    a = ap.parse_args()
    if a.seeds < 1:
        raise SystemExit("--seeds must be >= 1")
    runnable = [t for t, m in compatible_pairs() if m == "scripted"]
    for task in a.tasks:  # unknown names fail here, in one line, before any episode
        if task not in runnable:
            raise SystemExit(f"bench_first_view: {task!r} is not a rummaging task; one of {', '.join(runnable)}")
    print(f"{'task':<10} {'seed':>4} {'rot err (deg)':>14} {'s':>6}")
    with tempfile.TemporaryDirectory() as tmp:
        for task in a.tasks:
            for seed in range(a.seeds):
                t0 = time.perf_counter()
                s = run_episode(EpisodeConfig(task=task, method="scripted", seed=seed, steps=1, progress=False,
                                              figures=False, planner={"actions": [[0, 0, 0]]}), f"{tmp}/{task}-{seed}")
                rot = s["initial_mean_rot_err_deg"]
                print(f"{task:<10} {seed:>4} {rot:14.1f} {time.perf_counter() - t0:6.1f}", flush=True)


if __name__ == "__main__":
    main()

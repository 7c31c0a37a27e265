"""Time per iteration of the touch-only system split by sub-step, like the paper's Fig. 3.

Usage: ``python benchmarks/bench_touch_step.py [--task grasp-box-0] [--iterations 5] [--predict rollout static]
[--out DIR]``

Each iteration on a fresh prior belief of the task (100 particles): the grasp check (the grasp simulated on every
particle, App. D-d), candidate sampling (20 spline pokes, IK), the prediction of every particle under every candidate
(MuJoCo rollouts, or none with ``predict=static``), the whole-robot distances and Eq. 10, Alg. 1's expected IG, the
executed poke (physics) and the belief update (rollouts of the executed poke + re-weighing + resampling). Prints the
median and mean of each sub-step and writes ``fig3.png`` (box plots sorted by mean, as in Fig. 3) and
``fig3.csv``. The paper's target: the expected IG of 20 candidates x 100 particles in <= 1 s.
"""
from __future__ import annotations

import argparse
import csv
import statistics
import time
from pathlib import Path

import torch

from activetouch.experiments.estimators import TouchEstimator
from activetouch.experiments.runner import EpisodeConfig
from activetouch.registry import get_task
from activetouch.planning.touch_ig import TouchIGPlanner, TouchPlannerConfig

KEYS = ("grasp_s", "sample_s", "rollout_s", "distance_s", "ig_s", "step_s", "update_s")
LABELS = {"grasp_s": "grasp check (App. D-d)", "sample_s": "candidates: splines + IK", "rollout_s":
          "predict particles (rollouts)", "distance_s": "whole-robot distance + Eq. 10", "ig_s": "expected IG (Alg. 1)",
          "step_s": "execute poke (physics)", "update_s": "belief update"}


def run(task: str, iterations: int, predict: str, seed: int = 0) -> list[dict]:
    torch.set_num_threads(1)
    entry = get_task(task)
    cfg = EpisodeConfig(task=task, method="touch-ig", seed=seed, progress=False, figures=False)
    env = entry.make_env(seed=seed)
    est = TouchEstimator(env, cfg, "cpu")
    planner = TouchIGPlanner(env, est.config, TouchPlannerConfig(predict=predict), seed=seed)
    gen = torch.Generator().manual_seed(seed)
    out = []
    for it in range(iterations):
        obs, info = env.reset(seed=seed + it)
        est.initialise(entry, obs, info, gen)
        planner.reset()
        a, timings = planner.next_action(est.belief, env.ee_state(), False)
        t0 = time.perf_counter()
        obs, *_ = env.step(a)
        t1 = time.perf_counter()
        est.observe(obs, info, None, gen)
        t2 = time.perf_counter()
        row = {k: float(timings.get(k, 0.0)) for k in KEYS}
        row.update(step_s=t1 - t0, update_s=t2 - t1, total_s=sum(float(timings.get(k, 0.0)) for k in KEYS[:5])
                   + (t2 - t0))
        out.append(row)
        print(f"{predict} iteration {it}: " + ", ".join(f"{k} {row[k]:.3f}" for k in (*KEYS, "total_s")), flush=True)
    env.close()
    return out


def main(argv=None) -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="grasp-box-0")
    ap.add_argument("--iterations", type=int, default=5)
    ap.add_argument("--predict", nargs="+", default=["rollout", "static"], choices=["rollout", "static"])
    ap.add_argument("--out", type=Path, default=Path("runs/bench-touch-step"))
    a = ap.parse_args(argv)
    if a.iterations < 1:
        raise SystemExit("--iterations must be >= 1")
    a.out.mkdir(parents=True, exist_ok=True)
    results = {p: run(a.task, a.iterations, p) for p in a.predict}
    with open(a.out / "fig3.csv", "w", newline="") as fh:
        w = csv.writer(fh)
        w.writerow(["predict", "substep", "median_s", "mean_s"])
        for p, rows in results.items():
            print(f"\n{p}: sub-step, median s, mean s (over {len(rows)} iterations, 1 torch thread)")
            for k in (*KEYS, "total_s"):
                v = [r[k] for r in rows]
                w.writerow([p, k, f"{statistics.median(v):.4f}", f"{statistics.fmean(v):.4f}"])
                print(f"  {LABELS.get(k, 'total'):32s} {statistics.median(v):7.3f} {statistics.fmean(v):7.3f}")
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(results), figsize=(6 * len(results), 3.5), squeeze=False)
    for ax, (p, rows) in zip(axes[0], results.items()):
        keys = sorted(KEYS, key=lambda k: statistics.fmean(r[k] for r in rows))
        ax.boxplot([[r[k] for r in rows] for k in keys], orientation="horizontal", showmeans=True, meanline=True)
        ax.set_yticks(range(1, len(keys) + 1), [LABELS[k] for k in keys], fontsize=8)
        ax.set_xlabel("seconds per iteration")
        ax.set_title(f"predict = {p}", fontsize=9)
    fig.tight_layout()
    fig.savefig(a.out / "fig3.png", dpi=110)
    print(f"\nwrote {a.out / 'fig3.csv'} and {a.out / 'fig3.png'}")


if __name__ == "__main__":
    main()

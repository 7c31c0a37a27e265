"""Median wall time of one ``RummageEnv.step`` (mini steps + IK + physics + sensing) per task family.

Usage: ``.venv/bin/python benchmarks/bench_step.py [--steps 20] [--tasks mug-0 drill-0 box-0]``

Actions drive the gripper toward the object (plus seeded noise) so that contact-rich steps are part
of the sample. Target: <= 100 ms per step.
"""
from __future__ import annotations

import argparse
import statistics
import time

import numpy as np
import torch

from activetouch.sim import make


def bench(task: str, steps: int, seed: int = 0) -> dict:
    env = make(task, seed=seed)
    rng = np.random.default_rng(seed)
    t0 = time.perf_counter()
    env.reset()
    t_reset = time.perf_counter() - t0
    env.object.sdf(torch.zeros(1, 3))  # warm-up: the first exact-SDF query builds its scene
    env.step(np.zeros(env.action_dim))
    times, contacts = [], 0
    for _ in range(steps):
        ee = env.ee_state()
        goal = env.true_pose()[:3, 3]
        d = (goal - ee[:3]) / env.action_scale[0]
        if env.spec.action_space == "planar":
            u = np.array([d[0], d[1], 0.0])
        else:
            u = np.array([d[0], d[1], (0.03 - ee[2]) / env.action_scale[0], 0.0])
        u = np.clip(u + rng.normal(0, 0.3, size=u.shape), -1, 1)
        t = time.perf_counter()
        obs, *_ = env.step(u)
        times.append(time.perf_counter() - t)
        contacts += int(obs.in_contact)
    return {"task": task, "median_ms": 1e3 * statistics.median(times), "max_ms": 1e3 * max(times),
            "reset_ms": 1e3 * t_reset, "contact_steps": contacts, "steps": steps}


def main() -> None:
    p = argparse.ArgumentParser(description=__doc__)
    p.add_argument("--steps", type=int, default=20)
    p.add_argument("--tasks", nargs="+", default=["mug-0", "drill-0", "box-0"])
    args = p.parse_args()
    for task in args.tasks:
        r = bench(task, args.steps)
        print(f"{r['task']:8s} median step {r['median_ms']:6.1f} ms  max {r['max_ms']:6.1f} ms  "
              f"reset {r['reset_ms']:6.1f} ms  contact in {r['contact_steps']}/{r['steps']} steps")


if __name__ == "__main__":
    main()

"""Benchmark RUMI's planning step (field cache + KMPPI with f^ and Eq. 31) on a sim task's set-up (mug-0).

Synthetic belief (no simulation run): for the mug P = 100 particles sharing the body axis at the task's start
position with yaws spread over the half circle hidden from the camera (what CHSEL returns from the first
view); for the drill / box the paper's prior (N(0, 5 cm) positions, uniform yaw). The task's workspace grid
(mug: r_w = 10 mm, one layer at the ee height), the sim gripper points at spacing r_w
(``activetouch.sim.robot.gripper_points``) and the sim reachability map (``--synthetic-reach``: a ramp). Paper parameters (Table IV, V-F): 500 samples x 5 rollouts x H = 15 x 4 mini steps.

Each "step" perturbs the particle weights (so the field is recomputed, as after a belief update) and runs one
planning call (one KMPPI iteration after the warm start). Prints the median / mean split into field cache,
dynamics and cost, for the configured thread count and device.

Measured 2026-11-22 on this project's 2-core CPU box (torch 2.13 CPU, other jobs running; medians over 10 steps,
one KMPPI iteration per planning call, paper parameters, P = 100):

    task     start                threads  total   field   dynamics  cost
    mug-0    ee_start (0.25,0.22)  2       0.29 s  0.03 s  0.20 s    0.05 s
    mug-0    --near (8 cm away)    2       0.26 s  0.02 s  0.19 s    0.05 s
    mug-0    ee_start              1       0.35 s  0.04 s  0.24 s    0.06 s
    mug-0    --near                1       0.39 s  0.04 s  0.27 s    0.07 s
    drill-0  ee_start (3-D)        2       3.3 s   0.12 s  3.1 s     0.16 s   (357 robot points, 40x40x10 grid)

The first call of an episode adds the warm start (5 more iterations): ~1.5 s for the mug, ~16 s for the drill.
The paper reports 0.96 s per step on an RTX 4090. With 2 threads on a machine whose cores are busy with other
processes, torch's OpenMP threads contend and the same call took ~5 s: use ``--threads 1`` (or
``torch.set_num_threads(1)``) when the cores are shared.

    python benchmarks/bench_planning.py [--task mug-0] [--steps 10] [--threads 1] [--device cpu] [--particles 100] [--near]
"""
from __future__ import annotations

import argparse
import json
import math
import statistics
import time

import torch


def build(device: str, particles: int, synthetic_reach: bool, task: str = "mug-0"):
    from activetouch import objects, sim
    from activetouch.geometry import VoxelGrid, pose_from_xyz_yaw
    from activetouch.sim.robot import gripper_points

    spec = sim.get_spec(task)
    obj = objects.load(spec.object_name)
    lo, up = spec.workspace
    ws = VoxelGrid(lo, up, spec.r_w)
    h, mask = gripper_points(spec.r_w)
    true = spec.start_pose(obj.mesh.vertices).float()
    gen = torch.Generator().manual_seed(0)
    if spec.object_name == "mug":
        # particles: body axis at the start position, yaws over the half circle hidden from the camera
        body_offset = torch.tensor([-0.012, 0.0, 0.0])
        centre = torch.tensor([spec.start_xy[0], spec.start_xy[1], 0.0])
        yaws = spec.start_yaw + torch.linspace(-math.pi / 2, math.pi / 2, particles)
        R = pose_from_xyz_yaw(torch.zeros(particles, 3), yaws)[:, :3, :3]
        poses = pose_from_xyz_yaw(centre - torch.einsum("pij,j->pi", R, body_offset), yaws)
    else:
        # the paper's prior for the drill / box: N(0, 0.05) in x, y around the start, uniform yaw
        yaws = 2 * math.pi * torch.rand(particles, generator=gen)
        R = pose_from_xyz_yaw(torch.zeros(particles, 3), yaws)[:, :3, :3]
        poses = true.expand(particles, 4, 4).clone()
        poses[:, :3, :3] = R @ true[:3, :3]
        poses[:, :2, 3] += 0.05 * torch.randn(particles, 2, generator=gen)
    poses = poses.to(device)
    if synthetic_reach:
        pts = ws.points()
        reach = (ws, ((0.55 - pts[:, 0]) / 0.2).clamp(0, 1).reshape(ws.shape))
    else:
        from activetouch.sim.reachability import reachability_map

        reach = reachability_map(lo, up, planar=spec.action_space == "planar")
    return obj, ws, h, mask, reach, poses, spec


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--task", default="mug-0", help="sim task whose set-up is used (default mug-0)")
    ap.add_argument("--steps", type=int, default=10)
    ap.add_argument("--threads", type=int, default=None, help="torch threads (default: torch's choice)")
    ap.add_argument("--device", default="cpu")
    ap.add_argument("--particles", type=int, default=100)
    ap.add_argument("--samples", type=int, default=500)
    ap.add_argument("--rollouts", type=int, default=5)
    ap.add_argument("--synthetic-reach", action="store_true", help="skip the (cached) IK reachability map")
    ap.add_argument("--near", action="store_true", help="start 8 cm in front of the mug (most rollouts touch it)")
    ap.add_argument("--json", default=None, help="write the raw timings here")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    from activetouch.planning import RumiPlanner, RumiPlannerConfig

    obj, ws, h, mask, reach, poses, spec = build(args.device, args.particles, args.synthetic_reach, args.task)
    cfg = RumiPlannerConfig(num_samples=args.samples, rollout_samples=args.rollouts)
    planner = RumiPlanner(obj, ws, h, mask, reachability=reach, config=cfg, action_space=spec.action_space,
                          ee_bounds=(spec.ee_lower, spec.ee_upper), seed=0, device=args.device)
    gen = torch.Generator().manual_seed(0)
    ee = list(spec.ee_start)
    if args.near:
        ee = [spec.start_xy[0] - 0.047 - 0.08, spec.start_xy[1], ee[2], 0.0]
    ee0 = list(ee)
    t0 = time.perf_counter()
    planner.plan(poses, torch.full((args.particles,), 1.0 / args.particles), ee)  # warm start (not timed)
    warm = time.perf_counter() - t0
    rows = []
    for _ in range(args.steps):
        w = torch.rand(args.particles, generator=gen) + 0.5
        w = (w / w.sum()).to(args.device)
        t0 = time.perf_counter()
        u, t = planner.plan(poses, w, ee)
        t["total_s"] = time.perf_counter() - t0
        rows.append(t)
        ee[0] += 0.08 * float(u[0]) / 4  # drift the start state a little, as execution would
        ee[1] += 0.08 * float(u[1]) / 4
    keys = ["total_s", "field_s", "dynamics_s", "cost_s", "mppi_s"]
    summary = {k: {"median": statistics.median(r[k] for r in rows),
                   "mean": statistics.fmean(r[k] for r in rows)} for k in keys}
    print(f"task={args.task} device={args.device} threads={torch.get_num_threads()} P={args.particles} K={args.samples} "
          f"M={args.rollouts} H={cfg.horizon} mini_steps={cfg.mini_steps} gripper points={len(h)} "
          f"workspace={ws.shape} ee={[round(v, 3) for v in ee0]} "
          f"warm start ({cfg.warmstart_iters + 1} iterations)={warm:.2f}s")
    for k in keys:
        print(f"  {k:11s} median {summary[k]['median']:.3f}s  mean {summary[k]['mean']:.3f}s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "summary": summary, "rows": rows}, f, indent=1)
    return summary


if __name__ == "__main__":
    main()

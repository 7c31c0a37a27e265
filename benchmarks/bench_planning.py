"""Benchmark RUMI's planning step (field cache + KMPPI with f^ and Eq. 31) on a sim task's set-up (mug-0).

Synthetic belief (no simulation run): for the mug P = 100 particles sharing the body axis at the task's start
position with yaws spread over the half circle hidden from the camera (what CHSEL returns from the first
view); for the drill / box the paper's prior (N(0, 5 cm) positions, uniform yaw). The task's workspace grid
(mug: r_w = 10 mm, one layer at the ee height), the sim gripper points at spacing r_w
(``activetouch.sim.robot.gripper_points``) and the sim reachability map (``--synthetic-reach``: a ramp). Paper parameters (Table IV, V-F): 500 samples x 5 rollouts x H = 15 x 4 mini steps.

Each "step" perturbs the particle weights (so the field is recomputed, as after a belief update) and runs one
planning call (one KMPPI iteration after the warm start). Prints the median / mean split into field cache,
dynamics and cost, for the configured thread count and device.

Measured 2026-11-22 on this project's 2-core CPU box (torch 2.13 CPU, other jobs running; medians over 5 steps,
one KMPPI iteration per planning call, paper parameters, P = 100, --threads 1). CPU seconds
(``time.process_time``, robust to the other jobs), before / after the exact lazy p(free) look-ups of the
dynamics (planning.dynamics._FreeBounds), both measured in the same run:

    task     gripper pts  grid        total         field   dynamics       cost   warm start (6 iters)
    mug-0    1836 (2-D)   80x80x1     0.34 -> 0.24  0.04    0.24 -> 0.13   0.06   1.5 -> 1.1
    box-0    357          40x40x10    4.2  -> 0.77  0.21    3.7  -> 0.35   0.21   22  -> 3.4
    drill-0  357          40x40x10    4.0  -> 0.69  0.18    3.6  -> 0.31   0.19   23  -> 2.8

(wall times were 1.1 s / 1.0 s per box / drill call on the loaded machine). The paper reports 0.96 s (mug)
and 2.19 s (3-D) per step on an RTX 4090. With 2 threads on a machine whose cores are busy with other
processes, torch's OpenMP threads contend (busy-waiting: the box call then took 3.8 CPU s / 5.7 s wall):
use ``--threads 1`` (or ``torch.set_num_threads(1)``) when the cores are shared. ``--no-screen`` runs the
dynamics without the lazy look-ups (identical result; mug-0 --near: 0.39 CPU s total with them).

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
    ap.add_argument("--no-screen", action="store_true",
                    help="look up p(free) at every robot point (StochasticDynamics.screen = False; same result)")
    ap.add_argument("--json", default=None, help="write the raw timings here")
    args = ap.parse_args(argv)
    if args.threads:
        torch.set_num_threads(args.threads)
    from activetouch.planning import RumiPlanner, RumiPlannerConfig, StochasticDynamics

    StochasticDynamics.screen = not args.no_screen

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
        t0, c0 = time.perf_counter(), time.process_time()
        u, t = planner.plan(poses, w, ee)
        t["total_s"] = time.perf_counter() - t0
        t["total_cpu_s"] = time.process_time() - c0
        rows.append(t)
        ee[0] += 0.08 * float(u[0]) / 4  # drift the start state a little, as execution would
        ee[1] += 0.08 * float(u[1]) / 4
    keys = ["total_s", "field_s", "dynamics_s", "cost_s", "mppi_s",
            "total_cpu_s", "field_cpu_s", "dynamics_cpu_s", "cost_cpu_s", "mppi_cpu_s"]
    summary = {k: {"median": statistics.median(r[k] for r in rows),
                   "mean": statistics.fmean(r[k] for r in rows)} for k in keys}
    print(f"task={args.task} device={args.device} threads={torch.get_num_threads()} P={args.particles} K={args.samples} "
          f"M={args.rollouts} H={cfg.horizon} mini_steps={cfg.mini_steps} gripper points={len(h)} "
          f"workspace={ws.shape} ee={[round(v, 3) for v in ee0]} "
          f"warm start ({cfg.warmstart_iters + 1} iterations)={warm:.2f}s")
    for k in keys:
        print(f"  {k:15s} median {summary[k]['median']:.3f}s  mean {summary[k]['mean']:.3f}s")
    if args.json:
        with open(args.json, "w") as f:
            json.dump({"args": vars(args), "summary": summary, "rows": rows}, f, indent=1)
    return summary


if __name__ == "__main__":
    main()

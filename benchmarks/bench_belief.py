"""Benchmark of the RUMI belief hot paths on this machine (CPU unless CUDA is available).

* WeighParticles (Algorithm 2): 100 particles against 5,000 features with the voxel-cached SDF
  (target: <= 5 ms; weighing takes the values-only lookup ``KnownObject.sdf_world_values``).
* One Resample call (Algorithm 4: systematic resampling, PerturbTransform, N_o = 10 Adam steps on C^).

Usage: ``python benchmarks/bench_belief.py [--repeats 20] [--device cpu] [--threads 1]``. Prints medians of wall
and process CPU time (on a shared, loaded machine the CPU time is the steadier number; with 2 torch threads
on a loaded 2-core machine OpenMP spinning inflates both, so compare ``--threads 1`` too).
"""
from __future__ import annotations

import argparse
import os
import statistics
import time

import torch

from activetouch import objects
from activetouch.belief import BeliefConfig, ParticleBelief, mug_prior
from activetouch.geometry import pose_from_xyz_yaw, transform_points
from activetouch.observations import Features


def features_5000(obj, T, device, seed=0) -> Features:
    """2,000 surface points on the posed mug and 3,000 free points around it (outside the mug)."""
    g = torch.Generator().manual_seed(seed)
    surf = transform_points(T, obj.sample_surface(2000, seed=seed))
    cand = T[:3, 3] + (torch.rand(20000, 3, generator=g) - 0.5) * torch.tensor([0.25, 0.25, 0.2]) \
        + torch.tensor([0.0, 0.0, 0.1])
    v, _ = obj.sdf_world(T[None], cand)
    free = cand[v[0] > 0.005][:3000]
    pos = torch.cat([surf, free]).to(device)
    sem = torch.tensor([0] * len(surf) + [1] * len(free), device=device)
    return Features(pos, sem)


def _median_s(fn, repeats: int, sync) -> tuple[float, float]:
    """Median wall time and median CPU time of this process (all its threads) per call, seconds."""
    wall, cpu = [], []
    for _ in range(repeats):
        sync()
        t0, c0 = time.perf_counter(), time.process_time()
        fn()
        sync()
        wall.append(time.perf_counter() - t0)
        cpu.append(time.process_time() - c0)
    return statistics.median(wall), statistics.median(cpu)


def main(argv=None) -> dict[str, float]:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--repeats", type=int, default=20)
    ap.add_argument("--resample-repeats", type=int, default=5)
    ap.add_argument("--device", default="cuda" if torch.cuda.is_available() else "cpu")
    ap.add_argument("--threads", type=int, default=None, help="torch CPU threads (default: torch's choice)")
    args = ap.parse_args(argv)
    if args.threads is not None:
        torch.set_num_threads(args.threads)
    device = torch.device(args.device)
    sync = torch.cuda.synchronize if device.type == "cuda" else (lambda: None)

    obj = objects.load("mug")
    T = pose_from_xyz_yaw(torch.tensor([0.8, 0.0, 0.0]), torch.tensor(0.3))
    X = features_5000(obj, T, device)
    g = torch.Generator().manual_seed(0)
    prior = mug_prior(T[:3, 3], 100, g).to(device)
    cfg = BeliefConfig()
    b = ParticleBelief(obj, prior, config=cfg)
    b.weigh(X)  # warm-up: loads the SDF cache onto the device
    weigh_s, weigh_cpu = _median_s(lambda: b.weigh(X), args.repeats, sync)

    poses0 = b.poses.clone()

    def one_resample():
        b._poses = poses0.clone()
        b.resample(X, generator=torch.Generator().manual_seed(1))

    resample_s, resample_cpu = _median_s(one_resample, args.resample_repeats, sync)
    print(f"device: {device}, torch threads: {torch.get_num_threads()}, features: {len(X)} "
          f"({int((X.semantics == 0).sum())} surface, {int((X.semantics == 1).sum())} free), particles: 100, "
          f"load average: {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs")
    print(f"WeighParticles (Alg. 2), median of {args.repeats}: {weigh_s * 1e3:.1f} ms wall, "
          f"{weigh_cpu * 1e3:.1f} ms CPU (target <= 5 ms)")
    print(f"Resample (Alg. 4, N_o = {cfg.n_opt} Adam steps), median of {args.resample_repeats}: "
          f"{resample_s * 1e3:.0f} ms wall, {resample_cpu * 1e3:.0f} ms CPU")
    return {"weigh_s": weigh_s, "weigh_cpu_s": weigh_cpu, "resample_s": resample_s, "resample_cpu_s": resample_cpu}


if __name__ == "__main__":
    main()

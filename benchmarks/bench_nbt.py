"""Benchmark of next-best-touch scoring (visuo-tactile clutter paper, Sec. II-D-2, Eq. 25) on the TIQF belief.

Per object and number of touches K: K random touches (``random_touches``) on the object at a random true
pose, a TIQF posterior registered on them from a pose ``--init-deg`` deg and ``--init-mm`` mm off, then
``--rays-per-face`` Monte-Carlo candidate rays on each of the five touchable faces of the bounding box at that
estimate (default 40 x 5 = 200). Timed, each as the median of ``--repeats`` calls after one warm-up call:

* ``select``: ``select_next_best_touch`` as the loop calls it (ray casting + gains + arg max), per
  prediction mode: ``kalman`` (the batched closed-form Kalman update, the default) and ``register`` (one
  TIQF registration per candidate). The issue's target: scoring 200 candidates in <= ``--target-ms`` (50) ms.
* ``gains``: ``expected_information_gain`` alone on the predicted contacts (no ray casting), kalman mode only
  (for ``register`` it is the select time less the rays, and not worth 20 more slow repeats).
* ``rays``: ``ray_mesh_intersect`` alone (open3d Embree scene built per call, float64 refinement).

Also printed, on the kalman row: the Spearman rank correlation of the two modes' gains over the candidates
that hit, and the rank of the kalman choice among the register gains (1: both choose the same touch).
Writes nothing.

Usage: ``python benchmarks/bench_nbt.py [--objects cracker_box mustard_bottle] [--touches 3 10]
[--rays-per-face 40] [--repeats 20] [--threads 1] [--modes kalman register]``.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import time


def _parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--objects", nargs="*", default=["cracker_box", "mustard_bottle"], help="object names")
    ap.add_argument("--touches", type=int, nargs="*", default=[3, 10], help="numbers K of touches so far")
    ap.add_argument("--rays-per-face", type=int, default=40, help="candidates per face (5 faces)")
    ap.add_argument("--modes", nargs="*", default=["kalman", "register"], help="prediction modes to time")
    ap.add_argument("--repeats", type=int, default=20, help="timed calls per measurement (median)")
    ap.add_argument("--model-points", type=int, default=2000, help="TIQF model cloud size")
    ap.add_argument("--init-deg", type=float, default=5.0, help="initial rotation error of the TIQF estimate")
    ap.add_argument("--init-mm", type=float, default=5.0, help="initial translation error of the TIQF estimate")
    ap.add_argument("--target-ms", type=float, default=50.0, help="target time of one scoring")
    ap.add_argument("--threads", type=int, default=1, help="torch and OpenMP threads")
    ap.add_argument("--seed", type=int, default=0)
    return ap.parse_args(argv)


def _median_ms(fn, repeats: int):
    """(median ms of ``repeats`` calls after one warm-up call, the last call's result)."""
    out = fn()  # warm-up
    times = []
    for _ in range(repeats):
        t0 = time.perf_counter()
        out = fn()
        times.append(time.perf_counter() - t0)
    return 1000 * statistics.median(times), out


def main(argv=None) -> dict:
    args = _parse(argv)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))  # before open3d / torch start their pools
    import torch
    from scipy.stats import spearmanr

    from activetouch import objects
    from activetouch.belief.tiqf import TIQFConfig, register
    from activetouch.geometry import axis_angle_to_matrix, make_pose
    from activetouch.planning.nbt import (
        NBTConfig,
        expected_information_gain,
        random_touches,
        ray_mesh_intersect,
        select_next_best_touch,
        touch_candidates,
    )

    torch.set_num_threads(args.threads)
    cfg = TIQFConfig()
    F64 = torch.float64

    def unit(g):
        v = torch.randn(3, generator=g, dtype=F64)
        return v / v.norm()

    print(f"NBT scoring: {args.rays_per_face} rays/face x 5 faces, median of {args.repeats} after a warm-up, "
          f"threads {args.threads}; TIQF {cfg.pairing} pairing, rho {cfg.rho}; target {args.target_ms:g} ms")
    header = (f"{'object':15s} {'K':>3s} {'N hit':>5s} {'mode':9s} {'select ms':>10s} {'gains ms':>9s} "
              f"{'rays ms':>8s} {'target':>7s} {'spearman':>9s} {'a* rank':>8s}")
    print(header)
    print("-" * len(header))
    summary = {}
    for name in args.objects:
        obj = objects.load(name)
        V, Fc = obj.mesh.vertices, obj.mesh.faces
        lo, hi = obj.bounds[0].double(), obj.bounds[1].double()
        model = obj.sample_surface(args.model_points, seed=1).double()
        for k in args.touches:
            g = torch.Generator().manual_seed(args.seed * 1009 + k)
            T_true = make_pose(axis_angle_to_matrix(torch.tensor([0.0, 0.0, 2 * math.pi * float(torch.rand((), generator=g))],
                                                                 dtype=F64)), torch.tensor([0.5, 0.0, 0.0], dtype=F64))
            T_init = make_pose(axis_angle_to_matrix(unit(g) * math.radians(args.init_deg)) @ T_true[:3, :3],
                               T_true[:3, 3] + unit(g) * args.init_mm / 1000)
            _, touched = random_touches(V, Fc, T_true, lo, hi, NBTConfig(), g, n=k)
            _, state, _ = register(model, touched, T_init, cfg)
            cands = touch_candidates(state.pose, lo, hi, NBTConfig(rays_per_face=args.rays_per_face), g)
            hit, pts, _ = ray_mesh_intersect(V, Fc, state.pose, cands.starts, cands.directions)
            pts = pts[hit]
            rays_ms, _ = _median_ms(lambda: ray_mesh_intersect(V, Fc, state.pose, cands.starts, cands.directions),
                                 args.repeats)
            picks, gains = {}, {}
            for mode in args.modes:
                sel_ms, (picks[mode], gains[mode]) = _median_ms(
                    lambda: select_next_best_touch(model, V, Fc, state, touched, cands, cfg, prediction=mode),
                    args.repeats)
                gain_ms = math.nan  # the register path is the select time less the rays: not timed again
                if mode == "kalman":
                    gain_ms, _ = _median_ms(lambda: expected_information_gain(model, state, touched, pts, cfg),
                                            args.repeats)
                summary[(name, k, mode)] = dict(select_ms=sel_ms, gains_ms=gain_ms, rays_ms=rays_ms,
                                                n_hit=int(hit.sum()), n=len(cands))
            for mode in args.modes:
                s = summary[(name, k, mode)]
                agree = ""
                if mode != "register" and "register" in gains:
                    h = torch.isfinite(gains[mode])
                    rho = spearmanr(gains[mode][h].numpy(), gains["register"][h].numpy()).correlation
                    rank = 1 + int((gains["register"] > gains["register"][picks[mode]]).sum())
                    agree = f"{rho:9.3f} {rank:8d}"
                    s.update(spearman=rho, choice_rank_in_register=rank)
                ok = "met" if s["select_ms"] <= args.target_ms else "MISSED"
                gtxt = "-" if math.isnan(s["gains_ms"]) else f"{s['gains_ms']:.2f}"
                print(f"{name:15s} {k:3d} {s['n_hit']:5d} {mode:9s} {s['select_ms']:10.2f} {gtxt:>9s} "
                      f"{s['rays_ms']:8.2f} {ok:>7s} {agree}")
    return summary


if __name__ == "__main__":
    main()

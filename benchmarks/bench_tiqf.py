"""Benchmark of TIQF (visuo-tactile clutter paper, Sec. II-C) against Open3D point-to-point ICP.

Both methods get the same model cloud (object-frame surface samples), the same scene clouds and the same
initial poses (random true pose, initial error ``--init-deg`` deg and ``--init-cm`` cm), and both find
correspondences from every scene point to its nearest model point, so neither sees more than the other:

* ``dense``: a 1,000-point view: surface samples whose normals face a random camera direction (back-face
  culling; self-occlusion is ignored, which costs realism on the mug's handle only).
* ``tactile-K``: K = 5, 10, 15 exact surface points from all around the object, from the same initial errors.
  ``TIQF+R`` (beyond the paper, what the clutter estimator does with touches): ``register_restarts`` from the
  same initial pose, restarted when the touches lie more than 1 mm (mean) from the mesh, from 54 starts around the
  initial pose (turned about the world vertical in 60 deg steps, shifted by +-3 cm) and 3 x 30 around the best.
  ``TIQF+RS``: ``TIQF+R``, then the pose polished on the exact mesh (``belief.surface_fit.refine_on_surface``; the
  estimator does so from 7 touches on, here on every K).
* ``visual+tactile-K``: the paper's use (Sec. II-D, "correct and verify"): the dense view comes from a camera
  with a calibration error (``--calib-deg``, ``--calib-mm``), and K exact tactile points refine that visual
  estimate. TIQF continues from its visual posterior (``register(..., init=state)``); ICP from its own
  visual pose; ``TIQF+RS`` as the clutter estimator: the touches alone from the visual posterior, restarted around
  the initial pose (the task's prior) when they fit badly, then polished on the mesh.

Open3D's ``registration_icp`` aligns the scene (source) to the model cloud (target) from the inverse of the
initial pose (so its correspondences are scene -> model like TIQF's), with ``TransformationEstimationPointToPoint``,
``--icp-max-dist`` (default 1 m: every correspondence kept, as TIQF keeps them) and up to 100 iterations.
Reported per method and cloud: success rate (ADI < 1 cm, TIQF Eq. 28 via ``experiments.metrics.adi``),
median final ADI and median wall and process-CPU time per registration (model KD-tree build included for
both; on a loaded shared machine the CPU time is the steadier number).

Usage: ``python benchmarks/bench_tiqf.py [--trials 10] [--objects mug drill cracker_box] [--threads 1]
[--pairing centroid|random] [--iteration-prior call|previous] [--tol-scale 1]``.
"""
from __future__ import annotations

import argparse
import math
import os
import statistics
import time


def _parse(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--trials", type=int, default=10, help="random poses per object and cloud")
    ap.add_argument("--objects", nargs="*", default=None, help="object names (default: all in the registry)")
    ap.add_argument("--points", type=int, default=1000, help="points of the dense view")
    ap.add_argument("--model-points", type=int, default=1000, help="model cloud size")
    ap.add_argument("--tactile", type=int, nargs="*", default=[5, 10, 15], help="tactile cloud sizes")
    ap.add_argument("--init-deg", type=float, nargs=2, default=[10.0, 20.0], help="initial rotation error range")
    ap.add_argument("--init-cm", type=float, nargs=2, default=[2.0, 3.0], help="initial translation error range")
    ap.add_argument("--calib-deg", type=float, default=2.0, help="camera calibration rotation error (visual+tactile)")
    ap.add_argument("--calib-mm", type=float, default=6.0, help="camera calibration translation error")
    ap.add_argument("--icp-max-dist", type=float, default=1.0, help="Open3D ICP max correspondence distance (m)")
    ap.add_argument("--pairing", default=None, help="TIQFConfig.pairing (default: the config default)")
    ap.add_argument("--iteration-prior", default=None, help="TIQFConfig.iteration_prior")
    ap.add_argument("--tol-scale", type=float, default=None, help="scale the paper's 0.1 mm / 0.1 deg convergence test")
    ap.add_argument("--threads", type=int, default=1, help="torch and OpenMP threads")
    ap.add_argument("--seed", type=int, default=0)
    return ap.parse_args(argv)


def main(argv=None) -> dict:
    args = _parse(argv)
    os.environ.setdefault("OMP_NUM_THREADS", str(args.threads))  # before open3d / torch start their pools
    import numpy as np
    import open3d as o3d
    import torch

    from activetouch import objects
    from activetouch.belief.surface_fit import refine_on_surface, surface_residual
    from activetouch.belief.tiqf import TIQFConfig, register, register_restarts, yaw_shift_starts
    from activetouch.experiments.metrics import adi
    from activetouch.geometry import axis_angle_to_matrix, invert, make_pose, transform_points

    torch.set_num_threads(args.threads)
    overrides = {k: v for k, v in (("pairing", args.pairing), ("iteration_prior", args.iteration_prior)) if v}
    if args.tol_scale is not None:
        overrides.update(tol_translation=1e-4 * args.tol_scale, tol_rotation_deg=0.1 * args.tol_scale)
    cfg = TIQFConfig(**overrides)
    o3d.utility.set_verbosity_level(o3d.utility.VerbosityLevel.Error)
    reg = o3d.pipelines.registration
    icp_crit = reg.ICPConvergenceCriteria(relative_fitness=1e-7, relative_rmse=1e-7, max_iteration=100)

    def unit(g):
        v = torch.randn(3, generator=g, dtype=torch.float64)
        return v / v.norm()

    def rot(g, deg):
        return axis_angle_to_matrix(unit(g) * math.radians(deg))

    def uniform(g, lo, hi):
        return lo + (hi - lo) * float(torch.rand((), generator=g))

    def timed(fn, *a):
        """(result, wall s, process CPU s) of one call."""
        t0, c0 = time.perf_counter(), time.process_time()
        out = fn(*a)
        return out, time.perf_counter() - t0, time.process_time() - c0

    def icp(model_pcd, scene, init):
        src = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(scene.double().numpy()))
        res = reg.registration_icp(src, model_pcd, args.icp_max_dist, invert(init).double().numpy(),
                                   reg.TransformationEstimationPointToPoint(), icp_crit)
        return invert(torch.tensor(np.asarray(res.transformation)))

    def tiqf(scene, init):
        pose, state, info = register(model, scene, init, cfg)
        iters.append(info["iterations"])
        return pose, state

    def tiqf_restarts(obj, scene, init, prior=None):
        """Restarts around ``prior`` (default: ``init``), scored by the scene's mean distance to the mesh as the
        estimator scores them."""
        starts = yaw_shift_starts(init if prior is None else prior, 6, 0.03)
        pose, state, info = register_restarts(model, scene, init, starts, cfg,
                                              residual=lambda P: surface_residual(obj.sdf, scene, P))
        return pose, state

    def tiqf_restarts_fit(obj, scene, init, prior):
        pose, state = tiqf_restarts(obj, scene, init, prior)
        return refine_on_surface(obj.sdf, scene, pose).pose, state

    def view(obj, T, n, g):
        """n surface points facing a random camera direction (world frame), back-face culled."""
        import trimesh

        pts, face = trimesh.sample.sample_surface(obj.mesh, 6 * n, seed=int(torch.randint(0, 2**31, (), generator=g)))
        normals = torch.as_tensor(obj.mesh.face_normals[face])
        cam_dir = unit(g)  # world direction towards the camera
        facing = (normals @ T[:3, :3].T.double()) @ cam_dir > 0.1
        pts = torch.as_tensor(pts)[facing][:n]
        return transform_points(T.double(), pts)

    names = args.objects or ["mug", "drill", "cracker_box"]  # the README's numbers; --objects for others
    clouds = ["dense"] + [f"tactile-{k}" for k in args.tactile] + [f"visual+tactile-{k}" for k in args.tactile]
    rows = {}  # (object, cloud, method) -> list of (adi, wall s, cpu s)
    iters, dense_iters = [], []
    for name in names:
        obj = objects.load(name)
        model = obj.sample_surface(args.model_points, seed=1).double()
        model_pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(model.numpy()))
        for trial in range(args.trials):
            g = torch.Generator().manual_seed(args.seed * 100003 + trial)
            T = make_pose(rot(g, uniform(g, 0, 180)), torch.tensor([0.5, 0.0, 0.1], dtype=torch.float64))
            init = make_pose(rot(g, uniform(g, *args.init_deg)) @ T[:3, :3],
                             T[:3, 3] + unit(g) * uniform(g, *args.init_cm) / 100)
            dense = view(obj, T, args.points, g)
            calib = make_pose(rot(g, args.calib_deg), unit(g) * args.calib_mm / 1000)
            dense_biased = transform_points(calib, dense)
            touches = {k: transform_points(T, obj.sample_surface(k, seed=1000 + 37 * trial + k).double())
                       for k in args.tactile}

            def record(cloud, method, result):
                (pose, *_), wall, cpu = result if method.startswith("TIQF") else ((result[0],), *result[1:])
                rows.setdefault((name, cloud, method), []).append((adi(obj, pose.float(), T.float()), wall, cpu))

            iters.clear()
            record("dense", "TIQF", timed(tiqf, dense, init))
            dense_iters.extend(iters)
            record("dense", "ICP", timed(icp, model_pcd, dense, init))
            (pv, state_v), *_ = timed(tiqf, dense_biased, init)
            pv_icp = icp(model_pcd, dense_biased, init)
            record("visual only (biased)", "TIQF", ((pv, state_v), 0.0, 0.0))
            record("visual only (biased)", "ICP", (pv_icp, 0.0, 0.0))
            for k, tp in touches.items():
                record(f"tactile-{k}", "TIQF", timed(tiqf, tp, init))
                record(f"tactile-{k}", "ICP", timed(icp, model_pcd, tp, init))
                record(f"tactile-{k}", "TIQF+R", timed(tiqf_restarts, obj, tp, init))
                record(f"tactile-{k}", "TIQF+RS", timed(tiqf_restarts_fit, obj, tp, init, init))
                record(f"visual+tactile-{k}", "TIQF+RS", timed(tiqf_restarts_fit, obj, tp, state_v, init))
                record(f"visual+tactile-{k}", "TIQF", timed(tiqf, tp, state_v))
                record(f"visual+tactile-{k}", "ICP", timed(icp, model_pcd, tp, pv_icp))

    print(f"TIQF {cfg}\nOpen3D {o3d.__version__} ICP point-to-point, max_dist {args.icp_max_dist} m; "
          f"{args.trials} trials/object, init error {args.init_deg} deg, {args.init_cm} cm; threads {args.threads}")
    print(f"TIQF iterations on the dense view: median {statistics.median(dense_iters)}, max {max(dense_iters)}")
    header = (f"{'object':12s} {'cloud':24s} {'method':7s} {'success':>8s} {'med ADI mm':>10s} {'wall ms':>8s} "
              f"{'cpu ms':>8s}")
    print(header)
    print("-" * len(header))
    summary = {}
    for cloud in clouds[:1] + ["visual only (biased)"] + clouds[1:]:
        for name in names + ["ALL"]:
            for method in ("TIQF", "ICP", "TIQF+R", "TIQF+RS"):
                vals = (sum((rows.get((n, cloud, method), []) for n in names), []) if name == "ALL"
                        else rows.get((name, cloud, method), []))
                if not vals:
                    continue
                a = [v[0] for v in vals]
                wall = statistics.median(v[1] for v in vals) * 1000
                cpu = statistics.median(v[2] for v in vals) * 1000
                succ = sum(x < 0.01 for x in a) / len(a)
                summary[(name, cloud, method)] = (succ, statistics.median(a), wall, cpu)
                ms_txt = f"{wall:8.2f} {cpu:8.2f}" if wall > 0 else f"{'-':>8s} {'-':>8s}"
                print(f"{name:12s} {cloud:24s} {method:7s} {succ:8.0%} {statistics.median(a) * 1000:10.2f} {ms_txt}")
        print()
    return summary


if __name__ == "__main__":
    main()

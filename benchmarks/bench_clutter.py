"""Timings of the visuo-tactile clutter pipeline (``activetouch.sim.clutter_env``, ``planning.clutter``).

Usage: ``.venv/bin/python benchmarks/bench_clutter.py [--task clutter-mustard] [--seed 0] [--repeats 5]``

Measures (median wall time over ``--repeats``, and CPU time):
- the environment: ``reset`` (dropping a pile), a ``ViewAction`` (ray-cast segmented depth image), a guarded
  ``TouchAction``, the declutter decision (``plan_declutter``: Eq. 1-2 on the view);
- next best view: scoring ``--views`` (default 50, the paper's N is not given) candidate views on the occupancy grid
  of the target region after one integrated view (Eq. 23-24), with the environment's camera (96 x 72 rays each);
  the issue's target is <= 1 s;
- one TIQF registration of the segmented target cloud of a view.
"""
from __future__ import annotations

import argparse
import math

import numpy as np
import torch


from activetouch.experiments.timing import timed  # noqa: E402  (median wall / CPU seconds)


def main(argv=None) -> int:
    from activetouch.belief.tiqf import register
    from activetouch.information.occupancy import OccupancyConfig, OccupancyGrid
    from activetouch.planning.declutter import DeclutterConfig, SegmentedView, plan_declutter
    from activetouch.planning.nbv import NBVConfig, cameras_for, hemisphere_views, select_next_best_view
    from activetouch.sim.clutter_env import TouchAction, ViewAction
    from activetouch.sim.clutter_tasks import make_clutter_env

    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--task", default="clutter-mustard")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--repeats", type=int, default=5)
    p.add_argument("--views", type=int, default=50)
    a = p.parse_args(argv)
    torch.manual_seed(a.seed)
    env = make_clutter_env(a.task)
    rows = []
    w, c, _ = timed(lambda: env.reset(a.seed), a.repeats)
    rows.append(("reset (drop a pile of %d objects)" % (len(env.names) - 1), w, c))
    T = env.true_pose()
    ctr = T[:3, 3] + np.array([0.0, 0.0, 0.1])
    el = math.radians(70)
    view = ViewAction(tuple(ctr + 0.55 * np.array([-math.cos(el), 0.0, math.sin(el)])), tuple(ctr))
    w, c, (obs, *_) = timed(lambda: env.step(view), a.repeats)
    rows.append(("view (%dx%d rays, segmentation)" % (env.spec.camera_width, env.spec.camera_height), w, c))
    cfg = DeclutterConfig.for_gripper(env.gripper)
    sv = SegmentedView(obs.seg, obs.cloud, np.asarray(obs.camera.pos))
    w, c, _ = timed(lambda: plan_declutter(sv, 0, cfg), a.repeats)
    rows.append(("declutter decision (Eq. 1-2)", w, c))
    model = env.object.sample_surface(2000, seed=0).double()
    if len(obs.points) >= 3:
        w, c, _ = timed(lambda: register(model, torch.as_tensor(obs.points), torch.as_tensor(T)), a.repeats)
        rows.append((f"TIQF registration of the view's {len(obs.points)} target points", w, c))
    # next best view on the target region's grid after this view
    r = float(np.linalg.norm(env.object.bounds[1].numpy() - env.object.bounds[0].numpy()) / 2) + 0.08
    c0 = T[:3, :3] @ ((env.object.bounds[0].numpy() + env.object.bounds[1].numpy()) / 2) + T[:3, 3]
    grid = OccupancyGrid(torch.as_tensor(c0 - r), torch.as_tensor(c0 + r), OccupancyConfig(max_range=1.5))
    pts = obs.cloud.reshape(-1, 3)
    hit = np.isfinite(pts).all(1)
    dirs = obs.camera.ray_directions()
    grid.integrate(torch.as_tensor(obs.camera.pos), torch.as_tensor(np.where(hit[:, None], pts,
                                                                             np.asarray(obs.camera.pos) + 1.5 * dirs)),
                   torch.as_tensor(hit))
    nbv = NBVConfig(num_views=a.views, radius=env.spec.view_radius, width=env.spec.camera_width,
                    height=env.spec.camera_height, fov_y_deg=env.spec.camera_fov_y_deg)
    pos, R = hemisphere_views(torch.as_tensor(c0), nbv, torch.Generator().manual_seed(a.seed))
    cams = cameras_for(pos, R, nbv)
    H, W = env.spec.camera_height, env.spec.camera_width
    for k in (1, 3):  # every ray, and the planner's default stride (ClutterPlannerConfig.nbv_ray_stride)
        rays = torch.as_tensor(np.stack([cm.ray_directions().reshape(H, W, 3)[::k, ::k].reshape(-1, 3)
                                         for cm in cams]), dtype=grid.dtype)
        w, c, _ = timed(lambda: select_next_best_view(grid, pos.to(grid.dtype), rays, 1.5), a.repeats)
        rows.append((f"NBV: score {a.views} views x {rays.shape[1]} rays (target <= 1 s)", w, c))
    # a guarded touch from the -x side of the estimate
    lo, hi = (b.numpy() for b in env.object.bounds)
    start = T[:3, :3] @ np.array([lo[0] - 0.05, (lo[1] + hi[1]) / 2, 0.1]) + T[:3, 3]
    d = T[:3, 0] / np.linalg.norm(T[:3, 0])
    w, c, _ = timed(lambda: env.step(TouchAction(tuple(start), tuple(d), 0.15)), 1)
    rows.append(("guarded touch (approach, touch, retreat)", w, c))
    print(f"{a.task} seed {a.seed}, torch threads {torch.get_num_threads()}")
    print(f"| {'what':60s} | wall s | cpu s |")
    print(f"|{'-' * 62}|--------|-------|")
    for name, w, c in rows:
        print(f"| {name:60s} | {w:6.3f} | {c:5.2f} |")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

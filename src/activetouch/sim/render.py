"""Headless pictures of a ``RummageEnv`` state (matplotlib, no OpenGL).

A top view (x-y) and a side view (x-z) with the table, the shelf walls, the workspace, the object
(its exact mesh's triangles projected), the gripper pads and palm, the arm's joint chain, the
camera with its view frustum and, optionally, observed features (free orange, surface blue, as in
RUMI Fig. 11).
"""
from __future__ import annotations

import pathlib

import numpy as np

from .robot import GRIPPER
from .scene import SceneLayout

__all__ = ["render_env"]


def _box_corners(centre, half) -> np.ndarray:
    c, h = np.asarray(centre), np.asarray(half)
    s = np.array([[sx, sy, sz] for sx in (-1, 1) for sy in (-1, 1) for sz in (-1, 1)], float)
    return c + s * h


def _draw_box(ax, corners_world: np.ndarray, dims: tuple[int, int], **kw):
    from scipy.spatial import ConvexHull

    p = corners_world[:, dims]
    hull = ConvexHull(p)
    ax.fill(p[hull.vertices, 0], p[hull.vertices, 1], **kw)


def render_env(env, path, features=None, title: str | None = None, max_features: int = 20000) -> pathlib.Path:
    """Save a top + side view of ``env``'s current state to ``path`` (PNG); returns the path.

    Args:
        features: optional ``Features`` (e.g. ``obs.features``) drawn over the scene.
    """
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    from matplotlib.collections import PolyCollection

    spec = env.spec
    L = SceneLayout()
    T = env.true_pose()
    verts = np.asarray(env.object.mesh.vertices) @ T[:3, :3].T + T[:3, 3]
    faces = np.asarray(env.object.mesh.faces)
    E = env.ee_pose()
    d, m = env.data, env.model
    fig, axes = plt.subplots(1, 2, figsize=(13, 5.6), gridspec_kw={"width_ratios": [1.0, 1.25]})
    views = [(axes[0], (0, 1), "top view (x-y)"), (axes[1], (0, 2), "side view (x-z)")]
    lo, up = spec.workspace
    cam = spec.camera
    for ax, dims, name in views:
        i, j = dims
        if j == 1:
            ax.add_patch(plt.Rectangle((L.table_lower[0], L.table_lower[1]), L.table_upper[0] - L.table_lower[0],
                                       L.table_upper[1] - L.table_lower[1], color="#e8dcc4", zorder=0))
            for s in (1, -1):
                ax.add_patch(plt.Rectangle((L.wall_x_start, s * L.wall_y - (L.wall_thickness if s < 0 else 0)),
                                           L.back_wall_x - L.wall_x_start, L.wall_thickness, color="#8c7b5e"))
            ax.add_patch(plt.Rectangle((L.back_wall_x, -L.wall_y - L.wall_thickness), L.wall_thickness,
                                       2 * (L.wall_y + L.wall_thickness), color="#8c7b5e"))
        else:
            ax.add_patch(plt.Rectangle((L.table_lower[0], -0.05), L.table_upper[0] - L.table_lower[0], 0.05,
                                       color="#e8dcc4", zorder=0))
            ax.add_patch(plt.Rectangle((L.back_wall_x, 0), L.wall_thickness, L.wall_height, color="#8c7b5e"))
        ax.add_patch(plt.Rectangle((lo[i], lo[j]), up[i] - lo[i], up[j] - lo[j], fill=False, ls="--", ec="k",
                                   lw=1, label="workspace"))
        # object
        tri = verts[faces][:, :, [i, j]]
        ax.add_collection(PolyCollection(tri[::2], facecolors="#3a6fd8", edgecolors="none", alpha=0.35, zorder=2))
        # arm chain
        chain = [d.xpos[b] for b in range(m.nbody) if m.body(b).name.startswith(("lbr_iiwa_link", "gripper"))]
        chain = np.array([m.body("iiwa_base").pos] + chain) if len(chain) else np.zeros((0, 3))
        ax.plot(chain[:, i], chain[:, j], "-o", color="#555", lw=3, ms=4, zorder=3, label="arm")
        # gripper
        for c in GRIPPER.pad_centres:
            _draw_box(ax, _box_corners(c, GRIPPER.pad_half) @ E[:3, :3].T + E[:3, 3], dims, color="#d84a3a",
                      zorder=4)
        _draw_box(ax, _box_corners(GRIPPER.palm_centre, GRIPPER.palm_half) @ E[:3, :3].T + E[:3, 3], dims,
                  color="#444", zorder=4)
        # camera and frustum (rays of the image corners, 1.2 m long or to the table)
        K = cam.intrinsics()
        R = cam.rotation()
        ax.plot([cam.pos[i]], [cam.pos[j]], "k^", ms=9, zorder=5, label="camera")
        for u, v in ((0, 0), (cam.width - 1, 0), (0, cam.height - 1), (cam.width - 1, cam.height - 1)):
            ray = R @ np.linalg.solve(K, np.array([u, v, 1.0]))
            ray /= np.linalg.norm(ray)
            t = 1.2
            if ray[2] < -1e-6:
                t = min(t, -cam.pos[2] / ray[2])
            end = np.asarray(cam.pos) + t * ray
            ax.plot([cam.pos[i], end[i]], [cam.pos[j], end[j]], "k:", lw=0.8, zorder=5)
        if features is not None and len(features) > 0:
            pos = features.positions.detach().cpu().numpy()
            sem = features.semantics.detach().cpu().numpy()
            free = pos[sem == 1]
            if len(free) > max_features:
                free = free[np.random.default_rng(0).choice(len(free), max_features, replace=False)]
            ax.scatter(free[:, i], free[:, j], s=0.3, c="#f39c12", alpha=0.25, zorder=1, label="free")
            surf = pos[sem == 0]
            ax.scatter(surf[:, i], surf[:, j], s=3, c="#1f3fbf", zorder=6, label="surface")
        ax.set_aspect("equal")
        ax.set_title(name)
        ax.set_xlabel("xyz"[i] + " (m)")
        ax.set_ylabel("xyz"[j] + " (m)")
        if j == 1:
            ax.set_xlim(-0.45, 1.1)
            ax.set_ylim(-0.6, 0.6)
        else:
            ax.set_xlim(-0.45, 1.1)
            ax.set_ylim(-0.06, 1.35)
    axes[0].legend(loc="lower left", fontsize=7)
    fig.suptitle(title or f"{spec.name} step {env._step}")
    path = pathlib.Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=100, bbox_inches="tight")
    plt.close(fig)
    return path

"""Figures like the RUMI paper's: belief particles coloured by weight (Fig. 6), the information field as a
top-down heat map with particles and observed points (Fig. 4), NLL / APC curves (Fig. 13, 16).

Everything is drawn top-down (world x right, world y up) with matplotlib's Agg backend: no display needed.
"""
from __future__ import annotations

from pathlib import Path
from typing import Sequence

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt  # noqa: E402
import numpy as np  # noqa: E402
import torch  # noqa: E402

from activetouch.geometry.transforms import transform_points  # noqa: E402

# Semantics values (activetouch.observations.Semantics): SURFACE=0, FREE=1, OCCUPIED=2
_SEM_STYLE = {1: ("free", "#f39c12", 2.0, 0.25), 0: ("surface", "#d62728", 6.0, 0.9), 2: ("occupied", "#7f3c8d", 6.0, 0.9)}


def _np(x) -> np.ndarray:
    return x.detach().cpu().numpy() if isinstance(x, torch.Tensor) else np.asarray(x)


def draw_field(ax, grid, values, *, cmap="Greys", label="information gain", reduce="max", alpha=0.9):
    """Draw a workspace field top-down.

    Args:
        grid: :class:`activetouch.geometry.voxel.VoxelGrid` of the field.
        values: ``(nx, ny, nz)`` field values on the grid's cell centres.
        reduce: how to collapse z, ``"max"`` or ``"mean"``.
    """
    v = _np(values)
    if v.ndim == 3:
        v = v.max(axis=2) if reduce == "max" else v.mean(axis=2)
    lo, hi = _np(grid.lower), _np(grid.upper)
    im = ax.imshow(v.T, origin="lower", extent=(lo[0], hi[0], lo[1], hi[1]), cmap=cmap, alpha=alpha,
                   interpolation="nearest", aspect="equal")
    cb = ax.figure.colorbar(im, ax=ax, fraction=0.046, pad=0.02)
    cb.set_label(label)
    return im


def draw_features(ax, features, *, max_free: int = 4000):
    """Scatter observed geometric features top-down: free (orange), surface (red), occupied (purple)."""
    if features is None or len(features) == 0:
        return
    pos, sem = _np(features.positions), _np(features.semantics)
    for value, (name, color, size, alpha) in _SEM_STYLE.items():
        sel = pos[sem == value]
        if value == 1 and len(sel) > max_free:  # thin free space for legibility only
            sel = sel[np.linspace(0, len(sel) - 1, max_free).astype(int)]
        if len(sel):
            ax.scatter(sel[:, 0], sel[:, 1], s=size, c=color, alpha=alpha, label=f"{name} ({len(sel)})",
                       linewidths=0, zorder=3)


def _footprint(obj, n: int) -> torch.Tensor:
    """``(n, 3)`` object-frame surface points in a 1 cm band at mid height: a clean outline per particle
    (body ring + handle for the mug) instead of a cloud of the whole surface."""
    pts = obj.sample_surface(40 * n, seed=1)
    lo, hi = (torch.as_tensor(b, dtype=pts.dtype) for b in obj.bounds)
    band = pts[(pts[:, 2] - (lo[2] + hi[2]) / 2).abs() < 0.005]
    if len(band) < n:
        return pts[:n]
    return band[torch.linspace(0, len(band) - 1, n).long()]


def draw_particles(ax, obj, poses, weights, *, n_points: int = 150, true_pose=None, max_particles: int = 100,
                   cmap="viridis"):
    """Draw pose particles as object surface footprints coloured by weight (RUMI Fig. 6).

    Args:
        poses: ``(P, 4, 4)`` object->world particle poses.
        weights: ``(P,)`` normalised weights.
        true_pose: optional ``(4, 4)`` ground truth, drawn as a black outline.
    """
    poses, weights = torch.as_tensor(poses), torch.as_tensor(weights)
    pts = _footprint(obj, n_points).to(poses)
    order = torch.argsort(weights)  # heaviest drawn last (on top)
    if len(order) > max_particles:
        order = order[-max_particles:]
    world = _np(transform_points(poses[order], pts))  # (P', n, 3)
    w = _np(weights[order])
    wmax = max(float(w.max()), 1e-12)
    cm = plt.get_cmap(cmap)
    for k in range(len(order)):
        ax.scatter(world[k, :, 0], world[k, :, 1], s=1.5, color=cm(w[k] / wmax), alpha=0.6, linewidths=0, zorder=2)
    sm = plt.cm.ScalarMappable(cmap=cmap, norm=plt.Normalize(0, wmax))
    cb = ax.figure.colorbar(sm, ax=ax, orientation="horizontal", fraction=0.046, pad=0.12)
    cb.set_label("particle weight")
    if true_pose is not None:
        tw = _np(transform_points(torch.as_tensor(true_pose).to(pts), pts))
        ax.scatter(tw[:, 0], tw[:, 1], s=2, c="k", alpha=0.8, linewidths=0, label="true pose", zorder=4)


def _view(panel: dict, zoom: float) -> tuple[tuple[float, float], float]:
    """Square view holding the weighted particle mean and the true pose (if given) with ``zoom`` m margin."""
    w = torch.as_tensor(panel["weights"]).double()
    mean = (torch.as_tensor(panel["poses"]).double()[:, :2, 3] * w[:, None]).sum(0) / w.sum()
    pts = [mean.numpy()]
    if panel.get("true_pose") is not None:
        pts.append(_np(panel["true_pose"])[:2, 3])
    pts = np.stack(pts)
    lo, hi = pts.min(0), pts.max(0)
    return tuple((lo + hi) / 2), float((hi - lo).max() / 2 + zoom)


def belief_figure(path, obj, panels: Sequence[dict], *, title: str | None = None, zoom: float | None = 0.18):
    """Save a row of top-down belief panels.

    Each panel is a dict with keys ``poses``, ``weights`` and optionally ``features``, ``true_pose``,
    ``field`` = (grid, values), ``title``. The view holds the weighted particle mean and the true pose with a
    ``zoom`` metre margin.
    """
    n = len(panels)
    fig, axes = plt.subplots(1, n, figsize=(6.2 * n, 5.6), squeeze=False)
    for ax, p in zip(axes[0], panels):
        if p.get("field") is not None:
            draw_field(ax, *p["field"])
        draw_features(ax, p.get("features"))
        draw_particles(ax, obj, p["poses"], p["weights"], true_pose=p.get("true_pose"))
        if zoom:
            (cx, cy), half = _view(p, zoom)
            ax.set_xlim(cx - half, cx + half)
            ax.set_ylim(cy - half, cy + half)
        ax.set_aspect("equal")
        ax.set_xlabel("x (m)")
        ax.set_ylabel("y (m)")
        ax.set_title(p.get("title", ""))
        ax.legend(loc="lower left", fontsize=7, markerscale=3)
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=130)
    plt.close(fig)
    return Path(path)


def curves_figure(path, rows: Sequence[dict], *, nll_threshold: float | None = None, apc_threshold: float | None = None,
                  title: str | None = None):
    """Save NLL and APC against step (RUMI Fig. 13/16) from ``steps.csv`` rows (dicts with step, nll, apc), and the
    belief's weighted rotation error when the rows have ``mean_rot_err_deg`` (the mug's NLL barely sees the yaw)."""
    steps = [int(r["step"]) for r in rows]
    nll = [float(r["nll"]) for r in rows]
    apc = [float(r["apc"]) for r in rows]
    rot = [float(r["mean_rot_err_deg"]) for r in rows] if rows and "mean_rot_err_deg" in rows[0] else None
    fig, axes = plt.subplots(1, 3 if rot else 2, figsize=(16 if rot else 11, 4))
    a1, a2 = axes[0], axes[1]
    a1.plot(steps, nll, "-o", ms=3)
    if nll_threshold is not None:
        a1.axhline(nll_threshold, ls="--", c="g", label=f"success threshold {nll_threshold:g}")
        a1.legend()
    a1.set_yscale("log")
    a1.set_xlabel("step")
    a1.set_ylabel("nll (Eq. 36)")
    a2.plot(steps, apc, "-o", ms=3, c="tab:orange")
    if apc_threshold is not None:
        a2.axhline(apc_threshold, ls="--", c="g", label=f"termination {apc_threshold:.4f} m")
        a2.legend()
    a2.set_xlabel("step")
    a2.set_ylabel("APC (Eq. 33, m)")
    if rot:
        from .metrics import ROT_SUCCESS_DEG

        a3 = axes[2]
        a3.plot(steps, rot, "-o", ms=3, c="tab:purple")
        a3.axhline(ROT_SUCCESS_DEG, ls="--", c="g", label=f"strict success {ROT_SUCCESS_DEG:g} deg")
        a3.legend()
        a3.set_xlabel("step")
        a3.set_ylabel("weighted rotation error (deg)")
    if title:
        fig.suptitle(title)
    fig.tight_layout()
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=120)
    plt.close(fig)
    return Path(path)

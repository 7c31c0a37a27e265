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


#: Colours of the methods in :func:`nll_grid_figure` (fixed, so every figure of a report reads the same).
METHOD_COLORS = {"rumi": "#1f77b4", "info-only": "#ff7f0e", "reach-only": "#2ca02c", "gpvr": "#d62728",
                 "slide": "#9467bd"}


def panel_layout(tasks: Sequence[str]) -> tuple[list[str], list[int], dict[str, tuple[int, int]]]:
    """Grid of Fig. 16 for ``tasks`` named ``<object>-<configuration>``: rows the objects present (mug, drill, box
    first), columns the configurations present; returns ``(row objects, column configurations, {task: (i, j)})``."""
    from .tables import OBJECTS, configuration_of, object_of

    objs = sorted({object_of(t) for t in tasks}, key=lambda o: (OBJECTS.index(o) if o in OBJECTS else len(OBJECTS), o))
    confs = sorted({configuration_of(t) for t in tasks})
    return objs, confs, {t: (objs.index(object_of(t)), confs.index(configuration_of(t))) for t in tasks}


def nll_grid_figure(path, curves: dict[str, dict[str, dict]], *, thresholds: dict[str, float] | None = None,
                    log_y: bool = True, note: str | None = None, title: str | None = None,
                    labels: dict[str, str] | None = None, panel_size: tuple[float, float] = (4.2, 3.0),
                    dpi: int = 110):
    """Save RUMI Fig. 16: the NLL after each execution step, one panel per task (rows objects, columns
    configurations, :func:`panel_layout`), one line per method: the median over the seeds with the 25-75 %
    band shaded.

    Args:
        curves: ``{task: {method: {"step", "median", "q25", "q75" (arrays), "n" (seeds)}}}``.
        thresholds: Table III success threshold per task, drawn dashed.
        log_y: log-scale NLL axis.
        note: text under the grid (how the curves were made).
        labels: legend names of the methods.
    """
    from .tables import method_order

    labels = labels or {}
    tasks = [t for t in curves if curves[t]]
    if not tasks:
        raise ValueError("nll_grid_figure needs at least one task with curves")
    objs, confs, where = panel_layout(tasks)
    pw, ph = panel_size
    import math
    import textwrap

    n_entries = len({m for t in tasks for m in curves[t]}) + (1 if thresholds else 0)
    W = 0.9 + pw * len(confs)
    ncol = min(n_entries, max(1, int(W // 1.9)))
    legend_h = 0.28 * math.ceil(n_entries / ncol)
    note_lines = textwrap.wrap(note, max(40, int(W * 15))) if note else []
    top = 0.45 + legend_h + (0.3 if title else 0.0)
    bottom = 0.6 + 0.16 * len(note_lines)
    H = top + bottom + ph * len(objs)
    fig, axes = plt.subplots(len(objs), len(confs), figsize=(W, H), squeeze=False)
    fig.subplots_adjust(left=0.8 / W, right=1 - 0.15 / W, top=1 - top / H, bottom=bottom / H,
                        wspace=0.28, hspace=0.42)
    used = set(where.values())
    for i in range(len(objs)):
        for j in range(len(confs)):
            if (i, j) not in used:
                axes[i, j].axis("off")
    methods = method_order({m for t in tasks for m in curves[t]}, with_paper=False)
    handles = {}
    for t in tasks:
        ax = axes[where[t]]
        for m in methods:
            c = curves[t].get(m)
            if c is None:
                continue
            color = METHOD_COLORS.get(m, f"C{5 + methods.index(m) % 5}")
            x = np.asarray(c["step"])
            ax.fill_between(x, c["q25"], c["q75"], color=color, alpha=0.2, linewidth=0)
            (ln,) = ax.plot(x, c["median"], color=color, lw=1.6)
            handles.setdefault(m, ln)
        thr = (thresholds or {}).get(t)
        if thr is not None:
            h = ax.axhline(thr, color="0.35", ls="--", lw=1)
            handles.setdefault("_threshold", h)
        if log_y:
            from matplotlib import ticker

            ax.set_yscale("log")
            ax.yaxis.set_major_formatter(ticker.LogFormatter())  # plain numbers (40, 100), not 4 x 10^1
            ax.yaxis.set_minor_formatter(ticker.LogFormatter(labelOnlyBase=False, minor_thresholds=(1, 0.5)))
        ax.set_title(f"sim {objs[where[t][0]]} {confs[where[t][1]]}", fontsize=10)
        ax.grid(True, which="major", alpha=0.3)
        ax.tick_params(labelsize=8)
        if where[t][1] == 0 or (where[t][0], 0) not in used:
            ax.set_ylabel("nll(X)" + (" (log)" if log_y else ""), fontsize=9)
        if where[t][0] == len(objs) - 1 or (where[t][0] + 1, where[t][1]) not in used:
            ax.set_xlabel("execution step", fontsize=9)
    names = [labels.get(m, m) + "" for m in methods if m in handles]
    hs = [handles[m] for m in methods if m in handles]
    if "_threshold" in handles:
        hs.append(handles["_threshold"])
        names.append("Table III success threshold")
    fig.legend(hs, names, loc="upper center", ncol=ncol, frameon=False, fontsize=9,
               bbox_to_anchor=(0.5, 1 - (0.3 if title else 0.05) / H))
    if title:
        fig.suptitle(title, y=1 - 0.05 / H, va="top", fontsize=11)
    if note_lines:
        fig.text(0.5, 0.1 / H, "\n".join(note_lines), ha="center", va="bottom", fontsize=8, color="0.25")
    Path(path).parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)

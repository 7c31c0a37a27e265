"""Figures of the visuo-tactile clutter episodes (visuo-tactile paper Fig. 6: error over the acquisitions)."""
from __future__ import annotations

from pathlib import Path

import numpy as np

#: Colours of the action kinds (background bands of the error curves).
ACTION_COLOURS = {"view": "#cfe2f3", "touch": "#f4cccc", "push": "#fff2cc", "pick": "#d9ead3", "stop": "#eeeeee"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _posed(points: np.ndarray, T: np.ndarray) -> np.ndarray:
    return points @ T[:3, :3].T + T[:3, 3]


def tiqf_figure(path: Path, env, belief, rows: list[dict], title: str = "") -> Path:
    """Three panels: the scene from above (every object's true pose as grey model points, the target's true pose
    in black, the TIQF estimate in orange, visual points blue, tactile points red), the same from the side, and
    ADI (Eq. 28) and translation error (Eq. 26) after every action, on bands coloured by the action's kind (Fig. 6)."""
    from activetouch import objects

    plt = _plt()
    fig = plt.figure(figsize=(13, 4.2))
    ax_top = fig.add_subplot(1, 3, 1)
    ax_side = fig.add_subplot(1, 3, 2)
    ax_err = fig.add_subplot(1, 3, 3)
    poses = env.object_poses()
    model = belief.model_points.detach().cpu().numpy()
    true = poses[0]
    est = belief.pose.detach().cpu().numpy()
    for i in range(1, len(poses)):
        pts = objects.load(env.names[i]).sample_surface(400, seed=0).numpy()
        w = _posed(pts, poses[i])
        for ax, (a, b) in ((ax_top, (0, 1)), (ax_side, (0, 2))):
            ax.scatter(w[:, a], w[:, b], s=1, c="0.75")
    gt, es = _posed(model, true), _posed(model, est)
    vis = belief.visual.detach().cpu().numpy()
    tac = belief.tactile.detach().cpu().numpy()
    for ax, (a, b), lab in ((ax_top, (0, 1), ("x (m)", "y (m)")), (ax_side, (0, 2), ("x (m)", "z (m)"))):
        ax.scatter(gt[:, a], gt[:, b], s=1, c="k", label="target (truth)")
        ax.scatter(es[:, a], es[:, b], s=1, c="tab:orange", alpha=0.6, label="TIQF estimate")
        if len(vis):
            ax.scatter(vis[:, a], vis[:, b], s=3, c="tab:blue", label="visual points")
        if len(tac):
            ax.scatter(tac[:, a], tac[:, b], s=18, c="tab:red", marker="x", label="tactile points")
        c = true[:3, 3]
        ax.set_xlim(c[a] - 0.25, c[a] + 0.25)
        ax.set_ylim((c[b] - 0.25, c[b] + 0.25) if b != 2 else (-0.02, 0.35))
        ax.set_aspect("equal")
        ax.set_xlabel(lab[0])
        ax.set_ylabel(lab[1])
    ax_top.set_title("from above")
    ax_side.set_title("from the side")
    ax_top.legend(loc="upper left", fontsize=7, markerscale=3)
    steps = np.array([int(r["step"]) for r in rows])
    for r in rows[1:]:
        ax_err.axvspan(int(r["step"]) - 0.5, int(r["step"]) + 0.5, color=ACTION_COLOURS.get(r.get("action"), "white"),
                       lw=0)
    ax_err.plot(steps, [r["adi_mm"] for r in rows], "o-", c="k", ms=3, label="ADI (mm)")
    ax_err.plot(steps, [r["trans_err_mm"] for r in rows], "s--", c="tab:purple", ms=3, label="translation error (mm)")
    ax_err.set_yscale("log")
    ax_err.set_xlabel("action")
    ax_err.set_ylabel("error (mm)")
    handles = [plt.Rectangle((0, 0), 1, 1, color=c) for c in ACTION_COLOURS.values()]
    leg = ax_err.legend(loc="upper right", fontsize=7)
    ax_err.add_artist(leg)
    ax_err.legend(handles, list(ACTION_COLOURS), loc="lower left", fontsize=7, ncol=3)
    ax_err.set_title("error after each action (Fig. 6)")
    fig.suptitle(title)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)

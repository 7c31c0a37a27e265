"""Figures of the touch-only localisation episodes (touch paper Fig. 1 and the entropy terms of Alg. 1)."""
from __future__ import annotations

import math
from pathlib import Path

import numpy as np


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _footprint(obj, state) -> np.ndarray:
    """Closed outline ``(5, 2)`` of the object's x-y bounds at SE(2) ``state``."""
    lo, hi = (np.asarray(b, dtype=np.float64) for b in obj.bounds.numpy())
    c = np.array([[lo[0], lo[1]], [hi[0], lo[1]], [hi[0], hi[1]], [lo[0], hi[1]], [lo[0], lo[1]]])
    x, y, yaw = state
    R = np.array([[math.cos(yaw), -math.sin(yaw)], [math.sin(yaw), math.cos(yaw)]])
    return c @ R.T + np.array([x, y])


def particles_figure(path: Path, obj, history: list[dict], true_state, title: str = "", max_panels: int = 6) -> Path:
    """Like the paper's Fig. 1: the particles (position + heading arrow, coloured by weight) over the table at
    selected steps, the true box outline, the robot's ee path of the step's poke and its contacts (red)."""
    plt = _plt()
    n = len(history)
    idx = sorted(set(np.linspace(0, n - 1, min(n, max_panels)).round().astype(int).tolist()))
    fig, axes = plt.subplots(1, len(idx), figsize=(3.2 * len(idx), 3.6), squeeze=False)
    allxy = np.concatenate([h["states"][:, :2] for h in history] + [np.asarray(true_state)[None, :2]])
    lo, hi = allxy.min(0) - 0.12, allxy.max(0) + 0.12
    for ax, i in zip(axes[0], idx):
        h = history[i]
        s, w = h["states"], h["weights"]
        order = np.argsort(w)
        ax.quiver(s[order, 0], s[order, 1], np.cos(s[order, 2]), np.sin(s[order, 2]), w[order], cmap="viridis",
                  scale=25, width=0.006, clim=(0, max(float(w.max()), 1e-9)))
        fp = _footprint(obj, true_state)
        ax.plot(fp[:, 0], fp[:, 1], "k-", lw=1.5, label="true box")
        best = s[int(np.argmax(w))]
        fb = _footprint(obj, best)
        ax.plot(fb[:, 0], fb[:, 1], "--", color="tab:orange", lw=1.2, label="ML particle")
        if h.get("ee") is not None:
            ee = h["ee"]
            ax.plot(ee[:, 0], ee[:, 1], "-", color="tab:green", lw=1.2, label="ee path")
            z = h["z"]
            if z is not None and z.any():
                ax.plot(ee[1:][z, 0], ee[1:][z, 1], "o", color="red", ms=4, label="contact z = 1")
        ax.set_xlim(lo[0], hi[0])
        ax.set_ylim(lo[1], hi[1])
        ax.set_aspect("equal")
        ax.set_title(f"step {i}" if i else "prior", fontsize=9)
        ax.tick_params(labelsize=7)
    axes[0][0].legend(fontsize=6, loc="lower left")
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)


def entropy_figure(path: Path, rows: list[dict], title: str = "") -> Path:
    """The belief's entropy terms of Eq. 5 (weight entropy, log V(Omega)) and the chosen candidate's expected
    information gain (Alg. 1) and grasp probability against the step."""
    plt = _plt()
    steps = [r["step"] for r in rows]
    fig, (a1, a2) = plt.subplots(1, 2, figsize=(9, 3.4))
    for key, lab in (("weight_entropy", "H_w (weights)"), ("log_support_volume", "log V(Omega) (spatial)"),
                     ("entropy", "H = H_w + log V (Eq. 5)")):
        a1.plot(steps, [r.get(key, np.nan) for r in rows], marker="o", ms=3, label=lab)
    a1.set_xlabel("step")
    a1.set_ylabel("nats")
    a1.legend(fontsize=7)
    a1.set_title("belief entropy", fontsize=9)
    ig = [r.get("expected_ig", np.nan) for r in rows]
    a2.plot(steps, [np.nan if v == "" else v for v in ig], marker="o", ms=3, label="expected IG of the chosen poke")
    a2.plot(steps, [r.get("grasp_p", np.nan) for r in rows], marker="s", ms=3, label="P(grasp success) (App. D-d)")
    a2.axhline(0.8, color="grey", ls=":", lw=1)
    a2.set_xlabel("step")
    a2.legend(fontsize=7)
    a2.set_title("planning", fontsize=9)
    fig.suptitle(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return Path(path)

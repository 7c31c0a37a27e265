"""Figures of the visuo-tactile clutter episodes (visuo-tactile paper Fig. 6: error over the acquisitions)."""
from __future__ import annotations

from collections.abc import Mapping, Sequence
from pathlib import Path

import numpy as np

#: Colours of the action kinds (background bands of the error curves).
ACTION_COLOURS = {"view": "#cfe2f3", "touch": "#f4cccc", "push": "#fff2cc", "pick": "#d9ead3", "stop": "#eeeeee"}


def _plt():
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    return plt


def _save(fig, path, dpi: int = 110, tight: bool = True) -> Path:
    """Lay out (``tight_layout``), write and close a figure; returns ``Path(path)``."""
    plt = _plt()
    if tight:
        fig.tight_layout()
    fig.savefig(path, dpi=dpi)
    plt.close(fig)
    return Path(path)


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
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------------------
# Helpers shared by the figures below
# ----------------------------------------------------------------------------------------------------------------


def _np(x, dtype=float) -> np.ndarray:
    """``x`` (array-like or torch tensor on any device) as a numpy array."""
    if hasattr(x, "detach"):
        x = x.detach().cpu().numpy()
    return np.asarray(x, dtype=dtype)


def _check_seg(seg) -> np.ndarray:
    seg = np.asarray(seg)
    if seg.ndim != 2 or seg.size == 0 or not np.issubdtype(seg.dtype, np.integer):
        raise ValueError(f"seg must be a non-empty 2-D integer array (H, W), got shape {seg.shape} dtype {seg.dtype}")
    return seg


def _label_name(label: int, names) -> str:
    if names is not None and 0 <= int(label) < len(names):
        return str(names[int(label)])
    return f"object {int(label)}"


def _label_colours(labels) -> dict[int, tuple]:
    """A fixed colour per object label (tab10, then tab20's light colours, no greys or reds, cycled)."""
    import matplotlib

    tab10, tab20 = matplotlib.colormaps["tab10"], matplotlib.colormaps["tab20"]
    # the strong tab10 colours first, then tab20's light ones; no greys (the background) and no reds (the ring
    # that marks the next object)
    palette = [tab10(i) for i in range(10) if i not in (3, 7)]
    palette += [tab20(i) for i in range(1, 20, 2) if i not in (7, 15)]
    return {int(lab): palette[int(lab) % len(palette)] for lab in labels}


# ----------------------------------------------------------------------------------------------------------------
# Declutter graph over the segmentation (Fig. 3a)
# ----------------------------------------------------------------------------------------------------------------

_BACKGROUND_RGB = (0.82, 0.82, 0.82)


def _node_position(mask: np.ndarray) -> np.ndarray:
    """Where an object's node is drawn, pixel coordinates ``(u, v)``: the centroid of its mask, or, when the
    centroid falls outside the mask (a mask split by an occluder, a ring), the mask pixel furthest inside the mask
    (largest distance to its outside; ties: the one nearest to the centroid), so nodes of overlapping objects do
    not land on each other."""
    from scipy import ndimage

    rows, cols = np.nonzero(mask)
    c = np.array([cols.mean(), rows.mean()])
    r, q = int(round(c[1])), int(round(c[0]))
    if 0 <= r < mask.shape[0] and 0 <= q < mask.shape[1] and mask[r, q]:
        return c
    depth = ndimage.distance_transform_edt(np.pad(mask, 1))[1:-1, 1:-1][rows, cols]
    deep = np.flatnonzero(depth >= depth.max() - 1e-9)
    best = deep[np.argmin((cols[deep] - c[0]) ** 2 + (rows[deep] - c[1]) ** 2)]
    return np.array([float(cols[best]), float(rows[best])])


def _draw_declutter(ax, seg: np.ndarray, decision, names) -> None:
    """One panel: segmentation, minimum-area rectangles, declutter graph (nodes at mask centroids)."""
    from matplotlib.lines import Line2D

    from activetouch.planning.declutter import mask_contour, min_area_rectangle, object_labels

    H, W = seg.shape
    labels = object_labels(seg)
    colours = _label_colours(labels)
    img = np.empty((H, W, 3))
    img[:] = _BACKGROUND_RGB
    for lab in labels:
        img[seg == lab] = colours[lab][:3]
    ax.imshow(img, origin="upper", extent=(-0.5, W - 0.5, H - 0.5, -0.5), interpolation="nearest")
    centroids: dict[int, np.ndarray] = {}
    for lab in labels:
        mask = seg == lab
        centroids[lab] = _node_position(mask)
        crow, ccol = np.nonzero(mask_contour(mask))
        rect = min_area_rectangle(np.stack([ccol, crow], axis=1).astype(float), pad=0.5)
        corners = np.vstack([rect.corners(), rect.corners()[:1]])
        ax.plot(corners[:, 0], corners[:, 1], "-", c="k", lw=0.9, alpha=0.8)
    scale = max(H, W)
    ax.set_xlim(-0.5, W - 0.5)
    ax.set_ylim(H - 0.5, -0.5)
    ax.set_xticks([])
    ax.set_yticks([])
    graph = decision.graph if decision is not None else None
    in_graph = set(graph.nodes) if graph is not None else set()
    missing = sorted(k for k in in_graph if k not in centroids)
    if missing:
        raise ValueError(f"declutter graph nodes {missing} are not labels of seg {labels}")
    # objects outside G: their name only, in grey
    for lab in labels:
        if lab not in in_graph:
            ax.text(*centroids[lab], _label_name(lab, names), ha="center", va="center", fontsize=7, color="0.25",
                    bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="none", alpha=0.6))
    if graph is None:
        return
    roots = [k for k, d in graph.nodes(data=True) if d.get("root")]
    root = roots[0] if roots else next(iter(graph.nodes))
    nxt = decision.next_object
    for p, c, data in graph.edges(data=True):
        a, b = centroids[p], centroids[c]
        ax.annotate("", xy=b, xytext=a, arrowprops=dict(arrowstyle="-|>", color="k", lw=1.6, mutation_scale=14,
                                                         shrinkA=9, shrinkB=9))
        d = b - a
        n = np.array([-d[1], d[0]]) / max(float(np.hypot(*d)), 1e-9)
        if n[1] > 0:  # the label on the upper side of the edge (image rows grow downwards)
            n = -n
        # beside the edge's midpoint, so that short edges stay visible (display y = -image v)
        ax.annotate(f"e={data.get('weight', float('nan')):.2f}", 0.5 * (a + b), xytext=(10 * n[0], -10 * n[1]),
                    textcoords="offset points", ha="center", va="center", fontsize=7.5, zorder=8,
                    bbox=dict(boxstyle="round,pad=0.15", fc="#ffffcc", ec="0.4", lw=0.5))
    for k, data in graph.nodes(data=True):
        xy = centroids[k]
        if k == root:
            ax.scatter(*xy, s=260, marker="*", c="gold", edgecolors="k", linewidths=1.0, zorder=5)
            text = f"{_label_name(k, names)}\nTARGET"
        else:
            ax.scatter(*xy, s=70, marker="o", c="white", edgecolors="k", linewidths=1.0, zorder=5)
            q = data.get("quality")
            q_txt = f"q={q:.2f}" if q is not None and np.isfinite(q) else "q=?"
            text = f"{_label_name(k, names)}\n{data.get('action') or '?'} {q_txt}"
        if k == nxt:
            ax.scatter(*xy, s=420, marker="o", facecolors="none", edgecolors="red", linewidths=2.2, zorder=6)
            text += "\nNEXT"
        ax.text(xy[0], xy[1] + 0.035 * scale, text, ha="center", va="top", fontsize=7.5, zorder=7,
                bbox=dict(boxstyle="round,pad=0.2", fc="white", ec="red" if k == nxt else "0.5",
                          lw=1.2 if k == nxt else 0.5, alpha=0.9))
    handles = [Line2D([], [], marker="*", ls="", ms=13, mfc="gold", mec="k", label="target (root)"),
               Line2D([], [], marker="o", ls="", ms=7, mfc="white", mec="k", label="object in G"),
               Line2D([], [], marker="o", ls="", ms=13, mfc="none", mec="red", mew=2, label="next to remove"),
               Line2D([], [], c="k", lw=0.9, label="min-area rectangle")]
    ax.legend(handles=handles, loc="lower right", fontsize=6.5, framealpha=0.85)


def _decision_caption(decision, names) -> str:
    if decision is None:
        return "segmentation"
    if decision.next_object is None:
        return "target free: declutter done"
    return f"next: {_label_name(decision.next_object, names)} ({decision.action})"


def declutter_figure(path: Path, seg, decision=None, names: Sequence[str] | None = None, title: str = "") -> Path:
    """Fig. 3a: the segmentation ``seg (H, W)`` (each object label its colour, labels < 0 grey), each object's
    minimum-area rectangle (the ``C_i`` of Eq. 1), and the declutter graph G of ``decision`` (a
    ``DeclutterDecision``) drawn over it: nodes at the objects' mask centroids (pixel coordinates), arrows
    parent -> child labelled with ``e_ij`` (Eq. 1), node labels with the object's name (``names[label]``, else the
    label), its action (Eq. 2) and ``q_k``; the target (root) a gold star, the next object to remove ringed red.
    (A node whose mask centroid falls outside its mask, e.g. a target split by an occluder, is drawn at the mask
    pixel furthest inside the mask instead.) Objects outside G carry their name only. ``decision=None`` draws the
    segmentation and rectangles only.

    Raises:
        ValueError: ``seg`` is not a 2-D integer array, or a node of G is not a label of ``seg``.
    """
    seg = _check_seg(seg)
    plt = _plt()
    H, W = seg.shape
    w = 7.0
    fig, ax = plt.subplots(figsize=(w, max(3.0, min(10.0, w * H / W)) + 0.6))
    _draw_declutter(ax, seg, decision, names)
    ax.set_title(_decision_caption(decision, names), fontsize=10)
    if title:
        fig.suptitle(title)
    return _save(fig, path, dpi=120)


#: Most panels of :func:`declutter_sequence_figure`.
MAX_DECLUTTER_PANELS = 6


def declutter_sequence_figure(path: Path, items: Sequence, names: Sequence[str] | None = None,
                              title: str = "") -> Path:
    """:func:`declutter_figure` for several declutter decisions, one panel per ``(seg, decision)`` pair of
    ``items`` in order (at most :data:`MAX_DECLUTTER_PANELS` = 6 panels, 3 per row). With more than 6 items, 6
    evenly spaced ones are drawn, always the first and the last, and the panel titles give each one's index.

    Raises:
        ValueError: ``items`` is empty, an item is not a ``(seg, decision)`` pair, or a ``seg`` is invalid.
    """
    items = list(items)
    if not items:
        raise ValueError("items must hold at least one (seg, decision) pair")
    for i, it in enumerate(items):
        if not isinstance(it, (tuple, list)) or len(it) != 2:
            raise ValueError(f"items[{i}] must be a (seg, decision) pair, got {type(it).__name__}")
    segs = [_check_seg(s) for s, _ in items]
    n = len(items)
    chosen = list(range(n)) if n <= MAX_DECLUTTER_PANELS else \
        sorted(set(np.linspace(0, n - 1, MAX_DECLUTTER_PANELS).round().astype(int).tolist()))
    plt = _plt()
    ncols = min(3, len(chosen))
    nrows = int(np.ceil(len(chosen) / ncols))
    H, W = segs[chosen[0]].shape
    pw = 5.2
    ph = max(2.5, min(7.0, pw * H / W)) + 0.5
    fig, axes = plt.subplots(nrows, ncols, figsize=(pw * ncols, ph * nrows), squeeze=False)
    for ax in axes.ravel()[len(chosen):]:
        ax.set_visible(False)
    for ax, i in zip(axes.ravel(), chosen):
        decision = items[i][1]
        _draw_declutter(ax, segs[i], decision, names)
        ax.set_title(f"decision {i + 1}/{n}: {_decision_caption(decision, names)}", fontsize=9)
    sup = title or "declutter graphs"
    if len(chosen) < n:
        sup += f" ({len(chosen)} of {n} decisions shown)"
    fig.suptitle(sup)
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------------------
# Next best views and the occupancy grid (Fig. 4, Eq. 19-23)
# ----------------------------------------------------------------------------------------------------------------


def _box_edges(lower: np.ndarray, upper: np.ndarray) -> list[np.ndarray]:
    """The 12 edges ``(2, 3)`` of the axis-aligned box ``[lower, upper]``."""
    corners = np.array([[(lower, upper)[i][0], (lower, upper)[j][1], (lower, upper)[k][2]]
                        for i in (0, 1) for j in (0, 1) for k in (0, 1)])
    edges = []
    for a in range(8):
        for b in range(a + 1, 8):
            if bin(a ^ b).count("1") == 1:
                edges.append(corners[[a, b]])
    return edges


def views_figure(path: Path, grid, centroid, view_positions, candidate_positions=None, candidate_gains=None,
                 entropy_history: Sequence[float] = (), title: str = "") -> Path:
    """Fig. 4 and Eq. 19: the next-best-view selection of one episode.

    Left, in 3-D: the hemisphere candidates ``candidate_positions (N, 3)`` coloured by their expected gain
    ``candidate_gains (N,)`` (Eq. 23; the last NBV round's), the executed views ``view_positions (V, 3)`` numbered
    in order with a line from each to the target's ``centroid (3,)``, and the box of ``grid``. Middle: the
    occupancy grid (:class:`~activetouch.information.occupancy.OccupancyGrid`) from above: the mean cell entropy
    of each ``(x, y)`` column (nats; ``ln 2`` = never observed) with the outline of the columns holding an occupied
    cell (``p > 0.5``). Right: the grid entropy (Eq. 19) ``entropy_history[k]`` after view ``k + 1``, against the
    prior's ``n_cells * ln 2``.

    Raises:
        ValueError: on wrongly shaped inputs (``centroid`` not ``(3,)``, positions not ``(V, 3)`` / ``(N, 3)``,
            gains not ``(N,)``, gains without positions) or a ``grid`` without ``cell_entropy``.
    """
    centroid = _np(centroid).reshape(-1)
    if centroid.shape != (3,) or not np.isfinite(centroid).all():
        raise ValueError(f"centroid must be a finite (3,) vector, got shape {centroid.shape}")
    views = _np(view_positions) if view_positions is not None else np.zeros((0, 3))
    if views.size == 0:
        views = np.zeros((0, 3))
    if views.ndim != 2 or views.shape[1] != 3:
        raise ValueError(f"view_positions must have shape (V, 3), got {views.shape}")
    cand = gains = None
    if candidate_positions is not None:
        cand = _np(candidate_positions)
        if cand.ndim != 2 or cand.shape[1] != 3:
            raise ValueError(f"candidate_positions must have shape (N, 3), got {cand.shape}")
        if candidate_gains is not None:
            gains = _np(candidate_gains)
            if gains.shape != (len(cand),):
                raise ValueError(f"candidate_gains must have shape ({len(cand)},) like candidate_positions, "
                                 f"got {gains.shape}")
    elif candidate_gains is not None:
        raise ValueError("candidate_gains given without candidate_positions")
    if not hasattr(grid, "cell_entropy"):
        raise ValueError(f"grid must be an OccupancyGrid, got {type(grid).__name__}")
    history = [float(h) for h in (entropy_history if entropy_history is not None else [])]

    plt = _plt()  # the "3d" projection (mpl_toolkits.mplot3d) is registered by matplotlib itself

    fig = plt.figure(figsize=(15, 4.8))
    ax3 = fig.add_subplot(1, 3, 1, projection="3d")
    ax_og = fig.add_subplot(1, 3, 2)
    ax_h = fig.add_subplot(1, 3, 3)

    # --- left: candidates, executed views, grid box
    lower, upper = _np(grid.lower), _np(grid.upper)
    for e in _box_edges(lower, upper):
        ax3.plot(e[:, 0], e[:, 1], e[:, 2], c="0.55", lw=0.7)
    if cand is not None and len(cand):
        if gains is not None:
            sc = ax3.scatter(cand[:, 0], cand[:, 1], cand[:, 2], c=gains, cmap="viridis", s=22, depthshade=False,
                             edgecolors="none")
            cb = fig.colorbar(sc, ax=ax3, shrink=0.6, pad=0.1)
            cb.set_label("expected gain (nats, Eq. 23)", fontsize=8)
            best = int(np.nanargmax(gains)) if np.isfinite(gains).any() else None
            if best is not None:
                ax3.scatter(*cand[best], s=110, facecolors="none", edgecolors="tab:green", linewidths=1.5,
                            depthshade=False, label="best candidate")
        else:
            ax3.scatter(cand[:, 0], cand[:, 1], cand[:, 2], c="0.6", s=14, depthshade=False, label="candidates")
    ax3.scatter(*centroid, marker="*", s=160, c="gold", edgecolors="k", depthshade=False, label="target centroid")
    for i, v in enumerate(views):
        ax3.plot([v[0], centroid[0]], [v[1], centroid[1]], [v[2], centroid[2]], "--", c="tab:red", lw=0.9)
        ax3.text(v[0], v[1], v[2] + 0.02, str(i + 1), color="tab:red", fontsize=10, weight="bold")
    if len(views):
        ax3.scatter(views[:, 0], views[:, 1], views[:, 2], c="tab:red", s=40, marker="^", depthshade=False,
                    label="executed views (in order)")
    pts = [centroid[None], lower[None], upper[None], views]
    if cand is not None:
        pts.append(cand)
    allp = np.vstack(pts)
    lo, hi = allp.min(0), allp.max(0)
    half = 0.5 * float((hi - lo).max()) * 1.05 + 1e-6
    mid = 0.5 * (lo + hi)
    ax3.set_xlim(mid[0] - half, mid[0] + half)
    ax3.set_ylim(mid[1] - half, mid[1] + half)
    ax3.set_zlim(max(lo[2] - 0.02, mid[2] - half), max(lo[2] - 0.02, mid[2] - half) + 2 * half)
    ax3.set_box_aspect((1, 1, 1))
    ax3.set_xlabel("x (m)", fontsize=8)
    ax3.set_ylabel("y (m)", fontsize=8)
    ax3.set_zlabel("z (m)", fontsize=8)
    ax3.tick_params(labelsize=7)
    ax3.view_init(elev=28, azim=-60)
    ax3.legend(loc="upper left", fontsize=7)
    ax3.set_title("views on the hemisphere (Fig. 4)", fontsize=10)

    # --- middle: the grid from above
    ent = _np(grid.cell_entropy())  # (X, Y, Z)
    prob = _np(grid.prob())
    col_ent = ent.mean(axis=2).T  # (Y, X) for imshow
    occupied = (prob > 0.5).any(axis=2).T
    extent = (lower[0], upper[0], lower[1], upper[1])
    im = ax_og.imshow(col_ent, origin="lower", extent=extent, cmap="magma", vmin=0.0, vmax=float(np.log(2.0)),
                      interpolation="nearest")
    cb = fig.colorbar(im, ax=ax_og, shrink=0.85)
    cb.set_label("mean cell entropy of the column (nats)", fontsize=8)
    if occupied.any():
        res = float(grid.resolution)
        xs = lower[0] + (np.arange(occupied.shape[1]) + 0.5) * res
        ys = lower[1] + (np.arange(occupied.shape[0]) + 0.5) * res
        ax_og.contour(xs, ys, occupied.astype(float), levels=[0.5], colors="cyan", linewidths=1.2)
    ax_og.plot([], [], c="cyan", label="occupied (p > 0.5)")
    ax_og.scatter(centroid[0], centroid[1], marker="*", s=120, c="gold", edgecolors="k", zorder=5,
                  label="target centroid")
    ax_og.legend(loc="upper right", fontsize=7)
    ax_og.set_xlabel("x (m)")
    ax_og.set_ylabel("y (m)")
    ax_og.set_title(f"occupancy grid from above ({grid.resolution * 100:g} cm cells)", fontsize=10)

    # --- right: Eq. 19 after each view
    if history:
        xs = np.arange(1, len(history) + 1)
        ax_h.plot(xs, history, "o-", c="tab:red", label="grid entropy after the view")
        ax_h.set_xticks(xs)
        for x, h in zip(xs, history):
            ax_h.annotate(f"{h:.0f}", (x, h), textcoords="offset points", xytext=(0, 6), ha="center", fontsize=7)
    else:
        ax_h.text(0.5, 0.5, "no view integrated", transform=ax_h.transAxes, ha="center", va="center")
    n_cells = int(np.prod(ent.shape))
    ax_h.axhline(n_cells * np.log(2.0), ls="--", c="0.5", label=f"prior: {n_cells} cells x ln 2")
    ax_h.margins(y=0.2)
    ax_h.set_xlabel("view")
    ax_h.set_ylabel("H(OG) (nats, Eq. 19)")
    ax_h.legend(loc="lower left", fontsize=7)
    ax_h.set_title("grid entropy after each view", fontsize=10)
    ax_h.grid(alpha=0.3)
    if title:
        fig.suptitle(title)
    return _save(fig, path)


# ----------------------------------------------------------------------------------------------------------------
# Error after each view / touch over many episodes (Fig. 6)
# ----------------------------------------------------------------------------------------------------------------

#: Row actions that remove clutter (their views belong to the declutter phase).
DECLUTTER_ACTIONS = ("push", "pick")


def _value(row: Mapping, key: str) -> float:
    v = row.get(key)
    if v is None:
        return float("nan")
    if isinstance(v, str):
        v = v.strip()
        if not v:
            return float("nan")
    try:
        return float(v)
    except (TypeError, ValueError):
        return float("nan")


def acquisition_series(rows: Sequence[Mapping], metric: str = "adi_mm") -> tuple[list[float], list[float]]:
    """The error ``metric`` (a column of ``steps.csv``: ``adi_mm``, ``trans_err_mm``, ``rot_err_deg``) after each
    acquisition of the perception phase of one episode: ``(views, touches)``, ``views[k]`` after the ``k+1``-th
    view and ``touches[k]`` after the ``k+1``-th touch.

    ``rows``: the episode's step rows in order (dicts as read by ``csv.DictReader``, values strings or numbers).
    Counted: every ``view`` row after the episode's last ``push`` / ``pick`` row (the views before it are the
    declutter phase's) and every ``touch`` row; ``reset``, ``push``, ``pick`` and ``stop`` rows are skipped.
    Failed acquisitions (``action_success`` 0) count: the index is the number of attempts. Missing values are NaN.
    """
    rows = list(rows)
    actions = [str(r.get("action") or "").strip() for r in rows]
    last_declutter = max((i for i, a in enumerate(actions) if a in DECLUTTER_ACTIONS), default=-1)
    views, touches = [], []
    for i, (r, a) in enumerate(zip(rows, actions)):
        if a == "view" and i > last_declutter:
            views.append(_value(r, metric))
        elif a == "touch":
            touches.append(_value(r, metric))
    return views, touches


STATS = ("median", "mean")


def _stats(series: list[list[float]], k: int, stat: str = "median") -> tuple[float, float, float, int]:
    """``(centre, low, high, count)`` over the episodes whose series reach index ``k`` (NaN values dropped):
    ``stat="median"``: the median and the 25th / 75th percentiles; ``"mean"``: the mean and mean -+ one std."""
    vals = np.array([s[k] for s in series if len(s) > k], dtype=float)
    vals = vals[np.isfinite(vals)]
    if len(vals) == 0:
        return float("nan"), float("nan"), float("nan"), 0
    if stat == "median":
        lo, mid, hi = np.percentile(vals, [25, 50, 75])
        return float(mid), float(lo), float(hi), len(vals)
    m, sd = float(vals.mean()), float(vals.std())
    return m, m - sd, m + sd, len(vals)


def error_curves_figure(path: Path, episodes: Mapping[str, Sequence[Sequence[Mapping]]], title: str = "",
                        stat: str = "median") -> Path:
    """Fig. 6 over many episodes: for each method, the ADI (Eq. 28, left) and the translation error (Eq. 26,
    right) after the k-th acquisition of the perception phase (:func:`acquisition_series`): x = views 1..V, then
    touches 1..T. The line is the median over the episodes that reached that index, the band the 25-75 %
    range (``stat="mean"``: the mean and +- one standard deviation, which one episode that lost its target can
    dominate); the number of those episodes is written in a strip under each panel, in the method's colour. A log
    scale is used when the plotted errors span more than a factor 8.

    ``episodes[method]``: a list of episodes, each a list of step rows (:func:`load_episode_rows`).

    Raises:
        ValueError: no method, an episode that is not a list of row mappings, or an unknown ``stat``.
    """
    if not episodes:
        raise ValueError("episodes must hold at least one method")
    if stat not in STATS:
        raise ValueError(f"stat must be one of {STATS}, got {stat!r}")
    series: dict[str, dict[str, tuple[list, list]]] = {}
    for method, eps in episodes.items():
        eps = list(eps)
        for j, ep in enumerate(eps):
            if isinstance(ep, (str, bytes, Mapping)) or not all(isinstance(r, Mapping) for r in ep):
                raise ValueError(f"episodes[{method!r}][{j}] must be a list of step rows (dicts)")
        series[method] = {m: tuple(map(list, zip(*[acquisition_series(ep, m) for ep in eps]))) if eps else ([], [])
                          for m in ("adi_mm", "trans_err_mm")}
    n_views = max((len(v) for s in series.values() for v in s["adi_mm"][0]), default=0)
    n_touch = max((len(t) for s in series.values() for t in s["adi_mm"][1]), default=0)

    plt = _plt()
    methods = list(series)
    fig, grid_axes = plt.subplots(2, 2, figsize=(13, 5.2 + 0.22 * len(methods)), sharex="col",
                                  gridspec_kw=dict(height_ratios=[5.0, 0.45 + 0.25 * len(methods)], hspace=0.05))
    axes, count_axes = grid_axes[0], grid_axes[1]
    colours = plt.rcParams["axes.prop_cycle"].by_key()["color"]
    xs_v = np.arange(1, n_views + 1)
    xs_t = np.arange(n_views + 1, n_views + n_touch + 1)
    ticks = list(xs_v) + list(xs_t)
    tick_labels = [f"V{i}" for i in range(1, n_views + 1)] + [f"T{i}" for i in range(1, n_touch + 1)]
    for ax, ax_n, metric, name in ((axes[0], count_axes[0], "adi_mm", "ADI (mm, Eq. 28)"),
                                   (axes[1], count_axes[1], "trans_err_mm", "translation error (mm, Eq. 26)")):
        if n_views:
            ax.axvspan(0.5, n_views + 0.5, color=ACTION_COLOURS["view"], lw=0, zorder=0)
        if n_touch:
            ax.axvspan(n_views + 0.5, n_views + n_touch + 0.5, color=ACTION_COLOURS["touch"], lw=0, zorder=0)
        x = np.array(ticks, dtype=float)
        drawn = {}
        for method in methods:
            views_s, touch_s = series[method][metric]
            stats = ([_stats(views_s, k, stat) for k in range(n_views)]
                     + [_stats(touch_s, k, stat) for k in range(n_touch)])
            drawn[method] = tuple(np.array([s[i] for s in stats]) for i in range(3)) + ([s[3] for s in stats],)
        vals = np.concatenate([np.concatenate([m, hi]) for m, _, hi, _ in drawn.values()]) if ticks else np.zeros(0)
        vals = vals[np.isfinite(vals) & (vals > 0)]
        log = bool(len(vals) and vals.max() / vals.min() > 8)
        for m_i, method in enumerate(methods):
            c = colours[m_i % len(colours)]
            mean, low, high, cnt = drawn[method]
            ax.plot([], [], "o-", c=c, label=f"{method} (n={len(episodes[method])} episodes)")
            if not len(mean):
                continue
            ok = np.isfinite(mean)
            if log:  # keep the band's lower edge on the log axis
                low = np.maximum(low, 0.5 * vals.min())
            dx = (m_i - 0.5 * (len(methods) - 1)) * 0.06  # so that the methods' markers do not overlap
            for part in (xs_v, xs_t):  # no line across the view -> touch boundary
                sel = np.isin(x, part) & ok
                if sel.any():
                    ax.fill_between(x[sel] + dx, low[sel], high[sel], color=c, alpha=0.18, lw=0)
                    ax.plot(x[sel] + dx, mean[sel], "o-", c=c, ms=4, lw=1.6)
            for xi, n in zip(x, cnt):
                ax_n.text(xi, len(methods) - 1 - m_i, f"{n}", ha="center", va="center", fontsize=7,
                          color=c if n else "0.6")
        if log:
            ax.set_yscale("log")
            ax.set_ylim(bottom=vals.min() / 3.0)
        else:
            ax.set_ylim(bottom=0.0)
        top = ax.get_ylim()[1]
        if len(vals):
            ax.set_ylim(top=top * (1.6 if ax.get_yscale() == "log" else 1.1))
        ax_n.set_ylim(-0.6, len(methods) - 0.4)
        ax_n.set_yticks([])
        ax_n.set_ylabel("n", rotation=0, ha="right", va="center", fontsize=8)
        ax_n.set_xticks(ticks)
        ax_n.set_xticklabels(tick_labels, fontsize=8 if len(ticks) <= 16 else 6.5)
        ax_n.set_xlim(0.5, max(1, n_views + n_touch) + 0.5)
        ax_n.set_xlabel("acquisition of the perception phase (V: view, T: touch); n: episodes that reached it")
        ax.tick_params(axis="x", labelbottom=False)
        ax.set_ylabel(name)
        ax.grid(alpha=0.3, which="both", axis="y")
        ax.set_title(f"{name.split(' (')[0]} after each acquisition (Fig. 6)", fontsize=10)
        if not ticks:
            ax.text(0.5, 0.5, "no view or touch in the perception phase", transform=ax.transAxes,
                    ha="center", va="center")
    axes[0].legend(loc="upper right", fontsize=7.5)
    if title:
        fig.suptitle(title)
    fig.subplots_adjust(left=0.06, right=0.985, bottom=0.11, top=0.88 if title else 0.92, wspace=0.16)
    return _save(fig, path, tight=False)


def load_episode_rows(root, task: str | Sequence[str] | None = None) -> dict[str, list[list[dict]]]:
    """The step rows of a sweep folder ``root/<task>/<method>/seed*/steps.csv``, grouped by method:
    ``{method: [rows of each episode]}`` (methods and seeds in sorted order; rows as ``csv.DictReader`` gives
    them). Only episode folders that hold a ``summary.json`` (finished episodes) count. ``task``: a task name or
    several, to keep only those tasks' folders (``None``: all).

    Raises:
        FileNotFoundError: ``root`` is not a folder.
    """
    import csv

    root = Path(root)
    if not root.is_dir():
        raise FileNotFoundError(f"no sweep folder {root}")
    tasks = None if task is None else ({task} if isinstance(task, str) else set(task))
    out: dict[str, list[list[dict]]] = {}
    for steps in sorted(root.glob("*/*/seed*/steps.csv")):
        ep_dir = steps.parent
        method_dir = ep_dir.parent
        if tasks is not None and method_dir.parent.name not in tasks:
            continue
        if not (ep_dir / "summary.json").is_file():
            continue
        with open(steps, newline="") as fh:
            rows = list(csv.DictReader(fh))
        out.setdefault(method_dir.name, []).append(rows)
    return dict(sorted(out.items()))

"""Declutter graph of the visuo-tactile clutter paper (TIQF paper), section II-B.

The target object ``O_T`` is hidden in clutter. From one segmented depth view we

1. describe every object ``O_i`` by its mask, the mask's contour and the minimum-area bounding rectangle of the
   contour; ``C_i`` is the set of pixels inside that rectangle;
2. join two objects by an edge (Eq. 1)::

       e_ij = IoU_ij            if IoU_ij > mu_o                  (the rectangles overlap)
            = 1 / d_ij          if d_ij < mu_d and IoU_ij <= mu_o  (the contours nearly touch)
            = 0                 otherwise,

   with ``IoU_ij = |C_i n C_j| / |C_i u C_j|`` and ``d_ij`` the minimum distance between the two contours;
3. grow the *declutter graph* G, a tree rooted at the target, over the non-zero edges (breadth-first search);
4. give every object ``O_k`` of G an action from its grasp quality ``q_k`` (Eq. 2)::

       a_k = grasp  if q_k >= mu_q,   push  if q_k < mu_q;

5. remove next the leaf of G with the heaviest incoming edge ``e_ik``, by a top-down grasp (II-B-2) or by a
   straight push away from the clutter (II-B-1).

Everything here is a pure function of images: ``seg (H, W)`` object labels (``-1``: background, table, robot) and
``points (H, W, 3)`` the world points the pixels' rays hit (``NaN``: no hit). The table is the plane ``z = 0``.
Two conventions used throughout: pixel coordinates are ``(u, v) = (column, row)``; "in the table plane" means the
world ``x-y`` coordinates of a point.

Choices of ours where the paper is silent (each repeated where it is used):

- ``d_ij`` is measured in the table plane between the contours' back-projected points, in the unit
  ``DeclutterConfig.distance_unit`` (default centimetres, so ``mu_d = 0.5`` means "closer than 5 mm"). The paper
  gives ``mu_d = 0.5`` with no unit. In image pixels, two different contours can never be closer than one pixel,
  so the threshold would never fire; centimetres fits a 5 mm "touching" tolerance.
- With ``mu_d = 0.5`` every distance edge is ``1/d > 2`` and so heavier than any overlap edge (``IoU <= 1``):
  Eq. 1 read literally ranks touching neighbours ahead of overlapping ones. We keep that.
- The grasp quality is a transparent analytic stand-in for GG-CNN [23], whose weights are not available here
  (``grasp_candidate``).
- The push weights are ``w_i = 1 / |v_ik|^p`` with ``p = push_weight_power = 2``; the paper only says that objects
  further away have less influence (``plan_push``).
"""
from __future__ import annotations

import math
from collections.abc import Collection, Mapping
from dataclasses import dataclass

import networkx as nx  # a hard dependency of torch, so always installed with activetouch
import numpy as np
from scipy import ndimage
from scipy.spatial import ConvexHull, QhullError, cKDTree

__all__ = [
    "DeclutterConfig",
    "DeclutterDecision",
    "GraspCandidate",
    "ObjectGeometry",
    "PushPlan",
    "Rectangle",
    "SegmentedView",
    "build_declutter_graph",
    "contour_distance",
    "descent_clear",
    "declutter_edges",
    "edge_weight",
    "grasp_candidate",
    "iou",
    "mask_contour",
    "min_area_rectangle",
    "next_object",
    "object_geometry",
    "object_labels",
    "plan_declutter",
    "plan_push",
    "rectangle_mask",
]


# ----------------------------------------------------------------------------------------------------------------
# Inputs and parameters
# ----------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class SegmentedView:
    """One segmented depth view.

    Attributes:
        seg: ``(H, W)`` integer object label per pixel; ``-1`` (any negative label) is background, table or robot.
        points: ``(H, W, 3)`` world point hit by each pixel's ray; ``NaN`` where the ray hit nothing.
        camera_pos: ``(3,)`` world position of the camera, or ``None`` (carried along; the planner only needs the
            points).
    """

    seg: np.ndarray
    points: np.ndarray
    camera_pos: np.ndarray | None = None

    def __post_init__(self):
        seg = np.asarray(self.seg)
        if seg.ndim != 2 or not np.issubdtype(seg.dtype, np.integer):
            raise ValueError(f"seg must be a 2-D integer array (H, W), got shape {seg.shape} dtype {seg.dtype}")
        points = np.asarray(self.points, dtype=float)
        if points.shape != (*seg.shape, 3):
            raise ValueError(f"points must have shape (H, W, 3) = {(*seg.shape, 3)}, got {points.shape}")
        object.__setattr__(self, "seg", seg)
        object.__setattr__(self, "points", points)
        if self.camera_pos is not None:
            pos = np.asarray(self.camera_pos, dtype=float)
            if pos.shape != (3,):
                raise ValueError(f"camera_pos must have shape (3,), got {pos.shape}")
            object.__setattr__(self, "camera_pos", pos)

    @property
    def shape(self) -> tuple[int, int]:
        return self.seg.shape

    @classmethod
    def from_depth(cls, seg: np.ndarray, depth: np.ndarray, camera) -> SegmentedView:
        """Back-project a depth image of a pinhole camera.

        Args:
            seg: ``(H, W)`` integer labels.
            depth: ``(H, W)`` distance in metres along each pixel's (unit) ray, ``inf`` (or ``NaN``) for no hit,
                as rendered by ``activetouch.sim.camera.cast_rays``.
            camera: anything with ``intrinsics()`` K ``(3, 3)``, ``rotation()`` camera-to-world ``(3, 3)`` with
                columns (right, down, forward) and ``pos`` ``(3,)``, e.g. ``PinholeCamera``.

        The ray of pixel ``(u, v)`` is ``R K^-1 (u, v, 1)^T`` normalised; its point is ``pos + depth * ray``.
        """
        seg = np.asarray(seg)
        depth = np.asarray(depth, dtype=float)
        if depth.shape != seg.shape or depth.ndim != 2:
            raise ValueError(f"depth must have the shape (H, W) of seg {seg.shape}, got {depth.shape}")
        H, W = depth.shape
        K = np.asarray(camera.intrinsics(), dtype=float)
        R = np.asarray(camera.rotation(), dtype=float)
        pos = np.asarray(camera.pos, dtype=float)
        u, v = np.meshgrid(np.arange(W), np.arange(H))
        pix = np.stack([u, v, np.ones_like(u)], axis=-1).reshape(-1, 3).astype(float)
        rays = np.linalg.solve(K, pix.T).T @ R.T
        rays /= np.linalg.norm(rays, axis=1, keepdims=True)
        d = depth.reshape(-1)
        d = np.where(np.isfinite(d), d, np.nan)
        points = pos + rays * d[:, None]
        return cls(seg=seg, points=points.reshape(H, W, 3), camera_pos=pos)


@dataclass(frozen=True)
class DeclutterConfig:
    """Parameters of the declutter graph (section II-B) and of the two actions.

    Paper values (II-B, READING-NOTES): ``mu_o = 0.05`` (IoU threshold of Eq. 1), ``mu_d = 0.5`` (distance
    threshold of Eq. 1), ``mu_q = 0.1`` (grasp-quality threshold of Eq. 2).

    Not in the paper (choices of ours):

    - ``distance_unit`` = 0.01 m: ``d_ij`` of Eq. 1 is the table-plane distance in metres divided by this, i.e.
      in centimetres, so ``mu_d = 0.5`` means closer than 5 mm. The paper states no unit.
    - ``min_distance`` = 0.05 (same unit): floor on ``d_ij`` before ``1/d_ij`` so touching contours (distance 0,
      e.g. stacked objects) give a finite edge, at most ``1/min_distance = 20``.
    - ``min_pixels`` = 20: segments with fewer pixels are ignored (segmentation noise).
    - gripper: ``max_opening`` = 0.09 m between the fingers, ``finger_width`` = 0.02 m (each finger's footprint is
      ``finger_width x finger_width``); ``grasp_min_height`` = 0.02 m, the visible height above the table from
      which on an object is tall enough to grasp (the height factor of ``grasp_candidate`` ramps up to it).
    - the gripper's shape, for the collision checks of both actions (defaults: the simulated iiwa gripper's pads
      and palm, ``sim.clutter_env.CLUTTER_GRIPPER``; ``for_gripper`` reads them off any gripper geometry):
      ``finger_thickness`` = 0.012 m (each pad's extent along the closing direction), ``palm_size`` =
      (0.036, 0.14) m (the palm's footprint along the jaw and along the closing direction), ``palm_height`` = 0.07 m
      (the palm's underside above the fingertips); ``grasp_clearance`` = 0.03 m, the fingers open to the object's
      width plus this (at most ``max_opening``), as ``ClutterEnv``'s pick does; ``collision_margin`` = 0.005 m,
      the gripper's footprints grow by this (depth noise, arm tracking); ``free_distance`` = 0.02 m, the clearance
      beyond a finger at which ``f_free`` saturates; ``grasp_yaws`` = 12 closing directions searched (every 15 deg,
      plus the principal axis); ``push_turns_deg`` = (0, 20, -20, 40, -40), the deviations from the paper's push
      direction tried in turn when no push start on the contour leaves the descending gripper clear.
    - push: ``push_length`` = 0.10 m straight push; ``push_offset`` = 0.03 m, the finger starts this far outside
      the contour; ``push_search_radius`` = 0.03 m, contour points this close to the nominal push point are the
      candidates of the gripper-box search; ``push_weight_power`` = 2, ``w_i = 1/|v_ik|^p``;
      ``push_height_fraction`` = 0.5, the finger pushes at this fraction of the object's visible height.
    """

    mu_o: float = 0.05
    mu_d: float = 0.5
    mu_q: float = 0.1
    distance_unit: float = 0.01
    min_distance: float = 0.05
    min_pixels: int = 20
    max_opening: float = 0.09
    finger_width: float = 0.02
    grasp_min_height: float = 0.02
    push_length: float = 0.10
    push_offset: float = 0.03
    push_search_radius: float = 0.03
    push_weight_power: float = 2.0
    push_height_fraction: float = 0.5
    finger_thickness: float = 0.012
    palm_size: tuple[float, float] = (0.036, 0.14)
    palm_height: float = 0.07
    grasp_clearance: float = 0.03
    collision_margin: float = 0.005
    free_distance: float = 0.02
    grasp_yaws: int = 12
    push_turns_deg: tuple[float, ...] = (0.0, 20.0, -20.0, 40.0, -40.0)

    @classmethod
    def for_gripper(cls, gripper, **overrides) -> DeclutterConfig:
        """The config whose gripper fields are those of ``gripper`` (a ``sim.grasp_scene.GraspGripperGeometry``:
        box pads of half sizes ``pad_half`` (jaw, closing, height), palm of half sizes ``palm_half`` above them);
        ``overrides`` set any other field."""
        ph, qh = gripper.pad_half, gripper.palm_half
        values = dict(max_opening=float(gripper.max_opening), finger_width=2.0 * ph[0], finger_thickness=2.0 * ph[1],
                      palm_size=(2.0 * qh[0], 2.0 * qh[1]), palm_height=2.0 * ph[2])
        values.update(overrides)
        return cls(**values)

    def __post_init__(self):
        def check(name, ok, what):
            if not ok(getattr(self, name)):
                raise ValueError(f"{name} must be {what}, got {getattr(self, name)!r}")

        check("mu_o", lambda x: 0.0 <= x < 1.0, "in [0, 1)")
        check("mu_q", lambda x: 0.0 <= x <= 1.0, "in [0, 1]")
        for name in ("mu_d", "distance_unit", "min_distance", "max_opening", "finger_width", "grasp_min_height",
                     "push_length"):
            check(name, lambda x: x > 0 and math.isfinite(x), "> 0 and finite")
        for name in ("finger_thickness", "palm_height", "free_distance"):
            check(name, lambda x: x > 0 and math.isfinite(x), "> 0 and finite")
        for name in ("push_offset", "push_search_radius", "push_weight_power", "grasp_clearance",
                     "collision_margin"):
            check(name, lambda x: x >= 0 and math.isfinite(x), ">= 0 and finite")
        check("palm_size", lambda x: len(x) == 2 and all(v > 0 and math.isfinite(v) for v in x),
              "two positive finite sizes (along the jaw, along the closing direction)")
        check("grasp_yaws", lambda x: int(x) == x and x >= 1, "an integer >= 1")
        check("push_turns_deg", lambda x: len(x) >= 1 and all(math.isfinite(v) and abs(v) < 90 for v in x),
              "a non-empty sequence of angles in (-90, 90) degrees")
        check("push_height_fraction", lambda x: 0.0 <= x <= 1.0, "in [0, 1]")
        check("min_pixels", lambda x: int(x) == x and x >= 1, "an integer >= 1")


# ----------------------------------------------------------------------------------------------------------------
# Contours, minimum-area rectangles and IoU (Eq. 1's overlap measure)
# ----------------------------------------------------------------------------------------------------------------


def object_labels(seg: np.ndarray, min_pixels: int = 1) -> list[int]:
    """Sorted object labels (``>= 0``) of ``seg (H, W)`` that have at least ``min_pixels`` pixels."""
    labels, counts = np.unique(np.asarray(seg), return_counts=True)
    return [int(lab) for lab, n in zip(labels, counts) if lab >= 0 and n >= min_pixels]


def mask_contour(mask: np.ndarray) -> np.ndarray:
    """Boundary pixels ``(H, W) bool`` of ``mask (H, W) bool``: mask pixels with a 4-neighbour outside the mask
    (pixels on the image border count as boundary)."""
    mask = np.asarray(mask, dtype=bool)
    interior = ndimage.binary_erosion(mask, structure=ndimage.generate_binary_structure(2, 1), border_value=0)
    return mask & ~interior


@dataclass(frozen=True)
class Rectangle:
    """An oriented rectangle in a plane.

    Attributes:
        center: ``(2,)``.
        axes: ``(2, 2)``, rows the unit side directions; row 0 along the longer side.
        size: ``(2,)`` side lengths along ``axes[0]`` and ``axes[1]`` (``size[0] >= size[1]``).
    """

    center: np.ndarray
    axes: np.ndarray
    size: np.ndarray

    @property
    def angle(self) -> float:
        """Direction of the longer side, radians in ``[-pi/2, pi/2)``."""
        a = math.atan2(self.axes[0, 1], self.axes[0, 0])
        return (a + math.pi / 2) % math.pi - math.pi / 2

    @property
    def area(self) -> float:
        return float(self.size[0] * self.size[1])

    def corners(self) -> np.ndarray:
        """``(4, 2)`` corners in counter-clockwise order (for a right-handed plane)."""
        h0, h1 = 0.5 * self.size[0] * self.axes[0], 0.5 * self.size[1] * self.axes[1]
        c = np.stack([self.center - h0 - h1, self.center + h0 - h1, self.center + h0 + h1, self.center - h0 + h1])
        return c if _signed_area(c) >= 0 else c[::-1]

    def contains(self, points: np.ndarray, tol: float = 1e-9) -> np.ndarray:
        """Whether ``points (N, 2)`` lie inside (boundary included), ``(N,) bool``."""
        local = (np.asarray(points, float) - self.center) @ self.axes.T
        return (np.abs(local) <= 0.5 * self.size + tol).all(axis=1)


def min_area_rectangle(points: np.ndarray, pad: float = 0.0) -> Rectangle:
    """Minimum-area bounding rectangle of ``points (N, 2)`` (N >= 1), grown by ``pad`` on every side.

    Rotating calipers: the minimum-area rectangle has one side collinear with an edge of the convex hull
    (Freeman & Shapira 1975), so we try every hull edge direction and keep the smallest axis-aligned box in that
    frame. Written here because OpenCV's ``minAreaRect`` is not a dependency of activetouch. Degenerate inputs
    (one point, collinear points) get the principal direction of the points instead of hull edges.
    """
    pts = np.asarray(points, dtype=float)
    if pts.ndim != 2 or pts.shape[1] != 2 or len(pts) == 0:
        raise ValueError(f"points must have shape (N, 2) with N >= 1, got {pts.shape}")
    try:
        hull = pts[ConvexHull(pts).vertices]
        edges = np.roll(hull, -1, axis=0) - hull
        dirs = edges / np.linalg.norm(edges, axis=1, keepdims=True)
    except (QhullError, ValueError):  # fewer than 3 points or all collinear
        hull = pts
        centred = pts - pts.mean(axis=0)
        dirs = np.linalg.svd(centred, full_matrices=True)[2][:1] if len(pts) > 1 else np.array([[1.0, 0.0]])
    normals = np.stack([-dirs[:, 1], dirs[:, 0]], axis=1)
    along = hull @ dirs.T  # (h, n_dirs)
    across = hull @ normals.T
    lengths = along.max(axis=0) - along.min(axis=0)
    widths = across.max(axis=0) - across.min(axis=0)
    best = int(np.argmin(lengths * widths))
    u, n = dirs[best], normals[best]
    center = u * 0.5 * (along[:, best].max() + along[:, best].min()) + n * 0.5 * (across[:, best].max()
                                                                             + across[:, best].min())
    size = np.array([lengths[best], widths[best]]) + 2.0 * pad
    axes = np.stack([u, n])
    if size[1] > size[0]:
        size, axes = size[::-1].copy(), axes[::-1].copy()
    return Rectangle(center=center, axes=axes, size=size)


def rectangle_mask(rect: Rectangle, shape: tuple[int, int]) -> np.ndarray:
    """``C``: the pixels ``(H, W) bool`` whose centres ``(u, v) = (column, row)`` lie inside ``rect``."""
    H, W = shape
    r = 0.5 * float(np.hypot(*rect.size))
    u0, u1 = max(0, int(math.floor(rect.center[0] - r))), min(W, int(math.ceil(rect.center[0] + r)) + 1)
    v0, v1 = max(0, int(math.floor(rect.center[1] - r))), min(H, int(math.ceil(rect.center[1] + r)) + 1)
    out = np.zeros((H, W), dtype=bool)
    if u0 >= u1 or v0 >= v1:
        return out
    uu, vv = np.meshgrid(np.arange(u0, u1), np.arange(v0, v1))
    inside = rect.contains(np.stack([uu.ravel(), vv.ravel()], axis=1), tol=1e-6)
    out[v0:v1, u0:u1] = inside.reshape(uu.shape)
    return out


def iou(a: np.ndarray, b: np.ndarray) -> float:
    """Intersection over union ``|a n b| / |a u b|`` of two ``(H, W) bool`` pixel sets (0 if both are empty)."""
    a, b = np.asarray(a, bool), np.asarray(b, bool)
    union = np.count_nonzero(a | b)
    return float(np.count_nonzero(a & b) / union) if union else 0.0


@dataclass(frozen=True)
class ObjectGeometry:
    """What the declutter graph needs to know about one object ``O_i`` of a view.

    Attributes:
        label: the object's label in ``seg``.
        mask: ``(H, W) bool`` the object's pixels.
        contour: ``(H, W) bool`` its boundary pixels (``mask_contour``).
        rectangle: minimum-area rectangle of the contour pixels in pixel coordinates ``(u, v)``, grown by half a
            pixel on every side so that it covers the pixels' areas (an axis-aligned ``a x b`` block of pixels
            gives an ``a x b`` rectangle).
        box_pixels: ``C_i``, ``(H, W) bool`` the pixels inside ``rectangle`` (Eq. 1's overlap sets).
        points: ``(N, 3)`` world points of the object's pixels (no-hit pixels dropped).
        contour_points: ``(M, 3)`` world points of its contour pixels.
        table_rectangle: minimum-area rectangle of ``contour_points`` in the table plane (world ``x-y``), used by
            the push action.
    """

    label: int
    mask: np.ndarray
    contour: np.ndarray
    rectangle: Rectangle
    box_pixels: np.ndarray
    points: np.ndarray
    contour_points: np.ndarray
    table_rectangle: Rectangle


def object_geometry(view: SegmentedView, label: int) -> ObjectGeometry:
    """Mask, contour, rectangles ``C_i`` and 3-D points of object ``label`` of ``view``."""
    mask = view.seg == label
    if not mask.any():
        raise ValueError(f"label {label} does not occur in seg")
    contour = mask_contour(mask)
    rows, cols = np.nonzero(contour)
    rect = min_area_rectangle(np.stack([cols, rows], axis=1).astype(float), pad=0.5)
    points = _finite(view.points[mask])
    contour_points = _finite(view.points[contour])
    if len(contour_points) == 0:
        raise ValueError(f"object {label} has no valid 3-D points (points are all NaN on its pixels)")
    return ObjectGeometry(label=int(label), mask=mask, contour=contour, rectangle=rect,
                          box_pixels=rectangle_mask(rect, view.shape), points=points,
                          contour_points=contour_points, table_rectangle=min_area_rectangle(contour_points[:, :2]))


# ----------------------------------------------------------------------------------------------------------------
# Edges (Eq. 1) and the declutter graph
# ----------------------------------------------------------------------------------------------------------------


def contour_distance(a: ObjectGeometry, b: ObjectGeometry) -> float:
    """Minimum table-plane distance (metres) between the back-projected contour points of two objects.

    Measured in world ``x-y``, not in 3-D: seen from above, an object's contour lies on its top rim, so the 3-D
    distance between two touching objects of different heights would be their height difference.
    """
    tree = cKDTree(b.contour_points[:, :2])
    return float(tree.query(a.contour_points[:, :2], k=1)[0].min())


def edge_weight(iou_ij: float, d_ij: float, config: DeclutterConfig = DeclutterConfig()) -> float:
    """Eq. 1: ``IoU_ij`` if ``IoU_ij > mu_o``; else ``1/d_ij`` if ``d_ij < mu_d``; else 0.

    Args:
        iou_ij: overlap of the two objects' rectangles ``C_i, C_j``.
        d_ij: contour distance in ``config.distance_unit`` (default centimetres), floored at
            ``config.min_distance`` before the reciprocal.
    """
    if iou_ij > config.mu_o:
        return float(iou_ij)
    if d_ij < config.mu_d:
        return 1.0 / max(float(d_ij), config.min_distance)
    return 0.0


def declutter_edges(view: SegmentedView, config: DeclutterConfig = DeclutterConfig(),
                    geometry: Mapping[int, ObjectGeometry] | None = None) -> dict[tuple[int, int], float]:
    """Eq. 1 for every pair of objects of ``view``.

    Returns:
        ``{(i, j): e_ij}`` for labels ``i < j`` with ``e_ij > 0`` (missing pairs have no edge).
    """
    if geometry is None:
        geometry = {lab: object_geometry(view, lab) for lab in object_labels(view.seg, config.min_pixels)}
    labels = sorted(geometry)
    edges = {}
    for n, i in enumerate(labels):
        for j in labels[n + 1:]:
            overlap = iou(geometry[i].box_pixels, geometry[j].box_pixels)
            d = math.inf if overlap > config.mu_o else contour_distance(geometry[i], geometry[j]) / config.distance_unit
            e = edge_weight(overlap, d, config)
            if e > 0:
                edges[(i, j)] = e
    return edges


def build_declutter_graph(edges: Mapping[tuple[int, int], float], target: int) -> nx.DiGraph:
    """The declutter graph G: a tree rooted at ``target`` over the non-zero edges ``{(i, j): e_ij}`` (II-B).

    Level-by-level breadth-first search from the target: the objects one edge away from the target are its
    children, the not yet reached objects one edge away from those are theirs, and so on. An object reachable from
    several objects of the previous level gets as parent the one with the heaviest edge to it (ties: the smaller
    label), so the tree is deterministic. Objects not connected to the target are not in G: they do not hinder it.

    Returns:
        ``networkx.DiGraph`` with edges parent -> child carrying ``weight = e_ik``; node ``target`` has
        ``root=True``.
    """
    adjacency: dict[int, dict[int, float]] = {}
    for (i, j), e in edges.items():
        if e > 0 and i != j:
            adjacency.setdefault(i, {})[j] = float(e)
            adjacency.setdefault(j, {})[i] = float(e)
    graph = nx.DiGraph()
    graph.add_node(target, root=True)
    level = [target]
    while level:
        parents: dict[int, tuple[float, int]] = {}
        for p in level:
            for child, e in adjacency.get(p, {}).items():
                if child in graph:
                    continue
                best = parents.get(child)
                if best is None or (e, -p) > (best[0], -best[1]):
                    parents[child] = (e, p)
        for child in sorted(parents):
            e, p = parents[child]
            graph.add_node(child, root=False)
            graph.add_edge(p, child, weight=e)
        level = sorted(parents)
    return graph


def next_object(graph: nx.DiGraph, target: int) -> int | None:
    """The object to remove next: the leaf of G (a non-target node without children) with the heaviest incoming
    edge ``e_ik`` (II-B; ties: the smaller label). ``None`` when the target has no neighbour (decluttered)."""
    order = _leaves_in_order(graph, target)
    return order[0] if order else None


def _leaves_in_order(graph: nx.DiGraph, target: int) -> list[int]:
    """The leaves of G (non-target nodes without children), heaviest incoming edge first (ties: smaller label)."""
    leaves = [k for k in graph.nodes if k != target and graph.out_degree(k) == 0]

    def incoming(k):
        (p,) = graph.predecessors(k)
        return graph.edges[p, k]["weight"]

    return sorted(leaves, key=lambda k: (-incoming(k), k))


# ----------------------------------------------------------------------------------------------------------------
# Grasp action (II-B-2)
# ----------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class GraspCandidate:
    """A top-down parallel-jaw grasp.

    Attributes:
        position: ``(3,)`` world grasp point (between the fingertips).
        yaw: closing direction of the gripper in the table plane, radians in ``[-pi/2, pi/2)``.
        width: ``(m)`` the object's extent between the fingers.
        quality: ``q_k`` in ``[0, 1]`` (Eq. 2 compares it with ``mu_q``).
    """

    position: np.ndarray
    yaw: float
    width: float
    quality: float


def grasp_candidate(view: SegmentedView, label: int, config: DeclutterConfig = DeclutterConfig(),
                    obstacles: np.ndarray | None = None) -> GraspCandidate:
    """Top-down antipodal grasp of object ``label`` and its quality ``q_k`` (II-B-2).

    A transparent analytic **stand-in for GG-CNN** [23] (its trained weights cannot be fetched here), from the
    object's masked points, as the paper masks GG-CNN's depth input with the segmentation, and the other objects'
    points for the gripper's clearance. Like GG-CNN, which scores every pixel and angle and returns the best, we
    score ``grasp_yaws`` closing directions (every ``180 / grasp_yaws`` deg, plus the principal minor axis of the
    object's points) and keep the best (ties: the narrower grasp, then the minor axis). For a closing direction
    ``b`` and the jaw direction ``a`` (both in the table plane):

    - the finger band is ``|t| <= finger_width/2 + collision_margin`` along ``a`` around the centroid; the width
      ``w`` is the extent along ``b`` of the object's points in the band (all points if fewer than 2); the grasp
      point is the middle of that extent at the centroid along ``a``, at height
      ``z_g = max(h/2, h - palm_height + collision_margin)`` with ``h`` the visible height (95th percentile of the
      object's ``z`` above the table ``z = 0``): half-way up, or as low as the palm clears the object's top;
    - the fingers open to ``o = min(max_opening, w + grasp_clearance)`` and descend vertically onto ``z_g``: each
      pad occupies ``o/2 <= +-s <= o/2 + finger_thickness`` along ``b`` by the band along ``a``, the palm
      ``palm_size`` centred on the grasp point from ``z_g + palm_height`` up.

    ``q_k = f_open * f_free * f_height`` in ``[0, 1]``:

    - ``f_open = max(0, 1 - w / max_opening)``: the fraction of the opening left as clearance (0 when the object
      is wider than the open gripper);
    - ``f_free = f_+ f_-``, 0 when another object's point (label ``>= 0``, the target included) lies in the palm's
      descent volume (above ``z_g + palm_height - collision_margin``, footprint grown by ``collision_margin``);
      else, per finger, ``f_+- = min(1, g / free_distance)`` with ``g`` the gap from the finger's outer face grown
      by ``collision_margin`` to the nearest other point in the band beyond the object on that side and above
      ``z_g`` (``f = 0`` when such a point lies inside the finger or between finger and object, ``g = inf`` if
      there is none): a finger that lands on a neighbour, or closes on one, scores 0, so Eq. 2 pushes instead;
    - ``f_height = min(1, h / grasp_min_height)``: flat objects give the fingers nothing to hold.

    Only the visible points count, plus ``obstacles (M, 3)``, world points of objects the view does not show (e.g.
    the target's model at its estimated pose: a transparent target's depth rays report what lies behind it): a
    neighbour hidden under an overhang cannot be avoided (GG-CNN has the same blindness).
    """
    geom_points = _finite(view.points[view.seg == label])
    if len(geom_points) < 3:
        raise ValueError(f"object {label} has fewer than 3 valid points in the view")
    xy = geom_points[:, :2]
    centroid = xy.mean(axis=0)
    eigval, eigvec = np.linalg.eigh(np.cov((xy - centroid).T))
    minor = math.atan2(eigvec[1, 0], eigvec[0, 0])
    height = max(0.0, float(np.percentile(geom_points[:, 2], 95)))
    m = config.collision_margin
    z_grasp = max(0.5 * height, height - config.palm_height + m)
    f_height = min(1.0, height / config.grasp_min_height)
    others = _finite(view.points[(view.seg >= 0) & (view.seg != label)])
    others = np.vstack([others, _obstacle_points(obstacles)])
    fingers = others[others[:, 2] > z_grasp]  # what a finger descending onto z_grasp can meet
    palm = others[others[:, 2] > z_grasp + config.palm_height - m]  # what the palm can meet
    half_band = 0.5 * config.finger_width + m
    yaws = [minor] + [math.pi * j / config.grasp_yaws for j in range(config.grasp_yaws)]
    best = None
    for n, yaw in enumerate(yaws):
        b = np.array([math.cos(yaw), math.sin(yaw)])
        a = np.array([-b[1], b[0]])
        s, t = (xy - centroid) @ b, (xy - centroid) @ a
        band = np.abs(t) <= half_band
        s_band = s[band] if np.count_nonzero(band) >= 2 else s
        s_lo, s_hi = float(s_band.min()), float(s_band.max())
        width = s_hi - s_lo
        mid = centroid + 0.5 * (s_lo + s_hi) * b
        opening = min(config.max_opening, width + config.grasp_clearance)
        f_open = max(0.0, 1.0 - width / config.max_opening)
        f_free = 1.0
        palm_box = Rectangle(center=mid, axes=np.stack([a, b]), size=np.asarray(config.palm_size) + 2 * m)
        if palm_box.contains(palm[:, :2], tol=0.0).any():
            f_free = 0.0
        if f_free > 0 and len(fingers):
            so, to = (fingers[:, :2] - mid) @ b, (fingers[:, :2] - mid) @ a
            in_band = np.abs(to) <= half_band
            outer = 0.5 * opening + config.finger_thickness + m
            for side in (1.0, -1.0):
                beyond = side * so[in_band]
                beyond = beyond[beyond > 0.5 * width]  # past the object's side: in or beyond this finger's path
                if len(beyond):
                    f_free *= min(1.0, max(0.0, float(beyond.min()) - outer) / config.free_distance)
        quality = float(np.clip(f_open * f_free * f_height, 0.0, 1.0))
        key = (quality, -round(width, 9), -n)
        if best is None or key > best[0]:
            closing = (yaw + math.pi / 2) % math.pi - math.pi / 2
            best = (key, GraspCandidate(position=np.array([mid[0], mid[1], z_grasp]), yaw=closing, width=width,
                                        quality=quality))
    return best[1]


# ----------------------------------------------------------------------------------------------------------------
# Push action (II-B-1)
# ----------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class PushPlan:
    """A straight quasi-static push: the fingertip starts at ``start (3,)`` (world) and moves ``length`` metres
    along ``direction (3,)`` (unit, horizontal). ``clear``: the gripper's descent onto ``start`` met no visible
    point (``plan_push`` step 4); False for the paper's nominal start taken when no start was clear."""

    start: np.ndarray
    direction: np.ndarray
    length: float
    clear: bool = True


def plan_push(view: SegmentedView, label: int, config: DeclutterConfig = DeclutterConfig(),
              geometry: Mapping[int, ObjectGeometry] | None = None, obstacles: np.ndarray | None = None) -> PushPlan:
    """Push object ``label`` away from the clutter (II-B-1), everything in the table plane (world ``x-y``).

    1. Direction: with ``c_i`` the centre of object ``O_i``'s bounding rectangle, ``v_ik = c_k - c_i`` points from
       every other object to the pushed one ``O_k``; ``d = sum_i w_i v_ik / |sum_i w_i v_ik|`` (the paper's
       ``-v/|v|`` with its ``v`` pointing towards the clutter). The paper only asks that objects further away have
       less influence; we take ``w_i = 1 / |v_ik|^p``, ``p = push_weight_power = 2``, so object ``i`` pulls with
       strength ``1/|v_ik|`` (``p = 1`` would give every object the same say whatever its distance). If the sum
       vanishes (clutter all around), ``d`` points away from the nearest object.
    2. Nominal push point: where the ray from ``O_k``'s centroid along ``-d`` meets the contour, i.e. the contour
       point furthest along ``-d`` among those within a contour-point spacing of the ray, moved onto the ray; the
       finger starts ``push_offset`` further out, so a push along ``d`` runs through the centroid.
    3. Clearance for the finger: the nominal point and the contour points of ``O_k`` within
       ``push_search_radius`` of it (on its side of the centroid) are candidates; each gets a
       ``finger_width x finger_width`` box, aligned with ``d``, at ``push_offset`` outside it; boxes that cover
       points of ``O_k`` itself are dropped. The start is the candidate whose box has the least mean IoU with the
       other objects' table-plane rectangles (ties: the closest to the nominal point). The paper does this in the
       image with the gripper's projected size; in the table plane the gripper's size needs no projection (the
       same thing for a top-down camera).

    4. Clearance (ours, not in the paper): a candidate is kept only if the closed gripper can descend onto its start
       without meeting a visible point (``descent_clear``: the fingers' and the palm's footprints against every
       object's points, the pushed one's included, and ``obstacles (M, 3)``: world points of objects the view does
       not show, as in ``grasp_candidate``); when no candidate is clear, the direction is turned by each of
       ``push_turns_deg`` in turn; when none is clear at any turn, the nominal start of step 2 is returned with
       ``clear=False``. In our runs most failed pushes were guarded descents stopped by a neighbour's top or by the
       palm (7 cm above the fingertips, 14 cm across) landing on the target.

    The start's height is ``push_height_fraction`` of the pushed object's highest visible point within
    ``push_search_radius`` of the contour point (at least 1.5 cm).
    """
    if geometry is None:
        geometry = {lab: object_geometry(view, lab) for lab in object_labels(view.seg, config.min_pixels)}
    if label not in geometry:
        raise ValueError(f"object {label} is not among the view's objects {sorted(geometry)}")
    k = geometry[label]
    others = [g for lab, g in geometry.items() if lab != label]
    c_k = k.table_rectangle.center
    centroid = k.points[:, :2].mean(axis=0)

    direction = np.zeros(2)
    for g in others:
        v = c_k - g.table_rectangle.center
        n = float(np.linalg.norm(v))
        if n > 1e-12:
            direction += v / n ** config.push_weight_power
    if np.linalg.norm(direction) < 1e-12 and others:
        nearest = min(others, key=lambda g: contour_distance(k, g))
        direction = c_k - nearest.table_rectangle.center
    if np.linalg.norm(direction) < 1e-12:
        direction = np.array([1.0, 0.0])
    direction = direction / np.linalg.norm(direction)

    # Clearance of the descending gripper (ours; the paper's gripper-box IoU only looks at the other objects'
    # boxes): the closed fingers come down vertically onto the start, so every visible point (any object, the pushed
    # one included) above the fingertips in the fingers' footprint, or above the palm's underside in the palm's, is
    # a collision that stops the guarded descent before the push begins. When no start near the nominal point is
    # clear, the direction is turned by push_turns_deg in turn (still away from the clutter) before giving up and
    # taking the paper's nominal choice.
    every = _finite(view.points[view.seg >= 0])
    every = np.vstack([every, _obstacle_points(obstacles)])
    turns = [math.radians(x) for x in config.push_turns_deg]
    fallback = None
    for turn in turns:
        c_, s_ = math.cos(turn), math.sin(turn)
        d_t = np.array([c_ * direction[0] - s_ * direction[1], s_ * direction[0] + c_ * direction[1]])
        cand_xy, cand_z, cand_dist = _push_candidates(k, centroid, d_t, config)
        n_t = np.array([-d_t[1], d_t[0]])
        box_axes = np.stack([d_t, n_t])
        best = None  # (mean IoU, distance to the nominal point, candidate)
        for c in range(len(cand_xy)):
            start_xy = cand_xy[c] - config.push_offset * d_t
            box = Rectangle(center=start_xy, axes=box_axes,
                            size=np.array([config.finger_width, config.finger_width]))
            if box.contains(k.points[:, :2]).any():
                continue
            if not descent_clear(every, start_xy, cand_z[c], d_t, config):
                continue
            mean_iou = np.mean([_polygon_iou(box.corners(), g.table_rectangle.corners()) for g in others]) \
                if others else 0.0
            key = (round(float(mean_iou), 12), float(cand_dist[c]), c)
            best = key if best is None or key < best else best
        if best is not None:
            start_xy = cand_xy[best[2]] - config.push_offset * d_t
            return PushPlan(start=np.array([start_xy[0], start_xy[1], cand_z[best[2]]]),
                            direction=np.array([d_t[0], d_t[1], 0.0]), length=config.push_length, clear=True)
        if fallback is None:  # the paper's own choice: the nominal point along the unturned direction
            start_xy = cand_xy[0] - config.push_offset * d_t
            fallback = PushPlan(start=np.array([start_xy[0], start_xy[1], cand_z[0]]),
                                direction=np.array([d_t[0], d_t[1], 0.0]), length=config.push_length, clear=False)
    return fallback


def _push_candidates(k: ObjectGeometry, centroid: np.ndarray, direction: np.ndarray, config: DeclutterConfig):
    """Push-start candidates of object ``k`` for a push along ``direction (2,)`` (``plan_push`` steps 2-3).

    Returns ``(xy (C, 2), z (C,), dist (C,))``: the nominal contour point (where the ray from ``centroid (2,)``
    along ``-direction`` leaves the contour) first, then the contour points behind the centroid within
    ``push_search_radius`` of it, each with its finger height (``push_height_fraction`` of the highest point of
    ``k`` within ``push_search_radius`` of it, at least 1.5 cm: the fingertips stay above the table) and its
    distance to the nominal point.
    """
    normal = np.array([-direction[1], direction[0]])
    contour_xy = k.contour_points[:, :2]
    back = (contour_xy - centroid) @ (-direction)  # how far behind the centroid, seen along the push
    off_ray = np.abs((contour_xy - centroid) @ normal)
    behind = back > 0
    if not behind.any():
        behind = np.ones(len(back), dtype=bool)
    spacing = _point_spacing(contour_xy)
    near_ray = np.flatnonzero(behind & (off_ray <= off_ray[behind].min() + spacing))
    hit = int(near_ray[np.lexsort((off_ray[near_ray], -back[near_ray]))[0]])  # furthest back, then closest
    nominal_xy = centroid - back[hit] * direction  # that contour point moved onto the ray
    dist = np.linalg.norm(contour_xy - nominal_xy, axis=1)
    near = np.flatnonzero(behind & (dist <= config.push_search_radius))
    cand_xy = np.vstack([nominal_xy[None], contour_xy[near]])
    cand_dist = np.concatenate([[0.0], dist[near]])
    tree = cKDTree(k.points[:, :2])
    z = np.empty(len(cand_xy))
    for c, xy in enumerate(cand_xy):
        local = tree.query_ball_point(xy, config.push_search_radius)
        top = float(k.points[local, 2].max()) if local else float(np.percentile(k.points[:, 2], 95))
        z[c] = max(0.015, config.push_height_fraction * max(0.0, top))
    return cand_xy, z, cand_dist


def descent_clear(points: np.ndarray, start_xy: np.ndarray, z: float, direction: np.ndarray,
                  config: DeclutterConfig) -> bool:
    """Whether the closed gripper can descend vertically onto a push (or touch) start: no point of
    ``points (N, 3)`` above the fingertips ``z`` in the fingers' footprint (``finger_width`` along ``direction`` by
    twice ``finger_thickness`` across: the two closed pads side by side), none above the palm's underside in the
    palm's footprint (``palm_size[0]`` along, ``palm_size[1]`` across); footprints grown by ``collision_margin``."""
    m = config.collision_margin
    axes = np.stack([direction, [-direction[1], direction[0]]])
    fingers = Rectangle(center=start_xy, axes=axes,
                        size=np.array([config.finger_width, 2 * config.finger_thickness]) + 2 * m)
    palm = Rectangle(center=start_xy, axes=axes, size=np.asarray(config.palm_size) + 2 * m)
    low, high = points[:, 2] > z, points[:, 2] > z + config.palm_height - m
    return not (fingers.contains(points[low, :2], tol=0.0).any() or palm.contains(points[high, :2], tol=0.0).any())

# ----------------------------------------------------------------------------------------------------------------
# The whole decision
# ----------------------------------------------------------------------------------------------------------------


@dataclass(frozen=True)
class DeclutterDecision:
    """Result of ``plan_declutter``.

    Attributes:
        graph: the declutter graph G (``build_declutter_graph``); every non-root node carries ``quality`` (q_k) and
            ``action`` (``'grasp'`` or ``'push'``, Eq. 2).
        next_object: label of the object to remove next, ``None`` when the target is free.
        action: ``'grasp'``, ``'push'`` or ``None``.
        grasp: the grasp of ``next_object`` when ``action == 'grasp'``, else ``None``.
        push: the push of ``next_object`` when ``action == 'push'``, else ``None``.
        edges: Eq. 1 for all pairs of objects of the view, ``{(i, j): e_ij}`` with ``i < j`` and ``e_ij > 0``.
        blocked: the target still has neighbours but no leaf of G has a feasible action (``next_object`` is then
            ``None``); False when ``next_object`` is set or the target is free.
    """

    graph: nx.DiGraph
    next_object: int | None
    action: str | None
    grasp: GraspCandidate | None
    push: PushPlan | None
    edges: dict
    blocked: bool = False


def plan_declutter(view: SegmentedView, target_label: int, config: DeclutterConfig = DeclutterConfig(),
                   failed: Mapping[int, Collection[str]] | None = None,
                   obstacles: np.ndarray | None = None) -> DeclutterDecision:
    """Section II-B: build the declutter graph around ``target_label`` and choose the next object and action.

    Eq. 1 edges between all objects of ``view`` (segments of at least ``min_pixels`` pixels), the BFS tree G rooted
    at the target, Eq. 2 actions from ``grasp_candidate``'s ``q_k`` for every object of G, and as next object the
    leaf with the heaviest incoming edge; its grasp (``q_k >= mu_q``) or push (``plan_push``).

    Feasibility and replanning (ours; the paper re-plans after a failure detected by contact, II-B-2): an action
    is *feasible* when its collision check passes (a grasp with ``q_k > 0``, a push with ``clear``) and it has not
    failed on that object before (``failed``: ``{label: {'grasp', 'push'}}``, the actions that failed). The leaves
    are taken in the paper's order (heaviest incoming edge first, ties: the smaller label), and for each the Eq. 2
    action, then the other one; the first feasible pair is the decision. When no leaf has a feasible action the
    decision is ``blocked`` (the paper's robot would ask for help): executing an action whose gripper is known to
    land on a neighbour only spends an action and disturbs the pile. ``obstacles (M, 3)``: world points the view
    does not show, avoided by both actions (``grasp_candidate``).
    """
    labels = object_labels(view.seg, config.min_pixels)
    if target_label not in labels:
        raise ValueError(f"target_label {target_label} is not an object of the view (labels with >= "
                         f"{config.min_pixels} pixels: {labels})")
    failed = {} if failed is None else failed
    geometry = {lab: object_geometry(view, lab) for lab in labels}
    edges = declutter_edges(view, config, geometry)
    graph = build_declutter_graph(edges, target_label)
    grasps: dict[int, GraspCandidate] = {}
    for k in graph.nodes:
        if k == target_label:
            graph.nodes[k].update(quality=None, action=None)
            continue
        grasps[k] = grasp_candidate(view, k, config, obstacles)
        graph.nodes[k].update(quality=grasps[k].quality, action=_action(grasps[k].quality, config))
    order = _leaves_in_order(graph, target_label)
    if not order:
        return DeclutterDecision(graph=graph, next_object=None, action=None, grasp=None, push=None, edges=edges)
    for k in order:
        eq2 = graph.nodes[k]["action"]
        for action in (eq2, "push" if eq2 == "grasp" else "grasp"):
            if action in failed.get(k, ()):
                continue
            if action == "grasp" and grasps[k].quality > 0:
                return DeclutterDecision(graph=graph, next_object=k, action="grasp", grasp=grasps[k], push=None,
                                         edges=edges)
            if action == "push":
                push = plan_push(view, k, config, geometry, obstacles)
                if push.clear:
                    return DeclutterDecision(graph=graph, next_object=k, action="push", grasp=None, push=push,
                                             edges=edges)
    return DeclutterDecision(graph=graph, next_object=None, action=None, grasp=None, push=None, edges=edges,
                             blocked=True)


# ----------------------------------------------------------------------------------------------------------------
# Helpers
# ----------------------------------------------------------------------------------------------------------------


def _action(quality: float, config: DeclutterConfig) -> str:
    """Eq. 2: grasp if ``q_k >= mu_q`` else push."""
    return "grasp" if quality >= config.mu_q else "push"


def _finite(points: np.ndarray) -> np.ndarray:
    """Rows of ``points (N, 3)`` without NaN / inf."""
    points = np.asarray(points, dtype=float).reshape(-1, 3)
    return points[np.isfinite(points).all(axis=1)]


def _obstacle_points(obstacles: np.ndarray | None) -> np.ndarray:
    """``obstacles (M, 3)`` without NaN / inf rows; ``(0, 3)`` for ``None``."""
    if obstacles is None:
        return np.zeros((0, 3))
    arr = np.asarray(obstacles, dtype=float)
    if arr.ndim != 2 or arr.shape[1] != 3:
        raise ValueError(f"obstacles must have shape (M, 3), got {arr.shape}")
    return _finite(arr)


def _point_spacing(xy: np.ndarray) -> float:
    """Median nearest-neighbour distance of ``xy (N, 2)`` (0 for fewer than 2 points)."""
    if len(xy) < 2:
        return 0.0
    return float(np.median(cKDTree(xy).query(xy, k=2)[0][:, 1]))


def _signed_area(poly: np.ndarray) -> float:
    """Shoelace area of polygon ``poly (n, 2)``, positive for counter-clockwise vertices."""
    x, y = poly[:, 0], poly[:, 1]
    return 0.5 * float(np.dot(x, np.roll(y, -1)) - np.dot(y, np.roll(x, -1)))


def _clip_convex(subject: np.ndarray, clip: np.ndarray) -> np.ndarray:
    """Sutherland-Hodgman: the part of polygon ``subject (n, 2)`` inside the convex counter-clockwise ``clip``."""
    out = [p for p in subject]
    for a, b in zip(clip, np.roll(clip, -1, axis=0)):
        edge = b - a
        inside = [edge[0] * (p[1] - a[1]) - edge[1] * (p[0] - a[0]) >= 0 for p in out]
        new = []
        for i, p in enumerate(out):
            q, q_in = out[i - 1], inside[i - 1]
            if inside[i] != q_in:  # the edge q -> p crosses the clip line
                d = p - q
                denom = edge[0] * d[1] - edge[1] * d[0]
                s = (edge[1] * (q[0] - a[0]) - edge[0] * (q[1] - a[1])) / denom
                new.append(q + s * d)
            if inside[i]:
                new.append(p)
        out = new
        if not out:
            return np.zeros((0, 2))
    return np.array(out)


def _polygon_iou(p: np.ndarray, q: np.ndarray) -> float:
    """IoU of two convex counter-clockwise polygons ``(n, 2)``, ``(m, 2)`` in the plane."""
    inter = _clip_convex(p, q)
    a_inter = abs(_signed_area(inter)) if len(inter) >= 3 else 0.0
    union = abs(_signed_area(p)) + abs(_signed_area(q)) - a_inter
    return a_inter / union if union > 0 else 0.0


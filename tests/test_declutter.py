"""Declutter graph (visuo-tactile clutter paper, section II-B): geometry, Eq. 1, the BFS tree, Eq. 2, the actions.

Scenes are synthetic orthographic top-down views: pixel (row, col) sees the world point
(col * spacing, row * spacing, height of whatever is there), the table is z = 0.
"""
import math

import numpy as np
import pytest

from activetouch.planning.declutter import (
    DeclutterConfig,
    SegmentedView,
    build_declutter_graph,
    declutter_edges,
    edge_weight,
    grasp_candidate,
    iou,
    mask_contour,
    min_area_rectangle,
    next_object,
    object_geometry,
    plan_declutter,
    plan_push,
)

S = 0.002  # 2 mm pixels


class Scene:
    """Orthographic top-down view under construction; later boxes lie on top of earlier ones."""

    def __init__(self, shape=(80, 80), spacing=S):
        H, W = shape
        rows, cols = np.mgrid[0:H, 0:W]
        self.seg = -np.ones(shape, dtype=int)
        self.points = np.stack([cols * spacing, rows * spacing, np.zeros(shape)], axis=-1)

    def box(self, label, x0, x1, y0, y1, height):
        """Object ``label`` over the pixel centres with x in [x0, x1), y in [y0, y1) (metres)."""
        x, y, eps = self.points[..., 0], self.points[..., 1], 1e-9
        m = (x >= x0 - eps) & (x < x1 - eps) & (y >= y0 - eps) & (y < y1 - eps)
        self.seg[m] = label
        self.points[m, 2] = height
        return self

    def view(self):
        return SegmentedView(seg=self.seg.copy(), points=self.points.copy(), camera_pos=np.array([0.08, 0.08, 1.0]))


def contour_pixels(mask):
    rows, cols = np.nonzero(mask_contour(mask))
    return np.stack([cols, rows], axis=1).astype(float)


# ---------------------------------------------------------------------------------------------------------------
# Minimum-area rectangle and IoU
# ---------------------------------------------------------------------------------------------------------------


def test_min_area_rectangle_of_axis_aligned_block_is_exact():
    mask = np.zeros((40, 50), bool)
    mask[5:15, 10:30] = True  # 10 rows x 20 columns
    rect = min_area_rectangle(contour_pixels(mask), pad=0.5)
    np.testing.assert_allclose(rect.size, [20.0, 10.0], atol=1e-9)
    assert rect.area == pytest.approx(200.0)
    np.testing.assert_allclose(rect.center, [19.5, 9.5], atol=1e-9)


def test_min_area_rectangle_recovers_rotated_rectangle():
    length, width, angle = 40.0, 16.0, math.radians(30.0)
    v, u = np.mgrid[0:100, 0:100]
    axes = np.array([[math.cos(angle), math.sin(angle)], [-math.sin(angle), math.cos(angle)]])
    local = np.stack([u - 50.0, v - 50.0], axis=-1) @ axes.T
    mask = (np.abs(local[..., 0]) <= length / 2) & (np.abs(local[..., 1]) <= width / 2)
    rect = min_area_rectangle(contour_pixels(mask), pad=0.5)
    assert abs(rect.size[0] - length) <= 1.0 and abs(rect.size[1] - width) <= 1.0
    assert abs(rect.angle - angle) <= math.atan(1.0 / length) + 1e-9  # one pixel over the long side
    assert (length - 1) * (width - 1) <= rect.area <= (length + 1) * (width + 1)
    np.testing.assert_allclose(rect.center, [50.0, 50.0], atol=0.5)


def test_min_area_rectangle_of_disc_is_its_square():
    r = 15.0
    v, u = np.mgrid[0:60, 0:60]
    mask = (u - 30.0) ** 2 + (v - 30.0) ** 2 <= r**2
    rect = min_area_rectangle(contour_pixels(mask), pad=0.5)
    assert np.all(np.abs(rect.size - 2 * r) <= 1.0)
    assert rect.area == pytest.approx((2 * r) ** 2, rel=0.07)


def test_min_area_rectangle_degenerate_inputs():
    line = np.stack([np.arange(10.0), 2 * np.arange(10.0)], axis=1)  # collinear
    rect = min_area_rectangle(line, pad=0.5)
    assert rect.size[0] == pytest.approx(math.hypot(9, 18) + 1) and rect.size[1] == pytest.approx(1.0)
    assert min_area_rectangle(np.array([[3.0, 4.0]]), pad=0.5).area == pytest.approx(1.0)


def test_iou_identical_disjoint_and_known_overlap():
    a = np.zeros((30, 40), bool)
    a[5:15, 5:15] = True
    b = np.zeros_like(a)
    b[5:15, 25:35] = True
    assert iou(a, a) == 1.0
    assert iou(a, b) == 0.0
    # through the rectangles C of two 10 x 10 blocks overlapping by 5 columns: 50 / 150
    seg = -np.ones((30, 40), int)
    seg[5:15, 5:15] = 0
    seg[16:26, 10:20] = 1  # a separate object ...
    view = SegmentedView(seg, np.zeros((30, 40, 3)))
    g0 = object_geometry(view, 0)
    np.testing.assert_array_equal(g0.box_pixels, seg == 0)  # C of a block is the block
    c = np.zeros_like(a)
    c[5:15, 10:20] = True  # ... and the known overlap, on pixels
    assert iou(g0.box_pixels, c) == pytest.approx(1 / 3)


# ---------------------------------------------------------------------------------------------------------------
# Eq. 1
# ---------------------------------------------------------------------------------------------------------------


def test_edge_weight_cases_of_eq1():
    cfg = DeclutterConfig()
    assert edge_weight(0.3, 10.0, cfg) == 0.3  # overlap wins
    assert edge_weight(0.04, 0.3, cfg) == pytest.approx(1 / 0.3)  # close contours
    assert edge_weight(0.04, 0.6, cfg) == 0.0
    assert edge_weight(0.0, 0.0, cfg) == pytest.approx(1 / cfg.min_distance)  # touching: finite


def test_eq1_edges_from_contour_distance_in_centimetres():
    # 1 mm pixels: boxes 3 mm apart (centre to centre of the facing pixels), different heights
    near = Scene((40, 80), spacing=0.001).box(0, 0.010, 0.030, 0.010, 0.030, 0.03).box(1, 0.032, 0.052, 0.010,
                                                                                          0.030, 0.06)
    edges = declutter_edges(near.view())
    assert list(edges) == [(0, 1)]
    assert edges[(0, 1)] == pytest.approx(1 / 0.3)  # d = 0.3 cm
    far = Scene((40, 120), spacing=0.001).box(0, 0.010, 0.030, 0.010, 0.030, 0.03).box(1, 0.080, 0.100, 0.010,
                                                                                          0.030, 0.03)
    assert declutter_edges(far.view()) == {}


def clutter_scene():
    """Target T=0 with a strip A=1 lying across it, B=2 4 mm beside T, C=3 2 mm beyond the end of A."""
    return (Scene((80, 80))
            .box(0, 0.02, 0.08, 0.04, 0.10, 0.04)
            .box(1, 0.04, 0.06, 0.02, 0.12, 0.06)
            .box(2, 0.082, 0.11, 0.04, 0.10, 0.03)
            .box(3, 0.04, 0.06, 0.12, 0.15, 0.03))


def test_declutter_graph_tree_and_next_object():
    scene = clutter_scene()
    view = scene.view()
    edges = declutter_edges(view)
    assert set(edges) == {(0, 1), (0, 2), (1, 3)}
    # T's visible mask is split by A, its rectangle is the whole 6 x 6 cm top: IoU = 300 / 1100 pixels
    assert edges[(0, 1)] == pytest.approx(300 / 1100)
    assert edges[(0, 2)] == pytest.approx(1 / 0.4)  # 4 mm
    assert edges[(1, 3)] == pytest.approx(1 / 0.2)  # 2 mm
    decision = plan_declutter(view, 0)
    g = decision.graph
    assert set(g.edges) == {(0, 1), (0, 2), (1, 3)}
    assert {k for k in g.nodes if g.out_degree(k) == 0} == {2, 3}
    assert decision.next_object == 3  # heavier leaf edge: 5 > 2.5
    assert decision.edges == edges
    for k in (1, 2, 3):
        assert g.nodes[k]["action"] == ("grasp" if g.nodes[k]["quality"] >= 0.1 else "push")


def test_bfs_parent_is_heaviest_edge_of_previous_level():
    g = build_declutter_graph({(0, 1): 1.0, (0, 2): 1.0, (1, 3): 0.2, (2, 3): 0.9, (3, 4): 3.0, (5, 6): 1.0}, 0)
    assert set(g.edges) == {(0, 1), (0, 2), (2, 3), (3, 4)}
    assert 5 not in g and 6 not in g  # not connected to the target
    assert next_object(g, 0) == 4
    assert next_object(build_declutter_graph({}, 0), 0) is None


def test_lone_target_is_decluttered():
    view = Scene().box(0, 0.02, 0.06, 0.02, 0.06, 0.04).box(1, 0.10, 0.14, 0.10, 0.14, 0.04).view()
    d = plan_declutter(view, 0)
    assert d.next_object is None and d.action is None and d.grasp is None and d.push is None
    assert list(d.graph.nodes) == [0] and d.edges == {}


# ---------------------------------------------------------------------------------------------------------------
# Grasp quality and Eq. 2
# ---------------------------------------------------------------------------------------------------------------


def test_grasp_of_5cm_object_and_push_of_12cm_object():
    cfg = DeclutterConfig()
    # a 5 x 10 cm object, the target touching its far end (outside the finger band)
    view = Scene((80, 80)).box(1, 0.02, 0.07, 0.02, 0.12, 0.05).box(0, 0.02, 0.07, 0.122, 0.15, 0.04).view()
    g = grasp_candidate(view, 1, cfg)
    assert g.width == pytest.approx(0.048, abs=1e-9)  # pixel centres 2 mm apart
    assert g.quality == pytest.approx(1 - 0.048 / 0.09, abs=1e-6) and g.quality >= cfg.mu_q
    assert abs(math.sin(g.yaw)) < 1e-6  # closes along x, across the minor axis
    np.testing.assert_allclose(g.position, [0.044, 0.069, 0.025], atol=1e-6)
    d = plan_declutter(view, 0, cfg)
    assert d.next_object == 1 and d.action == "grasp" and d.grasp is not None and d.push is None

    # a 12 x 14 cm object and a flat target touching it: the finger starts over the target, above its 1 cm top
    wide = Scene((100, 100)).box(1, 0.02, 0.14, 0.02, 0.16, 0.05).box(0, 0.02, 0.14, 0.162, 0.19, 0.01).view()
    g = grasp_candidate(wide, 1, cfg)
    assert g.width > cfg.max_opening and g.quality == 0.0
    d = plan_declutter(wide, 0, cfg)
    assert d.action == "push" and d.push is not None and d.push.clear and d.grasp is None and not d.blocked
    # a 4 cm tall target there: the finger would land on it, and no turn clears it: nothing feasible
    tall = Scene((100, 100)).box(1, 0.02, 0.14, 0.02, 0.16, 0.05).box(0, 0.02, 0.14, 0.162, 0.19, 0.04).view()
    d = plan_declutter(tall, 0, cfg)
    assert d.blocked and d.next_object is None and d.action is None
    assert not plan_push(tall, 1, cfg).clear
    # replanning: an action that failed on an object is not repeated, and the other one is taken only if feasible
    assert plan_declutter(wide, 0, cfg, failed={1: {"push"}}).blocked
    d = plan_declutter(view, 0, cfg, failed={1: {"grasp"}})  # its push would start on the 4 cm target
    assert d.blocked and d.grasp is None and not plan_push(view, 1, cfg).clear


def test_clutter_beside_a_finger_lowers_quality_by_its_gap():
    # object 1: pixel centres x 0.050..0.068 (w = 1.8 cm), y 0.04..0.118; closing along x the fingers open to
    # w + 3 cm = 4.8 cm, so a finger's outer face (+ 5 mm margin) lies 2.4 + 1.2 + 0.5 = 4.1 cm from the middle
    # x = 0.059; a 6 cm tall neighbour from x = 0.110 leaves a 1 cm gap: f = 1 cm / 2 cm
    alone = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).view()
    beside = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).box(3, 0.11, 0.12, 0.04, 0.12, 0.06).view()
    low = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).box(2, 0.03, 0.04, 0.04, 0.12, 0.01) \
        .box(3, 0.08, 0.09, 0.04, 0.12, 0.01).view()
    g_alone, g_beside = grasp_candidate(alone, 1), grasp_candidate(beside, 1)
    assert g_alone.quality == pytest.approx(1 - 0.018 / 0.09) and abs(math.sin(g_alone.yaw)) < 1e-9
    assert g_beside.quality == pytest.approx((1 - 0.018 / 0.09) * 0.5, rel=1e-6)
    assert abs(math.sin(g_beside.yaw)) < 1e-9  # still across the minor axis: 0.4 beats 1 - 7.8 / 9 along y
    assert grasp_candidate(low, 1).quality == pytest.approx(g_alone.quality)  # below the fingertips: no collision


def test_grasp_turns_away_from_a_neighbour_in_the_fingers_path():
    # a neighbour 1.7 cm beyond the object's side along x: inside the descending finger (4.1 cm from the middle)
    view = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).box(3, 0.085, 0.095, 0.04, 0.12, 0.06).view()
    g = grasp_candidate(view, 1)
    assert abs(abs(math.sin(g.yaw)) - 1) < 1e-9  # closes along y, over the object's length, clear of the neighbour
    assert g.width == pytest.approx(0.078, abs=1e-9)
    assert g.quality == pytest.approx(1 - 0.078 / 0.09, rel=1e-6) and g.quality >= DeclutterConfig().mu_q
    # and a neighbour on both sides of the length too: no direction is clear, so Eq. 2 pushes
    boxed = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).box(3, 0.085, 0.095, 0.02, 0.14, 0.06) \
        .box(2, 0.025, 0.035, 0.02, 0.14, 0.06).box(4, 0.04, 0.08, 0.125, 0.135, 0.06) \
        .box(5, 0.04, 0.08, 0.025, 0.035, 0.06).box(0, 0.12, 0.14, 0.06, 0.10, 0.04).view()
    assert grasp_candidate(boxed, 1).quality == 0.0


def test_palm_over_a_tall_neighbour_forbids_the_grasp():
    # a 20 cm neighbour 1.2 cm from the object's side: clear of the fingers when closing along y, but the palm
    # (3.6 cm along the jaw + 5 mm margins, from z_g + 7 cm = 9.5 cm up) would land on it, and at every other
    # direction the fingers or the palm meet it
    tall = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).box(3, 0.08, 0.09, 0.0, 0.16, 0.20) \
        .box(0, 0.12, 0.14, 0.06, 0.10, 0.04).view()
    assert grasp_candidate(tall, 1).quality == 0.0
    short = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).box(3, 0.08, 0.09, 0.0, 0.16, 0.06) \
        .box(0, 0.12, 0.14, 0.06, 0.10, 0.04).view()
    assert grasp_candidate(short, 1).quality == pytest.approx(1 - 0.078 / 0.09, rel=1e-6)


def test_obstacles_the_view_does_not_show_count_like_seen_objects():
    # a transparent neighbour: segmented nowhere in the view, known only as points (e.g. its model at the estimate)
    alone = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).view()
    beside = Scene().box(1, 0.05, 0.07, 0.04, 0.12, 0.05).box(3, 0.11, 0.12, 0.04, 0.12, 0.06)
    hidden = beside.points[beside.seg == 3]
    assert grasp_candidate(alone, 1, obstacles=hidden).quality == pytest.approx(grasp_candidate(beside.view(), 1).quality)
    assert grasp_candidate(alone, 1, obstacles=hidden).quality < grasp_candidate(alone, 1).quality
    # a hidden object where the push's finger would descend: the start moves off it
    view = Scene().box(1, 0.02, 0.07, 0.04, 0.12, 0.04).box(0, 0.12, 0.16, 0.04, 0.12, 0.05).view()
    free = plan_push(view, 1)
    blocker = np.array([[free.start[0], free.start[1], 0.06], [free.start[0] + 0.005, free.start[1], 0.06]])
    moved = plan_push(view, 1, obstacles=blocker)
    assert moved.clear and np.linalg.norm(moved.start[:2] - free.start[:2]) > 0.01


def test_config_for_the_simulated_gripper():
    from activetouch.sim.clutter_env import CLUTTER_GRIPPER

    cfg = DeclutterConfig.for_gripper(CLUTTER_GRIPPER, mu_q=0.2)
    assert cfg.max_opening == CLUTTER_GRIPPER.max_opening and cfg.finger_width == pytest.approx(0.04)
    assert cfg.finger_thickness == pytest.approx(0.012) and cfg.palm_height == pytest.approx(0.07)
    assert cfg.palm_size == pytest.approx((0.036, 0.14)) and cfg.mu_q == 0.2


def test_flat_object_has_low_quality():
    flat = Scene().box(1, 0.05, 0.09, 0.04, 0.12, 0.005).view()
    tall = Scene().box(1, 0.05, 0.09, 0.04, 0.12, 0.05).view()
    assert grasp_candidate(flat, 1).quality == pytest.approx(0.25 * grasp_candidate(tall, 1).quality)


# ---------------------------------------------------------------------------------------------------------------
# Push
# ---------------------------------------------------------------------------------------------------------------


def pixel_of(view, xy):
    return int(round(xy[1] / S)), int(round(xy[0] / S))


def test_push_away_from_clutter_starts_outside_on_the_clutter_side():
    view = Scene().box(1, 0.02, 0.07, 0.04, 0.12, 0.04).box(0, 0.12, 0.16, 0.04, 0.12, 0.05).view()
    push = plan_push(view, 1)
    assert push.clear  # the finger (2 cm + 5 mm margins) at 3 cm from the contour ends 7 mm before the target
    np.testing.assert_allclose(push.direction, [-1.0, 0.0, 0.0], atol=1e-9)
    assert push.length == 0.10
    assert push.start[0] == pytest.approx(0.068 + 0.03)  # 3 cm beyond the last pixel centre on the +x side
    assert push.start[1] == pytest.approx(0.079, abs=1e-9)  # in line with the centroid
    assert push.start[2] == pytest.approx(0.02)  # half the visible height
    r, c = pixel_of(view, push.start)
    assert view.seg[r, c] != 1


def test_push_start_is_shifted_to_a_free_gripper_box():
    scene = Scene().box(1, 0.02, 0.07, 0.04, 0.12, 0.04).box(0, 0.12, 0.16, 0.04, 0.12, 0.05) \
        .box(2, 0.09, 0.11, 0.07, 0.09, 0.05)  # a small object right where the nominal finger would go
    view = scene.view()
    push = plan_push(view, 1)
    np.testing.assert_allclose(push.direction, [-1.0, 0.0, 0.0], atol=1e-9)
    assert push.start[0] > 0.068 and view.seg[pixel_of(view, push.start)] != 1
    assert abs(push.start[1] - 0.079) > 0.015
    xy = view.points[view.seg == 2][:, :2]
    half = 0.5 * DeclutterConfig().finger_width
    in_box = (np.abs(xy - push.start[:2]) < half).all(axis=1)
    assert not in_box.any()


def test_push_weights_favour_near_objects():
    # a near object on +x and a far one on +y: the push goes mostly along -x
    view = Scene((100, 100)).box(1, 0.04, 0.08, 0.04, 0.08, 0.04).box(0, 0.084, 0.10, 0.04, 0.08, 0.04) \
        .box(2, 0.04, 0.08, 0.17, 0.19, 0.04).view()
    d = plan_push(view, 1, DeclutterConfig(push_turns_deg=(0.0,))).direction  # the paper's direction, unturned
    assert d[0] < -0.9 and d[1] < 0 and abs(np.linalg.norm(d) - 1) < 1e-12


def test_push_turns_when_the_gripper_cannot_descend_onto_the_start():
    # the target 6 mm from the pushed object's side: a finger 3 cm behind the contour would land on it
    view = Scene((100, 100)).box(1, 0.04, 0.08, 0.04, 0.08, 0.04).box(0, 0.084, 0.10, 0.04, 0.08, 0.04) \
        .box(2, 0.04, 0.08, 0.17, 0.19, 0.04).view()
    cfg = DeclutterConfig()
    straight = plan_push(view, 1, DeclutterConfig(push_turns_deg=(0.0,)))
    assert not straight.clear  # the paper's start, returned flagged when nothing is clear
    push = plan_push(view, 1, cfg)
    assert push.clear
    turn = math.degrees(math.acos(np.clip(push.direction @ straight.direction, -1, 1)))
    assert turn == pytest.approx(20.0, abs=1e-6) or turn == pytest.approx(40.0, abs=1e-6)
    # no visible point above the fingertips in the closed fingers' footprint at the start
    pts = view.points[view.seg >= 0]
    rel = pts[:, :2] - push.start[:2]
    d2 = push.direction[:2]
    along, across = np.abs(rel @ d2), np.abs(rel @ np.array([-d2[1], d2[0]]))
    hit = (pts[:, 2] > push.start[2]) & (along <= 0.5 * cfg.finger_width + cfg.collision_margin) \
        & (across <= cfg.finger_thickness + cfg.collision_margin)
    assert not hit.any()
    assert push.direction[0] < 0  # still away from the target


# ---------------------------------------------------------------------------------------------------------------
# From a pinhole depth image; bad inputs
# ---------------------------------------------------------------------------------------------------------------


class TopDownCamera:
    """Pinhole camera 1 m above the origin looking down (right = +x, down = -y, forward = -z)."""

    pos = np.array([0.0, 0.0, 1.0])

    def intrinsics(self):
        return np.array([[100.0, 0, 9.5], [0, 100.0, 7.5], [0, 0, 1]])

    def rotation(self):
        return np.array([[1.0, 0, 0], [0, -1, 0], [0, 0, -1]])


def test_from_depth_back_projects_rays():
    v, u = np.mgrid[0:16, 0:20]
    x, y = (u - 9.5) / 100.0, (v - 7.5) / 100.0
    depth = np.sqrt(x**2 + y**2 + 1.0)  # the table plane z = 0, 1 m below
    depth[0, 0] = np.inf
    view = SegmentedView.from_depth(-np.ones((16, 20), int), depth, TopDownCamera())
    assert np.isnan(view.points[0, 0]).all()
    np.testing.assert_allclose(view.points[1:, :, 2], 0.0, atol=1e-12)
    np.testing.assert_allclose(view.points[5, 3], [x[5, 3], -y[5, 3], 0.0], atol=1e-12)


def test_from_depth_matches_pinhole_camera_rays():
    from activetouch.sim.camera import PinholeCamera

    cam = PinholeCamera(pos=(0.5, -0.3, 0.8), target=(0.0, 0.0, 0.0))
    depth = np.linspace(0.5, 1.0, cam.height * cam.width).reshape(cam.height, cam.width)
    view = SegmentedView.from_depth(-np.ones(depth.shape, int), depth, cam)
    expected = np.asarray(cam.pos) + cam.ray_directions() * depth.reshape(-1, 1)
    np.testing.assert_allclose(view.points.reshape(-1, 3), expected, atol=1e-12)


def test_convex_polygon_iou():
    from activetouch.planning.declutter import _polygon_iou

    square = np.array([[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]])
    assert _polygon_iou(square, square) == pytest.approx(1.0)
    assert _polygon_iou(square, square + [0.5, 0.0]) == pytest.approx(1 / 3)
    assert _polygon_iou(square, square + [0.5, 0.5]) == pytest.approx(0.25 / 1.75)
    assert _polygon_iou(square, square + [2.0, 0.0]) == 0.0


def test_bad_inputs_raise_naming_the_problem():
    seg = -np.ones((10, 10), int)
    with pytest.raises(ValueError, match="seg"):
        SegmentedView(seg.astype(float), np.zeros((10, 10, 3)))
    with pytest.raises(ValueError, match="points"):
        SegmentedView(seg, np.zeros((10, 11, 3)))
    with pytest.raises(ValueError, match="camera_pos"):
        SegmentedView(seg, np.zeros((10, 10, 3)), camera_pos=np.zeros(2))
    with pytest.raises(ValueError, match="depth"):
        SegmentedView.from_depth(seg, np.ones((5, 5)), TopDownCamera())
    view = clutter_scene().view()
    with pytest.raises(ValueError, match="target_label 7"):
        plan_declutter(view, 7)
    with pytest.raises(ValueError, match="target_label"):
        plan_declutter(view, 0, DeclutterConfig(min_pixels=10_000))  # the target is a "tiny" segment now
    with pytest.raises(ValueError, match="object 9"):
        plan_push(view, 9)
    with pytest.raises(ValueError, match="obstacles"):
        grasp_candidate(view, 1, obstacles=np.zeros((4, 2)))
    with pytest.raises(ValueError, match="mu_o"):
        DeclutterConfig(mu_o=1.5)
    with pytest.raises(ValueError, match="finger_width"):
        DeclutterConfig(finger_width=0.0)
    with pytest.raises(ValueError, match="min_pixels"):
        DeclutterConfig(min_pixels=0)
    with pytest.raises(ValueError, match="palm_size"):
        DeclutterConfig(palm_size=(0.03,))
    with pytest.raises(ValueError, match="grasp_yaws"):
        DeclutterConfig(grasp_yaws=0)
    with pytest.raises(ValueError, match="push_turns_deg"):
        DeclutterConfig(push_turns_deg=(0.0, 95.0))
    with pytest.raises(ValueError, match="points"):
        min_area_rectangle(np.zeros((0, 2)))

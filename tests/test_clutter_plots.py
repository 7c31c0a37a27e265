"""Figures of the clutter episodes (experiments.clutter_plots): declutter graph (Fig. 3a), next best views (Fig. 4),
error after each view / touch over many episodes (Fig. 6). Synthetic inputs only, no simulation."""
import csv
import json

import numpy as np
import pytest
import torch

from activetouch.experiments import clutter_plots as cp
from activetouch.information.occupancy import OccupancyConfig, OccupancyGrid
from activetouch.planning.declutter import SegmentedView, plan_declutter

S = 0.002  # 2 mm pixels of the orthographic top-down view


def three_box_view():
    """Target 0 with a strip 1 across it (IoU edge), box 2 4 mm beside it (distance edge): 3 rectangles."""
    H, W = 80, 80
    rows, cols = np.mgrid[0:H, 0:W]
    seg = -np.ones((H, W), dtype=int)
    points = np.stack([cols * S, rows * S, np.zeros((H, W))], axis=-1)
    for label, (x0, x1, y0, y1, h) in enumerate([(0.02, 0.08, 0.04, 0.10, 0.04), (0.04, 0.06, 0.02, 0.12, 0.06),
                                                 (0.082, 0.11, 0.04, 0.10, 0.03)]):
        m = (points[..., 0] >= x0 - 1e-9) & (points[..., 0] < x1 - 1e-9) & (points[..., 1] >= y0 - 1e-9) \
            & (points[..., 1] < y1 - 1e-9)
        seg[m] = label
        points[m, 2] = h
    return SegmentedView(seg=seg, points=points, camera_pos=np.array([0.08, 0.08, 1.0]))


def assert_png(path, min_bytes=10_000):
    import matplotlib.image as mpimg

    assert path.is_file() and path.stat().st_size > min_bytes
    img = mpimg.imread(path)
    assert img.ndim == 3 and img.shape[0] > 100 and img.shape[1] > 100
    assert float(img[..., :3].var()) > 1e-3  # not blank


def row(step, action, adi, trans=None, success="1"):
    return {"step": str(step), "action": action, "action_success": success, "adi_mm": str(adi),
            "trans_err_mm": str(adi * 2 if trans is None else trans), "rot_err_deg": "1.0", "n_visual": "0",
            "n_tactile": "0"}


def declutter_episode():
    """reset, 2 declutter views with a push and a pick, 3 perception views, 2 touches (one failed), stop."""
    return [row(0, "reset", 30.0, success=""), row(1, "view", 20.0), row(2, "push", 19.0, success="0"),
            row(3, "view", 18.0), row(4, "pick", 17.0), row(5, "view", 10.0), row(6, "view", 8.0),
            row(7, "view", 6.0), row(8, "touch", 5.0, success="0"), row(9, "touch", 4.0), row(10, "stop", 4.0)]


# ---------------------------------------------------------------------------------------------------------------
# Declutter graph (Fig. 3a)
# ---------------------------------------------------------------------------------------------------------------


def test_declutter_figure_draws_graph_and_segmentation_only(tmp_path):
    view = three_box_view()
    decision = plan_declutter(view, 0)
    assert set(decision.graph.edges) == {(0, 1), (0, 2)}
    out = cp.declutter_figure(tmp_path / "declutter.png", view.seg, decision, names=["target", "strip", "box"],
                              title="three boxes")
    assert out == tmp_path / "declutter.png"
    assert_png(out)
    assert_png(cp.declutter_figure(tmp_path / "seg.png", view.seg, None))


def test_declutter_sequence_figure_one_panel_per_decision(tmp_path):
    view = three_box_view()
    decision = plan_declutter(view, 0)
    seg2 = view.seg.copy()
    seg2[seg2 == 1] = -1  # the strip removed
    points2 = view.points.copy()
    points2[view.seg == 1, 2] = 0.0
    decision2 = plan_declutter(SegmentedView(seg=seg2, points=points2), 0)
    items = [(view.seg, decision), (seg2, decision2), (seg2, None)]
    assert_png(cp.declutter_sequence_figure(tmp_path / "seq.png", items, names=["target", "strip", "box"]))
    # more than 6 decisions: 6 panels (first and last among them), no error
    assert_png(cp.declutter_sequence_figure(tmp_path / "many.png", items * 3))
    with pytest.raises(ValueError):
        cp.declutter_sequence_figure(tmp_path / "none.png", [])


def test_declutter_figure_rejects_bad_seg(tmp_path):
    view = three_box_view()
    decision = plan_declutter(view, 0)
    with pytest.raises(ValueError):
        cp.declutter_figure(tmp_path / "a.png", view.seg[..., None], decision)  # (H, W, 1)
    with pytest.raises(ValueError):
        cp.declutter_figure(tmp_path / "b.png", view.seg.astype(float), decision)  # not integer
    with pytest.raises(ValueError):
        cp.declutter_figure(tmp_path / "c.png", np.where(view.seg == 2, -1, view.seg), decision)  # node 2 missing
    with pytest.raises(ValueError):
        cp.declutter_sequence_figure(tmp_path / "d.png", [(view.seg[0], decision)])


# ---------------------------------------------------------------------------------------------------------------
# Next best views (Fig. 4)
# ---------------------------------------------------------------------------------------------------------------


def small_grid():
    ctr = np.array([0.0, 0.0, 0.05])
    grid = OccupancyGrid(torch.as_tensor(ctr - 0.08), torch.as_tensor(ctr + 0.08), OccupancyConfig(resolution=0.02))
    rng = np.random.default_rng(0)
    ends = ctr + rng.uniform(-0.03, 0.03, (200, 3))
    ends[:, 2] = 0.08
    grid.integrate(torch.tensor([0.0, -0.3, 0.4]), torch.as_tensor(ends), torch.ones(200, dtype=torch.bool))
    return grid, ctr


def test_views_figure(tmp_path):
    grid, ctr = small_grid()
    rng = np.random.default_rng(1)
    phi = rng.uniform(0, 2 * np.pi, 20)
    el = rng.uniform(0.4, 1.4, 20)
    cand = ctr + 0.45 * np.stack([np.cos(el) * np.cos(phi), np.cos(el) * np.sin(phi), np.sin(el)], 1)
    gains = rng.uniform(0, 30, 20)
    views = np.array([[0.0, -0.3, 0.4], cand[int(np.argmax(gains))]])
    h0 = float(grid.entropy())
    out = cp.views_figure(tmp_path / "views.png", grid, ctr, views, cand, gains, [h0, h0 - 20.0], title="views")
    assert_png(out)
    # no candidates, no history
    assert_png(cp.views_figure(tmp_path / "bare.png", grid, torch.as_tensor(ctr), views[:1], None, None, []))


def test_views_figure_rejects_bad_shapes(tmp_path):
    grid, ctr = small_grid()
    views = np.array([[0.0, -0.3, 0.4]])
    with pytest.raises(ValueError):
        cp.views_figure(tmp_path / "a.png", grid, ctr[:2], views, None, None, [])
    with pytest.raises(ValueError):
        cp.views_figure(tmp_path / "b.png", grid, ctr, views[:, :2], None, None, [])
    with pytest.raises(ValueError):
        cp.views_figure(tmp_path / "c.png", grid, ctr, views, np.zeros((4, 3)), np.zeros(3), [])
    with pytest.raises(ValueError):
        cp.views_figure(tmp_path / "d.png", grid, ctr, views, None, np.zeros(3), [])


# ---------------------------------------------------------------------------------------------------------------
# Error after each acquisition (Fig. 6)
# ---------------------------------------------------------------------------------------------------------------


def test_acquisition_series_excludes_declutter_views():
    views, touches = cp.acquisition_series(declutter_episode())
    assert views == [10.0, 8.0, 6.0]  # the views at steps 1 and 3 precede the pick at step 4
    assert touches == [5.0, 4.0]  # the failed touch counts
    v_t, t_t = cp.acquisition_series(declutter_episode(), "trans_err_mm")
    assert v_t == [20.0, 16.0, 12.0] and t_t == [10.0, 8.0]
    # no push / pick: every view counts; blank values are NaN
    plain = [row(0, "reset", 9.0), row(1, "view", 7.0), {"step": "2", "action": "view", "adi_mm": ""},
             row(3, "stop", 7.0)]
    views, touches = cp.acquisition_series(plain)
    assert views[0] == 7.0 and np.isnan(views[1]) and len(views) == 2 and touches == []
    assert cp.acquisition_series([]) == ([], [])


def test_error_curves_figure(tmp_path):
    short = [row(0, "reset", 30.0), row(1, "view", 12.0), row(2, "touch", 9.0), row(3, "stop", 9.0)]
    static = [row(0, "reset", 30.0), row(1, "view", 25.0), row(2, "stop", 25.0)]
    episodes = {"visuo-tactile": [declutter_episode(), short], "static": [static, static]}
    assert_png(cp.error_curves_figure(tmp_path / "err.png", episodes, title="Fig. 6"))
    # errors over several decades: log axis
    wide = [row(0, "reset", 300.0), row(1, "view", 100.0), row(2, "view", 3.0), row(3, "touch", 0.5)]
    assert_png(cp.error_curves_figure(tmp_path / "wide.png", {"m": [wide]}))
    with pytest.raises(ValueError):
        cp.error_curves_figure(tmp_path / "none.png", {})
    with pytest.raises(ValueError):
        cp.error_curves_figure(tmp_path / "bad.png", {"m": [["not a row"]]})
    assert_png(cp.error_curves_figure(tmp_path / "mean.png", episodes, stat="mean"))
    with pytest.raises(ValueError, match="stat"):
        cp.error_curves_figure(tmp_path / "x.png", episodes, stat="mode")


def test_error_curve_statistics():
    """The median line and its 25-75 % band ignore one lost episode; the mean and its std do not."""
    series = [[2.0], [3.0], [4.0], [5.0], [200.0], [7.0, 1.0]]
    mid, lo, hi, n = cp._stats(series, 0, "median")
    assert (mid, n) == (4.5, 6) and lo == pytest.approx(3.25) and hi == pytest.approx(6.5)
    m, lo_m, hi_m, _ = cp._stats(series, 0, "mean")
    assert m == pytest.approx(221.0 / 6) and hi_m - m == pytest.approx(m - lo_m) and hi_m > 100
    assert cp._stats(series, 1, "median")[::3] == (1.0, 1)  # only the episodes that reached index 1
    assert np.isnan(cp._stats(series, 2)[0]) and cp._stats(series, 2)[3] == 0


def test_load_episode_rows(tmp_path):
    def write(task, method, seed, rows, finished=True):
        d = tmp_path / task / method / f"seed{seed:03d}"
        d.mkdir(parents=True)
        with open(d / "steps.csv", "w", newline="") as fh:
            w = csv.DictWriter(fh, fieldnames=list(rows[0]))
            w.writeheader()
            w.writerows(rows)
        if finished:
            (d / "summary.json").write_text(json.dumps({"method": method}))

    write("clutter-a", "vt", 0, declutter_episode())
    write("clutter-a", "vt", 1, declutter_episode(), finished=False)  # still running: skipped
    write("clutter-b", "vt", 0, declutter_episode())
    write("clutter-b", "static", 0, [row(0, "reset", 3.0), row(1, "view", 2.0)])
    got = cp.load_episode_rows(tmp_path)
    assert sorted(got) == ["static", "vt"] and len(got["vt"]) == 2 and len(got["static"]) == 1
    assert cp.acquisition_series(got["vt"][0]) == ([10.0, 8.0, 6.0], [5.0, 4.0])
    only_a = cp.load_episode_rows(tmp_path, task="clutter-a")
    assert list(only_a) == ["vt"] and len(only_a["vt"]) == 1
    assert cp.load_episode_rows(tmp_path, task=["clutter-a", "clutter-b"]).keys() == got.keys()
    with pytest.raises(FileNotFoundError):
        cp.load_episode_rows(tmp_path / "missing")

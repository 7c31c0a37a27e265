"""The benchmark report of a sweep folder (Tables V, VI, VII and Fig. 16) on a hand-written sweep with known numbers."""
import dataclasses
import shutil

import matplotlib.image as mpimg
import numpy as np
import pytest

from activetouch.experiments import tables
from activetouch.experiments.plots import METHOD_COLORS, panel_layout
from activetouch.experiments.records import STEP_COLUMNS, StepWriter, write_json_atomic
from activetouch.experiments.report import build_report, format_report, held_nll, nll_curves
from activetouch.experiments.runner import EpisodeConfig, episode_dir

THRESHOLD = {"mug-0": 20.0, "box-0": 100.0}
#: NLL after each step (step 0 first) of every episode; mug-0 / rumi / seed 1 ends early (APC convergence).
NLL = {
    ("mug-0", "rumi", 0): [40, 30, 25, 18, 15, 14],  # success (min 14 < 20), cum 142
    ("mug-0", "rumi", 1): [40, 22, 19, 16],  # success, cum 97, ended after 3 steps
    ("mug-0", "rumi", 2): [40, 35, 30, 28, 26, 24],  # failure, cum 183
    ("mug-0", "gpvr", 0): [40, 38, 36, 34, 32, 30],  # failure, cum 210
    ("mug-0", "gpvr", 1): [40, 39, 37, 35, 33, 31],  # failure, cum 215
    ("mug-0", "gpvr", 2): [40, 36, 30, 25, 21, 19],  # success, cum 171
    ("box-0", "rumi", 0): [900, 500, 300, 150, 90, 80],  # success, cum 2020
    ("box-0", "rumi", 1): [900, 600, 400, 200, 120, 95],  # success, cum 2315
    ("box-0", "rumi", 2): [900, 800, 700, 600, 500, 400],  # failure, cum 3900
    ("box-0", "gpvr", 0): [900, 850, 800, 750, 700, 650],  # failure, cum 4650
    ("box-0", "gpvr", 1): [900, 880, 860, 840, 820, 800],  # failure, cum 5100
    ("box-0", "gpvr", 2): [900, 870, 840, 810, 780, 750],  # failure, cum 4950
}
STRICT = {("mug-0", "rumi", 0), ("box-0", "rumi", 1)}
REPLAN_STEPS = (1, 4)  # the other steps reuse a queued action: 0 s of planning, as the planners write


def _timing(method, seed, t):
    """Per-step seconds. On planning steps field_s = 0.1 (seed + 1) + 0.01 t, dynamics_s = 0.5, cost_s = 0.2 (rumi)
    / 0.3 (gpvr), plan_s = 0.8; update_s = 0.01 (seed + 1) and step_s = 0.04 on every step. GPVR refits its GP
    (gp_fit_s 1.5 on planning steps, 1.2 on the others) and recaches the field (+0.05 s) at every step."""
    planned = t in REPLAN_STEPS
    gp = method == "gpvr"
    row = {"replanned": int(planned), "update_s": 0.01 * (seed + 1), "step_s": 0.04,
           "field_s": 0.1 * (seed + 1) + 0.01 * t if planned else 0.0, "dynamics_s": 0.5 if planned else 0.0,
           "cost_s": (0.3 if gp else 0.2) if planned else 0.0, "plan_s": 0.8 if planned else 0.001}
    if gp:
        row["field_s"] += 0.05
        row["gp_fit_s"] = 1.5 if planned else 1.2
    return row


COLUMNS = STEP_COLUMNS + tuple(c for c in ("gp_fit_s",) if c not in STEP_COLUMNS)


def _episode(root, task, method, seed, nll, **config):
    d = episode_dir(root, task, method, seed)
    with StepWriter(d / "steps.csv", COLUMNS) as w:
        for t, v in enumerate(nll):
            row = {"step": t, "nll": float(v), "apc": 0.01, "mean_rot_err_deg": 5.0}
            if t:
                row.update(_timing(method, seed, t))
            w.write(row)
    cfg = dataclasses.asdict(EpisodeConfig(task=task, method=method, seed=seed, **config))
    write_json_atomic(d / "summary.json", {
        "task": task, "method": method, "seed": seed, "nll_threshold": THRESHOLD[task],
        "success": bool(min(nll) < THRESHOLD[task]), "strict_success": (task, method, seed) in STRICT,
        "cumulative_nll": float(sum(nll)), "min_nll": float(min(nll)), "steps": len(nll) - 1, "config": cfg})
    return d


@pytest.fixture(scope="module")
def sweep(tmp_path_factory):
    root = tmp_path_factory.mktemp("sweep")
    for (task, method, seed), nll in NLL.items():
        _episode(root, task, method, seed, nll)
    return root


@pytest.fixture(scope="module")
def report(sweep):
    return build_report(sweep)


def _row(rows, task, method, **extra):
    (r,) = [r for r in rows if r["task"] == task and r["method"] == method
            and all(r.get(k) == v for k, v in extra.items())]
    return r


def test_table_v_successes_wilson_and_strict(report):
    r = _row(report.table_v, "mug-0", "rumi")
    assert (r["successes"], r["runs"], r["strict_successes"]) == (2, 3, 1)
    assert r["wilson_lo"] == pytest.approx(0.2077, abs=1e-3) and r["wilson_hi"] == pytest.approx(0.9385, abs=1e-3)
    assert (r["paper_successes"], r["paper_runs"]) == (9, 10)
    r = _row(report.table_v, "box-0", "gpvr")
    assert (r["successes"], r["runs"], r["wilson_lo"], r["strict_successes"]) == (0, 3, 0.0, 0)
    assert r["wilson_hi"] == pytest.approx(0.5615, abs=1e-3)  # Wilson upper bound of 0/3
    assert r["paper_successes"] == 4
    # the paper's grid is kept: tasks and methods that did not run show "-" beside the paper's numbers
    r = _row(report.table_v, "drill-1", "slide")
    assert r["successes"] is None and r["paper_successes"] == 10
    md = report.table_v_md.read_text()
    assert "| mug-0 | 2/3 [0.21, 0.94] | 9/10 | 1/3 | - | 3/10 | - |" in md
    assert "| drill-0 | - | 10/10 | - |" in md


def test_table_v_totals_rows(report):
    r = _row(report.table_v, "mug total", "rumi")
    # only mug-0 ran: the total pools its 3 runs and the paper's total is over the same task
    assert r["is_total"] and r["tasks_in_total"] == "mug-0"
    assert (r["successes"], r["runs"], r["paper_successes"], r["paper_runs"]) == (2, 3, 9, 10)
    r = _row(report.table_v, "drill total", "gpvr")
    assert r["successes"] is None and (r["paper_successes"], r["paper_runs"]) == (1, 30)  # published total
    md = report.table_v_md.read_text()
    assert "| **mug total** | 2/3 [0.21, 0.94] \u2020 | 9/10 \u2020 | 1/3 \u2020 |" in md
    assert "| **drill total** | - | 26/30 | - |" in md


def test_totals_of_complete_objects_pool_runs_and_sum_medians():
    ss = []
    for k, (wins, cums) in enumerate([(2, [100, 200, 300]), (1, [50, 60, 70]), (3, [10, 40, 20])]):
        for seed in range(3):
            ss.append({"task": f"mug-{k}", "method": "info-only", "seed": seed, "success": seed < wins,
                       "strict_success": False, "cumulative_nll": cums[seed]})
    r = _row(tables.success_rows(ss), "mug total", "info-only")
    lo, hi = tables.wilson_interval(6, 9)
    assert (r["successes"], r["runs"], r["paper_successes"], r["paper_runs"]) == (6, 9, 14, 30)
    assert (r["wilson_lo"], r["wilson_hi"]) == (lo, hi) and r["tasks_in_total"] == "mug-0 mug-1 mug-2"
    r = _row(tables.cumulative_nll_rows(ss), "mug total", "info-only")
    assert r["median_cumulative_nll"] == 200 + 60 + 20  # sum of the three medians
    assert r["paper_median_cumulative_nll"] == 4444  # as published
    assert "\u2020" not in tables.success_markdown(tables.success_rows(ss)).split("\n\n")[0]


def test_paper_totals_are_the_sums_of_their_rows():
    for obj in tables.OBJECTS:
        for m in tables.PAPER_METHODS:
            rows = [f"{obj}-{k}" for k in range(3)]
            assert tables.PAPER_SUCCESS_TOTALS[obj][m] == sum(tables.PAPER_SUCCESSES[t][m] for t in rows)
            s = sum(tables.PAPER_CUMULATIVE_NLL[t][m] for t in rows)
            if (obj, m) == ("mug", "info-only"):
                assert (s, tables.PAPER_CUMULATIVE_NLL_TOTALS[obj][m]) == (3872, 4444)  # the paper's own slip
            else:
                assert tables.PAPER_CUMULATIVE_NLL_TOTALS[obj][m] == s


def test_table_vi_median_cumulative_nll_and_totals(report):
    assert _row(report.table_vi, "mug-0", "rumi")["median_cumulative_nll"] == 142  # of 142, 97, 183
    assert _row(report.table_vi, "mug-0", "gpvr")["median_cumulative_nll"] == 210  # of 210, 215, 171
    assert _row(report.table_vi, "box-0", "rumi")["median_cumulative_nll"] == 2315  # of 2020, 2315, 3900
    assert _row(report.table_vi, "box-0", "rumi")["paper_median_cumulative_nll"] == 12744
    r = _row(report.table_vi, "box total", "gpvr")
    assert r["median_cumulative_nll"] == 4950 and r["paper_median_cumulative_nll"] == 24276
    md = report.table_vi_md.read_text()
    assert "| mug-0 | 142 | 925 | - | 1447 | - | 1691 | 210 | 1691 | - | 2478 |" in md
    assert "| **drill total** | - | 46204 |" in md


def test_table_vii_means_are_over_the_planning_steps_only(report):
    rows = report.table_vii
    r = _row(rows, "mug-0", "rumi", column="field_s")
    # planning steps 1 and 4 of seeds 0 and 2, step 1 of seed 1 (it ended after step 3)
    vals = [0.11, 0.14, 0.21, 0.31, 0.34]
    assert r["steps"] == "planned" and r["n_steps"] == 5 and r["n_episodes"] == 3
    assert r["mean_s"] == pytest.approx(np.mean(vals))  # the 8 steps that did not plan (0 s) are left out
    assert r["std_s"] == pytest.approx(np.std(vals))
    assert r["std_of_episode_means_s"] == pytest.approx(np.std([0.125, 0.21, 0.325]))
    assert (r["paper_mean_s"], r["paper_std_s"]) == (0.061, 0.001)
    r = _row(rows, "mug-0", "rumi", column="cost_s")
    assert r["mean_s"] == pytest.approx(0.2) and r["paper_mean_s"] == 0.178  # "our cost lookup"
    r = _row(rows, "box-0", "gpvr", column="cost_s")
    assert r["process"] == "GP cost lookup" and r["mean_s"] == pytest.approx(0.3) and r["paper_mean_s"] == 0.184
    r = _row(rows, "box-0", "gpvr", column="gp_fit_s")  # refit at every executed step: averaged over all 15
    assert r["steps"] == "all" and r["n_steps"] == 15 and r["mean_s"] == pytest.approx((2 * 1.5 + 3 * 1.2) / 5)
    assert r["paper_mean_s"] == 2.541
    r = _row(rows, "box-0", "gpvr", column="field_s")
    assert r["steps"] == "all" and r["mean_s"] == pytest.approx((0.05 * 15 + 0.11 + 0.14 + 0.21 + 0.24 + 0.31 + 0.34) / 15)
    r = _row(rows, "box-0", "gpvr", column="dynamics_s")
    assert r["steps"] == "planned" and r["n_steps"] == 6 and r["mean_s"] == pytest.approx(0.5)
    assert not [r for r in rows if r["method"] == "rumi" and r["column"] == "gp_fit_s"]  # GPVR's only
    # belief update and sim step: every executed step (5 + 3 + 5 of mug-0 rumi)
    r = _row(rows, "mug-0", "rumi", column="update_s")
    assert r["n_steps"] == 13 and r["mean_s"] == pytest.approx((5 * 0.01 + 3 * 0.02 + 5 * 0.03) / 13)
    assert r["paper_mean_s"] is None
    md = report.table_vii_md.read_text()
    assert f"| mug-0 | RUMI | 0.222 ({np.std(vals):.3f}) | 0.500 (0.000) | 0.200 (0.000) | - |" in md
    assert "| mug-0 | *paper, sim mug 0 (RTX 4090)* | 0.061 (0.001) | 0.724 (0.012) |" in md
    assert "| box-0 | GPVR | 0.140 (0.122) * | 0.500 (0.000) | 0.300 (0.000) | 1.320 (0.147) * |" in md


def test_early_ending_episode_is_held_at_its_last_nll(report, sweep):
    M = held_nll([[3.0, 2.0], [5.0, 4.0, 1.0, 0.5]])
    assert M.tolist() == [[3, 2, 2, 2], [5, 4, 1, 0.5]]
    from activetouch.experiments.records import load_summaries, read_steps

    eps = [(s, read_steps(f"{s['_dir']}/steps.csv")) for s in load_summaries(sorted(sweep.rglob("seed*")))]
    c = nll_curves(eps)["mug-0"]["rumi"]
    assert c["values"].shape == (3, 6) and c["held"] == 1
    short = [i for i, row in enumerate(c["values"]) if row[1] == 22][0]
    assert c["values"][short].tolist() == [40, 22, 19, 16, 16, 16]
    assert c["median"][5] == 16  # median of 14, 16 (held), 24
    assert c["q25"][5] == pytest.approx(15) and c["q75"][5] == pytest.approx(20)


def test_figure_is_a_drawn_grid_of_the_tasks_present(report):
    objs, confs, where = panel_layout(["mug-0", "box-0"])
    assert (objs, confs, where) == (["mug", "box"], [0], {"mug-0": (0, 0), "box-0": (1, 0)})
    objs, confs, where = panel_layout(list(tables.PAPER_TASKS))
    assert objs == ["mug", "drill", "box"] and confs == [0, 1, 2] and where["drill-2"] == (1, 2)
    assert report.figure.name == "nll_curves.png" and report.figure.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    img = mpimg.imread(report.figure)[..., :3]
    assert img.shape[0] > img.shape[1]  # two rows (mug, box) of one column (configuration 0)
    assert img.std() > 0.05  # not blank
    for m in ("rumi", "gpvr"):  # a line per method, in its colour
        rgb = np.array([int(METHOD_COLORS[m][i:i + 2], 16) / 255 for i in (1, 3, 5)])
        assert (np.abs(img - rgb).max(axis=-1) < 0.02).sum() > 200


def test_report_md_names_the_settings_and_embeds_the_tables(report, sweep):
    text = report.report_md.read_text()
    assert report.out_dir == sweep / "report" and report.n_episodes == 12
    assert "| particles | `100` |" in text and "| beta_t | `0.03` |" in text and "seeds 0-2" in text
    assert "![nll after each execution step](nll_curves.png)" in text and "hold their last nll" in text
    for p in (report.table_v_csv, report.table_vi_csv, report.table_vii_csv):
        assert p.exists() and f"({p.name})" in text
    assert report.markdown["v"] in text and report.markdown["vii"] in text
    assert report.settings["particles"] == 100 and "task" not in report.settings
    out = format_report(report)
    assert "particles = 100" in out and report.markdown["vi"] in out and str(report.figure) in out


def test_out_dir_and_errors(sweep, tmp_path):
    r = build_report(sweep, tmp_path / "elsewhere")
    assert r.report_md == tmp_path / "elsewhere" / "report.md" and r.table_v_md.exists()
    with pytest.raises(ValueError, match="no finished episodes under"):
        build_report(tmp_path / "empty")
    mixed = tmp_path / "mixed"
    shutil.copytree(sweep, mixed)
    _episode(mixed, "mug-0", "rumi", 3, NLL[("mug-0", "rumi", 0)], steps=30)
    with pytest.raises(ValueError, match="different settings"):
        build_report(mixed)
    twice = tmp_path / "twice"
    shutil.copytree(sweep, twice / "a")
    shutil.copytree(sweep / "mug-0", twice / "b" / "mug-0")
    with pytest.raises(ValueError, match="occurs twice"):
        build_report(twice)

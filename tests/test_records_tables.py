"""Result files (written as an episode goes, resumable) and the results table."""
import json

import pytest

from activetouch.experiments.metrics import first_success_step
from activetouch.experiments.records import StepWriter, is_finished, load_summaries, read_steps, write_json_atomic
from activetouch.experiments.tables import aggregate, markdown_table


def test_step_rows_are_on_disk_before_close(tmp_path):
    w = StepWriter(tmp_path / "steps.csv")
    w.write({"step": 0, "nll": 123.456789, "apc": 0.01, "in_contact": False})
    w.write({"step": 1, "nll": 50.0, "apc": 0.005, "in_contact": True})
    rows = read_steps(tmp_path / "steps.csv")  # read while the writer is still open: a crash loses nothing
    assert [r["step"] for r in rows] == ["0", "1"]
    assert float(rows[0]["nll"]) == pytest.approx(123.457, rel=1e-5)
    assert rows[1]["in_contact"] == "1"
    w.close()


def test_step_row_needs_step(tmp_path):
    with StepWriter(tmp_path / "s.csv") as w, pytest.raises(ValueError, match="step"):
        w.write({"nll": 1.0})


def test_summary_marks_episode_finished(tmp_path):
    assert not is_finished(tmp_path)
    (tmp_path / "summary.json").write_text("{truncated")  # a crash mid-write of a non-atomic writer
    assert not is_finished(tmp_path)
    write_json_atomic(tmp_path / "summary.json", {"success": True, "min_nll": 12.5})
    assert is_finished(tmp_path)
    assert json.loads((tmp_path / "summary.json").read_text())["min_nll"] == 12.5


def _summary(task, method, seed, success, cum):
    return {"task": task, "method": method, "seed": seed, "success": success, "cumulative_nll": cum,
            "median_plan_s": 0.3, "initial_nll": 30.0, "final_mean_rot_err_deg": 2.0 * seed,
            "success_at_step0": seed < 2, "strict_success": seed % 2 == 0,
            "first_strict_success_step": seed if seed % 2 == 0 else None}


def test_aggregate_counts_successes_with_wilson_interval():
    ss = [_summary("mug-0", "rumi", s, s != 3, 100.0 * (s + 1)) for s in range(10)]
    agg = aggregate(ss)
    a = agg[("mug-0", "rumi")]
    assert (a["successes"], a["runs"]) == (9, 10)
    assert a["median_cumulative_nll"] == pytest.approx(550.0)
    assert (a["rot_successes"], a["rot_runs"]) == (5, 10)  # rotation errors 0, 2, ..., 18 deg: 5 below 10
    assert 0.55 < a["wilson_lo"] < 0.6 and 0.98 < a["wilson_hi"] <= 1.0
    assert (a["at_step0"], a["strict_successes"], a["strict_runs"]) == (2, 5, 10)
    assert a["median_strict_step"] == 4.0  # steps 0, 2, 4, 6, 8
    table = markdown_table(ss)
    assert "| mug-0 | rumi | 9/10 |" in table and "| 9/10 |" in table  # ours and the paper's Table V value
    assert "| 2 | 5/10 | 4 |" in table


def test_strict_success_needs_low_nll_and_low_rotation_error_at_the_same_step():
    nll = [15.0, 40.0, 12.0, 8.0]
    rot = [95.0, 5.0, 30.0, 4.0]
    assert first_success_step(nll, 20.0) == 0  # Table III alone: the vision-only belief already "succeeds"
    assert first_success_step(nll, 20.0, rot) == 3  # steps 1 and 2 meet only one of the two conditions
    assert first_success_step(nll, 5.0, rot) is None
    with pytest.raises(ValueError, match="one rotation error per step"):
        first_success_step(nll, 20.0, rot[:2])


def test_old_summaries_get_strict_success_from_their_steps(tmp_path):
    with StepWriter(tmp_path / "steps.csv") as w:
        for t, (n, r) in enumerate([(15.0, 95.0), (9.0, 3.0)]):
            w.write({"step": t, "nll": n, "mean_rot_err_deg": r})
    write_json_atomic(tmp_path / "summary.json", {"task": "mug-0", "method": "rumi", "nll_threshold": 20.0})
    (s,) = load_summaries([tmp_path])
    assert s["success_at_step0"] and s["strict_success"] and s["first_strict_success_step"] == 1

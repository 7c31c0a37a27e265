"""Result tables of a sweep, side by side with the RUMI paper's Tables V (successes out of 10) and VI (median
cumulative NLL)."""
from __future__ import annotations

from collections import defaultdict
from typing import Any, Iterable

import numpy as np

from activetouch.experiments.metrics import ROT_SUCCESS_DEG, wilson_interval

#: RUMI Table V: successes out of 10 runs (Ours, InfoOnly, ReachOnly, GPVR, Slide).
PAPER_SUCCESSES: dict[str, dict[str, int]] = {
    "mug-0": {"rumi": 9, "info-only": 3, "reach-only": 7, "gpvr": 2, "slide": 0},
    "mug-1": {"rumi": 9, "info-only": 5, "reach-only": 8, "gpvr": 0, "slide": 0},
    "mug-2": {"rumi": 10, "info-only": 6, "reach-only": 10, "gpvr": 7, "slide": 0},
    "drill-0": {"rumi": 10, "info-only": 9, "reach-only": 5, "gpvr": 1, "slide": 6},
    "drill-1": {"rumi": 9, "info-only": 9, "reach-only": 7, "gpvr": 0, "slide": 10},
    "drill-2": {"rumi": 7, "info-only": 7, "reach-only": 7, "gpvr": 0, "slide": 0},
    "box-0": {"rumi": 9, "info-only": 9, "reach-only": 8, "gpvr": 4, "slide": 0},
    "box-1": {"rumi": 10, "info-only": 9, "reach-only": 10, "gpvr": 4, "slide": 10},
    "box-2": {"rumi": 6, "info-only": 6, "reach-only": 4, "gpvr": 1, "slide": 1},
}

#: RUMI Table VI: median cumulative nll over 10 runs.
PAPER_CUMULATIVE_NLL: dict[str, dict[str, float]] = {
    "mug-0": {"rumi": 925, "info-only": 1447, "reach-only": 1691, "gpvr": 1691, "slide": 2478},
    "mug-1": {"rumi": 1447, "info-only": 1598, "reach-only": 1591, "gpvr": 2252, "slide": 2610},
    "mug-2": {"rumi": 1013, "info-only": 827, "reach-only": 1104, "gpvr": 1239, "slide": 2467},
    "drill-0": {"rumi": 7975, "info-only": 10425, "reach-only": 15401, "gpvr": 22725, "slide": 8369},
    "drill-1": {"rumi": 13750, "info-only": 12473, "reach-only": 21627, "gpvr": 22835, "slide": 6049},
    "drill-2": {"rumi": 24479, "info-only": 23892, "reach-only": 27471, "gpvr": 33419, "slide": 69321},
    "box-0": {"rumi": 12744, "info-only": 12811, "reach-only": 10718, "gpvr": 24276, "slide": 16527},
    "box-1": {"rumi": 8109, "info-only": 7412, "reach-only": 6596, "gpvr": 10183, "slide": 4601},
    "box-2": {"rumi": 23923, "info-only": 24675, "reach-only": 43254, "gpvr": 31196, "slide": 23157},
}


def _median(v) -> float:
    return float(np.median(v)) if len(v) else float("nan")


def aggregate(summaries: Iterable[dict[str, Any]]) -> dict[tuple[str, str], dict[str, Any]]:
    """Group episode summaries by (task, method): successes, runs, Wilson 95 % interval, median cumulative NLL."""
    groups: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for s in summaries:
        groups[(s["task"], s["method"])].append(s)
    out = {}
    for key, ss in sorted(groups.items()):
        k, n = sum(bool(s["success"]) for s in ss), len(ss)
        lo, hi = wilson_interval(k, n)
        plan = [s["median_plan_s"] for s in ss if s.get("median_plan_s") is not None]
        rot = [s["final_mean_rot_err_deg"] for s in ss if s.get("final_mean_rot_err_deg") is not None]
        rot_ok = sum(r < ROT_SUCCESS_DEG for r in rot)
        strict = [bool(s["strict_success"]) for s in ss if "strict_success" in s]
        out[key] = {"successes": k, "runs": n, "wilson_lo": lo, "wilson_hi": hi,
                    "at_step0": sum(bool(s.get("success_at_step0", False)) for s in ss),
                    "strict_successes": sum(strict), "strict_runs": len(strict),
                    "median_strict_step": _median([s["first_strict_success_step"] for s in ss
                                                   if s.get("first_strict_success_step") is not None]),
                    "median_cumulative_nll": float(np.median([s["cumulative_nll"] for s in ss])),
                    "median_initial_nll": float(np.median([s.get("initial_nll", np.nan) for s in ss])),
                    "median_final_rot_err_deg": _median(rot),
                    "rot_successes": rot_ok, "rot_runs": len(rot),
                    "median_plan_s": _median(plan)}
    return out


def markdown_table(summaries: Iterable[dict[str, Any]]) -> str:
    """A markdown table of our results next to the paper's (Table V / VI).

    Columns: successes by Table III (min NLL below the threshold) with their Wilson 95 % interval and how many of
    them the vision-only belief already had at step 0; strict successes (NLL below the threshold and weighted
    rotation error below ``ROT_SUCCESS_DEG`` at the same step) and the median step they first held; median
    cumulative NLL; the belief's NLL at step 0 and weighted rotation error at the end; median planning time.
    """
    agg = aggregate(summaries)
    lines = ["| task | method | successes (Tab. III) | 95 % CI | paper (Tab. V) | of them at step 0 "
             f"| strict successes (+ rot. < {ROT_SUCCESS_DEG:.0f} deg) | median step of strict success | median cum. NLL | paper (Tab. VI) "
             "| median NLL at step 0 | median final weighted rot. err (deg) | median plan s |",
             "|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    for (task, method), a in agg.items():
        ps = PAPER_SUCCESSES.get(task, {}).get(method)
        pn = PAPER_CUMULATIVE_NLL.get(task, {}).get(method)
        strict = f"{a['strict_successes']}/{a['strict_runs']}" if a["strict_runs"] else "-"
        step = "-" if np.isnan(a["median_strict_step"]) else f"{a['median_strict_step']:.0f}"
        lines.append(f"| {task} | {method} | {a['successes']}/{a['runs']} | [{a['wilson_lo']:.2f}, {a['wilson_hi']:.2f}] "
                     f"| {'-' if ps is None else f'{ps}/10'} | {a['at_step0']} | {strict} | {step} "
                     f"| {a['median_cumulative_nll']:.0f} | {'-' if pn is None else f'{pn:.0f}'} "
                     f"| {a['median_initial_nll']:.1f} | {a['median_final_rot_err_deg']:.1f} "
                     f"| {a['median_plan_s']:.2f} |")
    return "\n".join(lines)

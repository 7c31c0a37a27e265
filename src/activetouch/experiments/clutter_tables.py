"""The visuo-tactile paper's Table I from finished clutter episodes: ADI (Eq. 28) and translation error (Eq. 26) per
target object and method (mean +- std over seeds), their mean and median (+- median absolute deviation) over all
episodes, next to the paper's robot numbers; plus the decluttering's grasp and push success rates (Sec. III-B)."""
from __future__ import annotations

import statistics
from typing import Any, Iterable, Sequence

#: Table I of the paper (real robot, 4 target objects): (ADI mm mean, std, L2 translation mm mean, std) for the
#: mean and the median rows (the median row's +- is the median absolute deviation).
PAPER_TABLE_I = {
    "tiqf-static": {"mean": (85.63, 87.28, 203.99, 111.61), "median": (45.85, 7.59, 164.74, 25.66)},
    "tiqf-active-vision": {"mean": (31.53, 24.15, 130.60, 77.55), "median": (25.35, 12.23, 128.71, 55.99)},
    "tiqf-declutter-vision": {"mean": (28.88, 35.72, 63.84, 77.88), "median": (11.90, 2.06, 29.23, 7.40)},
    "tiqf-visuo-tactile": {"mean": (7.99, 3.50, 12.69, 4.28), "median": (7.66, 1.94, 14.31, 0.94)},
}
METHOD_ORDER = tuple(PAPER_TABLE_I)
LABELS = {"tiqf-static": "static vision", "tiqf-active-vision": "active vision, no decluttering",
          "tiqf-declutter-vision": "active vision, decluttered", "tiqf-visuo-tactile": "visuo-tactile, decluttered",
          "tiqf-visuo-tactile-verify": "visuo-tactile, touches verify vision"}


def is_clutter_summary(s: dict[str, Any]) -> bool:
    return "final_adi_mm" in s


def _mean_std(x: list[float]) -> str:
    if not x:
        return "-"
    return f"{statistics.fmean(x):.1f} +- {statistics.pstdev(x) if len(x) > 1 else 0.0:.1f}"


def _median_mad(x: list[float]) -> str:
    if not x:
        return "-"
    m = statistics.median(x)
    return f"{m:.1f} +- {statistics.median([abs(v - m) for v in x]):.1f}"


def table_i_markdown(summaries: Sequence[dict[str, Any]]) -> str:
    """Markdown: one row per task (target: median +- median absolute deviation over its seeds) and the overall Mean
    (+- std) and Median (+- MAD) rows, then the paper's; per method ``ADI | L2 (trans)`` in mm. Then one row per
    method: successes, actions and the decluttering's grasp / push success rates."""
    ss = [s for s in summaries if is_clutter_summary(s)]
    methods = [m for m in METHOD_ORDER if any(s["method"] == m for s in ss)]
    methods += sorted({s["method"] for s in ss} - set(methods))
    tasks = sorted({s["task"] for s in ss})

    def vals(task, method, key):
        return [float(s[key]) for s in ss if s["method"] == method and (task is None or s["task"] == task)]

    head = "| target | " + " | ".join(f"{LABELS.get(m, m)}: ADI (mm) | L2 trans (mm)" for m in methods) + " |"
    out = [head, "|---|" + "---|---|" * len(methods)]
    for t in tasks:
        n = len(vals(t, methods[0], "final_adi_mm")) if methods else 0
        cells = [f"{_median_mad(vals(t, m, 'final_adi_mm'))} | {_median_mad(vals(t, m, 'final_trans_err_mm'))}"
                 for m in methods]
        out.append(f"| {t} ({n} seeds) | " + " | ".join(cells) + " |")
    out.append("| **Mean** | " + " | ".join(f"{_mean_std(vals(None, m, 'final_adi_mm'))} | "
                                         f"{_mean_std(vals(None, m, 'final_trans_err_mm'))}" for m in methods) + " |")
    out.append("| **Median** | " + " | ".join(f"{_median_mad(vals(None, m, 'final_adi_mm'))} | "
                                           f"{_median_mad(vals(None, m, 'final_trans_err_mm'))}" for m in methods) + " |")
    paper = []
    for row in ("mean", "median"):
        cells = []
        for m in methods:
            p = PAPER_TABLE_I.get(m, {}).get(row)
            cells.append(f"{p[0]:.1f} +- {p[1]:.1f} | {p[2]:.1f} +- {p[3]:.1f}" if p else "- | -")
        paper.append(f"| paper {row.title()} | " + " | ".join(cells) + " |")
    out += paper
    lines = ["", "| method | episodes | success (final ADI < 10 mm) | views | touches | grasps (success) | "
                 "pushes (success) | median wall s |", "|---|---|---|---|---|---|---|---|"]
    for m in methods:
        mm = [s for s in ss if s["method"] == m]
        picks = sum(int(s["picks"]) for s in mm)
        pushes = sum(int(s["pushes"]) for s in mm)
        pk = sum(round((s.get("pick_success_rate") or 0) * int(s["picks"])) for s in mm)
        pu = sum(round((s.get("push_success_rate") or 0) * int(s["pushes"])) for s in mm)
        grasp = f"{picks} ({100 * pk / picks:.0f} %)" if picks else "0 (-)"
        push = f"{pushes} ({100 * pu / pushes:.0f} %)" if pushes else "0 (-)"
        lines.append(f"| {m} | {len(mm)} | {sum(bool(s['success']) for s in mm)}/{len(mm)} | "
                     f"{statistics.fmean(int(s['views']) for s in mm):.1f} | "
                     f"{statistics.fmean(int(s['touches']) for s in mm):.1f} | {grasp} | {push} | "
                     f"{statistics.median(float(s['wall_s']) for s in mm):.0f} |")
    return "\n".join(out + lines)


def rows_for(summaries: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """Per (task, method): episodes, mean ADI and translation error (mm), for scripts and tests."""
    acc: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for s in summaries:
        if is_clutter_summary(s):
            acc.setdefault((s["task"], s["method"]), []).append(s)
    return [{"task": t, "method": m, "episodes": len(v),
             "adi_mm": statistics.fmean(float(s["final_adi_mm"]) for s in v),
             "trans_mm": statistics.fmean(float(s["final_trans_err_mm"]) for s in v)} for (t, m), v in sorted(acc.items())]

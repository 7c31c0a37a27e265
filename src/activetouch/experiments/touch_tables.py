"""The touch paper's Table I from finished grasp episodes: grasp success rate with its Wilson 95 % interval and the
mean +- std number of localisation actions, per method, next to the paper's robot numbers."""
from __future__ import annotations

import statistics
from typing import Any, Iterable, Sequence

from activetouch.experiments.metrics import wilson_interval

#: Table I of the paper (30 real-robot runs each): success rate, its Wilson 95 % CI, mean +- std iterations.
PAPER_TABLE_I: dict[str, tuple[float, tuple[float, float], float, float]] = {
    "touch-ig": (0.80, (0.63, 0.90), 9.37, 3.47),
    "touch-uninformed": (0.23, (0.12, 0.41), 12.53, 3.68),
    "touch-max-contact": (0.33, (0.19, 0.51), 13.77, 2.76),
}
METHOD_ORDER = ("touch-ig", "touch-uninformed", "touch-max-contact")


def is_grasp_summary(s: dict[str, Any]) -> bool:
    return "iterations" in s and "grasped" in s


def table_i_rows(summaries: Iterable[dict[str, Any]]) -> list[dict[str, Any]]:
    """One row per method over all its grasp episodes (every task and seed)."""
    by_method: dict[str, list[dict[str, Any]]] = {}
    for s in summaries:
        if is_grasp_summary(s):
            by_method.setdefault(s["method"], []).append(s)
    order = [m for m in METHOD_ORDER if m in by_method] + sorted(set(by_method) - set(METHOD_ORDER))
    rows = []
    for m in order:
        ss = by_method[m]
        n, k = len(ss), sum(bool(s["success"]) for s in ss)
        it = [int(s["iterations"]) for s in ss]
        it_ok = [int(s["iterations"]) for s in ss if s["success"]]
        lo, hi = wilson_interval(k, n)
        rows.append({"method": m, "runs": n, "successes": k, "success_rate": k / n, "ci_low": lo, "ci_high": hi,
                     "mean_iterations": statistics.fmean(it), "std_iterations": statistics.pstdev(it) if n > 1 else 0.0,
                     "mean_iterations_success": statistics.fmean(it_ok) if it_ok else None,
                     "grasped": sum(bool(s.get("grasped")) for s in ss),
                     "tasks": ", ".join(sorted({s["task"] for s in ss})),
                     "median_plan_s": statistics.median([s["median_plan_s"] for s in ss if s.get("median_plan_s")] or [0.0]),
                     "paper": PAPER_TABLE_I.get(m)})
    return rows


def table_i_markdown(summaries: Sequence[dict[str, Any]]) -> str:
    rows = table_i_rows(summaries)
    out = ["| method | runs | success rate [95 % CI] | paper | iterations mean +- std | paper | iterations of "
           "successes | grasps attempted | median plan s | tasks |",
           "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p = r["paper"]
        paper_rate = f"{p[0]:.2f} [{p[1][0]:.2f}, {p[1][1]:.2f}]" if p else "-"
        paper_it = f"{p[2]:.2f} +- {p[3]:.2f}" if p else "-"
        it_ok = f"{r['mean_iterations_success']:.2f}" if r["mean_iterations_success"] is not None else "-"
        out.append(f"| {r['method']} | {r['runs']} | {r['success_rate']:.2f} [{r['ci_low']:.2f}, {r['ci_high']:.2f}] "
                   f"({r['successes']}/{r['runs']}) | {paper_rate} | {r['mean_iterations']:.2f} +- "
                   f"{r['std_iterations']:.2f} | {paper_it} | {it_ok} | {r['grasped']} | {r['median_plan_s']:.2f} | "
                   f"{r['tasks']} |")
    return "\n".join(out)

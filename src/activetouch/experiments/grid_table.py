"""One table for a grid sweep (``activetouch sweep --grid``): every (task, method) pair that ran, with its success
rate, the family's headline metric and the wall time, so methods of different papers are compared on equal terms."""
from __future__ import annotations

import statistics
from typing import Any, Sequence


def _family(s: dict[str, Any]) -> str:
    if "final_adi_mm" in s:
        return "clutter"
    if "grasped" in s and "iterations" in s:
        return "grasp"
    return "rummage"


def _headline(family: str, ss: list[dict[str, Any]]) -> str:
    """The family's own measure, median over the pair's episodes."""
    if family == "clutter":
        return f"final ADI {statistics.median(float(s['final_adi_mm']) for s in ss):.1f} mm"
    if family == "grasp":
        return f"pokes {statistics.median(int(s['iterations']) for s in ss):.0f}"
    vals = [float(s["min_nll"]) for s in ss if s.get("min_nll") is not None]
    return f"min NLL {statistics.median(vals):.1f}" if vals else "-"


def grid_markdown(summaries: Sequence[dict[str, Any]]) -> str:
    """Markdown: one row per (task, method) with episodes, successes (the task's own criterion), the family's headline
    metric (median) and the median and total wall time."""
    by: dict[tuple[str, str], list[dict[str, Any]]] = {}
    for s in summaries:
        by.setdefault((s["task"], s["method"]), []).append(s)
    out = ["| task | family | method | episodes | success | headline (median) | median wall s | total wall s |",
           "|---|---|---|---|---|---|---|---|"]
    for (task, method), ss in sorted(by.items()):
        fam = _family(ss[0])
        k = sum(bool(s["success"]) for s in ss)
        walls = [float(s.get("wall_s") or 0.0) for s in ss]
        out.append(f"| {task} | {fam} | {method} | {len(ss)} | {k}/{len(ss)} | {_headline(fam, ss)} | "
                   f"{statistics.median(walls):.1f} | {sum(walls):.0f} |")
    total = sum(float(s.get("wall_s") or 0.0) for s in summaries)
    out.append(f"\n{len(by)} pairs, {len(summaries)} episodes, {total / 60:.1f} min of episode wall time in all")
    return "\n".join(out)

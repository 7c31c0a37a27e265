"""Result tables of a sweep, side by side with the RUMI paper's Tables V (successes out of 10), VI (median
cumulative NLL) and VII (run time per step by process).

:func:`markdown_table` is the one-row-per-(task, method) table that ``activetouch sweep`` / ``activetouch table``
print; :func:`success_rows`, :func:`cumulative_nll_rows` and :func:`timing_rows` (with their ``*_markdown``
renderings) are the paper-shaped tables of the benchmark report (:mod:`activetouch.experiments.report`).
"""
from __future__ import annotations

from collections import defaultdict
from typing import Any, Iterable, Sequence

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


# --------------------------------------------------------------------------------------------------------------
# The benchmark report's tables (activetouch.experiments.report): Tables V, VI and VII laid out like the paper's,
# ours beside the paper's, with the per-object totals rows.

#: The paper's objects (rows of Fig. 16, groups of Tables V / VI) and methods (columns), in the paper's order.
OBJECTS: tuple[str, ...] = ("mug", "drill", "box")
PAPER_TASKS: tuple[str, ...] = tuple(f"{o}-{k}" for o in OBJECTS for k in range(3))
PAPER_METHODS: tuple[str, ...] = ("rumi", "info-only", "reach-only", "gpvr", "slide")
METHOD_LABELS: dict[str, str] = {"rumi": "RUMI", "info-only": "InfoOnly", "reach-only": "ReachOnly",
                                 "gpvr": "GPVR", "slide": "Slide"}
#: Runs per task and method in the paper.
PAPER_RUNS = 10

#: The totals rows of Table V as published (each is the sum of its object's three rows).
PAPER_SUCCESS_TOTALS: dict[str, dict[str, int]] = {
    "mug": {"rumi": 28, "info-only": 14, "reach-only": 25, "gpvr": 9, "slide": 0},
    "drill": {"rumi": 26, "info-only": 25, "reach-only": 19, "gpvr": 1, "slide": 16},
    "box": {"rumi": 25, "info-only": 24, "reach-only": 22, "gpvr": 9, "slide": 11},
}

#: The totals rows of Table VI as published: sums of the three medians, except mug InfoOnly, which the paper prints as
#: 4444 while its rows (1447 + 1598 + 827) sum to 3872.
PAPER_CUMULATIVE_NLL_TOTALS: dict[str, dict[str, float]] = {
    "mug": {"rumi": 3385, "info-only": 4444, "reach-only": 4386, "gpvr": 5182, "slide": 7555},
    "drill": {"rumi": 46204, "info-only": 46790, "reach-only": 64499, "gpvr": 78979, "slide": 83739},
    "box": {"rumi": 44776, "info-only": 44898, "reach-only": 60568, "gpvr": 65655, "slide": 44285},
}

#: RUMI Table VII: mean (std) seconds per execution step, RTX 4090, sim mug 0 ("mug") and sim box 0 ("box").
PAPER_TIMES: dict[str, dict[str, tuple[float, float]]] = {
    "cache": {"mug": (0.061, 0.001), "box": (0.387, 0.002)},
    "dynamics": {"mug": (0.724, 0.012), "box": (1.242, 0.054)},
    "our cost lookup": {"mug": (0.178, 0.002), "box": (0.556, 0.021)},
    "GP fit": {"mug": (1.870, 0.066), "box": (2.541, 0.061)},
    "GP cost lookup": {"mug": (0.116, 0.002), "box": (0.184, 0.004)},
}
#: The tasks Table VII was measured on.
PAPER_TIME_TASKS: dict[str, str] = {"mug-0": "mug", "box-0": "box"}

#: Processes of Table VII: (key, steps.csv column, label, planning process?). Planning processes are averaged over
#: the steps that planned (``replanned`` = 1); the others over every executed step (step >= 1).
PROCESSES: tuple[tuple[str, str, str, bool], ...] = (
    ("cache", "field_s", "field cache (p(S_x), I~(x))", True),
    ("dynamics", "dynamics_s", "dynamics", True),
    ("cost", "cost_s", "cost lookup", True),
    ("gp_fit", "gp_fit_s", "GP fit", True),
    ("plan", "plan_s", "whole planning call", True),
    ("update", "update_s", "belief update", False),
    ("sim", "step_s", "sim step", False),
)
#: Planning processes that a method may also run on the steps that did not plan: GPVR refits its GP and recaches
#: the field at every execution step (the paper's "refit after every robot execution step"). When a method's rows
#: hold such a time above 0 on a step that did not plan, the process is averaged over every executed step.
EVERY_STEP_CAPABLE: tuple[str, ...] = ("field_s", "gp_fit_s")
#: Methods that run the shared cache and dynamics (the paper: "processes shared by all methods" that plan with them).
_PLANNING_METHODS = ("rumi", "info-only", "reach-only", "gpvr")


def object_of(task: str) -> str:
    """``"mug-2"`` -> ``"mug"`` (a task name without a ``-<configuration>`` suffix is its own object)."""
    head, sep, tail = task.rpartition("-")
    return head if sep and tail.isdigit() else task


def configuration_of(task: str) -> int:
    """``"mug-2"`` -> 2 (0 for a task name without a numeric suffix)."""
    head, sep, tail = task.rpartition("-")
    return int(tail) if sep and tail.isdigit() else 0


def task_order(tasks: Iterable[str], with_paper: bool = True) -> list[str]:
    """The paper's nine tasks (``with_paper``) and then the other ``tasks``, sorted by object and configuration."""
    tasks = set(tasks)
    first = list(PAPER_TASKS) if with_paper else [t for t in PAPER_TASKS if t in tasks]
    rest = sorted(tasks - set(PAPER_TASKS), key=lambda t: (object_of(t), configuration_of(t), t))
    return first + rest


def method_order(methods: Iterable[str], with_paper: bool = True) -> list[str]:
    methods = set(methods)
    first = list(PAPER_METHODS) if with_paper else [m for m in PAPER_METHODS if m in methods]
    return first + sorted(methods - set(PAPER_METHODS))


def object_order(tasks: Sequence[str]) -> list[str]:
    out: list[str] = []
    for t in tasks:
        if object_of(t) not in out:
            out.append(object_of(t))
    return out


def _group(summaries: Iterable[dict[str, Any]]) -> dict[tuple[str, str], list[dict[str, Any]]]:
    groups: dict[tuple[str, str], list[dict[str, Any]]] = defaultdict(list)
    for s in summaries:
        groups[(s["task"], s["method"])].append(s)
    return groups


def _total_tasks(obj: str, method: str, present: set[tuple[str, str]], tasks: Sequence[str]) -> list[str]:
    return [t for t in tasks if object_of(t) == obj and (t, method) in present]


def _paper_total(per_task: dict, totals: dict, obj: str, method: str, used: Sequence[str]):
    """The paper's total over the tasks ``used``: the published total when they are the object's three tasks."""
    if list(used) == [f"{obj}-{k}" for k in range(3)] and method in totals.get(obj, {}):
        return totals[obj][method]
    vals = [per_task.get(t, {}).get(method) for t in used]
    return None if not used or any(v is None for v in vals) else sum(vals)


def success_rows(summaries: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Table V rows, one per (task, method) of the paper's grid and of the summaries, then one per (object total,
    method): our successes by Table III (``success``) with the Wilson 95 % interval, our strict successes and
    the paper's successes out of 10. Totals pool the tasks the method ran (``tasks_in_total``); ours are ``None``
    where nothing ran."""
    groups = _group(summaries)
    present = set(groups)
    tasks = task_order(t for t, _ in present)
    methods = method_order(m for _, m in present)
    rows = []

    def row(task, method, ss, paper, paper_runs, total_of=None):
        k = sum(bool(s["success"]) for s in ss)
        n = len(ss)
        lo, hi = wilson_interval(k, n) if n else (None, None)
        strict = [bool(s["strict_success"]) for s in ss if "strict_success" in s]
        return {"task": task, "method": method, "successes": k if n else None, "runs": n or None,
                "wilson_lo": lo, "wilson_hi": hi,
                "strict_successes": sum(strict) if strict else None, "strict_runs": len(strict) or None,
                "paper_successes": paper, "paper_runs": paper_runs if paper is not None else None,
                "is_total": total_of is not None,
                "tasks_in_total": None if total_of is None else " ".join(total_of)}

    for obj in object_order(tasks):
        obj_tasks = [t for t in tasks if object_of(t) == obj]
        for t in obj_tasks:
            for m in methods:
                rows.append(row(t, m, groups.get((t, m), []), PAPER_SUCCESSES.get(t, {}).get(m), PAPER_RUNS))
        for m in methods:
            used = _total_tasks(obj, m, present, obj_tasks)
            paper = _paper_total(PAPER_SUCCESSES, PAPER_SUCCESS_TOTALS, obj, m,
                                 used if used else [t for t in obj_tasks if t in PAPER_TASKS])
            ss = [s for t in used for s in groups[(t, m)]]
            n_paper = PAPER_RUNS * (len(used) if used else sum(t in PAPER_TASKS for t in obj_tasks))
            rows.append(row(f"{obj} total", m, ss, paper, n_paper, total_of=used))
    return rows


def cumulative_nll_rows(summaries: Sequence[dict[str, Any]]) -> list[dict[str, Any]]:
    """Table VI rows like :func:`success_rows`: median cumulative NLL per (task, method) beside the paper's, and per
    object the sum of the medians over the tasks the method ran (as the paper's totals are)."""
    groups = _group(summaries)
    present = set(groups)
    tasks = task_order(t for t, _ in present)
    methods = method_order(m for _, m in present)
    med = {key: float(np.median([float(s["cumulative_nll"]) for s in ss])) for key, ss in groups.items()}
    rows = []
    for obj in object_order(tasks):
        obj_tasks = [t for t in tasks if object_of(t) == obj]
        for t in obj_tasks:
            for m in methods:
                rows.append({"task": t, "method": m, "runs": len(groups.get((t, m), [])) or None,
                             "median_cumulative_nll": med.get((t, m)),
                             "paper_median_cumulative_nll": PAPER_CUMULATIVE_NLL.get(t, {}).get(m),
                             "is_total": False, "tasks_in_total": None})
        for m in methods:
            used = _total_tasks(obj, m, present, obj_tasks)
            paper = _paper_total(PAPER_CUMULATIVE_NLL, PAPER_CUMULATIVE_NLL_TOTALS, obj, m,
                                 used if used else [t for t in obj_tasks if t in PAPER_TASKS])
            rows.append({"task": f"{obj} total", "method": m,
                         "runs": sum(len(groups[(t, m)]) for t in used) or None,
                         "median_cumulative_nll": sum(med[(t, m)] for t in used) if used else None,
                         "paper_median_cumulative_nll": paper, "is_total": True,
                         "tasks_in_total": " ".join(used)})
    return rows


def _float(v) -> float | None:
    if v is None or v == "":
        return None
    try:
        f = float(v)
    except (TypeError, ValueError):
        return None
    return f if np.isfinite(f) else None


def planned(row: dict[str, Any]) -> bool:
    """Whether a ``steps.csv`` row is a step that planned: ``replanned`` = 1 (files from before that column: any
    planning time above zero). Step 0 (the initial belief, no action) never planned."""
    if int(float(row.get("step", 0) or 0)) == 0:
        return False
    r = _float(row.get("replanned"))
    if r is not None:
        return r > 0.5
    return any((_float(row.get(c)) or 0.0) > 0 for c in ("field_s", "dynamics_s", "cost_s", "gp_fit_s"))


def _paper_time(task: str, method: str, key: str) -> tuple[tuple[float, float] | None, str]:
    """(paper mean, std) of Table VII for our process ``key`` of ``method`` on ``task`` and the paper's row name."""
    where = PAPER_TIME_TASKS.get(task)
    name = {"cache": "cache", "dynamics": "dynamics", "gp_fit": "GP fit"}.get(key)
    if key == "cost":
        name = {"rumi": "our cost lookup", "gpvr": "GP cost lookup"}.get(method)
    if where is None or name is None or method not in _PLANNING_METHODS:
        return None, ""
    if key == "gp_fit" and method != "gpvr":
        return None, ""
    return PAPER_TIMES[name][where], name


def _executed(row: dict[str, Any]) -> bool:
    return int(float(row.get("step", 0) or 0)) > 0


def timing_rows(episodes: Sequence[tuple[dict[str, Any], Sequence[dict[str, Any]]]]) -> list[dict[str, Any]]:
    """Table VII rows, one per (task, method, process) present: the mean and std (over the steps, pooled across
    episodes) of the process's seconds per step, and the std of the episodes' means beside it (the paper's std is
    across its 10 runs), with the paper's Table VII value where it has one.

    Which steps (``steps``: ``"planned"`` / ``"all"``): the planning processes of :data:`PROCESSES` over the steps
    that planned (:func:`planned`), the belief update and the sim over every executed step. A process of
    :data:`EVERY_STEP_CAPABLE` that the (task, method)'s rows show above 0 on a step that did not plan (GPVR's
    per-step GP refit and field cache) is averaged over every executed step. A process whose times are all 0 (the
    Slide heuristic has no field, dynamics or cost) has no mean (``None``). ``gp_fit_s`` is shown for GPVR only.

    ``episodes`` are ``(summary, steps.csv rows)`` pairs.
    """
    by: dict[tuple[str, str], list[Sequence[dict[str, Any]]]] = defaultdict(list)
    for s, rows in episodes:
        by[(s["task"], s["method"])].append(rows)
    out = []
    tasks = task_order((t for t, _ in by), with_paper=False)
    methods = method_order((m for _, m in by), with_paper=False)
    for t in tasks:
        for m in methods:
            if (t, m) not in by:
                continue
            for key, col, label, planning in PROCESSES:
                if key == "gp_fit" and m != "gpvr":
                    continue
                every = not planning or (col in EVERY_STEP_CAPABLE and any(
                    (_float(r.get(col)) or 0.0) > 0 for rows in by[(t, m)] for r in rows
                    if _executed(r) and not planned(r)))
                per_ep = []
                for rows in by[(t, m)]:
                    sel = [r for r in rows if (_executed(r) if every else planned(r))]
                    vals = [v for v in (_float(r.get(col)) for r in sel) if v is not None]
                    if vals:
                        per_ep.append(vals)
                pooled = [v for vs in per_ep for v in vs]
                ran = any(v != 0 for v in pooled)
                ep_means = [float(np.mean(vs)) for vs in per_ep]
                paper, paper_name = _paper_time(t, m, key)
                if key == "plan" and m == "rumi" and t in PAPER_TIME_TASKS:
                    where = PAPER_TIME_TASKS[t]
                    paper = (sum(PAPER_TIMES[n][where][0] for n in ("cache", "dynamics", "our cost lookup")), None)
                    paper_name = "sum of cache, dynamics, our cost lookup"
                if key == "cost" and m == "gpvr":
                    label = "GP cost lookup"
                out.append({"task": t, "method": m, "process": label, "column": col,
                            "steps": "all" if every else "planned",
                            "mean_s": float(np.mean(pooled)) if ran else None,
                            "std_s": float(np.std(pooled)) if ran else None,
                            "n_steps": len(pooled), "n_episodes": len(per_ep),
                            "std_of_episode_means_s": float(np.std(ep_means)) if ran else None,
                            "paper_mean_s": None if paper is None else paper[0],
                            "paper_std_s": None if paper is None else paper[1],
                            "paper_process": paper_name})
    return out


def _cell(v, fmt: str = "{}") -> str:
    return "-" if v is None else fmt.format(v)


def _label(task: str, is_total: bool) -> str:
    return f"**{task}**" if is_total else task


def _partial(r: dict[str, Any]) -> bool:
    obj = r["task"].rsplit(" ", 1)[0]
    return r["is_total"] and bool(r["tasks_in_total"]) and r["tasks_in_total"].split() != [f"{obj}-{k}" for k in range(3)]


def _wide(rows: Sequence[dict[str, Any]], cells, headers: Sequence[str]) -> tuple[list[str], bool]:
    methods = list(dict.fromkeys(r["method"] for r in rows))
    tasks = list(dict.fromkeys((r["task"], r["is_total"]) for r in rows))
    at = {(r["task"], r["method"]): r for r in rows}
    head = ["task"] + [f"{METHOD_LABELS.get(m, m)}: {h}" for m in methods for h in headers]
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    partial = False
    for task, is_total in tasks:
        cs = [_label(task, is_total)]
        for m in methods:
            r = at[(task, m)]
            mark = " \u2020" if _partial(r) else ""
            partial |= bool(mark)
            cs += [c + (mark if c != "-" else "") for c in cells(r)]
        lines.append("| " + " | ".join(cs) + " |")
    return lines, partial


def success_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """Table V as markdown: per method our successes (Table III criterion) with the Wilson 95 % interval, the
    paper's, and our strict successes; rows the tasks and the per-object totals."""
    def cells(r):
        ours = "-" if r["runs"] is None else (f"{r['successes']}/{r['runs']} "
                                              f"[{r['wilson_lo']:.2f}, {r['wilson_hi']:.2f}]")
        paper = "-" if r["paper_successes"] is None else f"{r['paper_successes']}/{r['paper_runs']}"
        strict = "-" if r["strict_runs"] is None else f"{r['strict_successes']}/{r['strict_runs']}"
        return [ours, paper, strict]

    lines, partial = _wide(rows, cells, ["ours", "paper", "strict"])
    notes = ["", "Successes by Table III (minimum NLL below the task's threshold) with the Wilson 95 % interval; "
             "*paper*: Table V; *strict*: NLL below the threshold and weighted rotation error below "
             f"{ROT_SUCCESS_DEG:.0f} deg at the same step (ours only). Totals pool the runs of the object's tasks."]
    if partial:
        notes += ["", "\u2020 total over only the tasks this method ran (`tasks_in_total` in the CSV); the paper's "
                     "total beside it is over the same tasks."]
    return "\n".join(lines + notes)


def cumulative_nll_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """Table VI as markdown: per method our median cumulative NLL and the paper's; totals are sums of medians."""
    def cells(r):
        return [_cell(r["median_cumulative_nll"], "{:.0f}"), _cell(r["paper_median_cumulative_nll"], "{:.0f}")]

    lines, partial = _wide(rows, cells, ["ours", "paper"])
    notes = ["", "Median over the seeds of the cumulative NLL (sum of the NLL over the executed steps, step 0 "
             "included; episodes that end early on APC convergence sum fewer steps); *paper*: Table VI. Totals "
             "are sums of the medians, as the paper's are (the paper prints 4444 for the mug InfoOnly total, "
             "while its rows sum to 3872)."]
    if partial:
        notes += ["", "\u2020 total over only the tasks this method ran; the paper's total beside it is over the "
                  "same tasks."]
    return "\n".join(lines + notes)


def timing_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """Table VII as markdown: one row per (task, method) with our mean (std) seconds per step of every process, and
    under the rows of mug-0 / box-0 the paper's Table VII values (sim mug 0 / sim box 0) in the same columns."""
    keys = [(k, lab) for k, _, lab, _ in PROCESSES]
    head = {"cost": "cost lookup (GPVR: GP cost lookup)"}
    lines = ["| task | method | " + " | ".join(head.get(k, lab) for k, lab in keys) + " | planned / executed steps |",
             "|" + "---|" * (len(keys) + 3)]
    at: dict[tuple[str, str], dict[str, dict[str, Any]]] = {}
    for r in rows:
        at.setdefault((r["task"], r["method"]), {})[next(k for k, c, _, _ in PROCESSES if c == r["column"])] = r
    tasks = list(dict.fromkeys(t for t, _ in at))
    every_step = False
    for t in tasks:
        for (tt, m), per in at.items():
            if tt != t:
                continue
            cells = []
            for k, _, _, planning in PROCESSES:
                r = per.get(k)
                if r is None or r["mean_s"] is None:
                    cells.append("-")
                    continue
                every = planning and r["steps"] == "all"
                every_step |= every
                cells.append(f"{r['mean_s']:.3f} ({r['std_s']:.3f})" + (" *" if every else ""))
            n_plan = max((per[k]["n_steps"] for k, _, _, p in PROCESSES if p and k in per and per[k]["steps"] ==
                          "planned"), default=0)
            n_all = max((per[k]["n_steps"] for k, _, _, p in PROCESSES if not p and k in per), default=0)
            lines.append(f"| {t} | {METHOD_LABELS.get(m, m)} | " + " | ".join(cells) + f" | {n_plan} / {n_all} |")
        where = PAPER_TIME_TASKS.get(t)
        if where is not None:
            P = {n: f"{v[where][0]:.3f} ({v[where][1]:.3f})" for n, v in PAPER_TIMES.items()}
            total = sum(PAPER_TIMES[n][where][0] for n in ("cache", "dynamics", "our cost lookup"))
            paper = {"cache": P["cache"], "dynamics": P["dynamics"],
                     "cost": f"{P['our cost lookup']}; GP: {P['GP cost lookup']}", "gp_fit": P["GP fit"],
                     "plan": f"{total:.3f} (ours: sum of the three)"}
            lines.append(f"| {t} | *paper, sim {where} 0 (RTX 4090)* | "
                         + " | ".join(paper.get(k, "-") for k, _ in keys) + " | - |")
    lines += ["", "Mean (std) seconds per execution step. Planning processes (cache, dynamics, cost lookup, GP fit, "
              "whole planning call) over the steps that planned (`replanned` = 1; the other steps reuse a queued "
              "action), belief update and sim step over every executed step; std over those steps pooled across the "
              "seeds (table_vii.csv also has the std of the per-episode means: the paper's std is across its 10 "
              "runs). GP fit is GPVR's only. *paper*: Table VII, measured on sim mug 0 and sim box 0 on an RTX 4090; "
              "the paper gives the cache and the dynamics as shared by the methods, the cost lookup for ours and "
              "for GPVR, and no belief update or sim times. \"-\": not run (no times, or all 0)."]
    if every_step:
        lines += ["", "\\* over every executed step: the method spends this time also on the steps that did not plan "
                  "(GPVR refits its GP and recaches the field after every execution step, as in the paper)."]
    return "\n".join(lines)


def write_csv(path, rows: Sequence[dict[str, Any]]) -> None:
    """Rows (dicts with the same keys) as CSV; ``None`` is written as an empty field."""
    import csv
    from pathlib import Path

    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    cols = list(rows[0]) if rows else []
    with open(path, "w", newline="") as fh:
        w = csv.DictWriter(fh, fieldnames=cols)
        w.writeheader()
        for r in rows:
            w.writerow({k: ("" if v is None else (f"{v:.6g}" if isinstance(v, float) else v)) for k, v in r.items()})

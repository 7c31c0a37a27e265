"""The benchmark report of a finished sweep folder: the RUMI paper's Tables V, VI, VII and Fig. 16, ours beside
the paper's.

``build_report(root)`` reads every finished episode under ``root`` (``summary.json`` + ``steps.csv``, as
``activetouch sweep`` writes them: ``root/<task>/<method>/seedNNN``), checks that they share one setting and hold
each (task, method, seed) once (:func:`activetouch.experiments.records.check_same_settings`) and writes into
``out_dir`` (default ``root/report``):

* ``table_v.csv`` / ``table_v.md`` - successes by Table III with Wilson 95 % intervals, strict successes, the
  paper's Table V, per-object totals;
* ``table_vi.csv`` / ``table_vi.md`` - median cumulative NLL beside Table VI, totals as sums of medians;
* ``table_vii.csv`` / ``table_vii.md`` - mean (std) seconds per step by process beside Table VII (planning
  processes over the steps that planned, or over every step for those a method runs at every step: GPVR's GP
  refit and field cache; belief update and sim over every executed step);
* ``nll_curves.png`` - Fig. 16: median NLL per execution step with the 25-75 % band, one panel per task;
* ``report.md`` - the settings aggregated and the tables and figure.

:func:`format_report` is what ``activetouch report DIR`` prints.
"""
from __future__ import annotations

import json
from pathlib import Path
from typing import Any, NamedTuple, Sequence

import numpy as np

from activetouch.experiments import tables
from activetouch.experiments.records import check_same_settings, load_summaries, read_steps

__all__ = ["ReportResult", "build_report", "format_report", "episode_dirs", "held_nll", "nll_curves"]

FIGURE_NOTE = ("Median over the seeds of nll(X) after each execution step, 25-75 % of the seeds shaded; log-scale y. "
               "Episodes that ended early (APC convergence) hold their last nll up to the longest episode of their "
               "panel.")


class ReportResult(NamedTuple):
    """What :func:`build_report` wrote (paths) and the tables it holds (lists of row dicts, as in the CSVs)."""

    root: Path
    out_dir: Path
    report_md: Path
    table_v_csv: Path
    table_v_md: Path
    table_vi_csv: Path
    table_vi_md: Path
    table_vii_csv: Path
    table_vii_md: Path
    figure: Path | None
    settings: dict[str, Any]
    n_episodes: int
    table_v: list[dict[str, Any]]
    table_vi: list[dict[str, Any]]
    table_vii: list[dict[str, Any]]
    markdown: dict[str, str]  # "v", "vi", "vii": the markdown tables (as in the .md files, without their heading)


def episode_dirs(root: str | Path) -> list[Path]:
    """Every folder under ``root`` that holds a ``summary.json`` (finished or not; ``load_summaries`` decides)."""
    return sorted({p.parent for p in Path(root).rglob("summary.json")})


def held_nll(nlls: Sequence[Sequence[float]], length: int | None = None) -> np.ndarray:
    """``(episodes, length)`` NLL per step, each episode held at its last value up to ``length`` (default: the
    longest episode's), so that episodes which ended early on APC convergence still count at later steps."""
    if not nlls or any(len(v) == 0 for v in nlls):
        raise ValueError("need at least one episode and one NLL per episode")
    L = max(len(v) for v in nlls) if length is None else length
    if L < max(len(v) for v in nlls):
        raise ValueError(f"length {L} is shorter than the longest episode ({max(len(v) for v in nlls)} steps)")
    out = np.empty((len(nlls), L), dtype=float)
    for i, v in enumerate(nlls):
        v = np.asarray(v, dtype=float)
        out[i, :len(v)] = v
        out[i, len(v):] = v[-1]
    return out


def _nll_of(rows: Sequence[dict[str, Any]]) -> list[float]:
    rows = sorted(rows, key=lambda r: int(float(r["step"])))
    return [float(r["nll"]) for r in rows if r.get("nll", "") != ""]


def nll_curves(episodes: Sequence[tuple[dict[str, Any], Sequence[dict[str, Any]]]]
               ) -> dict[str, dict[str, dict[str, Any]]]:
    """Fig. 16's curves from ``(summary, steps.csv rows)`` pairs: ``{task: {method: {"step", "median", "q25",
    "q75", "n", "held", "values"}}}``, every method of a task over the longest episode of that task (episodes that
    ended earlier hold their last NLL; ``held`` counts them, ``values`` is the ``(seeds, steps)`` matrix)."""
    by: dict[str, dict[str, list[list[float]]]] = {}
    for s, rows in episodes:
        nll = _nll_of(rows)
        if nll:
            by.setdefault(s["task"], {}).setdefault(s["method"], []).append(nll)
    out: dict[str, dict[str, dict[str, Any]]] = {}
    for task, per in by.items():
        L = max(len(v) for vs in per.values() for v in vs)
        out[task] = {}
        for method, vs in per.items():
            M = held_nll(vs, L)
            q25, med, q75 = np.percentile(M, [25, 50, 75], axis=0)
            out[task][method] = {"step": np.arange(L), "median": med, "q25": q25, "q75": q75, "n": len(vs),
                                 "held": sum(len(v) < L for v in vs), "values": M}
    return out


def _fmt_value(v: Any) -> str:
    return json.dumps(v, sort_keys=True) if isinstance(v, (dict, list)) else str(v)


def _seeds(seeds: Sequence[int]) -> str:
    """``[0, 1, 2, 5]`` -> ``"0-2, 5"``."""
    seeds = sorted(set(seeds))
    parts, start = [], None
    for i, s in enumerate(seeds):
        if start is None:
            start = s
        if i + 1 == len(seeds) or seeds[i + 1] != s + 1:
            parts.append(f"{start}" if start == s else f"{start}-{s}")
            start = None
    return ", ".join(parts)


def _coverage(summaries: Sequence[dict[str, Any]]) -> list[str]:
    tasks = tables.task_order({s["task"] for s in summaries}, with_paper=False)
    methods = tables.method_order({s["method"] for s in summaries}, with_paper=False)
    lines = ["| task | " + " | ".join(tables.METHOD_LABELS.get(m, m) for m in methods) + " |",
             "|" + "---|" * (len(methods) + 1)]
    for t in tasks:
        cells = []
        for m in methods:
            seeds = [s["seed"] for s in summaries if s["task"] == t and s["method"] == m]
            cells.append(f"{len(seeds)} (seeds {_seeds(seeds)})" if seeds else "-")
        lines.append(f"| {t} | " + " | ".join(cells) + " |")
    return lines


def build_report(root: str | Path, out_dir: str | Path | None = None) -> ReportResult:
    """Write the benchmark report of the sweep folder ``root`` into ``out_dir`` (default ``root/report``).

    Raises ``ValueError`` when ``root`` holds no finished episode, or episodes of different settings, or one
    (task, method, seed) twice (:func:`~activetouch.experiments.records.check_same_settings`).
    """
    root = Path(root)
    out = Path(out_dir) if out_dir is not None else root / "report"
    summaries = load_summaries(episode_dirs(root)) if root.is_dir() else []
    if not summaries:
        raise ValueError(f"no finished episodes under {root}")
    settings = check_same_settings(summaries)

    episodes, no_steps = [], []
    for s in summaries:
        p = Path(s["_dir"]) / "steps.csv"
        if p.exists():
            episodes.append((s, read_steps(p)))
        else:
            no_steps.append(s["_dir"])

    t5, t6, t7 = tables.success_rows(summaries), tables.cumulative_nll_rows(summaries), tables.timing_rows(episodes)
    md = {"v": tables.success_markdown(t5), "vi": tables.cumulative_nll_markdown(t6),
          "vii": tables.timing_markdown(t7)}
    heads = {"v": "Table V: successful runs", "vi": "Table VI: median cumulative nll",
             "vii": "Table VII: run time per step by process"}
    out.mkdir(parents=True, exist_ok=True)
    paths = {}
    for key, rows in (("v", t5), ("vi", t6), ("vii", t7)):
        paths[f"{key}_csv"] = out / f"table_{key}.csv"
        paths[f"{key}_md"] = out / f"table_{key}.md"
        tables.write_csv(paths[f"{key}_csv"], rows)
        paths[f"{key}_md"].write_text(f"# {heads[key]} (ours beside the paper's)\n\n{md[key]}\n")

    curves = nll_curves(episodes)
    figure = None
    held = sum(c["held"] for per in curves.values() for c in per.values())
    if curves:
        from activetouch.experiments import plots

        thresholds = {}
        for s in summaries:
            if s.get("nll_threshold") is not None:
                thresholds.setdefault(s["task"], float(s["nll_threshold"]))
        log_y = all(float(np.min(c["values"])) > 0 for per in curves.values() for c in per.values())
        note = FIGURE_NOTE if log_y else FIGURE_NOTE.replace("; log-scale y", "; linear y (some nll <= 0)")
        figure = plots.nll_grid_figure(out / "nll_curves.png", curves, thresholds=thresholds, log_y=log_y,
                                       note=note, labels=tables.METHOD_LABELS,
                                       title="Fig. 16: nll(X) after each execution step")

    seeds = sorted({s["seed"] for s in summaries})
    lines = ["# Benchmark report: RUMI Tables V, VI, VII and Fig. 16", "",
             f"Sweep folder `{root}`: {len(summaries)} finished episodes "
             f"({len({s['task'] for s in summaries})} tasks, {len({s['method'] for s in summaries})} methods, "
             f"seeds {_seeds(seeds)}). Paper: 10 runs per task and method, PyBullet, RTX 4090.", "",
             "## Settings aggregated", "",
             "Every episode below ran with these settings (`EpisodeConfig` without task, method, seed and the "
             "output switches; checked by `check_same_settings`):", "",
             "| setting | value |", "|---|---|"]
    lines += [f"| {k} | `{_fmt_value(v)}` |" for k, v in settings.items()]
    lines += ["", "Episodes per task and method:", ""] + _coverage(summaries)
    if no_steps:
        lines += ["", f"{len(no_steps)} episodes have no `steps.csv` and are left out of Table VII and Fig. 16: "
                  + ", ".join(f"`{d}`" for d in no_steps)]
    for key in ("v", "vi", "vii"):
        lines += ["", f"## {heads[key]}", "", f"[{paths[key + '_md'].name}]({paths[key + '_md'].name}), "
                  f"[{paths[key + '_csv'].name}]({paths[key + '_csv'].name})", "", md[key]]
    lines += ["", "## Fig. 16: nll after each execution step", ""]
    if figure is not None:
        lines += [f"![nll after each execution step]({figure.name})", "",
                  f"{FIGURE_NOTE} Rows: mug, drill, box; columns: configuration 0, 1, 2 (only the tasks and methods "
                  f"in this folder are drawn). {held} episodes are held after their end. Dashed: Table III success "
                  "threshold."]
    else:
        lines += ["No `steps.csv` to draw."]
    report_md = out / "report.md"
    report_md.write_text("\n".join(lines) + "\n")
    return ReportResult(root=root, out_dir=out, report_md=report_md,
                        table_v_csv=paths["v_csv"], table_v_md=paths["v_md"],
                        table_vi_csv=paths["vi_csv"], table_vi_md=paths["vi_md"],
                        table_vii_csv=paths["vii_csv"], table_vii_md=paths["vii_md"],
                        figure=figure, settings=settings, n_episodes=len(summaries),
                        table_v=t5, table_vi=t6, table_vii=t7, markdown=md)


def format_report(result: ReportResult) -> str:
    """What ``activetouch report DIR`` prints: the settings aggregated, the three tables and where the files are."""
    lines = [f"{result.n_episodes} finished episodes under {result.root}, settings:"]
    lines += [f"  {k} = {_fmt_value(v)}" for k, v in result.settings.items()]
    for key, head in (("v", "Table V: successes (ours beside the paper's)"),
                      ("vi", "Table VI: median cumulative nll (ours beside the paper's)"),
                      ("vii", "Table VII: seconds per step by process (ours beside the paper's)")):
        lines += ["", head, "", result.markdown[key]]
    lines += ["", f"Fig. 16: {result.figure if result.figure is not None else '(no steps.csv to draw)'}",
              f"Report: {result.report_md} (tables as CSV and markdown in {result.out_dir})"]
    return "\n".join(lines)

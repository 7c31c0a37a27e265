"""Result files written while an episode runs, so nothing finished is lost on a crash.

* ``steps.csv`` - one row per step, appended and flushed as soon as the step is done.
* ``summary.json`` - written atomically (temp file + rename) when the episode ends; its presence marks the
  episode as finished, which is what sweeps use to resume.
"""
from __future__ import annotations

import csv
import json
import math
import os
from pathlib import Path
from typing import Any, Iterable, Sequence

STEP_COLUMNS: tuple[str, ...] = (
    "step", "nll", "apc", "n_features", "n_surface", "n_free", "in_contact", "resampled", "active_share",
    "trans_err", "rot_err_deg", "mean_rot_err_deg", "true_discrepancy", "replanned", "plan_s", "field_s", "dynamics_s", "cost_s",
    "gp_fit_s", "update_s", "step_s",
)


class StepWriter:
    """Append-only CSV writer of per-step rows with a fixed column order (flushed + fsynced per row)."""

    def __init__(self, path: str | os.PathLike, columns: Sequence[str] = STEP_COLUMNS):
        self.path = Path(path)
        self.columns = tuple(columns)
        self.path.parent.mkdir(parents=True, exist_ok=True)
        self._fh = open(self.path, "w", newline="")
        self._writer = csv.DictWriter(self._fh, fieldnames=self.columns, extrasaction="ignore")
        self._writer.writeheader()
        self._fh.flush()

    def write(self, row: dict[str, Any]) -> None:
        missing = [c for c in ("step",) if c not in row]
        if missing:
            raise ValueError(f"step row lacks columns {missing}")
        self._writer.writerow({k: _fmt(row.get(k, "")) for k in self.columns})
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        if not self._fh.closed:
            self._fh.close()

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def _fmt(v: Any) -> Any:
    if isinstance(v, bool):
        return int(v)
    if isinstance(v, float):
        return f"{v:.6g}" if math.isfinite(v) else str(v)
    return v


def read_steps(path: str | os.PathLike) -> list[dict[str, str]]:
    """Read ``steps.csv`` back as a list of dicts (strings)."""
    with open(path, newline="") as fh:
        return list(csv.DictReader(fh))


def write_json_atomic(path: str | os.PathLike, data: dict[str, Any]) -> Path:
    """Write JSON via a temporary file and an atomic rename."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    tmp = path.with_suffix(path.suffix + ".tmp")
    with open(tmp, "w") as fh:
        json.dump(data, fh, indent=2, sort_keys=True, default=_json_default)
        fh.flush()
        os.fsync(fh.fileno())
    os.replace(tmp, path)
    return path


def _json_default(o: Any):
    if hasattr(o, "tolist"):
        return o.tolist()
    if isinstance(o, Path):
        return str(o)
    raise TypeError(f"not JSON serialisable: {type(o).__name__}")


def is_finished(episode_dir: str | os.PathLike) -> bool:
    """An episode is finished when its ``summary.json`` exists and parses."""
    p = Path(episode_dir) / "summary.json"
    if not p.exists():
        return False
    try:
        json.loads(p.read_text())
        return True
    except json.JSONDecodeError:
        return False


#: Config fields that name an episode inside a sweep (or only change what is printed/plotted), not its settings.
RUN_FIELDS: tuple[str, ...] = ("task", "method", "seed", "progress", "figures")
#: Config fields added after episodes were run whose empty value means "the defaults": an episode run before the
#: field existed has the same settings as one that leaves it empty.
EMPTY_IS_UNSET: tuple[str, ...] = ("belief",)


def settings_of(config: dict[str, Any]) -> dict[str, Any]:
    """The settings of an episode: its ``EpisodeConfig`` as a dict without :data:`RUN_FIELDS`.

    Two episodes of one table must share these; a sweep resumed with other settings must not reuse them.
    """
    if not isinstance(config, dict):
        raise ValueError(f"an episode config must be a dict, got {type(config).__name__}")
    return {k: v for k, v in sorted(config.items())
            if k not in RUN_FIELDS and not (k in EMPTY_IS_UNSET and v in ({}, None))}


def settings_key(config: dict[str, Any]) -> str:
    """Short stable hash of :func:`settings_of` (for printing and grouping)."""
    import hashlib

    blob = json.dumps(settings_of(config), sort_keys=True, default=_json_default)
    return hashlib.sha256(blob.encode()).hexdigest()[:10]


def settings_diff(a: dict[str, Any], b: dict[str, Any]) -> str:
    """``"steps: 40 != 30, particles: 100 != 10"`` for two configs (empty when their settings agree)."""
    sa, sb = settings_of(a), settings_of(b)
    keys = sorted(set(sa) | set(sb))
    return ", ".join(f"{k}: {sa.get(k, '<unset>')!r} != {sb.get(k, '<unset>')!r}" for k in keys
                     if sa.get(k, "<unset>") != sb.get(k, "<unset>"))


def effective_belief(summary: dict[str, Any]) -> dict[str, Any]:
    """The belief settings an episode ran with beyond the method's defaults: the task's defaults
    (``task_belief_defaults``, recorded since they exist; none before) under the ``--belief`` overrides."""
    return {**summary.get("task_belief_defaults", {}), **(summary.get("config") or {}).get("belief", {})}


def check_same_settings(summaries: Sequence[dict[str, Any]]) -> dict[str, Any]:
    """The common settings of ``summaries``; ``ValueError`` naming the first difference, or a (task, method, seed)
    that occurs twice (a table that counts one seed twice, or mixes settings, is silently wrong)."""
    seen: dict[tuple, str] = {}
    task_defaults: dict[tuple, tuple] = {}
    first = None
    for s in summaries:
        cfg = s.get("config")
        if cfg is None:
            raise ValueError(f"summary of {s.get('task')}/{s.get('method')}/seed {s.get('seed')} has no config")
        key = (s["task"], s["method"], s["seed"])
        where = s.get("_dir", "?")
        if key in seen:
            raise ValueError(f"{key[1]} on {key[0]} seed {key[2]} occurs twice ({seen[key]} and {where}): "
                             "aggregate one sweep folder at a time")
        seen[key] = where
        # per (task, method): a task's belief defaults apply to the belief they are for (box-* gives RUMI's
        # particles `reinvigorate`, not TIQF), so two methods on one task may rightly differ here
        td, tm = effective_belief(s), key[:2]
        if tm in task_defaults and task_defaults[tm][0] != td:
            raise ValueError(f"episodes of {key[1]} on {key[0]} run with different belief settings (the task's "
                             f"defaults under --belief): {task_defaults[tm][1]} ({task_defaults[tm][0]}) vs {where} ({td})")
        task_defaults.setdefault(tm, (td, where))
        if first is None:
            first = s
        else:
            diff = settings_diff(first["config"], cfg)
            if diff:
                raise ValueError(f"episodes with different settings: {first.get('_dir', '?')} vs {where} ({diff});"
                                 " tables aggregate runs of one setting only")
    return settings_of(first["config"]) if first is not None else {}


def load_summaries(dirs: Iterable[str | os.PathLike]) -> list[dict[str, Any]]:
    """Summaries of the finished episodes in ``dirs``; fields added to ``summary.json`` later (the step-0 and
    strict successes) are recomputed from ``steps.csv`` for episodes run before them."""
    from .metrics import success_fields

    out = []
    for d in dirs:
        if not is_finished(d):
            continue
        s = json.loads((Path(d) / "summary.json").read_text())
        steps = Path(d) / "steps.csv"
        if "strict_success" not in s and "nll_threshold" in s and steps.exists():
            rows = read_steps(steps)
            s.update(success_fields([r["nll"] for r in rows], [r["mean_rot_err_deg"] for r in rows],
                                    s["nll_threshold"]))
        s["_dir"] = str(d)
        out.append(s)
    return out

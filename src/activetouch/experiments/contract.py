"""The contract every registered (task, method) pair keeps, checked the way gymnasium's ``check_env`` checks
environments: two steps through the one episode loop run, the belief stays finite and normalised with a fixed
particle count after every update, the step rows are finite, and the same seed gives the same numbers.

    from activetouch.experiments.contract import check_pair
    check_pair("mug-0", "my-method", tmp_dir)   # AssertionError naming what broke

Runs use the method's ``quick`` planner overrides (few samples) and no CHSEL, so a check takes seconds.
"""
from __future__ import annotations

import math
from dataclasses import replace
from pathlib import Path
from typing import Any


def _is_timing(key: str) -> bool:
    """Wall and CPU times (``plan_s``, ``gp_fit_cpu_s``, ...) differ between runs; everything else must not."""
    return key.endswith("_s")


def quick_config(task: str, method: str, seed: int = 0, steps: int = 2, particles: int = 20):
    """An ``EpisodeConfig`` for a cheap run of the pair: ``steps`` steps, ``particles`` particles, no CHSEL, the
    method's quick planner overrides, no figures, no progress bar."""
    from activetouch.experiments.runner import EpisodeConfig
    from activetouch.registry import get_method, get_task

    env = get_task(task).make_env(seed=seed)
    return EpisodeConfig(task=task, method=method, seed=seed, steps=steps, particles=particles, use_chsel=False,
                         planner=get_method(method).quick_overrides(env), figures=False, progress=False)


def _run(cfg, out: Path) -> tuple[dict[str, Any], list[dict[str, Any]]]:
    from activetouch.experiments.estimators import check_estimator
    from activetouch.experiments.runner import run_episode

    rows: list[dict[str, Any]] = []
    sizes: list[int] = []

    def on_step(t, est, row):
        check_estimator(est)
        sizes.append(int(est.weights.shape[0]))
        for k, v in row.items():
            if isinstance(v, float):
                assert math.isfinite(v) or k == "true_discrepancy", f"step {t}: {k} = {v} is not finite"
        rows.append({k: v for k, v in row.items() if not _is_timing(k)})

    summary = run_episode(cfg, out, on_step=on_step)
    assert len(set(sizes)) == 1, f"the particle count changed over the episode: {sizes}"
    assert rows and rows[0]["step"] == 0, "no step-0 row"
    assert summary["steps"] == len(rows) - 1 >= 1, f"summary steps {summary['steps']} vs {len(rows) - 1} rows"
    assert isinstance(summary["success"], bool), "summary['success'] must be a bool"
    return summary, rows


def check_pair(task: str, method: str, out_dir: str | Path, seed: int = 0, steps: int = 2,
               repeat: bool = True) -> dict[str, Any]:
    """Run ``steps`` steps of ``method`` on ``task`` (twice when ``repeat``: the rows must be equal) and check the
    contract; returns the summary. AssertionError names the broken property."""
    cfg = quick_config(task, method, seed, steps)
    out = Path(out_dir)
    summary, rows = _run(cfg, out / "a")
    if repeat:
        _, again = _run(replace(cfg), out / "b")
        assert len(again) == len(rows), f"same seed, {len(rows)} vs {len(again)} steps"
        for r1, r2 in zip(rows, again):
            assert r1 == r2, f"same seed, different step {r1['step']}: " + ", ".join(
                f"{k}: {r1[k]} vs {r2.get(k)}" for k in r1 if r1[k] != r2.get(k))
    return summary

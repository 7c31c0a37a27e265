"""What-if termination: RUMI's successes and episode lengths had each episode stopped at APC < beta_t l_c.

RUMI ends an episode when the pose particles converge, ``APC(T_1..P) < beta_t l_c`` (Eq. 33, section J; the paper
uses beta_t = 0.03 in sim), and a run succeeds when its NLL falls below Table III's threshold at some step before
it ends. The stop rule decides only *when* to stop, never what the robot or the belief does: an episode run with
``--no-terminate`` takes, step for step, the same actions and holds the same particles as the terminated
episode of the same seed, up to where that one stopped (checked on box-0..2: 150 episodes of five methods, identical
NLL rows).
So one ``--no-terminate`` sweep answers, exactly and without new runs, how any beta_t would have scored:

    activetouch sweep --tasks box-0 box-1 box-2 --methods rumi --seeds 10 --no-terminate --out runs/box-noterm
    activetouch table runs/box-noterm --stop-at-beta-t 0.03 0.02

The replay mirrors :meth:`RumiEstimator.converged` and the runner: the check runs before each step on the last
row's APC (step 0's included), and is off for an episode whose prior APC was already below the bound (the
estimator disables it there; ``prior_apc`` in summary.json).
"""
from __future__ import annotations

import functools
from typing import Any, NamedTuple, Sequence

import numpy as np

from activetouch.experiments.metrics import wilson_interval


class StoppedEpisode(NamedTuple):
    """One episode replayed under a stop rule."""

    stop_step: int  # last step the episode would have run
    success: bool  # NLL below the task's threshold at some step <= stop_step (Table III)
    converged: bool  # stopped by the rule (False: ran to its last recorded step)


def stop_step(apc: Sequence[float], apc_stop: float, prior_apc: float | None = None) -> tuple[int, bool]:
    """``(k, converged)``: the first step ``k`` whose APC ``(m)`` is below ``apc_stop`` (the episode ends after it),
    or ``(len(apc) - 1, False)`` when none is, or when ``prior_apc`` is already below ``apc_stop`` (termination
    disabled, as the estimator does)."""
    if not apc_stop > 0:
        raise ValueError(f"apc_stop must be > 0 metres, got {apc_stop!r}")
    if prior_apc is not None and prior_apc < apc_stop:
        return len(apc) - 1, False
    for k, v in enumerate(apc):
        if v is not None and np.isfinite(v) and v < apc_stop:
            return k, True
    return len(apc) - 1, False


def replay_stop(rows: Sequence[dict[str, Any]], nll_threshold: float, apc_stop: float,
                prior_apc: float | None = None) -> StoppedEpisode:
    """Replay one episode's ``steps.csv`` rows (``step``, ``nll``, ``apc``) under ``APC < apc_stop``."""
    apc = [_float(r.get("apc")) for r in rows]
    k, conv = stop_step(apc, apc_stop, prior_apc)
    nll = [_float(r.get("nll")) for r in rows[:k + 1]]
    return StoppedEpisode(k, any(v is not None and v < nll_threshold for v in nll), conv)


def _float(v) -> float | None:
    if v is None or v == "":
        return None
    return float(v)


@functools.lru_cache(maxsize=None)
def object_diagonal(task: str) -> float:
    """``l_c`` (m) of a RUMI task's object: the bounding-box diagonal APC's bound is a share of."""
    from activetouch.objects import load
    from activetouch.sim.tasks import get_spec

    return load(get_spec(task).object_name).diagonal


def stop_rule_rows(episodes: Sequence[tuple[dict[str, Any], Sequence[dict[str, Any]]]],
                   betas: Sequence[float]) -> list[dict[str, Any]]:
    """Per (task, method, beta_t): successes, runs, Wilson 95 % interval, median and mean episode length had each
    episode stopped at ``APC < beta_t l_c``. ``episodes``: ``(summary, steps rows)`` of RUMI-task episodes run
    with ``--no-terminate``; ValueError naming the first one that is not."""
    if not betas:
        raise ValueError("give at least one beta_t")
    for b in betas:
        if not (0 < b < 1):
            raise ValueError(f"beta_t must be in (0, 1), got {b!r}")
    for s, rows in episodes:
        where = f"{s.get('method')} on {s.get('task')} seed {s.get('seed')}"
        if s.get("nll_threshold") is None:
            raise ValueError(f"{where} is not a RUMI-task episode (no NLL threshold): the APC stop rule is RUMI's")
        if "apc_termination" not in s:  # RumiEstimator records it; the other estimators never stop on APC
            raise ValueError(f"{where}: its estimator does not stop on APC (only RUMI's particle belief does)")
        if (s.get("config") or {}).get("terminate_on_convergence", True):
            raise ValueError(f"{where} ran with APC termination: a what-if stop needs episodes run with "
                             "--no-terminate (a stopped episode cannot tell what a later stop would have seen)")
        if not rows or "apc" not in rows[0]:
            raise ValueError(f"{where}: steps.csv has no apc column")
    out = []
    for b in betas:
        groups: dict[tuple[str, str], list[StoppedEpisode]] = {}
        for s, rows in episodes:
            ep = replay_stop(rows, s["nll_threshold"], b * object_diagonal(s["task"]), s.get("prior_apc"))
            groups.setdefault((s["task"], s["method"]), []).append(ep)
        for (task, method), eps in sorted(groups.items()):
            k, n = sum(e.success for e in eps), len(eps)
            lo, hi = wilson_interval(k, n)
            steps = [e.stop_step for e in eps]
            out.append({"task": task, "method": method, "beta_t": b, "successes": k, "runs": n,
                        "ci_low": lo, "ci_high": hi, "median_steps": float(np.median(steps)),
                        "mean_steps": float(np.mean(steps)), "stopped": sum(e.converged for e in eps)})
    return out


def stop_rule_markdown(rows: Sequence[dict[str, Any]]) -> str:
    """:func:`stop_rule_rows` as Markdown, with a total per (method, beta_t) over the tasks."""
    lines = ["| beta_t | task | method | successes (Tab. III) | 95 % CI | stopped by APC | median steps | mean steps |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['beta_t']:g} | {r['task']} | {r['method']} | {r['successes']}/{r['runs']} | "
                     f"[{r['ci_low']:.2f}, {r['ci_high']:.2f}] | {r['stopped']}/{r['runs']} | "
                     f"{r['median_steps']:g} | {r['mean_steps']:.1f} |")
    totals: dict[tuple[float, str], list[int]] = {}
    for r in rows:
        t = totals.setdefault((r["beta_t"], r["method"]), [0, 0, 0])
        t[0] += r["successes"]
        t[1] += r["runs"]
        t[2] += 1
    for (b, m), (k, n, ntasks) in totals.items():
        if ntasks > 1:
            lo, hi = wilson_interval(k, n)
            lines.append(f"| {b:g} | all {ntasks} tasks | {m} | **{k}/{n}** | [{lo:.2f}, {hi:.2f}] | | | |")
    return "\n".join(lines)

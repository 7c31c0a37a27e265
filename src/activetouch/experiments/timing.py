"""Timing helper shared by the benchmark scripts (``benchmarks/bench_*.py``)."""
from __future__ import annotations

import statistics
import time
from typing import Any, Callable

__all__ = ["timed"]


def timed(fn: Callable[[], Any], repeats: int) -> tuple[float, float, Any]:
    """Run ``fn`` ``repeats`` times: ``(median wall s, median CPU s of this process, the last result)``."""
    if not isinstance(repeats, int) or repeats < 1:
        raise ValueError(f"repeats must be a positive int, got {repeats!r}")
    walls, cpus, out = [], [], None
    for _ in range(repeats):
        w, c = time.perf_counter(), time.process_time()
        out = fn()
        walls.append(time.perf_counter() - w)
        cpus.append(time.process_time() - c)
    return statistics.median(walls), statistics.median(cpus), out

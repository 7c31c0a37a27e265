"""Progress display for long work: a tqdm bar on a terminal, plain periodic lines otherwise.

A tqdm bar written to a file or a CI log is one carriage-return "line" per update (a 40-step demo log was a
single 30 kB line); when the stream is not a terminal we print a plain line every ``every_s`` seconds and at
the end instead.
"""
from __future__ import annotations

import sys
import time
from typing import Any, TextIO

__all__ = ["Progress", "progress"]


class Progress:
    """Plain-line progress: ``desc: 12/40 steps (30 %), 41 s, nll=5.2 apc=3.1mm``.

    Args:
        total: number of units of work.
        desc: what is progressing.
        unit: unit name (plural added with ``s``).
        every_s: minimum seconds between two lines (the last unit always prints).
        stream: where to write (default ``sys.stderr``).
    """

    def __init__(self, total: int, desc: str, unit: str = "step", every_s: float = 10.0, stream: TextIO | None = None):
        self.total, self.desc, self.unit, self.every_s = int(total), desc, unit, float(every_s)
        self.stream = stream if stream is not None else sys.stderr
        self.n = 0
        self.postfix = ""
        self._t0 = self._last = time.monotonic()

    def set_postfix(self, **kw: Any) -> None:
        self.postfix = " ".join(f"{k}={v}" for k, v in kw.items())

    def update(self, n: int = 1) -> None:
        self.n += n
        now = time.monotonic()
        if now - self._last >= self.every_s or self.n >= self.total:
            self._last = now
            self._line(now)

    def _line(self, now: float) -> None:
        pct = 100.0 * self.n / self.total if self.total else 100.0
        extra = f", {self.postfix}" if self.postfix else ""
        print(f"{self.desc}: {self.n}/{self.total} {self.unit}s ({pct:.0f} %), {now - self._t0:.0f} s{extra}",
              file=self.stream, flush=True)

    def close(self) -> None:
        pass

    def __enter__(self):
        return self

    def __exit__(self, *exc):
        self.close()


def progress(total: int, desc: str, unit: str = "step", stream: TextIO | None = None, every_s: float = 10.0):
    """A tqdm bar when ``stream`` (default stderr) is a terminal, else a :class:`Progress` of plain lines."""
    stream = stream if stream is not None else sys.stderr
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        from tqdm.auto import tqdm

        return tqdm(total=total, desc=desc, unit=unit, file=stream)
    return Progress(total, desc, unit=unit, every_s=every_s, stream=stream)

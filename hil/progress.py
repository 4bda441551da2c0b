"""One progress bar for every long command: a single stderr line, silent when stderr is no TTY.

Stdlib only, so any module may use it::

    from hil.progress import Progress

    with Progress("sim", total=300.0, unit="s") as bar:
        for t in ...:
            bar.update(t)                 # absolute position, redrawn at most 5 times a second
    # or bar.advance(n) for counts; total=None shows position and rate without a bar

Pass ``enabled=True/False`` to override the TTY test (tests pass a ``StringIO`` and
``enabled=True``). Output is ``\\r``-redrawn and ends with a newline on ``close()``. Work that runs
for hours, often with stderr in a log file (a campaign under nohup or on a cluster's node), passes
``log_every_s``: without a TTY it then writes the same line, newline-ended, at most that often and
at ``close()``, instead of nothing.
"""

from __future__ import annotations

import contextlib
import sys
import threading
import time
from collections.abc import Iterator
from types import TracebackType
from typing import TextIO

WIDTH = 28


def _fmt(x: float) -> str:
    return f"{x:.0f}" if abs(x) >= 100 or x == int(x) else f"{x:.1f}"


class Progress:
    """A redrawn one-line bar: ``label [#####     ]  42.0%  126/300 s  3.2 s elapsed``."""

    def __init__(
        self,
        label: str,
        total: float | None = None,
        *,
        unit: str = "",
        stream: TextIO | None = None,
        enabled: bool | None = None,
        min_interval_s: float = 0.2,
        log_every_s: float | None = None,
    ) -> None:
        self.label = label
        self.total = total if total and total > 0 else None
        self.unit = unit
        self.stream = stream if stream is not None else sys.stderr
        if enabled is None:
            isatty = getattr(self.stream, "isatty", None)
            enabled = bool(isatty and isatty())
        self.enabled = enabled
        self.min_interval_s = min_interval_s
        self.log_every_s = None if enabled else log_every_s
        self._last_log = -float("inf")
        self.done = 0.0
        self.stage = ""
        self._t0 = time.monotonic()
        self._last = -1e9
        self._width = 0
        self.closed = False

    def update(self, done: float, *, stage: str | None = None, force: bool = False) -> None:
        """Set the absolute position (same unit as ``total``)."""
        self.done = done
        if stage is not None:
            self.stage = stage
        self._draw(force)

    def advance(self, n: float = 1) -> None:
        self.update(self.done + n)

    def line(self) -> str:
        """The text of the bar as it would be drawn now."""
        elapsed = time.monotonic() - self._t0
        unit = f" {self.unit}" if self.unit else ""
        stage = f"  {self.stage}" if self.stage else ""
        if self.total is None:
            return f"{self.label}  {_fmt(self.done)}{unit}  {elapsed:.1f} s elapsed{stage}"
        frac = min(max(self.done / self.total, 0.0), 1.0)
        bar = "#" * int(frac * WIDTH)
        eta = ""
        if 0.02 < frac < 1.0 and elapsed > 1.0:
            eta = f", ~{elapsed * (1 - frac) / frac:.0f} s left"
        return (
            f"{self.label} [{bar:<{WIDTH}}] {100 * frac:5.1f}%  {_fmt(self.done)}/{_fmt(self.total)}{unit}"
            f"  {elapsed:.1f} s{eta}{stage}"
        )

    def _draw(self, force: bool) -> None:
        if self.closed:
            return
        if not self.enabled:
            if self.log_every_s is not None:
                now = time.monotonic()
                if force or now - self._last_log >= self.log_every_s:
                    self._last_log = now
                    self.stream.write(self.line() + "\n")
                    self.stream.flush()
            return
        now = time.monotonic()
        if not force and now - self._last < self.min_interval_s:
            return
        self._last = now
        text = self.line()
        pad = max(0, self._width - len(text))
        self._width = len(text)
        self.stream.write("\r" + text + " " * pad)
        self.stream.flush()

    def close(self) -> None:
        """Draw the final state and end the line (idempotent)."""
        if self.closed:
            return
        if self.enabled:
            self._draw(force=True)
            self.stream.write("\n")
            self.stream.flush()
        elif self.log_every_s is not None:
            self._draw(force=True)
        self.closed = True

    def __enter__(self) -> Progress:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()


@contextlib.contextmanager
def elapsed_progress(
    label: str, total_s: float | None = None, *, stream: TextIO | None = None, enabled: bool | None = None
) -> Iterator[Progress]:
    """A bar that advances with wall time, for work that reports no progress of its own (benches
    that run the rig for a set duration); with no total it shows the elapsed time."""
    bar = Progress(label, total_s, unit="s", stream=stream, enabled=enabled)
    stop = threading.Event()

    def tick() -> None:
        t0 = time.monotonic()
        while not stop.wait(0.5):
            t = time.monotonic() - t0
            bar.update(min(t, total_s) if total_s else t)

    th = threading.Thread(target=tick, name="progress", daemon=True)
    th.start()
    try:
        yield bar
    finally:
        stop.set()
        th.join(timeout=1.0)
        bar.close()

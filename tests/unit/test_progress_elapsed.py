"""`hil bench` shows a bar that advances with time (benches that run the rig for --duration)."""

from __future__ import annotations

import io
import time

from hil.progress import elapsed_progress


def test_bar_advances_with_wall_time_and_ends_the_line() -> None:
    out = io.StringIO()
    with elapsed_progress("hil bench rig", 10.0, stream=out, enabled=True) as bar:
        time.sleep(1.2)
        assert 0.5 <= bar.done <= 10.0
    text = out.getvalue()
    assert "hil bench rig" in text and text.endswith("\n")


def test_bar_is_silent_when_not_a_terminal() -> None:
    out = io.StringIO()  # StringIO.isatty() is False
    with elapsed_progress("hil bench seeds", None, stream=out):
        time.sleep(0.6)
    assert out.getvalue() == ""

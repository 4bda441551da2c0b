"""Without a terminal a long command's progress is a plain line now and then (log_every_s), not
nothing: a campaign of hours under nohup shows runs done, failed and the ETA in its log."""

from __future__ import annotations

import io

from hil.progress import Progress


def test_without_a_tty_the_bar_writes_whole_lines_at_most_every_interval_and_at_close() -> None:
    out = io.StringIO()  # no isatty: not a terminal
    bar = Progress("campaign", total=10, unit="runs", stream=out, log_every_s=3600.0)
    for i in range(1, 6):
        bar.update(i, stage="1 failed" if i > 3 else "")
    bar.close()
    lines = out.getvalue().splitlines()
    assert "\r" not in out.getvalue()
    assert len(lines) == 2  # the first update (the interval had not started) and the close
    assert lines[0].startswith("campaign [") and " 1/10 runs" in lines[0]
    assert " 5/10 runs" in lines[1] and lines[1].endswith("1 failed")


def test_every_update_is_a_line_when_the_interval_is_zero_and_none_without_log_every() -> None:
    out = io.StringIO()
    bar = Progress("campaign", total=4, unit="runs", stream=out, log_every_s=0.0)
    for i in range(1, 5):
        bar.update(i)
    bar.close()
    assert len(out.getvalue().splitlines()) == 5
    quiet = io.StringIO()
    with Progress("campaign", total=4, unit="runs", stream=quiet) as bar2:
        bar2.update(2)
    assert quiet.getvalue() == ""

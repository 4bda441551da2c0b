"""The receiver's pty line: what was written reaches a reader that opens it and reads late."""

from __future__ import annotations

import os
import threading
import time
from pathlib import Path

from hil.runners.serial import LineWriter


def test_closing_the_line_leaves_the_tail_to_a_reader_that_reads_late(tmp_path: Path) -> None:
    """Closing a pty master discards what its reader has not read (the reader gets EIO): the
    writer waits for a reader still there to take the tail (CI lost a replay's last epochs)."""
    link = tmp_path / "gnss0"
    line = LineWriter(921600, [str(link)])
    closer: threading.Thread | None = None
    fd = os.open(link, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
    try:
        data = bytes(range(256)) * 8  # 2 kB, under the pty's buffer
        line.write(data, time.time())
        closer = threading.Thread(target=line.close)
        closer.start()  # the writer is done and closing while nobody has read anything
        got = b""
        deadline = time.monotonic() + 30.0
        while len(got) < len(data) and time.monotonic() < deadline:
            time.sleep(0.05)  # a slow reader
            try:
                got += os.read(fd, 65536)
            except BlockingIOError:
                continue
        assert got == data
    finally:
        os.close(fd)
        if closer is not None:
            closer.join(timeout=10)
        line.close()
    assert not link.exists()  # the link is removed with the line

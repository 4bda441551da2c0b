"""SessionWriter's message fast path writes the very bytes ``mcap.Writer.add_message`` writes."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hil.messages import TYPES_BY_NAME
from hil.record import mcapio


def _write(path: Path, fast: bool, rows: list[tuple[str, bytes, int, int, int]]) -> bytes:
    w = mcapio.SessionWriter(path, chunk_size=4096, spill_index=False)
    if not fast:
        w._add_message = w._writer.add_message  # the library's own path
    else:
        assert w._add_message != w._writer.add_message, "the fast path is off: mcap's Writer changed?"
    cls = next(iter(TYPES_BY_NAME.values()))
    for i, (topic, data, log, pub, seq) in enumerate(rows):
        if i % 7 == 3:
            w.write_raw(topic + "/raw", data, log_time_ns=log, encoding="application/json", sequence=seq)
        else:
            w.write(topic, cls, data, log_time_ns=log, publish_time_ns=pub, seq=seq)
        if i == 500:
            w.flush()
    w.close()
    return path.read_bytes()


def test_fast_path_file_is_byte_identical(tmp_path: Path) -> None:
    g = np.random.default_rng(3)
    rows = []
    for i in range(1500):
        topic = f"hil/t/{int(g.integers(0, 9))}"
        data = bytes(g.integers(0, 256, size=int(g.integers(0, 300)), dtype=np.uint8))
        log = int(g.integers(0, 10**12)) if i % 50 == 0 else 10**9 + i * 2_500_000  # out of order too
        rows.append((topic, data, log, log - int(g.integers(0, 10**6)), int(g.integers(0, 2**32))))
    slow = _write(tmp_path / "slow.mcap", False, rows)
    fast = _write(tmp_path / "fast.mcap", True, rows)
    assert len(fast) > 50_000
    assert fast == slow

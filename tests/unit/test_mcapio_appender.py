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


def _write_queued(path: Path, rows: list[tuple[str, bytes, int, int, int]]) -> bytes:
    """The rows through ``SessionWriter.queue`` (the batch path ``hil sim`` takes), with the
    writer's other paths (a raw message, a flush, a new channel) cutting into the batches."""
    w = mcapio.SessionWriter(path, chunk_size=4096, spill_index=False)
    assert w._add_many is not None, "the batch path is off: mcap's Writer changed?"
    cls = next(iter(TYPES_BY_NAME.values()))
    q = w.queue
    for i, (topic, data, log, pub, seq) in enumerate(rows):
        if i % 7 == 3:
            w.write_raw(topic + "/raw", data, log_time_ns=log, encoding="application/json", sequence=seq)
        else:
            chan = w.channel(topic, cls)
            q.chans.append(chan)
            q.logs.append(log)
            q.datas.append(data)
            q.pubs.append(pub)
            q.seqs.append(seq)
        if i == 500:
            w.flush()
    w.close()
    return path.read_bytes()


def _rows(seed: int, n: int) -> list[tuple[str, bytes, int, int, int]]:
    g = np.random.default_rng(seed)
    rows = []
    for i in range(n):
        topic = f"hil/t/{int(g.integers(0, 9))}"
        data = bytes(g.integers(0, 256, size=int(g.integers(0, 300)), dtype=np.uint8))
        if i % 50 == 0:  # out of order
            log = int(g.integers(0, 10**12))
        elif i % 97 == 0:  # long payloads: chunks of one message
            log, data = 10**9 + i * 2_500_000, data * 40
        else:
            log = 10**9 + i * 2_500_000
        rows.append((topic, data, log, log - int(g.integers(0, 10**6)), int(g.integers(0, 2**32))))
    return rows


def test_queued_batches_write_the_library_bytes(tmp_path: Path) -> None:
    rows = _rows(5, 3000)
    slow = _write(tmp_path / "slow.mcap", False, rows)
    queued = _write_queued(tmp_path / "queued.mcap", rows)
    assert len(queued) > 100_000
    assert queued == slow


def test_queued_out_of_range_values_are_clamped_as_write_clamps_them(tmp_path: Path) -> None:
    """A negative time is 0, one past u64 the u64 maximum, a sequence its low 32 bits; a time
    past 2**63 takes the one-at-a-time path, with the same bytes."""
    rows = _rows(6, 300)
    rows[11] = (rows[11][0], b"{}", -5, -7, -1)
    rows[20] = (rows[20][0], b"{}", 2**64 + 3, 2**63 + 1, 2**40 + 9)
    slow = _write(tmp_path / "slow.mcap", False, rows)
    queued = _write_queued(tmp_path / "queued.mcap", rows)
    assert queued == slow


def test_queued_record_ending_exactly_at_the_chunk_size_keeps_the_chunk_open(tmp_path: Path) -> None:
    """32-byte records (a 1-byte payload) end on 4096 exactly; ``add_message`` closes a chunk
    only past its size, so the batch must too."""
    rows = [("hil/t/0", b"7", 10**9 + i, 10**9 + i, i) for i in range(2000)]
    rows = [r for i, r in enumerate(rows) if i % 7 != 3]  # no raw messages in between
    slow = _write(tmp_path / "slow.mcap", False, rows)
    queued = _write_queued(tmp_path / "queued.mcap", rows)
    assert queued == slow


def test_queued_drains_of_every_size_write_the_library_bytes(tmp_path: Path) -> None:
    """Drains on both sides of ``BATCH_MIN`` (one at a time below it, the batch from it on)
    make one file: the library's."""
    rows = _rows(7, 2500)
    cls = next(iter(TYPES_BY_NAME.values()))
    lib = mcapio.SessionWriter(tmp_path / "slow.mcap", chunk_size=4096, spill_index=False)
    lib._add_message = lib._writer.add_message
    for topic, data, log, pub, seq in rows:
        lib.write(topic, cls, data, log_time_ns=log, publish_time_ns=pub, seq=seq)
    lib.close()
    w = mcapio.SessionWriter(tmp_path / "sizes.mcap", chunk_size=4096, spill_index=False)
    sizes = [1, 2, mcapio.BATCH_MIN - 1, mcapio.BATCH_MIN, mcapio.BATCH_MIN + 1, 3, 300, 17]
    at, k, q = 0, 0, w.queue
    while at < len(rows):
        n = sizes[k % len(sizes)]
        for topic, data, log, pub, seq in rows[at : at + n]:
            q.chans.append(w.channel(topic, cls))
            q.logs.append(log)
            q.datas.append(data)
            q.pubs.append(pub)
            q.seqs.append(seq)
        w._drain()
        at, k = at + n, k + 1
    w.close()
    assert (tmp_path / "sizes.mcap").read_bytes() == (tmp_path / "slow.mcap").read_bytes()


def test_a_small_drain_takes_the_one_at_a_time_path(tmp_path: Path) -> None:
    """A live recorder writes its Foxglove messages one by one: a batch of one through numpy
    cost ~37 µs against ~2 µs (docs/benchmarks.md, rig-session31)."""
    from hil.wellknown import Derived

    w = mcapio.SessionWriter(tmp_path / "a.mcap", spill_index=False)
    batches: list[int] = []
    many = w._add_many
    assert many is not None

    def spy(chans: list[int], *rest: object) -> None:
        batches.append(len(chans))
        many(chans, *rest)  # type: ignore[arg-type]

    w._add_many = spy
    for i in range(50):
        w.write_wellknown(Derived("/foxglove/fix/nav/ins", "foxglove.LocationFix", b"{}", i), log_time_ns=i)
    cls = next(iter(TYPES_BY_NAME.values()))
    chan = w.channel("hil/t/0", cls)
    for n in (5, mcapio.BATCH_MIN):  # a few queued, then a batch's worth
        for i in range(n):
            w.queue.chans.append(chan)
            w.queue.logs.append(100 + i)
            w.queue.datas.append(b"{}")
            w.queue.pubs.append(100 + i)
            w.queue.seqs.append(i)
        w.flush()
    w.close()
    assert batches == [mcapio.BATCH_MIN]
    assert _counts(tmp_path / "a.mcap") == {"/foxglove/fix/nav/ins": 50, "hil/t/0": 5 + mcapio.BATCH_MIN}


def _counts(path: Path) -> dict[str, int]:
    from mcap.reader import make_reader

    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics is not None
    return {summary.channels[c].topic: n for c, n in summary.statistics.channel_message_counts.items()}

"""The recorder's packed chunk index writes the very file mcap's own list of objects writes."""

from __future__ import annotations

from pathlib import Path

from mcap.reader import make_reader

from hil.messages import ImuSample, Truth
from hil.record.mcapio import SessionWriter, read_session


def _write(path: Path, pack: bool, chunks: int) -> SessionWriter:
    w = SessionWriter(path, pack_index=pack)
    for k in range(chunks):
        for c in range(3 + k % 4):  # chunks with different channel sets
            cls = ImuSample if c % 2 else Truth
            w.write(f"hil/t/c{c}", cls, b'{"k":%d}' % k, log_time_ns=k * 10 + c, publish_time_ns=k, seq=k)
        w.flush()
    w.add_metadata("run", {"k": 1})
    w.close()
    return w


def test_packed_index_file_is_byte_identical_and_indexed(tmp_path: Path) -> None:
    packed = _write(tmp_path / "packed.mcap", True, 25)
    plain = _write(tmp_path / "plain.mcap", False, 25)
    assert packed.chunk_index is not None and len(packed.chunk_index) == 25
    assert plain.chunk_index is None
    data = (tmp_path / "packed.mcap").read_bytes()
    assert data == (tmp_path / "plain.mcap").read_bytes()
    with open(tmp_path / "packed.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and len(summary.chunk_indexes) == 25
    starts = sorted(ci.message_start_time for ci in summary.chunk_indexes)
    assert starts == [k * 10 for k in range(25)]
    # the indexed (seeking) reader finds every message through the packed index
    with open(tmp_path / "packed.mcap", "rb") as fh:
        n = sum(1 for _ in make_reader(fh).iter_messages())
    assert n == sum(3 + k % 4 for k in range(25))
    assert len(read_session(tmp_path / "packed.mcap").records) == n


def test_a_file_with_no_chunk_is_still_valid(tmp_path: Path) -> None:
    w = SessionWriter(tmp_path / "empty.mcap")
    w.close()
    with open(tmp_path / "empty.mcap", "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.chunk_indexes == []

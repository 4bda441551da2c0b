"""The recorder's packed chunk index writes the very file mcap's own list of objects writes."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from hil.messages import ImuSample, Truth
from hil.record.mcapio import PackedChunkIndex, SessionWriter, read_session


def _write(path: Path, pack: bool, chunks: int, spill: bool = True, on_open: Any = None) -> SessionWriter:
    w = SessionWriter(path, pack_index=pack, spill_index=spill)
    if on_open is not None:
        on_open(w)
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


def test_spilled_index_leaves_memory_and_the_file_identical(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(PackedChunkIndex, "SPILL_BLOCK", 300)  # a spill every ~3 chunks
    spilled = _write(tmp_path / "spilled.mcap", True, 60)
    memory = _write(tmp_path / "memory.mcap", True, 60, spill=False)
    plain = _write(tmp_path / "plain.mcap", False, 60)
    assert (tmp_path / "spilled.mcap").read_bytes() == (tmp_path / "plain.mcap").read_bytes()
    assert (tmp_path / "memory.mcap").read_bytes() == (tmp_path / "plain.mcap").read_bytes()
    assert spilled.chunk_index is not None and memory.chunk_index is not None and plain.chunk_index is None
    assert spilled.chunk_index.nbytes == memory.chunk_index.nbytes > 5000
    assert memory.chunk_index.held_bytes == memory.chunk_index.nbytes
    # what stays in memory is less than one spill block; the scratch file was never visible
    assert spilled.chunk_index.held_bytes < 300 + 200
    assert sorted(p.name for p in tmp_path.iterdir()) == ["memory.mcap", "plain.mcap", "spilled.mcap"]


def test_index_is_held_while_the_session_runs_and_spilled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(PackedChunkIndex, "SPILL_BLOCK", 300)
    w = SessionWriter(tmp_path / "live.mcap")
    for k in range(40):
        w.write("hil/t/c0", Truth, b'{"k":%d}' % k, log_time_ns=k, publish_time_ns=k, seq=k)
        w.flush()
    assert w.chunk_index is not None
    assert w.chunk_index.nbytes > 1000 and w.chunk_index.held_bytes < 300
    w.close()
    assert len(read_session(tmp_path / "live.mcap").records) == 40


class _FailingSpill:
    """A spill file whose disk fills up after ``ok`` writes."""

    def __init__(self, ok: int) -> None:
        self.fh = tempfile.TemporaryFile(buffering=0)  # noqa: SIM115 - closed by close()
        self.ok = ok

    def write(self, data: Any) -> int:
        if self.ok <= 0:
            raise OSError(28, "No space left on device")
        self.ok -= 1
        return self.fh.write(data) or 0

    def fileno(self) -> int:
        return self.fh.fileno()

    def close(self) -> None:
        self.fh.close()


def _written_with_spill(tmp_path: Path, name: str, spill: _FailingSpill, chunks: int) -> SessionWriter:
    """Write ``chunks`` through ``spill`` in place of the real scratch file; check the file is
    the one an unspilled index writes."""

    def swap(w: SessionWriter) -> None:
        assert w.chunk_index is not None
        w.chunk_index._spill.close()  # type: ignore[union-attr]
        w.chunk_index._spill = spill  # type: ignore[assignment]

    w = _write(tmp_path / f"{name}.mcap", True, chunks, on_open=swap)
    _write(tmp_path / "plain.mcap", False, chunks)
    assert (tmp_path / f"{name}.mcap").read_bytes() == (tmp_path / "plain.mcap").read_bytes()
    assert w.chunk_index is not None
    return w


def test_a_spill_that_fills_up_falls_back_to_memory(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(PackedChunkIndex, "SPILL_BLOCK", 300)
    w = _written_with_spill(tmp_path, "full", _FailingSpill(ok=2), 50)
    assert w.chunk_index is not None and w.chunk_index.held_bytes == w.chunk_index.nbytes


def test_unbuffered_partial_writes_are_completed(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(PackedChunkIndex, "SPILL_BLOCK", 300)

    class Trickle(_FailingSpill):
        def write(self, data: Any) -> int:  # at most 7 bytes a call, as a raw file may
            return os.write(self.fh.fileno(), bytes(data[:7]))

    w = _written_with_spill(tmp_path, "trickle", Trickle(ok=0), 30)
    assert w.chunk_index is not None and w.chunk_index.held_bytes < w.chunk_index.nbytes


def test_a_spill_that_takes_no_bytes_falls_back_instead_of_spinning(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setattr(PackedChunkIndex, "SPILL_BLOCK", 300)

    class Stuck(_FailingSpill):
        def write(self, data: Any) -> int:
            return 0

    w = _written_with_spill(tmp_path, "stuck", Stuck(ok=0), 30)
    assert w.chunk_index is not None and w.chunk_index.held_bytes == w.chunk_index.nbytes

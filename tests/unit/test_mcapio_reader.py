"""``iter_records``'s own chunk parser gives what mcap's ``StreamReader`` gives, whole or cut short,
and the reruns read through a topic filter decide exactly as they do reading every message."""

from __future__ import annotations

import dataclasses
from collections.abc import Iterator
from pathlib import Path
from typing import Any

import pytest
from mcap.records import Attachment, Channel, Header, Metadata, Schema
from mcap.records import Message as McapMessage
from mcap.stream_reader import StreamReader

from hil.record.mcapio import SessionStream, iter_records, split_part_path
from hil.record.rerun import fusion_topic, rerun_fusion_records
from hil.record.rerun_timesync import rerun_timesync_records, timesync_topic
from hil.runners.sim import SimOptions, run_sim


@pytest.fixture(scope="module")
def recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    rec = tmp_path_factory.mktemp("reader") / "s.mcap"
    run_sim(SimOptions(scenario="uav_survey", duration_s=4.0, record=rec, fusion_worker=False))
    return rec


def _reference(path: Path) -> Iterator[tuple[Any, ...]]:
    """What iter_records gave before it parsed chunks itself: mcap's StreamReader, record by record."""
    schemas: dict[int, Schema] = {}
    channels: dict[int, Channel] = {}
    with open(path, "rb") as fh:
        try:
            for rec in StreamReader(fh, skip_magic=False, emit_chunks=False).records:
                if isinstance(rec, Schema):
                    schemas[rec.id] = rec
                elif isinstance(rec, Channel):
                    channels[rec.id] = rec
                elif isinstance(rec, McapMessage):
                    ch = channels[rec.channel_id]
                    s = schemas.get(ch.schema_id)
                    meta = ch.metadata or {}
                    yield (
                        "message",
                        ch.topic,
                        s.name if s else "",
                        rec.data,
                        rec.log_time,
                        rec.publish_time,
                        rec.sequence,
                        meta.get("publisher", ""),
                        meta.get("origin", ""),
                    )
                elif isinstance(rec, (Metadata, Attachment, Header)):
                    yield type(rec).__name__, repr(rec)
        except Exception:
            yield ("truncated",)


def _ours(path: Path) -> Iterator[tuple[Any, ...]]:
    for kind, r in iter_records(path, derived=True, header=True):
        if kind == "message":
            yield (
                kind,
                r.topic,
                r.schema,
                r.payload,
                r.log_time_ns,
                r.publish_time_ns,
                r.sequence,
                r.publisher,
                r.origin,
            )
        elif kind == "truncated":
            yield (kind,)
        else:
            yield type(r).__name__, repr(r)


@pytest.mark.parametrize("cut", [None, 0.37, 0.81])
def test_records_are_mcaps_whole_or_cut(recording: Path, tmp_path: Path, cut: float | None) -> None:
    path = recording
    if cut is not None:
        data = recording.read_bytes()
        path = tmp_path / "cut.mcap"
        path.write_bytes(data[: int(len(data) * cut)])
    ref, ours = list(_reference(path)), list(_ours(path))
    assert len(ours) > 1000
    assert ours == ref
    assert (ours[-1][0] == "truncated") is (cut is not None)


def _both(path: Path, run: Any, keep: Any) -> list[dict[str, Any]]:
    out = []
    for k in (None, keep):
        d = dataclasses.asdict(run(SessionStream(path, keep=k, follow_parts=True)))
        d.pop("recomputed", None)
        out.append(d)
    return out


@pytest.mark.parametrize("cut", [None, 0.6, 0.93])
def test_filtered_reruns_decide_as_unfiltered(recording: Path, tmp_path: Path, cut: float | None) -> None:
    path = recording
    if cut is not None:
        data = recording.read_bytes()
        path = tmp_path / "cut.mcap"
        path.write_bytes(data[: int(len(data) * cut)])
    least = 100 if cut is None else 1  # a cut file: what its whole chunks hold
    full, filtered = _both(path, lambda s: rerun_timesync_records(s, "x"), timesync_topic)
    assert full == filtered and full["n_recorded"] >= least
    full, filtered = _both(path, lambda s: rerun_fusion_records(s, window_ns=30 * 10**9), fusion_topic)
    assert full == filtered and (full["n_recorded"] >= least or cut is not None)


def test_filtered_stream_carries_skipped_times_across_parts(tmp_path: Path) -> None:
    rec = tmp_path / "split.mcap"
    run_sim(SimOptions(scenario="uav_survey", duration_s=4.0, record=rec, split_s=1.5, fusion_worker=False))
    assert split_part_path(rec, 1).is_file()
    full, filtered = _both(rec, lambda s: rerun_timesync_records(s, "x"), timesync_topic)
    assert full == filtered and full["difference"] is None
    stream = SessionStream(rec, keep=lambda t: t.endswith("/synced/imu"), follow_parts=True)
    records = list(stream)
    everything = [r for r in SessionStream(rec, follow_parts=True)]
    assert len(records) == sum(r.topic.endswith("/synced/imu") for r in everything)
    # every left-out message's log time is told on the next record, or in the tail
    told = max(max(r.skipped_log_ns for r in records), stream.skipped_tail[0] if stream.skipped_tail else -1)
    assert told == max(r.log_time_ns for r in everything if not r.topic.endswith("/synced/imu"))
    assert stream.skipped_tail is None or stream.skipped_tail[1] == everything[-1].log_time_ns


def _short_records_file(path: Path) -> None:
    """Chunks whose last record is shorter than a message record's fixed part (a channel of a
    one-letter topic, 26 bytes): the reader unpacks a chunk's records as messages first."""
    from mcap.writer import CompressionType, Writer

    with open(path, "wb") as fh:
        w = Writer(fh, chunk_size=10**6, compression=CompressionType.NONE)
        w.start("hil", "test")
        s = w.register_schema("hil.X", "jsonschema", b"{}")
        a = w.register_channel("hil/r/sensor/imu", "json", s)
        for i in range(3):
            w.add_message(a, log_time=10 + i, data=b'{"i": %d}' % i, publish_time=5 + i, sequence=i)
            b = w.register_channel("b", "", 0)  # written into the open chunk, at its end
            w._Writer__finalize_chunk()  # type: ignore[attr-defined]
            w.add_message(b, log_time=20 + i, data=b"", publish_time=20 + i, sequence=7)
        w.finish()


def test_short_records_at_a_chunks_end_whole_and_cut_at_every_byte(tmp_path: Path) -> None:
    path = tmp_path / "short.mcap"
    _short_records_file(path)
    data = path.read_bytes()
    ours = list(_ours(path))
    assert ours == list(_reference(path)) and sum(k[0] == "message" for k in ours) == 6
    cut = tmp_path / "cut.mcap"
    for n in range(len(data)):
        cut.write_bytes(data[:n])
        assert list(_ours(cut)) == list(_reference(cut)), n


def _first_message_index(data: bytes) -> int:
    """The offset of the first message index record (after the first chunk) in a finished file."""
    import struct

    pos = 8
    while pos < len(data):
        op, n = struct.unpack_from("<BQ", data, pos)
        if op == 0x07:
            return pos
        pos += 9 + n
    raise AssertionError("no message index")


@pytest.mark.parametrize(
    "damage",
    ["an entry's offset past the chunk", "an entry's log time before the chunk", "the entries' length"],
)
def test_a_damaged_message_index_is_a_damaged_file(recording: Path, tmp_path: Path, damage: str) -> None:
    """The data is read, not the index, but an indexed reader (Foxglove's) seeks by it: a finished
    file whose index cannot be its chunk's is damaged, at that record, as a failed chunk CRC is,
    to what reads a whole file to say what it holds."""
    import struct

    from hil.record.mcapio import DamagedRecordingError, read_session

    data = bytearray(recording.read_bytes())
    at = _first_message_index(bytes(data))
    body = at + 9  # channel id (2), entries' length (4), then (log time, offset) pairs
    if damage == "an entry's offset past the chunk":
        struct.pack_into("<Q", data, body + 6 + 8, 2**40)
    elif damage == "an entry's log time before the chunk":
        struct.pack_into("<Q", data, body + 6, 1)
    else:
        struct.pack_into("<I", data, body + 2, struct.unpack_from("<I", data, body + 2)[0] - 16)
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(bytes(data))
    assert list(_ours(recording))[-1][0] != "truncated"  # the original reads whole
    with pytest.raises(
        DamagedRecordingError, match=rf"damaged at byte {at}\b.*a message index that does not fit its chunk"
    ):
        read_session(bad)  # what hil info reads with too (stream_session)
    # a rerun reads the data and its CRCs, not the index, and does not pay for checking it
    assert list(_ours(bad)) == list(_ours(recording))

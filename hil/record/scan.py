"""Read any MCAP file record by record in file order, salvaging what a crash left behind.

``mcap``'s own readers stop at the first damage: ``make_reader(f).iter_messages()`` needs the
footer and summary (a SIGKILLed recorder never writes them) and ``StreamReader`` raises at a
chunk cut in half. The recording tools (``hil recover``, ``filter``, ``merge``, ``cat``,
``attachments``, ``export``) read through this module instead, so they work on finished and
crashed files alike. It is a lexer over mcap's own record classes (``mcap.records``), with two
additions: a record cut off at the end of the file is noted, not raised, and a chunk cut off by
the end of the file is opened with a streaming decompressor, so every message record complete in
its readable prefix is kept (``mcap recover`` does the same). A complete chunk that fails its CRC
or does not decompress gives none of its records: its bytes are damaged, and a message read from
them may be any bytes (QA found ``{"seq":24I2,...``). What could not be read is accounted in
``ScanReport``: bytes, chunks, their messages (as their index counts them) and the log-time span
those chunks claimed beyond the last message read from them.

Messages come in file order -- the recorder's write order, which ``hil rerun`` and the
completeness accounting rely on.
"""

from __future__ import annotations

import io
import os
import struct
import zlib
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any

from mcap.data_stream import ReadDataStream
from mcap.opcode import Opcode
from mcap.records import (
    Attachment,
    Channel,
    Chunk,
    Footer,
    Header,
    Message,
    Metadata,
    Schema,
)

from hil.record.mcapio import MAGIC, PROFILE, RecordingError, ends_with_magic

_RECORD_HEAD = struct.Struct("<BQ")
_MAX_RECORD = 4 * 2**30  # mcap's own record_size_limit
_CHUNK_HEAD = struct.Struct("<QQQI")  # start, end, uncompressed size, uncompressed crc


@dataclass
class ChunkLoss:
    """A chunk that could not be read whole."""

    offset: int
    reason: str
    start_ns: int  # the log-time span the chunk header claimed
    end_ns: int
    messages_read: int  # message records salvaged from its readable prefix
    last_read_ns: int | None  # log time of the last salvaged message
    messages_indexed: int | None = None  # what the message index after it counts (None: none read)


@dataclass
class ScanReport:
    """What a scan read and what it could not: the basis of ``hil recover``'s account."""

    path: Path
    size: int
    profile: str = ""
    library: str = ""
    messages: int = 0
    chunks: int = 0
    first_ns: int | None = None
    last_ns: int | None = None
    per_topic: dict[str, int] = field(default_factory=dict)
    finished: bool = False  # the footer was read: the writer closed the file
    end_offset: int = 0  # the first byte not read as a complete record
    stop_reason: str = ""  # why reading stopped before the end ("" if it did not)
    lost_chunks: list[ChunkLoss] = field(default_factory=list)
    orphans: int = 0  # messages of a channel whose definition was lost with a damaged chunk

    @property
    def bytes_unread(self) -> int:
        return max(0, self.size - self.end_offset)

    def saw(self, topic: str, log_ns: int) -> None:
        self.messages += 1
        self.per_topic[topic] = self.per_topic.get(topic, 0) + 1
        self.first_ns = log_ns if self.first_ns is None else min(self.first_ns, log_ns)
        self.last_ns = log_ns if self.last_ns is None else max(self.last_ns, log_ns)


def _opcode_name(op: int) -> str:
    try:
        return Opcode(op).name.lower()
    except ValueError:
        return f"opcode 0x{op:02x}"


def open_recording(path: str | Path, *, profile: str | None = PROFILE) -> tuple[IO[bytes], Header, int]:
    """Open ``path``, check the magic and the header (and, unless ``profile`` is None, that the
    file is a hil recording); one line naming the file and the reason otherwise."""
    path = Path(path)
    try:
        fh = open(path, "rb")  # noqa: SIM115 - handed to the caller
        size = os.fstat(fh.fileno()).st_size
    except OSError as err:
        raise RecordingError(f"{path}: cannot open: {err.strerror}") from err
    try:
        magic = fh.read(len(MAGIC))
        if magic != MAGIC[: len(magic)] or not magic:
            raise RecordingError(f"{path}: not an MCAP file (it does not start with the MCAP magic)")
        if len(magic) < len(MAGIC) or size < len(MAGIC) + _RECORD_HEAD.size:
            raise RecordingError(
                f"{path}: an MCAP file cut off after {size} bytes, before its header: nothing to read"
            )
        head = fh.read(_RECORD_HEAD.size)
        op, length = _RECORD_HEAD.unpack(head)
        body = fh.read(length) if op == Opcode.HEADER and length < 1 << 20 else b""
        if op != Opcode.HEADER or len(body) < length:
            raise RecordingError(f"{path}: an MCAP file without a readable header record: nothing to read")
        header = Header.read(ReadDataStream(io.BytesIO(body)))
    except RecordingError:
        fh.close()
        raise
    except Exception as err:
        fh.close()
        raise RecordingError(f"{path}: unreadable MCAP header: {type(err).__name__}: {err}") from err
    if profile is not None and header.profile != profile:
        fh.close()
        what = f"profile {header.profile!r}" if header.profile else "no profile"
        raise RecordingError(
            f"{path}: an MCAP file with {what} ({header.library or 'unknown writer'}), not a hil "
            "recording: use the mcap CLI for other files"
        )
    return fh, header, size


def _decompress_prefix(compression: str, data: bytes, size: int) -> tuple[bytes, str]:
    """As much of a chunk's records as its (possibly cut or damaged) compressed bytes yield."""
    if compression == "":
        return data, ""
    if compression == "zstd":
        import zstandard

        out = bytearray()
        dec = zstandard.ZstdDecompressor().decompressobj()
        try:
            for i in range(0, len(data), 16384):  # block by block: keep what came before damage
                out += dec.decompress(data[i : i + 16384])
        except zstandard.ZstdError as err:
            return bytes(out), f"zstd: {err}"
        return bytes(out[:size]) if size else bytes(out), ""
    if compression == "lz4":
        import lz4.frame

        try:
            return lz4.frame.decompress(data), ""
        except RuntimeError as err:
            dec = lz4.frame.LZ4FrameDecompressor()
            try:
                return dec.decompress(data), f"lz4: {err}"
            except RuntimeError:
                return b"", f"lz4: {err}"
    return b"", f"unknown compression {compression!r}"


def _chunk_records(records: bytes) -> Iterator[Schema | Channel | Message]:
    """Schema, channel and message records of a chunk's (possibly partial) record bytes."""
    pos, n = 0, len(records)
    while pos + _RECORD_HEAD.size <= n:
        op, length = _RECORD_HEAD.unpack_from(records, pos)
        start = pos + _RECORD_HEAD.size
        if start + length > n:
            return  # the record the damage cut through
        stream = ReadDataStream(io.BytesIO(records[start : start + length]))
        if op == Opcode.MESSAGE:
            yield Message.read(stream, length)
        elif op == Opcode.SCHEMA:
            yield Schema.read(stream)
        elif op == Opcode.CHANNEL:
            yield Channel.read(stream)
        pos = start + length


def _parse_partial_chunk(body: bytes) -> tuple[Chunk | None, bytes]:
    """A chunk record's header fields and the compressed bytes present (the record may be cut)."""
    if len(body) < _CHUNK_HEAD.size + 4:
        return None, b""
    start, end, usize, ucrc = _CHUNK_HEAD.unpack_from(body, 0)
    pos = _CHUNK_HEAD.size
    (clen,) = struct.unpack_from("<I", body, pos)
    pos += 4
    if clen > 64 or pos + clen + 8 > len(body):
        return None, b""
    compression = body[pos : pos + clen].decode("utf-8", "replace")
    pos += clen
    (dlen,) = struct.unpack_from("<Q", body, pos)
    pos += 8
    data = body[pos : pos + dlen]
    return Chunk(
        compression=compression,
        data=b"",
        message_end_time=end,
        message_start_time=start,
        uncompressed_crc=ucrc,
        uncompressed_size=usize,
    ), data


def _chunk_len(body: bytes) -> int:
    try:
        (clen,) = struct.unpack_from("<I", body, _CHUNK_HEAD.size)
        return int(struct.unpack_from("<Q", body, _CHUNK_HEAD.size + 4 + clen)[0])
    except struct.error:
        return 0


_DATA_OPS = frozenset(
    {Opcode.CHUNK, Opcode.MESSAGE, Opcode.ATTACHMENT, Opcode.METADATA, Opcode.SCHEMA, Opcode.CHANNEL}
)

ScanItem = Schema | Channel | Message | Attachment | Metadata


class Scan:
    """One pass over a file: iterate it for its records (schemas and channels before the messages
    that use them, attachments, metadata), in file order; ``report`` is complete at the end.

    ``channels`` and ``schemas`` map the file's ids as read so far. Messages of a channel id the
    file never declared are counted as unreadable (``report.orphans``), not raised.
    """

    def __init__(self, path: str | Path, *, profile: str | None = PROFILE, messages: bool = True) -> None:
        self.path = Path(path)
        self.profile = profile
        self.want_messages = messages
        self.schemas: dict[int, Schema] = {}
        self.channels: dict[int, Channel] = {}
        fh, header, size = open_recording(self.path, profile=profile)
        fh.close()
        self.header = header
        self.report = ScanReport(self.path, size, header.profile, header.library)
        # a finished file's summary repeats every schema and channel: a message whose channel was
        # defined in a damaged chunk is still read (else it is an orphan, and lost)
        self._summary = _summary_definitions(self.path)
        self._indexing: ChunkLoss | None = None  # a lost chunk whose message indexes follow

    def __iter__(self) -> Iterator[ScanItem]:
        fh, _header, size = open_recording(self.path, profile=self.profile)
        self.report = rep = ScanReport(self.path, size, self.header.profile, self.header.library)
        with fh:
            pos = fh.tell()
            while True:
                rep.end_offset = pos
                head = fh.read(_RECORD_HEAD.size)
                if len(head) < _RECORD_HEAD.size:
                    if head or not rep.finished:
                        rep.stop_reason = rep.stop_reason or (
                            f"the file ends at byte {size} without the footer a finished file has"
                            if not head
                            else f"a record header cut off at byte {pos}"
                        )
                    return
                op, length = _RECORD_HEAD.unpack(head)
                left = size - pos - _RECORD_HEAD.size
                if length > _MAX_RECORD or (length > left and ends_with_magic(fh, size)):
                    # a finished file is not cut: a length past its end is damage
                    why = f"garbage at byte {pos} ({_a(_opcode_name(op))} record of {length} bytes)"
                    pos = self._resync(fh, pos, why)
                    if pos < 0:
                        return
                    continue
                body = fh.read(min(length, left))
                if op == Opcode.MESSAGE_INDEX and self._indexing is not None:
                    _count_index(self._indexing, body)
                else:
                    self._indexing = None
                if len(body) < length:
                    rep.stop_reason = f"the file ends inside {_a(_opcode_name(op))} record at byte {pos}" + (
                        "" if op in _DATA_OPS else " (an index: rebuilt, no data in it)"
                    )
                    if op == Opcode.CHUNK:
                        yield from self._chunk(body, pos, partial=True)
                    return
                try:
                    yield from self._record(op, body, pos)
                except _Stop as stop:
                    pos = self._resync(fh, pos, str(stop))
                    if pos < 0:
                        return
                    continue
                pos += _RECORD_HEAD.size + length
                if op == Opcode.FOOTER:
                    rep.end_offset = pos
                    rep.finished = fh.read(len(MAGIC)) == MAGIC
                    if rep.finished:
                        rep.end_offset = pos + len(MAGIC)
                        rep.stop_reason = ""
                    else:
                        rep.stop_reason = "the footer is not followed by the closing magic"
                    return

    def _resync(self, fh: IO[bytes], pos: int, why: str) -> int:
        """Damage at ``pos`` that the records cannot be read past: in a finished file whose
        summary lists its chunks, reading goes on at the next chunk after it (the damaged
        stretch a lost chunk, said; the summary repeats the schemas and channels it may have
        held). Returns that chunk's offset, or -1: reading stops here (``stop_reason``)."""
        after = [c for c in self._summary[2] if c[0] > pos]
        if not after:
            self.report.stop_reason = why
            return -1
        nxt, _start, _end = after[0]
        here = [c for c in self._summary[2] if c[0] == pos]
        t0, t1 = (here[0][1], here[0][2]) if here else (0, 0)
        reason = f"{why}: bytes {pos}..{nxt} skipped, reading goes on at the next chunk (the summary's index)"
        self.report.lost_chunks.append(ChunkLoss(pos, reason, t0, t1, 0, None))
        self.report.chunks += 1
        fh.seek(nxt)
        return nxt

    def _record(self, op: int, body: bytes, pos: int) -> Iterator[ScanItem]:
        stream = ReadDataStream(io.BytesIO(body))
        try:
            if op == Opcode.CHUNK:
                yield from self._chunk(body, pos, partial=False)
            elif op == Opcode.SCHEMA:
                s = Schema.read(stream)
                if s.id not in self.schemas:
                    self.schemas[s.id] = s
                    yield s
            elif op == Opcode.CHANNEL:
                c = Channel.read(stream)
                if c.id not in self.channels:
                    self.channels[c.id] = c
                    yield c
            elif op == Opcode.MESSAGE:
                yield from self._message(Message.read(stream, len(body)))
            elif op == Opcode.ATTACHMENT:
                yield Attachment.read(stream)
            elif op == Opcode.METADATA:
                yield Metadata.read(stream)
            elif op == Opcode.FOOTER:
                Footer.read(stream)
            # indexes, statistics, summary offsets, data end: derived data, rebuilt by any writer
        except (struct.error, UnicodeDecodeError, ValueError, EOFError) as err:
            raise _Stop(f"a malformed {_opcode_name(op)} record at byte {pos}: {err}") from err

    @property
    def orphans(self) -> int:
        return self.report.orphans

    def _message(self, m: Message) -> Iterator[ScanItem]:
        chan = self.channels.get(m.channel_id)
        if chan is None and m.channel_id in self._summary[1]:
            chan = self.channels[m.channel_id] = self._summary[1][m.channel_id]
            schema = self._summary[0].get(chan.schema_id)
            if schema is not None and schema.id not in self.schemas:
                self.schemas[schema.id] = schema
                yield schema
            yield chan
        if chan is None:
            self.report.orphans += 1
            return
        self.report.saw(chan.topic, m.log_time)
        if self.want_messages:
            yield m

    def _chunk(self, body: bytes, pos: int, *, partial: bool) -> Iterator[ScanItem]:
        rep = self.report
        rep.chunks += 1
        chunk, data = _parse_partial_chunk(body)
        if chunk is None:
            rep.lost_chunks.append(ChunkLoss(pos, "its header is cut off", 0, 0, 0, None))
            return
        records, problem = _decompress_prefix(chunk.compression, data, chunk.uncompressed_size)
        crc = chunk.uncompressed_crc
        if not problem and not partial and crc and zlib.crc32(records) != crc:
            problem = "its CRC does not match"
        if problem and not partial:  # whole but damaged: nothing in it can be trusted
            loss = ChunkLoss(
                pos, f"{problem} (damaged)", chunk.message_start_time, chunk.message_end_time, 0, None
            )
            rep.lost_chunks.append(loss)
            self._indexing = loss
            return
        if partial and not problem:
            problem = f"cut off after {len(data)} of its {len(body) and _chunk_len(body)} compressed bytes"
        n_read, last = 0, None
        for rec in _chunk_records(records):
            if isinstance(rec, Message):
                before = rep.messages
                yield from self._message(rec)
                if rep.messages > before:
                    n_read += 1
                    last = rec.log_time if last is None else max(last, rec.log_time)
            elif isinstance(rec, Schema) and rec.id not in self.schemas:
                self.schemas[rec.id] = rec
                yield rec
            elif isinstance(rec, Channel) and rec.id not in self.channels:
                self.channels[rec.id] = rec
                yield rec
        if problem:
            rep.lost_chunks.append(
                ChunkLoss(pos, problem, chunk.message_start_time, chunk.message_end_time, n_read, last)
            )


def _a(name: str) -> str:
    return f"{'an' if name[:1] in 'aeiou' else 'a'} {name}"


def _summary_definitions(
    path: Path,
) -> tuple[dict[int, Schema], dict[int, Channel], list[tuple[int, int, int]]]:
    """The schemas and channels of a finished file's summary, and its chunks (start offset, log
    time span), in file order (none: no readable summary)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
    except Exception:  # a crashed or damaged file: what its records declare is all there is
        return {}, {}, []
    if summary is None:
        return {}, {}, []
    chunks = sorted(
        (c.chunk_start_offset, c.message_start_time, c.message_end_time) for c in summary.chunk_indexes
    )
    return dict(summary.schemas), dict(summary.channels), chunks


def _count_index(loss: ChunkLoss, body: bytes) -> None:
    """Add a lost chunk's message index record (one channel's (time, offset) pairs) to its count."""
    try:
        (n_bytes,) = struct.unpack_from("<I", body, 2)
    except struct.error:
        return
    loss.messages_indexed = (loss.messages_indexed or 0) + n_bytes // 16


class _Stop(Exception):
    """A record that does not parse: reading stops there (what follows cannot be trusted)."""


def describe_loss(rep: ScanReport) -> list[str]:
    """What a scan could not read, as lines a user reads (empty for a finished, intact file)."""
    lines: list[str] = []
    for c in rep.lost_chunks:
        t0 = c.start_ns if c.last_read_ns is None else c.last_read_ns
        # a span only where it runs forward: a damaged header's times, or a last salvaged
        # message past the header's end, tell nothing of what is lost
        span = f"; its log time {t0 / 1e9:.3f}..{c.end_ns / 1e9:.3f} s is lost" if 0 < t0 <= c.end_ns else ""
        if c.reason.endswith("(damaged)"):
            n = "" if c.messages_indexed is None else f"{c.messages_indexed} "
            lines.append(f"the chunk at byte {c.offset}: {c.reason}; none of its {n}messages kept{span}")
        else:
            lines.append(
                f"the chunk at byte {c.offset}: {c.reason}; {c.messages_read} messages salvaged{span}"
            )
    if rep.orphans:
        lines.append(f"{rep.orphans} messages of channels whose definition was in what was lost: not kept")
    if not rep.finished:
        lines.append(
            f"{rep.stop_reason or 'the file is not finished'}; {rep.bytes_unread} bytes from byte "
            f"{rep.end_offset} on are unreadable. What the writer had not yet written is unknown "
            "(a crashed file has no summary to count it)"
        )
    return lines


def channel_key(chan: Channel, schema: Schema | None) -> tuple[Any, ...]:
    """What makes two channels of two files the same channel (``hil merge``)."""
    s = (schema.name, schema.encoding, schema.data) if schema is not None else None
    return (chan.topic, chan.message_encoding, tuple(sorted(chan.metadata.items())), s)

"""A fast, forgiving pass over an MCAP session: payloads grouped per chunk, truncation tolerated.

``hil.record.mcapio.read_session`` builds one Python object per message, which is right for
rerun but costs tens of seconds on an hour of 400 Hz traffic. The report needs most messages
only as numbers, so this walks the records itself (MCAP spec: ``opcode u8, length u64, body``)
and hands each chunk's payloads to the caller grouped by channel; the caller decodes a whole
group with one ``msgspec`` call. A file cut short by a crash is read up to its last complete
chunk, exactly like ``read_session``; the reason is reported, never raised.
"""

from __future__ import annotations

import contextlib
import mmap
import os
import struct
import zlib
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path

import lz4.frame
import numpy as np
import zstandard

from hil.record.mcapio import MAGIC, RecordingError, damaged, unsupported_compression

OP_HEADER, OP_FOOTER, OP_SCHEMA, OP_CHANNEL, OP_MESSAGE, OP_CHUNK = 0x01, 0x02, 0x03, 0x04, 0x05, 0x06
OP_ATTACHMENT, OP_METADATA, OP_DATA_END = 0x09, 0x0C, 0x0F

_U16 = struct.Struct("<H")
_U32 = struct.Struct("<I")
_U64 = struct.Struct("<Q")
_REC = struct.Struct("<BQ")
_MSG = struct.Struct("<HIQQ")  # channel_id, sequence, log_time, publish_time
_HEAD_DTYPE = np.dtype([("cid", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")])


class _CallerError(Exception):
    """Wraps an exception raised by ``on_batch`` so it is not mistaken for a cut file."""


@dataclass
class Channel:
    id: int
    topic: str
    schema: str
    foreign: bool = False  # a publisher that is not the rig's (hil.record.mcapio): not reported


@dataclass
class Batch:
    """One chunk's messages of one channel, in file order (``payloads`` empty if not wanted)."""

    channel: Channel
    sequences: np.ndarray  # (n,) int64
    log_times: np.ndarray  # (n,) int64
    payloads: list[bytes] = field(default_factory=list)
    publish_times: np.ndarray | None = None  # (n,) int64: start epoch + each one's time of validity


@dataclass
class ScanResult:
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    channels: dict[int, Channel] = field(default_factory=dict)
    messages: int = 0
    truncated: bool = False
    truncation_reason: str = ""
    bytes_total: int = 0
    cut: list[tuple[str, str]] = field(default_factory=list)  # a session's files cut short before the last


def _str(buf: bytes | memoryview, off: int) -> tuple[str, int]:
    (n,) = _U32.unpack_from(buf, off)
    off += 4
    return bytes(buf[off : off + n]).decode(), off + n


def _map(buf: bytes | memoryview, off: int) -> tuple[dict[str, str], int]:
    (n,) = _U32.unpack_from(buf, off)
    off += 4
    end = off + n
    out: dict[str, str] = {}
    while off < end:
        k, off = _str(buf, off)
        v, off = _str(buf, off)
        out[k] = v
    return out, end


class _Walker:
    def __init__(self, res: ScanResult, want: Callable[[Channel], bool]) -> None:
        self.res = res
        self.want = want
        self.schemas: dict[int, str] = {0: ""}
        self.at = 0  # the byte offset of the top-level record being read (where damage is)

    def records(self, buf: bytes | memoryview, *, top: bool) -> Iterator[tuple[int, int, int]]:
        """Yield (opcode, body offset, body end); raises ValueError at a cut record."""
        off = 8 if top else 0
        size = len(buf)
        while off < size:
            if top:
                self.at = off
            if off + 9 > size:
                raise ValueError(f"record header cut at byte {off}")
            op, n = _REC.unpack_from(buf, off)
            start = off + 9
            end = start + n
            if end > size:
                raise ValueError(
                    f"record 0x{op:02x} at byte {off} cut ({n} bytes declared, {size - start} left)"
                )
            yield op, start, end
            off = end

    def schema(self, buf: bytes | memoryview, off: int) -> None:
        (sid,) = _U16.unpack_from(buf, off)
        name, _ = _str(buf, off + 2)
        self.schemas[sid] = name

    def channel(self, buf: bytes | memoryview, off: int) -> None:
        cid, sid = struct.unpack_from("<HH", buf, off)
        topic, end = _str(buf, off + 4)
        _encoding, end = _str(buf, end)
        meta, _ = _map(buf, end)
        foreign = meta.get("origin") == "foreign"
        self.res.channels[cid] = Channel(cid, topic, self.schemas.get(sid, ""), foreign)

    def messages(self, buf: bytes | memoryview, on_batch: Callable[[Batch], None]) -> None:
        """Walk one chunk: offsets in a tight loop, then every header field at once with numpy."""
        starts: list[int] = []
        ends: list[int] = []
        rec = _REC.unpack_from
        off, size = 0, len(buf)
        try:
            while off < size:
                op, n = rec(buf, off)
                a = off + 9
                off = a + n
                if op == OP_MESSAGE:
                    starts.append(a)
                    ends.append(off)
                elif op == OP_SCHEMA:
                    self.schema(buf, a)
                elif op == OP_CHANNEL:
                    self.channel(buf, a)
            if off > size:
                raise ValueError(f"record at byte {starts[-1] - 9 if starts else 0} of a chunk is cut")
        finally:
            if starts:
                if off > size:
                    starts.pop()
                    ends.pop()
                self._emit(buf, starts, ends, on_batch)

    def _emit(
        self, buf: bytes | memoryview, starts: list[int], ends: list[int], on_batch: Callable[[Batch], None]
    ) -> None:
        if not starts:
            return
        raw = np.frombuffer(buf, dtype=np.uint8)
        a = np.asarray(starts, dtype=np.int64)
        head = raw[a[:, None] + np.arange(_MSG.size)].copy().view(_HEAD_DTYPE).reshape(-1)
        cids = head["cid"]
        self.res.messages += len(starts)
        for cid in np.unique(cids):
            ch = self.res.channels.get(int(cid))
            if ch is None or ch.foreign:  # a stranger's messages are not the rig's report
                continue
            idx = np.nonzero(cids == cid)[0]
            payloads: list[bytes] = []
            if self.want(ch):
                payloads = [bytes(buf[starts[i] + _MSG.size : ends[i]]) for i in idx.tolist()]
            seqs, logs, pubs = (head[k][idx].astype(np.int64) for k in ("seq", "log", "pub"))
            batch = Batch(ch, seqs, logs, payloads, pubs)
            try:
                on_batch(batch)
            except Exception as err:  # the caller's bug, not a damaged file: let it surface
                raise _CallerError() from err


def _decompress(compression: str, data: bytes | memoryview, size: int) -> bytes | memoryview:
    if compression == "":
        return data
    if compression == "zstd":
        return zstandard.ZstdDecompressor().decompress(bytes(data), max_output_size=size)
    if compression == "lz4":
        return lz4.frame.decompress(bytes(data))
    raise _Unsupported(compression)


def scan(
    path: str | Path,
    on_batch: Callable[[Batch], None],
    on_progress: Callable[[int, int], None] | None = None,
    want: Callable[[Channel], bool] = lambda _c: True,
) -> ScanResult:
    """Walk a recording; ``on_batch`` gets every chunk's messages per channel, in file order.

    ``on_progress(bytes_done, bytes_total)`` is called once per chunk; ``want(channel)`` says
    whether a channel's payloads are needed (sequence and log time always are).
    """
    path = Path(path)
    try:
        with open(path, "rb") as fh:
            size = os.fstat(fh.fileno()).st_size
            data = mmap.mmap(fh.fileno(), 0, access=mmap.ACCESS_READ) if size else b""
    except OSError as err:
        raise RecordingError(f"cannot open recording {path}: {err.strerror}") from err
    if data[:8] != MAGIC:
        raise RecordingError(f"{path} is not an MCAP file (no magic bytes)")
    res = ScanResult(bytes_total=size)
    buf = memoryview(data)
    try:
        _walk(path, _Walker(res, want), buf, res, on_batch, on_progress)
    finally:
        with contextlib.suppress(BufferError):
            buf.release()
            if isinstance(data, mmap.mmap):
                data.close()
    if on_progress is not None:
        on_progress(res.bytes_total, res.bytes_total)
    return res


class _CrcError(Exception):
    """A chunk whose records do not match its CRC: damage, whatever the rest of the file."""


class _Unsupported(Exception):
    """A chunk compressed with a codec this reader does not have."""


def _walk(
    path: Path,
    w: _Walker,
    buf: memoryview,
    res: ScanResult,
    on_batch: Callable[[Batch], None],
    on_progress: Callable[[int, int], None] | None,
) -> None:
    try:
        for op, a, b in w.records(buf, top=True):
            if op == OP_CHUNK:
                off = a + 8 + 8  # message start/end time
                size, crc = struct.unpack_from("<QI", buf, off)
                off += 8 + 4  # uncompressed size, crc
                comp, off = _str(buf, off)
                (n,) = _U64.unpack_from(buf, off)
                off += 8
                if off + n > b:
                    raise ValueError(f"chunk data of {n} bytes overruns its record")
                records = _decompress(comp, buf[off : off + n], size)
                if crc and zlib.crc32(records) != crc:
                    raise _CrcError()
                w.messages(records, on_batch)
                if on_progress is not None:
                    on_progress(b, res.bytes_total)
            elif op == OP_MESSAGE:  # unchunked files
                w.messages(buf[a - 9 : b], on_batch)
            elif op == OP_SCHEMA:
                w.schema(buf, a)
            elif op == OP_CHANNEL:
                w.channel(buf, a)
            elif op == OP_METADATA:
                name, off = _str(buf, a)
                res.metadata[name], _ = _map(buf, off)
            elif op == OP_ATTACHMENT:
                off = a + 16
                name, off = _str(buf, off)
                _media, off = _str(buf, off)
                (n,) = _U64.unpack_from(buf, off)
                res.attachments[name] = bytes(buf[off + 8 : off + 8 + n])
            elif op in (OP_DATA_END, OP_FOOTER):
                break
        else:
            res.truncated = True
            res.truncation_reason = "the file ends without a summary (the recorder did not finish it)"
    except _CallerError as err:
        raise err.__cause__ from None  # type: ignore[misc]
    except _Unsupported as err:
        raise unsupported_compression(path, w.at, str(err)) from None
    except _CrcError:
        raise damaged(path, w.at, "a chunk that fails its CRC") from None
    except Exception as err:  # a half-written chunk: zstd, struct or decode errors alike
        if len(buf) >= 16 and bytes(buf[-8:]) == MAGIC:  # a finished file: damage, not a cut
            raise damaged(path, w.at, f"a record that does not read: {type(err).__name__}: {err}") from None
        res.truncated = True
        res.truncation_reason = f"{type(err).__name__}: {err}"

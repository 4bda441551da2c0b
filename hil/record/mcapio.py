"""MCAP files in the rig's layout: write a session, read it back (also when truncated).

Layout (the contract): one channel per Zenoh key and publisher, schema encoding ``jsonschema``
with schema name ``hil.<Type>``, message encoding ``json``. A live recorder names each channel's
publisher in its metadata: ``publisher`` (the Zenoh source id, ``"<zid>:<eid>"``, "" for a
publisher that gave none) and ``origin`` (``rig``, ``foreign`` -- a process that is not one of
the rig's, recorded but never the rig's data -- or ``unknown`` when the recorder could not tell);
``hil sim`` and files from before have neither, and read as the rig's. ``sequence`` = the
message's per-publisher ``seq``. Chunks are zstd-compressed and flushed at least every second, so
a killed recorder leaves a file readable up to its last chunk.

Times are on the wall-clock timeline, so viewers (Foxglove, python-can's ``.asc``/``.blf``
exports) show the real date and line up with other logs: ``log_time`` = the run's start epoch
(``RunInfo.start_epoch_ns``: ``hil sim`` the scenario's ``start_utc``, ``hil up`` the wall clock
at time zero) + the recorder's receive time on the rig clock; ``publish_time`` = start epoch +
the message's ``stamp_ns`` (time of validity). The messages themselves keep rig time (their
``*_ns`` fields), so a rerun is bit for bit whatever the date. Recordings made before this carried
rig time in ``log_time``/``publish_time``; ``rig_time_ns`` reads both (hil's times never get near
``EPOCH_FLOOR_NS`` on the rig clock, an epoch instant from 1981 on is always past it).
"""

from __future__ import annotations

import contextlib
import errno
import functools
import glob
import io
import json
import os
import re
import struct
import sys
import tempfile
import zlib
from array import array
from collections import Counter
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from itertools import chain
from pathlib import Path
from typing import IO, TYPE_CHECKING, Any

import msgspec
import zstandard
from mcap.data_stream import ReadDataStream, RecordBuilder
from mcap.exceptions import (
    EndOfFile,
    InvalidMagic,
    McapError,
    RecordLengthLimitExceeded,
    UnsupportedCompressionError,
)
from mcap.opcode import Opcode
from mcap.records import Attachment, Channel, ChunkIndex, Header, MessageIndex, Metadata, Schema

from hil import __version__
from hil.messages import TYPES_BY_NAME, Message, decode, json_schema, schema_name

if TYPE_CHECKING:  # numpy (batches of messages) and the writer side (mcap.writer, the Foxglove
    # SDK's schemas) load when a file is written: a reader (rerun, info, report) skips their imports
    import numpy as np
    from mcap.writer import Writer

    from hil.wellknown import Derived

PROFILE = "hil"
MAGIC = b"\x89MCAP0\r\n"
FOREIGN_ORIGIN = "foreign"  # hil.bus.identity.FOREIGN (a channel's ``origin``)
MAX_CHANNELS_PER_TOPIC = 32  # publishers of one topic with a channel each; the rest share one
MANY_PUBLISHERS = "*"
RAW = "raw"  # channel metadata ``hil`` of a key outside the contract, recorded as its bytes
_U64_MAX = 2**64 - 1


class RecordingError(ValueError):
    """A recording cannot be read or written; the message names the file and the reason.

    A ``ValueError`` so every CLI boundary that already turns bad input into one line and exit
    code 2 treats a corrupt, truncated or non-MCAP file the same way.
    """


class DamagedRecordingError(RecordingError):
    """A recording whose bytes are damaged (a chunk that fails its CRC, or a record that does not
    parse in a finished file): not a file cut short, so no reader stops there quietly."""


def ends_with_magic(fh: IO[bytes], size: int) -> bool:
    """Whether the file ends with the MCAP magic: its writer closed it (footer and magic), so a
    record that does not parse there is damage, not the cut of a crash. ``fh`` keeps its place."""
    if size < 2 * len(MAGIC):
        return False
    here = fh.tell()
    try:
        fh.seek(size - len(MAGIC))
        return fh.read(len(MAGIC)) == MAGIC
    finally:
        fh.seek(here)


def is_finished(path: str | Path) -> bool:
    """:func:`ends_with_magic` of the file at ``path`` (False if it cannot be read)."""
    try:
        with open(path, "rb") as fh:
            return ends_with_magic(fh, os.fstat(fh.fileno()).st_size)
    except OSError:
        return False


def damaged(path: str | Path, offset: int, what: str) -> DamagedRecordingError:
    """The one line a reader raises at damage: the file, where, what, and how to get the rest."""
    return DamagedRecordingError(
        f"{path} is damaged at byte {offset} ({what}): the file is corrupt, not cut short; "
        f"hil recover {path} -o COPY copies what is intact"
    )


def unsupported_compression(path: str | Path, offset: int, compression: str) -> RecordingError:
    """A chunk compressed in a way this reader has no codec for: neither damage nor a cut."""
    return RecordingError(
        f"{path}: the chunk at byte {offset} is compressed with {compression!r}, which hil does not "
        "read (zstd, lz4 or none); recompress it with `mcap compress`"
    )


class _ChunkCrcError(Exception):
    """A chunk whose decompressed records do not match its CRC."""


class _IndexMismatch(Exception):
    """A message index that cannot be its chunk's: badly framed, or an entry outside the chunk's
    time span or data (an indexed reader, Foxglove's, would seek there)."""


def no_run_message(name: str, records: Any) -> str:
    """Why a rerun found no run: a later part of a split recording (the run is announced in the
    first), a file cut off before it, or not a rig session."""
    part = _leading_metadata(Path(name), "part") or {}
    if part.get("index", "0") != "0":
        first = split_first_path(Path(name), int(part["index"]))
        return (
            f"{name}: part {part['index']} of a split recording (after {part.get('previous', '?')}); "
            f"the run is announced in its first file: rerun {first}, which reads every part"
        )
    if getattr(records, "truncated", False):
        return (
            f"{name}: the file is cut off before the run was announced (no hil/<rig>/run): nothing to rerun"
        )
    meta = getattr(records, "metadata", {}) or {}
    if "filter" in meta:  # a piece hil filter cut: its run messages stayed in the session before it
        return (
            f"{name}: a piece cut by hil filter ({meta['filter'].get('from', '?')}), without the run's "
            "announcement (hil/<rig>/run): rerun the recording it was cut from"
        )
    if "hil" in meta:  # a rig's recording whose key filter left the run messages out
        return (
            f"{name}: a rig's recording without its run messages (hil/<rig>/run): its recorder's "
            "--record-include/--record-exclude left them out, and with them what rerun needs"
        )
    return f"{name}: no RunInfo (hil/<rig>/run): not a rig session"


def split_part_path(path: Path, part: int) -> Path:
    """Where a split recording's part ``part`` goes: part 0 is ``path``, then ``<stem>_0001<suffix>``, ..."""
    return path if part == 0 else path.with_name(f"{path.stem}_{part:04d}{path.suffix}")


def split_first_path(part: Path, index: int) -> Path:
    """The first file of the split recording whose part ``index`` is ``part`` (the inverse of
    :func:`split_part_path`)."""
    tail = f"_{index:04d}"
    stem = part.stem[: -len(tail)] if index and part.stem.endswith(tail) else part.stem
    return part.with_name(f"{stem}{part.suffix}")


def session_files(path: str | Path) -> list[Path]:
    """A recording and the parts it was split into (:func:`split_parts`), then the files a
    restarted recorder continued it in (:func:`restart_parts`), each with its split parts, in
    order: what the tools that read a session (rerun, replay, report, export, merge) read end to
    end."""
    first = Path(path)
    files = [first, *split_parts(first)]
    for part in restart_parts(first):
        files += [part, *split_parts(part)]
    return files


def restart_part_path(record: Path, part: int) -> Path:
    """Where a recorder restarted for the ``part``-th time writes: ``<stem>.part<N>.mcap``.

    Why not the same path: the killed recorder's file is readable up to its last flushed chunk
    (docs/recording.md); reopening it for writing would destroy that.
    """
    return record.with_name(f"{record.stem}.part{part}{record.suffix or '.mcap'}")


#: a restarted recorder's file (``restart_part_path``), not its split parts (``<stem>.part1_0001``)
RESTART_PART_NAME = re.compile(r"\.part\d+$")


def session_note(files: list[Path], did: str) -> str | None:
    """What a tool that read a session of several files (``session_files``) says of them;
    ``did``: what it did to them ("read", "reran", ...). None: one file."""
    if len(files) < 2:
        return None
    restarted = [f.name for f in files if RESTART_PART_NAME.search(f.stem)]
    if not restarted:
        return f"the recording is split: {did} its {len(files)} parts in order"
    return (
        f"the session is in {len(files)} files, continued by a restarted recorder in "
        f"{', '.join(restarted)}: {did} them in order"
    )


def cut_notes(cut: list[tuple[str, str]]) -> list[str]:
    """What a tool says of files of a session cut short before a later one continues it
    (``SessionStream.cut_files``: each file's name and why its reading stopped)."""
    out = []
    for name, reason in cut:
        why = reason.strip().rstrip(":")
        out.append(
            f"{name} is cut short{f' ({why})' if why else ''}: its recorder was killed, and the session "
            "continues in the next file; read up to the cut"
        )
    return out


#: how far into a live recording its ``hil`` metadata is looked for (it comes when the run starts,
#: after the boot's messages: a few dozen)
_RUN_METADATA_WITHIN = 100_000
#: the ``hil`` metadata that names a run: files that differ in any were recorded by other runs
RUN_IDENTITY = ("rig", "scenario", "scenario_sha256", "seed", "start_epoch_ns")


def summary_metadata(path: Path, name: str) -> dict[str, str] | None:
    """The metadata record ``name`` of a finished file, from its summary's metadata index (which
    points at it wherever it is); None when it has none or no readable summary (a cut file)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            reader = make_reader(fh)
            if reader.get_summary() is None:
                return None
            found = [m for m in reader.iter_metadata() if m.name == name]
    except Exception:  # no readable summary: a crashed recorder's file
        return None
    return dict(found[-1].metadata) if found else None


def run_identity(path: Path, *, leading: bool = False) -> dict[str, str] | None:
    """The run ``path`` was recorded in (its ``hil`` metadata's ``RUN_IDENTITY`` keys); None when
    it says none. From the summary's metadata index, which points at the record (a piece ``hil
    filter`` cut has its metadata after the messages); a file without one (a crashed recorder's)
    is read to it, within its first ``_RUN_METADATA_WITHIN`` records (``leading``: among the
    records it starts with, as a restarted recorder writes it)."""

    def identity(meta: dict[str, str]) -> dict[str, str]:
        return {k: meta[k] for k in RUN_IDENTITY if k in meta}

    if is_finished(path):  # the summary's index says where, or that there is none
        meta = summary_metadata(path, "hil")
        return identity(meta) if meta is not None else None
    try:
        for n, (kind, rec) in enumerate(iter_records(path)):
            if kind == "metadata" and rec.name == "hil":
                return identity(dict(rec.metadata))
            if n >= _RUN_METADATA_WITHIN or (leading and kind != "metadata"):
                return None
    except (McapError, OSError, ValueError, struct.error):
        pass
    return None


def session_first_path(path: Path, split_index: int = 0) -> Path:
    """The first file of the session a file is part of, by its name: ``path`` if it is, else the
    file its split parts (``split_index``: its ``part`` metadata's index) and a restarted
    recorder's files (``<stem>.part<N>``) go back to."""
    base = split_first_path(path, split_index)
    restart = RESTART_PART_NAME.search(base.stem)
    return base.with_name(f"{base.stem[: restart.start()]}{base.suffix}") if restart else base


def first_of_its_session(path: Path) -> Path | None:
    """The session's first file when ``path`` is a later file of one (a split part, a restarted
    recorder's file) and that first file is there; None otherwise. What a tool that needs the
    run's start (``hil rerun``) points to instead of saying the file lacks it."""
    index = (_leading_metadata(path, "part") or {}).get("index", 0)
    try:
        first = session_first_path(path, int(index))
    except (TypeError, ValueError):
        return None
    return first if first != path and first.is_file() and path in session_files(first) else None


def next_in_session(path: Path, split_index: int = 0) -> Path | None:
    """The file of its session that follows ``path`` (``session_files``), None if it is the last
    (or not one of them)."""
    files = session_files(session_first_path(path, split_index))
    names = [f.name for f in files]
    k = names.index(path.name) if path.name in names else -1
    return files[k + 1] if 0 <= k < len(files) - 1 else None


def restart_parts(path: Path) -> list[Path]:
    """The files recorders restarted by ``hil up --restart`` continued ``path``'s session in
    (``<stem>.part<N>.mcap``, :func:`restart_part_path`), in order. A part is taken when it
    records the same run (rig and start epoch in its ``hil`` metadata, which it starts with):
    a part an earlier session left at that name is not this one's. ``path``'s run unknown (cut
    before the run was announced): a part whose recorder was told it continues a file of
    ``path``'s name."""
    parts: list[Path] = []
    mine: dict[str, str] | bool | None = False  # read once, when a part is there
    while (part := restart_part_path(path, len(parts) + 1)).is_file():
        if mine is False:
            mine = run_identity(path)
        theirs = run_identity(part, leading=True)
        if mine is not None and theirs != mine:
            return parts
        if mine is None:
            opts = (_leading_metadata(part, "config") or {}).get("options", "{}")
            try:
                continues = json.loads(opts).get("continues") or [""]
            except (ValueError, AttributeError):
                continues = [""]
            if Path(str(continues[0])).name != path.name:
                return parts
        parts.append(part)
    return parts


def split_parts(path: Path) -> list[Path]:
    """The further parts of a recording split by size or duration (``<stem>_0001.mcap``, ...), in
    order. A part is taken only after the file it was started after: its ``part`` metadata gives
    that file's size when it was closed (``previous_bytes``). So parts that an earlier, longer
    recording left at these names are not read as this one's (a new ``hil sim --record`` or
    ``hil up --record`` at the same path writes its first file over the old one and leaves them);
    a part written before the size was recorded is taken on its name, as it was."""
    parts: list[Path] = []
    previous = path
    while True:
        part = split_part_path(path, len(parts) + 1)
        if not part.is_file() or not _continues(part, previous):
            return parts
        parts.append(part)
        previous = part


def stale_parts(path: Path) -> list[Path]:
    """Files at ``path``'s part names (``<stem>_0001.mcap``, ...), in order, gaps and all, that a
    new recording at ``path`` would not continue: left by an earlier one."""
    pattern = f"{glob.escape(path.stem)}_[0-9][0-9][0-9][0-9]{glob.escape(path.suffix)}"
    return sorted(p for p in path.parent.glob(pattern) if p.is_file())


def stale_parts_note(path: Path) -> str | None:
    """What ``hil sim`` and ``hil up`` say, before a recording at ``path``, of the :func:`stale_parts`
    there (None: none)."""
    stale = stale_parts(path)
    if not stale:
        return None
    names = stale[0].name if len(stale) == 1 else f"{stale[0].name} .. {stale[-1].name}"
    return (
        f"{names} beside {path} are left from an earlier recording there: not parts of this one "
        f"(it writes over those it reaches); remove them"
    )


def aside_path(path: Path, n_parts: int) -> Path:
    """Where ``keep_aside`` puts a recording of ``1 + n_parts`` files: the first free
    ``<stem>.<N><suffix>`` whose part names are free too."""
    n = 1
    while True:
        kept = path.with_name(f"{path.stem}.{n}{path.suffix}")
        if not any(split_part_path(kept, k).exists() for k in range(n_parts + 1)):
            return kept
        n += 1


def keep_aside(path: Path) -> Path | None:
    """Move an earlier recording at ``path`` (not empty), with the split parts it continues in, to
    the first free ``<stem>.<N><suffix>`` (N = 1, 2, ...; its parts ``<stem>.<N>_0001<suffix>``, ...),
    so that a recorder starting at ``path`` does not write over it; returns where it went (None:
    nothing there). A live session cannot be made again: a second ``docker compose up``, or a
    recorder container restarted after a crash, would otherwise truncate the one before. The parts
    still read as one session there (``split_parts`` goes by sizes, not names)."""
    try:
        if not path.is_file() or path.stat().st_size == 0:
            return None
    except OSError:
        return None
    parts = split_parts(path)
    restarted = [(r, split_parts(r)) for r in restart_parts(path)]
    kept = aside_path(path, len(parts))
    path.rename(kept)
    for k, part in enumerate(parts, start=1):
        part.rename(split_part_path(kept, k))
    for n, (r, r_parts) in enumerate(restarted, start=1):  # a restarted recorder's files go along
        moved = restart_part_path(kept, n)
        r.rename(moved)
        for k, part in enumerate(r_parts, start=1):
            part.rename(split_part_path(moved, k))
    return kept


def made_by_sim(path: Path) -> bool:
    """Whether ``path`` is a ``hil sim`` recording, finished or cut off (the ``hil`` metadata it
    starts with says executor ``sim``): one that the same options make again, so ``hil sim`` may
    write over it. A live session (whose ``hil`` metadata comes when the run starts, after the
    boot's messages), or any other file, is not."""
    return (_leading_metadata(path, "hil") or {}).get("executor") == "sim"


def part_metadata(previous: Path) -> dict[str, Any]:
    """The ``part`` metadata of the part that follows ``previous`` (closed just now): its index
    comes from the caller, this gives what ties the two files together."""
    try:
        return {"previous": previous.name, "previous_bytes": previous.stat().st_size}
    except OSError:  # gone already: the part is then taken on its name
        return {"previous": previous.name}


def _leading_metadata(path: Path, name: str) -> dict[str, str] | None:
    """The metadata record ``name`` among those a file starts with, before its first message
    (None: not there, or the file cannot be read so far): a split recording's ``part``, a
    sim's ``hil``."""
    try:
        for kind, rec in iter_records(path):
            if kind == "metadata" and rec.name == name:
                return dict(rec.metadata)
            if kind != "metadata":
                return None  # the messages began
    except (McapError, OSError, ValueError, struct.error):
        pass
    return None


def _continues(part: Path, previous: Path) -> bool:
    """Whether ``part`` says it was started after ``previous`` as it is now (see ``split_parts``).
    An unreadable start is taken on its name, and the reading then says what is wrong."""
    size = (_leading_metadata(part, "part") or {}).get("previous_bytes")
    try:
        return size is None or int(size) == previous.stat().st_size
    except (OSError, ValueError):
        return False


#: ~1973 as an epoch instant, three years as rig time: a recording's times below it are rig time
#: (a recording from before the wall-clock timeline), above it start epoch + rig time
EPOCH_FLOOR_NS = 10**17
#: what the ``hil`` metadata says about the times of a recording with the wall-clock timeline
TIME_SEMANTICS = (
    "log_time = start_epoch_ns + recorder receive time on the rig clock; publish_time = start_epoch_ns + "
    "message stamp_ns (time of validity); message fields keep rig time; sequence = per-publisher seq"
)


def wall_clock_log_time(rx_wall_ns: int, start_epoch_ns: int | None, speed: float = 1.0) -> int:
    """The log time of a sample received at ``rx_wall_ns``: start epoch + its receive time on the
    rig clock (``--speed`` scales it); before the run's start epoch is known, the wall clock."""
    if start_epoch_ns is None:
        return rx_wall_ns
    return start_epoch_ns + int((rx_wall_ns - start_epoch_ns) * speed)


def rig_time_ns(t_ns: int, start_epoch_ns: int) -> int:
    """A recorded ``log_time``/``publish_time`` as rig time (ns since the run's time zero), for a
    recording of either timeline: epoch (start epoch + rig time) or, before it, rig time."""
    return t_ns - start_epoch_ns if t_ns >= EPOCH_FLOOR_NS else t_ns


def run_start(path: str | Path) -> tuple[int | None, bool]:
    """A recording's start epoch (``hil`` metadata, else its first ``run`` message; None: neither)
    and whether its MCAP times are on the wall-clock timeline already (False: rig time, a
    recording from before). Reads from the start of the file until it knows: both come before the
    run's traffic."""
    start: int | None = None
    for kind, rec in iter_records(path, derived=True):
        if kind == "metadata" and rec.name == "hil" and "start_epoch_ns" in rec.metadata:
            with contextlib.suppress(ValueError, TypeError):
                start = int(json.loads(rec.metadata["start_epoch_ns"]))
        elif kind == "message" and start is None and rec.schema == "hil.RunInfo":
            with contextlib.suppress(ValueError):
                start = decode(TYPES_BY_NAME["hil.RunInfo"], rec.payload).start_epoch_ns  # type: ignore[attr-defined]
        elif kind == "message" and start is not None:
            return start, rec.log_time_ns >= EPOCH_FLOOR_NS
        elif kind == "truncated":
            break
    return start, False


def _u64(ns: int) -> int:
    return 0 if ns < 0 else min(ns, _U64_MAX)


# opcode, record length, channel id, sequence, log time, publish time: mcap's Message.write
_MESSAGE_HEAD = struct.Struct("<BQHIQQ")
_MESSAGE_FIXED = _MESSAGE_HEAD.size - 9  # the record length counts what follows opcode and length
_OP_MESSAGE = int(Opcode.MESSAGE)  # an enum member's lookup, once
_OP_MESSAGE_INDEX = int(Opcode.MESSAGE_INDEX)


@functools.cache
def _head_row() -> np.dtype[Any]:
    """The message head as one row of a packed numpy array (no padding: 31 bytes); numpy loads
    with the first batch written, not for a reader of files."""
    import numpy as np

    fields = [("op", "u1"), ("len", "<u8"), ("chan", "<u2"), ("seq", "<u4"), ("log", "<u8"), ("pub", "<u8")]
    row = np.dtype(fields)
    assert row.itemsize == _MESSAGE_HEAD.size
    return row


class _MessageAppender:
    """``mcap.Writer.add_message``'s work, byte for byte, without its per-message objects.

    The writer builds a ``Message`` dataclass and six small writes per message; at the sim's
    ~3300 messages per rig second that was an eighth of ``hil sim``'s CPU. This packs the same
    record in one ``struct`` call into the writer's open chunk and keeps the same statistics and
    message index. It reaches the writer's private state (mcap 1.6, pinned in requirements.lock),
    so :meth:`for_writer` gives None when that state is not what it expects, and the caller keeps
    ``add_message``; tests/unit/test_mcapio_appender.py checks the files are identical.
    """

    def __init__(self, writer: Writer, stats: Any, chunk_builder: Any, chunk_size: int) -> None:
        self._stats = stats
        self._chunk = chunk_builder
        self._chunk_size = chunk_size
        self._finalize = getattr(writer, "_Writer__maybe_finalize_chunk")  # noqa: B009

    @staticmethod
    def for_writer(writer: Writer) -> _MessageAppender | None:
        stats = getattr(writer, "_Writer__statistics", None)
        chunk = getattr(writer, "_Writer__chunk_builder", None)
        size = getattr(writer, "_Writer__chunk_size", None)
        finalize = getattr(writer, "_Writer__maybe_finalize_chunk", None)
        rb = getattr(chunk, "record_writer", None)
        ok = (
            isinstance(size, int)
            and callable(finalize)
            and isinstance(getattr(chunk, "message_indices", None), dict)
            and isinstance(getattr(rb, "_buffer", None), io.BytesIO)
            and all(hasattr(chunk, a) for a in ("num_messages", "message_start_time", "message_end_time"))
            and all(
                hasattr(stats, a)
                for a in ("message_count", "message_start_time", "message_end_time", "channel_message_counts")
            )
        )
        return _MessageAppender(writer, stats, chunk, size) if ok else None  # type: ignore[arg-type]

    def add(self, channel_id: int, log_time: int, data: bytes, publish_time: int, sequence: int) -> None:
        # packed first: a value out of range raises here, before any state changes
        head = _MESSAGE_HEAD.pack(
            _OP_MESSAGE, _MESSAGE_FIXED + len(data), channel_id, sequence, log_time, publish_time
        )
        st = self._stats
        if st.message_count == 0 or log_time < st.message_start_time:
            st.message_start_time = log_time
        if log_time > st.message_end_time:
            st.message_end_time = log_time
        st.channel_message_counts[channel_id] += 1
        st.message_count += 1
        cb = self._chunk
        if cb.num_messages == 0 or log_time < cb.message_start_time:
            cb.message_start_time = log_time
        if log_time > cb.message_end_time:
            cb.message_end_time = log_time
        index = cb.message_indices.get(channel_id)
        if index is None:
            index = cb.message_indices[channel_id] = _FlatMessageIndex(channel_id)
        buf = cb.record_writer._buffer  # a new BytesIO after every chunk: looked up each time
        offset = buf.tell()
        if type(index) is _FlatMessageIndex:
            flat = index.flat
            flat.append(log_time)  # two appends: 87 ns, one extend of a pair 138
            flat.append(offset)
        else:  # made by mcap's own add_message in this chunk
            index.records.append((log_time, offset))
        cb.num_messages += 1
        buf.write(head)
        buf.write(data)
        if offset + _MESSAGE_HEAD.size + len(data) > self._chunk_size:  # buf.tell(), uncalled
            self._finalize()

    def add_many(
        self, chans: list[int], logs: np.ndarray, datas: list[bytes], pubs: np.ndarray, seqs: np.ndarray
    ) -> None:
        """:meth:`add` of each message in turn, the same bytes, in a few numpy calls for all.

        A window of ``hil sim`` is ~3000 messages: per message :meth:`add` updates a dozen
        counters and makes three writes (0.65 µs a message, 0.44 µs through the queue and this,
        3000 messages of 130 bytes on 15 channels, chunk compression included in both); here
        each record's head is a row of one packed array, the counters move once per batch and a
        chunk's records go out in one write. Times must be u64 and sequences u32
        (:meth:`SessionWriter._drain` clamps them as ``write`` does); a chunk closes after the
        first record that ends past the chunk size, as ``add`` closes it."""
        import numpy as np

        m = len(chans)
        if m == 0:
            return
        head = np.empty(m, _head_row())
        head["op"] = _OP_MESSAGE
        sizes = np.fromiter(map(len, datas), np.int64, m)
        head["len"] = sizes + _MESSAGE_FIXED
        ch = np.asarray(chans, np.int64)
        head["chan"] = ch
        head["seq"] = seqs
        log = np.asarray(logs, np.uint64)
        head["log"] = log
        head["pub"] = pubs
        ends = np.cumsum(sizes + _MESSAGE_HEAD.size)
        st, start = self._stats, 0
        for c, n in Counter(chans).items():  # first seen first: the statistics' key order
            st.channel_message_counts[c] += n
        lo, hi = int(log.min()), int(log.max())
        if st.message_count == 0 or lo < st.message_start_time:
            st.message_start_time = lo
        if hi > st.message_end_time:
            st.message_end_time = hi
        st.message_count += m
        while start < m:
            cb = self._chunk
            buf = cb.record_writer._buffer
            base = buf.tell() - (int(ends[start - 1]) if start else 0)
            # the first record that ends past the chunk size closes the chunk after it
            over = int(np.searchsorted(ends[start:], self._chunk_size - base, side="right"))
            stop = min(m, start + over + 1)
            part = slice(start, stop)
            lg = log[part]
            lo, hi = int(lg.min()), int(lg.max())
            if cb.num_messages == 0 or lo < cb.message_start_time:
                cb.message_start_time = lo
            if hi > cb.message_end_time:
                cb.message_end_time = hi
            cb.num_messages += stop - start
            offsets = np.empty(stop - start, np.uint64)
            offsets[0] = base + (int(ends[start - 1]) if start else 0)
            offsets[1:] = base + ends[start : stop - 1]
            pairs = np.empty((stop - start, 2), np.uint64)
            pairs[:, 0] = lg
            pairs[:, 1] = offsets
            c_part = ch[part]
            uniq, first = np.unique(c_part, return_index=True)
            indices = cb.message_indices
            for c in uniq[np.argsort(first)].tolist():  # a chunk's indices in first-seen order
                index = indices.get(c)
                if index is None:
                    index = indices[c] = _FlatMessageIndex(c)
                sel = pairs[c_part == c]
                if type(index) is _FlatMessageIndex:
                    index.flat.frombytes(sel.tobytes())
                else:  # made by mcap's own add_message in this chunk
                    index.records.extend(map(tuple, sel.tolist()))
            heads = head[part].tobytes()
            w = _MESSAGE_HEAD.size
            buf.write(
                b"".join(
                    chain.from_iterable(
                        zip([heads[i : i + w] for i in range(0, len(heads), w)], datas[part], strict=True)
                    )
                )
            )
            if stop - start == over + 1:  # the last record ended past the chunk size
                self._finalize()
            start = stop


class _Pairs:
    """``MessageIndex.records``'s list of (log time, offset), kept flat in an ``array``."""

    def __init__(self, flat: array[int]) -> None:
        self._flat = flat

    def append(self, pair: tuple[int, int]) -> None:
        self._flat.extend(pair)

    def __len__(self) -> int:
        return len(self._flat) // 2

    def __iter__(self) -> Iterator[tuple[int, int]]:
        f = self._flat
        return iter(list(zip(f[0::2], f[1::2], strict=True)))


class _FlatMessageIndex(MessageIndex):
    """A chunk's message index for one channel as one flat array of u64, written in one piece.

    ``MessageIndex.write`` writes two 8-byte values per message with a call each (at chunk end
    that was a sixth of the recording's cost in ``hil sim``); the record's bytes are the same:
    the entries are little-endian u64 pairs, as the array holds them on a little-endian host.
    """

    def __init__(self, channel_id: int) -> None:  # not the dataclass's: no records list
        self.channel_id = channel_id
        self.flat: array[int] = array("Q")

    @property  # type: ignore[override]
    def records(self) -> _Pairs:  # type: ignore[override]
        return _Pairs(self.flat)

    def write(self, stream: RecordBuilder) -> None:
        stream.start_record(Opcode.MESSAGE_INDEX)
        stream.write2(self.channel_id)
        stream.write4(len(self.flat) * 8)
        flat = self.flat
        if sys.byteorder != "little":
            flat = array("Q", flat)
            flat.byteswap()
        stream.write(flat.tobytes())
        stream.finish_record()


class PackedChunkIndex:
    """The writer's list of ChunkIndex records, kept as their serialised bytes, on disk.

    ``mcap.Writer`` holds one ``ChunkIndex`` object per chunk until ``finish`` writes the summary;
    with a per-channel offset dict that is 2,390 B of Python objects per chunk (tracemalloc, 30
    channels; ``hil bench soak`` measures it), and the recorder closes a chunk at least every
    second: the linear part of its RSS growth over a long session. Serialised at once, the same
    record is 386 B (~10 bytes a channel plus 60); with a ``spill`` file the packed bytes go
    there in blocks of ``SPILL_BLOCK``, so the index costs no memory however long the session
    (a 1 kHz soak closes ~2 chunks a second: 820 B/s, 3 MiB an hour, otherwise held until the
    footer). ``finish`` only iterates the list and calls ``write`` on each item, so one item
    that writes every packed record keeps the file byte-identical. A spill that cannot be
    written (disk full) is given up and the index is held in memory from then on.
    """

    SPILL_BLOCK = 64 * 1024

    def __init__(self, spill: IO[bytes] | None = None) -> None:
        self._packed = bytearray()
        self._count = 0
        self._spill = spill
        self._spilled = 0

    def append(self, index: ChunkIndex) -> None:
        builder = RecordBuilder()
        index.write(builder)
        self._packed += builder.end()
        self._count += 1
        if self._spill is not None and len(self._packed) >= self.SPILL_BLOCK:
            self._spill_out()

    def spill_to(self, spill: IO[bytes] | None) -> None:
        """Spill from now on to ``spill`` (unbuffered, owned and closed here); None: keep it all."""
        assert self._spill is None and not self._spilled, "one spill file per index"
        self._spill = spill

    def _spill_out(self) -> None:
        assert self._spill is not None
        view = memoryview(self._packed)
        try:
            while view:  # an unbuffered file may take part of a block per call
                n = self._spill.write(view)
                if not n:  # nothing taken (None: would block): a spill that does not progress
                    raise OSError("the index spill file took no bytes")
                view = view[n:]
        except OSError:
            view.release()
            self._take_back()  # keep it in memory: the summary must still be complete
            return
        view.release()
        self._spilled += len(self._packed)
        self._packed = bytearray()

    def _read_spill(self) -> Iterator[bytes]:
        assert self._spill is not None
        fd, offset = self._spill.fileno(), 0
        while offset < self._spilled:
            try:
                block = os.pread(fd, min(self._spilled - offset, 1 << 20), offset)
            except OSError as err:
                raise RecordingError(f"cannot read back the chunk index spill file: {err}") from err
            if not block:
                raise RecordingError(f"the chunk index spill file ended {self._spilled - offset} bytes early")
            offset += len(block)
            yield block

    def _take_back(self) -> None:
        """Hold the whole index in memory again and drop the spill file."""
        if self._spill is None:
            return
        self._packed = bytearray(b"".join(self._read_spill())) + self._packed
        self._spilled = 0
        self.close()

    def __len__(self) -> int:
        return self._count

    def __iter__(self) -> Iterator[PackedChunkIndex]:
        if self._count:
            yield self

    def write(self, stream: RecordBuilder) -> None:
        out = stream._buffer  # RecordBuilder has no call for raw bytes
        if self._spilled:
            for block in self._read_spill():
                out.write(block)
        out.write(self._packed)

    def close(self) -> None:
        """Drop the spill file (unlinked at creation, so closing it frees the disk)."""
        if self._spill is not None:
            with contextlib.suppress(OSError):
                self._spill.close()
            self._spill = None

    @property
    def nbytes(self) -> int:
        """The whole index, in memory or spilled."""
        return self._spilled + len(self._packed)

    @property
    def held_bytes(self) -> int:
        """The part of the index in this process's memory."""
        return len(self._packed)


_CHUNK_INDICES = "_Writer__chunk_indices"  # mcap.Writer's private list (mcap 1.x)


def _pack_chunk_indices(writer: Writer) -> PackedChunkIndex | None:
    """Swap the writer's chunk-index list for a packed one (before any chunk is written).

    Left alone, with the summary still correct, on an mcap whose Writer keeps them otherwise.
    """
    current = getattr(writer, _CHUNK_INDICES, None)
    if not isinstance(current, list) or current:
        return None
    packed = PackedChunkIndex()
    setattr(writer, _CHUNK_INDICES, packed)
    return packed


def _index_spill_file(path: Path) -> IO[bytes] | None:
    """An unlinked, unbuffered scratch file beside the recording (never in a tmpfs ``/tmp``,
    which would be memory again); None, and the index stays in memory, where none can be made."""
    try:
        return tempfile.TemporaryFile(dir=path.parent, prefix=f".{path.name}.index-", buffering=0)
    except OSError:
        return None


# the batch path pays from here on: per message, one at a time 1.37 µs at 32-128 messages a
# drain; the batch 2.84 µs at 32, 1.84 at 64, 1.33 at 128, 1.03 at 256, 37 µs for one alone
# (3000 drains' worth of 130-byte messages on 15 channels, compression included, 2026-12-06)
BATCH_MIN = 128


class MessageQueue:
    """Messages handed to a :class:`SessionWriter` as columns, written in one batch
    (:meth:`_MessageAppender.add_many`) before anything else is written through it: a caller with
    many messages (``hil sim``, ~3000 a window) appends to the lists and the writer drains them."""

    __slots__ = ("chans", "datas", "logs", "pubs", "seqs")

    def __init__(self) -> None:
        self.chans: list[int] = []
        self.logs: list[int] = []  # log times, ns
        self.datas: list[bytes] = []
        self.pubs: list[int] = []  # publish times, ns
        self.seqs: list[int] = []

    def __len__(self) -> int:
        return len(self.chans)


def _why_not(path: Path, err: OSError) -> str:
    """Why ``path`` cannot be made, as a user fixes it: mkdir's "File exists" meant that a
    directory on the way is a file."""
    if isinstance(err, FileExistsError | NotADirectoryError):
        for parent in path.parents:
            if parent.exists() and not parent.is_dir():
                return f"{parent} is a file, not a directory"
    return str(err.strerror or err)


#: the errors of a write that failed for want of room or of a working disk (not of a bad path)
_WRITE_ERRNOS = frozenset({errno.ENOSPC, errno.EDQUOT, errno.EIO, errno.EFBIG, errno.EROFS})


def write_failed(path: str | Path, err: BaseException) -> RecordingError | None:
    """A recording's write that failed (a full disk, /dev/full, an I/O error) as one line naming
    the file; None for any other error (a bug, an interrupt: raised as it is)."""
    if isinstance(err, OSError) and err.filename is None and err.errno in _WRITE_ERRNOS:
        why = err.strerror
        return RecordingError(f"writing {path} failed: {why}; what was flushed before stays readable")
    return None


class _Zstd1:
    """What mcap's writer calls to compress a chunk, at zstd level 1 instead of ``zstandard``'s
    default 3: on the sim's chunks (0.4 MB of CAN frames, IMU samples and solutions) level 1 took
    1.08 ms a chunk against 1.33 and compressed them 6.01:1 against 5.78:1 (30 chunks of a
    straight_level recording, 2026-12-07). A fresh compressor per call, as ``zstandard.compress``
    makes: one shared would not be safe for two writers in two threads."""

    @staticmethod
    def compress(data: bytes) -> bytes:
        import zstandard

        return zstandard.ZstdCompressor(level=1).compress(data)


def _chunks_at_zstd_level_1() -> None:
    """mcap.writer's chunks through :class:`_Zstd1` (it names the module ``zstandard`` and calls
    its ``compress`` per chunk; readers are unaffected: a zstd frame is one at any level)."""
    import mcap.writer

    if getattr(mcap.writer, "zstandard", None) is not None and mcap.writer.zstandard is not _Zstd1:
        mcap.writer.zstandard = _Zstd1  # type: ignore[attr-defined,assignment]


class SessionWriter:
    """Writes one session file. Not thread-safe: one writer thread owns it."""

    def __init__(
        self,
        path: str | Path,
        *,
        chunk_size: int = 512 * 1024,
        pack_index: bool = True,
        spill_index: bool = True,
        after: SessionWriter | None = None,
    ) -> None:
        """``after``: the part of a split session this file continues: the Foxglove topics'
        sequences go on from its counts, so the parts merged are the unsplit session's."""
        self.path = Path(path)
        try:
            self.path.parent.mkdir(parents=True, exist_ok=True)
            self._fh: IO[bytes] = open(self.path, "wb")  # noqa: SIM115 - owned until close()
        except OSError as err:
            raise RecordingError(f"cannot open {self.path} for writing: {_why_not(self.path, err)}") from err
        from mcap.writer import CompressionType, Writer

        _chunks_at_zstd_level_1()
        self._writer = Writer(self._fh, chunk_size=chunk_size, compression=CompressionType.ZSTD)
        self.chunk_index = _pack_chunk_indices(self._writer) if pack_index else None
        if self.chunk_index is not None and spill_index:
            self.chunk_index.spill_to(_index_spill_file(self.path))
        self._writer.start(profile=PROFILE, library=f"hil {__version__}")
        appender = _MessageAppender.for_writer(self._writer)
        self._add_message = appender.add if appender is not None else self._writer.add_message
        self._add_many = appender.add_many if appender is not None and sys.byteorder == "little" else None
        self.queue = MessageQueue()
        self._schemas: dict[str, int] = {}
        # the contract's channels by (topic, publisher), the Foxglove well-known ones by topic
        self._channels: dict[tuple[str, str] | str, int] = {}
        self._publishers_per_topic: dict[str, int] = {}
        self._raw_channels: dict[tuple[str, str], int] = {}
        # each Foxglove topic's message count over the session (its parts too): its sequence
        self._wellknown_seq: dict[str, int] = dict(after._wellknown_seq) if after is not None else {}
        self.closed = False

    def _drain(self) -> None:
        """Write what :attr:`queue` holds (times clamped to u64 and sequences to u32 as
        :meth:`write` clamps them), and empty it in place. Fewer than ``BATCH_MIN`` messages go
        one at a time: the batch's numpy set-up costs ~37 µs, which a live recorder's Foxglove
        message (one per drain) paid alone."""
        q = self.queue
        if not q.chans:
            return
        add_many = self._add_many
        columns = self._columns(q) if add_many is not None and len(q.chans) >= BATCH_MIN else None
        if columns is None or add_many is None:  # the library's add_message, one at a time, as write() does
            for c, lg, d, pb, sq in zip(q.chans, q.logs, q.datas, q.pubs, q.seqs, strict=True):
                self._add_message(c, _u64(lg), d, _u64(pb), sq & 0xFFFFFFFF)
        else:
            logs, pubs, seqs = columns
            add_many(q.chans, logs, q.datas, pubs, seqs)
        for col in (q.chans, q.logs, q.datas, q.pubs, q.seqs):
            col.clear()

    @staticmethod
    def _columns(q: MessageQueue) -> tuple[np.ndarray, np.ndarray, np.ndarray] | None:
        """The queue's log times and publish times clamped at 0, and its sequences to u32, as
        arrays; None when a value does not fit int64 (a time past 2**63 ns, year 2262)."""
        import numpy as np

        try:
            logs, pubs = np.array(q.logs, np.int64), np.array(q.pubs, np.int64)
            seqs = np.array(q.seqs, np.int64) & 0xFFFFFFFF
        except OverflowError:
            return None
        np.maximum(logs, 0, out=logs)
        np.maximum(pubs, 0, out=pubs)
        return logs, pubs, seqs

    def _channel(self, topic: str, cls: type[Message], publisher: str | None, origin: str) -> int:
        chan = self._channels.get((topic, publisher or ""))
        if chan is None:
            self._drain()  # a channel's record goes into the chunk, after what was queued
            if publisher is not None:
                n = self._publishers_per_topic.get(topic, 0)
                if n >= MAX_CHANNELS_PER_TOPIC:  # a flood of made-up publishers shares one
                    publisher, origin = MANY_PUBLISHERS, FOREIGN_ORIGIN
                    chan = self._channels.get((topic, publisher))
                    if chan is not None:
                        return chan
                self._publishers_per_topic[topic] = n + 1
            name = schema_name(cls)
            sid = self._schemas.get(name)
            if sid is None:
                data = json.dumps(json_schema(cls), sort_keys=True).encode()
                sid = self._schemas[name] = self._writer.register_schema(name, "jsonschema", data)
            meta = {} if publisher is None else {"publisher": publisher, "origin": origin}
            chan = self._writer.register_channel(topic, "json", sid, meta)
            self._channels[(topic, publisher or "")] = chan
        return chan

    def write(
        self,
        topic: str,
        cls: type[Message],
        payload: bytes,
        *,
        log_time_ns: int,
        publish_time_ns: int,
        seq: int,
        publisher: str | None = None,
        origin: str = "",
    ) -> None:
        """One message; ``publisher`` (a live recorder's: the Zenoh source id) and its ``origin``
        go into the channel's metadata, one channel per topic and publisher."""
        chan = self._channel(topic, cls, publisher, origin)
        self._drain()
        self._add_message(chan, _u64(log_time_ns), payload, _u64(publish_time_ns), seq & 0xFFFFFFFF)

    def channel(self, topic: str, cls: type[Message]) -> int:
        """The id of ``topic``'s channel (no publisher), registered now if it is new: the
        channel of messages a caller appends to :attr:`queue`."""
        return self._channel(topic, cls, None, "")

    def write_wellknown(self, d: Derived, *, log_time_ns: int) -> None:
        """A Foxglove well-known message (``hil.wellknown``): its own channel, the SDK's schema,
        ``publish_time`` = its timestamp, ``sequence`` = its count on the topic."""
        chan, n = self._wellknown_next(d)
        self._drain()
        self._add_message(chan, _u64(log_time_ns), d.data, _u64(d.stamp_ns), n & 0xFFFFFFFF)

    def queue_wellknown(self, d: Derived, log_time_ns: int) -> None:
        """:meth:`write_wellknown` through :attr:`queue`."""
        chan, n = self._wellknown_next(d)
        q = self.queue
        q.chans.append(chan)
        q.logs.append(log_time_ns)
        q.datas.append(d.data)
        q.pubs.append(d.stamp_ns)
        q.seqs.append(n)

    def _wellknown_next(self, d: Derived) -> tuple[int, int]:
        """The channel of ``d``'s topic (registered at its first message) and ``d``'s sequence."""
        chan = self._channels.get(d.topic)
        if chan is None:
            self._drain()
            from hil.wellknown import MESSAGE_ENCODING, SCHEMAS

            schema = SCHEMAS[d.schema]
            sid = self._schemas.get(schema.name)
            if sid is None:
                sid = self._schemas[schema.name] = self._writer.register_schema(
                    schema.name, schema.encoding, schema.data
                )
            chan = self._channels[d.topic] = self._writer.register_channel(d.topic, MESSAGE_ENCODING, sid)
        n = self._wellknown_seq.get(d.topic, 0)
        self._wellknown_seq[d.topic] = n + 1
        return chan, n

    def write_raw(
        self, topic: str, payload: bytes, *, log_time_ns: int, encoding: str, sequence: int
    ) -> None:
        """A message on a key outside the contract, kept as its bytes on a schema-less channel.

        The channel's message encoding is ``json`` when the publisher's Zenoh encoding says JSON,
        else that Zenoh encoding itself (``zenoh/bytes``, ``text/plain``, ...); channel metadata
        ``hil: raw``. ``publish_time`` is the receive time: the bytes carry no stamp we can trust.
        """
        base = encoding.split(";", 1)[0]
        msg_encoding = "json" if base in ("application/json", "text/json") else (encoding or "zenoh/bytes")
        self._drain()
        chan = self._raw_channels.get((topic, msg_encoding))
        if chan is None:
            chan = self._raw_channels[(topic, msg_encoding)] = self._writer.register_channel(
                topic, msg_encoding, 0, {"hil": RAW, "zenoh_encoding": encoding}
            )
        self._add_message(chan, _u64(log_time_ns), payload, _u64(log_time_ns), sequence)

    def add_metadata(self, name: str, data: dict[str, Any]) -> None:
        """Metadata values must be strings in MCAP: non-strings are stored as JSON."""
        self._drain()
        self._writer.add_metadata(
            name, {k: v if isinstance(v, str) else json.dumps(v) for k, v in data.items()}
        )

    def add_attachment(
        self, name: str, data: bytes, media_type: str = "text/plain", log_time_ns: int = 0
    ) -> None:
        self._drain()
        self._writer.add_attachment(
            create_time=_u64(log_time_ns),
            log_time=_u64(log_time_ns),
            name=name,
            media_type=media_type,
            data=data,
        )

    def flush(self) -> None:
        """Close the chunk in progress and push it to the OS (a SIGKILL after this loses nothing)."""
        self._drain()
        self._writer.flush()

    def abandon(self) -> None:
        """Give up on a file that can no longer be written (disk full): close, never raise.

        What was flushed before stays readable up to its last complete chunk.
        """
        self.closed = True
        if self.chunk_index is not None:
            self.chunk_index.close()
        with contextlib.suppress(OSError):
            self._fh.close()

    def tell(self) -> int:
        """Bytes handed to the OS so far (for size-based splitting)."""
        self._drain()
        return self._fh.tell()

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._drain()
            self._writer.finish()
        finally:
            if self.chunk_index is not None:
                self.chunk_index.close()
        self._fh.close()


@dataclass
class Record:
    topic: str
    schema: str
    payload: bytes
    log_time_ns: int
    publish_time_ns: int
    sequence: int
    publisher: str = ""  # the Zenoh source id the recorder saw ("" offline or unknown)
    origin: str = ""  # "rig", "foreign", "unknown"; "" in files without publishers
    # a reader with a topic filter (``iter_records(keep=...)``): the largest log time of the
    # rig's messages it left out just before this one (-1: none), for a caller whose clock is
    # the log time of every message (``hil.record.rerun_timesync``)
    skipped_log_ns: int = -1
    # a restarted recorder's copy of a message published before it started: recovered from the
    # publishers' caches (``SessionStream``), written as it came, not in publication order
    recovered: bool = False

    @property
    def foreign(self) -> bool:
        """Published by a process that is not the rig's: recorded, never the rig's data."""
        return self.origin == FOREIGN_ORIGIN

    def decode(self) -> Message:
        cls = TYPES_BY_NAME.get(self.schema)
        if cls is None:
            raise RecordingError(
                f"channel {self.topic!r} has schema {self.schema!r}, not a hil contract type"
            )
        try:
            return decode(cls, self.payload)  # the previous form of a type too (LEGACY_FORMS)
        except (msgspec.DecodeError, msgspec.ValidationError) as err:
            raise PayloadError(self, str(err)) from None


class PayloadError(RecordingError):
    """A recorded payload that does not decode as its channel's type: which message, and what
    to do (the file is known to the caller: :meth:`in_file`)."""

    def __init__(self, rec: Record, why: str) -> None:
        self._set(rec.topic, rec.sequence, rec.log_time_ns, rec.schema, why)

    def _set(self, topic: str, sequence: int, log_time_ns: int, schema: str, why: str) -> None:
        self.topic, self.sequence, self.log_time_ns, self.schema, self.why = (
            topic,
            sequence,
            log_time_ns,
            schema,
            why,
        )
        super().__init__(self.in_file("FILE"))

    def __reduce__(self) -> tuple[Any, ...]:
        """Pickled by its fields (``hil info``'s second-half reader sends it back as it is)."""
        return (_payload_error, (self.topic, self.sequence, self.log_time_ns, self.schema, self.why))

    def in_file(self, path: str | Path) -> str:
        pat = f"'{re.escape(self.topic)}$'"
        return (
            f"{path}: {self.topic} seq {self.sequence} (log_time_ns {self.log_time_ns}): the payload is "
            f"not a {self.schema} ({self.why}); look at it with `hil cat {path} --topics {pat}`, or leave "
            f"the topic out with `hil filter {path} -o OUT.mcap --exclude-topics {pat}`"
        )


def _payload_error(topic: str, sequence: int, log_time_ns: int, schema: str, why: str) -> PayloadError:
    err = PayloadError.__new__(PayloadError)
    err._set(topic, sequence, log_time_ns, schema, why)
    return err


@dataclass
class Session:
    """Everything a file holds, read in file order (which is the recorder's write order)."""

    path: Path
    records: list[Record]
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    truncated: bool = False
    truncation_reason: str = ""

    def topics(self) -> dict[str, str]:
        out: dict[str, str] = {}
        for r in self.records:
            out.setdefault(r.topic, r.schema)
        return out

    def by_topic(self, topic: str) -> list[Record]:
        return [r for r in self.records if r.topic == topic]

    def by_topic_prefix(self, prefix: str) -> list[Record]:
        return [r for r in self.records if r.topic.startswith(prefix)]

    def meta(self, name: str, key: str, default: Any = None) -> Any:
        value = self.metadata.get(name, {}).get(key)
        if value is None:
            return default
        try:
            return json.loads(value)
        except ValueError:
            return value


PROGRESS_EVERY = 8192  # records between two progress callbacks of ``iter_records``


#: ``hil.wellknown.PREFIX``, written out: importing that module loads the Foxglove SDK (~15 ms),
#: which a reader does not use (tests/unit/test_service_startup.py checks the two are equal)
DERIVED_PREFIX = "/foxglove/"


def is_derived(topic: str) -> bool:
    """A channel of Foxglove well-known types derived from the rig's messages (``hil.wellknown``)."""
    return topic.startswith(DERIVED_PREFIX)


def iter_records(
    path: str | Path,
    on_progress: Callable[[int, int], None] | None = None,
    *,
    derived: bool = False,
    header: bool = False,
    keep: Callable[[str], bool] | None = None,
) -> Iterator[tuple[str, Any]]:
    """Yield ``(kind, record)`` from a file, stopping quietly at a truncated tail
    (``header``: the file's ``Header`` record too, as ``("header", rec)``).

    ``keep(topic)``: only the rig's messages (no foreign channel) of topics it keeps are made
    into ``Record``s; of the others' only their log times are told: each kept record's
    ``skipped_log_ns``, and at the end a ``("skipped", (largest, last))`` item for those after
    the last kept one. A caller that reads a fraction of the topics skips the cost of the rest.

    The derived ``/foxglove/...`` channels (``is_derived``) are left out unless ``derived``: they are
    a view of the rig's messages, not rig traffic, and rerun, replay and loss accounting read the
    messages themselves.

    ``on_progress(bytes_read, file_bytes)`` is called every ``PROGRESS_EVERY`` records: a one-hour
    file is read for minutes, and the byte position is the only total known before the end.

    Read by ``_FastReader``: what ``mcap.StreamReader`` reads, record by record, but a chunk's
    messages parsed with one ``struct`` call each (the reader's six small reads and a dataclass
    per message were half of ``hil rerun --core timesync``'s time) and the per-chunk message
    indexes skipped unparsed. A chunk is parsed whole before any of its records is given, as
    ``StreamReader`` does, so a damaged chunk yields nothing of itself.
    """
    for kind, rec in _iter_items(path, on_progress, derived=derived, header=header, keep=keep):
        if kind == "messages":
            for r in rec:
                yield "message", r
        else:
            yield kind, rec


@dataclass(frozen=True)
class FilePart:
    """A stretch of a finished file's data section, from the chunk at ``start`` to the record at
    ``stop`` (None: to the end), with the schemas and channels of its summary section: a reader
    that begins past the file's start knows every channel the records there refer to."""

    start: int
    stop: int | None
    schemas: tuple[Schema, ...] = ()
    channels: tuple[Channel, ...] = ()


def file_halves(path: str | Path) -> tuple[FilePart, FilePart] | None:
    """The file in two parts of about equal bytes, split at a chunk, for two readers at once;
    None when it has no summary with at least two chunks (a file cut short, a small one)."""
    from mcap.reader import make_reader

    try:
        with open(path, "rb") as fh:
            summary = make_reader(fh).get_summary()
    except Exception:  # a file without a readable summary is read in one pass, as ever
        return None
    if summary is None or len(summary.chunk_indexes) < 2:
        return None
    starts = sorted(c.chunk_start_offset for c in summary.chunk_indexes)
    end = max(c.chunk_start_offset + c.chunk_length for c in summary.chunk_indexes)
    mid = min(starts[1:], key=lambda o: abs(o - (starts[0] + end) / 2))
    defs = tuple(summary.schemas.values()), tuple(summary.channels.values())
    return FilePart(0, mid), FilePart(mid, None, *defs)


def _iter_items(
    path: str | Path,
    on_progress: Callable[[int, int], None] | None = None,
    *,
    derived: bool = False,
    header: bool = False,
    keep: Callable[[str], bool] | None = None,
    part: FilePart | None = None,
    check_indexes: bool = False,
) -> Iterator[tuple[str, Any]]:
    """``iter_records``' items, but a chunk's messages as one ``("messages", [Record, ...])``
    item: a reader that takes them in a batch (``SessionStream``) skips a generator step and a
    tuple per message. ``part``: only that stretch of the file (``file_halves``).
    ``check_indexes``: the message indexes checked too (``_FastReader._check_indexes``): what
    reads a whole file to say what it holds (``hil info``, ``read_session``) does; a rerun, which
    reads the data and its CRCs, not the index, does not pay for it."""
    try:
        fh = open(path, "rb")  # noqa: SIM115
        size = os.fstat(fh.fileno()).st_size
    except OSError as err:
        raise RecordingError(f"cannot open recording {path}: {err.strerror}") from err
    with fh:
        reader = _FastReader(fh, size, on_progress, derived, header, keep, check_indexes)
        try:
            yield from reader.records(part)
        except UnsupportedCompressionError as err:
            raise unsupported_compression(path, reader.at, str(err).split(": ")[-1]) from None
        except _ChunkCrcError:
            raise damaged(path, reader.at, "a chunk that fails its CRC") from None
        except _IndexMismatch:
            raise damaged(path, reader.at, "a message index that does not fit its chunk") from None
        except Exception as err:  # McapError, EOF, zstd errors on a half-written chunk and similar
            what = f"{type(err).__name__}: {err}".rstrip(": ")
            if is_finished(path):  # a closed file has no half-written tail: this is damage
                raise damaged(path, reader.at, f"a record that does not read: {what}") from None
            yield from reader.tail()
            yield "truncated", f"{type(err).__name__}: {err}"


_RECORD_HEAD = struct.Struct("<BQ")  # opcode, record length
_MESSAGE_FIELDS = struct.Struct("<HIQQ")  # channel id, sequence, log time, publish time
_MESSAGE_RECORD = struct.Struct("<BQHIQQ")  # the two above: a chunk's message record in one call
_CHUNK_HEAD = struct.Struct("<QQQII")  # start, end, uncompressed size, crc, compression length
_RECORD_SIZE_LIMIT = 4 * 2**30  # StreamReader's default
_SKIPPED = ("", "", "", "")  # a channel whose messages ``keep`` leaves out (their log times count)


class _FastReader:
    """The records of one MCAP file in file order, as ``iter_records`` gives them (see there)."""

    def __init__(
        self,
        fh: IO[bytes],
        size: int,
        on_progress: Callable[[int, int], None] | None,
        derived: bool,
        header: bool,
        keep: Callable[[str], bool] | None = None,
        check_indexes: bool = False,
    ) -> None:
        self.fh = fh
        self.keep = keep
        self.check_indexes = check_indexes
        self.skipped_max = -1  # the rig's messages left out by ``keep`` since the last kept one
        self.skipped_last = -1
        self.size = size
        self.on_progress = on_progress
        self.derived = derived
        self.header = header
        self.n = 0
        self.at = 0  # the byte offset of the record being read (where damage is reported)
        self.schemas: dict[int, Schema] = {}
        self._last_chunk: tuple[int, int, int] | None = None  # start, end, size: its indexes follow
        # channel id -> (topic, schema name, publisher, origin); None: a channel left out
        # (derived, or a foreign one ``keep`` leaves out), _SKIPPED: one whose log times count
        self.channels: dict[int, tuple[str, str, str, str] | None] = {}

    def _read(self, n: int) -> bytes:
        data = self.fh.read(n)
        if len(data) < n:
            raise EndOfFile()
        return data

    def _count(self, k: int = 1) -> None:
        """Progress as ``StreamReader``'s record count would give it: every ``PROGRESS_EVERY``."""
        before = self.n
        self.n += k
        if self.on_progress is not None and self.n // PROGRESS_EVERY != before // PROGRESS_EVERY:
            self.on_progress(self.fh.tell(), self.size)

    def _channel(self, rec: Channel) -> None:
        if not self.derived and is_derived(rec.topic):
            self.channels[rec.id] = None
            return
        schema = self.schemas.get(rec.schema_id)
        meta = rec.metadata or {}
        if self.keep is not None and meta.get("origin") == FOREIGN_ORIGIN:
            self.channels[rec.id] = None  # a filtering reader gives the rig's data only
            return
        if self.keep is not None and not self.keep(rec.topic):
            self.channels[rec.id] = _SKIPPED
            return
        self.channels[rec.id] = (
            rec.topic,
            schema.name if schema else "",
            meta.get("publisher", ""),
            meta.get("origin", ""),
        )

    def records(self, part: FilePart | None = None) -> Iterator[tuple[str, Any]]:
        stop = None
        if part is not None and part.start > 0:
            for schema in part.schemas:
                self.schemas[schema.id] = schema
            for channel in part.channels:
                self._channel(channel)
            self.fh.seek(part.start)
        elif self._read(len(MAGIC)) != MAGIC:
            raise InvalidMagic(MAGIC)
        if part is not None:
            stop = part.stop
        read, head, tell = self._read, _RECORD_HEAD, self.fh.tell
        check = self.check_indexes
        indexes: list[Any] = []  # the message indexes after the last chunk
        indexes_at = 0
        while True:
            self.at = tell()
            if stop is not None and self.at >= stop:
                yield from self.tail()
                return
            opcode, length = head.unpack(read(head.size))
            if length > _RECORD_SIZE_LIMIT:
                raise RecordLengthLimitExceeded(opcode, length, _RECORD_SIZE_LIMIT)
            body = read(length)
            self._count()
            if opcode == _OP_MESSAGE_INDEX:
                if check:
                    if not indexes:
                        indexes_at = self.at
                    indexes.append(body)
                continue
            if indexes:  # what followed the chunk before this record were its indexes
                here, self.at = self.at, indexes_at  # damage is said at the first of them
                self._check_indexes(indexes)
                self.at, indexes = here, []
            if opcode == Opcode.CHUNK:
                yield "messages", self._chunk(body)
            elif opcode == Opcode.MESSAGE:
                yield "messages", self._messages(body, 0, len(body), single=True)
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                self._definition(opcode, body)
            elif opcode == Opcode.METADATA:
                yield "metadata", Metadata.read(_stream(body))
            elif opcode == Opcode.ATTACHMENT:
                yield "attachment", Attachment.read(_stream(body))
            elif opcode == Opcode.HEADER:
                rec = Header.read(_stream(body))
                if self.header:
                    yield "header", rec
            elif opcode == Opcode.FOOTER:
                if read(len(MAGIC)) != MAGIC:
                    raise InvalidMagic(MAGIC)
                yield from self.tail()
                return
            # chunk indexes, statistics, ...: nothing iter_records gives

    def _definition(self, opcode: int, body: bytes) -> None:
        if opcode == Opcode.SCHEMA:
            s = Schema.read(_stream(body))
            self.schemas[s.id] = s
        else:
            self._channel(Channel.read(_stream(body)))

    def _check_indexes(self, bodies: list[bytes]) -> None:
        """The message indexes that followed a chunk, against it: each framed as its length says,
        each entry's log time within the chunk's span and its offset within the chunk's records.
        The data itself is read, not the index; but a file whose index is damaged is damaged.
        All of a chunk's at once: reading a uav_survey 120 s file spent 48 ms on them (one index
        at a time took 81 ms)."""
        unpack, n_data = struct.unpack_from, 0
        for body in bodies:
            if len(body) < 6:
                raise _IndexMismatch()
            (n,) = unpack("<I", body, 2)
            if 6 + n != len(body) or n % 16:
                raise _IndexMismatch()
            n_data += n
        if self._last_chunk is None or n_data == 0:  # the second half's first records: no chunk
            return
        start, end, size = self._last_chunk
        entries = array("Q")  # not numpy: the time-sync rerun reads files without importing it
        entries.frombytes(b"".join([b[6:] for b in bodies]))
        if sys.byteorder != "little":
            entries.byteswap()
        times = entries[0::2]
        if min(times) < start or max(times) > end or max(entries[1::2]) >= size:
            raise _IndexMismatch()

    def _chunk(self, body: bytes) -> list[Record]:
        start, end, size, crc, n_comp = _CHUNK_HEAD.unpack_from(body, 0)
        self._last_chunk = (start, end, size)
        at = _CHUNK_HEAD.size
        compression = str(body[at : at + n_comp], "utf-8")
        at += n_comp
        (n_data,) = struct.unpack_from("<Q", body, at)
        at += 8
        if at + n_data > len(body):
            raise EndOfFile()
        raw = body[at : at + n_data]
        if compression == "zstd":
            data: bytes = zstandard.decompress(raw, size)
        elif compression == "lz4":
            import lz4.frame

            data = lz4.frame.decompress(raw)
        elif compression == "":
            data = raw
        else:
            raise UnsupportedCompressionError(compression)
        if crc and zlib.crc32(data) != crc:  # ~0.4 ms a MB: a flipped bit is never replayed
            raise _ChunkCrcError()
        return self._messages(data, 0, len(data), single=False)

    def _messages(self, data: bytes, pos: int, end: int, *, single: bool) -> list[Record]:
        """The messages in ``data[pos:end]``: a chunk's records, or one message record's body
        (``single``). Schemas and channels among them are taken in as they come; what ``keep``
        left out counts only once all of them parsed (a damaged chunk gives nothing).

        A chunk's record is unpacked as a message record (head and fields in one ``struct``
        call: most of a chunk is messages); the fields are used only if it is one, and a record
        too near the chunk's end for that is unpacked head first, as any other record."""
        out: list[Record] = []
        channels, unpack_msg, unpack_head, unpack_record = (
            self.channels,
            _MESSAGE_FIELDS.unpack_from,
            _RECORD_HEAD.unpack_from,
            _MESSAGE_RECORD.unpack_from,
        )
        message = int(Opcode.MESSAGE)
        skipped_max, skipped_last = self.skipped_max, self.skipped_last
        n = 0
        while pos < end:
            if single:
                opcode, length = message, end - pos
                cid, seq, log, pub = unpack_msg(data, pos)
            else:
                try:
                    opcode, length, cid, seq, log, pub = unpack_record(data, pos)
                except struct.error:  # fewer than a message record's fixed bytes left
                    opcode, length = unpack_head(data, pos)
                    if pos + 9 + length > end:
                        raise EndOfFile() from None
                    if opcode == message:
                        cid, seq, log, pub = unpack_msg(data, pos + 9)
                pos += 9
                if pos + length > end:
                    raise EndOfFile()
            n += 1
            if opcode == message:
                chan = channels[cid]
                if chan is _SKIPPED:
                    skipped_last = log
                    if log > skipped_max:
                        skipped_max = log
                elif chan is not None:
                    topic, schema, publisher, origin = chan
                    payload = data[pos + 22 : pos + length]
                    rec = Record(topic, schema, payload, log, pub, seq, publisher, origin)
                    if skipped_max >= 0:
                        rec.skipped_log_ns = skipped_max
                        skipped_max = -1
                    out.append(rec)
            elif opcode in (Opcode.SCHEMA, Opcode.CHANNEL):
                self._definition(opcode, data[pos : pos + length])
            pos += length
        self.skipped_max, self.skipped_last = skipped_max, skipped_last
        if not single:
            self._count(n)
        return out

    def tail(self) -> Iterator[tuple[str, Any]]:
        """The log times of what ``keep`` left out after the last kept message, if any."""
        if self.skipped_max >= 0:
            yield "skipped", (self.skipped_max, self.skipped_last)
            self.skipped_max = -1


def _stream(body: bytes) -> ReadDataStream:
    return ReadDataStream(io.BytesIO(body))


class SessionStream:
    """A recording read once, message by message, in file order, without holding it in memory.

    What ``read_session`` gives, for files too big to hold (a one-hour session is ~12 million
    messages, several GB as Python objects): iterate it for the ``Record``s; ``metadata``,
    ``truncated`` and ``truncation_reason`` are filled as the reading goes and are complete once
    the iteration has ended. An unreadable file raises ``RecordingError`` like ``read_session``.
    Iterating again reads the file again.

    ``follow_parts``: a recording split by size or duration (``<stem>_0001.mcap``, ...) is read on
    through its parts, in order -- the recorder rotates between two messages, so the parts end
    to end are the session's one sequence of messages.

    ``keep(topic)``: only those topics' records (``iter_records``); each record's
    ``skipped_log_ns`` and ``skipped_tail`` tell the log times of the rest, across parts.
    """

    def __init__(
        self,
        path: str | Path,
        on_progress: Callable[[int, int], None] | None = None,
        *,
        follow_parts: bool = False,
        keep: Callable[[str], bool] | None = None,
    ) -> None:
        self.path = Path(path)
        if not self.path.is_file():
            raise RecordingError(f"no recording at {self.path}")
        self.keep = keep
        # with ``keep``: (largest, last) log time of the rig's messages left out after the last
        # record given (None: none); complete once the iteration has ended
        self.skipped_tail: tuple[int, int] | None = None
        self.on_progress = on_progress
        self.paths = session_files(self.path) if follow_parts else [self.path]
        self.metadata: dict[str, dict[str, str]] = {}
        self.truncated = False
        self.truncation_reason = ""
        # files cut short that a later one continues (a killed recorder's, before the restarted
        # one's part): read up to the cut, and not the session's end, so not ``truncated``
        self.cut_files: list[tuple[str, str]] = []
        self._cut_why = ""  # why the reading of the last file stopped

    def __iter__(self) -> Iterator[Record]:
        self.metadata = {}
        self.truncated = False
        self.truncation_reason = ""
        self.skipped_tail = None
        self.cut_files = []
        sizes = [p.stat().st_size for p in self.paths]
        for k, path in enumerate(self.paths):
            n = 0
            if self.truncated:  # the file before was cut, and this one continues the session
                self.cut_files.append((self.paths[k - 1].name, self._cut_why))
                self.truncated, self.truncation_reason = False, ""
            # a restarted recorder's first file: what was published before it started is recovered
            restarted_ns: int | None = None if k == 0 or not RESTART_PART_NAME.search(path.stem) else -1
            progress = self._progress(sum(sizes[:k]), sum(sizes))
            for kind, rec in _iter_items(path, progress, keep=self.keep):
                if kind == "messages":  # a chunk's, in a batch
                    if not rec:
                        continue
                    n += len(rec)
                    if self.skipped_tail is not None:  # the previous part's last messages
                        first = rec[0]
                        first.skipped_log_ns = max(first.skipped_log_ns, self.skipped_tail[0])
                        self.skipped_tail = None
                    if restarted_ns is not None:
                        if restarted_ns < 0:
                            restarted_ns = rec[0].log_time_ns
                        for r in rec:
                            r.recovered = r.publish_time_ns < restarted_ns
                    yield from rec
                elif kind == "skipped":
                    prev: tuple[int, int] | None = self.skipped_tail
                    self.skipped_tail = rec if prev is None else (max(prev[0], rec[0]), rec[1])
                elif kind == "metadata":
                    self.metadata[rec.name] = dict(rec.metadata)
                elif kind == "truncated":
                    self.truncated = True
                    self.truncation_reason = f"{path.name}: {rec}"
                    self._cut_why = str(rec)
            if not n and self.truncated and not self.metadata:
                raise RecordingError(f"{path} is not a readable MCAP file ({self.truncation_reason})")

    def _progress(self, before: int, total: int) -> Callable[[int, int], None] | None:
        """Progress over all parts: a part's byte position plus the parts before it."""
        report = self.on_progress
        if report is None:
            return None
        return lambda done, _size: report(before + done, total)


def check_hil_recording(path: str | Path) -> None:
    """Raise ``RecordingError`` (one line: the file and what is wrong) unless ``path`` is an MCAP
    file written by hil (``hil up``, ``hil sim``, the export, ...) that holds at least one message.

    Why before any work: an 8-byte file gave ``hil report`` an empty report and exit 0, and an
    MCAP from another tool sent ``hil replay`` into a raw Zenoh error on its first topic. A file
    cut short by a crash passes when something before the cut is readable (readers go up to its
    last complete chunk).
    """
    p = Path(path)
    if not p.is_file():
        raise RecordingError(f"no recording at {p}" + (" (a directory)" if p.is_dir() else ""))
    try:
        with open(p, "rb") as fh:
            head = fh.read(len(MAGIC))
    except OSError as err:
        raise RecordingError(f"cannot open recording {p}: {err.strerror}") from err
    if head != MAGIC:
        what = "empty" if not head else f"{p.stat().st_size} bytes, no MCAP magic"
        raise RecordingError(f"{p} is not an MCAP file ({what}); give a recording made by hil up or hil sim")
    profile = library = None
    for kind, rec in iter_records(p, header=True):
        if kind == "header":
            profile, library = rec.profile, rec.library
            if profile != PROFILE and not library.startswith("hil "):
                raise RecordingError(
                    f"{p} is an MCAP file but not a hil recording (profile {profile!r}, library "
                    f"{library!r}); hil reads recordings made by hil up, hil sim or their tools"
                )
        elif kind == "message":
            return
        elif kind == "truncated":
            where = "after its header" if profile is not None else "in its header"
            size = p.stat().st_size
            raise RecordingError(
                f"{p} is cut short {where} and holds no readable message ({size} bytes; {rec.rstrip(': ')})"
            )
    raise RecordingError(f"{p} is a hil recording that holds no messages")


def read_session(path: str | Path, *, derived: bool = False) -> Session:
    """Read a whole recording; a file cut short by a crash reads up to its last complete chunk.

    ``derived``: also the Foxglove well-known channels (``iter_records``)."""
    records: list[Record] = []
    session = stream_session(path, records.append, derived=derived)
    session.records = records
    return session


def stream_session(
    path: str | Path,
    on_message: Callable[[Record], None],
    *,
    derived: bool = False,
    on_batch: Callable[[list[Record]], None] | None = None,
    part: FilePart | None = None,
) -> Session:
    """``read_session`` without keeping the messages: each goes to ``on_message`` as it is read
    (a 12000 s session is 36 M of them); the returned Session has the metadata, attachments and
    truncation, and no records. ``on_batch``: a chunk's messages as one list instead, in file
    order (a caller with a loop of its own saves a call and a generator step a message).
    ``part``: that stretch of the file only (``file_halves``)."""
    path = Path(path)
    if not path.is_file():
        raise RecordingError(f"no recording at {path}")
    session = Session(path=path, records=[])
    n = 0
    for kind, rec in _iter_items(path, derived=derived, part=part, check_indexes=True):
        if kind == "messages":
            if on_batch is not None:
                on_batch(rec)
            else:
                for r in rec:
                    on_message(r)
            n += len(rec)
        elif kind == "metadata":
            session.metadata[rec.name] = dict(rec.metadata)
        elif kind == "attachment":
            session.attachments[rec.name] = rec.data
        elif kind == "truncated":
            session.truncated = True
            session.truncation_reason = rec
    if not n and session.truncated and not session.metadata:
        raise RecordingError(f"{path} is not a readable MCAP file ({session.truncation_reason})")
    return session

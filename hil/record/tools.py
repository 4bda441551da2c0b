"""The recording tools ``mcap`` and ``ros2 bag`` users expect, thin over mcap's own API.

``hil recover`` (as ``mcap recover``), ``hil filter`` (time range, topics), ``hil merge`` (split
parts or filtered pieces into one file), ``hil cat`` (messages as JSON lines) and ``hil
attachments`` (list or extract the embedded scenario, DBC and schemas). Every file written here
is a complete, indexed MCAP (summary, chunk and message indexes, statistics), readable by
``mcap.reader.make_reader(f).iter_messages()`` and by Foxglove's ``@mcap/core``; attachments and
metadata travel along. Inputs are read with ``hil.record.scan``, so a crashed recording is read
as far as it goes. A file that is not a hil recording raises ``RecordingError`` (one line).
"""

from __future__ import annotations

import heapq
import itertools
import json
import re
import sys
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import IO, Any, TextIO

from mcap.records import Attachment, Channel, Message, Metadata, Schema
from mcap.writer import CompressionType, Writer

from hil import __version__
from hil.record.completeness import Completeness
from hil.record.mcapio import (
    PROFILE,
    RUN_IDENTITY,
    RecordingError,
    run_identity,
    split_part_path,
    split_parts,
)
from hil.record.scan import Scan, ScanReport, channel_key, describe_loss

CHUNK_SIZE = 512 * 1024


class OutputWriter:
    """An indexed MCAP written from records of other files: schema and channel ids remapped."""

    def __init__(self, path: Path, library: str) -> None:
        self.path = path
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            self._fh: IO[bytes] = open(path, "wb")  # noqa: SIM115 - closed by finish()
        except OSError as err:
            raise RecordingError(f"cannot write {path}: {err.strerror}") from err
        self.writer = Writer(self._fh, chunk_size=CHUNK_SIZE, compression=CompressionType.ZSTD)
        self.writer.start(profile=PROFILE, library=library)
        self._schemas: dict[tuple[Any, ...], int] = {}
        self._channels: dict[tuple[Any, ...], int] = {}
        self.messages = 0
        self.attachments = 0
        self.metadata = 0

    def channel(self, chan: Channel, schema: Schema | None) -> int:
        key = channel_key(chan, schema)
        cid = self._channels.get(key)
        if cid is None:
            sid = 0
            if schema is not None:
                skey = (schema.name, schema.encoding, schema.data)
                sid = self._schemas.get(skey, 0)
                if not sid:
                    sid = self._schemas[skey] = self.writer.register_schema(
                        schema.name, schema.encoding, schema.data
                    )
            cid = self._channels[key] = self.writer.register_channel(
                chan.topic, chan.message_encoding, sid, dict(chan.metadata)
            )
        return cid

    def message(self, cid: int, m: Message) -> None:
        self.writer.add_message(
            cid, log_time=m.log_time, data=m.data, publish_time=m.publish_time, sequence=m.sequence
        )
        self.messages += 1

    def attachment(self, a: Attachment) -> None:
        self.writer.add_attachment(
            create_time=a.create_time, log_time=a.log_time, name=a.name, media_type=a.media_type, data=a.data
        )
        self.attachments += 1

    def add_metadata(self, name: str, data: dict[str, str]) -> None:
        self.writer.add_metadata(name, data)
        self.metadata += 1

    def finish(self) -> None:
        try:
            self.writer.finish()
            self._fh.close()
        except OSError as err:
            raise RecordingError(f"writing {self.path} failed: {err.strerror}") from err

    def abandon(self) -> None:
        """An output that failed half-way is removed: never leave a file that looks finished."""
        try:
            self._fh.close()
        finally:
            self.path.unlink(missing_ok=True)


def _same_file(a: Path, b: Path) -> bool:
    """One file under two names: the same path, a symlink, a hard link or a bind mount (the same
    device and inode). False when either cannot be stat'ed: reading or writing it says why."""
    try:
        return a.exists() and b.exists() and (a.resolve() == b.resolve() or a.samefile(b))
    except OSError:
        return False


def _check_output(out: Path, inputs: Iterable[Path]) -> None:
    """Refused before anything is opened: an output that is one of the inputs under another name
    (a symlink, a hard link, a bind mount: the same device and inode) would be truncated by the
    write and then removed as a failed output, the recording with it."""
    for p in inputs:
        if _same_file(out, p):
            raise RecordingError(f"{out}: the output is the input {p} (the same file); give another -o")


@dataclass
class Tagged:
    """A message with its channel and schema as read (what cat and the writers need)."""

    channel: Channel
    schema: Schema | None
    message: Message


def iter_tagged(scan: Scan, extras: list[Attachment | Metadata] | None = None) -> Iterator[Tagged]:
    """The messages of a scan with their channel; attachments and metadata go to ``extras``."""
    for rec in scan:
        if isinstance(rec, Message):
            chan = scan.channels[rec.channel_id]
            yield Tagged(chan, scan.schemas.get(chan.schema_id), rec)
        elif isinstance(rec, (Attachment, Metadata)) and extras is not None:
            extras.append(rec)


# -- recover ---------------------------------------------------------------------------------------


@dataclass
class RecoverResult:
    out: Path
    report: ScanReport
    seq_missing: int  # seq gaps within the recovered messages, summed over publishers
    attachments: int
    metadata: int
    had_completeness: bool

    def lines(self) -> list[str]:
        r = self.report
        span = (
            f"log time {r.first_ns / 1e9:.3f}..{r.last_ns / 1e9:.3f} s"
            if r.first_ns is not None and r.last_ns is not None
            else "no messages"
        )
        out = [
            f"hil recover: {r.path} -> {self.out}: {r.messages} messages on {len(r.per_topic)} topics "
            f"({span}), {self.attachments} attachments, {self.metadata} metadata records"
        ]
        loss = describe_loss(r)
        if not loss:
            out.append("nothing lost: the file was finished and every chunk read whole")
        out += [f"lost: {ln}" for ln in loss]
        if not self.had_completeness:
            out.append(
                "lost: the recorder's completeness summary (written at a clean stop only); "
                "hil info FILE recounts seq gaps"
            )
        if self.seq_missing:
            out.append(f"seq gaps inside what was recovered: {self.seq_missing} messages missing")
        return out


def recover(src: str | Path, out: str | Path | None = None) -> RecoverResult:
    """Rewrite a crashed or truncated recording as a finished, indexed file (``mcap recover``).

    Everything readable is kept in file order: messages (also from a chunk cut in half),
    schemas, channels, attachments, metadata; a ``recovered`` metadata record says from what and
    what was lost. The index, statistics and footer are rebuilt by mcap's writer.
    """
    src = Path(src)
    dest = Path(out) if out is not None else src.with_name(f"{src.stem}.recovered{src.suffix}")
    _check_output(dest, [src])
    scan = Scan(src)
    w = OutputWriter(dest, f"hil {__version__} recover")
    extras: list[Attachment | Metadata] = []
    comp = Completeness()
    try:
        for t in iter_tagged(scan, extras):
            w.message(w.channel(t.channel, t.schema), t.message)
            seq = _payload_seq(t.message.data)
            if seq is not None:
                comp.see(t.channel.topic, seq)
        had_completeness = False
        rep = scan.report
        lossy = bool(rep.lost_chunks) or not rep.finished
        for x in extras:
            if isinstance(x, Attachment):
                w.attachment(x)
            else:
                had_completeness |= x.name == "completeness"
                meta = dict(x.metadata)
                if x.name == "completeness" and lossy:  # the recorder's verdict was of the whole file
                    meta.update(replay_ready="false", recovered=f"from {src.name}, with losses")
                w.add_metadata(x.name, meta)
        indexed = [c.messages_indexed for c in rep.lost_chunks]
        w.add_metadata(
            "recovered",
            {
                "from": src.name,
                "messages": str(rep.messages),
                "finished": json.dumps(rep.finished),
                "bytes_unread": str(rep.bytes_unread),
                "chunks_lost": str(len(rep.lost_chunks)),
                # what the lost chunks' indexes count ("": a chunk without one read)
                "messages_lost": str(sum(indexed)) if indexed and None not in indexed else "",  # type: ignore[arg-type]
                "lost": json.dumps(describe_loss(rep)),
            },
        )
        w.finish()
    except BaseException:
        w.abandon()
        raise
    return RecoverResult(
        dest, scan.report, comp.total_missing(), w.attachments, w.metadata - 1, had_completeness
    )


def _payload_seq(data: bytes) -> int | None:
    """The seq of a recovered payload, None if it has none (hil.messages.payload_seq)."""
    import msgspec

    from hil.messages import payload_seq

    try:
        return payload_seq(data)
    except (msgspec.DecodeError, msgspec.ValidationError):  # a recovered payload may be anything
        return None


# -- filter ----------------------------------------------------------------------------------------


@dataclass
class Selection:
    """Which messages a tool takes: seconds after the first message (as ``hil replay``), and
    topic regular expressions (``--topics`` any of, ``--exclude-topics`` none of, as mcap filter)."""

    start_s: float | None = None
    end_s: float | None = None
    topics: list[str] = field(default_factory=list)
    exclude_topics: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        for name, v in (("--start", self.start_s), ("--end", self.end_s)):
            if v is not None and not (v == v and abs(v) < 1e9):
                raise RecordingError(f"{name} {v}: not a number of seconds")
            if v is not None and v < 0:  # as hil replay: the first message is 0, nothing is before it
                raise RecordingError(f"{name} {v:g}: must be >= 0 s (seconds after the first message)")
        if self.start_s is not None and self.end_s is not None and self.end_s < self.start_s:
            raise RecordingError(f"--end {self.end_s:g} is before --start {self.start_s:g}")
        try:
            self._inc = [re.compile(t) for t in self.topics]
            self._exc = [re.compile(t) for t in self.exclude_topics]
        except re.error as err:
            raise RecordingError(f"topic pattern {err.pattern!r}: {err}") from err
        self._cache: dict[str, bool] = {}
        self.t0_ns: int | None = None

    def topic_ok(self, topic: str) -> bool:
        ok = self._cache.get(topic)
        if ok is None:
            ok = (not self._inc or any(p.search(topic) for p in self._inc)) and not any(
                p.search(topic) for p in self._exc
            )
            self._cache[topic] = ok
        return ok

    def time_ok(self, log_ns: int) -> bool:
        if self.t0_ns is None:
            self.t0_ns = log_ns
        rel = (log_ns - self.t0_ns) / 1e9
        return (self.start_s is None or rel >= self.start_s) and (self.end_s is None or rel < self.end_s)

    def describe(self) -> dict[str, str]:
        return {
            "start_s": json.dumps(self.start_s),
            "end_s": json.dumps(self.end_s),
            "topics": json.dumps(self.topics),
            "exclude_topics": json.dumps(self.exclude_topics),
        }


@dataclass
class WriteResult:
    out: Path
    messages: int
    attachments: int
    metadata: int
    notes: list[str] = field(default_factory=list)


def filter_recording(src: str | Path, out: str | Path, sel: Selection) -> WriteResult:
    """Copy the selected messages into a new indexed file, with every attachment and metadata
    record (``filter`` metadata says what was selected): each piece is a recording of its own."""
    src, dest = Path(src), Path(out)
    _check_output(dest, [src])
    scan = Scan(src)
    w = OutputWriter(dest, f"hil {__version__} filter")
    extras: list[Attachment | Metadata] = []
    try:
        for t in iter_tagged(scan, extras):
            if sel.time_ok(t.message.log_time) and sel.topic_ok(t.channel.topic):
                w.message(w.channel(t.channel, t.schema), t.message)
        _copy_extras(w, extras)
        w.add_metadata("filter", {"from": src.name, **sel.describe()})
        w.finish()
    except BaseException:
        w.abandon()
        raise
    notes = [f"note: {ln}" for ln in describe_loss(scan.report)]
    r = scan.report
    if not w.messages and r.messages and r.first_ns is not None and r.last_ns is not None:
        notes.append(
            f"note: none of the {r.messages} messages was selected: they span "
            f"{(r.last_ns - r.first_ns) * 1e-9:.3f} s from the first (--start and --end count from it; "
            f"--topics and --exclude-topics search the topic names, `hil info` lists them)"
        )
    parts = split_parts(src)
    if parts:
        notes.append(
            f"note: {src.name} is the first of {1 + len(parts)} files of a split recording, and hil "
            f"filter reads the one file: `hil merge {src.name} -o whole.mcap` joins them"
        )
    return WriteResult(dest, w.messages, w.attachments, w.metadata, notes)


def _copy_extras(w: OutputWriter, extras: Iterable[Attachment | Metadata]) -> None:
    for x in extras:
        if isinstance(x, Attachment):
            w.attachment(x)
        else:
            w.add_metadata(x.name, dict(x.metadata))


# -- merge -----------------------------------------------------------------------------------------

_PER_PIECE = frozenset({"part", "filter", "recovered"})  # metadata that describes one input only


def merge_recordings(srcs: list[Path], out: str | Path, *, parts: bool | None = None) -> WriteResult:
    """One indexed file from several: the parts of a split session, or pieces ``hil filter`` cut.

    The parts of one split session (``parts``; None: when the inputs are named as the recorder
    names parts, ``s.mcap s_0001.mcap ...``) are joined end to end: the recorder rotates between
    two messages, so that is the session's own order. Other inputs are merged by log time, each
    in its own file order, ties in input order: pieces cut by time come out end to end, exactly
    as they were (``filter`` then ``merge`` gives the original messages), and pieces cut by topic
    interleave again. Attachments are
    kept once per name and content; metadata once per name, except ``completeness``, of which
    the last is kept (a split session's last part covers the whole session) and the per-piece
    ``part``/``filter``/``recovered`` records, which are dropped; the kept ``completeness``
    loses its ``part``/``parts``, as the merged file is no part. An input given twice, or
    inputs of different runs (``hil`` metadata: ``RUN_IDENTITY``), are refused.
    """
    dest = Path(out)
    if len(srcs) < 1:
        raise RecordingError("hil merge: give at least one input")
    _check_output(dest, srcs)
    _check_one_session(srcs)
    scans = [Scan(p) for p in srcs]  # every input checked before anything is written
    extras: list[list[Attachment | Metadata]] = [[] for _ in scans]
    streams = [
        ((t.message.log_time, k, n, t) for n, t in enumerate(iter_tagged(s, extras[k])))
        for k, s in enumerate(scans)
    ]
    if parts is None:
        parts = all(p.name == split_part_path(srcs[0], k).name for k, p in enumerate(srcs))
    ordered = itertools.chain(*streams) if parts else heapq.merge(*streams, key=lambda x: (x[0], x[1], x[2]))
    w = OutputWriter(dest, f"hil {__version__} merge")
    try:
        for _log, _k, _n, t in ordered:
            w.message(w.channel(t.channel, t.schema), t.message)
        _merge_extras(w, extras)
        w.add_metadata("merge", {"from": json.dumps([p.name for p in srcs])})
        w.finish()
    except BaseException:
        w.abandon()
        raise
    notes = [f"note: {s.path.name}: {ln}" for s in scans for ln in describe_loss(s.report)]
    return WriteResult(dest, w.messages, w.attachments, w.metadata, notes)


def _check_one_session(srcs: list[Path]) -> None:
    """Refused before anything is written: an input given twice (every message would be there
    twice), or inputs of different runs (another scenario, seed or start: ``hil info`` would
    take the mix for one run, with thousands of duplicates). Inputs that name no run at all
    are merged as given."""
    for i, a in enumerate(srcs):
        for b in srcs[:i]:
            if _same_file(a, b):
                raise RecordingError(
                    f"merge: {a} is given twice (as {b}): its messages would all be there twice; "
                    "give each input once"
                )
    runs = [(p, run_identity(p)) for p in srcs]
    if all(run is None for _p, run in runs):
        return
    p0, run0 = runs[0]
    for p, run in runs[1:]:
        if run == run0:
            continue
        if run is None or run0 is None:
            which, other = (p, p0) if run is None else (p0, p)
            raise RecordingError(
                f"merge: {which} names no run (no hil metadata) and {other} does: they are not "
                "pieces of one session; nothing written"
            )

        def show(v: str | None, k: str) -> str:
            return "?" if v is None else v[:12] if k == "scenario_sha256" else v

        diff = ", ".join(
            f"{k} {show(run.get(k), k)} (not {show(run0.get(k), k)})"
            for k in RUN_IDENTITY
            if run.get(k) != run0.get(k)
        )
        raise RecordingError(
            f"merge: {p} is another run than {p0}: {diff}; merge joins the parts or pieces of one "
            "session (`hil info` shows each one's run); nothing written"
        )


def _merge_extras(w: OutputWriter, extras: list[list[Attachment | Metadata]]) -> None:
    seen_att: set[tuple[str, bytes]] = set()
    meta: dict[str, dict[str, str]] = {}
    for piece in extras:
        for x in piece:
            if isinstance(x, Attachment):
                if (x.name, x.data) not in seen_att:
                    seen_att.add((x.name, x.data))
                    w.attachment(x)
            elif x.name not in _PER_PIECE and (x.name not in meta or x.name == "completeness"):
                meta[x.name] = dict(x.metadata)
    comp = meta.get("completeness")
    if comp is not None:  # the merged file is whole: its completeness is no part's
        meta["completeness"] = {k: v for k, v in comp.items() if k not in ("part", "parts")}
    for name, data in meta.items():
        w.add_metadata(name, data)


# -- cat -------------------------------------------------------------------------------------------


def cat(src: str | Path, sel: Selection, out: TextIO = sys.stdout, notes: list[str] | None = None) -> int:
    """Messages as JSON lines: topic, schema, times, sequence and the message itself
    (``message``: the decoded JSON; a payload that is not JSON, a raw channel's, goes as
    ``data_hex``). Returns the number of lines written; ``notes`` gets what could not be read
    (a cut or damaged file: its lines alone do not show what is missing)."""
    n = 0
    scan = Scan(src)
    for t in iter_tagged(scan):
        m = t.message
        if not (sel.time_ok(m.log_time) and sel.topic_ok(t.channel.topic)):
            continue
        head = {
            "topic": t.channel.topic,
            "schema": t.schema.name if t.schema else "",
            "log_time_ns": m.log_time,
            "publish_time_ns": m.publish_time,
            "sequence": m.sequence,
        }
        line = json.dumps(head)[:-1]
        if t.channel.message_encoding == "json" and _is_json(m.data):
            line += ', "message": ' + m.data.decode() + "}"
        else:
            line += ', "data_hex": "' + m.data.hex() + '"}'
        out.write(line + "\n")
        n += 1
    if notes is not None:
        notes += describe_loss(scan.report)
    return n


def _is_json(data: bytes) -> bool:
    try:
        json.loads(data)
    except ValueError:
        return False
    return b"\n" not in data


# -- attachments -----------------------------------------------------------------------------------


@dataclass
class AttachmentInfo:
    name: str
    media_type: str
    size: int
    log_time_ns: int


def list_attachments(src: str | Path, notes: list[str] | None = None) -> list[AttachmentInfo]:
    """The file's attachments; ``notes`` gets what could not be read (a cut file's listing is short)."""
    return [
        AttachmentInfo(a.name, a.media_type, len(a.data), a.log_time) for a in _attachments(Path(src), notes)
    ]


def _attachments(src: Path, notes: list[str] | None = None) -> Iterator[Attachment]:
    seen: set[str] = set()
    scan = Scan(src, messages=False)
    for rec in scan:
        if isinstance(rec, Attachment) and rec.name not in seen:
            seen.add(rec.name)  # a split part repeats them; a recording holds one of each
            yield rec
    if notes is not None:
        notes += describe_loss(scan.report)


def extract_attachments(
    src: str | Path, out_dir: str | Path, names: list[str] | None = None, notes: list[str] | None = None
) -> list[Path]:
    """Write attachments under ``out_dir`` by their names (``can/imu.dbc`` -> ``out_dir/can/imu.dbc``);
    ``names``: only those (each must exist). A name that would leave ``out_dir`` is refused.
    ``notes`` gets what could not be read."""
    out_root = Path(out_dir).resolve()
    lost: list[str] = []
    found = list(_attachments(Path(src), lost))
    if notes is not None:
        notes += lost
    if names:
        have = {a.name for a in found}
        missing = [n for n in names if n not in have]
        if missing:
            cut = f" (the file is not whole: {lost[-1]})" if lost else ""
            raise RecordingError(
                f"{src}: no attachment named {', '.join(map(repr, missing))}; it has {sorted(have)}{cut}"
            )
        found = [a for a in found if a.name in names]
    written: list[Path] = []
    for a in found:
        target = (out_root / a.name).resolve()
        if not target.is_relative_to(out_root):
            raise RecordingError(f"{src}: attachment name {a.name!r} points outside {out_root}; not written")
        try:
            target.parent.mkdir(parents=True, exist_ok=True)
            target.write_bytes(a.data)
        except OSError as err:
            raise RecordingError(f"cannot write {target}: {err.strerror}") from err
        written.append(target)
    return written

"""Everything the report needs from a recording, as numpy arrays, in one pass over the file.

Narrow ``msgspec`` structs decode only the fields the report uses, one call per chunk and
channel (a payload that does not decode is counted and skipped, never raised). Times are integer
ns on the recording's own timelines: ``Truth``/``CaptureTruth`` true time, the rest rig time.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import numpy as np

from hil.can.busload import frame_bits
from hil.messages import SEQ_GENERATION_SHIFT, Event, RunInfo, ServiceStatus, decode
from hil.record.info import stream_rate_hz
from hil.record.mcapio import cut_notes, is_derived, session_files, session_note
from hil.report.scan import Batch, Channel, ScanResult, scan

F64 = np.ndarray  # float64 arrays; shapes in the field comments


class _Truth(msgspec.Struct):
    stamp_ns: int
    pos_ned_m: list[float]
    vel_ned_mps: list[float]
    q_nb: list[float]


class _Nav(msgspec.Struct):
    stamp_ns: int
    estimator: str
    pos_ned_m: list[float]
    vel_ned_mps: list[float]
    q_nb: list[float]


class _Fix(msgspec.Struct):
    stamp_ns: int
    pos_ned_m: list[float]


class _Stamp(msgspec.Struct):
    seq: int
    stamp_ns: int


class _Capture(msgspec.Struct):
    seq: int
    sensor: str
    true_stamp_ns: int


class _Can(msgspec.Struct):
    stamp_ns: int
    data_hex: str
    is_fd: bool = False
    is_extended_id: bool = False
    bitrate_switch: bool = False


S = TypeVar("S")


@dataclass
class Series:
    """Time series of one source: ``t_ns`` (n,), ``pos``/``vel`` (n, 3) NED, ``q`` (n, 4) [w x y z]."""

    t_ns: np.ndarray
    pos: np.ndarray
    vel: np.ndarray
    q: np.ndarray

    @property
    def n(self) -> int:
        return int(self.t_ns.shape[0])


@dataclass
class TopicStats:
    topic: str
    schema: str
    count: int
    first_ns: int
    last_ns: int
    missing: int
    duplicates: int
    undecodable: int = 0
    restarts: int = 0  # the publisher counted again in a new restart generation
    first_pub_ns: int = 0  # publish times: start epoch + time of validity (``stream_rate_hz``)
    last_pub_ns: int = 0

    @property
    def rate_hz(self) -> float:
        return stream_rate_hz(self.count, self.first_ns, self.last_ns, self.first_pub_ns, self.last_pub_ns)

    @property
    def loss_pct(self) -> float:
        total = self.count - self.duplicates + self.missing
        return 100.0 * self.missing / total if total > 0 else 0.0


@dataclass
class ReportData:
    path: Path
    metadata: dict[str, dict[str, str]] = field(default_factory=dict)
    attachments: dict[str, bytes] = field(default_factory=dict)
    truncated: bool = False
    truncation_reason: str = ""
    messages: int = 0
    run: RunInfo | None = None
    truth: Series | None = None
    nav: dict[str, Series] = field(default_factory=dict)
    gnss_t_ns: np.ndarray = field(default_factory=lambda: np.zeros(0, np.int64))
    gnss_pos: np.ndarray = field(default_factory=lambda: np.zeros((0, 3)))
    # timesync: per sensor (synced stamp - true capture time), matched by seq
    sync_t_ns: dict[str, np.ndarray] = field(default_factory=dict)
    sync_err_ns: dict[str, np.ndarray] = field(default_factory=dict)
    sync_unmatched: dict[str, int] = field(default_factory=dict)
    # CAN: per channel, busy seconds on the wire per whole second of rig time
    can_load: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)  # (t_s, load 0..1)
    can_frames: dict[str, int] = field(default_factory=dict)
    events: list[Event] = field(default_factory=list)
    status: dict[str, ServiceStatus] = field(default_factory=dict)  # last per service
    # service -> (t_s, load 0..1) from its bus_load_permille counter
    status_load: dict[str, tuple[np.ndarray, np.ndarray]] = field(default_factory=dict)
    topics: list[TopicStats] = field(default_factory=list)
    notes: list[str] = field(default_factory=list)

    def span_ns(self) -> tuple[int, int]:
        firsts = [t.first_ns for t in self.topics if t.count]
        lasts = [t.last_ns for t in self.topics if t.count]
        return (min(firsts, default=0), max(lasts, default=0))


def _decode_batch(
    dec: msgspec.json.Decoder[list[S]], one: msgspec.json.Decoder[S], b: Batch
) -> tuple[list[S], list[int], int]:
    """Decode a batch in one call; on a bad payload, one by one. Returns rows, kept indices, bad count."""
    try:
        rows = dec.decode(b"[" + b",".join(b.payloads) + b"]")
        return rows, list(range(len(rows))), 0
    except (msgspec.DecodeError, msgspec.ValidationError):
        rows, keep, bad = [], [], 0
        for i, p in enumerate(b.payloads):
            try:
                rows.append(one.decode(p))
                keep.append(i)
            except (msgspec.DecodeError, msgspec.ValidationError):
                bad += 1
        return rows, keep, bad


class _Collector:
    def __init__(self) -> None:
        self.truth: list[list[_Truth]] = []
        self.nav: dict[str, list[list[_Nav]]] = {}
        self.gnss: list[list[_Fix]] = []
        self.synced: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        self.capture: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}
        self.can: dict[str, list[tuple[np.ndarray, np.ndarray]]] = {}  # channel -> (t_ns, busy_s)
        self.can_bits_cache: dict[tuple[int, bool, bool, bool], float] = {}
        self.seqs: dict[str, list[np.ndarray]] = {}
        self.times: dict[str, list[int]] = {}  # topic -> [first, last] log time
        self.schema: dict[str, str] = {}
        self.undecodable: dict[str, int] = {}
        self.small: list[tuple[str, str, int, bytes]] = []  # (topic, schema, log_ns, payload)
        self.decs: dict[type[Any], tuple[Any, Any]] = {}

    def _dec(self, cls: type[S], b: Batch) -> tuple[list[S], list[int]]:
        pair = self.decs.get(cls)
        if pair is None:
            pair = self.decs[cls] = (msgspec.json.Decoder(list[cls]), msgspec.json.Decoder(cls))  # type: ignore[valid-type]
        rows, keep, bad = _decode_batch(pair[0], pair[1], b)
        if bad:
            self.undecodable[b.channel.topic] = self.undecodable.get(b.channel.topic, 0) + bad
        return rows, keep

    def busy_s(self, n: int, fd: bool, brs: bool, ext: bool) -> float:
        key = (n, fd, brs, ext)
        v = self.can_bits_cache.get(key)
        if v is None:
            v = self.can_bits_cache[key] = frame_bits(n, fd=fd, brs=brs, extended=ext).seconds()
        return v

    def on_batch(self, b: Batch) -> None:
        topic, schema = b.channel.topic, b.channel.schema
        if is_derived(topic):
            return  # Foxglove's view of the messages (hil.wellknown), not rig traffic
        self.schema.setdefault(topic, schema)
        if not b.sequences.size:
            return
        if schema in _COUNTER_SCHEMAS:
            # numbered by the publisher's own counter: the restart generation lives above the 32
            # bits of MCAP's sequence field, so the seq comes from the payload
            self.seqs.setdefault(topic, []).append(_payload_seqs(b))
        else:
            self.seqs.setdefault(topic, []).append(b.sequences)
        lt = self.times.setdefault(topic, [int(b.log_times[0]), int(b.log_times[0]), 2**63, -1])
        lt[0] = min(lt[0], int(b.log_times.min()))
        lt[1] = max(lt[1], int(b.log_times.max()))
        if b.publish_times is not None:
            lt[2] = min(lt[2], int(b.publish_times.min()))
            lt[3] = max(lt[3], int(b.publish_times.max()))
        parts = topic.split("/")
        kind = parts[2] if len(parts) > 2 and parts[0] == "hil" else ""
        name = parts[3] if len(parts) > 3 else ""
        if schema == "hil.Truth":
            self.truth.append(self._dec(_Truth, b)[0])
        elif schema == "hil.NavSolution":
            rows, _ = self._dec(_Nav, b)
            for r in rows:
                self.nav.setdefault(r.estimator, [[]])[0].append(r)
        elif schema == "hil.GnssFix" and kind == "sensor":
            self.gnss.append(self._dec(_Fix, b)[0])
        elif schema in ("hil.GnssFix", "hil.ImuSample") and kind == "synced":
            rows, _keep = self._dec(_Stamp, b)
            seq = np.array([r.seq for r in rows], np.int64)
            st = np.array([r.stamp_ns for r in rows], np.int64)
            self.synced.setdefault(name, []).append((seq, st))
        elif schema == "hil.CaptureTruth":
            rows, _ = self._dec(_Capture, b)
            for sensor in {r.sensor for r in rows}:
                sel = [r for r in rows if r.sensor == sensor]
                self.capture.setdefault(sensor, []).append(
                    (
                        np.array([r.seq for r in sel], np.int64),
                        np.array([r.true_stamp_ns for r in sel], np.int64),
                    )
                )
        elif schema == "hil.CanFrame":
            rows, _ = self._dec(_Can, b)
            t = np.array([r.stamp_ns for r in rows], np.int64)
            busy = np.array(
                [self.busy_s(len(r.data_hex) // 2, r.is_fd, r.bitrate_switch, r.is_extended_id) for r in rows]
            )
            self.can.setdefault(name or topic, []).append((t, busy))
        elif schema in ("hil.Event", "hil.ServiceStatus", "hil.RunInfo"):
            self.small.extend(
                (topic, schema, int(lt_), p) for lt_, p in zip(b.log_times, b.payloads, strict=True)
            )


# Types some publisher numbers with its own counter (hil.bus.pubsub.Publisher.next_seq), whose
# seqs carry a restart generation (hil.messages.SEQ_GENERATION_SHIFT).
_COUNTER_SCHEMAS = {
    "hil.CanFrame",
    "hil.Event",
    "hil.ServiceStatus",
    "hil.RunInfo",
    "hil.ClockModel",
    "hil.FusionJournal",
    "hil.TimeTag",
}
_WANTED_SCHEMAS = {
    "hil.Truth",
    "hil.NavSolution",
    "hil.CaptureTruth",
    *_COUNTER_SCHEMAS,
}


class _Seq(msgspec.Struct):
    seq: int


_SEQS = msgspec.json.Decoder(list[_Seq])
_SEQ = msgspec.json.Decoder(_Seq)


def _payload_seqs(b: Batch) -> np.ndarray:
    """The messages' own seqs (one decode call per batch); MCAP's field where a payload has none.
    Undecodable payloads are counted where the batch is decoded for its content, not here."""
    try:
        return np.array([r.seq for r in _SEQS.decode(b"[" + b",".join(b.payloads) + b"]")], np.int64)
    except (msgspec.DecodeError, msgspec.ValidationError):
        out = np.asarray(b.sequences, np.int64).copy()
        for i, payload in enumerate(b.payloads):
            with contextlib.suppress(msgspec.DecodeError, msgspec.ValidationError):
                out[i] = _SEQ.decode(payload).seq
        return out


def seq_accounting(seqs: np.ndarray) -> tuple[int, int, int]:
    """(missing, duplicates, restarts) of one publisher's seqs, each restart generation a stream
    of its own (as ``hil.record.completeness`` counts them while recording)."""
    if not seqs.size:
        return 0, 0, 0
    gens = seqs >> SEQ_GENERATION_SHIFT
    missing = 0
    uniq_total = 0
    kinds = np.unique(gens)
    for g in kinds:
        uniq = np.unique(seqs[gens == g])
        uniq_total += uniq.size
        missing += int(uniq[-1] - uniq[0] + 1 - uniq.size)
    return missing, int(seqs.size - uniq_total), int(kinds.size - 1)


def _wanted(ch: Channel) -> bool:
    """Payloads the report decodes; the rest only count (sequence and log time from the header)."""
    if ch.schema in _WANTED_SCHEMAS:
        return True
    parts = ch.topic.split("/")
    kind = parts[2] if len(parts) > 2 else ""
    return kind == "synced" or (kind == "sensor" and ch.schema == "hil.GnssFix")


def _series_truth(rows: list[_Truth]) -> Series:
    return Series(
        np.array([r.stamp_ns for r in rows], np.int64),
        np.array([r.pos_ned_m for r in rows], float).reshape(-1, 3),
        np.array([r.vel_ned_mps for r in rows], float).reshape(-1, 3),
        np.array([r.q_nb for r in rows], float).reshape(-1, 4),
    )


def _sorted(s: Series) -> Series:
    o = np.argsort(s.t_ns, kind="stable")
    return Series(s.t_ns[o], s.pos[o], s.vel[o], s.q[o])


def _scan_session(
    path: Path, on_batch: Callable[[Batch], None], on_progress: Callable[[int, int], None] | None
) -> tuple[ScanResult, list[Path]]:
    """``scan`` of the recording and the parts it was split into (``session_files``), end to end:
    the collector keys by topic, so the parts read as one session. The later parts' metadata
    replace the earlier ones' (the last part's ``completeness`` covers the session); the counts
    add up; progress runs over all the files' bytes. Also returns the files read."""
    files = session_files(path)
    sizes = [f.stat().st_size if f.exists() else 0 for f in files]
    total = sum(sizes)
    out = ScanResult(bytes_total=total)
    before = 0
    for f, size in zip(files, sizes, strict=True):

        def progress(done: int, _total: int, before: int = before) -> None:
            if on_progress is not None:
                on_progress(before + done, total)

        res = scan(f, on_batch, progress, want=_wanted)
        out.metadata.update(res.metadata)
        out.attachments.update(res.attachments)
        out.messages += res.messages
        if res.truncated and f is not files[-1]:  # a killed recorder's, continued by the next
            out.cut.append((f.name, res.truncation_reason))
        elif res.truncated:
            out.truncated, out.truncation_reason = True, res.truncation_reason
        before += size
    return out, files


def load(path: str | Path, on_progress: Callable[[int, int], None] | None = None) -> ReportData:
    """Read ``path`` into a ``ReportData``; raises ``RecordingError`` only when nothing is readable."""
    col = _Collector()
    res, files = _scan_session(Path(path), col.on_batch, on_progress)
    d = ReportData(
        Path(path), res.metadata, res.attachments, res.truncated, res.truncation_reason, res.messages
    )
    many = session_note(files, "read")
    d.notes += ([many] if many else []) + cut_notes(res.cut)
    if res.truncated:
        d.notes.append(f"truncated recording: read up to its last complete chunk ({res.truncation_reason})")
    truth_rows = [r for chunk in col.truth for r in chunk]
    if len(truth_rows) >= 2:
        d.truth = _sorted(_series_truth(truth_rows))
    for est, chunks in sorted(col.nav.items()):
        rows = chunks[0]
        s = _series_truth(rows)  # same fields
        if s.n:
            d.nav[est] = _sorted(s)
    fixes = [r for chunk in col.gnss for r in chunk]
    if fixes:
        d.gnss_t_ns = np.array([f.stamp_ns for f in fixes], np.int64)
        d.gnss_pos = np.array([f.pos_ned_m for f in fixes], float).reshape(-1, 3)
    for sensor, parts in col.synced.items():
        seq = np.concatenate([p[0] for p in parts])
        st = np.concatenate([p[1] for p in parts])
        cap = col.capture.get(sensor)
        if not cap:
            continue
        cseq = np.concatenate([p[0] for p in cap])
        ctrue = np.concatenate([p[1] for p in cap])
        # a seq recorded twice (duplicate delivery) matches its first copy
        _u, first = np.unique(seq, return_index=True)
        seq, st = seq[first], st[first]
        _u, cfirst = np.unique(cseq, return_index=True)
        cseq, ctrue = cseq[cfirst], ctrue[cfirst]
        _common, i, j = np.intersect1d(seq, cseq, assume_unique=True, return_indices=True)
        d.sync_t_ns[sensor] = ctrue[j]
        d.sync_err_ns[sensor] = st[i] - ctrue[j]
        d.sync_unmatched[sensor] = int(len(seq) - len(i))
    for channel, parts in col.can.items():
        t = np.concatenate([p[0] for p in parts])
        busy = np.concatenate([p[1] for p in parts])
        d.can_frames[channel] = int(t.size)
        if t.size:
            sec = (t // 1_000_000_000).astype(np.int64)
            sec -= sec.min()
            load_s = np.bincount(sec, weights=busy)
            t0 = int(t.min() // 1_000_000_000)
            # the last second is usually partial: leave it out unless it is the only one
            if load_s.size > 1:
                load_s = load_s[:-1]
            d.can_load[channel] = (np.arange(load_s.size, dtype=float) + t0, load_s)
    loads: dict[str, list[tuple[float, float]]] = {}
    for topic, schema, _log, payload in col.small:
        cls = {"hil.Event": Event, "hil.ServiceStatus": ServiceStatus, "hil.RunInfo": RunInfo}.get(schema)
        if cls is None:
            continue
        try:
            m = decode(cls, payload)  # also the previous form of a type (hil.messages.LEGACY_FORMS)
        except (msgspec.DecodeError, msgspec.ValidationError):
            col.undecodable[topic] = col.undecodable.get(topic, 0) + 1
            continue
        if isinstance(m, RunInfo):
            d.run = d.run or m
        elif isinstance(m, Event):
            d.events.append(m)
        elif isinstance(m, ServiceStatus):
            d.status[m.service] = m
            load = m.counter_map().get("bus_load_permille")
            if load is not None:
                loads.setdefault(m.service, []).append((m.stamp_ns * 1e-9, load / 1000))
    for svc, pts in loads.items():
        a = np.array(sorted(pts))
        d.status_load[svc] = (a[:, 0], a[:, 1])
    for topic in sorted(col.seqs):
        seqs = np.concatenate(col.seqs[topic])
        missing, duplicates, restarts = seq_accounting(seqs)
        first, last, first_pub, last_pub = col.times[topic]
        d.topics.append(
            TopicStats(
                topic,
                col.schema[topic],
                int(seqs.size),
                int(first),
                int(last),
                missing,
                duplicates,
                col.undecodable.get(topic, 0),
                restarts,
                first_pub if last_pub >= first_pub else first,
                last_pub if last_pub >= first_pub else last,
            )
        )
    return d


def scenario_text(d: ReportData) -> str:
    """The recorded scenario TOML: from RunInfo, else from the attachment."""
    if d.run is not None and d.run.scenario_toml:
        return d.run.scenario_toml
    for name, data in d.attachments.items():
        if name.startswith("scenario/"):
            with contextlib.suppress(UnicodeDecodeError):
                return data.decode()
    return ""

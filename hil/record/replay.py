"""``hil replay FILE``: republish a recording onto Zenoh (and its CAN frames onto a CAN bus).

What is sent: every message of the file, in file order (the recorder's receive order), with its
payload bytes untouched, on its recorded key -- or on the same key under ``--rig NAME``, so a
replay runs beside a live rig without colliding. Selection: ``--start``/``--end`` (seconds from
the first message's ``log_time``) and ``--topics``/``--exclude-topics`` (regular expressions
searched in the recorded topic, as ``mcap filter -y/-n``).

When: message ``i`` leaves at ``wall0 + (log_time_i - log_time_0) / rate``: absolute deadlines
from the recorded receive times, never accumulated sleeps, so a long replay does not drift (the
python-can #1372 / can-utils "RealCAN" lesson). ``--afap`` drops the deadlines; ``--step`` waits
for Enter before each message (canplayer ``-i``); ``--loop`` starts again at the end.

CAN: with ``--can CHANNEL`` the recorded ``hil.CanFrame`` messages go onto that CAN bus (through
``hil.can.bus.open_can_bus``) at their recorded spacing instead of onto Zenoh -- the bridge on the
other side then decodes them, exactly as from the emulator.

Lockstep (``--lockstep``): the fusion inputs (``synced/imu``, ``synced/gnss``) are gated on the
fusion's consumed-input ack (``hil.record.lockstep``), so the replayer never outruns it, and the
inputs the live fusion journaled as dropped are not sent: the fresh fusion then consumes exactly
the inputs the recorded one used, in the same order, and publishes the same solutions bit for bit.

Exceptions::

    RecordingError (ValueError)   the file cannot be read (hil.record.mcapio)
    ReplayError                   the replay cannot go on (lockstep consumer silent, bus refuses)
"""

from __future__ import annotations

import re
import sys
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, TextIO

import msgspec
import zenoh
import zenoh.ext as zext
from mcap.reader import make_reader

from hil.bus.describe import encoding_of
from hil.bus.keys import rekey
from hil.bus.pubsub import declare_publisher
from hil.fusion.core import parse_journal_id
from hil.messages import TYPES_BY_NAME, CanFrame, FusionJournal, SerialChunk, decode
from hil.record.lockstep import ack_key, decode_ack
from hil.record.mcapio import (
    Record,
    RecordingError,
    check_hil_recording,
    cut_notes,
    iter_records,
    session_files,
    session_note,
)
from hil.wire.line import BITS_PER_BYTE

FUSION_INPUT = re.compile(r"^hil/[^/]+/synced/(imu|gnss)$")
SPIN_S = 0.0005  # the last half millisecond before a deadline is spun, not slept (CAN spacing)


class ReplayError(RuntimeError):
    """The replay cannot continue; the message says what was waited for and how long."""


@dataclass
class ReplayOptions:
    rate: float = 1.0  # replay speed: 2.0 = twice as fast as recorded
    afap: bool = False  # as fast as possible (no deadlines)
    start_s: float | None = None  # seconds after the first message's log_time
    end_s: float | None = None
    topics: list[str] = field(default_factory=list)  # include regexes (any match); empty = all
    exclude_topics: list[str] = field(default_factory=list)
    loop: bool = False
    step: bool = False
    rig: str | None = None  # republish under this rig instead of the recorded one
    can_channel: str | None = None
    can_interface: str | None = None
    lockstep: bool = False
    lockstep_window: int = 0  # fusion inputs allowed in flight beyond the last ack
    lockstep_timeout_s: float = 30.0
    progress: bool = False


@dataclass
class ReplayStats:
    sent: int = 0
    sent_can: int = 0
    sent_line_bytes: int = 0
    skipped_dropped: int = 0  # fusion inputs not sent because the live fusion had dropped them
    can_errors: int = 0
    passes: int = 0
    wall_s: float = 0.0
    span_s: float = 0.0  # recorded time the last pass sent: its first message to its last
    truncated: str = ""
    session: str = ""  # ``session_note`` of the session's files, replayed end to end ("" one)
    cut: list[tuple[str, str]] = field(default_factory=list)  # files cut short that a later one continues

    def summary(self) -> str:
        rate = self.sent / self.wall_s if self.wall_s > 0 else 0.0
        parts = [
            f"replay: {self.sent} messages ({self.sent_can} CAN frames on the bus) in {self.wall_s:.2f} s "
            f"({rate:.0f} msg/s, {self.span_s:.2f} s of recording, {self.passes} pass(es))"
        ]
        if self.sent_line_bytes:
            parts.append(f"{self.sent_line_bytes} bytes onto the receiver's line")
        if self.skipped_dropped:
            parts.append(f"{self.skipped_dropped} inputs the live fusion had dropped were not sent")
        if self.can_errors:
            parts.append(f"{self.can_errors} CAN frames refused by the bus")
        if self.truncated:
            parts.append(f"file truncated, replayed up to its last complete chunk ({self.truncated})")
        if self.session:
            parts.append(self.session)
        parts += cut_notes(self.cut)
        return "; ".join(parts)


def check_readable(path: str | Path) -> None:
    """Raise ``RecordingError`` unless ``path`` is a hil recording with at least one message
    (``hil.record.mcapio.check_hil_recording``: not MCAP, cut in its header, or another tool's)."""
    check_hil_recording(path)


def journaled_drops(path: str | Path) -> set[str]:
    """``sensor:seq[@publisher]`` of every input the live fusion journaled as not used."""
    out: set[str] = set()
    for kind, rec in session_records(path):
        if kind == "message" and rec.topic.endswith("/fusion/journal") and not rec.foreign:
            for d in decode(FusionJournal, rec.payload).dropped:
                _why, name, source = parse_journal_id(d)
                out.add(f"{name}@{source}" if source else name)
    return out


class _Seq(msgspec.Struct):
    seq: int


def _input_id(rec: Record) -> str:
    """The input's name as the live fusion journaled it (its full seq: MCAP keeps 32 bits)."""
    try:
        seq = msgspec.json.decode(rec.payload, type=_Seq).seq
    except (msgspec.DecodeError, msgspec.ValidationError):
        seq = rec.sequence
    name = f"{rec.topic.rsplit('/', 1)[1]}:{seq}"
    return f"{name}@{rec.publisher}" if rec.publisher else name


class Selector:
    """Topic regexes and a time window over recorded ``log_time``."""

    def __init__(self, opts: ReplayOptions) -> None:
        try:
            self.include = [re.compile(p) for p in opts.topics]
            self.exclude = [re.compile(p) for p in opts.exclude_topics]
        except re.error as err:
            raise ValueError(f"--topics/--exclude-topics: bad pattern {err.pattern!r}: {err}") from err
        self.start_ns = None if opts.start_s is None else int(opts.start_s * 1e9)
        self.end_ns = None if opts.end_s is None else int(opts.end_s * 1e9)

    def topic_ok(self, topic: str) -> bool:
        if self.include and not any(p.search(topic) for p in self.include):
            return False
        return not any(p.search(topic) for p in self.exclude)

    def time_ok(self, rel_ns: int) -> bool | None:
        """True: send; False: not yet; None: past the end (stop the pass). The window is
        half-open, [start, end), as ``hil filter``'s: back-to-back windows send a message once."""
        if self.end_ns is not None and rel_ns >= self.end_ns:
            return None
        return self.start_ns is None or rel_ns >= self.start_ns


class Pacer:
    """Absolute deadlines from recorded times: ``wall0 + (t - t0) / rate``."""

    def __init__(self, rate: float, afap: bool, stop: threading.Event) -> None:
        if not rate > 0:
            raise ValueError(f"rate must be > 0, got {rate}")
        self.rate = rate
        self.afap = afap
        self.stop = stop
        self.t0_ns: int | None = None
        self.wall0 = 0.0

    def reset(self) -> None:
        self.t0_ns = None

    def wait(self, log_ns: int) -> None:
        if self.afap:
            return
        if self.t0_ns is None:
            self.t0_ns = log_ns
            self.wall0 = time.perf_counter()
            return
        deadline = self.wall0 + (log_ns - self.t0_ns) * 1e-9 / self.rate
        while True:
            remaining = deadline - time.perf_counter()
            if remaining <= 0 or self.stop.is_set():
                return
            if remaining > SPIN_S:
                time.sleep(min(remaining - SPIN_S, 0.2))


class LockstepGate:
    """Waits for the fusion's consumed-input ack before sending the next fusion input."""

    def __init__(self, session: zenoh.Session, rig: str, window: int, timeout_s: float) -> None:
        self.rig = rig
        self.window = max(0, window)
        self.timeout_s = timeout_s
        self.acked = -1  # -1: nobody has acknowledged anything yet
        self._cv = threading.Condition()
        self._sub = session.declare_subscriber(ack_key(rig), self._on_ack)

    def _on_ack(self, sample: zenoh.Sample) -> None:
        n = decode_ack(sample.payload.to_bytes())
        if n is None:
            return
        with self._cv:
            if n > self.acked:
                self.acked = n
                self._cv.notify_all()

    def wait_for(self, n: int, stop: threading.Event) -> None:
        """Block until ``acked >= n`` (progress resets the timeout); raise if the fusion is silent."""
        with self._cv:
            last, t_last = self.acked, time.monotonic()
            while self.acked < n and not stop.is_set():
                self._cv.wait(0.1)
                if self.acked != last:
                    last, t_last = self.acked, time.monotonic()
                elif time.monotonic() - t_last > self.timeout_s:
                    who = "no fusion answered" if self.acked < 0 else f"the fusion acknowledged {self.acked}"
                    raise ReplayError(
                        f"lockstep: waited {self.timeout_s:g} s for the fusion on rig {self.rig!r} to "
                        f"consume input {n}; {who} (is a fusion running on that rig, and was "
                        f"hil/<rig>/run replayed?)"
                    )

    def before_input(self, sent: int, stop: threading.Event) -> None:
        self.wait_for(max(0, sent - self.window), stop)

    def close(self) -> None:
        self._sub.undeclare()


class Progress:
    """A one-line progress bar on a terminal (stderr), redrawn at most 5 times a second."""

    def __init__(self, out: TextIO, total_ns: int | None, enabled: bool) -> None:
        self.out = out
        self.total_ns = total_ns
        self.enabled = enabled
        self._t = 0.0

    def show(self, rel_ns: int, sent: int, force: bool = False) -> None:
        now = time.monotonic()
        if not self.enabled or (not force and now - self._t < 0.2):
            return
        self._t = now
        if self.total_ns:
            frac = min(max(rel_ns / self.total_ns, 0.0), 1.0)
            bar = "#" * int(frac * 30)
            self.out.write(
                f"\rreplay [{bar:<30}] {frac * 100:5.1f}% {rel_ns * 1e-9:8.2f}/{self.total_ns * 1e-9:.2f} s "
                f"{sent} msgs"
            )
        else:
            self.out.write(f"\rreplay {rel_ns * 1e-9:8.2f} s {sent} msgs")
        self.out.flush()

    def done(self) -> None:
        if self.enabled:
            self.out.write("\n")
            self.out.flush()


def recorded_span_ns(path: str | Path) -> int | None:
    """log_time span from the summaries of the file and its split parts (None when a crashed
    recorder left one without a summary)."""
    first, last = None, None
    for f in session_files(path):
        try:
            with open(f, "rb") as fh:
                summary = make_reader(fh).get_summary()
        except Exception:  # a truncated file has no summary: progress shows time only
            return None
        if summary is None or summary.statistics is None:
            return None
        st = summary.statistics
        if st.message_count:
            first = st.message_start_time if first is None else min(first, st.message_start_time)
            last = st.message_end_time if last is None else max(last, st.message_end_time)
    return None if first is None or last is None else int(last - first)


def session_records(path: str | Path) -> Iterator[tuple[str, Any]]:
    """``iter_records`` of the recording and of its split parts, end to end: one session. A file
    cut short before the last (a killed recorder's, continued by its restarted one) is a
    ``("cut", (name, why))`` there, not ``truncated``: the session goes on."""
    files = session_files(path)
    for k, f in enumerate(files):
        for kind, rec in iter_records(f):
            if kind == "truncated" and k < len(files) - 1:
                yield "cut", (f.name, str(rec))
            else:
                yield kind, rec


def check_selected(path: str | Path, opts: ReplayOptions) -> None:
    """Raise ``RecordingError`` (one line) when the selection takes no message of ``path``:
    refused up front, so ``--loop`` does not reread the file for ever sending nothing. Reads
    up to the first selected message."""
    sel = Selector(opts)
    topics: set[str] = set()
    first_ns: int | None = None
    rel = n = 0
    for rec in _messages(path, ReplayStats()):
        if first_ns is None:
            first_ns = rec.log_time_ns
        rel = rec.log_time_ns - first_ns
        n += 1
        ok = sel.time_ok(rel)
        if ok and sel.topic_ok(rec.topic):
            return
        topics.add(rec.topic)
    raise RecordingError(
        f"{path}: nothing selected: its {n} messages span {rel * 1e-9:.3f} s from the first (--start and "
        f"--end count from it) on {len(topics)} topics (--topics/--exclude-topics search their names; "
        "`hil info` lists them); give a selection that takes some"
    )


def _messages(path: str | Path, stats: ReplayStats) -> Iterator[Record]:
    for kind, rec in session_records(path):
        if kind == "message":
            yield rec
        elif kind == "truncated":
            stats.truncated = str(rec)
        elif kind == "cut":
            stats.cut.append(rec)


def replay(
    path: str | Path,
    opts: ReplayOptions,
    session: zenoh.Session,
    *,
    can_bus: Any = None,
    line: Any = None,
    stop: threading.Event | None = None,
    step_input: Callable[[str], str] | None = None,
    progress_out: TextIO | None = None,
) -> ReplayStats:
    """Replay ``path`` onto ``session`` (and CAN frames onto ``can_bus``, a receiver's recorded
    serial bytes onto ``line``: an object with ``write(data, start_wall_s)``, e.g.
    ``hil.runners.serial.LineWriter``); see the module doc.

    ``step_input`` reads one line for ``--step`` (default: ``input``; EOF or "q" stops).
    """
    check_readable(path)
    stop = stop or threading.Event()
    sel = Selector(opts)
    pacer = Pacer(opts.rate, opts.afap or opts.step, stop)
    files = session_files(path)
    stats = ReplayStats(session=session_note(files, "replayed") or "")
    pubs: dict[str, zenoh.Publisher | zext.AdvancedPublisher] = {}
    dropped = journaled_drops(path) if opts.lockstep else set()
    gate: LockstepGate | None = None
    target_rig: str | None = opts.rig
    progress = Progress(progress_out or sys.stderr, recorded_span_ns(path), opts.progress)
    ask = step_input or input

    def publisher(topic: str, schema: str = "") -> zenoh.Publisher | zext.AdvancedPublisher:
        pub = pubs.get(topic)
        if pub is None:
            key = rekey(topic, opts.rig) if opts.rig and topic.startswith("hil/") else topic
            # as the rig's own publishers: reliable, blocking, with Zenoh sample-miss detection,
            # and the recorded type in the encoding (hil.bus.describe)
            cls = TYPES_BY_NAME.get(schema)
            pub = pubs[topic] = declare_publisher(session, key, encoding=encoding_of(cls) if cls else None)
        return pub

    t_start = time.monotonic()
    inputs_sent = 0  # cumulative over --loop passes: the fusion's ack is too
    rel = 0
    sent_from: int | None = None  # the pass's first and last sent message (ns after the file's first)
    sent_to = 0
    try:
        while not stop.is_set():
            stats.passes += 1
            pacer.reset()
            first_ns: int | None = None
            sent_from = None
            for rec in _messages(path, stats):
                if first_ns is None:
                    first_ns = rec.log_time_ns
                rel = rec.log_time_ns - first_ns
                ok = sel.time_ok(rel)
                if ok is None:
                    break
                if not ok or not sel.topic_ok(rec.topic):
                    continue
                is_input = FUSION_INPUT.match(rec.topic) is not None
                if is_input and opts.lockstep:
                    if _input_id(rec) in dropped:
                        stats.skipped_dropped += 1
                        continue
                    if gate is None:
                        rig = target_rig or rec.topic.split("/")[1]
                        gate = LockstepGate(session, rig, opts.lockstep_window, opts.lockstep_timeout_s)
                    gate.before_input(inputs_sent, stop)
                pacer.wait(rec.log_time_ns)
                if stop.is_set():
                    break
                if opts.step:
                    line = _ask(ask, f"[{rel * 1e-9:.6f} s] {rec.topic} seq {rec.sequence} (Enter/q) ")
                    if line is None or line.strip().lower() == "q":
                        stop.set()
                        break
                if can_bus is not None and rec.schema == "hil.CanFrame":
                    if _send_can(can_bus, decode(CanFrame, rec.payload)):
                        stats.sent_can += 1
                    else:
                        stats.can_errors += 1
                elif line is not None and rec.schema == "hil.SerialChunk":
                    data = bytes.fromhex(decode(SerialChunk, rec.payload).data_hex)
                    # as it was read, paced by the recording: its last byte readable now, the
                    # line having carried it for its bytes' time at the line's baud rate
                    baud = getattr(line, "baud", 0)
                    line.write(data, time.time() - (len(data) * BITS_PER_BYTE / baud if baud else 0.0))
                    stats.sent_line_bytes += len(data)
                else:
                    publisher(rec.topic, rec.schema).put(rec.payload)
                stats.sent += 1
                sent_to = rel
                if sent_from is None:
                    sent_from = rel
                if is_input:
                    inputs_sent += 1
                progress.show(rel, stats.sent)
            stats.span_s = 0.0 if sent_from is None else (sent_to - sent_from) * 1e-9
            if sent_from is None and opts.loop and not stop.is_set() and not stats.skipped_dropped:
                check_selected(path, opts)  # a pass that sent nothing: never loop on it
            if gate is not None and not stop.is_set():
                gate.wait_for(inputs_sent, stop)  # the consumer has everything before we go on
            if not opts.loop:
                break
    finally:
        progress.show(rel, stats.sent, force=True)
        progress.done()
        stats.wall_s = time.monotonic() - t_start
        if gate is not None:
            gate.close()
        for pub in pubs.values():
            pub.undeclare()
    return stats


def _ask(ask: Callable[[str], str], prompt: str) -> str | None:
    try:
        return ask(prompt)
    except EOFError:
        return None


def _send_can(bus: Any, frame: Any) -> bool:
    import can  # lazy: python-can costs ~0.1 s at import and only --can sends frames

    msg = can.Message(
        arbitration_id=frame.arbitration_id,
        is_extended_id=frame.is_extended_id,
        is_fd=frame.is_fd,
        bitrate_switch=frame.bitrate_switch,
        is_error_frame=frame.is_error_frame,
        data=bytes.fromhex(frame.data_hex),
    )
    try:
        bus.send(msg, timeout=1.0)
    except (can.CanError, OSError):
        return False
    return True

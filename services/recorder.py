"""recorder: subscribes ``hil/<rig>/**`` and writes the session to MCAP.

Zenoh's callback only enqueues; one writer thread validates, accounts sequence numbers, writes
and flushes a chunk at least every second. SIGTERM writes the completeness summary and the index.
A path that cannot be written is reported in status (the other services keep running).

Loss is measured twice, because each measure sees what the other cannot:

- per-publisher ``seq`` gaps (``hil.record.completeness``) see every loss between a publisher and
  the file, whatever transport the publisher used;
- Zenoh's own sample-miss detection (option ``zenoh_advanced``, default on): the subscription is
  a ``zenoh.ext`` advanced subscriber with heartbeat recovery. The rig's publishers are advanced
  publishers with miss detection and a small cache (``hil.bus.pubsub.declare_publisher``), so a
  gap in a publisher's sequence is first recovered from its cache and what cannot be recovered
  is reported by the sample-miss listener -- a lost *last* sample included, which no seq gap can
  show. Samples that carry no Zenoh sequence number (a plain publisher: not the rig's) are
  counted as ``zenoh_unsequenced``: Zenoh cannot see their misses, and through a router the
  advanced subscriber can even drop them (``hil/bus/pubsub.py`` says why); their seq still can.
  ``zenoh_advanced: false`` subscribes plainly.

Beside each message the recorder writes the Foxglove well-known types derived from it
(``hil.wellknown``: ``foxglove.LocationFix``, ``FrameTransform``, ``Log``; option
``foxglove_types``, default on), so a raw recording opens in Foxglove's Map, 3D and Log panels.

Both go into status every second (``missing``, ``zenoh_missed``) and into the file's
``completeness`` metadata at a clean stop, with ``replay_ready`` true only when both are zero.

Who published each message is kept (``hil.bus.identity``): each channel names its publisher's
Zenoh source id and whether it is one of the rig's processes (``hil up`` tells the recorder the
run's key) or not. A stranger's messages are recorded on channels marked ``origin: foreign`` and
accounted apart (``foreign`` in the summary): their sequence numbers, gaps and Zenoh misses are
never the rig's loss.

Bounded (``hil.bus.inbox``): what waits for the writer is held in lanes per key kind and
publisher, drop-oldest, ``RIG_LANE_CAP`` messages a lane of the rig's and ``FOREIGN_LANE_CAP``
a stranger's, ``MAX_QUEUED`` in all, written in arrival order. A flood from a stranger therefore
costs the stranger's oldest messages (``dropped_foreign``), not the rig's; a rig message dropped
(``dropped_rig``: the writer fell ``RIG_LANE_CAP`` messages of one key behind) is loss, and the
file is not ``replay_ready``.

A recorder restarted by ``hil up --restart`` (option ``continues``: the files its earlier lives
wrote, oldest first) carries on the same session in its own file. Before it writes, it reads
what those files hold (a killed recorder's file up to its last flushed chunk): every rig
publisher's seqs go into this part's accounting, so its ``completeness`` covers the whole
session and what the rig sent while no recorder was writing is counted as missing. Every
recorder's subscriber asks the publishers' caches for their history when it starts, so what
they still hold of that time is recovered -- always, not only when a heartbeat happens to come
before a publisher's next sample -- and a message the earlier files already hold is not written
again (``already_recorded``): the files end to end hold each message once.

Optional splitting (options ``split_mb``, ``split_s``): at a flush boundary the current file is
finished (summary, index, completeness so far) and the next part ``<stem>_0001.mcap`` opened with
the same run metadata and attachments, so every part is a self-contained recording. No message
is lost across a split: the writer thread rotates between two messages.
"""

from __future__ import annotations

import contextlib
import json
import sys
import threading
import time
from pathlib import Path
from typing import Any

import msgspec
import zenoh
import zenoh.ext as zext

from hil import __version__
from hil.bus.identity import FOREIGN, RigIdentity
from hil.bus.inbox import BoundedInbox, key_kind
from hil.bus.keys import type_for_key
from hil.bus.pubsub import MAX_PAYLOAD_BYTES, source_id
from hil.messages import RunInfo, decode, split_batch
from hil.nodes.base import OptionsError, decode_options
from hil.record.completeness import Completeness, ForeignTraffic
from hil.record.keyfilter import KeyFilter, KeyFilterError
from hil.record.mcapio import (
    TIME_SEMANTICS,
    RecordingError,
    SessionWriter,
    iter_records,
    keep_aside,
    part_metadata,
    split_part_path,
    split_parts,
    wall_clock_log_time,
)
from hil.runtime.clock import RigClock, wall_ns
from hil.runtime.options import RecorderOptions
from hil.runtime.service import Service, run_service
from hil.wellknown import WellKnown

FLUSH_PERIOD_S = 1.0
WRITE_BATCH = 1024  # messages the writer takes from the queue at once
# after a short batch: ~170 records of the 400 Hz rig's ~3,300 a second, well inside a flush
# (the log time is stamped on arrival); 5 ms woke the writer 200 times a second for ~16 records
GATHER_S = 0.05
RIG_LANE_CAP = 50_000  # messages of one key kind of the rig's waiting: 2 min of 400 Hz
FOREIGN_LANE_CAP = 2_000
MAX_QUEUED = 400_000  # all lanes together (~300 MB of the largest payloads)
MAX_FOREIGN_TRACKED = 64  # strangers' publishers with their own seq accounting; the rest pooled


class _Stamp(msgspec.Struct):
    seq: int
    stamp_ns: int


_STAMP = msgspec.json.Decoder(_Stamp)


class _RunFromMetadata:
    """The run an earlier file records, from its ``hil`` metadata and scenario attachment: for a
    file whose RunInfo messages the key filter left out (``--record-include 'nav/**'``)."""

    def __init__(self) -> None:
        self.meta: dict[str, str] | None = None
        self.toml: dict[str, str] = {}  # scenario name -> its TOML

    def take(self, kind: str, rec: Any) -> None:
        if kind == "metadata" and rec.name == "hil" and self.meta is None:
            self.meta = dict(rec.metadata)
        elif kind == "attachment" and rec.name.startswith("scenario/") and rec.name.endswith(".toml"):
            self.toml[rec.name[len("scenario/") : -len(".toml")]] = rec.data.decode("utf-8", "replace")

    def run(self) -> RunInfo | None:
        """The RunInfo the metadata describes; None when it is not a live run's (no start epoch)."""
        m = self.meta
        if m is None or "start_epoch_ns" not in m:
            return None
        try:
            v = {k: json.loads(m[k]) for k in _RUN_FIELDS}
            v["rig"], v["scenario"], v["scenario_sha256"] = m["rig"], m["scenario"], m["scenario_sha256"]
            return RunInfo(seq=0, stamp_ns=0, scenario_toml=self.toml.get(m["scenario"], ""), **v)
        except (KeyError, ValueError, TypeError):
            return None


_RUN_FIELDS = (
    "start_epoch_ns",
    "speed",
    "seed",
    "duration_s",
    "origin_lat_deg",
    "origin_lon_deg",
    "origin_alt_m",
)


class Recorder(Service):
    name = "recorder"
    # Every second, not every 10: at 1 kHz the recorder's data path churns ~3.6 MiB of C heap a
    # second (``hil.runtime.heap`` has the figures); with 10 s trims its floor still crept up.
    heap_trim_default_s = 1.0

    def __init__(self, ctx: Any) -> None:
        self.opts: RecorderOptions = decode_options(RecorderOptions, ctx.options, "recorder")
        super().__init__(ctx)
        self.path = Path(self.opts.path)
        self.identity = RigIdentity.from_env()
        self.dropped_rig = 0
        self.dropped_foreign = 0
        # (key, payload, receive wall time, publisher, origin, Zenoh encoding)
        self.queue: BoundedInbox[tuple[str, bytes, int, str, str, Any]] = BoundedInbox(
            self._lane_cap, max_total=MAX_QUEUED, on_drop=self._count_drop
        )
        self._root_len = len(self.keys.root) + 1
        self._closing = threading.Event()
        try:
            self.keyfilter = KeyFilter(ctx.rig, self.opts.include, self.opts.exclude)
        except KeyFilterError as err:
            raise OptionsError(f"recorder: {err}") from None
        self.excluded = 0
        self.raw_written = 0
        self._raw_seq: dict[str, int] = {}
        self.completeness = Completeness()
        self.foreign = ForeignTraffic(MAX_FOREIGN_TRACKED)
        self.writer: SessionWriter | None = None
        self._writer_thread = threading.Thread(target=self._write_loop, name="mcap-writer", daemon=True)
        self._start_epoch_ns: int | None = None
        self._speed = 1.0
        self._meta_written = False  # the current part holds the run's metadata
        self._run: RunInfo | None = None
        self.part = 0
        self._part_t0 = time.monotonic()
        self.split_bytes = int(self.opts.split_mb * 1e6)
        self.split_s = self.opts.split_s
        self._pending: list[tuple[str, bytes, int]] = []
        self.written = 0
        self.bytes_written = 0
        self.foxglove_written = 0  # well-known messages derived (not counted in ``written``)
        self._wellknown = WellKnown()
        self.zenoh_missed: dict[str, int] = {}  # per key (or publisher id, if its key is unknown)
        self.zenoh_unsequenced = 0
        self._source_key: dict[str, str] = {}  # Zenoh publisher id -> its key, to name a miss
        self._source_origin: dict[str, str] = {}  # and whether it is the rig's
        self.zenoh_missed_foreign = 0
        self._keys_sourced: set[str] = set()
        self._advanced = self.opts.zenoh_advanced
        self._miss: zext.SampleMissListener[None] | None = None
        self._miss_lock = threading.Lock()
        self._peak_queue = 0
        self._write_failed = False
        self._last_rx = time.monotonic()  # when the last sample came in (the stop waits for quiet)
        self._abort = threading.Event()  # the stop deadline passed: the writer stops
        self.unwritten_at_stop = 0
        self._in_hand = 0  # of the writer's last batch, what the stop deadline left unwritten
        # What the files of this recorder's earlier lives hold (option ``continues``): read by the
        # writer thread before it writes anything, so the callback never waits for it.
        self.previous = Completeness()
        self.previous_files: list[str] = []
        self.previous_messages = 0
        self.already_recorded = 0
        # the run the earlier files record (their first RunInfo; else their ``hil`` metadata)
        self._previous_run: RunInfo | None = None
        self._earlier_run = _RunFromMetadata()

    # The base class sets ``state`` to "running" after setup(); a recorder that cannot write must
    # keep saying "degraded" for as long as it lives, so the state is derived, not assigned.
    @property
    def state(self) -> str:
        base = self.__dict__.get("_state", "starting")
        if self.__dict__.get("_degraded", False) and base in ("running", "stopping"):
            return "degraded"  # to the last status: the supervisor must not read "stopped cleanly"
        return base

    @state.setter
    def state(self, value: str) -> None:
        before = self.state if "_state" in self.__dict__ else None
        if value == "degraded":
            self.__dict__["_degraded"] = True
            value = "running"
        self.__dict__["_state"] = value
        # as the base class: a change goes out at once, not at the next 1 Hz status. Without
        # this the recorder said "running" up to a second after it was (1.0 s of the 2.9 s it
        # took to be ready in `hil up`), and time zero waits for it.
        wake = self.__dict__.get("_status_now")
        if wake is not None and self.state != before:
            wake.set()

    def needs_run(self) -> bool:
        return False  # record from boot: statuses before the run starts are evidence too

    def setup(self) -> None:
        kept = None
        try:
            if not self.opts.continues:  # a restarted recorder writes a new file of its own
                kept = keep_aside(self.path)
            self.writer = SessionWriter(self.path)
        except OSError as err:  # the earlier recording could not be moved: it is not written over
            self.stats.error("errors.recording_path", f"{self.path} holds an earlier recording: {err}")
            self.state = "degraded"
        except RecordingError as err:
            # the reason first: the status thread is already running, and a "degraded" status
            # must never go out without it
            self.stats.error("errors.recording_path", str(err))
            self.state = "degraded"
        if self._advanced:
            # The callback only enqueues (bounded lanes, see the module docstring): nothing between
            # Zenoh and the writer thread drops unless a lane overflows, and that is counted.
            # Heartbeat recovery: a gap in a publisher's sequence is queried from its cache before
            # it is reported as missed.
            # History: every publisher's cache is asked at once for what it holds, so what was
            # said before this subscription reached it is recorded too -- a service's first
            # messages when it started before the recorder, and for a restarted recorder
            # (``continues``) what the rig sent while no recorder was writing, as far as the
            # caches reach (what the earlier files hold is not written twice, see ``_handle``).
            # Without it, a cache was replayed only when the publisher's heartbeat came before
            # its next sample: a race. Lost to it were a publisher's only message (the bridge's
            # one event per life: its one heartbeat had gone out before the recorder listened)
            # and, for a restarted recorder, nothing, or everything again (duplicates).
            self._sub = zext.declare_advanced_subscriber(
                self.ctx.session,
                self.keys.all(),
                self._on_sample,
                history=zext.HistoryConfig(),
                recovery=zext.RecoveryConfig(periodic_queries=None, heartbeat=True),
                subscriber_detection=True,
            )
            self._miss = self._sub.sample_miss_listener(self._on_miss)
        else:
            self._sub = self.ctx.session.declare_subscriber(self.keys.all(), self._on_sample)
        self._writer_thread.start()
        if kept is not None:  # said once the recording listens, so that the event is in it too
            detail = f"{self.path} held an earlier recording: kept as {kept}, not written over"
            sys.stderr.write(f"recorder: {detail}\n")
            self.emit_event("earlier_recording_kept", detail)

    def _lane_cap(self, _kind: str, publisher: str) -> int:
        return FOREIGN_LANE_CAP if self.identity.classify(publisher) == FOREIGN else RIG_LANE_CAP

    def _count_drop(self, _kind: str, _publisher: str, item: tuple[str, bytes, int, str, str, Any]) -> None:
        if item[4] == FOREIGN:
            self.dropped_foreign += 1
        else:
            self.dropped_rig += 1

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Zenoh's thread: stamp and enqueue only; never raise into Zenoh.
        try:
            key = str(sample.key_expr)
            source = source_id(sample)
            origin = self.identity.classify(source)
            item = (key, sample.payload.to_bytes(), wall_ns(), source, origin, sample.encoding)
            self.queue.put(key_kind(key[self._root_len :]), source, item)
            self._last_rx = time.monotonic()
            if self._advanced:
                info = sample.source_info
                if info is None:
                    self.zenoh_unsequenced += 1
                elif info.source_sn == 0 or key not in self._keys_sourced:
                    # a publisher's first sample (or the first we saw): remember its key for misses
                    self._source_key[str(info.source_id)] = key
                    self._source_origin[str(info.source_id)] = origin
                    self._keys_sourced.add(key)
        except Exception as err:
            self.stats.error("errors.enqueue", f"{type(err).__name__}: {err}")

    def _on_miss(self, miss: zext.Miss) -> None:
        """Zenoh says ``miss.nb`` samples of one advanced publisher never reached us (nor its cache)."""
        source = str(miss.source)
        key = self._source_key.get(source, source)
        if self._source_origin.get(source) == FOREIGN:  # a stranger's loss is not the rig's
            with self._miss_lock:
                self.zenoh_missed_foreign += int(miss.nb)
            return
        with self._miss_lock:
            self.zenoh_missed[key] = self.zenoh_missed.get(key, 0) + int(miss.nb)
        self.stats.error("zenoh_missed_events", f"Zenoh sample miss: {miss.nb} samples of {key}")

    def total_zenoh_missed(self) -> int:
        with self._miss_lock:
            return sum(self.zenoh_missed.values())

    def extra_status(self) -> dict[str, int]:
        depth = self.queue.qsize()
        self._peak_queue = max(self._peak_queue, self.queue.peak)
        totals = {"gaps": 0, "duplicates": 0, "out_of_order": 0}
        writer = self.writer
        index = None if writer is None else writer.chunk_index
        for tr in list(self.completeness.topics.values()):
            totals["gaps"] += tr.gaps
            totals["duplicates"] += tr.duplicates
            totals["out_of_order"] += tr.out_of_order
        return {
            "written": self.written,
            "foxglove_written": self.foxglove_written,
            "bytes_written": self.bytes_written,
            "queue_depth": depth,
            "queue_peak": self._peak_queue,
            "already_recorded": self.already_recorded,
            "missing": self.completeness.total_missing(),
            "zenoh_missed": self.total_zenoh_missed(),
            "zenoh_unsequenced": self.zenoh_unsequenced,
            "dropped_rig": self.dropped_rig,
            "dropped_foreign": self.dropped_foreign,
            "foreign": self.foreign.messages,
            "recording": 0 if self.writer is None else 1,
            "raw_written": self.raw_written,
            "excluded": self.excluded,
            # memory the recorder holds by design, to tell it from a leak in a long session:
            # the MCAP summary index (grows per chunk until the footer; held is the part in
            # memory, the rest is in an unlinked scratch file beside the recording) and
            # Python's live blocks
            "index_bytes": 0 if index is None else index.nbytes,
            "index_held_bytes": 0 if index is None else index.held_bytes,
            "py_heap_blocks": sys.getallocatedblocks(),
            **totals,
        }

    def _log_time(self, rx_wall_ns: int) -> int:
        """Start epoch + receive time on the rig clock (``hil.record.mcapio``); before the run's
        ``RunInfo`` the receive time itself (services starting: the wall clock, as at speed 1)."""
        return wall_clock_log_time(rx_wall_ns, self._start_epoch_ns, self._speed)

    def _handle(
        self, key: str, payload: bytes, rx_wall_ns: int, source: str, origin: str, encoding: Any = None
    ) -> None:
        if self.keyfilter.active and not self.keyfilter.keeps(key):
            self.excluded += 1
            if self._start_epoch_ns is None and origin != FOREIGN and type_for_key(key) is RunInfo:
                self._take_run_unrecorded(key, payload)
            return
        cls = type_for_key(key)
        kind = ".".join(key.split("/")[2:3]) or key
        if cls is None:
            self._handle_raw(key, payload, rx_wall_ns, encoding)
            return
        if len(payload) > MAX_PAYLOAD_BYTES:
            self.stats.error(f"rejected.{kind}.oversized", f"{key}: {len(payload)} B")
            return
        try:
            parts = split_batch(payload)  # one message, or a batch's (Publisher.put_many) one by one
        except ValueError as err:
            self.stats.error(f"rejected.{kind}.invalid", f"{key}: {err}")
            return
        for part in parts:
            self._record(key, cls, kind, part, rx_wall_ns, source, origin)

    def _record(
        self, key: str, cls: type[Any], kind: str, payload: bytes, rx_wall_ns: int, source: str, origin: str
    ) -> None:
        """One contract message: decoded, checked, accounted, written with what it derives."""
        try:
            msg = decode(cls, payload)
        except (msgspec.ValidationError, msgspec.DecodeError) as err:
            self.stats.error(f"rejected.{kind}.invalid", f"{key}: not a valid {cls.__name__}: {err}")
            return
        foreign = origin == FOREIGN
        if self._start_epoch_ns is None and isinstance(msg, RunInfo) and not foreign:
            self._take_run(msg)
        if not foreign and self.previous.holds(key, msg.seq):
            self.already_recorded += 1  # an earlier life's file holds it (a cache's replay)
            return
        if foreign:
            self.foreign.see(key, source, msg.seq)
        else:
            self.completeness.see(key, msg.seq)
        if self.writer is None:
            return
        log_ns = self._log_time(rx_wall_ns)
        start = self._start_epoch_ns
        try:
            self.writer.write(
                key,
                cls,
                payload,
                log_time_ns=log_ns,
                publish_time_ns=log_ns if start is None else start + msg.stamp_ns,
                seq=msg.seq,
                publisher=source,
                origin=origin,
            )
            self.written += 1
            self.bytes_written += len(payload)
            self.stats.count_rate("in.all")
            self._write_wellknown(key, msg, log_ns)
        except OSError as err:
            self._fail(err)

    def _take_run(self, run: RunInfo) -> None:
        """The run's time base, metadata and attachments: the file's, whatever it records."""
        self._start_epoch_ns = run.start_epoch_ns
        self._speed = run.speed
        self._run = run
        # its own statuses and events on the rig clock, as every service's: they went out
        # stamped 0 all run (a file's recorder status then read as 13 Hz over its publish times)
        self.clock = RigClock(run.start_epoch_ns, run.speed)
        self._part_t0 = time.monotonic()
        self._write_run_metadata(run)

    def _take_run_unrecorded(self, key: str, payload: bytes) -> None:
        """``RunInfo`` on a key the filter leaves out (``--record-include 'nav/**'``): not written
        as a message, but still the file's time base, metadata and attachments -- without it the
        log times were raw receive times and ``hil rerun`` said "not a rig session"."""
        try:
            msg = decode(RunInfo, split_batch(payload)[0])
        except (msgspec.ValidationError, msgspec.DecodeError, ValueError, IndexError) as err:
            self.stats.error("rejected.run.invalid", f"{key}: not a valid RunInfo: {err}")
            return
        self._take_run(msg)

    def _write_wellknown(self, key: str, msg: Any, log_ns: int) -> None:
        """Foxglove's well-known types derived from the message, beside it (``hil.wellknown``)."""
        if not self.opts.foxglove_types or self.writer is None:
            return
        try:
            derived = self._wellknown.convert(key, msg, log_ns)
        except Exception as err:  # a conversion must never cost the recording
            self.stats.error("errors.foxglove_types", f"{key}: {type(err).__name__}: {err}")
            return
        for d in derived:
            self.writer.write_wellknown(d, log_time_ns=log_ns)
            self.foxglove_written += 1

    def _handle_raw(self, key: str, payload: bytes, rx_wall_ns: int, encoding: Any) -> None:
        """A key under ``hil/<rig>/`` outside the contract: its bytes, on a schema-less channel.

        Evidence is kept rather than refused (a tool's own topic, a newer release's key); it is
        not decoded, so it has no seq to account: MCAP's ``sequence`` counts it per key here.
        """
        if not self.opts.raw_unknown:
            self.stats.error("rejected.unknown_key", f"{key}: not a contract key")
            return
        if len(payload) > MAX_PAYLOAD_BYTES:
            self.stats.error("rejected.unknown_key.oversized", f"{key}: {len(payload)} B")
            return
        if self.writer is None:
            return
        n = self._raw_seq.get(key, 0)
        self._raw_seq[key] = n + 1
        try:
            self.writer.write_raw(
                key,
                payload,
                log_time_ns=self._log_time(rx_wall_ns),
                encoding=str(encoding) if encoding is not None else "",
                sequence=n & 0xFFFFFFFF,
            )
            self.written += 1
            self.raw_written += 1
            self.bytes_written += len(payload)
        except OSError as err:
            self._fail(err)

    def _fail(self, err: OSError) -> None:
        """A write error (disk full, file removed, I/O error): say so in status, stop writing.

        The process stays up, so the rest of the rig keeps running and the supervisor's table and
        the status key keep showing *why* nothing is being recorded.
        """
        self._write_failed = True
        self.stats.error(
            "errors.write", f"writing {self.part_path()} failed: {err.strerror or err}; recording stopped"
        )
        self.state = "degraded"  # after the reason, which the status thread may publish at once
        writer, self.writer = self.writer, None
        if writer is not None:
            writer.abandon()

    def _write_run_metadata(self, run: RunInfo) -> None:
        if self.writer is None or self._meta_written:
            return
        self._meta_written = True
        from hil.runtime.scenario_io import run_attachments

        self.writer.add_metadata(
            "hil",
            {
                "version": __version__,
                "rig": run.rig,
                "scenario": run.scenario,
                "scenario_sha256": run.scenario_sha256,
                "seed": run.seed,
                "start_epoch_ns": run.start_epoch_ns,
                "speed": run.speed,
                "duration_s": run.duration_s,
                "origin_lat_deg": run.origin_lat_deg,
                "origin_lon_deg": run.origin_lon_deg,
                "origin_alt_m": run.origin_alt_m,
                "executor": "live",
                "time_semantics": TIME_SEMANTICS,
                "time_base": "epoch",
            },
        )
        self.writer.add_metadata(
            "config", {"options": json.dumps(msgspec.to_builtins(self.opts), sort_keys=True)}
        )
        for name, data, media in run_attachments(run):
            self.writer.add_attachment(name, data, media, log_time_ns=run.start_epoch_ns)

    def part_path(self, part: int | None = None) -> Path:
        """Part 0 is the requested path; later parts are ``<stem>_0001<suffix>``, ..."""
        return split_part_path(self.path, self.part if part is None else part)

    def _due_split(self) -> bool:
        if self.writer is None or self._run is None:
            return False  # the first part runs from boot to at least the run's start
        if self.split_bytes and self.writer.tell() >= self.split_bytes:
            return True
        return bool(self.split_s) and time.monotonic() - self._part_t0 >= self.split_s

    def _rotate(self) -> None:
        """Finish the current part and open the next one (same metadata and attachments)."""
        assert self.writer is not None
        self.writer.add_metadata("completeness", {**self.completeness_summary(), "part": self.part})
        self.writer.close()
        previous = self.writer
        self.part += 1
        self._part_t0 = time.monotonic()
        self._meta_written = False
        try:
            self.writer = SessionWriter(self.part_path(), after=previous)
        except RecordingError as err:
            self.writer = None
            self.stats.error("errors.recording_path", str(err))
            self.state = "degraded"
            return
        self.writer.add_metadata("part", {"index": self.part, **part_metadata(self.part_path(self.part - 1))})
        if self._run is not None:
            self._write_run_metadata(self._run)

    def _read_previous(self) -> None:
        """Account what the files of this recorder's earlier lives hold (option ``continues``),
        each with its split parts: their rig messages' seqs go into ``previous`` (what is not
        written again) and into this part's ``completeness`` (which then covers the session).
        A file that cannot be read is reported, and the recording goes on without it."""
        for name in self.opts.continues:
            first = Path(name)
            for path in [first, *split_parts(first)]:
                try:
                    n = self._account_file(path)
                except Exception as err:  # unreadable or not ours: said, and the recording goes on
                    why = f"{type(err).__name__}: {err}"
                    self.stats.error("errors.previous_part", f"cannot read {path}: {why}")
                    continue
                self.previous_files.append(path.name)
                self.previous_messages += n

    def _account_file(self, path: Path) -> int:
        n = 0
        for kind, rec in iter_records(path):
            if self._previous_run is None and kind in ("metadata", "attachment"):
                self._earlier_run.take(kind, rec)
            if kind != "message" or rec.foreign or not rec.schema.startswith("hil."):
                continue
            if self._previous_run is None and rec.schema == "hil.RunInfo":
                with contextlib.suppress(msgspec.ValidationError, msgspec.DecodeError):
                    self._previous_run = decode(RunInfo, rec.payload)
            try:
                seq = _STAMP.decode(rec.payload).seq
            except (msgspec.ValidationError, msgspec.DecodeError):
                continue  # the recorder that wrote it had checked it; a damaged tail, say
            self.previous.see(rec.topic, seq)
            self.completeness.see(rec.topic, seq)
            n += 1
        return n

    def _write_loop(self) -> None:
        if self.opts.continues:
            self._read_previous()
            # the session's time base before anything is written: until the next RunInfo came,
            # the part's first second went out with publish time = log time (and, at a speed
            # other than 1, log times off the session's base), so what it recovered from the
            # caches did not read as recovered (``SessionStream``) and the time-sync rerun failed
            run = self._previous_run or self._earlier_run.run()
            if run is not None and self._start_epoch_ns is None:
                self._take_run(run)
        last_flush = time.monotonic()
        while not self._abort.is_set():
            items = self.queue.get_many(WRITE_BATCH, timeout=0.2)
            if not items and self._closing.is_set():
                break
            for i, item in enumerate(items):
                if self._abort.is_set():
                    self._in_hand = len(items) - i  # taken from the queue, not written: counted
                    break
                try:
                    self._handle(*item)
                except Exception as err:  # one bad record must not stop the recording
                    self.stats.error("errors.record", f"{type(err).__name__}: {err}")
            if self.writer is not None and time.monotonic() - last_flush >= FLUSH_PERIOD_S:
                last_flush = time.monotonic()
                try:
                    self.writer.flush()
                    if self._due_split():
                        self._rotate()
                except OSError as err:
                    self._fail(err)
            if len(items) < WRITE_BATCH and not self._closing.is_set():
                # let the next messages gather: the log time is stamped on arrival, and a
                # wake-up per message cost more than writing it
                self._abort.wait(GATHER_S)

    def teardown(self) -> None:
        """Let the last samples arrive, write every one of them, then finish the file.

        Why not a fixed pause: under load the recorder can be seconds behind a burst (samples in
        Zenoh's buffers and in the queue), and whatever is dropped at the stop is the *tail* of
        every stream, which no seq gap shows. So: wait until nothing has arrived for ``drain_s``
        (at most ``drain_max_s``), then let the writer empty the queue (at most
        ``stop_timeout_s``, inside the supervisor's 30 s); what is still queued then is counted
        (``unwritten_at_stop`` in status and summary, ``replay_ready`` false), never silent.
        """
        opts = self.opts
        quiet_s = opts.drain_s
        give_up = time.monotonic() + opts.drain_max_s
        time.sleep(quiet_s)
        while time.monotonic() - self._last_rx < quiet_s and time.monotonic() < give_up:
            time.sleep(0.05)
        try:
            if self._miss is not None:
                self._miss.undeclare()
            self._sub.undeclare()
        except Exception as err:  # a session already closing must not cost us the summary
            self.stats.error("errors.undeclare", f"{type(err).__name__}: {err}")
        self._closing.set()  # the writer ends once the queue is empty
        self._writer_thread.join(timeout=opts.stop_timeout_s)
        if self._writer_thread.is_alive():
            self._abort.set()  # the writer stops after the message in hand
            self._writer_thread.join(timeout=5.0)
            self.unwritten_at_stop = self.queue.qsize() + self._in_hand
            self.stats.error(
                "errors.stop_timeout",
                f"{self.unwritten_at_stop} received messages were still queued at the stop deadline "
                "and were not written",
            )
        if self.writer is None:
            return
        try:
            self.writer.add_metadata("completeness", {**self.completeness_summary(), "part": self.part})
            self.writer.close()
        except OSError as err:
            self._fail(err)

    def exit_code(self) -> int:
        """3 when the recording could not be written (the reason is in the last status)."""
        return 3 if self.__dict__.get("_degraded", False) else 0

    def completeness_summary(self) -> dict[str, Any]:
        """What the file is worth: per-topic seq accounting, Zenoh misses, rejects, the verdict."""
        missing = self.completeness.total_missing()
        zmissed = self.total_zenoh_missed()
        with self._miss_lock:
            by_source = dict(self.zenoh_missed)
        return {
            "topics": self.completeness.report(),
            "messages": self.written,
            "bytes": self.bytes_written,
            "missing": missing,
            "zenoh_missed": zmissed,
            "zenoh_missed_by_key": by_source,
            "zenoh_unsequenced": self.zenoh_unsequenced,
            "zenoh_miss_detection": self._advanced,
            "queue_peak": max(self._peak_queue, self.queue.peak),
            "unwritten_at_stop": self.unwritten_at_stop,
            "dropped_rig": self.dropped_rig,
            "rig_identity": "known" if self.identity.known else "unknown",
            "foreign": {
                **self.foreign.report(),
                "dropped": self.dropped_foreign,
                "zenoh_missed": self.zenoh_missed_foreign,
            },
            "replay_ready": missing == 0
            and zmissed == 0
            and not self.unwritten_at_stop
            and not self.dropped_rig
            and self._run is not None,
            "parts": self.part + 1,
            # a restarted recorder: the files it continues, how many of the rig's messages they
            # hold (``topics`` counts them too), and how many it received again and did not write
            "continues": {
                "files": self.previous_files,
                "messages": self.previous_messages,
                "already_recorded": self.already_recorded,
            },
            "raw_written": self.raw_written,
            "excluded": self.excluded,
            "rejected": {k: v for k, v in self.stats.counters.items() if k.startswith("rejected")},
            "method": "seq gaps per publisher"
            + (" + zenoh.ext advanced subscriber sample-miss listener" if self._advanced else ""),
        }


SERVICE = Recorder


def main(argv: list[str] | None = None) -> int:
    # here, not at the top: the live runner brings python-can and numpy, which the recorder
    # process under `hil up` (run_service with --options) never needs
    from hil.runners.live import options_parser

    ap = options_parser(
        RecorderOptions, "hil service recorder", {"--no-zenoh-miss-detection": "zenoh_advanced"}
    )
    a = ap.parse_args(argv)
    return run_service(Recorder, a.rig or "default", {k: v for k, v in vars(a).items() if k != "rig"})

"""``hil rerun FILE --core timesync [--verify]``: re-stamp the recorded raw measurements again.

The time-sync core is per sensor, and per sensor its inputs -- ``timetag/<sensor>`` edges and raw
``sensor/<sensor>`` measurements -- come from one publishing process (the bridge for the IMU, the
receiver for GNSS), so the recorder sees them in the order the timesync service saw them (one
Zenoh link per peer pair is FIFO). Feeding them in file order through a fresh
time-sync node (``hil.nodes.timesync``, configured from the run's scenario) therefore reproduces
every re-stamp; each
recomputed ``synced/<sensor>`` message (the raw one with its ``stamp_ns`` replaced) is compared
byte for byte with the recorded one, by (sensor, seq).

Live sessions: the timesync service consumes each sensor's measurements and time tags through
one subscription (``hil/<rig>/*/<sensor>``, one callback thread), so it sees them in publication
order, as the recorder does. (With separate subscribers, zenoh-python's one thread per callback
let a PPS edge and a fix published back to back reach the core in the other order: verify then
named e.g. ``synced/gnss seq 19: field 'stamp_ns' differs``.)

A stranger's messages (channels marked ``origin: foreign``) are left out: the live service
refuses them before they reach its core (``refuses_foreign``), so a stranger's raw measurement
never comes out as the rig's re-stamped one.

Two processes where a second CPU is there: this one reads the file and matches, a forked worker
decodes and re-stamps (``restamps``), one batch behind; the matcher's operations are kept in file
order and run once their batch's re-stamps are back, so it decides exactly as one process does
(``--one-process`` keeps everything here). 300 s of straight_level: 3.27 s in one process, 2.13-2.18
s in two (this process 1.46 s of CPU, the worker 1.65 s).

A time sync restarted mid-run (``hil up --restart``) is a fresh core on what its new process
received: its ``first_input`` events name, per sensor, the first input it took (it took every
later one of that sensor: one publisher, one link, in order), so a fresh core here is fed from
there (``_LaterLife``) and its re-stamps (another Zenoh session publishes them) are compared as
the first life's are. A recording made before the events said so (or one that lost them) cannot
tell which time tags the new life took first (``_Lives``): those re-stamps are counted as not
verifiable, in a note naming the restart.

What a silent sensor's held measurements are released by -- its next input stamped more than
``IDLE_RELEASE_NS`` after the last measurement's arrival -- is a rule on that sensor's inputs, so
the rerun releases where the service did; the service releases sooner on its clock, once the
rule is sure to hold. Where an input proved it early (on its way longer than the margin: a
stalled process or bus), the service said so (``idle_release_early`` on ``event/timesync``) and
the rerun notes it: its re-stamps of that sensor differ from there, and verify names the first.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from typing import Any

import msgspec

from hil.messages import (
    Event,
    RunInfo,
    ServiceStatus,
    TimeTag,
    decode,
    encode,
    encoded_today,
    payload_seq,
    schema_name,
)
from hil.nodes.timesync import TimeSyncNode, first_input_named
from hil.record.matching import TAIL_NS, Matcher, SeqSet, truncation_notes, verdict
from hil.record.mcapio import (
    Record,
    RecordingError,
    Session,
    SessionStream,
    cut_notes,
    no_run_message,
    rig_time_ns,
    session_note,
)
from hil.runners.sim_worker import RemoteNode, worker_possible
from hil.runtime.heap import freeze_command_startup
from hil.sensor_table import SENSORS

_RAW = {schema_name(k.message): k.message for k in SENSORS.values()}


@dataclass
class TimesyncRerun:
    measurements: int
    timetags: int
    n_recomputed: int
    n_recorded: int
    difference: str | None
    # a truncated file: the difference leaving out the recorded re-stamps of its last
    # ``TAIL_NS`` whose raw measurement the cut took (``unverified`` of them)
    difference_if_cut: str | None = None
    unverified: int = 0
    recovered: int = 0  # differing re-stamps of what a restarted recorder recovered: excused
    no_raw: int = 0  # recorded re-stamps whose raw measurement the recording lacks
    # recorded re-stamps of a restarted time sync (a later life: ``_Lives``), not compared, and
    # the rig time (s) of each restart
    restarted: int = 0
    restarts_s: tuple[float, ...] = ()
    # recorded re-stamps of restarted time syncs compared against a core fed from the first
    # input each one named (``_LaterLife``)
    restarted_compared: int = 0
    # the time sync's idle releases on its clock that an input proved early (its events)
    early_releases: int = 0
    # inputs the live time sync's bounded inbox dropped (its status counters, summed over its
    # lives): which ones is not journaled, so the rerun fed them
    inbox_dropped: int = 0

    def first_difference(self, truncated: bool = False) -> str | None:
        return self.difference_if_cut if truncated else self.difference

    @property
    def excused(self) -> int:
        return self.recovered + self.no_raw + self.restarted


def _synced_difference(key: tuple[str, int], recorded: bytes, mine: bytes) -> str:
    sensor, seq = key
    a, b = msgspec.json.decode(recorded), msgspec.json.decode(mine)
    for f in b:
        if a.get(f) != b.get(f):
            return (
                f"synced/{sensor} seq {seq}: field {f!r} differs: "
                f"recorded {a.get(f)!r}, recomputed {b.get(f)!r}"
            )
    return f"synced/{sensor} seq {seq}: payload bytes differ"


def _synced_current_form(payload: bytes) -> bytes:
    """A recorded re-stamp as today's encoder writes it (``encoded_today`` of its sensor's type):
    a recording made before a field was appended (``GnssFix.line_ns``) lacks it, the re-stamp
    recomputed from its raw measurement carries the default. Only where the bytes differ."""
    try:
        sensor = msgspec.json.decode(payload).get("sensor")
    except (msgspec.DecodeError, AttributeError):
        return payload
    kind = SENSORS.get(sensor) if isinstance(sensor, str) else None
    return encoded_today(kind.message, payload) if kind is not None else payload


# a restarted recorder's recovered messages come in a burst: what it recovered more than this much
# log time apart is another stretch (another restart)
RECOVERY_GAP_NS = 5_000_000_000
HORIZON_NS = 60_000_000_000  # log time a re-stamp waits for its recorded copy before it is let go
# A file cut short: a re-stamp can be recorded before its raw measurement (they come from two
# processes), so the cut may keep the one and lose the other; within this much log time of the
# end such an output is not verifiable, and not a failure.


#: the inputs the node side takes at a time (a worker's batch): ~10 s of a 400 Hz IMU's samples and
#: tags. While the worker re-stamps one batch, this process reads the next from the file.
NODE_BATCH = 4096

# one input of the time-sync node: kind ("timetag" or "sensor"), the node's key, the schema of a
# raw measurement, the payload as recorded, and the rig time it is handled at
_NodeInput = tuple[str, str, str, bytes, int]
# one re-stamp as the matcher takes it: sensor, seq, encoded bytes
_Restamp = tuple[str, int, bytes]
# a later life's inputs read before its ``first_input`` event, per sensor: the event comes just
# after the input it names (the new process publishes it on taking it), so a few suffice; 4096 is
# ~10 s of a 400 Hz IMU's samples
RECENT_INPUTS = 4096


@dataclass
class _LaterLife:
    """A restarted time sync's core, rebuilt here: fed, per sensor, from the first input its
    ``first_input`` event names. Its re-stamps are matched under ``label`` (``<sensor> (life N)``),
    apart from the first life's. From there the lives before it are no longer fed that sensor
    (``_TimesyncMatch._take_over``)."""

    n: int  # 2: the first restart's
    node: TimeSyncNode
    fed: set[str] = field(default_factory=set)  # sensors being fed
    waiting: dict[str, tuple[str, int, str]] = field(default_factory=dict)  # named, not read yet
    retired: set[str] = field(default_factory=set)  # sensors a later life took over: no longer fed

    def label(self, sensor: str) -> str:
        return f"{sensor} (life {self.n})"

    def restamps(self, inputs: list[_NodeInput]) -> list[_Restamp]:
        return [(self.label(s), q, p) for outs in restamps(self.node, inputs) for s, q, p in outs]


def _sensor_of(label: str) -> str:
    """The sensor of a matcher key's label (a later life's ``<sensor> (life N)``, or the sensor)."""
    return label.partition(" ")[0]


def restamps(node: TimeSyncNode, inputs: list[_NodeInput]) -> list[list[_Restamp]]:
    """The node side of a rerun: each input decoded and through the time-sync node, its
    re-stamps encoded -- in a worker process (``RemoteNode.call``) or in this one."""
    out: list[list[_Restamp]] = []
    on_message = node.on_message
    for kind, key, schema, payload, now_ns in inputs:
        msg = decode(TimeTag, payload) if kind == "timetag" else decode(_RAW[schema], payload)
        out.append([(m.sensor, m.seq, encode(m)) for _k, m in on_message(key, msg, now_ns)])
    return out


def _finish(node: TimeSyncNode, now_ns: int) -> list[_Restamp]:
    """What the node still holds at the end of input, encoded."""
    return [(m.sensor, m.seq, encode(m)) for _k, m in node.finish(now_ns)]


class _TimesyncMatch:
    """The reading and matching side of a rerun. A record's part in the matching is kept as an
    operation, in file order, and the operations run once the node side has re-stamped their
    batch: the matcher sees exactly the sequence of one process, however far the node side is
    behind (so its horizon and the too-late test decide as they would)."""

    def __init__(self, worker: bool | None) -> None:
        self.worker = worker
        self.node: TimeSyncNode | None = None
        self.remote: RemoteNode | None = None
        self.matcher = Matcher(_synced_difference, "recorded", HORIZON_NS, _synced_current_form)
        self.late: list[tuple[int, tuple[str, int]]] = []  # recorded after their re-stamp was let go
        self.counts = {"meas": 0, "tags": 0, "out": 0, "order": 0}
        # topic -> (kind, sensor, the node's key): split once per topic, not per record
        self.routes: dict[str, tuple[str, str, str] | None] = {}
        self.batch: list[_NodeInput] = []
        # this batch's operations: (rig time, None) an input's re-stamps (the next in the reply),
        # then a release; (rig time, (pair, payload, order)) a recorded re-stamp, then a release;
        # (rig time, ()) a release alone
        self.ops: list[tuple[int, Any]] = []
        self.in_flight: list[tuple[int, Any]] | None = None  # the operations of the batch sent
        self.raw_seen = SeqSet()  # (sensor, seq) of every raw measurement read
        # restarted time syncs (their Zenoh session) rebuilt here, and each sensor's latest inputs
        # of a live recording (for an event read after the input it names)
        self.lives: dict[str, _LaterLife] = {}
        self.recent: dict[str, deque[tuple[_NodeInput, str]]] = {}
        # sensors a restarted time sync took over from the first life: that process was dead by
        # then, so its core here is no longer fed them (nothing recorded to compare its re-stamps of
        # them with)
        self.retired: set[str] = set()

    def start(self, node: TimeSyncNode) -> None:
        self.node = node
        freeze_command_startup()  # the node and the modules live as long as the rerun (a worker too)
        if self.worker if self.worker is not None else worker_possible():
            self.remote = RemoteNode(node)

    def handle(
        self, topic: str, schema: str, payload: bytes, sequence: int, now_ns: int, publisher: str = ""
    ) -> None:
        routes = self.routes
        if topic in routes:
            rt = routes[topic]
        else:
            rt = routes[topic] = _route(topic)
        if rt is None:
            return
        kind, sensor, key = rt
        if kind == "sensor" and schema in _RAW:
            self.raw_seen.add(sensor, sequence)
        if kind == "timetag" or (kind == "sensor" and schema in _RAW):
            self.counts["tags" if kind == "timetag" else "meas"] += 1
            item = (kind, key, schema, payload, now_ns)
            if publisher:  # a live recording: a time sync may restart in it
                self._later_input(sensor, item, publisher, now_ns)
            if sensor in self.retired:
                self.ops.append((now_ns, ()))
                return
            self.batch.append(item)
            self.ops.append((now_ns, None))
            if len(self.batch) >= NODE_BATCH:
                self.flush()
        elif kind == "synced" and schema in _RAW:
            self.counts["order"] += 1
            self.ops.append((now_ns, ((sensor, sequence), payload, self.counts["order"])))
        else:
            self.ops.append((now_ns, ()))

    def release(self, t_ns: int) -> None:
        self.ops.append((t_ns, ()))

    def _later_input(self, sensor: str, item: _NodeInput, publisher: str, now_ns: int) -> None:
        """An input to the restarted time syncs' cores here that take it, and to the recent ones."""
        recent = self.recent.get(sensor)
        if recent is None:
            recent = self.recent[sensor] = deque(maxlen=RECENT_INPUTS)
        recent.append((item, publisher))
        lives = self.lives.values()
        for life in lives:  # first the life this input begins, so that the one before it stops here
            if sensor in life.waiting and self._is_named(life.waiting[sensor], item, publisher):
                del life.waiting[sensor]
                self._take_over(life, sensor)
        for life in lives:
            if sensor in life.fed:
                self.ops.append((now_ns, life.restamps([item])))

    def _take_over(self, life: _LaterLife, sensor: str) -> None:
        """``life`` fed ``sensor`` from its first input on; the lives before it no longer are.

        The supervisor restarts a service once its process is gone, so the earlier lives had died
        before this one subscribed: whatever their cores here would make of later inputs was
        never published, and a rerun of a run restarted N times would pay N+1 cores to the end
        of the file for one's worth of comparisons."""
        life.fed.add(sensor)
        self.retired.add(sensor)
        for earlier in self.lives.values():
            if earlier.n < life.n and sensor in earlier.fed:
                earlier.fed.discard(sensor)
                earlier.retired.add(sensor)

    @staticmethod
    def _is_named(named: tuple[str, int, str], item: _NodeInput, publisher: str) -> bool:
        key, seq, source = named
        return item[1] == key and publisher == source and payload_seq(item[3]) == seq

    def first_input(self, session: str, named: tuple[str, str, int, str], now_ns: int) -> None:
        """A restarted time sync's ``first_input`` event: its core here (made on its first event)
        fed that input of the sensor, if already read, and every later one."""
        assert self.node is not None
        life = self.lives.get(session)
        if life is None:
            life = self.lives[session] = _LaterLife(len(self.lives) + 2, TimeSyncNode(self.node.run))
        sensor, key, seq, source = named
        if sensor in life.fed or sensor in life.waiting or sensor in life.retired:
            return  # said once per sensor; a second one is not the live node's
        recent = list(self.recent.get(sensor, ()))
        at = next(
            (i for i, (item, p) in enumerate(recent) if self._is_named((key, seq, source), item, p)), None
        )
        if at is None:
            life.waiting[sensor] = (key, seq, source)
            return
        self._take_over(life, sensor)
        self.ops.append((now_ns, life.restamps([item for item, _p in recent[at:]])))

    def compares(self, session: str, sensor: str) -> str | None:
        """The matcher's label for a recorded re-stamp of ``sensor`` by a restarted time sync, if
        its core here is fed (or waits for the input its event named); None: not verifiable."""
        life = self.lives.get(session)
        if life is None or not (sensor in life.fed or sensor in life.waiting or sensor in life.retired):
            return None
        return life.label(sensor)

    def recorded_later(self, label: str, sequence: int, payload: bytes, now_ns: int) -> None:
        self.counts["order"] += 1
        self.ops.append((now_ns, ((label, sequence), payload, self.counts["order"])))

    def flush(self) -> None:
        """The batch to the node side; with a worker, the batch before it matched meanwhile."""
        batch, ops, self.batch, self.ops = self.batch, self.ops, [], []
        if self.remote is None:
            assert self.node is not None
            self._run(ops, restamps(self.node, batch))
            return
        self.drain()
        self.remote.call(restamps, batch)
        self.in_flight = ops

    def drain(self) -> None:
        if self.in_flight is not None:
            assert self.remote is not None
            ops, self.in_flight = self.in_flight, None
            self._run(ops, self.remote.called())

    def _run(self, ops: list[tuple[int, Any]], outs: list[list[_Restamp]]) -> None:
        m, late, counts = self.matcher, self.late, self.counts
        i = 0
        for now_ns, op in ops:
            if op is None:
                for sensor, seq, payload in outs[i]:
                    m.recomputed((sensor, seq), payload, -1, now_ns)
                    counts["out"] += 1
                i += 1
            elif type(op) is list:  # a restarted time sync's re-stamps, made here (_LaterLife)
                for label, seq, payload in op:
                    m.recomputed((label, seq), payload, -1, now_ns)
                    counts["out"] += 1
            elif op:
                pair, payload, order = op
                if pair in m.released:
                    late.append((order, pair))
                m.recorded(pair, payload, order, now_ns)  # rig time, as now_ns below
            m.release_before(now_ns)

    def finish(self, now_ns: int) -> None:
        """End of input: every batch matched, then what the node still holds."""
        self.flush()
        self.drain()
        if self.remote is not None:
            self.remote.call(_finish, now_ns)
            outs = self.remote.called()
        else:
            assert self.node is not None
            outs = _finish(self.node, now_ns)
        for life in self.lives.values():
            outs = outs + [(life.label(s), q, p) for s, q, p in _finish(life.node, now_ns)]
        for sensor, seq, payload in outs:
            self.matcher.recomputed((sensor, seq), payload, -1, now_ns)
            self.counts["out"] += 1

    def close(self) -> None:
        if self.remote is not None:
            self.remote.close()


def _route(topic: str) -> tuple[str, str, str] | None:
    parts = topic.split("/")
    if len(parts) != 4:
        return None
    kind, sensor = parts[2], parts[3]
    return kind, sensor, f"{kind}/{sensor}"


@dataclass
class _Lives:
    """The time sync's lives in a recording (``hil up --restart``): a restarted service publishes
    from a new Zenoh session, so ``synced/*`` records whose publisher session is not the first
    one's are a later life's.

    A later life is a fresh core that took the raw measurements and tags published after its
    subscription opened. Its first re-stamp names the first measurement it took, but not which of
    the time tags published between that one and the measurement before it reached it (GNSS: a
    1 Hz PPS tag falls there once in ten 10 Hz fixes), and a tag more or less is another tag filter
    and other stamps. Its ``first_input`` events name them (``_LaterLife``: a core here fed from
    there, its re-stamps compared); without them its re-stamps are counted as not verifiable,
    never compared against the first life's core, which the rerun goes on feeding."""

    first: str | None = None  # the first life's Zenoh session
    later: list[str] = field(default_factory=list)  # the later lives' sessions, in order
    first_out_ns: list[int] = field(default_factory=list)  # rig log time of each one's first output
    restarted_ns: list[int] = field(default_factory=list)  # the supervisor's service_restarted events
    n_later: int = 0  # recorded re-stamps of the later lives
    n_compared: int = 0  # of those, compared (``_LaterLife``)

    def is_later(self, r: Record, now_ns: int) -> bool:
        """Is ``r`` (a ``synced/*`` record) a later life's re-stamp? Counted if so."""
        session = r.publisher.partition(":")[0]
        if not session:  # a recording without publishers (``hil sim``, older files): one life
            return False
        if self.first is None or session == self.first:
            self.first = session
            return False
        if session not in self.later:
            self.later.append(session)
            self.first_out_ns.append(now_ns)
        self.n_later += 1
        return True

    def supervisor_event(self, r: Record) -> None:
        ev = r.decode()
        if isinstance(ev, Event) and ev.kind == "service_restarted" and ev.source == "timesync":
            self.restarted_ns.append(ev.stamp_ns)

    def times_s(self) -> tuple[float, ...]:
        """When each later life began: the supervisor's restart, else its first output."""
        events = self.restarted_ns if len(self.restarted_ns) == len(self.later) else self.first_out_ns
        return tuple(t / 1e9 for t in events)


def restart_note(res: TimesyncRerun) -> list[str]:
    """The note of a time sync restarted mid-run: when, how many of its re-stamps were compared
    (a core rebuilt from the first inputs it named) and how many it leaves out."""
    if not res.restarts_s:
        return []
    at = ", ".join(f"t={t:.1f} s" for t in res.restarts_s)
    n = len(res.restarts_s)
    when = f"note: the time sync restarted {'at' if n == 1 else f'{n} times, at'} {at}"
    if not res.restarted:
        return [
            f"{when} (a new process, a fresh core: rebuilt here from the first input of each sensor it "
            f"named in its first_input events): its {res.restarted_compared} re-stamps after that compared"
        ]
    compared = f"; {res.restarted_compared} others compared" if res.restarted_compared else ""
    return [
        f"{when} (a new process, a fresh core this rerun does not rebuild: which time tags it took "
        "before its first measurement the recording cannot tell, no first_input event names it): its "
        f"{res.restarted} re-stamps after that are not verifiable{compared}"
    ]


def _inputs_dropped(r: Record) -> int:
    """How many of its inputs (measurements, tags) a ``status/timesync`` record says the
    service's inbox has dropped so far (``inbox.dropped.<kind>``); 0 if it does not decode."""
    try:
        counters = decode(ServiceStatus, r.payload).counters
    except (msgspec.DecodeError, msgspec.ValidationError):
        return 0
    return sum(
        c.value for c in counters if c.key.startswith(("inbox.dropped.sensor.", "inbox.dropped.timetag."))
    )


def unjournaled_notes(res: TimesyncRerun) -> list[str]:
    """What the live time sync did that its inputs do not tell (``hil.nodes.timesync``): idle
    releases on its clock an input proved early (its events), inputs its inbox dropped (its
    status; not journaled, unlike the fusion's). The rerun fed those inputs as they came."""
    notes = []
    if res.early_releases:
        notes.append(
            f"released held measurements on its clock {res.early_releases} time(s) while an input "
            "of that sensor was still on its way (idle_release_early on event/timesync: a stalled "
            "process or bus)"
        )
    if res.inbox_dropped:
        notes.append(
            f"dropped {res.inbox_dropped} of its inputs from its inbox (its status: inbox.dropped.*; "
            "it fell that far behind; which ones is not journaled)"
        )
    return [f"note: the time sync {n}: re-stamps of that sensor after it can differ" for n in notes]


def rerun_timesync_records(
    records: Iterable[Record], name: str = "recording", worker: bool | None = None
) -> TimesyncRerun:
    """Feed time tags and raw measurements, in file order, through a fresh time-sync node.

    Streams: the records before the run's ``RunInfo`` (which configures the core) are held until
    it comes; after that only re-stamps waiting for their recorded copy (or the other way round)
    are held (``Matcher``), and a re-stamp nobody recorded is let go after ``HORIZON_NS`` of log
    time. A recorded copy that comes even later is reported as a difference, never skipped.

    ``worker``: the node in a forked worker process (None: where a second CPU is there,
    ``worker_possible``), one batch behind this process's reading and matching; the same
    operations in the same order either way.
    """
    run_side = _TimesyncMatch(worker)
    try:
        return _rerun(records, name, run_side)
    finally:
        run_side.close()


def _rerun(records: Iterable[Record], name: str, side: _TimesyncMatch) -> TimesyncRerun:
    held: list[Record] = []
    now_ns = start_ns = 0
    recovery: list[list[int]] = []  # (first, last) rig log time of each recovered stretch
    lives = _Lives()
    early_releases = 0
    dropped: dict[str, int] = {}  # the time sync's inbox drops of its inputs, per life (Zenoh session)
    for r in records:
        if r.skipped_log_ns >= 0 and side.node is not None:  # what handle() of those would have done
            side.release(rig_time_ns(r.skipped_log_ns, start_ns))
        if r.foreign:  # the live time sync refused a stranger's measurements and tags
            continue
        now_ns = rig_time_ns(r.log_time_ns, start_ns)
        if r.topic.endswith("/status/timesync"):
            n = _inputs_dropped(r)
            if n:
                session = r.publisher.partition(":")[0]
                dropped[session] = max(dropped.get(session, 0), n)  # cumulative within a life
        if r.topic.endswith("/event/supervisor"):
            lives.supervisor_event(r)
        elif r.topic.endswith("/event/timesync") and side.node is not None:
            ev = r.decode()
            named = (
                first_input_named(ev.detail) if isinstance(ev, Event) and ev.kind == "first_input" else None
            )
            if named is not None:
                side.first_input(r.publisher.partition(":")[0], named, now_ns)
            elif isinstance(ev, Event) and ev.kind == "idle_release_early":
                early_releases += 1
        elif "/synced/" in r.topic and lives.is_later(r, now_ns):
            if side.node is not None:
                label = side.compares(r.publisher.partition(":")[0], r.topic.rpartition("/")[2])
                if label is not None and r.schema in _RAW:
                    lives.n_compared += 1
                    side.recorded_later(label, r.sequence, r.payload, now_ns)
                side.release(now_ns)  # what handle() does with a record it does not match
            continue
        if r.recovered and side.node is not None:
            # a restarted recorder wrote what it recovered from the caches as it came, key by
            # key: in that stretch raw measurements and tags are not in the order the time sync
            # took them (a tag before the samples or fixes published before it), so re-stamps
            # of what was read there are not the live ones; the core takes all of it, and is
            # back in step once the stretch has been read
            if recovery and now_ns - recovery[-1][1] <= RECOVERY_GAP_NS:
                recovery[-1][1] = max(recovery[-1][1], now_ns)
            else:
                recovery.append([now_ns, now_ns])
        if side.node is None:
            if r.topic.endswith("/run"):
                run = decode(RunInfo, r.payload)
                start_ns = run.start_epoch_ns
                now_ns = rig_time_ns(r.log_time_ns, start_ns)
                side.start(TimeSyncNode(run))
                for h in held:  # handled at the run's rig time: theirs needed its start
                    side.handle(h.topic, h.schema, h.payload, h.sequence, now_ns)
                held.clear()
            else:
                held.append(r)
                continue
        side.handle(r.topic, r.schema, r.payload, r.sequence, now_ns, r.publisher)
    if side.node is None:
        raise RecordingError(no_run_message(name, records))
    tail = getattr(records, "skipped_tail", None)
    if tail is not None:  # the file's last messages were left out by the reader
        side.release(rig_time_ns(tail[0], start_ns))
        now_ns = rig_time_ns(tail[1], start_ns)
    side.finish(now_ns)
    matcher, late, counts = side.matcher, side.late, side.counts
    # a difference of what was read in a stretch a restarted recorder recovered is not one
    recovered = matcher.excuse(lambda t: any(lo <= t <= hi for lo, hi in recovery))
    # a recorded re-stamp whose raw measurement the file lacks (lost while no recorder wrote, the
    # re-stamp recovered from the time sync's cache): nothing to recompute it from
    no_raw = [k for k in matcher.recorded_pending if (_sensor_of(k[0]), k[1]) not in side.raw_seen]
    for k in no_raw:
        del matcher.recorded_pending[k]
    # a restarted time sync's re-stamps of a sensor whose named first input the file lacks (or
    # held too far from its event): no core here took them, not verifiable
    unfed = {life.label(s) for life in side.lives.values() for s in life.waiting}
    not_fed = [k for k in matcher.recorded_pending if k[0] in unfed]
    for k in not_fed:
        del matcher.recorded_pending[k]
    not_compared = lives.n_later - lives.n_compared
    strict = _first_difference(matcher, late, list(matcher.recorded_pending))
    early = matcher.pending_before(now_ns - TAIL_NS)
    if_cut = _first_difference(matcher, late, early)
    if if_cut is None and matcher.n_recorded == 0:
        if_cut = "the part of the file that exists holds no synced/<sensor> outputs to compare"
    if strict is None and matcher.n_recorded == 0:
        strict = "the recording holds no synced/<sensor> outputs to compare"
    unverified = len(matcher.recorded_pending) - len(early)
    return TimesyncRerun(
        counts["meas"],
        counts["tags"],
        counts["out"],
        matcher.n_recorded + not_compared,
        strict,
        if_cut,
        unverified=unverified,
        recovered=recovered,
        no_raw=len(no_raw),
        restarted=not_compared + len(not_fed),
        restarts_s=lives.times_s(),
        restarted_compared=lives.n_compared - len(not_fed),
        early_releases=early_releases,
        inbox_dropped=sum(dropped.values()),
    )


def _first_difference(
    matcher: Matcher, late: list[tuple[int, tuple[str, int]]], pending: list[tuple[str, int]]
) -> str | None:
    """The first difference in file order, among differing, missing and too-late recorded outputs."""
    candidates: list[tuple[int, str]] = [matcher.first] if matcher.first is not None else []
    if pending:
        order, (sensor, seq) = min((matcher.recorded_pending[k][0], k) for k in pending)
        text = f"synced/{sensor} seq {seq}: recorded but not recomputed ({len(pending)} such outputs)"
        candidates.append((order, text))
    if late:
        order, (sensor, seq) = late[0]
        candidates.append(
            (
                order,
                f"synced/{sensor} seq {seq}: recorded more than {HORIZON_NS / 1e9:g} s of log time after "
                f"its measurement was re-stamped ({len(late)} such outputs)",
            )
        )
    return min(candidates)[1] if candidates else None


def timesync_topic(topic: str) -> bool:
    """The topics ``rerun_timesync_records`` does more with than read their log time (time
    tags, raw and re-stamped measurements, the run, and any topic not of four parts, which it
    treats apart): what a filtered reader must give it (``SessionStream(keep=...)``)."""
    parts = topic.split("/")
    return (
        len(parts) != 4
        or parts[2] in ("timetag", "sensor", "synced")
        or topic.endswith("/run")
        or topic.endswith("/event/supervisor")  # a restarted time sync's ``service_restarted``
        or topic.endswith("/event/timesync")  # and its ``first_input`` events
        or topic.endswith("/status/timesync")  # what its inbox dropped
    )


def rerun_timesync(session: Session) -> TimesyncRerun:
    return rerun_timesync_records(session.records, str(session.path))


def rerun_timesync_report(
    path: str,
    verify: bool,
    on_progress: Callable[[int, int], None] | None = None,
    worker: bool | None = None,
) -> tuple[int, list[str]]:
    stream = SessionStream(path, on_progress, follow_parts=True, keep=timesync_topic)
    res = rerun_timesync_records(stream, path, worker)
    lines = [
        f"rerun timesync: {res.measurements} raw measurements, {res.timetags} time tags, "
        f"{res.n_recomputed} re-stamps recomputed, {res.n_recorded} recorded"
    ]
    many = session_note(stream.paths, "reran")
    lines += [f"note: {n}" for n in ([many] if many else []) + cut_notes(stream.cut_files)]
    lines += truncation_notes(res, stream.truncated, "re-stamps", "their raw measurement")
    if res.no_raw:
        lines.append(
            f"note: {res.no_raw} recorded re-stamps have no raw measurement in the recording (lost while "
            "no recorder was writing; hil info shows the gaps in sensor/*): not verifiable"
        )
    lines += restart_note(res) + unjournaled_notes(res)
    if res.recovered:
        lines.append(
            f"note: {res.recovered} re-stamps differ of measurements a restarted recorder recovered from "
            "the publishers' caches (it wrote them as they came, key by key, not in the order the time "
            "sync took them with its tags): not verifiable, not counted as differences"
        )
    return verdict(res, stream.truncated, lines, verify, "re-stamps")

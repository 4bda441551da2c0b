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

Also not covered: a measurement the live service released by its *idle* flush (a sensor silent for
``IDLE_FLUSH_S`` while the core held samples around a suspected clock step) was stamped with the
mapping of that wall-clock moment, which a recording cannot tell; verify then names it.
"""

from __future__ import annotations

from collections.abc import Callable, Iterable
from dataclasses import dataclass

import msgspec

from hil.messages import RunInfo, TimeTag, decode, encode, schema_name
from hil.nodes.base import Out
from hil.nodes.timesync import TimeSyncNode
from hil.record.matching import TAIL_NS, Matcher, truncation_notes, verdict
from hil.record.mcapio import Record, RecordingError, Session, SessionStream, no_run_message, rig_time_ns
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

    def first_difference(self, truncated: bool = False) -> str | None:
        return self.difference_if_cut if truncated else self.difference


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


HORIZON_NS = 60_000_000_000  # log time a re-stamp waits for its recorded copy before it is let go
# A file cut short: a re-stamp can be recorded before its raw measurement (they come from two
# processes), so the cut may keep the one and lose the other; within this much log time of the
# end such an output is not verifiable, and not a failure.


def rerun_timesync_records(records: Iterable[Record], name: str = "recording") -> TimesyncRerun:
    """Feed time tags and raw measurements, in file order, through a fresh time-sync node.

    Streams: the records before the run's ``RunInfo`` (which configures the core) are held until
    it comes; after that only re-stamps waiting for their recorded copy (or the other way round)
    are held (``Matcher``), and a re-stamp nobody recorded is let go after ``HORIZON_NS`` of log
    time. A recorded copy that comes even later is reported as a difference, never skipped.
    """
    node: TimeSyncNode | None = None
    held: list[Record] = []
    matcher = Matcher(_synced_difference, "recorded", HORIZON_NS)
    late: list[tuple[int, tuple[str, int]]] = []  # recorded after their re-stamp was let go
    counts = {"meas": 0, "tags": 0, "out": 0, "order": 0}
    now_ns = 0

    def keep(outs: list[Out]) -> None:
        for _key, m in outs:
            matcher.recomputed((m.sensor, m.seq), encode(m), -1, now_ns)
            counts["out"] += 1

    # topic -> (kind, sensor, the node's key): split once per topic, not per record
    routes: dict[str, tuple[str, str, str] | None] = {}

    def route(topic: str) -> tuple[str, str, str] | None:
        parts = topic.split("/")
        if len(parts) != 4:
            return None
        kind, sensor = parts[2], parts[3]
        return kind, sensor, f"{kind}/{sensor}"

    def handle(r: Record) -> None:
        assert node is not None
        topic = r.topic
        if topic in routes:
            rt = routes[topic]
        else:
            rt = routes[topic] = route(topic)
        if rt is None:
            return
        kind, sensor, key = rt
        if kind == "timetag":
            keep(node.on_message(key, decode(TimeTag, r.payload), now_ns))
            counts["tags"] += 1
        elif kind == "sensor" and r.schema in _RAW:
            keep(node.on_message(key, decode(_RAW[r.schema], r.payload), now_ns))
            counts["meas"] += 1
        elif kind == "synced" and r.schema in _RAW:
            pair = (sensor, r.sequence)
            counts["order"] += 1
            if pair in matcher.released:
                late.append((counts["order"], pair))
            matcher.recorded(pair, r.payload, counts["order"], now_ns)  # rig time, as now_ns below
        matcher.release_before(now_ns)

    start_ns = 0
    for r in records:
        if r.skipped_log_ns >= 0 and node is not None:  # what handle() of those would have done
            matcher.release_before(rig_time_ns(r.skipped_log_ns, start_ns))
        if r.foreign:  # the live time sync refused a stranger's measurements and tags
            continue
        now_ns = rig_time_ns(r.log_time_ns, start_ns)
        if node is None:
            if r.topic.endswith("/run"):
                run = decode(RunInfo, r.payload)
                start_ns = run.start_epoch_ns
                now_ns = rig_time_ns(r.log_time_ns, start_ns)
                node = TimeSyncNode(run)
                for h in held:
                    handle(h)
                held.clear()
            else:
                held.append(r)
                continue
        handle(r)
    if node is None:
        raise RecordingError(no_run_message(name, records))
    tail = getattr(records, "skipped_tail", None)
    if tail is not None:  # the file's last messages were left out by the reader
        matcher.release_before(rig_time_ns(tail[0], start_ns))
        now_ns = rig_time_ns(tail[1], start_ns)
    keep(node.finish(now_ns))
    strict = _first_difference(matcher, late, list(matcher.recorded_pending))
    early = matcher.pending_before(now_ns - TAIL_NS)
    if_cut = _first_difference(matcher, late, early)
    if if_cut is None and matcher.n_recorded == 0:
        if_cut = "the part of the file that exists holds no synced/<sensor> outputs to compare"
    if strict is None and matcher.n_recorded == 0:
        strict = "the recording holds no synced/<sensor> outputs to compare"
    unverified = len(matcher.recorded_pending) - len(early)
    return TimesyncRerun(
        counts["meas"], counts["tags"], counts["out"], matcher.n_recorded, strict, if_cut, unverified
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
    return len(parts) != 4 or parts[2] in ("timetag", "sensor", "synced") or topic.endswith("/run")


def rerun_timesync(session: Session) -> TimesyncRerun:
    return rerun_timesync_records(session.records, str(session.path))


def rerun_timesync_report(
    path: str, verify: bool, on_progress: Callable[[int, int], None] | None = None
) -> tuple[int, list[str]]:
    stream = SessionStream(path, on_progress, follow_parts=True, keep=timesync_topic)
    res = rerun_timesync_records(stream, path)
    lines = [
        f"rerun timesync: {res.measurements} raw measurements, {res.timetags} time tags, "
        f"{res.n_recomputed} re-stamps recomputed, {res.n_recorded} recorded"
    ]
    if len(stream.paths) > 1:
        lines.append(f"note: the recording is split: reran its {len(stream.paths)} parts in order")
    lines += truncation_notes(res, stream.truncated, "re-stamps", "their raw measurement")
    return verdict(res, stream.truncated, lines, verify, "re-stamps")

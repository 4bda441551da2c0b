"""What a recording holds: channels, types, counts, rates, duration, sequence gaps, accuracy.

The rig's traffic only: messages on channels marked ``origin: foreign`` (a publisher that is not
one of the rig's processes, ``hil.bus.identity``) are summed up on a line of their own and never
counted as the rig's loss, rate or accuracy. Duration and rates come from ``log_time`` (when the
recorder received a message, on the rig clock), not from the stamps a message claims: one stamped
10⁶ s ahead does not make a one-minute session last eleven days.
"""

from __future__ import annotations

import json
from array import array
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from hil.messages import SEQ_GENERATION_SHIFT, payload_seq
from hil.record.completeness import Completeness
from hil.record.mcapio import (
    RESTART_PART_NAME,
    FilePart,
    Record,
    RecordingError,
    Session,
    file_halves,
    iter_records,
    next_in_session,
    session_files,
    session_first_path,
    split_first_path,
    stream_session,
    summary_metadata,
)


def record_seq(r: Record) -> int:
    """The message's own ``seq``. MCAP's ``sequence`` field holds only its low 32 bits, which
    drops the restart generation (``hil.messages.SEQ_GENERATION_SHIFT``): a restarted publisher
    would read as repeating its seqs. ~1 us per message; a payload without one falls back."""
    try:
        return payload_seq(r.payload)
    except (msgspec.DecodeError, msgspec.ValidationError):
        return r.sequence


@dataclass
class ChannelInfo:
    topic: str
    schema: str
    count: int
    rate_hz: float
    first_ns: int
    last_ns: int
    missing: int
    duplicates: int
    restarts: int = 0


def stream_rate_hz(n: int, first_log_ns: int, last_log_ns: int, first_pub_ns: int, last_pub_ns: int) -> float:
    """A topic's rate over its messages' own times (``publish_time``: start epoch + the message's
    time of validity), not over when the recorder took them: the time sync releases the ~3 s it
    held before its first lock at once, so ``synced/imu`` of a 400 Hz IMU came out as 571 Hz over
    its log times. A raw channel's publish time is its receive time, the same thing; a topic
    whose publish times do not advance (a foreign writer's zeros) falls back to its log times."""
    if n < 2:
        return 0.0
    span = last_pub_ns - first_pub_ns
    if span <= 0:
        span = last_log_ns - first_log_ns
    return (n - 1) / (span * 1e-9) if span > 0 else 0.0


class _SeqRuns:
    """Each topic's seqs as runs of consecutive ones, ``[first, n]``, in file order: what the
    second reader of a file gives the first, which counts them after its own (``_merge``)."""

    def __init__(self) -> None:
        self.topics: dict[str, list[list[int]]] = {}

    def see(self, topic: str, seq: int) -> None:
        runs = self.topics.get(topic)
        if runs is None:
            self.topics[topic] = [[seq, 1]]
            return
        run = runs[-1]
        if seq == run[0] + run[1] and seq >> SEQ_GENERATION_SHIFT == run[0] >> SEQ_GENERATION_SHIFT:
            run[1] += 1
        else:
            runs.append([seq, 1])


class Summary:
    """One pass over a recording's messages, keeping what ``describe`` and ``info`` print and no
    message: a 12000 s session is 36 M messages, and holding them (``read_session``) took 18.9 GB.
    ``accuracy``: also the truth and every estimator's horizontal position, as float arrays.
    ``runs``: the seqs kept as runs (``_SeqRuns``) instead of counted: a part of a file read after
    another, whose counts they join (``_merge``)."""

    def __init__(self, accuracy: bool = True, runs: bool = False) -> None:
        self.accuracy = accuracy
        self.comp = Completeness()
        self.runs = _SeqRuns() if runs else None
        self.spans: dict[str, list[int]] = {}
        self.schemas: dict[str, str] = {}
        self.counts: dict[str, int] = {}
        self.foreign_topics: dict[str, int] = {}
        self.publishers: set[str] = set()
        self.truth: tuple[array[int], array[float], array[float]] = (array("q"), array("d"), array("d"))
        self.nav: dict[str, tuple[array[int], array[float], array[float]]] = {}
        self.fusion_status: bytes | None = None  # the fusion's last status (``fusion_refusals``)

    def add(self, r: Record) -> None:
        self.add_many((r,))

    def add_many(self, records: Iterable[Record]) -> None:
        """Each record in turn, as it is read (a chunk's at once: ``stream_session(on_batch=)``):
        the lookups hoisted out of the loop, a 12000 s file is 36 M records."""
        spans, counts, accuracy = self.spans, self.counts, self.accuracy
        see = self.comp.see if self.runs is None else self.runs.see
        for r in records:
            topic = r.topic
            if r.foreign:
                self.foreign_topics[topic] = self.foreign_topics.get(topic, 0) + 1
                self.publishers.add(r.publisher)
                continue
            see(topic, record_seq(r))
            t, p = r.log_time_ns, r.publish_time_ns
            sp = spans.get(topic)
            if sp is None:
                spans[topic] = [t, t, p, p]
                self.schemas[topic] = r.schema
                counts[topic] = 1
            else:
                if t < sp[0]:
                    sp[0] = t
                elif t > sp[1]:  # (t < first <= last: never both)
                    sp[1] = t
                if p < sp[2]:
                    sp[2] = p
                elif p > sp[3]:
                    sp[3] = p
                counts[topic] += 1
            if not accuracy:
                continue
            schema = r.schema
            if schema == "hil.Truth":
                self._row(self.truth, r.decode())
            elif schema == "hil.NavSolution":
                m = r.decode()
                rows = self.nav.get(m.estimator)  # type: ignore[attr-defined]
                if rows is None:
                    rows = self.nav[m.estimator] = (array("q"), array("d"), array("d"))  # type: ignore[attr-defined]
                self._row(rows, m)
            elif schema == "hil.ServiceStatus" and topic.endswith("/status/fusion"):
                self.fusion_status = r.payload  # the last one's counters cover the run

    @staticmethod
    def _row(rows: tuple[array[int], array[float], array[float]], m: Any) -> None:
        rows[0].append(m.stamp_ns)
        rows[1].append(m.pos_ned_m[0])
        rows[2].append(m.pos_ned_m[1])

    def channel_infos(self) -> list[ChannelInfo]:
        """Per topic, the rig's messages (foreign ones left out: ``foreign_summary``)."""
        out = []
        for topic in sorted(self.counts):
            a, b, pa, pb = self.spans[topic]
            n = self.counts[topic]
            rate = stream_rate_hz(n, a, b, pa, pb)
            tr = self.comp.topics[topic]
            out.append(
                ChannelInfo(topic, self.schemas[topic], n, rate, a, b, tr.missing, tr.duplicates, tr.restarts)
            )
        return out

    def fusion_refusals(self) -> list[str]:
        """``fusion_refusals`` of this file's last fusion status (none when it holds none)."""
        counts = status_counters(self.fusion_status)
        return [] if counts is None else fusion_refusals(counts)

    def foreign_summary(self) -> dict[str, object]:
        """What publishers that are not the rig's sent: messages per topic, and who."""
        topics = self.foreign_topics
        return {"messages": sum(topics.values()), "publishers": sorted(self.publishers), "topics": topics}

    def estimator_errors(self) -> dict[str, dict[str, float]]:
        """Horizontal position error of every estimator vs truth (interpolated at the solution stamps)."""
        if len(self.truth[0]) < 2:
            return {}
        tt = np.asarray(self.truth[0], dtype=np.float64)
        tn, te = (np.frombuffer(c, dtype=np.float64) for c in self.truth[1:])
        out: dict[str, dict[str, float]] = {}
        for name, (ts, pn, pe) in self.nav.items():
            t = np.asarray(ts, dtype=np.float64)
            ok = (t >= tt[0]) & (t <= tt[-1])
            if not ok.any():
                continue
            dn = np.frombuffer(pn, dtype=np.float64)[ok] - np.interp(t[ok], tt, tn)
            de = np.frombuffer(pe, dtype=np.float64)[ok] - np.interp(t[ok], tt, te)
            h = np.hypot(dn, de)
            out[name] = {
                "n": float(ok.sum()),
                "rms_m": float(np.sqrt(np.mean(h**2))),
                "p95_m": float(np.percentile(h, 95)),
                "max_m": float(h.max()),
                "final_m": float(h[-1]),
            }
        return out


def summarise(records: Iterable[Record], accuracy: bool = True) -> Summary:
    s = Summary(accuracy)
    for r in records:
        s.add(r)
    return s


def channel_infos(session: Session) -> list[ChannelInfo]:
    """Per topic, the rig's messages (foreign ones left out: ``foreign_summary``)."""
    return summarise(session.records, accuracy=False).channel_infos()


def foreign_summary(session: Session) -> dict[str, object]:
    """What publishers that are not the rig's sent: messages per topic, and who."""
    return summarise(session.records, accuracy=False).foreign_summary()


def estimator_errors(session: Session) -> dict[str, dict[str, float]]:
    """Horizontal position error of every estimator vs truth (interpolated at the solution stamps)."""
    return summarise(session.records).estimator_errors()


# from this size on a file is read by two processes at once, each half of it (on two CPUs and
# where fork exists). Reading and counting, one pass against two halves (2026-12-06): 41 MB
# 1.58 against 0.82 s, 28 MB 0.89 against 0.48 s, 12 MB 0.36 against 0.20 s, 1.3 MB 40 against
# 29 ms; below a few MB a fork is not worth a process
PARALLEL_MIN_BYTES = 4 * 2**20


def _scan(
    path: str | Path, *, derived: bool, accuracy: bool, parallel: bool = False
) -> tuple[Summary, Session]:
    """The file streamed once into a Summary; the Session holds its metadata and truncation.
    ``parallel``: a large finished file is read in two halves at once (``_scan_halves``)."""
    halves = _halves(path) if parallel else None
    if halves is not None:
        return _scan_halves(path, halves, derived=derived, accuracy=accuracy)
    summary = Summary(accuracy)
    return summary, stream_session(path, summary.add, derived=derived, on_batch=summary.add_many)


def _halves(path: str | Path) -> tuple[FilePart, FilePart] | None:
    from hil.runners.sim_worker import worker_possible

    try:
        big = Path(path).stat().st_size >= PARALLEL_MIN_BYTES
    except OSError:
        return None
    return file_halves(path) if big and worker_possible() else None


def _scan_part(
    path: str | Path, part: FilePart, derived: bool, accuracy: bool, runs: bool = True
) -> tuple[Summary, Session]:
    """A part of the file; ``runs``: its seqs as runs, not yet counted (the second half, in a
    forked process)."""
    summary = Summary(accuracy, runs=runs)
    return summary, stream_session(path, summary.add, derived=derived, on_batch=summary.add_many, part=part)


def _scan_part_or_damage(
    path: str | Path, part: FilePart, derived: bool, accuracy: bool
) -> tuple[Summary, Session] | RecordingError:
    """``_scan_part`` in the forked reader: damage there, or a payload that does not decode,
    comes back as the error itself, so the caller raises the one line one pass would (a failure
    of any other kind is a WorkerError)."""
    try:
        return _scan_part(path, part, derived, accuracy)
    except RecordingError as err:
        return err


def _scan_halves(
    path: str | Path, halves: tuple[FilePart, FilePart], *, derived: bool, accuracy: bool
) -> tuple[Summary, Session]:
    """The first half here while a forked process reads the second; then the second's figures
    added to the first's as if read after them (the very figures of one pass)."""
    from hil.runners.sim_worker import ForkedCall
    from hil.runtime.errors import WorkerError

    first, second = halves
    try:
        later = ForkedCall("second-half reader", _scan_part_or_damage, path, second, derived, accuracy)
    except OSError:  # no process to be had: one pass
        return _scan(path, derived=derived, accuracy=accuracy)
    try:
        summary, session = _scan_part(path, first, derived, accuracy, runs=False)
        if session.truncated:  # one pass stops at the damage: what follows is not read (closed)
            return summary, session
        answer = later.result()
        if isinstance(answer, RecordingError):
            raise answer
        rest, rest_session = answer
    except WorkerError:  # a half that says nothing alone (an error there), or a reader that died
        return _scan(path, derived=derived, accuracy=accuracy)
    finally:
        later.close()
    _merge(summary, rest)
    for name, meta in rest_session.metadata.items():
        session.metadata[name] = meta
    session.attachments.update(rest_session.attachments)
    session.truncated, session.truncation_reason = rest_session.truncated, rest_session.truncation_reason
    return summary, session


def _merge(summary: Summary, rest: Summary) -> None:
    """``rest`` (read after ``summary``'s messages, its seqs as runs) into ``summary``."""
    assert rest.runs is not None
    for topic, runs in rest.runs.topics.items():
        for first, n in runs:
            summary.comp.see_run(topic, first, n)
    for topic, (a, b, pa, pb) in rest.spans.items():
        sp = summary.spans.get(topic)
        if sp is None:
            summary.spans[topic] = [a, b, pa, pb]
            summary.schemas[topic] = rest.schemas[topic]
            summary.counts[topic] = rest.counts[topic]
        else:
            sp[0], sp[1] = min(sp[0], a), max(sp[1], b)
            sp[2], sp[3] = min(sp[2], pa), max(sp[3], pb)
            summary.counts[topic] += rest.counts[topic]
    summary.fusion_status = rest.fusion_status or summary.fusion_status
    for topic, n in rest.foreign_topics.items():
        summary.foreign_topics[topic] = summary.foreign_topics.get(topic, 0) + n
    summary.publishers |= rest.publishers
    for mine, theirs in zip(summary.truth, rest.truth, strict=True):
        mine.extend(theirs)  # type: ignore[arg-type]
    for name, rows in rest.nav.items():
        mine_rows = summary.nav.setdefault(name, (array("q"), array("d"), array("d")))
        for mine, theirs in zip(mine_rows, rows, strict=True):
            mine.extend(theirs)  # type: ignore[arg-type]


def _parts_lines(path: Path, part: dict[str, str]) -> list[str]:
    """Where the file stands in a split recording: the further parts it continues in, or, for a
    later part, which one it is (``hil info`` describes the one file it is given)."""
    index = part.get("index", "0")
    if index != "0":
        n = int(index) if index.isdigit() else 0
        first = session_first_path(path, n)
        if RESTART_PART_NAME.search(split_first_path(path, n).stem):
            return [
                f"parts:     part {index} of a restarted recorder's split file, after "
                f"{part.get('previous', '?')}, continuing the session begun in {first.name} (hil rerun, "
                "replay, report and export of that file read the whole session)"
            ]
        return [
            f"parts:     part {index} of a split recording, after {part.get('previous', '?')} (the run and "
            f"the whole session: its first file)"
        ]
    if RESTART_PART_NAME.search(path.stem):
        first = session_first_path(path)
        return [
            f"parts:     a restarted recorder's file, continuing the session begun in {first.name} "
            f"(hil rerun, replay, report and export of that file read the whole session)"
        ]
    more = session_files(path)[1:]
    if not more:
        return []
    names = ", ".join(p.name for p in more)
    restarted = " (a restarted recorder's)" if any(RESTART_PART_NAME.search(p.stem) for p in more) else ""
    return [
        f"parts:     the session continues in {len(more)} more part(s){restarted}: {names} (hil rerun, "
        f"replay, report and export read them all; hil merge joins them)"
    ]


def _session_line(path: Path, index: str) -> list[str]:
    """Of a session's first file, when more follow: the session's loss, from the completeness of
    its last file, which covers all of it (this file's covers itself, or is missing)."""
    if index != "0" or RESTART_PART_NAME.search(path.stem):
        return []
    files = session_files(path)
    if len(files) < 2:
        return []
    comp = summary_metadata(files[-1], "completeness")
    if comp is None:  # the last file is cut short too: no summary to read it from
        return [f"session:   its last file, {files[-1].name}, has no completeness summary (cut short)"]
    return [
        f"session:   missing={comp.get('missing')} replay_ready={comp.get('replay_ready')} over all "
        f"{len(files)} files (the completeness of its last, {files[-1].name})"
    ]


def status_counters(payload: bytes | None) -> dict[str, int] | None:
    """A recorded ``ServiceStatus``'s counters; None for none, or one that does not read (it
    then says nothing here)."""
    if payload is None:
        return None
    from hil.messages import ServiceStatus, decode

    try:
        return decode(ServiceStatus, payload).counter_map()
    except ValueError:  # msgspec's errors
        return None


def _is_fusion_status(topic: str) -> bool:
    return topic.endswith("/status/fusion")


def last_fusion_status(files: Sequence[Path]) -> tuple[bytes, Path] | None:
    """The last fusion status of a session's ``files`` (in order) and the file that holds it, or
    None. Its counters count from the fusion's start, so the session's last one covers the run,
    whichever part the recorder had rotated to (a split session's first file holds only the
    status of its first stretch). Read from the last file back, each only for that topic; a file
    that cannot be read says nothing, and the one before it is asked."""
    for path in reversed(files):
        last = None
        try:
            for kind, r in iter_records(path, keep=_is_fusion_status):
                if kind == "message" and r.schema == "hil.ServiceStatus":
                    last = r.payload
        except (RecordingError, OSError):
            continue
        if last is not None:
            return last, path
    return None


#: the share of a source's inputs a fusion may refuse as late before the run is said not to have
#: navigated on it (the IMU's: of all it took)
LATE_SHARE = 0.1


def fusion_refusals(counts: Mapping[str, int]) -> list[str]:
    """What a fusion that refused much of an input as late did (its status counters), one line
    a source; none for a fusion that fused its inputs. ``hil info`` says them; ``hil up`` and
    ``hil sim`` also exit 1 for them, a run that did not navigate being no success.

    The IMU: a tenth or more of its samples (of all the inputs it took): its horizon ran ahead of
    the samples' stamps, and its solutions thin out or stop while every service stays up.
    An aiding source (GNSS): a tenth or more of the fixes handed to it (``inputs.<sensor>``,
    taken or refused) came behind its horizon -- later after their time of validity than its
    lag -- and the estimators went without them, as in an outage that never ends. A GNSS outage
    is no refusal: the fixes that never came are not counted. A status without
    ``inputs.<sensor>`` (a fusion before that counter) is judged on the IMU alone."""
    out = []
    late, consumed = counts.get("dropped_late.imu", 0), counts.get("consumed", 0)
    if late and late >= LATE_SHARE * (late + consumed):
        out.append(
            f"refused {late} IMU samples as late (dropped_late.imu) and took {consumed} "
            "inputs: its horizon ran ahead of their stamps, so its solutions thin out or stop; "
            "event/fusion says when (latency_over_bound)"
        )
    from hil.sensor_table import SENSOR_NAMES, SENSORS

    lag_ms = counts.get("horizon_lag_ms")
    lag = f" ({lag_ms} ms, horizon_lag_ms)" if lag_ms is not None else ""
    for sensor in SENSOR_NAMES:
        n, late = counts.get(f"inputs.{sensor}"), counts.get(f"dropped_late.{sensor}", 0)
        if SENSORS[sensor].paces_fusion or n is None or not late or late < LATE_SHARE * n:
            continue
        what = "GNSS fixes" if sensor == "gnss" else f"{sensor} inputs"
        out.append(
            f"refused {late} of its {n} {what} as late (dropped_late.{sensor}): they reached it more "
            f"than its lag{lag} after their time of validity, so its estimators went without them; "
            f"raise the fusion's lag (--fusion-lag, lag_s) above the receiver's latency "
            "(event/fusion: latency_over_bound)"
        )
    return out


def _fusion_verdict(path: Path, index: str, summary: Summary) -> tuple[list[str], str]:
    """The fusion's refusals (``fusion_refusals``) and, when they are not this file's, where its
    status was read. Of a session's first file, which stands for the run (its exit code, ``hil
    up``'s description), the session's last fusion status wherever it is
    (``last_fusion_status``); of a later part, its own: its counters as they stood at its end."""
    if index == "0" and not RESTART_PART_NAME.search(path.stem):
        later = last_fusion_status(session_files(path)[1:])
        if later is not None:
            counts = status_counters(later[0])
            refused = [] if counts is None else fusion_refusals(counts)
            return refused, f" (the session's last fusion status, in {later[1].name})"
    return summary.fusion_refusals(), ""


def describe(
    path: str, *, accuracy: bool = True, parallel: bool = False, verdicts: list[str] | None = None
) -> str:
    """What ``hil info`` prints. ``parallel``: a large file read by two processes at once (a
    command's own process, which may fork: not a live rig's supervisor). ``verdicts``: where
    the run's failings it finds are added (the fusion's ``fusion_refusals``), for an exit code."""
    summary, s = _scan(path, derived=True, accuracy=accuracy, parallel=parallel)  # Foxglove's listed too
    infos = summary.channel_infos()
    t0 = min((c.first_ns for c in infos), default=0)
    t1 = max((c.last_ns for c in infos), default=0)
    lines = [f"file:      {path}"]
    meta = s.metadata.get("hil", {})
    if meta:
        lines.append(
            f"run:       rig={meta.get('rig')} scenario={meta.get('scenario')} seed={meta.get('seed')} "
            f"speed={meta.get('speed')} executor={meta.get('executor')} version={meta.get('version')}"
        )
    n_rig = sum(c.count for c in infos)
    lines.append(f"duration:  {(t1 - t0) * 1e-9:.3f} s   messages: {n_rig}   channels: {len(infos)}")
    lines += _parts_lines(Path(path), s.metadata.get("part", {}))
    foreign = summary.foreign_summary()
    if foreign["messages"]:
        topics = foreign["topics"]
        assert isinstance(topics, dict)
        names = ", ".join(f"{t.split('/', 2)[-1]} x{n}" for t, n in sorted(topics.items())[:6])
        more = f" (+{len(topics) - 6} topics)" if len(topics) > 6 else ""
        lines.append(
            f"foreign:   {foreign['messages']} messages from {len(foreign['publishers'])} publisher(s) that "  # type: ignore[arg-type]
            f"are not the rig's, recorded but not counted: {names}{more}"
        )
    start = meta.get("start_epoch_ns")
    if start is not None and start.lstrip("-").isdigit():
        when = datetime.fromtimestamp(int(start) / 1e9, tz=UTC).isoformat(timespec="milliseconds")
        base = (
            "MCAP log/publish times = start + rig time"
            if meta.get("time_base") == "epoch"
            else "MCAP log/publish times are rig time (recorded before the wall-clock timeline)"
        )
        lines.append(f"start:     {when.replace('+00:00', 'Z')} (rig time zero; {base})")
    index = s.metadata.get("part", {}).get("index", "0")
    after = next_in_session(Path(path), int(index) if index.isdigit() else 0)
    if s.truncated and after is not None:  # a killed recorder's, continued by its restarted one
        lines.append(
            f"CUT SHORT: read up to the last complete chunk ({s.truncation_reason}): its recorder was "
            f"killed, and the session continues in {after.name}"
        )
    elif s.truncated:
        lines.append(f"TRUNCATED: read up to the last complete chunk ({s.truncation_reason})")
    recovered = recovered_line(s.metadata.get("recovered"))
    if recovered:
        lines.append(recovered)
    comp = s.metadata.get("completeness")
    if comp:
        extra = ""
        if "zenoh_missed" in comp:
            extra += f" zenoh_missed={comp.get('zenoh_missed')}"
        for what in ("zenoh_unsequenced", "unwritten_at_stop", "dropped_rig"):  # when they say something
            if comp.get(what) not in (None, "0"):
                extra += f" {what}={comp.get(what)}"
        if comp.get("rig_identity") == "unknown":
            extra += " rig_identity=unknown"
        if comp.get("stopped_at_s") is not None:  # hil sim stopped before its duration (Ctrl-C)
            extra += f" stopped_at_s={comp.get('stopped_at_s')}"
        if comp.get("parts") not in (None, "1"):
            extra += f" split part={comp.get('part')}"
        lines.append(
            f"recorder:  missing={comp.get('missing')}{extra} replay_ready={comp.get('replay_ready')}"
        )
    elif s.truncated and after is not None:
        lines.append(
            "recorder:  no completeness summary here (the session's last file has it, for all of it)"
        )
    else:
        lines.append("recorder:  no completeness summary (the recorder did not finish the file)")
    lines += _session_line(Path(path), index)
    refused, held_in = _fusion_verdict(Path(path), index, summary)
    for line in refused:
        lines.append(f"fusion:    {line}{held_in}")
        if verdicts is not None:
            verdicts.append(f"the fusion {line}")
    restarted = [c for c in infos if c.restarts]
    if restarted:
        # a restart is its own fact, not loss: the publisher counts again in a new generation
        names = ", ".join(
            f"{c.topic.split('/', 2)[-1]}" + (f" x{c.restarts}" if c.restarts > 1 else "") for c in restarted
        )
        lines.append(f"restarts:  {len(restarted)} publisher(s) restarted during the recording: {names}")
    lines.append("")
    rst = f" {'restarts':>8}" if restarted else ""
    lines.append(f"{'topic':<33} {'type':<24} {'count':>7} {'rate Hz':>9} {'gaps':>6} {'dups':>5}{rst}")
    for c in infos:  # a space before every column: a long topic or a large count never runs on
        rst = f" {c.restarts:>8}" if restarted else ""
        row = f"{c.topic:<33} {c.schema:<24} {c.count:>7} {c.rate_hz:>9.2f}"
        lines.append(f"{row} {c.missing:>6} {c.duplicates:>5}{rst}")
    if accuracy:
        errs = summary.estimator_errors()
        if errs:
            lines.append("")
            lines.append(f"{'estimator':<11} {'horiz RMS m':>11} {'95% m':>9} {'max m':>9} {'final m':>9}")
            for name, e in sorted(errs.items()):  # a free INS over hours drifts to 10⁶ m: columns stay apart
                rms, p95, top, final = e["rms_m"], e["p95_m"], e["max_m"], e["final_m"]
                lines.append(f"{name:<11} {rms:>11.2f} {p95:>9.2f} {top:>9.2f} {final:>9.2f}")
    return "\n".join(lines)


def recovered_line(rec: dict[str, str] | None) -> str:
    """What ``hil recover`` wrote of the copy it made (its ``recovered`` metadata), in one line:
    a copy's figures are of what was left, and this says what was not."""
    if not rec:
        return ""
    try:
        lost = json.loads(rec.get("lost", "[]"))
    except ValueError:
        lost = []
    chunks, unread, msgs = rec.get("chunks_lost"), rec.get("bytes_unread", "0"), rec.get("messages_lost")
    if chunks is None:  # a copy from before these counts: its loss lines
        chunks = str(sum(1 for ln in lost if str(ln).startswith("the chunk at byte")))
    what = []
    if chunks != "0":
        what.append(f"{chunks} chunk(s)" + (f" ({msgs} messages)" if msgs else ""))
    if unread != "0":
        what.append(f"{unread} bytes at the end")
    if rec.get("finished") == "false" and unread == "0":
        what.append("the original's summary (its recorder did not finish it)")
    said = f"lost {', '.join(what)}" if what else "nothing lost"
    return f"recovered: a copy hil recover made of {rec.get('from', '?')}; {said}"


def info_json(path: str, *, parallel: bool = False) -> str:
    summary, s = _scan(path, derived=False, accuracy=True, parallel=parallel)
    return json.dumps(
        {
            "channels": [c.__dict__ for c in summary.channel_infos()],
            "foreign": summary.foreign_summary(),
            "truncated": s.truncated,
            "metadata": s.metadata,
            "errors": summary.estimator_errors(),
            # a session's first file: the further parts (split, or a restarted recorder's), in
            # order (a later split part says which it is in its ``part`` metadata)
            "parts": [p.name for p in session_files(path)[1:]],
        },
        indent=2,
    )

"""What a recording holds: channels, types, counts, rates, duration, sequence gaps, accuracy.

The rig's traffic only: messages on channels marked ``origin: foreign`` (a publisher that is not
one of the rig's processes, ``hil.bus.identity``) are summed up on a line of their own and never
counted as the rig's loss, rate or accuracy. Duration and rates come from ``log_time`` (when the
recorder received a message, on the rig clock), not from the stamps a message claims: one stamped
10⁶ s ahead does not make a one-minute session last eleven days.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from datetime import UTC, datetime

import msgspec
import numpy as np

from hil.record.completeness import Completeness
from hil.record.mcapio import Record, Session, read_session


class _Seq(msgspec.Struct):
    seq: int


_SEQ = msgspec.json.Decoder(_Seq)


def record_seq(r: Record) -> int:
    """The message's own ``seq``. MCAP's ``sequence`` field holds only its low 32 bits, which
    drops the restart generation (``hil.messages.SEQ_GENERATION_SHIFT``): a restarted publisher
    would read as repeating its seqs. ~1 us per message; a payload without one falls back."""
    try:
        return _SEQ.decode(r.payload).seq
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


def channel_infos(session: Session) -> list[ChannelInfo]:
    """Per topic, the rig's messages (foreign ones left out: ``foreign_summary``)."""
    comp = Completeness()
    spans: dict[str, list[int]] = {}
    schemas: dict[str, str] = {}
    counts: dict[str, int] = {}
    for r in session.records:
        if r.foreign:
            continue
        comp.see(r.topic, record_seq(r))
        sp = spans.setdefault(r.topic, [r.log_time_ns, r.log_time_ns])
        sp[0] = min(sp[0], r.log_time_ns)
        sp[1] = max(sp[1], r.log_time_ns)
        schemas.setdefault(r.topic, r.schema)
        counts[r.topic] = counts.get(r.topic, 0) + 1
    out = []
    for topic in sorted(counts):
        a, b = spans[topic]
        n = counts[topic]
        rate = (n - 1) / ((b - a) * 1e-9) if n > 1 and b > a else 0.0
        tr = comp.topics[topic]
        out.append(ChannelInfo(topic, schemas[topic], n, rate, a, b, tr.missing, tr.duplicates, tr.restarts))
    return out


def foreign_summary(session: Session) -> dict[str, object]:
    """What publishers that are not the rig's sent: messages per topic, and who."""
    topics: dict[str, int] = {}
    publishers: set[str] = set()
    for r in session.records:
        if r.foreign:
            topics[r.topic] = topics.get(r.topic, 0) + 1
            publishers.add(r.publisher)
    return {"messages": sum(topics.values()), "publishers": sorted(publishers), "topics": topics}


def estimator_errors(session: Session) -> dict[str, dict[str, float]]:
    """Horizontal position error of every estimator vs truth (interpolated at the solution stamps)."""
    truth = [r.decode() for r in session.records if r.schema == "hil.Truth" and not r.foreign]
    if len(truth) < 2:
        return {}
    tt = np.array([t.stamp_ns for t in truth], dtype=np.float64)
    tp = np.array([t.pos_ned_m for t in truth])
    sols: dict[str, list[tuple[int, list[float]]]] = {}
    for r in session.records:
        if r.schema == "hil.NavSolution" and not r.foreign:
            m = r.decode()
            sols.setdefault(m.estimator, []).append((m.stamp_ns, m.pos_ned_m))  # type: ignore[attr-defined]
    out: dict[str, dict[str, float]] = {}
    for name, rows in sols.items():
        t = np.array([s for s, _ in rows], dtype=np.float64)
        p = np.array([q for _, q in rows])
        ok = (t >= tt[0]) & (t <= tt[-1])
        if not ok.any():
            continue
        ref = np.column_stack([np.interp(t[ok], tt, tp[:, i]) for i in range(3)])
        h = np.hypot(*(p[ok, :2] - ref[:, :2]).T)
        out[name] = {
            "n": float(ok.sum()),
            "rms_m": float(np.sqrt(np.mean(h**2))),
            "p95_m": float(np.percentile(h, 95)),
            "max_m": float(h.max()),
            "final_m": float(h[-1]),
        }
    return out


def describe(path: str, *, accuracy: bool = True) -> str:
    s = read_session(path, derived=True)  # the Foxglove channels are listed too
    infos = channel_infos(s)
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
    foreign = foreign_summary(s)
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
    if s.truncated:
        lines.append(f"TRUNCATED: read up to the last complete chunk ({s.truncation_reason})")
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
        if comp.get("parts") not in (None, "1"):
            extra += f" split part={comp.get('part')}"
        lines.append(
            f"recorder:  missing={comp.get('missing')}{extra} replay_ready={comp.get('replay_ready')}"
        )
    else:
        lines.append("recorder:  no completeness summary (the recorder did not finish the file)")
    restarted = [c for c in infos if c.restarts]
    if restarted:
        # a restart is its own fact, not loss: the publisher counts again in a new generation
        names = ", ".join(
            f"{c.topic.split('/', 2)[-1]}" + (f" x{c.restarts}" if c.restarts > 1 else "") for c in restarted
        )
        lines.append(f"restarts:  {len(restarted)} publisher(s) restarted during the recording: {names}")
    lines.append("")
    rst = f"{'restarts':>9}" if restarted else ""
    lines.append(f"{'topic':<34}{'type':<25}{'count':>8}{'rate Hz':>10}{'gaps':>7}{'dups':>6}{rst}")
    for c in infos:
        rst = f"{c.restarts:>9}" if restarted else ""
        lines.append(
            f"{c.topic:<34}{c.schema:<25}{c.count:>8}{c.rate_hz:>10.2f}{c.missing:>7}{c.duplicates:>6}{rst}"
        )
    if accuracy:
        errs = estimator_errors(s)
        if errs:
            lines.append("")
            lines.append(f"{'estimator':<12}{'horiz RMS m':>12}{'95% m':>10}{'max m':>10}{'final m':>10}")
            for name, e in sorted(errs.items()):
                lines.append(
                    f"{name:<12}{e['rms_m']:>12.2f}{e['p95_m']:>10.2f}{e['max_m']:>10.2f}{e['final_m']:>10.2f}"
                )
    return "\n".join(lines)


def info_json(path: str) -> str:
    s = read_session(path)
    return json.dumps(
        {
            "channels": [c.__dict__ for c in channel_infos(s)],
            "foreign": foreign_summary(s),
            "truncated": s.truncated,
            "metadata": s.metadata,
            "errors": estimator_errors(s),
        },
        indent=2,
    )

"""``hil bench horizon``: the delayed fusion horizon and output predictor (issues 22.1 and 20.4).

Two parts, each printed and written as the ``horizon`` section of docs/benchmarks.md:

- **car** (``--car``): car_drive's whole run through ``hil sim`` twice -- the fusion before
  (``--fusion-lag 0.2 --no-output-predictor``: a 0.2 s watermark, the horizon's state published)
  and now (the defaults: a 0.5 s horizon and the output predictor) -- and the *published*
  solutions (``nav/*`` as recorded, not a replay) scored against the scenario's truth:
  horizontal RMS over the whole run after 60 s, after car_drive's GNSS latency event at 350 s,
  through the 420-480 s underpass, and the error at the end; fixes journaled ``late``.
  ``--before FILE --after FILE`` scores two recordings already made.
- **live** (``--live S``): ``hil up`` in real time (the rig clock at speed 1) for S seconds,
  measured from a second Zenoh session on the rig's hub: per source, the latency from capture
  (IMU sample k is captured at ``(k + 1) / rate``) or time of validity (a GNSS fix's stamp) to
  its arrival on ``synced/<sensor>``; per estimator, from the capture of the IMU sample an output
  belongs to (``imu_seq``) to that output's arrival. The probe's clock is the rig clock
  (``RigClock`` on the run's epoch); the load average is read before and after.
"""

from __future__ import annotations

import argparse
import os
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.bench import command_line, write_section
from hil.fusion.core import FREE_INS, parse_journal_id
from hil.messages import FusionJournal, GnssFix, ImuSample, NavSolution, RunInfo
from hil.nav.scenario import scenario_for_run
from hil.nav.trajectory import TruthGenerator
from hil.record.mcapio import SessionStream

SETTLE_S = 60.0
LATENCY_EVENT_S = 350.0
UNDERPASS = (420.0, 480.0)
BEFORE_ARGS = {"lag_s": 0.2, "output_predictor": False}
STARTUP_S = 5.0


# ---------------------------------------------------------------------------------------------
# car_drive: the published solutions against the truth


@dataclass
class Scored:
    """One recording's published solutions, per estimator: stamps (s) and horizontal errors (m)."""

    t_s: dict[str, np.ndarray]
    h_err: dict[str, np.ndarray]
    late_gnss: int
    gnss_fixes: int
    lag_s: float
    predictor: bool


def score_recording(path: Path) -> Scored:
    """The rig's recorded ``nav/*`` outputs against the truth of the recording's scenario."""
    run: RunInfo | None = None
    sols: dict[str, list[tuple[int, float, float]]] = {}
    late: int = 0
    fixes = 0
    lag_s, predictor = float("nan"), False
    for r in SessionStream(path, follow_parts=True):
        if r.foreign:
            continue
        t = r.topic
        if "/nav/" in t:
            m = r.decode()
            assert isinstance(m, NavSolution)
            sols.setdefault(m.estimator, []).append((m.stamp_ns, m.pos_ned_m[0], m.pos_ned_m[1]))
        elif t.endswith("/fusion/journal"):
            j = r.decode()
            assert isinstance(j, FusionJournal)
            for d in j.dropped:
                why, name, _src = parse_journal_id(d)
                late += why == "late" and name.startswith("gnss:")
        elif t.endswith("/synced/gnss"):
            fixes += 1
        elif run is None and t.endswith("/run"):
            run = r.decode()  # type: ignore[assignment]
        elif t.endswith("/fusion/config"):
            from hil.record.rerun import config_of_record

            cfg = config_of_record(r)
            if cfg is not None:
                lag_s, predictor = cfg.lag_s, cfg.output_predictor
    if run is None:
        raise ValueError(f"{path}: no run (hil/<rig>/run)")
    truth = TruthGenerator(scenario_for_run(run))
    t_s: dict[str, np.ndarray] = {}
    h_err: dict[str, np.ndarray] = {}
    for name, rows in sols.items():
        a = np.array(rows, dtype=np.float64)
        stamps = np.array([row[0] for row in rows], dtype=np.int64)
        tb = truth.sample(stamps)
        t_s[name] = stamps * 1e-9
        h_err[name] = np.hypot(a[:, 1] - tb.pos_ned_m[:, 0], a[:, 2] - tb.pos_ned_m[:, 1])
    return Scored(t_s, h_err, late, fixes, lag_s, predictor)


def _rms(x: np.ndarray) -> float:
    return float(np.sqrt(np.mean(np.square(x)))) if len(x) else float("nan")


def _f(x: float) -> str:
    if not np.isfinite(x):
        return "—"
    return f"{x:.3g}" if abs(x) < 1000 else f"{x:,.0f}"


def car_rows(before: Scored, after: Scored) -> list[str]:
    """Per estimator: horizontal RMS (whole run after 60 s / after 350 s / underpass) and the
    error at the end, before → after."""
    lines = [
        "| estimator | whole run after 60 s | after 350 s | underpass 420–480 s | at the end |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    names = [FREE_INS, *sorted(n for n in after.h_err if n != FREE_INS)]
    for name in names:
        cells = []
        for a, b in ((SETTLE_S, 1e9), (LATENCY_EVENT_S, 1e9), UNDERPASS, (None, None)):
            vals = []
            for sc in (before, after):
                if name not in sc.h_err:
                    vals.append("—")
                    continue
                t, e = sc.t_s[name], sc.h_err[name]
                vals.append(_f(float(e[-1])) if a is None else _f(_rms(e[(t >= a) & (t < b)])))
            cells.append(" → ".join(vals))
        lines.append(f"| {name} | {' | '.join(cells)} |")
    return lines


def car_section(before: Scored, after: Scored, how: str) -> str:
    def mode(s: Scored) -> str:
        out = "output predictor" if s.predictor else "the horizon's state published"
        return f"horizon lag {s.lag_s:g} s, {out}"

    return "\n".join(
        [
            "### car_drive: the published solutions, before → after",
            "",
            f"Before: {mode(before)}; {before.late_gnss} of {before.gnss_fixes} GNSS fixes journaled "
            f"late. After: {mode(after)}; {after.late_gnss} of {after.gnss_fixes} late. "
            f"Horizontal error of the recorded `nav/*` against the truth at each output's stamp, m. {how}",
            "",
            *car_rows(before, after),
        ]
    )


# ---------------------------------------------------------------------------------------------
# live: latency per source and per estimator


@dataclass
class LatencyProbe:
    """What a second Zenoh session sees of a running rig: arrival minus capture, per key."""

    rate_hz: int
    run: RunInfo | None = None
    ns: dict[str, list[tuple[int, int]]] = field(default_factory=dict)  # (capture, arrival − capture)
    lock: threading.Lock = field(default_factory=threading.Lock)
    clock: object | None = None

    def on_run(self, run: RunInfo, _k: str) -> None:
        from hil.runtime.clock import RigClock

        self.run = run
        self.clock = RigClock(run.start_epoch_ns, run.speed)

    def _add(self, key: str, capture_ns: int, now_ns: int) -> None:
        with self.lock:
            self.ns.setdefault(key, []).append((capture_ns, now_ns - capture_ns))

    def _now(self) -> int | None:
        clock = self.clock
        return None if clock is None else clock.now_ns()  # type: ignore[attr-defined]

    def on_imu(self, m: ImuSample, _k: str) -> None:
        now = self._now()
        if now is not None:
            self._add("source imu (capture → synced/imu)", (m.seq + 1) * 1_000_000_000 // self.rate_hz, now)

    def on_gnss(self, m: GnssFix, _k: str) -> None:
        now = self._now()
        if now is not None:
            self._add("source gnss (time of validity → synced/gnss)", m.stamp_ns, now)

    def on_nav(self, sol: NavSolution, _k: str) -> None:
        now = self._now()
        if now is not None and sol.imu_seq >= 0:
            capture = (sol.imu_seq + 1) * 1_000_000_000 // self.rate_hz
            self._add(f"nav/{sol.estimator} (IMU capture → output)", capture, now)


def live_run(duration_s: float, rate_hz: int, scenario: str, rig: str) -> tuple[dict[str, np.ndarray], str]:
    """One real-time ``hil up`` with the default estimators; latencies in ms per key, of what was
    captured after the start-up (``STARTUP_S``: the IMU is held until time sync locks, up to
    3.5 s, and then arrives late by design)."""
    from hil.bus.keys import Keys
    from hil.bus.pubsub import Stats, Subscriber
    from hil.bus.session import open_session
    from hil.estimators.registry import DEFAULT_ESTIMATORS
    from hil.runtime.supervisor import Supervisor, UpOptions

    load0 = os.getloadavg()
    with tempfile.TemporaryDirectory() as d:
        sup = Supervisor(
            UpOptions(
                scenario=scenario,
                duration_s=duration_s,
                record=Path(d) / "horizon.mcap",
                rig=rig,
                live=False,
                log_dir=Path(d) / "logs",
                imu_rate_hz=rate_hz,
            )
        )
        probe = LatencyProbe(rate_hz)
        k = Keys(rig)
        cfg = sup.child_bus  # joins the hub as the rig's services do (its per-run secret)
        holder: dict[str, object] = {}

        def attach() -> None:
            time.sleep(0.5)  # the supervisor opens its hub first
            session = open_session(cfg)
            stats = Stats()
            holder["session"] = session
            holder["stats"] = stats
            subs = [
                Subscriber(session, k.run(), RunInfo, probe.on_run, stats),
                Subscriber(session, k.synced("imu"), ImuSample, probe.on_imu, stats),
                Subscriber(session, k.synced("gnss"), GnssFix, probe.on_gnss, stats),
            ]
            subs += [
                Subscriber(session, k.nav(n), NavSolution, probe.on_nav, stats)
                for n in (FREE_INS, *DEFAULT_ESTIMATORS)
            ]
            holder["subs"] = subs

        threading.Thread(target=attach, daemon=True).start()
        rc = sup.run()
        session = holder.get("session")
        if session is not None:
            session.close()  # type: ignore[attr-defined]
    load1 = os.getloadavg()
    st = holder.get("stats")
    if st is not None and getattr(st, "last_error", ""):
        print(f"probe: {st.last_error}")  # type: ignore[attr-defined]
    with probe.lock:
        skip_ns = round(STARTUP_S * 1e9)
        out = {
            key: np.array([late for cap, late in v if cap >= skip_ns], dtype=np.float64) * 1e-6
            for key, v in sorted(probe.ns.items())
        }
    note = (
        f"exit code {rc}; load average (1 min) {load0[0]:.2f} before, {load1[0]:.2f} after "
        f"(5 min {load0[1]:.2f} / {load1[1]:.2f}) on {os.cpu_count()} cores"
    )
    return out, note


def live_section(lat: dict[str, np.ndarray], note: str, duration_s: float, rate_hz: int) -> str:
    lines = [
        f"### Live `hil up`, {duration_s:g} s real time, IMU {rate_hz} Hz, every default estimator",
        "",
        f"Latency in ms, of what was captured after the first {STARTUP_S:g} s (start-up: the IMU is "
        f"held until time sync locks). {note}.",
        "",
        "| what | n | p50 | p99 | max |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for key, st in lat.items():
        if not len(st):
            continue
        p50, p99 = np.percentile(st, [50, 99])
        lines.append(f"| {key} | {len(st)} | {p50:.1f} | {p99:.1f} | {st.max():.1f} |")
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="hil bench horizon", description=__doc__.splitlines()[0])
    ap.add_argument("--car", action="store_true", help="run car_drive through hil sim, before and after")
    ap.add_argument("--before", type=Path, default=None, help="score this recording as 'before'")
    ap.add_argument("--after", type=Path, default=None, help="score this recording as 'after'")
    ap.add_argument("--out", type=Path, default=Path("recordings"), help="where --car's recordings go")
    ap.add_argument("--live", type=float, default=0.0, metavar="S", help="a live hil up of S seconds")
    ap.add_argument("--imu-rate", type=int, default=400, help="the live rig's IMU rate (Hz)")
    ap.add_argument("--scenario", default="straight_level", help="the live rig's scenario")
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch docs/benchmarks.md")
    args = ap.parse_args(argv)
    parts: list[str] = []
    if args.car or (args.before and args.after):
        how = ""
        if args.before and args.after:
            before_path, after_path = args.before, args.after
            how = f"Recordings: {before_path.name}, {after_path.name}."
        else:
            from hil.runners.sim import SimOptions, run_sim

            args.out.mkdir(parents=True, exist_ok=True)
            before_path, after_path = args.out / "car_before.mcap", args.out / "car_after.mcap"
            walls = []
            for path, kw in ((before_path, BEFORE_ARGS), (after_path, {})):
                res = run_sim(SimOptions(scenario="car_drive", record=path, rig="horizon", **kw))  # type: ignore[arg-type]
                walls.append(f"{res.duration_s / res.wall_s:.1f}x")
            how = f"hil sim at {walls[0]} (before) and {walls[1]} (after) real time."
        parts.append(car_section(score_recording(before_path), score_recording(after_path), how))
    if args.live > 0:
        lat, note = live_run(args.live, args.imu_rate, args.scenario, "horizon")
        parts.append(live_section(lat, note, args.live, args.imu_rate))
    if not parts:
        ap.error("nothing to do: give --car, --before/--after or --live S")
    md = "\n\n".join(parts)
    print(md)
    if not args.no_write:
        write_section("horizon", md, command_line())
    return 0

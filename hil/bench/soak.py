"""``hil bench soak``: the live rig for a long time at a high IMU rate, every estimator on.

Runs ``hil up`` in-process (the same :class:`~hil.runtime.supervisor.Supervisor`: seven OS
processes, real Zenoh, this machine's CAN transport) in real time -- the rig clock runs at
speed 1, nothing is sped up -- and measures while it runs, from a second Zenoh session on the
rig's hub (so a 30-minute recording never has to be read back):

- **loss**: seq gaps on ``sensor/imu``, ``synced/imu`` and ``nav/ekf15`` (every publisher's seq is
  an index, so a gap is a count), plus the recorder's own ``missing``/``gaps`` counters;
- **latency**: arrival of each fused output (``nav/ekf15``) on the rig clock minus the true
  capture time of the IMU sample it was computed at (``imu_seq``; sample k is captured at
  ``(k + 1) / rate``), p50/p99/max;
- **memory**: VmRSS of every service (``/proc/<pid>/status``) every ``--rss-every`` seconds
  until the stop begins (the teardown, e.g. the recorder writing its footer, is not the run);
  growth = the least-squares line through the samples from 10 % of the run (after start-up and
  warm-up) to the end, as a % of its start; also last sample vs the one at 10 %, and the
  min–max, since a single sample can land on a transient backlog's few MiB;
- **CPU**: per service over the run (the supervisor's figures).

Then ``--sweep`` runs short real-time rigs at increasing IMU rates and reports the highest with
zero loss on this machine.
"""

from __future__ import annotations

import tempfile
import threading
import time
import tracemalloc
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.bench import command_line, write_section
from hil.bus.keys import Keys
from hil.bus.pubsub import Stats, Subscriber
from hil.bus.session import open_session
from hil.messages import ImuSample, NavSolution, RunInfo, ServiceStatus
from hil.record.completeness import SeqTracker
from hil.record.mcapio import SessionWriter
from hil.runtime.argtypes import OneLineParser, duration_s, speed
from hil.runtime.clock import RigClock
from hil.runtime.supervisor import Supervisor, UpOptions

SUSTAINED_P99_MS = 500.0  # beyond it the fusion is falling behind (it was the 200 ms watermark plus margin)


def vm_rss_kib(pid: int) -> int | None:
    """Resident set size of a live process in KiB (Linux ``/proc``); None where unavailable."""
    try:
        with open(f"/proc/{pid}/status") as fh:
            for line in fh:
                if line.startswith("VmRSS:"):
                    return int(line.split()[1])
    except (OSError, ValueError, IndexError):
        return None
    return None


@dataclass
class SoakProbe:
    """What the bench's own Zenoh session sees of a running rig."""

    rate_hz: int
    run: RunInfo | None = None
    seqs: dict[str, SeqTracker] = field(default_factory=dict)
    latency_ns: list[int] = field(default_factory=list)
    recorder: ServiceStatus | None = None
    lock: threading.Lock = field(default_factory=threading.Lock)

    def on_run(self, run: RunInfo, _k: str) -> None:
        self.run = run

    def on_seq(self, msg: ImuSample | NavSolution, key: str) -> None:
        with self.lock:
            self.seqs.setdefault(key.split("/", 2)[2], SeqTracker()).see(msg.seq)

    def on_nav(self, sol: NavSolution, key: str) -> None:
        run = self.run
        if run is not None and sol.imu_seq >= 0:
            now = RigClock(run.start_epoch_ns, run.speed).now_ns()
            with self.lock:
                self.latency_ns.append(now - (sol.imu_seq + 1) * 1_000_000_000 // self.rate_hz)
        self.on_seq(sol, key)

    def on_status(self, st: ServiceStatus, _k: str) -> None:
        if st.service == "recorder":
            self.recorder = st


@dataclass
class SoakResult:
    rate_hz: int
    duration_s: float
    wall_s: float
    rc: int
    failures: list[str]
    seqs: dict[str, dict[str, int]]
    recorder: dict[str, int]
    latency_ms: np.ndarray
    rss_kib: dict[str, list[tuple[float, int]]]
    cpu_s: dict[str, float]
    cpu_window_s: float
    speed: float = 1.0
    fd: bool = False

    def steady_latency_ms(self) -> np.ndarray:
        """Latency after start-up: the first 10 % of outputs (at least 5 s of them) dropped.

        Start-up (imports, Zenoh discovery, the first watermark) is a one-off transient; whether
        the rig keeps up is a property of the steady state.
        """
        v = self.latency_ms
        skip = max(len(v) // 10, int(5.0 * len(v) / max(self.duration_s, 1e-9)))
        return v[skip:]

    def latency_p99_by_quarter(self) -> list[float]:
        """p99 per quarter of the steady state: a backlog that grows shows as a rising sequence."""
        v = self.steady_latency_ms()
        return [float(np.percentile(q, 99)) for q in np.array_split(v, 4) if len(q)]

    @property
    def lost(self) -> int:
        own = sum(t["missing"] for t in self.seqs.values())
        return own + self.recorder.get("missing", 0)

    def expected_imu(self) -> int:
        return int(self.duration_s * self.rate_hz)


def soak_run(
    duration_s: float,
    rate_hz: int,
    scenario: str,
    rss_every_s: float,
    rig: str,
    *,
    speed: float = 1.0,
    fd: bool = False,
) -> SoakResult:
    """One ``hil up`` with every default estimator at rig clock ``speed``, measured from outside."""
    with tempfile.TemporaryDirectory() as d:
        sup = Supervisor(
            UpOptions(
                scenario=scenario,
                duration_s=duration_s,
                record=Path(d) / "soak.mcap",
                rig=rig,
                live=False,
                log_dir=Path(d) / "logs",
                imu_rate_hz=rate_hz,
                speed=speed,
                fd=fd,
            )
        )
        probe = SoakProbe(rate_hz)
        k = Keys(rig)
        # joins the hub as the rig's services do: a bare peer config lacks the per-run secret, and
        # an authenticated hub lets it in to see nothing (0 samples read as 0 lost)
        cfg = sup.child_bus
        rss: dict[str, list[tuple[float, int]]] = {}
        stop = threading.Event()

        def sample_rss() -> None:
            t0 = time.monotonic()
            while not stop.wait(rss_every_s):
                children = list(sup.children.items())
                if any(child.stopping for _, child in children):
                    break  # the stop has begun: teardown (the recorder's footer) is not the run
                for name, child in children:
                    v = vm_rss_kib(child.proc.pid)
                    if v is not None:
                        rss.setdefault(name, []).append((time.monotonic() - t0, v))

        holder: dict[str, object] = {}

        def attach() -> None:
            time.sleep(0.5)  # the supervisor opens its hub first
            session = open_session(cfg)
            stats = Stats()
            holder["session"] = session
            holder["subs"] = [
                Subscriber(session, k.run(), RunInfo, probe.on_run, stats),
                Subscriber(session, k.sensor("imu"), ImuSample, probe.on_seq, stats),
                Subscriber(session, k.synced("imu"), ImuSample, probe.on_seq, stats),
                Subscriber(session, k.nav("ekf15"), NavSolution, probe.on_nav, stats),
                Subscriber(session, k.status("recorder"), ServiceStatus, probe.on_status, stats),
            ]

        threading.Thread(target=attach, daemon=True).start()
        sampler = threading.Thread(target=sample_rss, daemon=True)
        sampler.start()
        t0 = time.monotonic()
        rc = sup.run()
        wall = time.monotonic() - t0
        stop.set()
        sampler.join(timeout=5)
        session = holder.get("session")
        if session is not None:
            session.close()  # type: ignore[attr-defined]
    rec = probe.recorder.counter_map() if probe.recorder is not None else {}
    with probe.lock:
        seqs = {
            key: {"count": t.count, "missing": t.missing, "gaps": t.gaps} for key, t in probe.seqs.items()
        }
        lat = np.array(probe.latency_ns, dtype=np.float64) * 1e-6
    return SoakResult(
        rate_hz=rate_hz,
        duration_s=duration_s,
        wall_s=wall,
        rc=rc,
        failures=list(sup.failures),
        seqs=seqs,
        recorder={
            k2: v
            for k2, v in rec.items()
            if k2
            in (
                "written",
                "missing",
                "gaps",
                "zenoh_missed",
                "queue_peak",
                "index_bytes",
                "index_held_bytes",
                "heap_trims",
                "heap_trim_released_kib",
                "heap_trim_max_us",
            )
        },
        latency_ms=lat,
        rss_kib=rss,
        cpu_s=dict(sup.cpu_s),
        cpu_window_s=sup.cpu_window_s,
        speed=speed,
        fd=fd,
    )


def rss_growth(series: list[tuple[float, int]]) -> tuple[int, int, float]:
    """(RSS at 10 % of the run, last RSS, growth %) of one service."""
    if len(series) < 2:
        return (0, 0, float("nan"))
    base = series[max(0, len(series) // 10)][1]
    last = series[-1][1]
    return base, last, 100.0 * (last - base) / base if base else float("nan")


def rss_trend_growth(series: list[tuple[float, int]]) -> float:
    """Growth % from 10 % of the run to its end along a least-squares line through the samples.

    A single sample sits anywhere on the saw-tooth of a heap that churns between trims (a few
    MiB at 1 kHz); the fitted line is what a leak would move.
    """
    tail = series[len(series) // 10 :]
    if len(tail) < 3:
        return float("nan")
    t = np.array([x[0] for x in tail], dtype=np.float64)
    v = np.array([x[1] for x in tail], dtype=np.float64)
    slope, intercept = np.polyfit(t, v, 1)
    start = slope * t[0] + intercept
    return float(100.0 * slope * (t[-1] - t[0]) / start) if start > 0 else float("nan")


def rss_second_half_growth(series: list[tuple[float, int]]) -> float:
    """Growth % over the second half of the run: a leak keeps growing, a high-water mark does not."""
    if len(series) < 4:
        return float("nan")
    mid = series[len(series) // 2][1]
    return 100.0 * (series[-1][1] - mid) / mid if mid else float("nan")


def index_bytes_per_chunk(pack: bool, chunks: int = 400, channels: int = 30, spill: bool = False) -> float:
    """Python heap a :class:`SessionWriter` keeps per written chunk (tracemalloc): mcap's objects,
    packed in memory, or packed and spilled to the scratch file (what the recorder does).

    Each chunk carries one message on every channel, as the recorder's 1 s chunks do at the
    rig's topic count; what stays allocated after the chunks are out is the summary index.
    """
    with tempfile.TemporaryDirectory() as tmp:
        w = SessionWriter(Path(tmp) / "index.mcap", pack_index=pack, spill_index=spill)
        payload = b'{"seq":0}'
        for c in range(channels):  # channels registered before the baseline
            w.write(f"hil/b/t{c}", ImuSample, payload, log_time_ns=0, publish_time_ns=0, seq=0)
        w.flush()
        tracemalloc.start()
        base = tracemalloc.get_traced_memory()[0]
        for k in range(chunks):
            for c in range(channels):
                w.write(f"hil/b/t{c}", ImuSample, payload, log_time_ns=k, publish_time_ns=k, seq=k)
            w.flush()
        held = tracemalloc.get_traced_memory()[0] - base
        tracemalloc.stop()
        w.close()
    return held / chunks


def _mode(r: SoakResult) -> str:
    can = "CAN FD (one frame per sample)" if r.fd else "classic CAN (4 frames per sample + sync)"
    if r.speed == 1.0:
        return f"real time (rig clock at speed 1), {can}"
    how = "sped up" if r.speed > 1 else "slowed down"
    return (
        f"rig clock {how} to {r.speed:g}x wall time ({r.rate_hz * r.speed:g} IMU samples per wall "
        f"second), {can}"
    )


def soak_markdown(
    r: SoakResult, sweep: list[SoakResult], note: str, index_b: tuple[float, float, float] | None = None
) -> str:
    imu = r.seqs.get("sensor/imu", {})
    lines = [
        f"`hil up`, {_mode(r)}, scenario straight_level, IMU at **{r.rate_hz} Hz** of rig time, "
        f"every default estimator, **{r.duration_s / 60:g} min** of rig time ({r.wall_s:.0f} s wall). {note}",
        "",
        f"- exit code {r.rc}" + (f"; failures: {r.failures}" if r.failures else ""),
        f"- lost messages (seq gaps on sensor/imu, synced/imu, nav/ekf15 + recorder `missing`): **{r.lost}**",
        f"- IMU samples seen: {imu.get('count', 0)} of {r.expected_imu()} expected",
        f"- recorder: {r.recorder}",
    ]
    if len(r.latency_ms):
        v = r.latency_ms
        st = r.steady_latency_ms()
        unit = "ms" if r.speed == 1.0 else "ms of rig time"
        lines.append(
            f"- latency IMU capture → fused output (nav/ekf15 arrival), n={len(v)}: "
            f"p50 **{np.median(v):.1f} {unit}**, p99 **{np.percentile(v, 99):.1f} {unit}**, "
            f"max {v.max():.1f} {unit} "
            "(the output predictor publishes at each IMU sample's arrival; before it, outputs carried "
            "the fusion's 200 ms watermark lag)"
        )
        if len(st):
            quarters = ", ".join(f"{q:.0f}" for q in r.latency_p99_by_quarter())
            lines.append(
                f"- the same after start-up (first 10 % of outputs dropped): p50 {np.median(st):.1f}, "
                f"p99 {np.percentile(st, 99):.1f}, max {st.max():.1f} {unit}; p99 per quarter of the run: "
                f"{quarters} (flat = keeping up, rising = a growing backlog)"
            )
    lines += [
        "",
        "| service | CPU s | share of one core | RSS at 10 % (MiB) | RSS at end (MiB) | growth "
        "| growth over 2nd half | trend 10 %→end (fit) | RSS min–max after 10 % (MiB) |",
    ]
    lines += ["| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |"]
    worst = worst_trend = 0.0
    for name in sorted(r.rss_kib):
        base, last, g = rss_growth(r.rss_kib[name])
        worst = max(worst, g) if np.isfinite(g) else worst
        cpu = r.cpu_s.get(name, float("nan"))
        share = 100 * cpu / r.cpu_window_s if r.cpu_window_s else float("nan")
        g2 = rss_second_half_growth(r.rss_kib[name])
        trend = rss_trend_growth(r.rss_kib[name])
        worst_trend = max(worst_trend, trend) if np.isfinite(trend) else worst_trend
        after = [v for _, v in r.rss_kib[name][len(r.rss_kib[name]) // 10 :]] or [0]
        lines.append(
            f"| {name} | {cpu:.1f} | {share:.1f} % | {base / 1024:.1f} | {last / 1024:.1f} | {g:+.2f} % "
            f"| {g2:+.2f} % | {trend:+.2f} % | {min(after) / 1024:.1f}–{max(after) / 1024:.1f} |"
        )
    lines += [
        "",
        f"Largest RSS growth along the fitted trend: **{worst_trend:+.2f} %** (target < 5 %); "
        f"between two single samples (10 % and end): {worst:+.2f} %. The trend is the criterion: "
        "a single sample lands anywhere on the few-MiB saw-tooth of a heap that churns between "
        "trims (the min–max column).",
    ]
    if index_b:
        plain, packed, spilled = index_b
        total = r.recorder.get("index_bytes", 0)
        held = r.recorder.get("index_held_bytes", 0)
        rate = (
            f" In this run the index reached {total / 2**20:.2f} MiB "
            f"({total / max(r.duration_s, 1e-9) * 3600 / 2**20:.1f} MiB per hour: a chunk closes at "
            f"512 KiB or after 1 s, whichever comes first), of which the recorder held "
            f"{held / 1024:.1f} KiB in memory at the end."
            if total
            else ""
        )
        lines += [
            "",
            f"Recorder summary index, kept until the footer (tracemalloc, 30 channels, per chunk): "
            f"{plain:,.0f} B as mcap's ChunkIndex objects, {packed:,.0f} B packed in memory "
            f"({plain / packed:.1f}x less), **{spilled:,.0f} B** packed and spilled to the "
            f"recording's scratch file as the recorder does (less than one 64 KiB block stays)." + rate,
        ]
        trims = r.recorder.get("heap_trims", 0)
        if trims:
            lines.append(
                f"Recorder heap trims: {trims}, giving back "
                f"{r.recorder.get('heap_trim_released_kib', 0) / 1024:.1f} MiB of free C heap in all; "
                f"longest call {r.recorder.get('heap_trim_max_us', 0) / 1000:.1f} ms."
            )
    if sweep:
        lines += ["", f"IMU rate sweep ({_mode(sweep[0])}, every default estimator):", ""]
        lines += [
            "| IMU rate | duration | exit | lost | IMU samples / expected | p99 latency ms (all) "
            "| p99 after start-up | p99 per quarter |"
        ]
        lines += ["| ---: | ---: | ---: | ---: | ---: | ---: | ---: | --- |"]
        best = best_lossless = 0
        for s in sweep:
            n = s.seqs.get("sensor/imu", {}).get("count", 0)
            p99_all = np.percentile(s.latency_ms, 99) if len(s.latency_ms) else float("nan")
            st = s.steady_latency_ms()
            p99 = np.percentile(st, 99) if len(st) else float("nan")
            quarters = " / ".join(f"{q:.0f}" for q in s.latency_p99_by_quarter())
            lines.append(
                f"| {s.rate_hz} Hz | {s.duration_s:g} s | {s.rc} | {s.lost} "
                f"| {n} / {s.expected_imu()} | {p99_all:.1f} | {p99:.1f} | {quarters} |"
            )
            lossless = s.rc == 0 and s.lost == 0 and n >= 0.99 * s.expected_imu()
            if lossless:
                best_lossless = max(best_lossless, s.rate_hz)
            # sustained = nothing lost AND the fusion keeps up: a growing backlog is not real time
            if lossless and p99 < SUSTAINED_P99_MS:
                best = max(best, s.rate_hz)
        lines += [
            "",
            f"Highest IMU rate with zero loss here: **{best_lossless} Hz** (of the rates tried).",
            "",
            f"Highest IMU rate sustained with zero loss and p99 latency after start-up "
            f"< {SUSTAINED_P99_MS:g} ms here: "
            f"**{best} Hz** (of the rates tried).",
        ]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench soak")
    ap.add_argument("--duration", type=duration_s, default=1800.0, help="soak seconds of rig time")
    ap.add_argument(
        "--speed", type=speed, default=1.0, help="rig clock K times wall time (1 = real time; < 1 slows it)"
    )
    ap.add_argument("--fd", action="store_true", help="CAN FD: one frame per IMU sample")
    ap.add_argument("--sweep-speed", type=speed, default=1.0, help="rig clock speed of the sweep runs")
    ap.add_argument("--imu-rate", type=int, default=1000)
    ap.add_argument("--scenario", default="straight_level")
    ap.add_argument("--rss-every", type=float, default=10.0, help="seconds between RSS samples")
    ap.add_argument("--sweep", default="400,1000,2000", help="IMU rates for the sweep ('' to skip)")
    ap.add_argument("--sweep-duration", type=duration_s, default=20.0)
    ap.add_argument("--note", default="", help="a sentence for the section (e.g. why shorter than 30 min)")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    a = ap.parse_args(argv)
    r = soak_run(a.duration, a.imu_rate, a.scenario, a.rss_every, "soakrig", speed=a.speed, fd=a.fd)
    sweep = [
        soak_run(a.sweep_duration, int(x), a.scenario, 2.0, f"sweep{x}", speed=a.sweep_speed, fd=a.fd)
        for x in a.sweep.split(",")
        if x.strip()
    ]
    index = (
        index_bytes_per_chunk(False),
        index_bytes_per_chunk(True),
        index_bytes_per_chunk(True, spill=True),
    )
    body = soak_markdown(r, sweep, a.note, index)
    print(body)
    if not a.no_write:
        write_section("soak", body, command_line())
    return 0 if r.rc == 0 and r.lost == 0 else 1

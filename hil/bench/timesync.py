"""``hil bench timesync``: re-stamping error against the emulators' truth, then its navigation effect.

Part 1 runs :class:`hil.timesync.core.TimeSyncCore` on measurement streams made by the rig's own
device-clock model (:class:`hil.sensors.clock.DeviceClock`) and a transport model (fixed minimum
delay + exponential extra delay of a given mean; GNSS: uniform output jitter, as the receiver
model). Rig time == true time (the rig clock is the reference), so the error of a re-stamp is
``restamped - true capture``. Cases: time tags; arrival times only; 50 ppm drift; 1 ms and
10 ms arrival jitter; a clock step (both directions), for the IMU (400 Hz, sync frame 1 Hz) and
the GNSS receiver (10 Hz, PPS).

Part 2 runs ``hil sim`` (the offline executor: the same cores on a virtual clock) on the UAV
scenario at 50 m/s with 100 ms GNSS latency, once with synchronisation and once with raw arrival
stamps, and compares the fused position error with truth.
"""

from __future__ import annotations

import math
import tempfile
import time
from dataclasses import dataclass, replace
from pathlib import Path

import numpy as np

from hil.bench.capture import restamp_errors  # the benches' and tests' name for it
from hil.runtime.argtypes import OneLineParser, duration_s
from hil.sensor_table import CAN_FRAME_TIME_NS, IMU_FRAMES_PER_SAMPLE
from hil.sensors.clock import ClockStep, DeviceClock, DeviceClockConfig
from hil.sensors.imu import sensor_rng
from hil.timesync.core import SyncConfig, TimeSyncCore

IMU_BASE = DeviceClockConfig(
    offset_s=0.0071,
    drift_ppm=20.0,
    drift_rw_ppm_per_sqrt_s=0.005,
    jitter_s=0.5e-6,
    quantum_s=1e-6,
    latch_jitter_s=5e-6,
)
GNSS_BASE = DeviceClockConfig(
    offset_s=0.0015, drift_ppm=0.02, jitter_s=20e-9, quantum_s=1e-9, latch_jitter_s=1e-6
)


@dataclass(frozen=True)
class StreamCase:
    """One synthetic stream: a device clock, a rate, a transport, with or without tags."""

    name: str
    sensor: str  # "imu" | "gnss"
    clock: DeviceClockConfig
    timetag: bool
    rate_hz: float = 400.0
    duration_s: float = 60.0
    min_delay_s: float = 20e-6 + IMU_FRAMES_PER_SAMPLE * CAN_FRAME_TIME_NS * 1e-9
    jitter_s: float = 10e-6  # mean of the exponential extra delay (GNSS: width of uniform)
    converge_tol_us: float = 100.0
    seed: int = 7


@dataclass
class StreamResult:
    case: StreamCase
    t_s: np.ndarray  # true capture times
    err_ns: np.ndarray  # restamped - true
    steps_detected_at_s: list[float]  # true time of the measurement at which a step was declared
    final_state: str

    def window(self, t0: float, t1: float = math.inf) -> np.ndarray:
        m = (self.t_s >= t0) & (self.t_s < t1)
        return self.err_ns[m]

    def converged_after_s(self, t_end: float = math.inf, tol_us: float | None = None) -> float:
        """First time after which every |error| (up to ``t_end``) stays within the tolerance."""
        tol = (tol_us if tol_us is not None else self.case.converge_tol_us) * 1e3
        m = self.t_s < t_end
        bad = np.nonzero(np.abs(self.err_ns[m]) > tol)[0]
        if len(bad) == 0:
            return float(self.t_s[0])
        i = bad[-1] + 1
        return float(self.t_s[m][i]) if i < m.sum() else math.inf


def sync_config_of(case: StreamCase) -> SyncConfig:
    tag_latency = 20e-6 + CAN_FRAME_TIME_NS * 1e-9 if case.sensor == "imu" else 0.0
    return SyncConfig(
        source="timetag" if case.timetag else "arrival",
        tag_latency_ns=round(tag_latency * 1e9),
        min_delay_ns=round(case.min_delay_s * 1e9),
    )


def run_stream(case: StreamCase) -> StreamResult:
    """Feed one stream through a fresh TimeSyncCore in arrival order; errors per measurement."""
    clock = DeviceClock(case.clock, sensor_rng(case.seed, f"{case.sensor}.clock"))
    rng = sensor_rng(case.seed, f"{case.sensor}.transport")
    n = round(case.duration_s * case.rate_hz)
    dt_ns = round(1e9 / case.rate_hz)
    t_true = (np.arange(n, dtype=np.int64) + 1) * dt_ns
    dev = clock.device_ns_array(t_true)
    if case.sensor == "imu":
        extra = rng.exponential(case.jitter_s * 1e9, n) if case.jitter_s else np.zeros(n)
        rx = t_true + round(case.min_delay_s * 1e9) + np.round(extra).astype(np.int64)
        rx = np.maximum.accumulate(rx)  # a CAN bus is FIFO
        # the sync frame goes first at every whole second's sample: one frame + latency, kernel-
        # stamped (latch jitter), independent of the data path's jitter
        per = round(case.rate_hz)
        tag_idx = np.arange(per - 1, n, per)
        tag_dev = dev[tag_idx]
        latch = np.array([clock.latch_ns(int(t)) for t in t_true[tag_idx]], dtype=np.int64)
        tag_latch = latch + round(20e-6 * 1e9) + CAN_FRAME_TIME_NS
    else:
        u = rng.random(n)
        rx = t_true + round(case.min_delay_s * 1e9) + np.round(u * case.jitter_s * 1e9).astype(np.int64)
        edges = np.arange(1, int(case.duration_s) + 1, dtype=np.int64) * 1_000_000_000
        tag_dev = clock.device_ns_array(edges)
        tag_latch = np.array([clock.latch_ns(int(e)) for e in edges], dtype=np.int64)
    core: TimeSyncCore[int] = TimeSyncCore({case.sensor: sync_config_of(case)})
    rest = np.zeros(n, dtype=np.int64)
    got = np.zeros(n, dtype=bool)
    steps_at: list[float] = []
    j = 0
    n_steps = 0
    n_tags = len(tag_latch) if case.timetag else 0
    for i in range(n):
        while j < n_tags and tag_latch[j] <= rx[i]:
            core.on_timetag(case.sensor, int(tag_dev[j]), int(tag_latch[j]))
            j += 1
        for k, stamp in core.on_measurement(case.sensor, int(dev[i]), int(rx[i]), i):
            rest[k] = stamp
            got[k] = True
        m = core.mapping(case.sensor)
        if m.steps_detected > n_steps:
            n_steps = m.steps_detected
            steps_at.append(float(t_true[i]) * 1e-9)
    for k, stamp in core.flush():
        rest[k] = stamp
        got[k] = True
    assert got.all()
    return StreamResult(case, t_true * 1e-9, rest - t_true, steps_at, core.mapping(case.sensor).state)


def imu_case(name: str, **kw: object) -> StreamCase:
    return replace(StreamCase(name=name, sensor="imu", clock=IMU_BASE, timetag=True), **kw)  # type: ignore[arg-type]


def gnss_case(name: str, **kw: object) -> StreamCase:
    base = StreamCase(
        name=name,
        sensor="gnss",
        clock=GNSS_BASE,
        timetag=True,
        rate_hz=10.0,
        min_delay_s=0.1,
        jitter_s=0.005,
        converge_tol_us=100.0,
    )
    return replace(base, **kw)  # type: ignore[arg-type]


STEP_T_S = 30.0


def default_cases(duration_s: float = 60.0) -> list[StreamCase]:
    step_back = (ClockStep(STEP_T_S, -0.25),)
    step_fwd = (ClockStep(STEP_T_S, 0.04),)
    d = duration_s
    return [
        imu_case("IMU, time tags (sync frame), 20 ppm", duration_s=d),
        imu_case("IMU, arrival only, 20 ppm, 10 µs jitter", timetag=False, duration_s=d),
        imu_case("IMU, time tags, 50 ppm", clock=replace(IMU_BASE, drift_ppm=50.0), duration_s=d),
        imu_case(
            "IMU, arrival only, 50 ppm", timetag=False, clock=replace(IMU_BASE, drift_ppm=50.0), duration_s=d
        ),
        imu_case("IMU, time tags, 1 ms arrival jitter", jitter_s=1e-3, duration_s=d),
        imu_case("IMU, arrival only, 1 ms jitter", timetag=False, jitter_s=1e-3, duration_s=d),
        imu_case(
            "IMU, arrival only, 10 ms jitter",
            timetag=False,
            jitter_s=10e-3,
            duration_s=d,
            converge_tol_us=1000.0,
        ),
        imu_case(
            "IMU, time tags, step -250 ms",
            clock=replace(IMU_BASE, offset_s=1.0, steps=step_back),
            duration_s=d,
        ),
        imu_case("IMU, time tags, step +40 ms", clock=replace(IMU_BASE, steps=step_fwd), duration_s=d),
        imu_case(
            "IMU, arrival only (1 ms jitter), step -250 ms",
            timetag=False,
            jitter_s=1e-3,
            clock=replace(IMU_BASE, offset_s=1.0, steps=step_back),
            duration_s=d,
        ),
        gnss_case("GNSS, PPS time tags, 100 ms ± 5 ms latency", duration_s=d),
        gnss_case(
            "GNSS, arrival only, 100 ms ± 5 ms latency", timetag=False, converge_tol_us=5000.0, duration_s=d
        ),
        gnss_case(
            "GNSS, PPS, step -250 ms", clock=replace(GNSS_BASE, offset_s=1.0, steps=step_back), duration_s=d
        ),
    ]


def stream_rows(results: list[StreamResult]) -> list[dict[str, str]]:
    rows = []
    for r in results:
        steps = r.case.clock.steps
        t_step = steps[0].t_s if steps else math.inf
        settled = r.window(5.0, t_step)
        after = r.window(t_step + 2.0) if steps else np.array([], dtype=np.int64)
        row = {
            "case": r.case.name,
            "RMS µs (5 s on)": f"{np.sqrt(np.mean(settled.astype(float) ** 2)) / 1e3:.1f}",
            "max µs (5 s on)": f"{np.max(np.abs(settled)) / 1e3:.1f}",
            "mean µs": f"{np.mean(settled) / 1e3:+.1f}",
            "converged (s)": f"{r.converged_after_s(t_step):.2f}",
        }
        if steps:
            det = [t for t in r.steps_detected_at_s if t >= t_step - 1e-9]
            rec = _recovered_after(r, t_step)
            row["step: detected after (s)"] = f"{det[0] - t_step:.2f}" if det else "not detected"
            row["recovered after (s)"] = f"{rec:.2f}"
            row["RMS µs (step+2 s on)"] = f"{np.sqrt(np.mean(after.astype(float) ** 2)) / 1e3:.1f}"
        else:
            row["step: detected after (s)"] = (
                "-" if not r.steps_detected_at_s else f"false: {len(r.steps_detected_at_s)}"
            )
            row["recovered after (s)"] = "-"
            row["RMS µs (step+2 s on)"] = "-"
        rows.append(row)
    return rows


def _recovered_after(r: StreamResult, t_step: float) -> float:
    m = r.t_s >= t_step
    tol = r.case.converge_tol_us * 1e3
    bad = np.nonzero(np.abs(r.err_ns[m]) > tol)[0]
    if len(bad) == 0:
        return 0.0
    i = bad[-1] + 1
    return float(r.t_s[m][i]) - t_step if i < m.sum() else math.inf


def md_table(rows: list[dict[str, str]]) -> str:
    if not rows:
        return ""
    cols = list(rows[0])
    out = ["| " + " | ".join(cols) + " |", "|" + "|".join(" --- " for _ in cols) + "|"]
    out += ["| " + " | ".join(r.get(c, "") for c in cols) + " |" for r in rows]
    return "\n".join(out)


# ---------------------------------------------------------------------------------------------
# navigation effect


def nav_effect(duration_s: float, workdir: Path) -> list[dict[str, str]]:
    """UAV survey at 50 m/s, 10 Hz GNSS with 100 ms latency: fused error with sync on and off."""
    import tomllib

    from hil.nav.scenario import dump_toml, load_scenario
    from hil.record.info import estimator_errors
    from hil.record.mcapio import read_session
    from hil.runners.sim import SimOptions, run_sim

    base = load_scenario("uav_survey")
    doc = tomllib.loads(base.source_text)
    doc["initial"]["speed_mps"] = 50.0
    doc["gnss"].update({"latency_s": 0.1, "jitter_s": 0.005, "rate_hz": 10.0})
    doc.pop("event", None)
    doc["duration_s"] = float(duration_s)
    rows = []
    for label, sync in (("on (time tags)", "timetag"), ("off (raw arrival stamps)", "off")):
        d = dict(doc)
        d["clock"] = {"imu": {"sync": sync}, "gnss": {"sync": sync}}
        path = workdir / f"uav50_{sync}.toml"
        path.write_text(dump_toml(d, header="uav_survey at 50 m/s, 10 Hz GNSS, 100 ms latency"))
        rec = workdir / f"uav50_{sync}.mcap"
        run_sim(SimOptions(scenario=str(path), record=rec, duration_s=duration_s))
        errs = estimator_errors(read_session(rec))
        for est in sorted(errs):
            if est == "ins":
                continue
            e = errs[est]
            rows.append(
                {"sync": label, "estimator": est, "rms_m": f"{e['rms_m']:.2f}", "max_m": f"{e['max_m']:.2f}"}
            )
    return rows


def main(argv: list[str]) -> int:
    from hil.bench import command_line, write_section

    ap = OneLineParser(prog="hil bench timesync")
    ap.add_argument("--duration", type=duration_s, default=60.0, help="seconds per synthetic stream")
    ap.add_argument("--nav-duration", type=duration_s, default=300.0, help="seconds of each hil sim run")
    ap.add_argument("--no-nav", action="store_true", help="skip the navigation comparison")
    ap.add_argument("--no-write", action="store_true", help="print only")
    ap.add_argument(
        "--live",
        type=float,
        default=0.0,
        help="also run the live rig (hil up) this many seconds and add its IMU row (0: no)",
    )
    ap.add_argument(
        "--wire",
        type=float,
        default=0.0,
        help="also run the rig on its wires (the receiver on a serial line, the IMU on CAN FD), "
        "hil sim and hil up, this many seconds each, and add their rows (0: no)",
    )
    a = ap.parse_args(argv)
    t0 = time.monotonic()
    if a.wire > 0:  # alone: the other parts are the core's
        rows = wire_rows(a.wire)
        print(md_table(rows))
        if not a.no_write:
            write_section("timesync-wire", wire_text(a.wire, rows), command_line())
        return 0
    results = [run_stream(c) for c in default_cases(a.duration)]
    rows = stream_rows(results)
    if a.live > 0:
        rows.append(live_row(a.live))
    body = [
        "Re-stamping error = rig stamp from `hil.timesync.core` − true capture time, from streams "
        "made by the rig's device-clock model (offset, drift, drift random walk, 0.5 µs stamp jitter, "
        "1 µs tick; GNSS disciplined) and transport model (IMU: 20 µs + 4 frames × 135 µs + exponential "
        "extra delay of the stated mean, FIFO; GNSS: 100 ms + uniform [0, 5 ms)). "
        f"Streams of {a.duration:g} s; steps at t = {STEP_T_S:g} s; RMS/max from 5 s on (and, with a "
        "step, up to it); 'converged' = time after which |error| stays within 100 µs (10 ms jitter: "
        "1 ms; GNSS arrival-only: 5 ms); 'recovered' = the same after the step. Core-level runs "
        "(no processes, no bus)."
        + (
            f" The last row is the live rig (`hil up` for {a.live:g} s: emulator process → CAN → "
            "bridge → timesync; synced stamp − the emulator's capture truth, matched by seq) with "
            "the load average before it."
            if a.live > 0
            else ""
        ),
        "",
        md_table(rows),
    ]
    print(md_table(rows))
    if not a.no_nav:
        with tempfile.TemporaryDirectory() as td:
            nav = nav_effect(a.nav_duration, Path(td))
        print(md_table(nav))
        body += [
            "",
            f"Navigation effect (offline `hil sim`, {a.nav_duration:g} s of `uav_survey` at 50 m/s, 10 Hz "
            "GNSS with 100 ms output latency + 5 ms jitter; fused position error vs truth). "
            "Sync off = measurements keep their raw arrival stamps, so each fix is fused 100 ms "
            "after its time of validity, about v × latency = 5 m behind:",
            "",
            md_table(nav),
        ]
    body.append(f"\nWall time {time.monotonic() - t0:.0f} s.")
    if not a.no_write:
        write_section("timesync", "\n".join(body), command_line())
    return 0


def live_row(duration_s: float) -> dict[str, str]:
    """The IMU row of a live ``hil up`` (time-tagged IMU over CAN), in the stream rows' columns."""
    from hil.bench.pacing import SYNC_SETTLE_S, run_live

    run = run_live(duration_s)
    e = run.sync_err_ns
    name = f"LIVE: IMU over CAN, time tags (load {run.load_before:.1f})"
    if run.rc != 0 or not len(e):
        return {"case": name, "RMS µs (5 s on)": f"no synced samples after {SYNC_SETTLE_S:g} s (rc {run.rc})"}
    return {
        "case": name,
        "RMS µs (5 s on)": f"{np.sqrt(np.mean(e.astype(float) ** 2)) / 1e3:.1f}",
        "max µs (5 s on)": f"{np.max(np.abs(e)) / 1e3:.1f}",
        "mean µs": f"{np.mean(e) / 1e3:+.1f}",
        "converged (s)": "-",
        "step: detected after (s)": "-",
        "recovered after (s)": "-",
        "RMS µs (step+2 s on)": "-",
    }


# -- the rig on its wires ------------------------------------------------------------------------

#: (case, sensor, [clock.<sensor>] lines, wire options): the receiver on a serial line (NMEA, UBX,
#: both) timed by arrivals alone and by its PPS, and the IMU on CAN FD timed by arrivals alone
WIRE_CASES: tuple[tuple[str, str, str, dict[str, object]], ...] = (
    ("GNSS NMEA line, arrivals", "gnss", "timetag = false", {"gnss_protocol": ["nmea"]}),
    ("GNSS UBX line, arrivals", "gnss", "timetag = false", {"gnss_protocol": ["ubx"]}),
    ("GNSS NMEA+UBX line, arrivals", "gnss", "timetag = false", {"gnss_protocol": ["nmea", "ubx"]}),
    ("GNSS NMEA line, PPS", "gnss", "", {"gnss_protocol": ["nmea"]}),
    ("IMU CAN FD, arrivals", "imu", "timetag = false", {"fd": True}),
)
WIRE_SETTLE_S = 10.0  # errors from here on: the arrival hull has its 2 s span and more


def wire_rows(duration_s: float) -> list[dict[str, str]]:
    """Each wire case through ``hil sim`` and ``hil up`` (straight_level, 115200 baud): the
    re-stamping error of every synced measurement against the emulator's capture truth."""
    import os

    from hil.nav.scenario import load_scenario
    from hil.record.mcapio import read_session
    from hil.runners.sim import SimOptions, run_sim
    from hil.runtime.supervisor import Supervisor, UpOptions

    rows: list[dict[str, str]] = []
    base = load_scenario("straight_level").source_text
    with tempfile.TemporaryDirectory() as d:
        for name, sensor, clock, wire in WIRE_CASES:
            scenario = Path(d) / f"{sensor}_{len(rows)}.toml"
            scenario.write_text(base + (f"\n[clock.{sensor}]\n{clock}\n" if clock else ""))
            for mode in ("sim", "live"):
                rec = Path(d) / f"{len(rows)}_{mode}.mcap"
                load = os.getloadavg()[0]
                if mode == "sim":
                    kw = {k: v for k, v in wire.items() if k in ("gnss_protocol", "fd")}
                    run_sim(SimOptions(scenario=str(scenario), duration_s=duration_s, record=rec, **kw))  # type: ignore[arg-type]
                else:
                    links = {"gnss_serial": str(Path(d) / "gnss0")} if "gnss_protocol" in wire else {}
                    Supervisor(
                        UpOptions(
                            scenario=str(scenario), duration_s=duration_s, record=rec, rig="benchwire",
                            live=False, log_dir=Path(d) / f"logs{len(rows)}", **wire, **links,  # type: ignore[arg-type]
                        )
                    ).run()  # fmt: skip
                t, e = restamp_errors(read_session(rec), sensor)
                e = e[t > WIRE_SETTLE_S] / 1e3
                rows.append(
                    {
                        "case": f"{'SIM' if mode == 'sim' else 'LIVE'}: {name}"
                        + (f" (load {load:.1f})" if mode == "live" else ""),
                        "n": str(len(e)),
                        "mean µs": f"{np.mean(e):+.1f}" if len(e) else "-",
                        "min µs": f"{np.min(e):+.1f}" if len(e) else "-",
                        "max µs": f"{np.max(e):+.1f}" if len(e) else "-",
                    }
                )
    return rows


def wire_text(duration_s: float, rows: list[dict[str, str]]) -> str:
    return "\n".join(
        [
            "The rig on its wires: re-stamping error = synced stamp − the emulator's capture truth "
            f"(matched by seq) of every measurement from {WIRE_SETTLE_S:g} s on, for `hil sim` and "
            f"`hil up` of `straight_level` for {duration_s:g} s each: the GNSS receiver on a serial "
            "line at 115200 baud (`--gnss-serial`, `--gnss-protocol`) timed by arrivals alone "
            "(`[clock.gnss] timetag = false`: from the epoch's first byte, `GnssFix.line_ns`) and by "
            "its PPS; the IMU on CAN FD (`--fd`) timed by arrivals alone (its minimum delay one "
            "frame's, `RunInfo.imu_can_fd`). Live rows on this machine's pty and local CAN bus, "
            "the load average before each.",
            "",
            md_table(rows),
        ]
    )

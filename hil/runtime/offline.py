"""``hil sim``: the live rig's cores wired in one process on a virtual clock, as fast as possible.

Same physics, same DBC codec and frame assembler (so the wire's quantisation is identical to the
live rig), same time-sync and fusion cores, same MCAP layout. Devices stamp on their own clocks
(``hil.sensors.clock``: offset, drift, wander, jitter, tick, steps). Transport is modelled: a CAN
burst leaves at capture and each frame arrives after the bus latency, an exponential extra delay
(``[clock.imu] transport_*``) and its wire time, first in first out; the sync frame goes first
at its edge and carries the kernel-stamp latch jitter; a GNSS fix arrives at its output time
(validity + latency + jitter), the PPS is latched with its latch jitter. Messages are written in
arrival (log time) order, window by window, so a one-hour session never sits in memory.

Timed faults (the scenario's ``[[event]]``) go through the code the live emulators run: the GNSS
ones through ``GnssEmulatorCore``, clock steps through ``hil.sensors.clock``, the IMU/CAN ones
(frame loss, stuck, saturated, burst errors, bus-off) through ``hil.faults.ImuFaults`` and
``FrameCorruptor``, so the wire carries what the live bus would and the frame assembler counts
what the live ``can_bridge`` counts. Each is announced as ``fault_start``/``fault_end`` on
``event/<emulator>`` as live. ``kill_service`` has no meaning in one process: a warning line and a
``fault_ignored`` event on ``event/sim`` say so. ``status/imu_emulator`` and ``status/can_bridge``
carry those cores' counters once per rig second (pid 0: nothing here depends on the host).
Everything is seeded by the scenario, so the same scenario gives the same file, byte for byte.
"""

from __future__ import annotations

import heapq
import itertools
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec
import numpy as np

from hil import __version__
from hil.bus.keys import Keys
from hil.faults import (
    SIM_NOT_APPLICABLE,
    DelayLine,
    FrameCorruptor,
    ImuFaults,
    device_timeline,
    edge_time_ns,
    fault_detail,
)
from hil.fusion.core import FREE_INS, FusionConfig, FusionCore
from hil.messages import (
    CaptureTruth,
    Event,
    GnssFix,
    ImuSample,
    Message,
    RunInfo,
    ServiceStatus,
    TimeTag,
    encode,
)
from hil.record.mcapio import SessionWriter
from hil.runtime.builders import can_frame_msg, clock_model_msg, gnss_fix_msg, imu_sample_msg, truth_msg
from hil.runtime.scenario_io import run_attachments, scenario_for_run, sha256_text
from hil.sensors.clock import CAN_FRAME_TIME_NS
from hil.timesync.core import TimeSyncCore

__all__ = ["CAN_FRAME_TIME_NS", "SimOptions", "SimResult", "run_sim"]
TRUTH_RATE_HZ = 100.0
WINDOW_NS = 1_000_000_000


@dataclass
class SimOptions:
    scenario: str = "straight_level"
    duration_s: float | None = None
    record: Path = Path("recordings/sim.mcap")
    rig: str = "sim"
    estimators: list[str] = field(default_factory=list)
    fd: bool = False
    lag_s: float = 0.2
    output_every: int = 8
    progress: bool = False
    on_progress: Any = None  # callable(rig_s_done, rig_s_total), called once per simulated second
    on_warning: Callable[[str], None] | None = None  # default: "hil sim: warning: ..." on stderr


@dataclass
class SimResult:
    path: Path
    messages: int
    duration_s: float
    wall_s: float
    warnings: list[str] = field(default_factory=list)

    @property
    def summary(self) -> str:
        x = self.duration_s / self.wall_s if self.wall_s > 0 else float("inf")
        return (
            f"hil sim: {self.duration_s:g} s of rig time in {self.wall_s:.1f} s ({x:.1f}x real time), "
            f"{self.messages} messages -> {self.path}"
        )


class _Pubs:
    """Per-publisher seq counters, as the live services keep them."""

    def __init__(self) -> None:
        self.seq: dict[str, int] = {}

    def next(self, key: str) -> int:
        s = self.seq.get(key, 0)
        self.seq[key] = s + 1
        return s


def run_sim(opts: SimOptions) -> SimResult:
    from hil.can.codec import ImuCanCodec, ImuFrameAssembler
    from hil.nav.scenario import load_scenario
    from hil.nav.trajectory import TruthGenerator
    from hil.sensors.clock import clock_config_for, device_clock_for
    from hil.sensors.gnss import GnssEmulatorCore
    from hil.sensors.imu import ImuEmulatorCore, sensor_rng
    from hil.timesync.config import sync_configs_for
    from hil.timesync.sample_index import ImuSampleIndexer
    from services.fusion import default_estimators

    t_wall = time.monotonic()
    base = load_scenario(opts.scenario)
    duration_s = float(opts.duration_s if opts.duration_s is not None else base.duration_s)
    keys = Keys(opts.rig)
    run = RunInfo(
        seq=0,
        stamp_ns=0,
        rig=opts.rig,
        start_epoch_ns=0,
        speed=0.0 + 1.0,
        scenario=base.name,
        scenario_sha256=sha256_text(base.source_text),
        seed=base.seed,
        duration_s=duration_s,
        origin_lat_deg=base.origin_lat_deg,
        origin_lon_deg=base.origin_lon_deg,
        origin_alt_m=base.origin_alt_m,
        scenario_toml=base.source_text,
    )
    s = scenario_for_run(run)
    truth = TruthGenerator(s)
    imu_core = ImuEmulatorCore(s, truth, sensor_rng(s.seed, "imu"))
    gnss_core = GnssEmulatorCore(s, truth, sensor_rng(s.seed, "gnss"))
    imu_clock = device_clock_for(s, "imu")
    gnss_clock = device_clock_for(s, "gnss")
    codec = ImuCanCodec.from_dbc(fd=opts.fd)
    assembler = ImuFrameAssembler(ImuCanCodec.from_dbc(fd=opts.fd))
    sync: TimeSyncCore[ImuSample | GnssFix] = TimeSyncCore(sync_configs_for(s))
    imu_cc = clock_config_for(s, "imu")
    can_rng = sensor_rng(s.seed, "imu.transport")
    can_latency_ns = round(imu_cc.transport_latency_s * 1e9)
    can_jitter_ns = imu_cc.transport_jitter_s * 1e9
    names = tuple(opts.estimators) or default_estimators()
    cfg = FusionConfig(estimators=names, lag_ns=int(opts.lag_s * 1e9), output_every=opts.output_every)
    fusion = FusionCore.for_scenario(s, cfg)

    w = SessionWriter(opts.record)
    w.add_metadata(
        "hil",
        {
            "version": __version__,
            "rig": opts.rig,
            "scenario": s.name,
            "scenario_sha256": run.scenario_sha256,
            "seed": s.seed,
            "start_epoch_ns": 0,
            "speed": 0,
            "duration_s": duration_s,
            "origin_lat_deg": s.origin_lat_deg,
            "origin_lon_deg": s.origin_lon_deg,
            "origin_alt_m": s.origin_alt_m,
            "executor": "sim",
        },
    )
    for name, data, media in run_attachments(run):
        w.add_attachment(name, data, media)
    pubs = _Pubs()
    n_written = 0

    def put(out: list[tuple[int, int, str, Message]], t_log: int, key: str, msg: Message) -> None:
        out.append((t_log, len(out), key, msg))

    def flush(out: list[tuple[int, int, str, Message]]) -> None:
        nonlocal n_written
        out.sort(key=lambda r: (r[0], r[1]))
        for t_log, _i, key, msg in out:
            w.write(key, type(msg), encode(msg), log_time_ns=t_log, publish_time_ns=msg.stamp_ns, seq=msg.seq)
        n_written += len(out)
        out.clear()

    from hil.record.rerun import FUSION_CONFIG_EVENT, fusion_config_detail

    out: list[tuple[int, int, str, Message]] = []

    def event(t_ns: int, source: str, kind: str, detail: str) -> None:
        key = keys.event(source)
        put(out, t_ns, key, Event(seq=pubs.next(key), stamp_ns=t_ns, kind=kind, source=source, detail=detail))

    imu_faults = ImuFaults(s.seed, s.events)  # the live imu_emulator's fault core
    corruptor = FrameCorruptor()  # ... and its CAN node's burst corruption
    gnss_timeline = device_timeline(s.events, "gnss")  # the live gnss_emulator's announcements
    not_sent: dict[str, int] = {}
    warnings, ignored = not_applicable_faults(s.events, duration_s)
    for line in warnings:
        if opts.on_warning is not None:
            opts.on_warning(line)
        else:
            sys.stderr.write(f"hil sim: warning: {line}\n")
            sys.stderr.flush()
    put(out, 0, keys.run(), run)
    put(
        out,
        0,
        keys.event("fusion"),
        Event(
            seq=pubs.next(keys.event("fusion")),
            stamp_ns=0,
            kind=FUSION_CONFIG_EVENT,
            source="fusion",
            detail=fusion_config_detail(cfg),
        ),
    )
    rate_hz = float(s.imu.rate_hz)
    dt_ns = round(1e9 / rate_hz)
    n_imu = round(duration_s * rate_hz)
    end_ns = int(duration_s * 1e9)
    truth_dt = round(1e9 / TRUTH_RATE_HZ)
    k_imu = 0
    k_truth = 0
    next_pps = 1_000_000_000
    next_clock = 1_000_000_000
    next_journal = 500_000_000
    gnss_pending: list[tuple[int, int, Any, int]] = []
    gnss_counter = 0
    t_win = 0
    channel = "vcan0"
    indexer = ImuSampleIndexer(dt_ns)
    seen_status = seen_lost = 0
    can_last_rx = -(2**62)
    # frames that left the emulator, not yet on the bus: (time left, order, nominal rx, frame)
    wire: list[tuple[int, int, int, Any]] = []
    wire_order = itertools.count()
    can_delay: DelayLine[None] = DelayLine(sensor_rng(s.seed, "imu.can_latency"))  # as live
    arrivals: list[tuple[int, int, ImuSample | GnssFix]] = []

    def bus_deliver(t_now: int, last_rx: int) -> int:
        """Frames that left the emulator at or before ``t_now``, in the order they left, onto
        the FIFO bus and into the bridge's assembler and the time sync (as rx stamps them)."""
        nonlocal seen_status, seen_lost
        while wire and wire[0][0] <= t_now:
            _t_emit, _o, nominal, fr = heapq.heappop(wire)
            corruptor(fr)  # on the wire, in wire order, as the live node's _send does
            rx = max(nominal, last_rx + CAN_FRAME_TIME_NS)  # the bus is FIFO
            last_rx = rx
            fr.timestamp = rx * 1e-9
            put(out, rx, keys.can(channel), can_frame_msg(pubs.next(keys.can(channel)), rx, channel, fr))
            for item in assembler.feed(fr):
                if hasattr(item, "dtheta_b_rad"):
                    c = assembler.counters
                    n_status, n_lost = c["status"], c["lost_frames"] + c["incomplete_sample"]
                    count = assembler.last_sample_count if n_status != seen_status else None
                    step = indexer.next(item.device_stamp_ns, count, n_lost != seen_lost)
                    assert step is not None  # the sim's bridge listens from the first frame
                    idx, dtn = step
                    seen_status, seen_lost = n_status, n_lost
                    raw = imu_sample_msg(idx, rx, dtn, item)
                    put(out, rx, keys.sensor("imu"), raw)
                    for m, t_rig in sync.on_measurement("imu", raw.device_stamp_ns, rx, raw):
                        synced = msgspec.structs.replace(m, stamp_ns=t_rig)
                        put(out, rx, keys.synced(m.sensor), synced)
                        arrivals.append((rx, len(arrivals), synced))
                else:
                    tag = TimeTag(
                        seq=pubs.next(keys.timetag("imu")),
                        stamp_ns=rx,
                        sensor="imu",
                        kind="sync_frame",
                        device_stamp_ns=item.device_stamp_ns,
                    )
                    put(out, rx, keys.timetag("imu"), tag)
                    sync.on_timetag("imu", item.device_stamp_ns, rx)
        return last_rx

    while t_win < end_ns + WINDOW_NS:
        t_end = min(t_win + WINDOW_NS, end_ns + 1)
        arrivals: list[tuple[int, int, ImuSample | GnssFix]] = []  # (rx, order, synced msg)
        while ignored and ignored[0][0] < t_end:
            t_ig, detail = ignored.pop(0)
            event(t_ig, "sim", "fault_ignored", detail)
        # truth
        n_t = max(0, min((t_end - 1) // truth_dt + 1, end_ns // truth_dt + 1) - k_truth)
        if n_t:
            tt = np.arange(k_truth, k_truth + n_t, dtype=np.int64) * truth_dt
            b = truth.sample(tt)
            for i in range(n_t):
                put(
                    out,
                    int(tt[i]),
                    keys.truth(),
                    truth_msg(pubs.next(keys.truth()), int(tt[i]), b, i),
                )
            k_truth += n_t
        # IMU: physics -> wire -> assembler -> raw sample -> synced sample
        n_i = max(0, min(n_imu, (t_end - 1) // dt_ns) - k_imu)
        if n_i:
            batch = imu_core.next_batch(n_i)
            extra = can_rng.exponential(can_jitter_ns, n_i) if can_jitter_ns > 0 else np.zeros(n_i)
            for i in range(n_i):
                t_true = int(batch.t_ns[i])
                dev = imu_clock.device_ns(t_true)
                k = k_imu + i
                # faults exactly as services/imu_emulator.py applies them, sample by sample
                for edge, f in imu_faults.timeline.edges(t_true):
                    detail = fault_detail(f.kind, f.t0_ns, f.t1_ns, f.params, f.origin)
                    event(t_true, "imu_emulator", edge, detail)
                act = imu_faults.apply(k, t_true, batch.dtheta_b_rad[i], batch.dvel_b_mps[i])
                corruptor.arm(act.corrupt_frames)
                # the sync edge is this sample's capture; its frame goes first, kernel-stamped,
                # and is never held by can_latency (the live emulator sends it at once too)
                sync_first = act.send and (k + 1) % round(rate_hz) == 0
                if sync_first:
                    t_sync = imu_clock.latch_ns(t_true) + can_latency_ns + CAN_FRAME_TIME_NS
                    heapq.heappush(wire, (t_true, next(wire_order), t_sync, codec.encode_sync(dev)))
                # encoded even when not sent: the device's counters and SampleCount advance (live too)
                sample_frames = codec.encode_sample(
                    device_stamp_ns=dev, dtheta_b_rad=act.dtheta_b_rad, dvel_b_mps=act.dvel_b_mps
                )
                if act.send:
                    # leaves the emulator when the live DelayLine would release it (at capture
                    # unless can_latency holds it), then the bus latency and extra delay
                    t_emit = can_delay.release_ns(t_true, act.latency_ns, act.jitter_ns)
                    t_burst = t_emit + can_latency_ns + round(float(extra[i]))
                    for j, fr in enumerate(sample_frames, start=1 if sync_first else 0):
                        nominal = t_burst + (j + 1) * CAN_FRAME_TIME_NS
                        heapq.heappush(wire, (t_emit, next(wire_order), nominal, fr))
                else:
                    not_sent[act.reason] = not_sent.get(act.reason, 0) + 1
                put(
                    out,
                    t_true,
                    keys.capture("imu"),
                    CaptureTruth(seq=k, stamp_ns=t_true, sensor="imu", true_stamp_ns=t_true),
                )
                # what has left the emulator by now is on the bus, in the order it left
                can_last_rx = bus_deliver(t_true, can_last_rx)
            can_last_rx = bus_deliver(t_end - 1, can_last_rx)
            k_imu += n_i
        # GNSS: the core applies the timed faults; the emulator announces their edges
        for edge, f in gnss_timeline.edges(min(t_end - 1, end_ns)):
            event(
                edge_time_ns(edge, f),
                "gnss_emulator",
                edge,
                fault_detail(f.kind, f.t0_ns, f.t1_ns, f.params, f.origin),
            )
        # GNSS: fixes come out at their output time (validity + latency)
        gb = gnss_core.next_batch(min(t_end - 1, end_ns))
        for i in range(len(gb.t_valid_ns)):
            heapq.heappush(gnss_pending, (int(gb.t_output_ns[i]), gnss_counter, gb, i))
            gnss_counter += 1
        gnss_events: list[tuple[int, int, Any]] = []  # (rig time, order, fix index or None)
        while gnss_pending and gnss_pending[0][0] < t_end:
            t_out, _c, gb_i, i = heapq.heappop(gnss_pending)
            gnss_events.append((t_out, len(gnss_events), (gb_i, i)))
        while next_pps < t_end and next_pps <= end_ns:
            gnss_events.append((gnss_clock.latch_ns(next_pps), len(gnss_events), next_pps))
            next_pps += 1_000_000_000
        gnss_events.sort(key=lambda e: (e[0], e[1]))
        for t_ev, _o, ev in gnss_events:
            if isinstance(ev, int):  # a PPS edge at true time ev, latched at t_ev
                dev_edge = gnss_clock.device_ns(ev)
                put(
                    out,
                    t_ev,
                    keys.timetag("gnss"),
                    TimeTag(
                        seq=pubs.next(keys.timetag("gnss")),
                        stamp_ns=t_ev,
                        sensor="gnss",
                        kind="pps",
                        device_stamp_ns=dev_edge,
                    ),
                )
                sync.on_timetag("gnss", dev_edge, t_ev)
                continue
            gb_i, i = ev
            t_out = t_ev
            t_valid = int(gb_i.t_valid_ns[i])
            seq = pubs.next(keys.sensor("gnss"))
            raw = gnss_fix_msg(seq, t_out, gnss_clock.device_ns(t_valid), gb_i, i)
            put(out, t_out, keys.sensor("gnss"), raw)
            put(
                out,
                t_out,
                keys.capture("gnss"),
                CaptureTruth(seq=seq, stamp_ns=t_valid, sensor="gnss", true_stamp_ns=t_valid),
            )
            for m, t_rig in sync.on_measurement("gnss", raw.device_stamp_ns, t_out, raw):
                synced = msgspec.structs.replace(m, stamp_ns=t_rig)
                put(out, t_out, keys.synced(m.sensor), synced)
                arrivals.append((t_out, len(arrivals), synced))
        # fusion consumes in arrival order, exactly like the live service's inbox
        arrivals.sort(key=lambda a: (a[0], a[1]))
        for rx, _o, msg in arrivals:
            while next_journal <= rx:
                put(
                    out,
                    next_journal,
                    keys.journal(),
                    fusion.journal(pubs.next(keys.journal()), next_journal),
                )
                next_journal += 500_000_000
            for sol in fusion.push(msg):
                put(out, rx, keys.nav(sol.estimator), sol)
        while next_clock < t_end and next_clock <= end_ns:
            for m in list(sync.mappings.values()):
                put(
                    out,
                    next_clock,
                    keys.clock(m.sensor),
                    clock_model_msg(pubs.next(keys.clock(m.sensor)), next_clock, m),
                )
            next_clock += 1_000_000_000
        # the fault-relevant counters of the emulator and the bridge cores, as of this window's end
        imu_counters = {f"fault.imu_samples_not_sent.{r}": n for r, n in sorted(not_sent.items())}
        imu_counters.update(
            tx_fault_dropped_samples=sum(not_sent.values()),
            tx_corrupted_frames=corruptor.corrupted,
            tx_saturated_samples=codec.saturated_samples,
        )
        if can_delay.delayed:  # as the live emulator reports it (absent when never delayed)
            imu_counters["fault.can_latency.delayed_samples"] = can_delay.delayed
        bridge_counters = {f"can.{k}": v for k, v in assembler.counters.items()}
        for svc, counters in (("imu_emulator", imu_counters), ("can_bridge", bridge_counters)):
            if t_end == end_ns:  # the 1 ns window of the last sample follows: it reports
                break
            key = keys.status(svc)
            put(out, t_end, key, sim_status(pubs.next(key), t_end, svc, counters))
        t_win += WINDOW_NS
        if t_win > end_ns:
            t_last = end_ns + 1
            for m, t_rig in sync.flush():  # measurements still held at the end of input
                synced = msgspec.structs.replace(m, stamp_ns=t_rig)
                put(out, t_last, keys.synced(m.sensor), synced)
                for sol in fusion.push(synced):
                    put(out, t_last, keys.nav(sol.estimator), sol)
            for sol in fusion.flush():
                put(out, t_last, keys.nav(sol.estimator), sol)
            put(
                out,
                t_last,
                keys.journal(),
                fusion.journal(pubs.next(keys.journal()), t_last),
            )
        flush(out)
        w.flush()
        if opts.on_progress is not None:
            opts.on_progress(min(t_win, end_ns) * 1e-9, duration_s)
    w.add_metadata("completeness", {"messages": n_written, "missing": 0, "replay_ready": True, "topics": {}})
    w.close()
    _ = FREE_INS
    return SimResult(opts.record, n_written, duration_s, time.monotonic() - t_wall, warnings)


def not_applicable_faults(events: Any, duration_s: float) -> tuple[list[str], list[tuple[int, str]]]:
    """The scenario's timed faults ``hil sim`` cannot apply: warning lines, and (t_ns, detail) of
    the ``fault_ignored`` events that record them (only those inside the run, as live)."""
    lines: list[str] = []
    ignored: list[tuple[int, str]] = []
    for ev in events:
        if ev.kind not in SIM_NOT_APPLICABLE or ev.t_start_s > duration_s:
            continue
        t0 = round(ev.t_start_s * 1e9)
        target = ev.params.get("service", "")
        lines.append(
            f"{ev.kind} of {target!r} at t={ev.t_start_s:g} s is not applied: hil sim runs every core "
            "in one process, there is no service to kill (use hil up; recorded as event fault_ignored)"
        )
        params = {"service": target, "reason": "offline"}
        ignored.append((t0, fault_detail(ev.kind, t0, None, params, "scenario")))
    ignored.sort()
    return lines, ignored


def sim_status(seq: int, t_ns: int, service: str, counters: dict[str, int]) -> ServiceStatus:
    """A core's counters as its live service would report them; nothing host-dependent (pid 0,
    uptime in rig time, no rates), so the file stays a pure function of the scenario."""
    return ServiceStatus(
        seq=seq,
        stamp_ns=t_ns,
        service=service,
        state="running",
        pid=0,
        uptime_s=t_ns / 1e9,
        counters=counters,
    )


def _fields(m: Message) -> dict[str, Any]:
    return {f: getattr(m, f) for f in m.__struct_fields__}

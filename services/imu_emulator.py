"""imu_emulator: an IMU as a CAN node -- samples paced on the sample clock, sent as DBC frames.

The physics (truth -> sensor errors -> increments) is ``hil.sensors.imu.ImuEmulatorCore``; the
wire (DBC codec, counters, CRC, back-off, bus load) is ``hil.can.node.ImuCanNode``. This module
only paces them on the rig clock. Every sample's true capture time goes to ``capture/imu``.

Restarted mid-run (option ``resume``, or the run already more than ``RESUME_AFTER_S`` old), the
device resumes at the sample index of the current rig time -- not at 0, which would burst the
whole past onto the bus. The codec's SampleCount starts at that index and the first sample
carries a status frame, so the bridge's ``seq`` (the device sample index) continues without
colliding with the samples sent before the restart; the samples of the dead time are a seq gap.
Calibration errors (turn-on bias, scale factor, misalignment) are drawn from the scenario seed
and so survive the restart; the noise after it is a fresh stream (a power-cycled device).
"""

from __future__ import annotations

import argparse
import logging
from typing import Any

from hil.faults import IMU_FAULTS, CommandInbox, DelayLine, ImuFaults, fault_detail
from hil.messages import CaptureTruth, FaultCommand, RunInfo
from hil.runtime.clock import RigClock
from hil.runtime.scenario_io import scenario_for_run
from hil.runtime.service import Service, run_service
from hil.sensors.clock import device_clock_for

log = logging.getLogger(__name__)
GENERATE_AHEAD_S = 0.1  # physics computed this far ahead of the wire
RESUME_AFTER_S = 2.0  # a start this late into the run is a restart: resume, do not burst the past


class ImuEmulator(Service):
    name = "imu_emulator"

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self._commands = CommandInbox(IMU_FAULTS, "imu", self.stats)

    def setup(self) -> None:
        self.subscribe(self.keys.control("fault"), FaultCommand, self._commands.on_command)
        # Import the numerics before reporting ready: a late start would burst samples at time zero.
        import hil.can.bus
        import hil.can.codec
        import hil.can.node
        import hil.nav.trajectory
        import hil.sensors.imu  # noqa: F401

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        from hil.can.bus import open_can_bus
        from hil.can.codec import ImuCanCodec
        from hil.can.node import ImuCanNode
        from hil.nav.trajectory import TruthGenerator
        from hil.sensors.imu import ImuEmulatorCore, sensor_rng

        opts = self.ctx.options
        s = scenario_for_run(run)
        core = ImuEmulatorCore(s, TruthGenerator(s), sensor_rng(s.seed, "imu"))
        dev_clock = device_clock_for(s, "imu")
        fd = bool(opts.get("fd", False))
        bus, desc = open_can_bus(
            opts.get("channel", "vcan0"), opts.get("interface"), fd=fd, rig=self.keys.rig
        )
        print(f"[imu_emulator] CAN: {desc}", flush=True)  # noqa: T201 - the one start-up line users need
        node = ImuCanNode(bus, ImuCanCodec.from_dbc(fd=fd), self.stats)
        self._node = node
        cap_pub = self.publisher(self.keys.capture("imu"), CaptureTruth)
        rate_hz = float(s.imu.rate_hz)
        dt_ns = round(1e9 / rate_hz)
        n_total = round(run.duration_s * rate_hz)
        sync_every = max(1, round(rate_hz))  # one sync/time-tag frame per second
        k = 0  # samples sent; sample k ends at (k+1)*dt
        now = clock.now_ns()
        if opts.get("resume") or now > RESUME_AFTER_S * 1e9:
            k = min(max(0, now // dt_ns), n_total)
            core.count = k  # next_batch starts at the interval ending at (k+1)*dt
            node.codec.samples_encoded = k  # SampleCount = device sample index
            self.emit_event(
                "resumed", f"imu_emulator restarted: resumes at sample {k} (t={k * dt_ns / 1e9:.3f} s)"
            )
        # The physics runs ahead in blocks (its output does not depend on block size); only the
        # wire is paced sample by sample, so the per-sample cost is the CAN send alone.
        ahead = max(1, int(rate_hz * GENERATE_AHEAD_S))
        batch = None
        i = 0
        faults = ImuFaults(s.seed, s.events)
        # can_latency: every sample's frames go through the delay line (released at once when no
        # window is active); the sync frame does not -- it is the time tag (see below)
        delay: DelayLine[list[Any]] = DelayLine(sensor_rng(s.seed, "imu.can_latency"))
        self._delay = delay
        try:
            while k < n_total and not self.ctx.stop.is_set():
                now = clock.now_ns()
                for frames in delay.due(now):
                    node.send_frames(frames)
                due = min(now // dt_ns, n_total) - k
                if due <= 0:
                    wake = (k + 1) * dt_ns
                    held = delay.next_release_ns()
                    clock.sleep_until(wake if held is None else min(wake, held), self.ctx.stop)
                    continue
                for _ in range(due):
                    if batch is None or i >= len(batch.t_ns):
                        batch = core.next_batch(min(ahead, n_total - k))
                        i = 0
                    t_true = int(batch.t_ns[i])
                    if self._commands:
                        self._take_commands(faults, dev_clock, t_true)
                    for edge, f in faults.timeline.edges(t_true):
                        self.emit_event(edge, fault_detail(f.kind, f.t0_ns, f.t1_ns, f.params, f.origin))
                    act = faults.apply(k, t_true, batch.dtheta_b_rad[i], batch.dvel_b_mps[i])
                    dev = dev_clock.device_ns(t_true)
                    if act.corrupt_frames:
                        node.corrupt_next(act.corrupt_frames)
                    if act.send and (k + 1) % sync_every == 0:
                        # the sync edge is this capture: its frame goes first and is never held
                        # by can_latency -- it is the time tag the rig's sync measures the
                        # transport against, so a held data path shows as late arrivals
                        node.send_sync(dev)
                    frames = node.encode_sample(dev, act.dtheta_b_rad, act.dvel_b_mps, drop=not act.send)
                    if frames is not None:
                        delay.push(t_true, act.latency_ns, act.jitter_ns, frames)
                        for ready in delay.due(now):  # no can_latency: this sample, now
                            node.send_frames(ready)
                    if not act.send:
                        self.stats.inc(f"fault.imu_samples_not_sent.{act.reason}")
                    cap_pub.put(CaptureTruth(seq=k, stamp_ns=t_true, sensor="imu", true_stamp_ns=t_true))
                    i += 1
                    k += 1
            while delay and not self.ctx.stop.is_set():  # the last samples' held frames
                clock.sleep_until(delay.next_release_ns() or 0, self.ctx.stop)
                for frames in delay.due(clock.now_ns()):
                    node.send_frames(frames)
            self.ctx.stop.wait()
        finally:
            bus.shutdown()

    def _take_commands(self, faults: ImuFaults, dev_clock: Any, t_ns: int) -> None:
        cmds = self._commands.take()
        for cmd in cmds:
            if cmd.kind == "clock_step":
                dev_clock.add_step(t_ns, round(cmd.params["step_s"] * 1e9))
                self.emit_event("fault_start", fault_detail(cmd.kind, t_ns, None, cmd.params, "command"))
                continue
            faults.timeline.add(cmd.kind, t_ns, cmd.duration_s, dict(cmd.params))

    def extra_status(self) -> dict[str, int]:
        node = getattr(self, "_node", None)
        if node is None:
            return {}
        out = dict(node.counters())
        out["bus_load_permille"] = int(node.bus_load() * 1000)
        delay = getattr(self, "_delay", None)
        if delay is not None and delay.delayed:
            out["fault.can_latency.delayed_samples"] = delay.delayed  # pushed with latency/jitter
        return out


SERVICE = ImuEmulator


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hil service imu_emulator")
    ap.add_argument("--rig", default="default")
    ap.add_argument("--channel", default="vcan0")
    ap.add_argument(
        "--interface",
        default=None,
        help="python-can interface (default: socketcan if the channel exists, else hilzenoh)",
    )
    ap.add_argument("--fd", action="store_true", help="CAN FD: one frame per sample")
    a = ap.parse_args(argv)
    return run_service(ImuEmulator, a.rig, {"channel": a.channel, "interface": a.interface, "fd": a.fd})

"""imu_emulator: an IMU as a CAN node -- samples paced on the sample clock, sent as DBC frames.

The physics (truth -> sensor errors -> increments) is ``hil.sensors.imu.ImuEmulatorCore``; the
wire (DBC codec, counters, CRC, back-off, bus load) is ``hil.can.node.ImuCanNode``. This module
only paces them on the rig clock. Every sample's true capture time goes to ``capture/imu``.
"""

from __future__ import annotations

import argparse
import logging

from hil.messages import CaptureTruth, RunInfo
from hil.runtime.clock import RigClock
from hil.runtime.scenario_io import scenario_for_run
from hil.runtime.service import Service, run_service
from hil.sensors.clock import device_clock_for

log = logging.getLogger(__name__)
GENERATE_AHEAD_S = 0.1  # physics computed this far ahead of the wire


class ImuEmulator(Service):
    name = "imu_emulator"

    def setup(self) -> None:
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
        # The physics runs ahead in blocks (its output does not depend on block size); only the
        # wire is paced sample by sample, so the per-sample cost is the CAN send alone.
        ahead = max(1, int(rate_hz * GENERATE_AHEAD_S))
        batch = None
        i = 0
        try:
            while k < n_total and not self.ctx.stop.is_set():
                due = min(clock.now_ns() // dt_ns, n_total) - k
                if due <= 0:
                    clock.sleep_until((k + 1) * dt_ns, self.ctx.stop)
                    continue
                for _ in range(due):
                    if batch is None or i >= len(batch.t_ns):
                        batch = core.next_batch(min(ahead, n_total - k))
                        i = 0
                    t_true = int(batch.t_ns[i])
                    dev = dev_clock.device_ns(t_true)
                    if (k + 1) % sync_every == 0:
                        node.send_sync(dev)  # the sync edge is this capture: its frame goes first
                    node.send_sample(dev, batch.dtheta_b_rad[i], batch.dvel_b_mps[i])
                    cap_pub.put(CaptureTruth(seq=k, stamp_ns=t_true, sensor="imu", true_stamp_ns=t_true))
                    i += 1
                    k += 1
            self.ctx.stop.wait()
        finally:
            bus.shutdown()

    def extra_status(self) -> dict[str, int]:
        node = getattr(self, "_node", None)
        if node is None:
            return {}
        out = dict(node.counters())
        out["bus_load_permille"] = int(node.bus_load() * 1000)
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

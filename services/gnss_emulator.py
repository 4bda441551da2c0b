"""gnss_emulator: a receiver that outputs fixes late (latency + jitter) and raises a PPS edge.

The fix's time of validity is stamped on the receiver clock (``device_stamp_ns``); its true
capture time goes to ``capture/gnss`` so synchronisation error is measurable from a recording.
"""

from __future__ import annotations

import argparse
import heapq
from typing import Any

from hil.messages import CaptureTruth, GnssFix, RunInfo, TimeTag
from hil.runtime.builders import gnss_fix_msg
from hil.runtime.clock import RigClock
from hil.runtime.scenario_io import scenario_for_run
from hil.runtime.service import Service, run_service
from hil.sensors.clock import device_clock_for


class GnssEmulator(Service):
    name = "gnss_emulator"

    def setup(self) -> None:
        # Import the numerics before reporting ready: a late start would burst samples at time zero.
        import hil.nav.trajectory
        import hil.sensors.gnss
        import hil.sensors.imu  # noqa: F401

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        from hil.nav.trajectory import TruthGenerator
        from hil.sensors.gnss import GnssEmulatorCore
        from hil.sensors.imu import sensor_rng

        s = scenario_for_run(run)
        core = GnssEmulatorCore(s, TruthGenerator(s), sensor_rng(s.seed, "gnss"))
        dev_clock = device_clock_for(s, "gnss")
        fix_pub = self.publisher(self.keys.sensor("gnss"), GnssFix)
        cap_pub = self.publisher(self.keys.capture("gnss"), CaptureTruth)
        pps_pub = self.publisher(self.keys.timetag("gnss"), TimeTag)
        end_ns = int(run.duration_s * 1e9)
        poll_ns = int(0.02e9)
        pending: list[tuple[int, int, Any, int]] = []  # (t_output, idx, batch, i)
        next_pps_s = 1
        t_pulled = -1
        counter = 0
        while not self.ctx.stop.is_set():
            now = clock.now_ns()
            if t_pulled < min(now, end_ns):
                t_pulled = min(now, end_ns)
                b = core.next_batch(t_pulled)
                for i in range(len(b.t_valid_ns)):
                    heapq.heappush(pending, (int(b.t_output_ns[i]), counter, b, i))
                    counter += 1
            while pending and pending[0][0] <= now:
                _t_out, _c, b, i = heapq.heappop(pending)
                self._publish_fix(fix_pub, cap_pub, b, i, dev_clock, clock)
            while next_pps_s * 1_000_000_000 <= min(now, end_ns):
                t_edge = next_pps_s * 1_000_000_000
                pps_pub.put(
                    TimeTag(
                        seq=pps_pub.next_seq(),
                        stamp_ns=dev_clock.latch_ns(t_edge),  # latched on the rig clock (latch jitter)
                        sensor="gnss",
                        kind="pps",
                        device_stamp_ns=dev_clock.device_ns(t_edge),
                    )
                )
                next_pps_s += 1
            if now > end_ns and not pending:
                self.ctx.stop.wait()
                break
            nxt = min([pending[0][0]] if pending else [now + poll_ns]) if pending else now + poll_ns
            clock.sleep_until(min(nxt, now + poll_ns), self.ctx.stop)

    def _publish_fix(
        self, fix_pub: Any, cap_pub: Any, b: Any, i: int, dev_clock: Any, clock: RigClock
    ) -> None:
        seq = fix_pub.next_seq()
        t_valid = int(b.t_valid_ns[i])
        rx = clock.now_ns()
        fix_pub.put(gnss_fix_msg(seq, rx, dev_clock.device_ns(t_valid), b, i))
        cap_pub.put(CaptureTruth(seq=seq, stamp_ns=t_valid, sensor="gnss", true_stamp_ns=t_valid))


SERVICE = GnssEmulator


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(prog="hil service gnss_emulator")
    ap.add_argument("--rig", default="default")
    a = ap.parse_args(argv)
    return run_service(GnssEmulator, a.rig, {})

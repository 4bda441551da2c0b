"""gnss_emulator: a receiver that outputs fixes late (latency + jitter) and raises a PPS edge.

The fix's time of validity is stamped on the receiver clock (``device_stamp_ns``); its true
capture time goes to ``capture/gnss`` so synchronisation error is measurable from a recording.

``seq`` of a fix (and of its capture truth) is the receiver's output index: the number of epochs
it output before this one in the scenario, omitted outage epochs not counted (so an outage is not
a seq gap). It is computed from the scenario, not counted by the process, so a restarted
receiver (option ``resume``, or a start more than ``RESUME_AFTER_S`` into the run) skips the
epochs of the time it was dead -- a seq gap, honest loss -- and never reuses a seq. The PPS
``seq`` is the PPS second minus one, for the same reason.
"""

from __future__ import annotations

import argparse
import heapq
from typing import Any

from hil.faults import GNSS_FAULTS, CommandInbox, FaultTimeline, device_timeline, fault_detail
from hil.messages import CaptureTruth, FaultCommand, GnssFix, RunInfo, TimeTag
from hil.runtime.builders import gnss_fix_msg
from hil.runtime.clock import RigClock
from hil.runtime.scenario_io import scenario_for_run
from hil.runtime.service import Service, run_service
from hil.sensors.clock import device_clock_for

RESUME_AFTER_S = 2.0


class GnssEmulator(Service):
    """Faults: the scenario's timed GNSS events are applied by the core (hil/sensors/gnss.py) and
    announced here as ``fault_start``/``fault_end`` events when rig time passes their edges;
    commanded ones (``control/fault``) become scenario-like events from the current rig time on."""

    name = "gnss_emulator"

    def __init__(self, ctx: Any) -> None:
        super().__init__(ctx)
        self._commands = CommandInbox(GNSS_FAULTS, "gnss", self.stats)
        # seq of the next fix: the output index, derived from the scenario (not the publisher's
        # restart-generation counter), so synced/gnss and the fusion's gnss_seq keep their meaning
        self._fix_index = 0

    def _take_commands(self, core: Any, dev_clock: Any, timeline: FaultTimeline, now: int) -> None:
        from hil.nav.scenario import ScenarioEvent

        cmds = self._commands.take()
        for cmd in cmds:
            p = cmd.params
            if cmd.kind == "clock_step":
                dev_clock.add_step(now, round(p["step_s"] * 1e9))
                self.emit_event("fault_start", fault_detail(cmd.kind, now, None, p, "command"))
                continue
            params: dict[str, Any] = {}
            if cmd.kind == "gnss_jump":
                params["offset_ned_m"] = (p.get("n_m", 0.0), p.get("e_m", 0.0), p.get("d_m", 0.0))
            elif cmd.kind == "gnss_velocity_glitch":
                params["offset_ned_mps"] = (p.get("n_mps", 0.0), p.get("e_mps", 0.0), p.get("d_mps", 0.0))
            elif cmd.kind == "gnss_latency":
                params.update(p)
            t0 = now / 1e9
            t1 = t0 + cmd.duration_s if cmd.duration_s > 0 and cmd.kind != "gnss_latency" else None
            core._events = (*core._events, ScenarioEvent(cmd.kind, t0, t1, params))
            timeline.add(cmd.kind, now, cmd.duration_s if t1 is not None else 0.0, params)

    def setup(self) -> None:
        self.subscribe(self.keys.control("fault"), FaultCommand, self._commands.on_command)
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
        timeline = device_timeline(s.events, "gnss")  # what hil sim announces too
        now = clock.now_ns()
        if self.ctx.options.get("resume") or now > RESUME_AFTER_S * 1e9:
            # skip what was due while dead; the core still draws its noise (same stream after)
            t_pulled = min(now, end_ns)
            skipped = len(core.next_batch(t_pulled).t_valid_ns)
            self._fix_index = skipped
            next_pps_s = now // 1_000_000_000 + 1
            self.emit_event(
                "resumed", f"gnss_emulator restarted at t={now / 1e9:.3f} s: resumes at fix seq {skipped}"
            )
        while not self.ctx.stop.is_set():
            now = clock.now_ns()
            if self._commands:
                self._take_commands(core, dev_clock, timeline, now)
            for edge, f in timeline.edges(now):
                self.emit_event(edge, fault_detail(f.kind, f.t0_ns, f.t1_ns, f.params, f.origin))
            if t_pulled < min(now, end_ns) and core.has_due(min(now, end_ns)):
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
                        seq=next_pps_s - 1,  # the PPS second: a restart never reuses a seq
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
        seq = self._fix_index
        self._fix_index += 1
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

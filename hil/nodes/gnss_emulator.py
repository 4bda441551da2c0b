"""The GNSS receiver: fixes at their output time (validity + latency + jitter) and a PPS edge.

An epoch is computed at its time of validity (``hil.sensors.gnss.GnssEmulatorCore``: truth,
the seed paper's error model, the scenario's faults) and output ``latency + jitter`` later, its
validity stamped on the receiver clock (``device_stamp_ns``); its true capture time goes to
``capture/gnss``, so sync error is measurable from a recording. The PPS edge of each second is
latched on the rig clock (``latch_ns``: latch jitter) and published at that instant as a
``TimeTag``. Fault edges (timed, or commanded on ``control/fault`` and applied from that rig
time on) are announced as ``fault_start``/``fault_end`` events at the edge's time.

``seq`` of a fix (and of its capture truth) is the receiver's output index: epochs output before
it in the scenario, outage epochs not counted (an outage is no seq gap). A restarted receiver
(option ``resume``, or a start more than ``RESUME_AFTER_S`` into the run) skips the epochs of the
time it was dead -- a seq gap, honest loss -- and never reuses a seq. The PPS ``seq`` is the PPS
second minus one, for the same reason. Nothing is output after the run's end except the latch of
its last PPS edge.
"""

from __future__ import annotations

import heapq
from typing import Any

from hil.faults import GNSS_FAULTS, FaultError, check_fault, command_addressee, device_timeline, edge_time_ns
from hil.faults import fault_detail as _detail
from hil.messages import CaptureTruth, FaultCommand, TimeTag
from hil.nav.scenario import ScenarioEvent, scenario_for_run
from hil.nav.trajectory import TruthGenerator
from hil.nodes.base import Input, Node, Out
from hil.nodes.builders import gnss_fix_msg
from hil.sensors.clock import device_clock_for
from hil.sensors.gnss import GnssEmulatorCore
from hil.sensors.imu import sensor_rng

RESUME_AFTER_S = 2.0
_S = 1_000_000_000


class GnssEmulatorNode(Node):
    name = "gnss_emulator"
    inputs = (Input("control/fault", {"control": FaultCommand}),)
    outputs = ("sensor/gnss", "capture/gnss", "timetag/gnss")

    def __init__(self, run: Any, options: Any = None) -> None:
        super().__init__(run, options)
        s = scenario_for_run(run)
        self.core = GnssEmulatorCore(s, TruthGenerator(s), sensor_rng(s.seed, "gnss"))
        self.clock = device_clock_for(s, "gnss")
        self.timeline = device_timeline(s.events, "gnss")
        self.end_ns = int(run.duration_s * 1e9)
        self._pending: list[tuple[int, int, Any, int]] = []  # (t_output, order, batch, row)
        self._order = 0
        self.fix_index = 0  # seq of the next fix: the output index
        self.next_pps_s = 1

    def start(self, now_ns: int) -> list[Out]:
        if not (self.options.resume or now_ns > RESUME_AFTER_S * 1e9):
            return []
        # skip what was due while dead; the core still draws its noise (the same stream after)
        skipped = len(self.core.next_batch(min(now_ns, self.end_ns)).t_valid_ns)
        self.fix_index = skipped
        self.next_pps_s = now_ns // _S + 1
        detail = f"gnss_emulator restarted at t={now_ns / 1e9:.3f} s: resumes at fix seq {skipped}"
        return [self.event("resumed", detail, now_ns)]

    def next_tick_ns(self) -> int | None:
        times = [self.core.next_epoch_ns(), self.timeline.next_edge_ns()]
        if self._pending:
            times.append(self._pending[0][0])
        times = [t for t in times if t is not None and t <= self.end_ns]
        if self.next_pps_s * _S <= self.end_ns:  # an edge within the run, latched maybe just after
            times.append(self.clock.latch_ns(self.next_pps_s * _S))
        return min(times) if times else None

    def on_message(self, key: str, msg: Any, now_ns: int) -> list[Out]:
        if key != "control/fault":
            return []
        mine, nobodys = command_addressee(msg, GNSS_FAULTS, "gnss")
        if not (mine or nobodys):
            return []
        try:
            check_fault(msg.kind, msg.target, msg.params)
        except FaultError as err:
            self.error("rejected.control.fault", str(err))
            return []
        return self._apply(msg, now_ns) if mine else []

    def _apply(self, cmd: FaultCommand, now_ns: int) -> list[Out]:
        """A commanded fault from ``now_ns`` on: as a scenario event the core applies to the
        epochs it has not computed yet, and on the timeline that announces its edges."""
        p = cmd.params
        if cmd.kind == "clock_step":
            self.clock.add_step(now_ns, round(p["step_s"] * 1e9))
            return [self.event("fault_start", _detail(cmd.kind, now_ns, None, p, "command"), now_ns)]
        params: dict[str, Any] = {}
        if cmd.kind == "gnss_jump":
            params["offset_ned_m"] = (p.get("n_m", 0.0), p.get("e_m", 0.0), p.get("d_m", 0.0))
        elif cmd.kind == "gnss_velocity_glitch":
            params["offset_ned_mps"] = (p.get("n_mps", 0.0), p.get("e_mps", 0.0), p.get("d_mps", 0.0))
        elif cmd.kind == "gnss_latency":
            params.update(p)
        t0 = now_ns / 1e9
        t1 = t0 + cmd.duration_s if cmd.duration_s > 0 and cmd.kind != "gnss_latency" else None
        self.core.add_event(ScenarioEvent(cmd.kind, t0, t1, params))
        self.timeline.add(cmd.kind, now_ns, cmd.duration_s if t1 is not None else 0.0, params)
        return []

    def tick(self, now_ns: int) -> list[Out]:
        outs: list[Out] = []
        for edge, f in self.timeline.edges(min(now_ns, self.end_ns)):
            detail = _detail(f.kind, f.t0_ns, f.t1_ns, f.params, f.origin)
            outs.append(self.event(edge, detail, edge_time_ns(edge, f)))
        if self.core.has_due(min(now_ns, self.end_ns)):
            b = self.core.next_batch(min(now_ns, self.end_ns))
            for i in range(len(b.t_valid_ns)):
                t_out = int(b.t_output_ns[i])
                if t_out <= self.end_ns:  # the receiver's output after the run is not the run's
                    heapq.heappush(self._pending, (t_out, self._order, b, i))
                    self._order += 1
        while self._pending and self._pending[0][0] <= now_ns:
            _t, _o, b, i = heapq.heappop(self._pending)
            outs.extend(self._fix(b, i, now_ns))
        while self.next_pps_s * _S <= self.end_ns and self.clock.latch_ns(self.next_pps_s * _S) <= now_ns:
            t_edge = self.next_pps_s * _S
            tag = TimeTag(
                seq=self.next_pps_s - 1,  # the PPS second: a restart never reuses a seq
                stamp_ns=self.clock.latch_ns(t_edge),  # latched on the rig clock (latch jitter)
                sensor="gnss",
                kind="pps",
                device_stamp_ns=self.clock.device_ns(t_edge),
            )
            outs.append(("timetag/gnss", tag))
            self.next_pps_s += 1
        return outs

    def _fix(self, b: Any, i: int, now_ns: int) -> list[Out]:
        seq = self.fix_index
        self.fix_index += 1
        t_valid = int(b.t_valid_ns[i])
        fix = gnss_fix_msg(seq, now_ns, self.clock.device_ns(t_valid), b, i)
        cap = CaptureTruth(seq=seq, stamp_ns=t_valid, sensor="gnss", true_stamp_ns=t_valid)
        return [("sensor/gnss", fix), ("capture/gnss", cap)]

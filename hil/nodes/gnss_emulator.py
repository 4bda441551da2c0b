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

On a wire (option ``protocol``: ``nmea``, ``ubx`` or both on one line) the receiver is what a
device under test would plug in: each epoch becomes the protocol's bytes (``hil.wire``), with the
time of validity as GPS/UTC time from the run's start epoch on the receiver's clock, paced by the
line's UART at ``baud`` (``hil.wire.line.Uart``: what does not fit in the transmit buffer
overruns and is counted), out on ``SERIAL_TX``; the fixes then reach the rig through the
``gnss_bridge`` node that reads the line, so the rig's own fusion sees what the device sees, and
this node publishes no ``sensor/gnss`` itself. On a wire ``seq`` is the epoch index (time of
validity over the period, what the bytes carry), an outage is output as "no fix" epochs as real
receivers do, and UBX's TIM-TP announces each second's PPS. The PPS tag then states the pulse's
receiver time as the line states the fixes' (the published protocol's ``printed_time_ns``:
NMEA's 10 ms), so the pulses and the fixes the rig reads tell one clock.
"""

from __future__ import annotations

import dataclasses
import heapq
from typing import Any

import msgspec

from hil.faults import (
    GNSS_FAULTS,
    LINE_FAULTS,
    RECEIVER_FAULTS,
    FaultError,
    LineFaults,
    check_fault,
    command_addressee,
    device_timeline,
    edge_time_ns,
)
from hil.faults import fault_detail as _detail
from hil.messages import CaptureTruth, FaultCommand, TimeTag
from hil.nav.scenario import DEFAULT_SPOOF_SIGMA_M, ScenarioEvent, scenario_for_run
from hil.nav.trajectory import truth_for
from hil.nodes.base import SERIAL_TX, Input, LineBurst, Node, NodeOptions, Out
from hil.nodes.builders import gnss_fix_msg
from hil.sensors.clock import device_clock_for
from hil.sensors.gnss import GnssEmulatorCore
from hil.sensors.imu import sensor_rng
from hil.wire import protocol as wire_protocol
from hil.wire.base import ReceiverEpoch
from hil.wire.gnss_time import gps_ns_to_utc_ns, utc_ns_to_gps_ns
from hil.wire.line import BITS_PER_BYTE, Uart

RESUME_AFTER_S = 2.0
NO_WIRE = "no wire (--gnss-protocol)"  # why a line fault is fault_ignored
# what a frozen receiver repeats (the wire's frozen epoch keeps the same: all but time, sats, DOP)
_FROZEN_FIELDS = ("lat_deg", "lon_deg", "alt_m", "pos_ned_m", "vel_ned_mps", "pos_sigma_m", "vel_sigma_mps")
_S = 1_000_000_000


VDOP_PER_HDOP = 1.5  # the rig models HDOP only; VDOP and PDOP follow a typical open-sky ratio


class GnssEmulatorOptions(NodeOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    # the receiver's wire: "nmea", "ubx" (both: one line carries both); empty: fixes on Zenoh only
    protocol: list[str] = msgspec.field(default_factory=list)
    # message set, the protocols' names (GGA, RMC, ..., NAV-PVT, NAV-COV, TIM-TP); empty: defaults
    messages: list[str] = msgspec.field(default_factory=list)
    talker: str = "GN"  # NMEA talker ID
    baud: int = 115200  # the line's rate (8N1)
    tx_buffer_bytes: int = 4096  # the UART's transmit buffer: a message beyond it overruns
    port: str = "gnss"  # the line's name (serial/<port>)
    # live: pseudo-terminals linked at these paths (a device's, gpsd's, the rig's bridge's)
    serial_links: list[str] = msgspec.field(default_factory=list)
    tcp_listen: str | None = None  # live: also serve the line over TCP, HOST:PORT
    device: str | None = None  # live: also write to a real serial device (a USB-serial adapter)
    # compute the epochs of each second of rig time at its start (hil sim: fewer, larger batches,
    # the same numbers); 0: each at its time of validity, so a commanded fault applies at once
    pull_block_s: float = 0.0

    def __post_init__(self) -> None:
        check_wire(self.protocol, self.messages, self.talker, self.baud)


def encoder(name: str, messages: list[str], talker: str) -> Any:
    """The protocol ``name`` with the messages of ``messages`` it supports (none: its defaults)."""
    cls = wire_protocol(name)
    return cls(tuple(m for m in messages if m in cls.SUPPORTED_MESSAGES) or None, talker=talker)


#: What the rig's ``gnss_bridge`` needs of an epoch to publish a position fix the fusion takes,
#: and the messages that carry it, per protocol (the decoders: ``hil.wire.nmea.NmeaDecoder``,
#: ``hil.wire.ubx.UbxDecoder``; the bridge's ``_fix``): without a full date a fix is dropped
#: (``dropped.line.undated_fixes``); without a fix type it is published as "no fix" (type 0,
#: position zeroed) and the fusion takes none; NMEA's altitude is GGA's alone (RMC's position
#: without it is at height 0). Velocity is optional: without it the bridge says it is unknown
#: (σ 1 km/s). UBX's NAV-POSLLH + NAV-VELNED carry neither date nor fix type (TIM-TP gives only
#: the GPS week): NAV-PVT carries all of it.
FIX_NEEDS: dict[str, tuple[tuple[str, tuple[str, ...]], ...]] = {
    "nmea": (
        ("date", ("RMC", "ZDA")),
        ("position", ("GGA", "RMC")),
        ("altitude", ("GGA",)),
        ("fix type", ("GSA",)),
    ),
    "ubx": (("date and fix type", ("NAV-PVT",)),),
}
PPS_MESSAGES = {"ubx": ("TIM-TP",)}  # a protocol's time-pulse announcement, sent once a second


def epoch_index(device_ns: int, period_ns: int) -> int:
    """A fix's epoch index from its time of validity on the receiver's clock (the seq of a fix
    read off a line: the bridge's, and the emulator's capture truth of it)."""
    return round(device_ns / period_ns)


def bridge_protocol(protocols: list[str]) -> str:
    """The protocol whose fixes the bridge publishes: UBX if the line carries it (more digits)."""
    return "ubx" if "ubx" in protocols else protocols[0]


def undated_problem(protocols: list[str], messages: list[str]) -> str:
    """Why the bridge can make no usable dated position fix of this message set ("" if it can)."""
    name = bridge_protocol(protocols)
    sent = encoder(name, messages, "GN").messages  # the set it sends (none of its own: the defaults)
    missing = [(what, by) for what, by in FIX_NEEDS.get(name, ()) if not set(by) & set(sent)]
    if not missing:
        return ""
    needs = "; ".join(f"no {what} (add {' or '.join(by)})" for what, by in missing)
    return f"{name} messages {','.join(sent)} give the rig's GNSS bridge no usable fix: {needs}"


#: An epoch as a receiver in flight reports it (3-D fix, 14 satellites): what ``line_load``
#: sizes a message set by (NMEA's fields vary by a few characters with the numbers).
TYPICAL_EPOCH = ReceiverEpoch(
    1_448_000_000_000_000_000, 50.4512345, 30.5234567, 412.3, (12.3, -4.5, 0.2), (1.5, 1.5, 3.0),
    (0.1, 0.1, 0.2), 3, 14, 0.7, 1.26, 1.05,
)  # fmt: skip


def line_load(protocols: list[str], messages: list[str], baud: int, rate_hz: float) -> float:
    """The share of the line (0..1+) the receiver's bytes take at ``rate_hz`` epochs a second:
    each epoch's messages (``TYPICAL_EPOCH`` encoded by the node's own encoders) and UBX's
    TIM-TP once a second where the node sends it, 10 bits a byte (8N1, ``hil.wire.line``).
    Past 1 the UART's transmit buffer fills and epochs overrun (are lost whole)."""
    per_epoch = sum(len(encoder(p, messages, "GN").encode_epoch(TYPICAL_EPOCH)) for p in protocols)
    per_second = 0
    if "ubx" in protocols and (not messages or "TIM-TP" in messages):  # as the node decides
        per_second = len(encoder("ubx", messages, "GN").encode_pps_announcement(TYPICAL_EPOCH.gps_time_ns))
    return (per_epoch * rate_hz + per_second) * BITS_PER_BYTE / baud


def check_wire(protocols: list[str], messages: list[str], talker: str, baud: int) -> None:
    """Refuse a wire that cannot be built: an unknown protocol or message, a bad talker or baud,
    or a message set the rig's bridge can make no dated position fix of (``FIX_NEEDS``)."""
    for name in protocols:
        encoder(name, messages, talker)  # KeyError naming the known ones, ValueError
    known = {
        m
        for name in protocols
        for m in (*wire_protocol(name).SUPPORTED_MESSAGES, *PPS_MESSAGES.get(name, ()))
    }
    unknown = [m for m in messages if m not in known]
    if protocols and unknown:
        raise ValueError(f"messages {unknown} are not in {sorted(protocols)}; known: {sorted(known)}")
    if protocols and (problem := undated_problem(protocols, messages)):
        raise ValueError(problem)
    if not 300 <= baud <= 4_000_000:
        raise ValueError(f"baud must be in [300, 4000000], got {baud}")


class GnssEmulatorNode(Node):
    name = "gnss_emulator"
    Options = GnssEmulatorOptions
    inputs = (Input("control/fault", {"control": FaultCommand}),)
    outputs = ("sensor/gnss", "capture/gnss", "timetag/gnss")
    serial = "tx"  # with option protocol: the receiver's line

    def __init__(self, run: Any, options: GnssEmulatorOptions | None = None) -> None:
        super().__init__(run, options)
        o: GnssEmulatorOptions = self.options  # type: ignore[assignment]
        self.wire = bool(o.protocol)
        if self.wire:
            self._encoders = [encoder(p, o.messages, o.talker) for p in o.protocol]
            primary = self._encoders[o.protocol.index(bridge_protocol(o.protocol))]
            self._printed_time = getattr(primary, "printed_time_ns", None)
            tim_tp = "ubx" in o.protocol and (not o.messages or "TIM-TP" in o.messages)
            self._ubx = self._encoders[o.protocol.index("ubx")] if tim_tp else None
            self._next_tim_tp_s = 0
            # in rig time: the line keeps its baud rate in wall time (``hil up --speed``)
            self.line_baud = o.baud
            self.uart = Uart(o.baud / float(run.speed), o.tx_buffer_bytes)
            self._last_epoch: ReceiverEpoch | None = None
            self._lines: list[tuple[int, int, bytes]] = []  # (first byte out, last byte done, bytes)
            self._next_k = 0  # the next epoch index to put on the wire (outages: "no fix" epochs)
        s = scenario_for_run(run)
        self.scenario = s
        # the receiver's faults (gnss_frozen, gnss_time_jump) apply with or without a wire; the
        # line's need one (without it they are announced fault_ignored, not applied)
        self.line_faults = LineFaults(run.seed, s.events)
        self._last_fix: Any = None
        self.core = GnssEmulatorCore(s, truth_for(s), sensor_rng(s.seed, "gnss"))
        self.clock = device_clock_for(s, "gnss")
        self.timeline = device_timeline(s.events, "gnss")
        self.end_ns = int(run.duration_s * 1e9)
        self.pull_block_ns = round(self.options.pull_block_s * 1e9)  # type: ignore[attr-defined]
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
        if self.wire:  # nor "no fix" epochs for the time it was dead: a dead receiver sends nothing
            self._next_k = self.core.next_epoch
        # the next whole second's edge; a run's first is at 1 s, also for a restart before time
        # zero (the world's lead: now_ns < 0), which gave an edge at 0 s with seq -1, refused by
        # time sync and the recorder as an invalid TimeTag
        self.next_pps_s = max(1, now_ns // _S + 1)
        detail = f"gnss_emulator restarted at t={now_ns / 1e9:.3f} s: resumes at fix seq {skipped}"
        return [self.event("resumed", detail, now_ns)]

    def _pull_until(self, now_ns: int) -> int:
        """Epochs with validity up to this are computed at ``now_ns``."""
        b = self.pull_block_ns
        return min(((now_ns // b) + 1) * b - 1 if b > 0 else now_ns, self.end_ns)

    def next_tick_ns(self) -> int | None:
        epoch = self.core.next_epoch_ns()
        if epoch is not None and epoch > self.end_ns:
            # past the run's end (the truth's duration can round 1 ns beyond it): no tick, or
            # its block's start would be asked for again and again (hil sim hung on car_drive)
            epoch = None
        if epoch is not None and self.pull_block_ns > 0:
            epoch = epoch // self.pull_block_ns * self.pull_block_ns
        times = [epoch, self.timeline.next_edge_ns()]
        if self._pending:
            times.append(self._pending[0][0])
        if self.wire and self._lines:
            times.append(self._lines[0][0])
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
            check_fault(msg.kind, msg.target, msg.param_map())
        except FaultError as err:
            self.error("rejected.control.fault", str(err))
            return []
        # a command that arrives before time zero (the rig's services are running a moment
        # before the run starts) takes effect at time zero, as the IMU's does at its first sample:
        # applied at its arrival, a 2 s outage covered the run's first 2 s and cut no hole
        return self._apply(msg, max(now_ns, 0)) if mine else []

    def _apply(self, cmd: FaultCommand, now_ns: int) -> list[Out]:
        """A commanded fault from ``now_ns`` on: as a scenario event the core applies to the
        epochs it has not computed yet, and on the timeline that announces its edges."""
        p = cmd.param_map()
        if cmd.kind == "clock_step":
            self.clock.add_step(now_ns, round(p["step_s"] * 1e9))
            return [self.event("fault_start", _detail(cmd.kind, now_ns, None, p, "command"), now_ns)]
        params: dict[str, Any] = {}
        if cmd.kind in ("gnss_jump", "gnss_spoof"):
            params["offset_ned_m"] = (p.get("n_m", 0.0), p.get("e_m", 0.0), p.get("d_m", 0.0))
        if cmd.kind == "gnss_spoof":
            params["sigma_m"] = p.get("sigma_m", DEFAULT_SPOOF_SIGMA_M)
        elif cmd.kind == "gnss_velocity_glitch":
            params["offset_ned_mps"] = (p.get("n_mps", 0.0), p.get("e_mps", 0.0), p.get("d_mps", 0.0))
        elif cmd.kind == "gnss_latency":
            params.update(p)
        if cmd.kind in LINE_FAULTS | RECEIVER_FAULTS:  # the line's: for the epochs from now on
            if self.wire or cmd.kind in RECEIVER_FAULTS:
                self.line_faults.timeline.add(cmd.kind, now_ns, cmd.duration_s, dict(p))
            else:
                self.error(
                    "rejected.control.fault", f"{cmd.kind}: the receiver is on no wire (--gnss-protocol)"
                )
                return []
            self.timeline.add(cmd.kind, now_ns, cmd.duration_s, dict(p))
            return []
        t0 = now_ns / 1e9
        t1 = t0 + cmd.duration_s if cmd.duration_s > 0 and cmd.kind != "gnss_latency" else None
        self.core.add_event(ScenarioEvent(cmd.kind, t0, t1, params))
        self.timeline.add(cmd.kind, now_ns, cmd.duration_s if t1 is not None else 0.0, params)
        return []

    def tick(self, now_ns: int) -> list[Out]:
        outs: list[Out] = []
        for edge, f in self.timeline.edges(min(now_ns, self.end_ns)):
            if not self.wire and f.kind in LINE_FAULTS:  # no line to damage: said, not applied
                if edge == "fault_start":
                    params = {**f.params, "reason": NO_WIRE}
                    outs.append(
                        self.event(
                            "fault_ignored", _detail(f.kind, f.t0_ns, f.t1_ns, params, f.origin), f.t0_ns
                        )
                    )
                continue
            detail = _detail(f.kind, f.t0_ns, f.t1_ns, f.params, f.origin)
            outs.append(self.event(edge, detail, edge_time_ns(edge, f)))
        until = self._pull_until(now_ns)
        if self.core.has_due(until):
            b = self.core.next_batch(until)
            for i in range(len(b.t_valid_ns)):
                if self.wire:
                    self._no_fix_epochs_before(int(b.t_valid_ns[i]))
                t_out = int(b.t_output_ns[i])
                if t_out <= self.end_ns:  # the receiver's output after the run is not the run's
                    heapq.heappush(self._pending, (t_out, self._order, b, i))
                    self._order += 1
            if self.wire and self.core.next_epoch_ns() is None:
                self._no_fix_epochs_before(self.end_ns + 1)
            elif self.wire:
                # the epochs the core has passed and left out (an outage) are "no fix" epochs now,
                # each at its own output time -- not once the outage's end shows, all at once
                self._no_fix_epochs_before(self.core.next_epoch * self.core.period_ns, passed=True)
        while self._pending and self._pending[0][0] <= now_ns:
            _t, _o, b, i = heapq.heappop(self._pending)
            outs.extend(self._wire_epoch(b, i, now_ns) if self.wire else self._fix(b, i, now_ns))
        while self.wire and self._lines and self._lines[0][0] <= now_ns:
            start, end, data = self._lines.pop(0)
            outs.append((SERIAL_TX, LineBurst(data, start, end, self.options.port)))  # type: ignore[attr-defined]
        while self.next_pps_s * _S <= self.end_ns and self.clock.latch_ns(self.next_pps_s * _S) <= now_ns:
            t_edge = self.next_pps_s * _S
            tag = TimeTag(
                seq=self.next_pps_s - 1,  # the PPS second: a restart never reuses a seq
                stamp_ns=self.clock.latch_ns(t_edge),  # latched on the rig clock (latch jitter)
                sensor="gnss",
                kind="pps",
                device_stamp_ns=self._pulse_device_ns(t_edge),
            )
            outs.append(("timetag/gnss", tag))
            self.next_pps_s += 1
        return outs

    # -- on a wire ---------------------------------------------------------------------------
    def _pulse_device_ns(self, t_edge_ns: int) -> int:
        """The receiver's time of a PPS edge as the rig's tag states it. On a wire, as the line
        states times (the fixes the rig reads): NMEA prints them to 10 ms, so a receiver clock
        1.5 ms off its epochs' grid (the default) prints each fix 1.5 ms early and a pulse
        stamped to the ns would put every fix that much early on the rig clock."""
        device_ns = self.clock.device_ns(t_edge_ns)
        if not self.wire:
            return device_ns
        return self._stated_device_ns(utc_ns_to_gps_ns(self.run.start_epoch_ns + device_ns))

    def _stated_device_ns(self, gps_ns: int) -> int:
        """A receiver time (GPS ns) as the line states it, on the run's device timeline: what
        the bridge reads back (``device_stamp_ns``)."""
        if self._printed_time is not None:
            gps_ns = int(self._printed_time(gps_ns))
        return gps_ns_to_utc_ns(gps_ns) - self.run.start_epoch_ns

    def _no_fix_epochs_before(self, t_valid_ns: int, passed: bool = False) -> None:
        """Epochs the core left out (an outage) up to ``t_valid_ns``: a receiver still outputs
        them, saying it has no fix. ``t_valid_ns`` is a real epoch's (done with it), or with
        ``passed`` the first the core has not returned yet (still to come)."""
        period = self.core.period_ns
        while self._next_k * period < t_valid_ns:
            t = self._next_k * period
            t_out = t + round(self.scenario.gnss.latency_s * 1e9)
            if t_out <= self.end_ns:
                heapq.heappush(self._pending, (t_out, self._order, None, t))
                self._order += 1
            self._next_k += 1
        if not passed:
            self._next_k = max(self._next_k, t_valid_ns // period + 1)

    def _wire_epoch(self, b: Any, i: int, now_ns: int) -> list[Out]:
        """One epoch onto the line (and its capture truth): the bytes wait for the UART.

        ``b`` None: a "no fix" epoch, ``i`` its time of validity."""
        t_valid = int(b.t_valid_ns[i]) if b is not None else int(i)
        k = t_valid // self.core.period_ns
        act = self.line_faults.epoch(k, t_valid)
        epoch = self._epoch(b, i, t_valid)
        # the epoch index its bytes will state (the bridge's seq): k, unless the receiver's clock
        # is half a period or more off the true grid (a step, an offset)
        seq = epoch_index(self._stated_device_ns(epoch.gps_time_ns), self.core.period_ns)
        cap = CaptureTruth(seq=seq, stamp_ns=t_valid, sensor="gnss", true_stamp_ns=t_valid)
        if act.frozen and self._last_epoch is not None and epoch.fix_type:
            last = self._last_epoch  # the receiver repeats its last solution under a new time
            epoch = dataclasses.replace(
                last, gps_time_ns=epoch.gps_time_ns, num_sats=epoch.num_sats, hdop=epoch.hdop
            )
        self._last_epoch = epoch
        if act.time_step_ns:
            epoch = dataclasses.replace(epoch, gps_time_ns=epoch.gps_time_ns + act.time_step_ns)
        if not act.send:
            self.inc("fault.line.dropout_epochs")
            return [("capture/gnss", cap)]
        data = b"".join(enc.encode_epoch(epoch) for enc in self._encoders)
        if self._ubx is not None and t_valid // _S >= self._next_tim_tp_s:
            # the first epoch of each second announces the next pulse (UBX TIM-TP)
            pulse_s = t_valid // _S + 1
            pulse_gps_ns = utc_ns_to_gps_ns(self.run.start_epoch_ns + self.clock.device_ns(pulse_s * _S))
            data += self._ubx.encode_pps_announcement(pulse_gps_ns)
            self._next_tim_tp_s = pulse_s
        if act.corrupt or act.burst_bytes:
            data = self.line_faults.damage(data, act, k)
            self.inc(f"fault.line.{act.corrupt or 'burst'}_epochs")
        slot = self.uart.send(len(data), now_ns)
        if slot is None:
            self.error("line.overrun_epochs", f"UART overrun: {len(data)} bytes at {self.line_baud} baud")
            self.inc("line.overrun_bytes", len(data))
        else:
            self._lines.append((slot[0], slot[1], data))
        self.inc("line.epochs")
        return [("capture/gnss", cap)]

    def _epoch(self, b: Any, i: int, t_valid: int) -> ReceiverEpoch:
        """What the receiver reports: the fix at its time of validity on the receiver's clock,
        as GPS time from the run's start epoch."""
        gps_ns = utc_ns_to_gps_ns(self.run.start_epoch_ns + self.clock.device_ns(t_valid))
        cfg = self.scenario.gnss
        if b is None:  # no fix
            hdop = float(cfg.hdop)
            return ReceiverEpoch(
                gps_ns, 0.0, 0.0, 0.0, (0.0, 0.0, 0.0), (0.0, 0.0, 0.0), (0.0, 0.0, 0.0),
                0, 0, hdop, hdop * (1 + VDOP_PER_HDOP**2) ** 0.5, hdop * VDOP_PER_HDOP,
            )  # fmt: skip
        hdop = float(b.hdop[i])
        return ReceiverEpoch(
            gps_time_ns=gps_ns,
            lat_deg=float(b.lat_deg[i]),
            lon_deg=float(b.lon_deg[i]),
            alt_m=float(b.alt_m[i]),
            vel_ned_mps=tuple(float(v) for v in b.vel_ned_mps[i]),  # type: ignore[arg-type]
            pos_sigma_ned_m=tuple(float(v) for v in b.pos_sigma_m[i]),  # type: ignore[arg-type]
            vel_sigma_mps=tuple(float(v) for v in b.vel_sigma_mps[i]),  # type: ignore[arg-type]
            fix_type=int(b.fix_type[i]),
            num_sats=int(b.num_sats[i]),
            hdop=hdop,
            pdop=hdop * (1 + VDOP_PER_HDOP**2) ** 0.5,
            vdop=hdop * VDOP_PER_HDOP,
        )

    def counters(self) -> dict[str, int]:
        out = dict(self.counts)
        if self.wire:
            out["line.bytes_sent"] = self.uart.sent_bytes
        return out

    def _fix(self, b: Any, i: int, now_ns: int) -> list[Out]:
        seq = self.fix_index
        self.fix_index += 1
        t_valid = int(b.t_valid_ns[i])
        act = self.line_faults.epoch(t_valid // self.core.period_ns, t_valid)
        # gnss_time_jump: the time of validity the receiver reports is off (as on a wire)
        fix = gnss_fix_msg(seq, now_ns, self.clock.device_ns(t_valid) + act.time_step_ns, b, i)
        if act.frozen and self._last_fix is not None and fix.fix_type:
            last = self._last_fix  # gnss_frozen: its last solution again, under a fresh time
            fix = msgspec.structs.replace(
                fix,
                **{k: getattr(last, k) for k in _FROZEN_FIELDS},
            )
        self._last_fix = fix
        cap = CaptureTruth(seq=seq, stamp_ns=t_valid, sensor="gnss", true_stamp_ns=t_valid)
        return [("sensor/gnss", fix), ("capture/gnss", cap)]

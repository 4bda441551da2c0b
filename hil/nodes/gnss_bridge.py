"""The GNSS bridge: a receiver's serial line -> ``hil.GnssFix``, the twin of the CAN bridge.

It reads the line as a device under test would (``hil.wire.line.LineDecoder``: NMEA sentences and
UBX frames, checksums, framing), stamps each chunk with its receive time on the rig clock, and
publishes

- ``serial/<port>``  every chunk read, byte for byte (``hil.SerialChunk``), so the recording holds
  the line and a replay can put it back on one;
- ``sensor/gnss``    each fix decoded from the bytes -- the quantised numbers a device sees --
  ``stamp_ns = rx_stamp_ns`` = the receive time of the chunk that completed it, ``line_ns`` =
  how long the line had carried its epoch by then (``DecodedFix.line_bytes`` at ``baud``, at
  most one receiver period: more is a line that paused mid-epoch),
  ``device_stamp_ns`` = its time of validity as the receiver printed it (GPS/UTC time) less the
  run's start epoch, ``seq`` = the epoch index (time of validity over the receiver's period: the
  emulator's capture truth carries the same), position in the scenario's NED frame.

What a protocol does not carry comes from the receiver's datasheet, i.e. the scenario's
``[gnss]`` model: NMEA has no vertical velocity (sent as 0 with a σ of ``NO_VERTICAL_SIGMA_MPS``)
and no velocity σ. With both protocols on one line, the UBX fix is published (it carries more
digits); the NMEA sentences are still decoded and checked. Bad input -- bad checksum, truncated
sentence, unknown message, garbage, a line at the wrong baud rate -- is counted
(``rejected.line.<kind>``) with the last one described; nothing stops the bridge.
"""

from __future__ import annotations

import math
from typing import Any

import msgspec
import numpy as np

from hil.messages import GnssFix, SerialChunk
from hil.nav.earth import lla_to_ned
from hil.nav.scenario import scenario_for_run
from hil.nodes.base import SERIAL_RX, Node, NodeOptions, Out
from hil.nodes.gnss_emulator import bridge_protocol, check_wire, epoch_index
from hil.wire.base import DecodedFix
from hil.wire.gnss_time import gps_ns_to_utc_ns
from hil.wire.line import LineDecoder, byte_time_ns

NO_VERTICAL_SIGMA_MPS = 1000.0  # NMEA carries no vertical velocity: "0 m/s, σ 1 km/s" = unknown
CHUNK_MAX_BYTES = 4096  # a longer read is recorded as several chunks
_REJECTED = ("bad_checksum", "truncated", "unknown", "too_long", "malformed", "baud_mismatch")


class GnssBridgeOptions(NodeOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    protocol: list[str] = msgspec.field(default_factory=lambda: ["nmea"])  # what the line carries
    messages: list[str] = msgspec.field(default_factory=list)  # the receiver's message set (empty: defaults)
    talker: str = "GN"
    baud: int = 115200  # the line's rate (a real device path is opened at it)
    port: str = "gnss"  # the line's name (serial/<port>)
    serial_path: str | None = None  # live: read this path (a pseudo-terminal link or a device)
    tcp_connect: str | None = None  # live: or read the line from a TCP server, HOST:PORT

    def __post_init__(self) -> None:
        if not self.protocol:
            raise ValueError("protocol: name what the line carries (nmea, ubx)")
        check_wire(self.protocol, self.messages, self.talker, self.baud)


class GnssBridgeNode(Node):
    inputs_move_timers = False  # its timers are its own: periodic, or none
    name = "gnss_bridge"
    Options = GnssBridgeOptions
    outputs = ("sensor/gnss",)
    serial = "rx"

    def __init__(self, run: Any, options: GnssBridgeOptions | None = None) -> None:
        super().__init__(run, options)
        o: GnssBridgeOptions = self.options  # type: ignore[assignment]
        s = scenario_for_run(run)
        self.decoder = LineDecoder(tuple(o.protocol), tuple(o.messages))
        self.primary = bridge_protocol(o.protocol)  # UBX carries more digits
        self.period_ns = round(1e9 / s.gnss.rate_hz)
        self.vel_sigma_mps = tuple(float(v) for v in s.gnss.vel_sigma_mps)
        self.pos_sigma_m = tuple(float(v) for v in s.gnss.pos_sigma_m)
        self.origin = (math.radians(run.origin_lat_deg), math.radians(run.origin_lon_deg), run.origin_alt_m)
        # a byte's time on the line in rig ns: the line keeps its baud rate in wall time, and rig
        # time runs ``speed`` times as fast (``hil up --speed``)
        self.byte_ns = byte_time_ns(o.baud) * float(run.speed)
        self.raw_key = f"serial/{o.port}"
        self._seen: dict[str, int] = {}
        self._last_k = -1

    def on_message(self, key: str, msg: Any, now_ns: int) -> list[Out]:
        """``key`` ``@serial/<port>``: bytes read off the line at rig time ``now_ns``."""
        if not key.startswith(SERIAL_RX):
            return []
        data = bytes(msg)
        outs: list[Out] = []
        for i in range(0, len(data), CHUNK_MAX_BYTES):
            part = data[i : i + CHUNK_MAX_BYTES]
            chunk = SerialChunk(
                seq=self.next_seq(self.raw_key), stamp_ns=now_ns, port=self.raw_key[7:], data_hex=part.hex()
            )
            outs.append((self.raw_key, chunk))
        fixes = self.decoder.feed(data, now_ns)
        self._count_problems()
        for fix in fixes:
            if fix.protocol == self.primary:
                out = self._fix(fix)
                if out is not None:
                    outs.append(("sensor/gnss", out))
        return outs

    def _count_problems(self) -> None:
        counters = self.decoder.all_counters()
        for name, n in counters.items():
            kind = name.rsplit(".", 1)[-1]
            if kind in _REJECTED and n != self._seen.get(name, 0):
                self.error(f"rejected.line.{kind}", self.decoder.problem() or f"{name}: {n}")
                self.inc(f"rejected.line.{kind}", n - self._seen.get(name, 0) - 1)
            self._seen[name] = n

    def _fix(self, f: DecodedFix) -> GnssFix | None:
        """The decoded epoch as the rig's message; None if it has no time to place it by."""
        if f.gps_time_ns is None:
            self.inc("dropped.line.undated_fixes")
            return None
        device_ns = gps_ns_to_utc_ns(f.gps_time_ns) - self.run.start_epoch_ns
        k = epoch_index(device_ns, self.period_ns)
        if k <= self._last_k:
            self.inc("dropped.line.repeated_epochs")
            return None
        self._last_k = k
        fix_type = f.fix_type or 0
        lat, lon, alt = (f.lat_deg or 0.0), (f.lon_deg or 0.0), (f.alt_m or 0.0)
        if fix_type >= 2:
            ned = lla_to_ned(math.radians(lat), math.radians(lon), alt, *self.origin)
            pos = [float(v) for v in np.asarray(ned).reshape(3)]
        else:
            lat = lon = alt = 0.0
            pos = [0.0, 0.0, 0.0]
        vel = [v if v is not None else 0.0 for v in f.vel_ned_mps]
        vel_sigma = [
            s
            if s is not None
            else (NO_VERTICAL_SIGMA_MPS if f.vel_ned_mps[i] is None else self.vel_sigma_mps[i])
            for i, s in enumerate(f.vel_sigma_mps)
        ]
        pos_sigma = [
            s if s is not None and s > 0 else self.pos_sigma_m[i] for i, s in enumerate(f.pos_sigma_ned_m)
        ]
        return GnssFix(
            seq=k,
            stamp_ns=f.rx_ns,
            device_stamp_ns=device_ns,
            rx_stamp_ns=f.rx_ns,
            lat_deg=lat,
            lon_deg=lon,
            alt_m=alt,
            pos_ned_m=pos,
            vel_ned_mps=vel,
            pos_sigma_m=pos_sigma,
            vel_sigma_mps=[max(s, 1e-3) for s in vel_sigma],
            fix_type=min(max(fix_type, 0), 5),
            num_sats=min(max(f.num_sats or 0, 0), 200),
            hdop=float(f.hdop if f.hdop is not None else (f.pdop or 99.99)),
            line_ns=min(round(f.line_bytes * self.byte_ns), self.period_ns),
        )

    def finish(self, now_ns: int) -> list[Out]:
        return [
            ("sensor/gnss", m)
            for f in self.decoder.flush()
            if f.protocol == self.primary and (m := self._fix(f))
        ]

    def counters(self) -> dict[str, int]:
        out = {f"line.{k}": v for k, v in self.decoder.all_counters().items()}
        out.update(self.counts)
        return out

#!/usr/bin/env python3
"""navbox: a reference navigation unit that knows the rig only through its wires.

It is what ``hil up --dut examples/dut/navbox.toml --dut-emulator`` plugs in, and what a real
unit would be: it reads the IMU's CAN frames (``schemas/imu.dbc``, decoded with cantools, E2E
CRC and rolling counters checked), reads a GNSS receiver's UART (NMEA 0183 with pynmeagps, u-blox
UBX with pyubx2), runs a small navigation filter and puts its solution on CAN in its own DBC
(``navbox.dbc``) at 10 Hz. It imports nothing from ``hil``: the CAN bus is python-can's
(``socketcan``, or the rig's ``hilzenoh`` plugin, which python-can loads by name and configures
from the environment), the GNSS line is a path opened with pyserial. docs/dut.md says how to
wire a real unit in its place.

The filter: strapdown attitude from the gyro increments (earth and transport rate removed),
velocity and position (latitude, longitude, height) from the accelerometer increments in the
local level NED frame with normal gravity and Coriolis; at each GNSS fix a closed-loop Kalman
filter per NED axis (position, velocity, acceleration error) corrects position and velocity
and turns the acceleration error into a tilt (and, under horizontal acceleration, heading)
correction. Time: each IMU sample is placed on the unit's UTC clock (the host's here, as a
PPS-disciplined clock would be on hardware) by its device time, anchored by the least delayed
sample; a fix, which arrives ~0.1 s after its time of validity, is compared with the state the
unit had at that time (a short history), and a solution is predicted to the instant it is sent.
Initial attitude: level from the accelerometer, heading from the GNSS course once moving. It is
plausible, not great: it estimates no sensor bias, which a tactical IMU does not need over
minutes and a consumer MEMS one does (docs/dut.md).

Bad input never stops it: a frame with a bad CRC, a repeated or missing counter, a garbled or
truncated sentence, a UBX frame with a bad checksum are counted and skipped (a lost IMU sample's
interval is bridged by scaling the next one). SIGTERM/SIGINT stop it cleanly.
"""

from __future__ import annotations

import argparse
import logging
import math
import os
import queue
import signal
import threading
import time
from collections import deque
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import UTC, date, datetime
from pathlib import Path
from typing import Any

import can
import cantools
import numpy as np
import serial
from pynmeagps import NMEAReader
from pyubx2 import UBXReader

LOG = logging.getLogger("navbox")
HERE = Path(__file__).resolve().parent
DEFAULT_IMU_DBC = HERE.parents[1] / "schemas" / "imu.dbc"
DEFAULT_NAV_DBC = HERE / "navbox.dbc"

# WGS84 and normal gravity (Somigliana)
A_M, E2, OMEGA_IE_RADPS = 6378137.0, 6.69437999014e-3, 7.292115e-5
G_EQ_MPS2, K_SOMIGLIANA = 9.7803253359, 1.931852652e-3
KNOT_MPS = 1852.0 / 3600.0

OUTPUT_PERIOD_S = 0.1  # 10 Hz solutions
MAX_PREDICT_S = 1.0  # a solution is predicted to its send time from a state at most this old
MAX_FIX_WAIT_S = 2.0  # a fix waits at most this long for the IMU to reach its time of validity
FRAME_BATCH = 64  # CAN frames taken in between two looks at the clock
CLOCK_LEAK = 100e-6  # the IMU clock's offset estimate may rise this fast (s/s): its drift
HISTORY_ROWS = 4096  # IMU-rate states kept to meet delayed fixes (~10 s at 400 Hz)
MIN_COURSE_SPEED_MPS = 3.0  # below this the GNSS course says nothing about heading
GATE_SIGMA = 5.0  # innovation gate; after GATE_RESET rejections in a row, accept (re-converge)
GATE_RESET = 5
Q_POS_M2PS, Q_VEL_M2PS3, Q_ACC_M2PS5 = 0.01, 0.0025, 4e-6  # process noise densities per axis
HEADING_FIXES = 20  # heading = course averaged over this many fixes once moving
P0_ACC_MPS2 = 0.05  # initial acceleration-error sigma (about 0.3 deg of tilt)
LEVEL_TAU_S = 0.5  # accelerometer levelling averages this long before alignment
COUNTER_MODULO = 15  # AUTOSAR E2E profile 1: counter 0..14


def _crc_table() -> tuple[int, ...]:
    out = []
    for byte in range(256):
        crc = byte
        for _ in range(8):
            crc = ((crc << 1) ^ 0x1D) & 0xFF if crc & 0x80 else (crc << 1) & 0xFF
        out.append(crc)
    return tuple(out)


CRC_TABLE = _crc_table()


def e2e_crc(frame_id: int, data: bytes, length: int) -> int:
    """AUTOSAR E2E profile 1 CRC (DATAID_BOTH): CRC-8 SAE-J1850 over ID low, ID high, bytes 1.."""
    crc = CRC_TABLE[CRC_TABLE[frame_id & 0xFF] ^ ((frame_id >> 8) & 0xFF)]
    for b in data[1:length]:
        crc = CRC_TABLE[crc ^ b]
    return crc


@dataclass(slots=True)
class ImuSample:
    device_ns: int  # device clock, modulo 2^48
    dtheta_rad: tuple[float, float, float]  # body-axis delta-angle over the sample interval
    dvel_mps: tuple[float, float, float]  # body-axis delta-velocity
    rx_s: float  # receive time of the frame that completed it (UTC seconds)


class ImuDecoder:
    """IMU frames in (``schemas/imu.dbc``), samples out; bad frames counted, never raised."""

    def __init__(self, dbc_path: Path) -> None:
        db = cantools.database.load_file(str(dbc_path))
        self.by_id: dict[int, Any] = {}
        self.e2e_len: dict[int, int] = {}
        self.role: dict[int, str] = {}
        for m in db.messages:
            attrs = m.dbc.attributes if m.dbc is not None else {}
            role = attrs["HilRole"].value if "HilRole" in attrs else ""
            if role in ("sample_part", "sample_fd"):
                self.by_id[m.frame_id] = m
                self.role[m.frame_id] = "time" if m.name.endswith("_Time") else role
                e2e = attrs.get("HilE2EDataLength")
                self.e2e_len[m.frame_id] = int(e2e.value) if e2e is not None else 8
        kinds = ("frames", "samples", "bad_crc", "bad_frames", "repeats", "lost_frames", "incomplete")
        self.counts = dict.fromkeys(kinds, 0)
        self._last_counter: dict[int, int] = {}
        self._parts: dict[int, tuple[int, dict[str, float]]] = {}  # frame id -> (counter, signals)

    def feed(self, msg: can.Message) -> ImuSample | None:
        m = self.by_id.get(msg.arbitration_id)
        if m is None or msg.is_error_frame or msg.is_remote_frame:
            return None
        self.counts["frames"] += 1
        data = bytes(msg.data)
        n = self.e2e_len[msg.arbitration_id]
        if len(data) < max(n, 2) or data[0] != e2e_crc(msg.arbitration_id, data, n):
            self.counts["bad_crc"] += 1
            return None
        counter = data[1] & 0x0F
        if counter >= COUNTER_MODULO:
            self.counts["bad_frames"] += 1
            return None
        last = self._last_counter.get(msg.arbitration_id)
        self._last_counter[msg.arbitration_id] = counter
        if last is not None:
            step = (counter - last) % COUNTER_MODULO
            if step == 0:
                self.counts["repeats"] += 1
                return None
            self.counts["lost_frames"] += step - 1
        try:
            values = m.decode(data, decode_choices=False)
        except Exception:  # cantools: wrong length, value out of the signal
            self.counts["bad_frames"] += 1
            return None
        role = self.role[msg.arbitration_id]
        if role == "sample_part":
            self._parts[msg.arbitration_id] = (counter, values)
            return None
        if role == "time":
            parts = [p[1] for p in self._parts.values() if p[0] == counter]
            self._parts.clear()
            if len(parts) != 3:
                self.counts["incomplete"] += 1
                return None
            for p in parts:
                values.update(p)
        self.counts["samples"] += 1
        return ImuSample(
            int(values["DeviceTime"]),
            (float(values["DeltaAngleX"]), float(values["DeltaAngleY"]), float(values["DeltaAngleZ"])),
            (float(values["DeltaVelX"]), float(values["DeltaVelY"]), float(values["DeltaVelZ"])),
            float(msg.timestamp) if msg.timestamp else time.time(),
        )


@dataclass(slots=True)
class Fix:
    """One GNSS epoch as the unit uses it; ``nan`` where the protocol carries nothing."""

    t_valid_s: float  # time of validity, UTC seconds
    lat_deg: float
    lon_deg: float
    alt_m: float  # ellipsoidal
    vel_ned_mps: np.ndarray
    pos_sigma_m: np.ndarray  # N, E, D
    vel_sigma_mps: np.ndarray
    source: str  # "nmea" or "ubx"
    rx_s: float = 0.0


class GnssParser:
    """Bytes of a receiver's line in, fixes out: NMEA (RMC + GGA, sigmas from GST) and UBX NAV-PVT.

    Framing is the unit's own (a line may carry both protocols, split anywhere, damaged);
    pynmeagps and pyubx2 parse each message with its checksum checked.
    """

    MAX_NMEA = 100
    MAX_UBX = 2048

    def __init__(self, nmea_vel_sigma_mps: float = 0.3) -> None:
        self.buf = bytearray()
        self.counts = dict.fromkeys(("messages", "bad_messages", "garbage_bytes", "fixes", "no_fix"), 0)
        self.nmea_vel_sigma_mps = nmea_vel_sigma_mps
        self._epoch: dict[str, Any] = {}  # NMEA messages of the current time of day
        self._sigma = np.full(3, math.nan)  # last GST sigmas (GST comes after GGA)

    def feed(self, data: bytes, rx_s: float) -> list[Fix]:
        self.buf += data
        out = []
        for kind, raw in self._messages():
            try:
                fix = self._nmea(raw) if kind == "nmea" else self._ubx(raw)
            except Exception:  # pynmeagps/pyubx2 parse errors, bad fields: count and go on
                self.counts["bad_messages"] += 1
                continue
            self.counts["messages"] += 1
            if fix is not None:
                fix.rx_s = rx_s
                out.append(fix)
                self.counts["fixes"] += 1
        return out

    def _messages(self) -> Iterator[tuple[str, bytes]]:
        buf = self.buf
        while True:
            starts = [i for i in (buf.find(b"$"), buf.find(b"\xb5\x62")) if i >= 0]
            if not starts:
                self._drop(max(0, len(buf) - 1))  # keep a lone 0xB5: a UBX header may follow
                return
            self._drop(min(starts))
            if buf[:1] == b"$":
                end = buf.find(b"\n")
                if end < 0:
                    if len(buf) > self.MAX_NMEA:
                        self._drop(1)
                        continue
                    return
                line = bytes(buf[: end + 1])
                cut = max(line.rfind(b"$"), line.find(b"\xb5\x62"))
                if cut > 0 or end >= self.MAX_NMEA:  # a sentence cut short by another message
                    self._drop(max(cut, 1))
                    continue
                del buf[: end + 1]
                yield "nmea", line
            else:
                if len(buf) < 6:
                    return
                n = 8 + int.from_bytes(buf[4:6], "little")
                if n > self.MAX_UBX:
                    self._drop(2)
                    continue
                if len(buf) < n:
                    return
                frame = bytes(buf[:n])
                del buf[:n]
                yield "ubx", frame

    def _drop(self, n: int) -> None:
        if n > 0:
            self.counts["garbage_bytes"] += n
            del self.buf[:n]

    def _nmea(self, raw: bytes) -> Fix | None:
        msg = NMEAReader.parse(raw, validate=1)
        kind = msg.msgID if msg is not None else ""
        if kind == "GST":
            sigma = (msg.stdLat, msg.stdLong, msg.stdAlt)
            if all(isinstance(x, int | float) for x in sigma):  # empty without a fix
                self._sigma = np.array(sigma, dtype=float)
            return None
        if kind not in ("RMC", "GGA"):
            return None
        if self._epoch.get("time") != msg.time:
            self._epoch = {"time": msg.time}
        self._epoch[kind] = msg
        rmc, gga = self._epoch.get("RMC"), self._epoch.get("GGA")
        if rmc is None or gga is None:
            return None
        if rmc.status != "A" or int(gga.quality or 0) == 0:
            self.counts["no_fix"] += 1
            return None
        if not isinstance(rmc.date, date):
            return None
        t = datetime.combine(rmc.date, rmc.time, tzinfo=UTC).timestamp()
        speed, course = float(rmc.spd) * KNOT_MPS, math.radians(float(rmc.cog or 0.0))
        vel = np.array([speed * math.cos(course), speed * math.sin(course), math.nan])
        vsig = np.array([self.nmea_vel_sigma_mps] * 2 + [math.nan])
        alt = float(gga.alt) + float(gga.sep or 0.0)
        return Fix(t, float(gga.lat), float(gga.lon), alt, vel, self._sigma.copy(), vsig, "nmea")

    def _ubx(self, raw: bytes) -> Fix | None:
        msg = UBXReader.parse(raw, validate=1)
        if msg.identity != "NAV-PVT":
            return None
        if msg.fixType not in (2, 3) or not msg.gnssFixOk or not (msg.validDate and msg.validTime):
            self.counts["no_fix"] += 1
            return None
        t = datetime(msg.year, msg.month, msg.day, msg.hour, msg.min, msg.second, tzinfo=UTC).timestamp()
        vel = np.array([msg.velN, msg.velE, msg.velD], dtype=float) * 1e-3
        sig = np.array([msg.hAcc, msg.hAcc, msg.vAcc], dtype=float) * 1e-3
        return Fix(
            t + msg.nano * 1e-9, float(msg.lat), float(msg.lon), msg.height * 1e-3, vel, sig,
            np.full(3, msg.sAcc * 1e-3), "ubx",
        )  # fmt: skip


class GnssLine(threading.Thread):
    """Reads the receiver's line (a pty or a UART) with pyserial; reopens it if it goes away."""

    def __init__(self, path: str, baud: int, parser: GnssParser, stop: threading.Event) -> None:
        super().__init__(name="gnss-line", daemon=True)
        self.path, self.baud, self.parser, self.stop = path, baud, parser, stop
        self.fixes: queue.SimpleQueue[Fix] = queue.SimpleQueue()
        self.reopens = 0

    def run(self) -> None:
        while not self.stop.is_set():
            try:
                with serial.Serial(self.path, self.baud, timeout=0.2) as port:
                    LOG.info("GNSS line %s open at %d baud", self.path, self.baud)
                    self._read(port)
            except (OSError, serial.SerialException) as err:
                if self.reopens % 50 == 0:
                    LOG.info("GNSS line %s: %s; retrying", self.path, err)
                self.reopens += 1
                self.stop.wait(0.2)

    def _read(self, port: serial.Serial) -> None:
        while not self.stop.is_set():
            data = port.read(max(1, port.in_waiting))
            if data:
                for fix in self.parser.feed(data, time.time()):
                    self.fixes.put(fix)


def radii_m(lat_rad: float) -> tuple[float, float]:
    """Meridian and prime-vertical radii of curvature."""
    w = 1.0 - E2 * math.sin(lat_rad) ** 2
    return A_M * (1.0 - E2) / (w * math.sqrt(w)), A_M / math.sqrt(w)


def gravity_mps2(lat_rad: float, h_m: float) -> float:
    s2 = math.sin(lat_rad) ** 2
    return G_EQ_MPS2 * (1.0 + K_SOMIGLIANA * s2) / math.sqrt(1.0 - E2 * s2) * (1.0 - 3.1572e-7 * h_m)


Vec = tuple[float, float, float]
Quat = tuple[float, float, float, float]


def quat_mul(p: Quat, q: Quat) -> Quat:
    pw, px, py, pz = p
    qw, qx, qy, qz = q
    return (
        pw * qw - px * qx - py * qy - pz * qz,
        pw * qx + px * qw + py * qz - pz * qy,
        pw * qy - px * qz + py * qw + pz * qx,
        pw * qz + px * qy - py * qx + pz * qw,
    )


def quat_rotvec(x: float, y: float, z: float) -> Quat:
    a = math.sqrt(x * x + y * y + z * z)
    if a < 1e-12:
        return (1.0, 0.5 * x, 0.5 * y, 0.5 * z)
    k = math.sin(a / 2) / a
    return (math.cos(a / 2), k * x, k * y, k * z)


def rotate(q: Quat, v: Vec) -> Vec:
    """``v`` (body axes) in NED, by q_nb."""
    w, x, y, z = q
    a, b, c = v
    return (
        (1 - 2 * (y * y + z * z)) * a + 2 * (x * y - w * z) * b + 2 * (x * z + w * y) * c,
        2 * (x * y + w * z) * a + (1 - 2 * (x * x + z * z)) * b + 2 * (y * z - w * x) * c,
        2 * (x * z - w * y) * a + 2 * (y * z + w * x) * b + (1 - 2 * (x * x + y * y)) * c,
    )


def cross(a: Vec, b: Vec) -> Vec:
    return (a[1] * b[2] - a[2] * b[1], a[2] * b[0] - a[0] * b[2], a[0] * b[1] - a[1] * b[0])


def quat_euler(roll: float, pitch: float, yaw: float) -> Quat:
    cr, sr, cp, sp = math.cos(roll / 2), math.sin(roll / 2), math.cos(pitch / 2), math.sin(pitch / 2)
    cy, sy = math.cos(yaw / 2), math.sin(yaw / 2)
    return (
        cr * cp * cy + sr * sp * sy,
        sr * cp * cy - cr * sp * sy,
        cr * sp * cy + sr * cp * sy,
        cr * cp * sy - sr * sp * cy,
    )


def euler_of(q: Quat) -> Vec:
    """Roll, pitch, yaw (ZYX) of q_nb, radians."""
    w, x, y, z = q
    roll = math.atan2(2 * (w * x + y * z), 1 - 2 * (x * x + y * y))
    pitch = math.asin(max(-1.0, min(1.0, 2 * (w * y - z * x))))
    yaw = math.atan2(2 * (w * z + x * y), 1 - 2 * (y * y + z * z))
    return roll, pitch, yaw


class Navigator:
    """Strapdown INS + a closed-loop Kalman filter per NED axis, aided by GNSS fixes."""

    def __init__(self) -> None:
        self.aligned = self.heading_valid = False
        # the state is plain floats: at the IMU rate, numpy's per-call cost would dominate
        self.q: Quat = (1.0, 0.0, 0.0, 0.0)  # q_nb, body (FRD) to NED
        self.v: Vec = (0.0, 0.0, 0.0)  # NED m/s
        self.llh: Vec = (0.0, 0.0, 0.0)  # latitude rad, longitude rad, height m
        self.acc_corr: Vec = (0.0, 0.0, 0.0)  # NED m/s^2, fed back by the filter
        self.P = np.zeros((3, 3, 3))  # per NED axis: position, velocity, acceleration error
        self.counts = dict.fromkeys(("fixes_used", "fixes_rejected", "fixes_unaligned"), 0)
        self._f_level: Vec = (0.0, 0.0, 0.0)  # body specific force, averaged, before alignment
        self._f_nav: Vec = (0.0, 0.0, 0.0)  # NED specific force x dt since the last fix ...
        self._f_nav_s = 0.0  # ... over this long
        self._last_dev_ns: int | None = None
        self._sample_dt_s = math.inf
        self._t_s = 0.0  # time of the last sample on the unit's UTC clock
        self._dev_s, self._clock_offset_s = 0.0, 0.0  # device time since the IMU started; UTC - it
        self._t_fix_s = -math.inf  # validity of the last fix taken
        self._gate_misses = 0
        self._course_fixes = 0  # fixes the heading was averaged from
        self._hist = np.full((HISTORY_ROWS, 7), -math.inf)  # rx time, llh, v at each sample
        self._hist_i = 0

    def imu(self, s: ImuSample) -> None:
        """One IMU sample: integrate it (or, before alignment, level with it)."""
        last, self._last_dev_ns = self._last_dev_ns, s.device_ns
        dt = ((s.device_ns - last) % (1 << 48)) * 1e-9 if last is not None else 0.0
        if not 0.0 < dt < 0.2:  # the first sample, or a stalled or restarted IMU: start over
            self._dev_s, self._clock_offset_s = 0.0, s.rx_s
            return
        t_s = self._t_s = self._sample_time(dt, s.rx_s)
        self._sample_dt_s = min(self._sample_dt_s, dt)
        dth, dv = s.dtheta_rad, s.dvel_mps
        if dt > 1.5 * self._sample_dt_s:  # lost samples: their interval taken at this one's rate
            k = dt / self._sample_dt_s
            dth, dv = (dth[0] * k, dth[1] * k, dth[2] * k), (dv[0] * k, dv[1] * k, dv[2] * k)
        if not self.aligned:
            a, f = min(1.0, dt / LEVEL_TAU_S), self._f_level
            self._f_level = (
                f[0] + a * (dv[0] / dt - f[0]),
                f[1] + a * (dv[1] / dt - f[1]),
                f[2] + a * (dv[2] / dt - f[2]),
            )
            return
        self._propagate(dth, dv, dt)
        self._hist[self._hist_i % HISTORY_ROWS] = (t_s, *self.llh, *self.v)
        self._hist_i += 1

    def _sample_time(self, dt: float, rx_s: float) -> float:
        """A sample's time on the unit's UTC clock: its device time plus the device clock's offset,
        taken from the least delayed sample (a lower bound on delay, let rise by CLOCK_LEAK to
        follow the device clock's drift). Receive stamps alone would count a late delivery (a
        busy host) as fresh data."""
        self._dev_s += dt
        self._clock_offset_s = min(self._clock_offset_s + CLOCK_LEAK * dt, rx_s - self._dev_s)
        return self._dev_s + self._clock_offset_s

    def _propagate(self, dth: Vec, dv: Vec, dt: float) -> None:
        """One strapdown step in the local level NED frame (earth and transport rate, gravity,
        Coriolis); the velocity increment rotated with the attitude during the interval."""
        lat, lon, h = self.llh
        vn, ve, vd = self.v
        r_m, r_n = radii_m(lat)
        sl, cl = math.sin(lat), math.cos(lat)
        w_en = (ve / (r_n + h), -vn / (r_m + h), -ve * sl / (cl * (r_n + h)))
        w_in = (OMEGA_IE_RADPS * cl + w_en[0], w_en[1], -OMEGA_IE_RADPS * sl + w_en[2])
        turn = cross(dth, dv)
        f = rotate(self.q, (dv[0] + 0.5 * turn[0], dv[1] + 0.5 * turn[1], dv[2] + 0.5 * turn[2]))
        fn = self._f_nav
        self._f_nav, self._f_nav_s = (fn[0] + f[0], fn[1] + f[1], fn[2] + f[2]), self._f_nav_s + dt
        q = quat_mul(
            quat_rotvec(-w_in[0] * dt, -w_in[1] * dt, -w_in[2] * dt), quat_mul(self.q, quat_rotvec(*dth))
        )
        norm = 1.0 / math.sqrt(q[0] * q[0] + q[1] * q[1] + q[2] * q[2] + q[3] * q[3])
        self.q = (q[0] * norm, q[1] * norm, q[2] * norm, q[3] * norm)
        cor = cross((w_in[0] + OMEGA_IE_RADPS * cl, w_in[1], w_in[2] - OMEGA_IE_RADPS * sl), self.v)
        ac, g = self.acc_corr, gravity_mps2(lat, h)
        vn2 = vn + f[0] + (ac[0] - cor[0]) * dt
        ve2 = ve + f[1] + (ac[1] - cor[1]) * dt
        vd2 = vd + f[2] + (g + ac[2] - cor[2]) * dt
        self.v = (vn2, ve2, vd2)
        self.llh = (
            lat + 0.5 * (vn + vn2) / (r_m + h) * dt,
            lon + 0.5 * (ve + ve2) / ((r_n + h) * cl) * dt,
            h - 0.5 * (vd + vd2) * dt,
        )

    def gnss(self, fix: Fix) -> str:
        """One fix: align on it, or correct the INS with it. Says what became of it."""
        if fix.t_valid_s <= self._t_fix_s + 0.005:  # the same epoch again (both protocols), or older
            return "duplicate"
        if not self.aligned:
            self._align(fix)
            return "aligned"
        self._t_fix_s, dt = fix.t_valid_s, max(fix.t_valid_s - self._t_fix_s, 1e-3)
        self._heading_from_course(fix.vel_ned_mps)
        row, age = self._state_at(fix.t_valid_s)
        r_m, r_n = radii_m(self.llh[0])
        h = self.llh[2]
        z_pos = np.array(
            [
                (math.radians(fix.lat_deg) - row[1]) * (r_m + h),
                (math.radians(fix.lon_deg) - row[2]) * (r_n + h) * math.cos(row[1]),
                row[3] - fix.alt_m,
            ]
        )
        z_vel = fix.vel_ned_mps - row[4:7]
        dx = self._update(z_pos, z_vel, fix, dt)
        if dx is None:
            return "rejected"
        self._correct(dx, fix.t_valid_s, age)
        self.counts["fixes_used"] += 1
        return "used"

    def _align(self, fix: Fix) -> None:
        f = self._f_level
        roll, pitch = math.atan2(-f[1], -f[2]), math.atan2(f[0], math.hypot(f[1], f[2]))
        vn, ve = fix.vel_ned_mps[:2]
        self.q = quat_euler(roll, pitch, 0.0)
        self._heading_from_course(fix.vel_ned_mps)
        self.v = tuple(float(x) for x in np.nan_to_num(fix.vel_ned_mps))  # type: ignore[assignment]
        self.llh = (math.radians(fix.lat_deg), math.radians(fix.lon_deg), fix.alt_m)
        ps = np.nan_to_num(fix.pos_sigma_m, nan=10.0)
        vs = np.nan_to_num(fix.vel_sigma_mps, nan=1.0)
        self.P = np.array([np.diag([ps[i] ** 2, vs[i] ** 2, P0_ACC_MPS2**2]) for i in range(3)])
        self._t_fix_s = fix.t_valid_s
        self.aligned = True
        LOG.info(
            "aligned at %.6f, %.6f: roll %.2f pitch %.2f heading %s", fix.lat_deg, fix.lon_deg,
            math.degrees(roll), math.degrees(pitch),
            f"{math.degrees(math.atan2(ve, vn)):.1f} deg (course)" if self.heading_valid else "unknown",
        )  # fmt: skip

    def _heading_from_course(self, vel_ned_mps: np.ndarray) -> None:
        """Heading = the GNSS course, averaged over the first ``HEADING_FIXES`` fixes once moving
        (the mean of course - heading, so a turn meanwhile does not bias it); then the gyros'."""
        if self._course_fixes >= HEADING_FIXES or math.hypot(*vel_ned_mps[:2]) < MIN_COURSE_SPEED_MPS:
            return
        roll, pitch, yaw = euler_of(self.q)
        err = math.remainder(math.atan2(vel_ned_mps[1], vel_ned_mps[0]) - yaw, math.tau)
        self._course_fixes += 1
        self.q = quat_euler(roll, pitch, yaw + err / self._course_fixes)
        self.heading_valid = True

    def _state_at(self, t_s: float) -> tuple[np.ndarray, float]:
        """The remembered state nearest ``t_s`` and its age now; the current one if none fits
        (a clock that does not run at real time: the fix then counts as taken now)."""
        t = self._hist[:, 0]
        k = int(np.argmin(np.abs(t - t_s)))
        if abs(t[k] - t_s) > 0.05:
            self.counts["fixes_unaligned"] += 1
            return np.array([self._t_s, *self.llh, *self.v]), 0.0
        return self._hist[k].copy(), max(0.0, self._t_s - t[k])

    def _update(self, z_pos: np.ndarray, z_vel: np.ndarray, fix: Fix, dt: float) -> np.ndarray | None:
        """The Kalman update of each axis; the corrections (3 axes x pos, vel, acc) or None if gated."""
        f = np.array([[1.0, dt, 0.5 * dt * dt], [0.0, 1.0, dt], [0.0, 0.0, 1.0]])
        q = np.diag([Q_POS_M2PS, Q_VEL_M2PS3, Q_ACC_M2PS5]) * dt
        r_pos = np.nan_to_num(fix.pos_sigma_m, nan=10.0) ** 2
        r_vel = fix.vel_sigma_mps**2
        self.P = np.array([f @ p @ f.T + q for p in self.P])
        dx, new_p, worst = np.zeros((3, 3)), self.P.copy(), 0.0
        for i in range(3):
            rows = [0] if not math.isfinite(z_vel[i]) or not math.isfinite(r_vel[i]) else [0, 1]
            hm = np.eye(3)[rows]
            z = np.array([z_pos[i], z_vel[i]])[rows]
            s = hm @ self.P[i] @ hm.T + np.diag(np.array([r_pos[i], r_vel[i]])[rows])
            worst = max(worst, float(np.max(np.abs(z) / np.sqrt(np.diag(s)))))
            k = self.P[i] @ hm.T @ np.linalg.inv(s)
            dx[i] = k @ z
            p = (np.eye(3) - k @ hm) @ self.P[i]
            new_p[i] = 0.5 * (p + p.T)
        if worst > GATE_SIGMA and self._gate_misses < GATE_RESET:
            self._gate_misses += 1
            self.counts["fixes_rejected"] += 1
            return None
        self._gate_misses = 0
        self.P = new_p
        return dx

    def _correct(self, dx: np.ndarray, t_valid_s: float, age_s: float) -> None:
        """Feed the corrections back (closed loop): position, velocity, attitude, accel error."""
        r_m, r_n = radii_m(self.llh[0])
        h = self.llh[2]
        to_llh = np.array([1.0 / (r_m + h), 1.0 / ((r_n + h) * math.cos(self.llh[0])), -1.0])
        dpos, dvel, dacc = dx[:, 0], dx[:, 1], dx[:, 2]
        self.llh = tuple((self.llh + (dpos + dvel * age_s) * to_llh).tolist())  # type: ignore[assignment]
        self.v = tuple((self.v + dvel).tolist())  # type: ignore[assignment]
        since = np.maximum(self._hist[:, 0] - t_valid_s, 0.0)[:, None]  # history stays consistent
        self._hist[:, 1:4] += (dpos + dvel * since) * to_llh
        self._hist[:, 4:7] += dvel
        f = np.array(self._f_nav) / self._f_nav_s if self._f_nav_s > 0 else np.array([0.0, 0.0, -9.8])
        self._f_nav, self._f_nav_s = (0.0, 0.0, 0.0), 0.0
        ff = float(f @ f)
        phi = np.cross(f, dacc) / ff  # the part of the accel error an attitude error explains
        if not self.heading_valid:
            phi[2] = 0.0
        self.q = quat_mul(quat_rotvec(*phi.tolist()), self.q)
        along = (dacc @ f) / ff * f  # along the specific force: not an attitude error
        self.acc_corr = tuple((self.acc_corr + along).tolist())  # type: ignore[assignment]

    def latest_s(self) -> float:
        """The time of the newest IMU sample taken in, on the unit's UTC clock."""
        return self._t_s

    def lag_s(self, now_s: float) -> float:
        """How old the newest IMU sample taken in is at ``now_s`` (the unit's processing lag)."""
        return now_s - self._t_s

    def solution(self, now_s: float) -> dict[str, float]:
        """The solution predicted to ``now_s`` (the send time), in the unit's output units."""
        lat, lon, h = self.llh
        r_m, r_n = radii_m(lat)
        ahead = min(max(now_s - self._t_s, 0.0), MAX_PREDICT_S)
        roll, pitch, yaw = euler_of(self.q)
        sig = np.sqrt(self.P[:, 0, 0])
        return {
            "lat_deg": math.degrees(lat + self.v[0] * ahead / (r_m + h)),
            "lon_deg": math.degrees(lon + self.v[1] * ahead / ((r_n + h) * math.cos(lat))),
            "alt_m": h - self.v[2] * ahead,
            "vel_ned_mps": self.v,
            "sigma_h_m": float(math.hypot(sig[0], sig[1]) / math.sqrt(2.0)),
            "sigma_v_m": float(sig[2]),
            "roll_deg": math.degrees(roll),
            "pitch_deg": math.degrees(pitch),
            "heading_deg": math.degrees(yaw) % 360.0,
        }


class NavEncoder:
    """The solution as the unit's own frames (``navbox.dbc``); NAV_Attitude last closes a cycle."""

    def __init__(self, dbc_path: Path) -> None:
        self.db = cantools.database.load_file(str(dbc_path))

    def frames(self, sol: dict[str, float]) -> list[can.Message]:
        vn, ve, vd = (float(x) for x in sol["vel_ned_mps"])
        values = {
            "NAV_Position": {"Latitude": sol["lat_deg"], "Longitude": sol["lon_deg"]},
            "NAV_Height": {
                "Altitude": sol["alt_m"],
                "PosSigmaH": sol["sigma_h_m"],
                "PosSigmaV": sol["sigma_v_m"],
            },
            "NAV_Velocity": {"VelNorth": vn, "VelEast": ve, "VelUp": -vd},
            "NAV_Attitude": {
                "Roll": sol["roll_deg"],
                "Pitch": sol["pitch_deg"],
                "Heading": sol["heading_deg"],
            },
        }
        out = []
        for name, signals in values.items():
            m = self.db.get_message_by_name(name)
            clipped = {}
            for s in m.signals:  # a value beyond the DBC's range is sent at its limit
                x = signals[s.name] if math.isfinite(signals[s.name]) else 0.0
                lo = s.minimum if s.minimum is not None else -math.inf
                clipped[s.name] = min(max(x, lo), s.maximum if s.maximum is not None else math.inf)
            out.append(can.Message(arbitration_id=m.frame_id, data=m.encode(clipped), is_extended_id=False))
        return out


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    p = argparse.ArgumentParser(description=(__doc__ or "navbox").split("\n\n")[0])
    p.add_argument("--can-interface", default="socketcan", help="python-can interface (socketcan, hilzenoh)")
    p.add_argument("--channel", default="vcan0", help="CAN channel of the IMU (and of the unit's output)")
    p.add_argument("--fd", action="store_true", help="the IMU sends CAN FD (one frame per sample)")
    p.add_argument("--gnss", required=True, help="the GNSS receiver's line: a serial device or pty path")
    p.add_argument("--gnss-baud", type=int, default=115200, help="its baud rate (8N1)")
    p.add_argument("--imu-dbc", type=Path, default=DEFAULT_IMU_DBC, help="the IMU's DBC")
    p.add_argument("--nav-dbc", type=Path, default=DEFAULT_NAV_DBC, help="the unit's own output DBC")
    p.add_argument("--nmea-vel-sigma", type=float, default=0.3, help="m/s: NMEA carries no velocity sigma")
    p.add_argument("--stop-with-pid", type=int, default=None, help="stop when this process is gone")
    return p.parse_args(argv)


class Unit:
    """The unit's main loop: CAN in, GNSS fixes in, solutions out at 10 Hz on its own clock."""

    def __init__(self, args: argparse.Namespace, stop: threading.Event) -> None:
        self.args, self.stop = args, stop
        self.imu = ImuDecoder(args.imu_dbc)
        self.out = NavEncoder(args.nav_dbc)
        self.nav = Navigator()
        self.parser = GnssParser(args.nmea_vel_sigma)
        self.line = GnssLine(args.gnss, args.gnss_baud, self.parser, stop)
        kinds = ("solutions", "send_errors", "stale_skipped", "fixes_duplicate", "lag_max_ms")
        self.counts = dict.fromkeys(kinds, 0)
        self.pending: deque[Fix] = deque()  # fixes ahead of the IMU data taken in

    def run(self) -> None:
        a = self.args
        bus = can.Bus(interface=a.can_interface, channel=a.channel, fd=a.fd)
        LOG.info("CAN %s %s%s, GNSS %s at %d baud", a.can_interface, a.channel, " FD" if a.fd else "",
                 a.gnss, a.gnss_baud)  # fmt: skip
        self.line.start()
        next_out = next_check = next_log = 0.0
        try:
            while not self.stop.is_set():
                self._frames(bus)
                now = time.time()
                self._fixes(now)
                if now >= next_out:
                    next_out = (math.floor(now / OUTPUT_PERIOD_S) + 1) * OUTPUT_PERIOD_S
                    self._send(bus, now)
                if now >= next_check:
                    next_check = now + 1.0
                    if now >= next_log:
                        next_log = now + 10.0
                        LOG.info("%s", self.summary())
                    if a.stop_with_pid and not _alive(a.stop_with_pid):
                        LOG.info("process %d is gone: stopping", a.stop_with_pid)
                        break
        finally:
            self.stop.set()
            bus.shutdown()
            self.line.join(timeout=2.0)
            LOG.info("stopped: %s", self.summary())

    def _frames(self, bus: can.BusABC) -> None:
        """The frames waiting (up to a batch: the output must not wait), at most 50 ms for one."""
        msg, n = bus.recv(timeout=0.05), 0
        while msg is not None:
            sample = self.imu.feed(msg)
            if sample is not None:
                self.nav.imu(sample)
            n += 1
            msg = bus.recv(timeout=0.0) if n < FRAME_BATCH else None

    def _fixes(self, now: float) -> None:
        """Fixes in time order, each once the IMU has reached its time of validity (on a busy
        host the IMU frames can fall behind the line); one that waited too long goes as it is."""
        while True:
            try:
                self.pending.append(self.line.fixes.get_nowait())
            except queue.Empty:
                break
        while self.pending:
            fix = self.pending[0]
            if fix.t_valid_s > self.nav.latest_s() and now - fix.rx_s < MAX_FIX_WAIT_S:
                return
            self.pending.popleft()
            if self.nav.gnss(fix) == "duplicate":
                self.counts["fixes_duplicate"] += 1

    def _send(self, bus: can.BusABC, now: float) -> None:
        if not self.nav.aligned:
            return
        lag_s = self.nav.lag_s(now)
        if lag_s > MAX_PREDICT_S:  # no IMU data for too long: say nothing rather than guess
            self.counts["stale_skipped"] += 1
            return
        self.counts["lag_max_ms"] = max(self.counts["lag_max_ms"], round(lag_s * 1e3))
        for frame in self.out.frames(self.nav.solution(now)):
            try:
                bus.send(frame, timeout=0.05)
            except can.CanError:
                self.counts["send_errors"] += 1
                return
        self.counts["solutions"] += 1

    def summary(self) -> str:
        c = {**{f"imu_{k}": v for k, v in self.imu.counts.items()}, **self.parser.counts}
        c.update(self.nav.counts)
        c.update(self.counts)
        return " ".join(f"{k}={v}" for k, v in c.items())


def _alive(pid: int) -> bool:
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:
        return True
    return True


def main(argv: list[str] | None = None) -> int:
    logging.basicConfig(level=logging.INFO, format="%(asctime)s navbox: %(message)s")
    args = parse_args(argv)
    stop = threading.Event()
    for sig in (signal.SIGTERM, signal.SIGINT):
        signal.signal(sig, lambda *_: stop.set())
    Unit(args, stop).run()
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

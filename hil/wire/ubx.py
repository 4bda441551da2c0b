"""u-blox UBX as an F9 receiver sends it: NAV-PVT (+ NAV-COV), or NAV-POSLLH + NAV-VELNED; TIM-TP.

Layouts from the u-blox interface descriptions (ZED-F9P Interface Description UBX-18010854; u-blox 8 /
M8 Receiver Description UBX-13003221), as pyubx2 (``ubxtypes_get.py``) defines them too. A frame is
``B5 62 class id len(u16 LE) payload ck_a ck_b`` with the 8-bit Fletcher checksum over class..payload.

Field quantisation (the round trip is exact to within half a quantum):

==============================  ====================================================================
field                           quantum
==============================  ====================================================================
iTOW (all NAV)                  1 ms, rounded to nearest; NAV-PVT's UTC date/time + ``nano`` keep 1 ns
lat / lon                       1e-7 deg (1.1 cm north)
height / hMSL                   1 mm (hMSL = height: geoid separation 0, as in the NMEA codec)
velN/E/D, gSpeed, sAcc (PVT)    1 mm/s; NAV-VELNED: 1 cm/s
hAcc / vAcc                     1 mm
headMot / headAcc               1e-5 deg
pDOP                            0.01
NAV-COV covariances             float32 (relative 6e-8)
==============================  ====================================================================

Choices, stated:

* Accuracies: ``hAcc = sqrt((sN^2 + sE^2) / 2)`` (per-axis RMS, so a reader that takes hAcc as the
  north and east sigma -- the ROS u-blox driver does -- gets the right size), ``vAcc = sD``,
  ``sAcc = sqrt((vN^2 + vE^2 + vD^2) / 3)`` of the velocity sigmas, ``headAcc`` = horizontal speed
  sigma / gSpeed in degrees, capped at 180. NAV-COV carries the exact diagonal (off-diagonals 0):
  the decoder prefers it, else takes (hAcc, hAcc, vAcc) and (sAcc, sAcc, sAcc).
* NAV-PVT flags of a valid fix as an F9 sets them: valid = validDate|validTime|fullyResolved (0x07),
  flags = gnssFixOK (0x01), flags2 = confirmedAvai|confirmedDate|confirmedTime (0xE0), flags3 = 0;
  without a fix fixType 0 and flags 0x00. headVeh = headMot (headVehValid unset), magDec 0.
* The UTC fields are the time of validity in UTC (sec 60 inside a leap second) with ``nano`` in
  [0, 1e9); tAcc from ``ReceiverEpoch.time_sigma_ns``.
* Message order in an epoch is by message ID, as a u-blox receiver emits its periodic NAV messages:
  NAV-POSLLH (0x02), NAV-PVT (0x07), NAV-VELNED (0x12), NAV-COV (0x36), NAV-EOE (0x61, end of epoch).
* TIM-TP announces the next pulse in GPS time (timeBase GNSS, timeRefGnss GPS, UTC available,
  utcStandard USNO: flags 0x02, refInfo 0x30), sent before the pulse it describes.
* The decoder refuses frames whose length field exceeds :data:`MAX_PAYLOAD` (``too_long``): a
  garbage ``B5 62`` must not make it wait for 64 KiB.
"""

from __future__ import annotations

import math
import struct
from dataclasses import replace
from itertools import accumulate
from typing import ClassVar

from hil.wire.base import FIX_NONE, NO_VEC3, DecodedFix, ReceiverEpoch, StreamDecoder, select_messages
from hil.wire.gnss_time import (
    MS_PER_WEEK,
    NS_PER_MS,
    gps_ns_from_week_tow,
    gps_ns_to_utc_fields,
    gps_week_tow,
    utc_fields_to_gps_ns,
)

SYNC = b"\xb5\x62"
MAX_PAYLOAD = 8192

# (class, id) of the messages this codec writes and reads
NAV_POSLLH = (0x01, 0x02)
NAV_PVT = (0x01, 0x07)
NAV_VELNED = (0x01, 0x12)
NAV_COV = (0x01, 0x36)
NAV_EOE = (0x01, 0x61)
TIM_TP = (0x0D, 0x01)
MESSAGE_IDS: dict[str, tuple[int, int]] = {
    "NAV-POSLLH": NAV_POSLLH,
    "NAV-PVT": NAV_PVT,
    "NAV-VELNED": NAV_VELNED,
    "NAV-COV": NAV_COV,
    "NAV-EOE": NAV_EOE,
    "TIM-TP": TIM_TP,
}
MESSAGE_NAMES = {v: k for k, v in MESSAGE_IDS.items()}

_PVT = struct.Struct("<IHBBBBBBIiBBBBiiiiIIiiiiiIIHH4xihH")
_COV = struct.Struct("<IBBB9x12f")
_POSLLH = struct.Struct("<IiiiiII")
_VELNED = struct.Struct("<IiiiIIiII")
_EOE = struct.Struct("<I")
_TIM_TP = struct.Struct("<IIiHBB")
_PAYLOAD_SIZES = {
    NAV_PVT: _PVT.size,
    NAV_COV: _COV.size,
    NAV_POSLLH: _POSLLH.size,
    NAV_VELNED: _VELNED.size,
    NAV_EOE: _EOE.size,
    TIM_TP: _TIM_TP.size,
}

PVT_VALID_DATE, PVT_VALID_TIME, PVT_FULLY_RESOLVED = 0x01, 0x02, 0x04
PVT_GNSS_FIX_OK = 0x01
PVT_FLAGS2_CONFIRMED = 0xE0
TIM_TP_FLAGS = 0x02  # timeBase GNSS, UTC available, RAIM no info, qErr valid
TIM_TP_REFINFO = 0x30  # timeRefGnss GPS, utcStandard USNO
_U4_MAX = 0xFFFFFFFF
_DEG_E5_180 = 18_000_000


def checksum(data: bytes) -> bytes:
    """8-bit Fletcher over class, id, length and payload (C-speed sums, not a byte loop)."""
    return bytes((sum(data) & 0xFF, sum(accumulate(data)) & 0xFF))


def frame(cls_id: tuple[int, int], payload: bytes) -> bytes:
    """A complete UBX frame."""
    body = struct.pack("<BBH", cls_id[0], cls_id[1], len(payload)) + payload
    return SYNC + body + checksum(body)


def _u4(value: float) -> int:
    """Round and clamp to an unsigned 32-bit field (a huge sigma must not break the encoder)."""
    return min(max(round(value), 0), _U4_MAX)


def _i4(value: float) -> int:
    return min(max(round(value), -0x80000000), 0x7FFFFFFF)


def _rounded_itow(gps_ns: int) -> int:
    return gps_week_tow(gps_ns + NS_PER_MS // 2)[1]


class _Accuracies:
    """The sigma fields shared by NAV-PVT, NAV-POSLLH and NAV-VELNED."""

    __slots__ = ("h_acc_mm", "head_acc_e5", "s_acc_mmps", "v_acc_mm")

    def __init__(self, epoch: ReceiverEpoch) -> None:
        sn, se, sd = epoch.pos_sigma_ned_m
        vn, ve, vd = epoch.vel_sigma_mps
        self.h_acc_mm = _u4(math.sqrt((sn * sn + se * se) / 2.0) * 1e3)
        self.v_acc_mm = _u4(sd * 1e3)
        self.s_acc_mmps = _u4(math.sqrt((vn * vn + ve * ve + vd * vd) / 3.0) * 1e3)
        speed = epoch.ground_speed_mps
        h_speed_sigma = math.sqrt((vn * vn + ve * ve) / 2.0)
        head_deg = math.degrees(h_speed_sigma / speed) if speed > 0.0 else 180.0
        self.head_acc_e5 = _u4(min(head_deg, 180.0) * 1e5)


def _nav_pvt(epoch: ReceiverEpoch, itow_ms: int, acc: _Accuracies) -> bytes:
    y, mo, d, h, mi, s, nano = gps_ns_to_utc_fields(epoch.gps_time_ns)
    fix_ok = epoch.fix_type != FIX_NONE
    vn, ve, vd = epoch.vel_ned_mps
    head_e5 = round(epoch.course_deg * 1e5) % 36_000_000
    height_mm = _i4(epoch.alt_m * 1e3)
    payload = _PVT.pack(
        itow_ms,
        y,
        mo,
        d,
        h,
        mi,
        s,
        PVT_VALID_DATE | PVT_VALID_TIME | PVT_FULLY_RESOLVED,
        _u4(epoch.time_sigma_ns),
        nano,
        epoch.fix_type,
        PVT_GNSS_FIX_OK if fix_ok else 0,
        PVT_FLAGS2_CONFIRMED,
        min(max(epoch.num_sats, 0), 255),
        _i4(epoch.lon_deg * 1e7),
        _i4(epoch.lat_deg * 1e7),
        height_mm,
        height_mm,  # hMSL: geoid separation 0
        acc.h_acc_mm,
        acc.v_acc_mm,
        _i4(vn * 1e3),
        _i4(ve * 1e3),
        _i4(vd * 1e3),
        _i4(epoch.ground_speed_mps * 1e3),
        head_e5,
        acc.s_acc_mmps,
        acc.head_acc_e5,
        min(max(round(epoch.pdop * 100.0), 0), 0xFFFF),
        0,  # flags3
        head_e5,  # headVeh = headMot while headVehValid is unset
        0,  # magDec
        0,  # magAcc
    )
    return frame(NAV_PVT, payload)


def _nav_cov(epoch: ReceiverEpoch, itow_ms: int) -> bytes:
    sn, se, sd = epoch.pos_sigma_ned_m
    vn, ve, vd = epoch.vel_sigma_mps
    payload = _COV.pack(
        itow_ms, 0, 1, 1, sn * sn, 0.0, 0.0, se * se, 0.0, sd * sd, vn * vn, 0.0, 0.0, ve * ve, 0.0, vd * vd
    )
    return frame(NAV_COV, payload)


def _nav_posllh(epoch: ReceiverEpoch, itow_ms: int, acc: _Accuracies) -> bytes:
    height_mm = _i4(epoch.alt_m * 1e3)
    payload = _POSLLH.pack(
        itow_ms,
        _i4(epoch.lon_deg * 1e7),
        _i4(epoch.lat_deg * 1e7),
        height_mm,
        height_mm,
        acc.h_acc_mm,
        acc.v_acc_mm,
    )
    return frame(NAV_POSLLH, payload)


def _nav_velned(epoch: ReceiverEpoch, itow_ms: int, acc: _Accuracies) -> bytes:
    vn, ve, vd = epoch.vel_ned_mps
    payload = _VELNED.pack(
        itow_ms,
        _i4(vn * 100.0),
        _i4(ve * 100.0),
        _i4(vd * 100.0),
        _u4(math.sqrt(vn * vn + ve * ve + vd * vd) * 100.0),
        _u4(epoch.ground_speed_mps * 100.0),
        round(epoch.course_deg * 1e5) % 36_000_000,
        _u4(acc.s_acc_mmps / 10.0),
        acc.head_acc_e5,
    )
    return frame(NAV_VELNED, payload)


class UbxProtocol:
    """UBX output of a u-blox F9; ``talker`` is accepted for a uniform signature and ignored."""

    name: ClassVar[str] = "ubx"
    START: ClassVar[bytes] = SYNC  # what a frame begins with, for a line carrying several protocols

    @staticmethod
    def message_length(buf: bytes | bytearray) -> int:
        """Bytes of the frame at the start of ``buf`` (sync, class, id, length, payload, checksum);
        0: not all there yet; -1: not a frame (a length beyond any message)."""
        if len(buf) < 6:
            return 0
        n = 8 + int.from_bytes(buf[4:6], "little")
        if n > MAX_PAYLOAD + 8:
            return -1
        return n if len(buf) >= n else 0

    SUPPORTED_MESSAGES: ClassVar[tuple[str, ...]] = (
        "NAV-POSLLH",
        "NAV-PVT",
        "NAV-VELNED",
        "NAV-COV",
        "NAV-EOE",
    )
    DEFAULT_MESSAGES: ClassVar[tuple[str, ...]] = ("NAV-PVT", "NAV-COV", "NAV-EOE")
    LEGACY_MESSAGES: ClassVar[tuple[str, ...]] = ("NAV-POSLLH", "NAV-VELNED")

    def __init__(self, messages: tuple[str, ...] | None = None, talker: str = "GN") -> None:
        self.messages = select_messages(messages, self.DEFAULT_MESSAGES, self.SUPPORTED_MESSAGES, "UBX")
        if "NAV-PVT" not in self.messages and "NAV-POSLLH" not in self.messages:
            raise ValueError(f"UBX: {self.messages} has no position message (NAV-PVT or NAV-POSLLH)")
        self.talker = talker

    def printed_time_ns(self, gps_ns: int) -> int:
        """A time of validity as the frames state it: NAV-PVT's UTC fields and ``nano`` to the
        ns, iTOW alone (NAV-POSLLH + NAV-VELNED) to the nearest ms."""
        if "NAV-PVT" in self.messages:
            return gps_ns
        return (gps_ns + NS_PER_MS // 2) // NS_PER_MS * NS_PER_MS

    def encode_epoch(self, epoch: ReceiverEpoch) -> bytes:
        """All configured NAV messages of one epoch, in message-ID order."""
        itow_ms = _rounded_itow(epoch.gps_time_ns)
        acc = _Accuracies(epoch)
        out: list[bytes] = []
        for m in self.messages:
            if m == "NAV-PVT":
                out.append(_nav_pvt(epoch, itow_ms, acc))
            elif m == "NAV-COV":
                out.append(_nav_cov(epoch, itow_ms))
            elif m == "NAV-POSLLH":
                out.append(_nav_posllh(epoch, itow_ms, acc))
            elif m == "NAV-VELNED":
                out.append(_nav_velned(epoch, itow_ms, acc))
            else:
                out.append(frame(NAV_EOE, _EOE.pack(itow_ms)))
        return b"".join(out)

    def encode_pps_announcement(self, next_pps_gps_ns: int, q_err_ps: int = 0) -> bytes:
        """TIM-TP for the pulse at ``next_pps_gps_ns`` (GPS time): week, towMS, towSubMS (2^-32 ms)."""
        week, tow_ms, sub_ns = gps_week_tow(next_pps_gps_ns)
        sub_ms = (sub_ns << 32) // NS_PER_MS
        q_err = min(max(q_err_ps, -0x80000000), 0x7FFFFFFF)
        return frame(TIM_TP, _TIM_TP.pack(tow_ms, sub_ms, q_err, week & 0xFFFF, TIM_TP_FLAGS, TIM_TP_REFINFO))

    def decoder(self) -> UbxDecoder:
        return UbxDecoder(self.messages)


# ---------------------------------------------------------------------------------------------
# decoding


class _Epoch:
    """The NAV payloads received for one iTOW."""

    __slots__ = ("at", "itow_ms", "names", "payloads")

    def __init__(self, itow_ms: int, at: int) -> None:
        self.itow_ms = itow_ms
        self.at = at  # where its first frame began on the line
        self.names: list[str] = []
        self.payloads: dict[str, bytes] = {}


def _sigma(variance: float) -> float:
    return math.sqrt(variance) if variance > 0.0 else 0.0


class UbxDecoder(StreamDecoder):
    """Streaming UBX decoder: one DecodedFix per iTOW, resynchronising on garbage.

    An epoch closes on NAV-EOE if the configuration has it, else when every configured NAV message
    of that iTOW has arrived, and in any case when a NAV message of another iTOW arrives. NAV-PVT
    alone makes a fix; NAV-COV refines its sigmas; NAV-POSLLH + NAV-VELNED make one too. TIM-TP sets
    :attr:`last_pps_gps_ns` and the GPS week used for messages without a date. Longer payloads than
    this codec's layout are accepted (u-blox appends fields in later versions); shorter are malformed.
    """

    def __init__(self, messages: tuple[str, ...] | None = None, max_payload: int = MAX_PAYLOAD) -> None:
        super().__init__()
        configured = messages or UbxProtocol.DEFAULT_MESSAGES
        self._close_on_eoe = "NAV-EOE" in configured
        self._required = frozenset(m for m in configured if m.startswith("NAV-") and m != "NAV-EOE")
        self._max_payload = max_payload
        self.counters["pps_announcements"] = 0
        self.last_pps_gps_ns: int | None = None
        self._week_ref: tuple[int, int] | None = None  # (GPS week, tow ms) of a recent message
        self._open: _Epoch | None = None
        self._closed_itow: int | None = None

    GARBAGE = "outside any UBX frame"

    def _scan(self, buf: bytearray, out: list[DecodedFix]) -> int:
        pos = 0
        while True:
            start = buf.find(SYNC, pos)
            if start < 0:
                keep = len(buf) - 1 if buf.endswith(SYNC[:1]) else len(buf)  # a sync may be split
                self._garbage(keep - pos)
                pos = max(keep, pos)
                break
            self._garbage(start - pos)
            if len(buf) - start < 8:
                pos = start
                break
            cls, msg_id, length = struct.unpack_from("<BBH", buf, start + 2)
            if length > self._max_payload:
                self.problem(
                    "too_long", f"UBX 0x{cls:02x} 0x{msg_id:02x} length {length} > {self._max_payload}"
                )
                self.counters["garbage_bytes"] += 2
                pos = start + 2
                continue
            end = start + 8 + length
            if len(buf) < end:
                pos = start
                break
            self._msg_at = self._at + start
            pos = self._frame(bytes(buf[start:end]), start, buf, out)
        return pos

    def _frame(self, raw: bytes, start: int, buf: bytearray, out: list[DecodedFix]) -> int:
        """Check one complete-length frame at ``start``; return where to scan next."""
        if checksum(raw[2:-2]) != raw[-2:]:
            inner = raw.find(SYNC, 2)
            if inner > 0:  # the next frame began inside this one: it was cut short
                self.problem("truncated", f"UBX frame cut short after {inner} bytes")
                return start + inner
            self.problem("bad_checksum", f"UBX 0x{raw[2]:02x} 0x{raw[3]:02x} checksum mismatch")
            self.counters["garbage_bytes"] += 2
            return start + 2
        self.counters["messages"] += 1
        self._message((raw[2], raw[3]), raw[6:-2], out)
        return start + len(raw)

    def _message(self, cls_id: tuple[int, int], payload: bytes, out: list[DecodedFix]) -> None:
        name = MESSAGE_NAMES.get(cls_id)
        if name is None:
            self.problem("unknown", f"UBX 0x{cls_id[0]:02x} 0x{cls_id[1]:02x} not read")
            return
        if len(payload) < _PAYLOAD_SIZES[cls_id]:
            self.problem("malformed", f"{name} payload {len(payload)} < {_PAYLOAD_SIZES[cls_id]} bytes")
            return
        if cls_id == TIM_TP:
            tow_ms, sub_ms, _q_err, week, _flags, _ref = _TIM_TP.unpack_from(payload)
            self.last_pps_gps_ns = gps_ns_from_week_tow(week, tow_ms, (sub_ms * NS_PER_MS) >> 32)
            self._week_ref = (week, tow_ms)
            self.counters["pps_announcements"] += 1
            return
        (itow_ms,) = _EOE.unpack_from(payload)
        epoch = self._open
        if epoch is not None and epoch.itow_ms != itow_ms:
            self._close(out)
            epoch = None
        if epoch is None:
            if itow_ms == self._closed_itow:
                self.problem("late", f"{name} of the closed epoch iTOW {itow_ms}")
                return
            epoch = self._open = _Epoch(itow_ms, self._msg_at)
        epoch.names.append(name)
        epoch.payloads[name] = payload
        if name == "NAV-EOE" or (not self._close_on_eoe and self._required.issubset(epoch.payloads)):
            self._close(out)

    def _close(self, out: list[DecodedFix]) -> None:
        epoch, self._open = self._open, None
        if epoch is None:
            return
        self._closed_itow = epoch.itow_ms
        if "NAV-PVT" not in epoch.payloads and "NAV-POSLLH" not in epoch.payloads:
            self.problem("incomplete", f"iTOW {epoch.itow_ms} closed without NAV-PVT or NAV-POSLLH")
            return
        try:
            fix = self._assemble(epoch)
        except (ValueError, OverflowError) as exc:
            self.problem("malformed", f"iTOW {epoch.itow_ms}: {exc}")
            return
        self.counters["fixes"] += 1
        out.append(replace(fix, first_byte_at=epoch.at))

    def _time_from_week(self, itow_ms: int) -> int | None:
        """GPS ns from iTOW and the week of a recent TIM-TP or dated NAV-PVT (None before one)."""
        if self._week_ref is None:
            return None
        week, ref_tow = self._week_ref
        if itow_ms - ref_tow > MS_PER_WEEK // 2:
            week -= 1
        elif ref_tow - itow_ms > MS_PER_WEEK // 2:
            week += 1
        return gps_ns_from_week_tow(week, itow_ms)

    def _assemble(self, epoch: _Epoch) -> DecodedFix:
        p = epoch.payloads
        pvt = p.get("NAV-PVT")
        if pvt is not None:
            fix = self._from_pvt(epoch, pvt)
        else:
            fix = self._from_posllh_velned(epoch, p["NAV-POSLLH"], p.get("NAV-VELNED"))
        cov = p.get("NAV-COV")
        if cov is None:
            return fix
        _itow, _version, pos_valid, vel_valid, nn, _ne, _nd, ee, _ed, dd, vnn, _vne, _vnd, vee, _ved, vdd = (
            _COV.unpack_from(cov)
        )
        return _replace_sigmas(
            fix,
            (_sigma(nn), _sigma(ee), _sigma(dd)) if pos_valid else fix.pos_sigma_ned_m,
            (_sigma(vnn), _sigma(vee), _sigma(vdd)) if vel_valid else fix.vel_sigma_mps,
        )

    def _pvt_time(self, itow_ms: int, valid: int, ymdhms: tuple[int, ...], nano: int) -> int | None:
        """GPS ns from NAV-PVT's UTC fields when date and time are valid, else from iTOW + week."""
        if valid & (PVT_VALID_DATE | PVT_VALID_TIME) != PVT_VALID_DATE | PVT_VALID_TIME:
            return self._time_from_week(itow_ms)
        try:
            gps_ns = utc_fields_to_gps_ns(*ymdhms, nano)
        except ValueError as exc:
            self.problem("malformed", f"NAV-PVT iTOW {itow_ms}: {exc}")
            return None
        if gps_ns >= 0:
            week, tow_ms, _ = gps_week_tow(gps_ns)
            self._week_ref = (week, tow_ms)
        return gps_ns

    def _from_pvt(self, epoch: _Epoch, pvt: bytes) -> DecodedFix:
        (itow, year, month, day, hour, minute, sec, valid, _t_acc, nano, fix_type, flags, _flags2, num_sv,
         lon, lat, height, _h_msl, h_acc, v_acc, vel_n, vel_e, vel_d, _g_speed, _head, s_acc, _head_acc,
         p_dop, _flags3, _head_veh, _mag_dec, _mag_acc) = _PVT.unpack_from(pvt)  # fmt: skip
        gps_ns = self._pvt_time(itow, valid, (year, month, day, hour, minute, sec), nano)
        tod_ns = ((hour * 60 + minute) * 60 + sec) * 1_000_000_000 + nano if valid & PVT_VALID_TIME else None
        h_sigma, s_sigma = h_acc * 1e-3, s_acc * 1e-3
        return DecodedFix(
            protocol="ubx",
            messages=tuple(epoch.names),
            rx_ns=self._rx_ns,
            gps_time_ns=gps_ns,
            utc_time_of_day_ns=tod_ns,
            lat_deg=lat * 1e-7,
            lon_deg=lon * 1e-7,
            alt_m=height * 1e-3,
            vel_ned_mps=(vel_n * 1e-3, vel_e * 1e-3, vel_d * 1e-3),
            pos_sigma_ned_m=(h_sigma, h_sigma, v_acc * 1e-3),
            vel_sigma_mps=(s_sigma, s_sigma, s_sigma),
            fix_type=fix_type if flags & PVT_GNSS_FIX_OK else FIX_NONE,
            num_sats=num_sv,
            hdop=None,
            pdop=p_dop * 0.01,
            vdop=None,
        )

    def _from_posllh_velned(self, epoch: _Epoch, posllh: bytes, velned: bytes | None) -> DecodedFix:
        itow, lon, lat, height, _h_msl, h_acc, v_acc = _POSLLH.unpack_from(posllh)
        h_sigma = h_acc * 1e-3
        vel: tuple[float | None, float | None, float | None] = NO_VEC3
        vel_sigma: tuple[float | None, float | None, float | None] = NO_VEC3
        if velned is not None:
            _itow, vel_n, vel_e, vel_d, _speed, _g_speed, _heading, s_acc, _c_acc = _VELNED.unpack_from(
                velned
            )
            vel = (vel_n * 1e-2, vel_e * 1e-2, vel_d * 1e-2)
            vel_sigma = (s_acc * 1e-2, s_acc * 1e-2, s_acc * 1e-2)
        return DecodedFix(
            protocol="ubx",
            messages=tuple(epoch.names),
            rx_ns=self._rx_ns,
            gps_time_ns=self._time_from_week(itow),
            utc_time_of_day_ns=None,
            lat_deg=lat * 1e-7,
            lon_deg=lon * 1e-7,
            alt_m=height * 1e-3,
            vel_ned_mps=vel,
            pos_sigma_ned_m=(h_sigma, h_sigma, v_acc * 1e-3),
            vel_sigma_mps=vel_sigma,
            fix_type=None,
            num_sats=None,
            hdop=None,
            pdop=None,
            vdop=None,
        )


def _replace_sigmas(
    fix: DecodedFix,
    pos_sigma: tuple[float | None, float | None, float | None],
    vel_sigma: tuple[float | None, float | None, float | None],
) -> DecodedFix:
    return replace(fix, pos_sigma_ned_m=pos_sigma, vel_sigma_mps=vel_sigma)

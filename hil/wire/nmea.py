"""NMEA 0183 v4.10 as a u-blox M8/F9 receiver prints it: GGA, RMC, GSA, GST, VTG, ZDA.

Formats follow the u-blox receiver interface descriptions (u-blox 8 / M8 Receiver Description incl.
Protocol Specification, UBX-13003221; ZED-F9P Interface Description, UBX-18010854, NMEA section) and
their examples such as ``$GNGGA,092725.00,4717.11399,N,00833.91590,E,1,08,1.01,499.6,M,48.0,M,,*5B``;
pynmeagps (``nmeatypes_get.py``, ``nmeatypes_core.py``: TM ``hhmmss.ss``, LA ``ddmm.mmmmm``, LN
``dddmm.mmmmm``) parses the same layout. Printed precision, and so the round-trip quantisation:

===========================  ==================  ==========================================
field                        printed as          quantum (max error is half of it)
===========================  ==================  ==========================================
UTC time (all timed)         ``hhmmss.ss``       10 ms (time of validity rounded to nearest)
latitude / longitude         ``ddmm.mmmmm``      1e-5 arc minute = 1.85 cm north, x cos(lat) east
altitude (GGA)               ``x.x``             0.1 m
geoid separation (GGA)       ``0.0``             always 0.0: MSL altitude = ellipsoidal height
speed over ground (RMC/VTG)  knots ``x.xxx``     0.001 kn = 0.514 mm/s (VTG km/h ``x.xxx``: 0.278 mm/s)
course over ground           ``x.xx``            0.01 deg
HDOP/PDOP/VDOP               ``x.xx``            0.01
GST sigma (lat, lon, alt)    2 significant       ~5 % relative, 1 mm at least (u-blox prints e.g.
                             digits              ``0.46,0.29,0.64`` and ``1.2,0.77,2.2``)
===========================  ==================  ==========================================

Choices, stated:

* The geoid separation is reported as 0.0, so the GGA "MSL" altitude is the WGS84 ellipsoidal height
  and altitude + separation round-trips to it. The decoder returns altitude + separation, so a real
  receiver's output (with a real separation) decodes to ellipsoidal height too.
* GSA lists no satellite IDs (12 empty fields): the rig does not simulate a constellation, and
  fake PRNs would contradict the absent GSV. One GSA per epoch, systemId 1 (GPS).
* GST: rangeRms is derived as ``sqrt(sN^2 + sE^2 + sD^2) / PDOP`` (position sigma = DOP x range
  sigma); the error ellipse fields are empty (as u-blox M8 prints them). Empty when PDOP is 0.
* Course over ground is always printed (0.00 when standing still); a real receiver may leave it
  empty at low speed, and the decoder accepts that (velocity (0, 0) if the speed is 0, else None).
* Without a fix (fix_type 0) position, speed and course fields are empty, GGA quality 0, RMC
  status V, posMode N; fix 2-D/3-D is quality 1 (autonomous), posMode A. RMC navStatus is V, as
  u-blox prints it for NMEA 4.10.
* Sentence order in an epoch is the u-blox order: RMC, VTG, GGA, GSA, (GSV, GLL,) GST, ZDA.
* The time of validity is rounded to 10 ms before conversion, so 23:59:59.996 prints as
  ``000000.00`` with the next day's date. A receiver's epochs are on its own clock's grid (e.g.
  .00/.20/... at 5 Hz); an epoch time off that grid is quantised here, not preserved.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import replace
from typing import Any, ClassVar

from hil.wire.base import (
    FIX_NONE,
    NO_VEC3,
    DecodedFix,
    OptVec3,
    ReceiverEpoch,
    StreamDecoder,
    select_messages,
)
from hil.wire.gnss_time import NS_PER_S, gps_ns_to_utc_fields, utc_fields_to_gps_ns

KNOT_MPS = 1852.0 / 3600.0
KMH_MPS = 1000.0 / 3600.0
MAX_SENTENCE_CHARS = 82  # NMEA 0183: "$" to "\n" inclusive
_CENTI_NS = 10_000_000


def checksum(body: bytes) -> int:
    """XOR of the bytes between ``$`` and ``*``: folded in one big integer, C speed for <= 128 bytes."""
    if len(body) > 128:
        x = 0
        for c in body:
            x ^= c
        return x
    v = int.from_bytes(body, "little")
    v ^= v >> 512
    v ^= v >> 256
    v ^= v >> 128
    v ^= v >> 64
    v ^= v >> 32
    v ^= v >> 16
    v ^= v >> 8
    return v & 0xFF


def _frame(body: str) -> bytes:
    raw = body.encode("ascii")
    return b"$%s*%02X\r\n" % (raw, checksum(raw))


def _latlon(value_deg: float, deg_digits: int, hemispheres: str) -> tuple[str, str]:
    """(d)ddmm.mmmmm and hemisphere, rounded in integer 1e-5 minutes so 59.999996' carries to a degree."""
    units = round(abs(value_deg) * 6_000_000.0)
    deg, rest = divmod(units, 6_000_000)
    minute, frac = divmod(rest, 100_000)
    return f"{deg:0{deg_digits}d}{minute:02d}.{frac:05d}", hemispheres[value_deg < 0.0]


def _sig2(value: float) -> str:
    """Two significant digits as u-blox prints GST sigmas (36, 3.2, 0.87, 0.046), 1 mm at least."""
    if not math.isfinite(value) or value < 0.0:
        return ""
    if value >= 9.95:
        return f"{value:.0f}"
    if value >= 0.995:
        return f"{value:.1f}"
    if value >= 0.0995:
        return f"{value:.2f}"
    return f"{value:.3f}"


class _Fields:
    """The printed fields of one epoch, computed once and shared by its sentences."""

    __slots__ = ("cog", "date", "ew", "fix", "hms", "kmh", "knots", "lat", "lon", "mode", "ns", "zda")

    def __init__(self, epoch: ReceiverEpoch) -> None:
        grid_ns = NmeaProtocol.printed_time_ns(epoch.gps_time_ns)
        y, mo, d, h, mi, s, ns = gps_ns_to_utc_fields(grid_ns)
        self.hms = f"{h:02d}{mi:02d}{s:02d}.{ns // _CENTI_NS:02d}"
        self.date = f"{d:02d}{mo:02d}{y % 100:02d}"
        self.zda = f"{d:02d},{mo:02d},{y:04d}"
        self.fix = epoch.fix_type != FIX_NONE
        if self.fix:
            self.lat, self.ns = _latlon(epoch.lat_deg, 2, "NS")
            self.lon, self.ew = _latlon(epoch.lon_deg, 3, "EW")
            speed = epoch.ground_speed_mps
            self.knots = f"{speed / KNOT_MPS:.3f}"
            self.kmh = f"{speed / KMH_MPS:.3f}"
            self.cog = f"{epoch.course_deg:.2f}"
            self.mode = "A"
        else:
            self.lat = self.ns = self.lon = self.ew = self.knots = self.kmh = self.cog = ""
            self.mode = "N"


def _gga(e: ReceiverEpoch, f: _Fields) -> str:
    if not f.fix:
        return f"GGA,{f.hms},,,,,0,{e.num_sats:02d},{e.hdop:.2f},,,,,,"
    return (
        f"GGA,{f.hms},{f.lat},{f.ns},{f.lon},{f.ew},1,{e.num_sats:02d},{e.hdop:.2f},{e.alt_m:.1f},M,0.0,M,,"
    )


def _rmc(e: ReceiverEpoch, f: _Fields) -> str:
    status = "A" if f.fix else "V"
    return f"RMC,{f.hms},{status},{f.lat},{f.ns},{f.lon},{f.ew},{f.knots},{f.cog},{f.date},,,{f.mode},V"


def _vtg(e: ReceiverEpoch, f: _Fields) -> str:
    if not f.fix:
        return "VTG,,T,,M,,N,,K,N"
    return f"VTG,{f.cog},T,,M,{f.knots},N,{f.kmh},K,{f.mode}"


def _gsa(e: ReceiverEpoch, f: _Fields) -> str:
    nav_mode = e.fix_type if f.fix else 1
    return f"GSA,A,{nav_mode},,,,,,,,,,,,,{e.pdop:.2f},{e.hdop:.2f},{e.vdop:.2f},1"


def _gst(e: ReceiverEpoch, f: _Fields) -> str:
    if not f.fix:
        return f"GST,{f.hms},,,,,,,"
    sn, se, sd = e.pos_sigma_ned_m
    rms = _sig2(math.sqrt(sn * sn + se * se + sd * sd) / e.pdop) if e.pdop > 0.0 else ""
    return f"GST,{f.hms},{rms},,,,{_sig2(sn)},{_sig2(se)},{_sig2(sd)}"


def _zda(e: ReceiverEpoch, f: _Fields) -> str:
    return f"ZDA,{f.hms},{f.zda},00,00"


_ENCODERS: dict[str, Callable[[ReceiverEpoch, _Fields], str]] = {
    "RMC": _rmc,
    "VTG": _vtg,
    "GGA": _gga,
    "GSA": _gsa,
    "GST": _gst,
    "ZDA": _zda,
}


class NmeaProtocol:
    """NMEA 0183 output of a u-blox receiver; ``talker`` is the 2-letter talker ID (GN, GP, ...)."""

    name: ClassVar[str] = "nmea"
    START: ClassVar[bytes] = b"$"  # what a sentence begins with, for a line carrying several protocols

    @staticmethod
    def message_length(buf: bytes | bytearray) -> int:
        """Bytes of the sentence at the start of ``buf`` ("$" ... "\\n"); 0: not all there yet;
        a sentence far longer than NMEA allows is handed on whole to be counted too long."""
        end = buf.find(b"\n", 0, 4 * MAX_SENTENCE_CHARS)
        if end >= 0:
            return end + 1
        return 0 if len(buf) < 4 * MAX_SENTENCE_CHARS else 4 * MAX_SENTENCE_CHARS

    SUPPORTED_MESSAGES: ClassVar[tuple[str, ...]] = ("RMC", "VTG", "GGA", "GSA", "GST", "ZDA")
    DEFAULT_MESSAGES: ClassVar[tuple[str, ...]] = SUPPORTED_MESSAGES

    def __init__(self, messages: tuple[str, ...] | None = None, talker: str = "GN") -> None:
        if len(talker) != 2 or not talker.isascii() or not talker.isupper():
            raise ValueError(f"NMEA talker {talker!r} is not two upper-case letters (GN, GP, ...)")
        self.messages = select_messages(messages, self.DEFAULT_MESSAGES, self.SUPPORTED_MESSAGES, "NMEA")
        self.talker = talker
        self._encoders = [_ENCODERS[m] for m in self.messages]

    @staticmethod
    def printed_time_ns(gps_ns: int) -> int:
        """A time of validity as the sentences state it: to the nearest 10 ms (``hhmmss.ss``)."""
        return (gps_ns + _CENTI_NS // 2) // _CENTI_NS * _CENTI_NS

    def encode_epoch(self, epoch: ReceiverEpoch) -> bytes:
        """All configured sentences of one epoch, in u-blox order, each ``$...*hh\\r\\n``."""
        f = _Fields(epoch)
        talker = self.talker
        return b"".join([_frame(talker + enc(epoch, f)) for enc in self._encoders])

    def encode_pps_announcement(self, next_pps_gps_ns: int, q_err_ps: int = 0) -> bytes:
        """NMEA has no time-pulse announcement (UBX TIM-TP has): nothing to send."""
        return b""

    def decoder(self) -> NmeaDecoder:
        return NmeaDecoder(self.messages)


# ---------------------------------------------------------------------------------------------
# decoding


def _num(text: str) -> float | None:
    """A decimal field: None when empty, ValueError when not a finite plain number."""
    if not text:
        return None
    value = float(text)
    if not math.isfinite(value) or "_" in text:
        raise ValueError(f"not a finite number: {text!r}")
    return value


def _angle(text: str, hemi: str, deg_digits: int, limit: float, hemispheres: str) -> float | None:
    """(d)ddmm.mmmmm + hemisphere -> signed degrees."""
    if not text:
        return None
    if hemi not in hemispheres or text[deg_digits : deg_digits + 1] in ("", "-", "+"):
        raise ValueError(f"bad coordinate {text!r},{hemi!r}")
    deg = int(text[:deg_digits])
    minutes = _num(text[deg_digits:])
    if deg < 0 or minutes is None or not 0.0 <= minutes < 60.0 or deg + minutes / 60.0 > limit:
        raise ValueError(f"bad coordinate {text!r}")
    value = deg + minutes / 60.0
    return -value if hemi == hemispheres[1] else value


def _hex(text: bytes) -> int:
    try:
        return int(text, 16)
    except ValueError:
        return -1


def _time_of_day_ns(text: str) -> int | None:
    """``hhmmss[.s...]`` -> ns since midnight (second 60 allowed: a leap second)."""
    if not text:
        return None
    whole, _, frac = text.partition(".")
    if len(whole) != 6 or not whole.isdigit() or len(frac) > 9 or (frac and not frac.isdigit()):
        raise ValueError(f"bad time {text!r}")
    h, mi, s = int(whole[:2]), int(whole[2:4]), int(whole[4:])
    if h > 23 or mi > 59 or s > 60:
        raise ValueError(f"bad time {text!r}")
    return ((h * 60 + mi) * 60 + s) * NS_PER_S + int(frac.ljust(9, "0") or 0)


def _parse_gga(f: list[str]) -> dict[str, Any]:
    quality = int(f[6]) if f[6] else 0
    msl, sep = _num(f[9]), _num(f[11])
    return {
        "lat": _angle(f[2], f[3], 2, 90.0, "NS"),
        "lon": _angle(f[4], f[5], 3, 180.0, "EW"),
        "alt": None if msl is None else msl + (sep or 0.0),
        "quality": quality,
        "sats": int(f[7]) if f[7] else None,
        "hdop": _num(f[8]),
    }


def _parse_rmc(f: list[str]) -> dict[str, Any]:
    date = f[9]
    if date and (len(date) != 6 or not date.isdigit()):
        raise ValueError(f"bad date {date!r}")
    ymd = None
    if date:
        yy = int(date[4:])
        ymd = (yy + (1900 if yy >= 80 else 2000), int(date[2:4]), int(date[:2]))
    knots = _num(f[7])
    return {
        "status": f[2],
        "lat": _angle(f[3], f[4], 2, 90.0, "NS"),
        "lon": _angle(f[5], f[6], 3, 180.0, "EW"),
        "speed": None if knots is None else knots * KNOT_MPS,
        "course": _num(f[8]),
        "ymd": ymd,
    }


def _parse_vtg(f: list[str]) -> dict[str, Any]:
    kmh, knots = _num(f[7]), _num(f[5])
    speed = kmh * KMH_MPS if kmh is not None else (None if knots is None else knots * KNOT_MPS)
    return {"speed": speed, "course": _num(f[1])}


def _parse_gsa(f: list[str]) -> dict[str, Any]:
    nav_mode = int(f[2]) if f[2] else None
    if nav_mode not in (None, 1, 2, 3):
        raise ValueError(f"GSA navMode {nav_mode}")
    return {"nav_mode": nav_mode, "pdop": _num(f[15]), "hdop": _num(f[16]), "vdop": _num(f[17])}


def _parse_gst(f: list[str]) -> dict[str, Any]:
    return {"sigma": (_num(f[6]), _num(f[7]), _num(f[8]))}


def _parse_zda(f: list[str]) -> dict[str, Any]:
    ymd = (int(f[4]), int(f[3]), int(f[2])) if f[2] and f[3] and f[4] else None
    return {"ymd": ymd}


# kind -> (minimum field count incl. the address, parser, index of the UTC time field or 0)
_PARSERS: dict[str, tuple[int, Callable[[list[str]], dict[str, Any]], int]] = {
    "GGA": (12, _parse_gga, 1),
    "RMC": (10, _parse_rmc, 1),
    "VTG": (8, _parse_vtg, 0),
    "GSA": (18, _parse_gsa, 0),
    "GST": (9, _parse_gst, 1),
    "ZDA": (5, _parse_zda, 1),
}
_POSITION_KINDS = ("GGA", "RMC")


class _Epoch:
    """Sentences gathered for one UTC time (``key`` None until a timed sentence arrives)."""

    __slots__ = ("at", "key", "kinds", "parts", "tod_ns")

    def __init__(self, key: str | None, tod_ns: int | None, at: int) -> None:
        self.key = key
        self.tod_ns = tod_ns
        self.at = at  # where its first sentence began on the line
        self.kinds: list[str] = []
        self.parts: dict[str, dict[str, Any]] = {}


def _horizontal_velocity(speed: float | None, course: float | None) -> tuple[float | None, float | None]:
    if speed is None:
        return None, None
    if course is None:
        return (0.0, 0.0) if speed == 0.0 else (None, None)
    c = math.radians(course)
    return speed * math.cos(c), speed * math.sin(c)


def _fix_type(parts: dict[str, dict[str, Any]]) -> int | None:
    """GSA's navMode (1 -> 0); else no fix if GGA/RMC say so; else unknown (GGA has no 2-D/3-D)."""
    gsa = parts.get("GSA")
    if gsa is not None and gsa["nav_mode"] is not None:
        return 0 if gsa["nav_mode"] == 1 else int(gsa["nav_mode"])
    if "GGA" in parts and parts["GGA"]["quality"] == 0:
        return 0
    if "RMC" in parts and parts["RMC"]["status"] == "V":
        return 0
    return None


def _gps_time_ns(epoch: _Epoch, parts: dict[str, dict[str, Any]]) -> int | None:
    ymd = (parts.get("ZDA") or {}).get("ymd") or (parts.get("RMC") or {}).get("ymd")
    if ymd is None or epoch.tod_ns is None:
        return None
    s_of_day, nano = divmod(epoch.tod_ns, NS_PER_S)
    return utc_fields_to_gps_ns(*ymd, s_of_day // 3600, s_of_day // 60 % 60, s_of_day % 60, nano)


def _assemble(epoch: _Epoch, rx_ns: int) -> DecodedFix:
    """One DecodedFix from an epoch's sentences (ValueError for an impossible date)."""
    parts = epoch.parts
    gga, rmc, gsa = parts.get("GGA"), parts.get("RMC"), parts.get("GSA") or {}
    pos = gga if gga is not None and gga["lat"] is not None else (rmc or gga or {})
    motion = parts.get("VTG") or rmc or {}
    v_n, v_e = _horizontal_velocity(motion.get("speed"), motion.get("course"))
    sigma: OptVec3 = parts["GST"]["sigma"] if "GST" in parts else NO_VEC3
    return DecodedFix(
        protocol="nmea",
        messages=tuple(epoch.kinds),
        rx_ns=rx_ns,
        gps_time_ns=_gps_time_ns(epoch, parts),
        utc_time_of_day_ns=epoch.tod_ns,
        lat_deg=pos.get("lat"),
        lon_deg=pos.get("lon"),
        alt_m=gga["alt"] if gga is not None else None,
        vel_ned_mps=(v_n, v_e, None),
        pos_sigma_ned_m=sigma,
        vel_sigma_mps=NO_VEC3,
        fix_type=_fix_type(parts),
        num_sats=gga["sats"] if gga is not None else None,
        hdop=gga["hdop"] if gga is not None and gga["hdop"] is not None else gsa.get("hdop"),
        pdop=gsa.get("pdop"),
        vdop=gsa.get("vdop"),
    )


class NmeaDecoder(StreamDecoder):
    """Streaming NMEA decoder: one DecodedFix per epoch (sentences with the same UTC time).

    An epoch closes when its last configured sentence arrives (``messages[-1]``, ZDA by default) or
    when a sentence of a newer epoch does. Untimed sentences (VTG, GSA) join the open epoch. A
    sentence type it does not read (GSV, GLL, TXT, proprietary) is counted ``unknown`` and skipped;
    ``messages`` counts every sentence with a valid checksum, known or not.

    Where the values come from: position, altitude (MSL + separation), satellites, HDOP from GGA
    (position from RMC without GGA); the date from ZDA, else RMC (2-digit year read as 1980..2079);
    horizontal velocity from VTG (km/h) else RMC (knots) with the course, vertical velocity and
    velocity sigma None; sigma N/E/D from GST; fix type, PDOP, VDOP from GSA (without GSA the fix
    type is 0 if GGA/RMC say "no fix", else None: GGA cannot tell 2-D from 3-D).
    """

    def __init__(
        self, messages: tuple[str, ...] | None = None, max_sentence_chars: int = MAX_SENTENCE_CHARS
    ) -> None:
        super().__init__()
        configured = messages or NmeaProtocol.DEFAULT_MESSAGES
        self._closing_kind = configured[-1]
        self._max_chars = max_sentence_chars
        self._open: _Epoch | None = None
        self._closed_key: str | None = None

    GARBAGE = "outside any sentence"

    def _scan(self, buf: bytearray, out: list[DecodedFix]) -> int:
        pos = 0
        while True:
            start = buf.find(b"$", pos)
            if start < 0:
                self._garbage(len(buf) - pos)
                pos = len(buf)
                break
            self._garbage(start - pos)
            end = buf.find(b"\n", start)
            if end < 0:
                pos = self._unterminated(buf, start)
                break
            nxt = buf.find(b"$", start + 1, end)
            if nxt >= 0:  # a new sentence began before this one ended
                self.problem("truncated", f"sentence cut short: {bytes(buf[start:nxt])[:40]!r}")
                pos = nxt
                continue
            if end + 1 - start > self._max_chars:
                self.problem("too_long", f"sentence of {end + 1 - start} chars > {self._max_chars}")
            else:
                self._msg_at = self._at + start
                self._sentence(bytes(buf[start:end]), out)
            pos = end + 1
        return pos

    def _unterminated(self, buf: bytearray, start: int) -> int:
        """Where to keep the buffer from when no line end has arrived yet after ``start``."""
        if len(buf) - start <= self._max_chars:
            return start
        self.problem("too_long", f"no line end within {self._max_chars} chars")
        nxt = buf.find(b"$", start + 1)
        if nxt < 0:
            self.counters["garbage_bytes"] += len(buf) - start - 1  # the "$" itself counted as too_long
            return len(buf)
        self.counters["garbage_bytes"] += nxt - start - 1
        return nxt

    def _sentence(self, line: bytes, out: list[DecodedFix]) -> None:
        """Check one ``$...*hh`` line (without ``\\n``) and hand it to its parser."""
        if line.endswith(b"\r"):
            line = line[:-1]
        star = line.rfind(b"*")
        if star < 0:
            self.problem("truncated", f"no checksum: {line[:40]!r}")
            return
        body, given = line[1:star], line[star + 1 :]
        if len(given) != 2 or not given.isalnum() or _hex(given) != checksum(body):
            self.problem("bad_checksum", f"checksum {given[:8]!r} does not match {line[:40]!r}")
            return
        self.counters["messages"] += 1
        if not body.isascii():
            self.problem("malformed", f"non-ASCII sentence {line[:40]!r}")
            return
        fields = body.decode("ascii").split(",")
        kind = fields[0][2:] if len(fields[0]) == 5 else ""
        spec = _PARSERS.get(kind)
        if spec is None:
            self.problem("unknown", f"sentence {fields[0]!r} not read")
            return
        min_fields, parser, time_index = spec
        try:
            if len(fields) < min_fields:
                raise ValueError(f"{len(fields)} fields < {min_fields}")
            values = parser(fields)
            tod_ns = _time_of_day_ns(fields[time_index]) if time_index else None
        except ValueError as exc:
            self.problem("malformed", f"{fields[0]}: {exc}")
            return
        self._place(kind, fields[time_index] if tod_ns is not None else None, tod_ns, values, out)

    def _place(
        self, kind: str, key: str | None, tod_ns: int | None, values: dict[str, Any], out: list[DecodedFix]
    ) -> None:
        """Put a parsed sentence into its epoch, closing the open one when a newer epoch starts."""
        epoch = self._open
        if key is not None:
            if key == self._closed_key and (epoch is None or epoch.key is None):
                self.problem("late", f"{kind} of the closed epoch {key}")
                return
            if epoch is not None and epoch.key is not None and epoch.key != key:
                self._close(out)
                epoch = None
        if epoch is None:
            epoch = self._open = _Epoch(key, tod_ns, self._msg_at)
        elif epoch.key is None and key is not None:
            epoch.key, epoch.tod_ns = key, tod_ns
        epoch.kinds.append(kind)
        epoch.parts[kind] = values
        if kind == self._closing_kind:
            self._close(out)

    def _close(self, out: list[DecodedFix]) -> None:
        epoch, self._open = self._open, None
        if epoch is None:
            return
        self._closed_key = epoch.key
        if not any(k in epoch.parts for k in _POSITION_KINDS):
            self.problem("incomplete", f"epoch {epoch.key} closed without GGA or RMC")
            return
        try:
            fix = _assemble(epoch, self._rx_ns)
        except (ValueError, OverflowError) as exc:
            self.problem("malformed", f"epoch {epoch.key}: {exc}")
            return
        self.counters["fixes"] += 1
        out.append(replace(fix, first_byte_at=epoch.at))

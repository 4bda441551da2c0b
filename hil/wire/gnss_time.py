"""GPS time and UTC for the wire codecs: leap seconds, GPS week / time of week, calendar fields.

Time scales, all integer nanoseconds:

* GPS time: ns since the GPS epoch 1980-01-06T00:00:00 (UTC = GPS then), continuous, no leap seconds.
* UTC as POSIX time: ns since 1970-01-01T00:00:00 with 86 400 s per day, as ``time.time_ns()``
  counts it. A leap second has no POSIX number of its own.

Leap seconds: :data:`LEAP_SECONDS` holds every leap second since 1980 (GPS - UTC = 18 s since
2017-01-01). Table last updated 2026-12-02: IERS Bulletin C had announced no leap second after
2016-12-31 as of this writing. A future leap second needs a new entry here (IERS announces them
about six months ahead), otherwise UTC is off by one second after it.

What happens inside an inserted leap second (e.g. 2016-12-31T23:59:60.x UTC), explicitly:

* :func:`gps_ns_to_utc_fields` gives ``second == 60``, as a receiver prints it (NMEA ``235960.00``,
  UBX NAV-PVT ``sec = 60``), and :func:`utc_fields_to_gps_ns` reads it back: the round trip through
  calendar fields is exact there too.
* :func:`gps_ns_to_utc_ns` gives the POSIX time 23:59:59.x again (the leap second repeats the POSIX
  second before it, as an NTP-disciplined kernel does), so POSIX time cannot tell the two apart and
  :func:`utc_ns_to_gps_ns` maps 23:59:59.x of that day to the first one. The POSIX round trip
  GPS -> UTC -> GPS is exact everywhere except inside a leap second, where it is 1 s early.
"""

from __future__ import annotations

from bisect import bisect_right
from datetime import date

NS_PER_S = 1_000_000_000
NS_PER_MS = 1_000_000
NS_PER_DAY = 86_400 * NS_PER_S
NS_PER_WEEK = 7 * NS_PER_DAY
MS_PER_WEEK = 7 * 86_400_000

GPS_EPOCH_POSIX_S = 315_964_800  # 1980-01-06T00:00:00 UTC as POSIX seconds
GPS_EPOCH_POSIX_NS = GPS_EPOCH_POSIX_S * NS_PER_S
_POSIX_EPOCH_ORDINAL = date(1970, 1, 1).toordinal()

LEAP_TABLE_UPDATED = "2026-12-02"  # last entry 2017-01-01; see the module docstring

# (first UTC day after the inserted second, GPS - UTC in seconds from that day on)
_LEAP_DATES: tuple[tuple[tuple[int, int, int], int], ...] = (
    ((1981, 7, 1), 1),
    ((1982, 7, 1), 2),
    ((1983, 7, 1), 3),
    ((1985, 7, 1), 4),
    ((1988, 1, 1), 5),
    ((1990, 1, 1), 6),
    ((1991, 1, 1), 7),
    ((1992, 7, 1), 8),
    ((1993, 7, 1), 9),
    ((1994, 7, 1), 10),
    ((1996, 1, 1), 11),
    ((1997, 7, 1), 12),
    ((1999, 1, 1), 13),
    ((2006, 1, 1), 14),
    ((2009, 1, 1), 15),
    ((2012, 7, 1), 16),
    ((2015, 7, 1), 17),
    ((2017, 1, 1), 18),
)


def _posix_day_ns(year: int, month: int, day: int) -> int:
    return (date(year, month, day).toordinal() - _POSIX_EPOCH_ORDINAL) * NS_PER_DAY


# (POSIX ns of 00:00:00 UTC after the leap second, GPS - UTC from then on)
LEAP_SECONDS: tuple[tuple[int, int], ...] = tuple((_posix_day_ns(*d), s) for d, s in _LEAP_DATES)
_LEAP_POSIX_NS = [t for t, _ in LEAP_SECONDS]
# GPS ns at which each new offset starts to count: the end of the inserted second
_LEAP_GPS_NS = [t - GPS_EPOCH_POSIX_NS + s * NS_PER_S for t, s in LEAP_SECONDS]


def gps_minus_utc_s_at_utc(utc_ns: int) -> int:
    """GPS - UTC in whole seconds in force at POSIX time ``utc_ns`` (0 before 1981-07-01)."""
    i = bisect_right(_LEAP_POSIX_NS, utc_ns)
    return LEAP_SECONDS[i - 1][1] if i else 0


def gps_minus_utc_s_at_gps(gps_ns: int) -> int:
    """GPS - UTC in whole seconds at GPS time ``gps_ns``; inside a leap second, the old value."""
    i = bisect_right(_LEAP_GPS_NS, gps_ns)
    return LEAP_SECONDS[i - 1][1] if i else 0


def _in_leap_second(gps_ns: int) -> bool:
    """True inside an inserted second (UTC 23:59:60.x)."""
    i = bisect_right(_LEAP_GPS_NS, gps_ns)
    return i < len(_LEAP_GPS_NS) and gps_ns >= _LEAP_GPS_NS[i] - NS_PER_S


def utc_ns_to_gps_ns(utc_ns: int) -> int:
    """POSIX UTC ns -> GPS ns."""
    return utc_ns - GPS_EPOCH_POSIX_NS + gps_minus_utc_s_at_utc(utc_ns) * NS_PER_S


def gps_ns_to_utc_ns(gps_ns: int) -> int:
    """GPS ns -> POSIX UTC ns; inside a leap second the POSIX second 23:59:59 repeats."""
    offset_s = gps_minus_utc_s_at_gps(gps_ns) + (1 if _in_leap_second(gps_ns) else 0)
    return gps_ns + GPS_EPOCH_POSIX_NS - offset_s * NS_PER_S


def gps_week_tow(gps_ns: int) -> tuple[int, int, int]:
    """GPS ns -> (full week number, not modulo 1024; time of week in ms; ns within that ms)."""
    if gps_ns < 0:
        raise ValueError(f"GPS time {gps_ns} ns is before the GPS epoch 1980-01-06")
    week, ns_of_week = divmod(gps_ns, NS_PER_WEEK)
    tow_ms, nano = divmod(ns_of_week, NS_PER_MS)
    return week, tow_ms, nano


def gps_ns_from_week_tow(week: int, tow_ms: int, nano: int = 0) -> int:
    """(full week, time of week in ms, ns within the ms) -> GPS ns."""
    return week * NS_PER_WEEK + tow_ms * NS_PER_MS + nano


def utc_fields(utc_ns: int) -> tuple[int, int, int, int, int, int, int]:
    """POSIX UTC ns -> (year, month, day, hour, minute, second, nanosecond); second is 0..59."""
    days, ns_of_day = divmod(utc_ns, NS_PER_DAY)
    d = date.fromordinal(_POSIX_EPOCH_ORDINAL + days)
    s_of_day, nanosecond = divmod(ns_of_day, NS_PER_S)
    hour, rest = divmod(s_of_day, 3600)
    minute, second = divmod(rest, 60)
    return d.year, d.month, d.day, hour, minute, second, nanosecond


def gps_ns_to_utc_fields(gps_ns: int) -> tuple[int, int, int, int, int, int, int]:
    """GPS ns -> UTC calendar fields as a receiver prints them: second == 60 inside a leap second."""
    if _in_leap_second(gps_ns):
        y, mo, d, h, mi, s, ns = utc_fields(gps_ns_to_utc_ns(gps_ns))  # 23:59:59.x repeated
        return y, mo, d, h, mi, s + 1, ns
    return utc_fields(gps_ns_to_utc_ns(gps_ns))


def utc_fields_to_utc_ns(
    year: int, month: int, day: int, hour: int, minute: int, second: int, nanosecond: int = 0
) -> int:
    """Calendar fields -> POSIX UTC ns (second 60 lands on the next day's 00:00:00, as POSIX does)."""
    return _posix_day_ns(year, month, day) + ((hour * 60 + minute) * 60 + second) * NS_PER_S + nanosecond


def utc_fields_to_gps_ns(
    year: int, month: int, day: int, hour: int, minute: int, second: int, nanosecond: int = 0
) -> int:
    """UTC calendar fields -> GPS ns; second == 60 is the leap second (the inverse of
    :func:`gps_ns_to_utc_fields`). ``nanosecond`` may be negative (UBX ``nano`` is signed).
    A ValueError for an impossible date."""
    if not (0 <= hour < 24 and 0 <= minute < 60 and 0 <= second <= 60):
        raise ValueError(f"no such UTC time {hour:02d}:{minute:02d}:{second:02d}")
    if second == 60:
        before = utc_fields_to_utc_ns(year, month, day, hour, minute, 59)
        return before + NS_PER_S + nanosecond - GPS_EPOCH_POSIX_NS + gps_minus_utc_s_at_utc(before) * NS_PER_S
    whole = utc_fields_to_utc_ns(year, month, day, hour, minute, second)
    return utc_ns_to_gps_ns(whole) + nanosecond

"""GPS time and UTC (hil.wire.gnss_time): leap seconds, weeks past the 1024 rollovers, calendar fields,
and what NMEA prints at a day boundary, across the GPS week rollovers and around a leap second."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pynmeagps import NMEAReader, leapsecond, utc2wnotow

from hil.wire.base import ReceiverEpoch
from hil.wire.gnss_time import (
    LEAP_SECONDS,
    NS_PER_MS,
    NS_PER_S,
    NS_PER_WEEK,
    gps_minus_utc_s_at_gps,
    gps_minus_utc_s_at_utc,
    gps_ns_from_week_tow,
    gps_ns_to_utc_fields,
    gps_ns_to_utc_ns,
    gps_week_tow,
    utc_fields,
    utc_fields_to_gps_ns,
    utc_fields_to_utc_ns,
    utc_ns_to_gps_ns,
)
from hil.wire.nmea import NmeaProtocol

GPS_2100_NS = 3_800_000_000 * NS_PER_S  # beyond 2100
MS = NS_PER_MS


def _posix_ns(*fields: int) -> int:
    return int(datetime(*fields, tzinfo=UTC).timestamp()) * NS_PER_S


def _epoch(gps_ns: int) -> ReceiverEpoch:
    return ReceiverEpoch(
        gps_ns, 47.0, 8.0, 500.0, (0.0, 0.0, 0.0), (1.0, 1.0, 2.0), (0.1, 0.1, 0.1), 3, 10, 1.0, 1.5, 1.1
    )


def _nmea(gps_ns: int) -> dict[str, object]:
    """The time and date fields NMEA prints for an epoch at ``gps_ns`` (checked by pynmeagps)."""
    out: dict[str, object] = {}
    for line in NmeaProtocol(("RMC", "ZDA")).encode_epoch(_epoch(gps_ns)).splitlines():
        fields = line.split(b"*")[0].decode().split(",")
        NMEAReader.parse(line + b"\r\n", validate=1)  # raises on a bad checksum
        out[fields[0][3:]] = fields
    rmc, zda = out["RMC"], out["ZDA"]
    assert isinstance(rmc, list) and isinstance(zda, list)
    return {"hms": rmc[1], "rmc_date": rmc[9], "zda_hms": zda[1], "zda_date": tuple(zda[2:5])}


def test_leap_table_has_every_leap_second_since_1980() -> None:
    assert len(LEAP_SECONDS) == 18
    assert [s for _, s in LEAP_SECONDS] == list(range(1, 19))
    for t_ns, _ in LEAP_SECONDS:  # every one at the start of 1 January or 1 July
        d = datetime.fromtimestamp(t_ns // NS_PER_S, UTC)
        assert (d.month, d.day, d.hour, d.minute, d.second) in ((1, 1, 0, 0, 0), (7, 1, 0, 0, 0))
    assert LEAP_SECONDS[-1] == (_posix_ns(2017, 1, 1), 18)


@pytest.mark.parametrize("t_ns", [t for t, _ in LEAP_SECONDS])
def test_leap_table_agrees_with_pynmeagps(t_ns: int) -> None:
    for probe_ns in (t_ns - NS_PER_S, t_ns):
        dt = datetime.fromtimestamp(probe_ns // NS_PER_S, UTC)
        assert gps_minus_utc_s_at_utc(probe_ns) == leapsecond(dt), dt


def test_gps_minus_utc_at_landmarks() -> None:
    assert gps_minus_utc_s_at_utc(_posix_ns(1980, 1, 6)) == 0
    assert gps_minus_utc_s_at_utc(_posix_ns(1999, 8, 22)) == 13
    assert gps_minus_utc_s_at_utc(_posix_ns(2016, 12, 31, 23, 59, 59)) == 17
    assert gps_minus_utc_s_at_utc(_posix_ns(2026, 1, 1)) == 18
    assert utc_ns_to_gps_ns(_posix_ns(1980, 1, 6)) == 0
    assert gps_week_tow(0) == (0, 0, 0)


@pytest.mark.parametrize(
    ("week", "utc"),
    [(1024, (1999, 8, 21, 23, 59, 47)), (2048, (2019, 4, 6, 23, 59, 42))],
)
def test_gps_week_rollovers_give_full_weeks(week: int, utc: tuple[int, ...]) -> None:
    """GPS week 1024 and 2048 start at GPS midnight, which is UTC minus the leap seconds of then."""
    start = utc_fields_to_gps_ns(*utc)
    assert start == week * NS_PER_WEEK
    assert gps_week_tow(start) == (week, 0, 0)
    assert gps_week_tow(start - 1) == (week - 1, 604_799_999, 999_999)
    assert gps_ns_to_utc_fields(start) == (*utc, 0)
    wno, tow_ms, _ = utc2wnotow(datetime(*utc, 500_000, tzinfo=UTC) + timedelta(hours=1), modwno=False)
    assert (wno, tow_ms) == (week, 3_600_500)  # pynmeagps agrees an hour later (no 1024 modulo)


@pytest.mark.parametrize("utc", [(1999, 8, 21, 23, 59, 47), (2019, 4, 6, 23, 59, 42)])
def test_nmea_dates_across_the_week_rollovers(utc: tuple[int, ...]) -> None:
    start = utc_fields_to_gps_ns(*utc)
    y, mo, d = utc[0] % 100, utc[1], utc[2]
    before, at = _nmea(start - NS_PER_S), _nmea(start)
    assert at["hms"] == f"{utc[3]:02d}{utc[4]:02d}{utc[5]:02d}.00"
    assert at["rmc_date"] == before["rmc_date"]
    assert before["rmc_date"] == f"{d:02d}{mo:02d}{y:02d}"
    assert before["zda_date"] == (f"{d:02d}", f"{mo:02d}", str(utc[0]))
    # the UTC day changes 13 (1999) / 18 (2019) s after the week does; the date is never 1024 weeks off
    nxt = datetime(*utc[:3], tzinfo=UTC) + timedelta(days=1)
    late = _nmea(start + 30 * NS_PER_S)
    assert late["rmc_date"] == nxt.strftime("%d%m%y")
    assert late["zda_date"] == (nxt.strftime("%d"), nxt.strftime("%m"), str(nxt.year))


def test_nmea_day_boundary() -> None:
    """23:59:59.95 prints on its own day; 23:59:59.996 rounds to 00:00:00.00 of the next day."""
    last = _nmea(utc_fields_to_gps_ns(2024, 12, 31, 23, 59, 59, 950_000_000))
    assert (last["hms"], last["rmc_date"], last["zda_date"]) == ("235959.95", "311224", ("31", "12", "2024"))
    rounded = _nmea(utc_fields_to_gps_ns(2024, 12, 31, 23, 59, 59, 996_000_000))
    assert (rounded["hms"], rounded["rmc_date"], rounded["zda_date"]) == (
        "000000.00",
        "010125",
        ("01", "01", "2025"),
    )
    first = _nmea(utc_fields_to_gps_ns(2025, 1, 1, 0, 0, 0))
    assert first == rounded
    assert first["zda_hms"] == "000000.00"


def test_leap_second_2016_12_31() -> None:
    """Inside the inserted second the calendar says 23:59:60 (as a receiver prints it); POSIX time
    repeats 23:59:59; calendar fields round-trip exactly, POSIX time does not inside the leap second."""
    t0 = utc_fields_to_gps_ns(2016, 12, 31, 23, 59, 59)
    steps = [t0 + k * 500 * MS for k in range(5)]
    assert [gps_ns_to_utc_fields(t)[3:6] for t in steps] == [
        (23, 59, 59),
        (23, 59, 59),
        (23, 59, 60),
        (23, 59, 60),
        (0, 0, 0),
    ]
    assert [gps_minus_utc_s_at_gps(t) for t in steps] == [17, 17, 17, 17, 18]
    leap = steps[3]  # 23:59:60.5
    assert gps_ns_to_utc_fields(leap) == (2016, 12, 31, 23, 59, 60, 500_000_000)
    assert utc_fields_to_gps_ns(2016, 12, 31, 23, 59, 60, 500_000_000) == leap
    assert gps_ns_to_utc_ns(leap) == utc_fields_to_utc_ns(2016, 12, 31, 23, 59, 59, 500_000_000)
    assert utc_ns_to_gps_ns(gps_ns_to_utc_ns(leap)) == leap - NS_PER_S  # the first 23:59:59.5
    assert (
        utc_fields_to_gps_ns(2017, 1, 1, 0, 0, 0) - utc_fields_to_gps_ns(2016, 12, 31, 23, 59, 59)
        == 2 * NS_PER_S
    )
    assert _nmea(leap)["hms"] == "235960.50"
    assert _nmea(leap)["rmc_date"] == "311216"
    assert _nmea(steps[4])["rmc_date"] == "010117"


def test_utc_fields_agree_with_datetime() -> None:
    for posix_s in (0, 315_964_800, 951_782_400, 1_483_228_799, 4_102_444_800):  # incl. 2000-02-29
        d = datetime.fromtimestamp(posix_s, UTC)
        assert utc_fields(posix_s * NS_PER_S + 123) == (*d.timetuple()[:6], 123)


def test_impossible_times_are_refused() -> None:
    with pytest.raises(ValueError):
        utc_fields_to_gps_ns(2024, 2, 30, 0, 0, 0)
    with pytest.raises(ValueError):
        utc_fields_to_gps_ns(2024, 1, 1, 24, 0, 0)
    with pytest.raises(ValueError):
        gps_week_tow(-1)


@settings(derandomize=True, max_examples=300)
@given(st.integers(min_value=0, max_value=GPS_2100_NS))
def test_round_trips(gps_ns: int) -> None:
    assert utc_fields_to_gps_ns(*gps_ns_to_utc_fields(gps_ns)) == gps_ns
    assert gps_ns_from_week_tow(*gps_week_tow(gps_ns)) == gps_ns
    week, tow_ms, nano = gps_week_tow(gps_ns)
    assert week == gps_ns // NS_PER_WEEK and 0 <= tow_ms < 604_800_000 and 0 <= nano < NS_PER_MS
    assert utc_ns_to_gps_ns(gps_ns_to_utc_ns(gps_ns)) == gps_ns  # no leap second is hit at random


@settings(derandomize=True, max_examples=100)
@given(
    st.sampled_from([t for t, _ in LEAP_SECONDS]),
    st.integers(min_value=-3 * NS_PER_S, max_value=3 * NS_PER_S),
)
def test_round_trips_around_every_leap_second(t_ns: int, offset_ns: int) -> None:
    gps_ns = utc_ns_to_gps_ns(t_ns) + offset_ns
    assert utc_fields_to_gps_ns(*gps_ns_to_utc_fields(gps_ns)) == gps_ns
    inside = -NS_PER_S <= offset_ns < 0
    assert utc_ns_to_gps_ns(gps_ns_to_utc_ns(gps_ns)) == gps_ns - (NS_PER_S if inside else 0)

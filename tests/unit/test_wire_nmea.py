"""The NMEA codec (hil.wire.nmea) against pynmeagps, the field's parser, and against itself.

Quantisation the round trips allow (half a printed digit, see the module docstring): lat/lon 1e-5
arc minute (0.93 cm), altitude 0.05 m, speed 0.0005 km/h + course 0.005 deg, DOPs 0.005, GST sigma
5 % (2 significant digits, 0.5 mm at least), time 5 ms (10 ms grid).
"""

from __future__ import annotations

import functools
import math
import operator
import random
from datetime import date, time

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pynmeagps import NMEAMessage, NMEAReader
from pynmeagps.nmeatypes_core import VALCKSUM, VALMSGID

from hil.wire import protocol
from hil.wire.base import COUNTER_NAMES, DecodedFix, ReceiverEpoch
from hil.wire.gnss_time import NS_PER_S, gps_ns_to_utc_fields, utc_fields_to_gps_ns
from hil.wire.nmea import KMH_MPS, KNOT_MPS, NmeaDecoder, NmeaProtocol, checksum
from tests.wire_samples import T0, sample_epoch

LATLON_TOL_DEG = 0.5e-5 / 60.0 + 1e-10
# years 1999..2068: pynmeagps reads RMC's 2-digit year with strptime's pivot (69 -> 1969); the codec
# reads yy < 80 as 20yy (GPS time starts in 1980), so the two agree up to 2068
GPS_2068_S = 2_808_000_000
FUZZ = settings(derandomize=True, max_examples=300, deadline=None)


_epoch = sample_epoch


@st.composite
def epochs(draw: st.DrawFn, fix_types: tuple[int, ...] = (2, 3)) -> ReceiverEpoch:
    f = st.floats
    vel = st.tuples(*[f(-120.0, 120.0)] * 3)
    sigma = st.tuples(*[f(0.001, 60.0)] * 3)
    return ReceiverEpoch(
        gps_time_ns=draw(st.integers(630_000_000, GPS_2068_S)) * NS_PER_S + draw(st.integers(0, 99)) * 10**7,
        lat_deg=draw(f(-89.999, 89.999)),
        lon_deg=draw(f(-179.999, 179.999)),
        alt_m=draw(f(-400.0, 9000.0)),
        vel_ned_mps=draw(vel),
        pos_sigma_ned_m=draw(sigma),
        vel_sigma_mps=draw(sigma),
        fix_type=draw(st.sampled_from(fix_types)),
        num_sats=draw(st.integers(0, 40)),
        hdop=draw(f(0.5, 30.0)),
        pdop=draw(f(0.5, 40.0)),
        vdop=draw(f(0.5, 30.0)),
    )


def _lines(data: bytes) -> list[bytes]:
    assert data.endswith(b"\r\n")
    return [line + b"\r\n" for line in data.split(b"\r\n")[:-1]]


def _parse(line: bytes) -> NMEAMessage:
    msg = NMEAReader.parse(line, validate=VALCKSUM | VALMSGID)  # raises on a bad checksum
    assert msg is not None
    return msg


def _sigma_close(printed: float, true: float) -> bool:
    return abs(printed - true) <= max(0.051 * true, 0.0005) + 1e-12


# ---------------------------------------------------------------------------------------------
# the format a u-blox receiver prints


def test_checksum_matches_the_u_blox_example() -> None:
    body = b"GPGGA,092725.00,4717.11399,N,00833.91590,E,1,08,1.01,499.6,M,48.0,M,,"
    assert checksum(body) == 0x5B  # the interface description prints *5B
    assert checksum(b"A" * 200) == 0  # the byte loop for long bodies agrees with XOR
    assert checksum(b"A" * 129) == ord("A")


def test_sentences_of_one_epoch_in_u_blox_order_and_format() -> None:
    gps_ns = utc_fields_to_gps_ns(2002, 12, 9, 9, 27, 25)
    lat = 47 + 17.11399 / 60
    lon = 8 + 33.91590 / 60
    data = NmeaProtocol().encode_epoch(_epoch(gps_ns, lat_deg=lat, lon_deg=lon, vel_ned_mps=(0.0, 0.0, 0.0)))
    text = [line.decode().split("*")[0] for line in _lines(data)]
    assert text == [
        "$GNRMC,092725.00,A,4717.11399,N,00833.91590,E,0.000,0.00,091202,,,A,V",
        "$GNVTG,0.00,T,,M,0.000,N,0.000,K,A",
        "$GNGGA,092725.00,4717.11399,N,00833.91590,E,1,08,1.01,499.6,M,0.0,M,,",
        "$GNGSA,A,3,,,,,,,,,,,,,1.80,1.01,1.40,1",
        "$GNGST,092725.00,0.47,,,,0.46,0.29,0.64",  # rangeRms = |sigma| / PDOP = 0.84 / 1.8
        "$GNZDA,092725.00,09,12,2002,00,00",
    ]
    assert all(len(line) <= 82 for line in _lines(data))


def test_southern_western_hemispheres_and_minute_carry() -> None:
    data = NmeaProtocol(("GGA",), talker="GP").encode_epoch(
        _epoch(lat_deg=-33.99999999, lon_deg=-70.9999999999)
    )
    fields = data.decode().split(",")
    assert fields[0] == "$GPGGA"
    assert fields[2:6] == ["3400.00000", "S", "07100.00000", "W"]  # 59.9999994' carries to a degree


def test_no_fix_prints_empty_position() -> None:
    data = NmeaProtocol().encode_epoch(_epoch(fix_type=0, hdop=99.99, pdop=99.99, vdop=99.99, num_sats=0))
    text = [line.decode().split("*")[0] for line in _lines(data)]
    assert text[0] == "$GNRMC,123456.20,V,,,,,,,060524,,,N,V"
    assert text[1] == "$GNVTG,,T,,M,,N,,K,N"
    assert text[2] == "$GNGGA,123456.20,,,,,0,00,99.99,,,,,,"
    assert text[3].startswith("$GNGSA,A,1,")
    for line in _lines(data):
        _parse(line)
    dec = NmeaDecoder()
    (fix,) = dec.feed(data, 1)
    assert fix.fix_type == 0 and fix.lat_deg is None and fix.vel_ned_mps == (None, None, None)


def test_configuration() -> None:
    assert protocol("nmea") is NmeaProtocol
    with pytest.raises(KeyError, match="known: nmea, ubx"):
        protocol("sirf")
    p = NmeaProtocol(("ZDA", "GGA"), talker="GP")
    assert p.messages == ("GGA", "ZDA")  # reordered to the send order
    assert [line[3:6] for line in _lines(p.encode_epoch(_epoch()))] == [b"GGA", b"ZDA"]
    with pytest.raises(ValueError, match="GSV"):
        NmeaProtocol(("GGA", "GSV"))
    with pytest.raises(ValueError, match="talker"):
        NmeaProtocol(talker="gps")
    assert p.encode_pps_announcement(T0) == b""
    assert NmeaProtocol.DEFAULT_MESSAGES == ("RMC", "VTG", "GGA", "GSA", "GST", "ZDA")


# ---------------------------------------------------------------------------------------------
# pynmeagps reads every sentence, to the printed precision


def _check_against_pynmeagps(e: ReceiverEpoch, msgs: dict[str, NMEAMessage]) -> None:
    y, mo, d, h, mi, s, ns = gps_ns_to_utc_fields(e.gps_time_ns)
    t = time(h, mi, s, ns // 1000)
    speed, course = e.ground_speed_mps, e.course_deg
    gga, rmc, vtg, gsa, gst, zda = (msgs[k] for k in ("GGA", "RMC", "VTG", "GSA", "GST", "ZDA"))
    for m in (gga, rmc, gst, zda):
        assert m.time == t
    assert rmc.date == date(y, mo, d) and (zda.day, zda.month, zda.year) == (d, mo, y)
    for m in (gga, rmc):
        assert abs(m.lat - e.lat_deg) <= LATLON_TOL_DEG and abs(m.lon - e.lon_deg) <= LATLON_TOL_DEG
    assert abs(gga.alt - e.alt_m) <= 0.05 + 1e-9 and gga.sep == 0.0
    assert gga.numSV == e.num_sats and gga.quality == 1
    assert abs(gga.HDOP - e.hdop) <= 0.005 + 1e-9 and abs(gsa.HDOP - e.hdop) <= 0.005 + 1e-9
    assert abs(gsa.PDOP - e.pdop) <= 0.005 + 1e-9 and abs(gsa.VDOP - e.vdop) <= 0.005 + 1e-9
    assert gsa.navMode == e.fix_type and rmc.status == "A" and rmc.posMode == "A"
    for knots in (rmc.spd, vtg.sogn):
        assert abs(knots - speed / KNOT_MPS) <= 0.0005 + 1e-9
    assert abs(vtg.sogk - speed / KMH_MPS) <= 0.0005 + 1e-9
    for cog in (rmc.cog, vtg.cogt):
        assert abs((cog - course + 180.0) % 360.0 - 180.0) <= 0.005 + 1e-9
    for printed, true in zip((gst.stdLat, gst.stdLong, gst.stdAlt), e.pos_sigma_ned_m, strict=True):
        assert _sigma_close(printed, true)
    assert _sigma_close(gst.rangeRms, math.sqrt(sum(v * v for v in e.pos_sigma_ned_m)) / e.pdop)


@settings(derandomize=True, max_examples=200, deadline=None)
@given(epochs(), st.sampled_from(["GN", "GP"]))
def test_every_sentence_parses_in_pynmeagps_to_the_same_values(e: ReceiverEpoch, talker: str) -> None:
    e = ReceiverEpoch(**{**_fields(e), "gps_time_ns": e.gps_time_ns // 10**7 * 10**7})  # on the 10 ms grid
    msgs: dict[str, NMEAMessage] = {}
    for line in _lines(NmeaProtocol(talker=talker).encode_epoch(e)):
        msg = _parse(line)
        assert msg.talker == talker and len(line) <= 82
        msgs[msg.msgID] = msg
    _check_against_pynmeagps(e, msgs)


def _fields(e: ReceiverEpoch) -> dict[str, object]:
    return {k: getattr(e, k) for k in ReceiverEpoch.__dataclass_fields__}


# ---------------------------------------------------------------------------------------------
# round trips through our own decoder


def _assert_round_trip(e: ReceiverEpoch, fix: DecodedFix) -> None:
    assert fix.protocol == "nmea" and fix.messages == NmeaProtocol.DEFAULT_MESSAGES
    assert fix.gps_time_ns is not None and abs(fix.gps_time_ns - e.gps_time_ns) <= 5_000_000
    assert fix.lat_deg is not None and abs(fix.lat_deg - e.lat_deg) <= LATLON_TOL_DEG
    assert fix.lon_deg is not None and abs(fix.lon_deg - e.lon_deg) <= LATLON_TOL_DEG
    assert fix.alt_m is not None and abs(fix.alt_m - e.alt_m) <= 0.05 + 1e-9
    speed = e.ground_speed_mps
    tol = 0.0005 * KMH_MPS + speed * math.radians(0.005) + 1e-9
    assert fix.vel_ned_mps[2] is None and fix.vel_sigma_mps == (None, None, None)
    for got, true in zip(fix.vel_ned_mps[:2], e.vel_ned_mps[:2], strict=True):
        assert got is not None and abs(got - true) <= tol
    for got_s, true_s in zip(fix.pos_sigma_ned_m, e.pos_sigma_ned_m, strict=True):
        assert got_s is not None and _sigma_close(got_s, true_s)
    assert (fix.fix_type, fix.num_sats) == (e.fix_type, e.num_sats)
    for got_d, true_d in ((fix.hdop, e.hdop), (fix.pdop, e.pdop), (fix.vdop, e.vdop)):
        assert got_d is not None and abs(got_d - true_d) <= 0.005 + 1e-9


@settings(derandomize=True, max_examples=200, deadline=None)
@given(epochs())
def test_encode_decode_round_trip(e: ReceiverEpoch) -> None:
    p = NmeaProtocol()
    dec = p.decoder()
    fixes = dec.feed(p.encode_epoch(e), rx_ns=42)
    assert len(fixes) == 1 and fixes[0].rx_ns == 42
    _assert_round_trip(e, fixes[0])
    assert dec.counters["messages"] == 6 and dec.counters["fixes"] == 1
    assert sum(dec.counters[k] for k in COUNTER_NAMES if k not in ("bytes", "messages", "fixes")) == 0


def _stream(n: int = 3, talker: str = "GN") -> tuple[list[ReceiverEpoch], bytes]:
    es = [_epoch(T0 + k * 200_000_000, lat_deg=47.0 + k * 1e-4) for k in range(n)]
    p = NmeaProtocol(talker=talker)
    return es, b"".join(p.encode_epoch(e) for e in es)


def test_stream_split_at_every_byte_decodes_identically() -> None:
    _, data = _stream()
    whole = NmeaDecoder().feed(data, 0)
    assert len(whole) == 3
    for cut in range(len(data) + 1):
        dec = NmeaDecoder()
        got = dec.feed(data[:cut], 0) + dec.feed(data[cut:], 0)
        assert got == whole, cut
    dec = NmeaDecoder()
    one_by_one = [fix for i in range(len(data)) for fix in dec.feed(data[i : i + 1], 0)]
    assert one_by_one == whole
    assert dec.counters["bytes"] == len(data) and dec.counters["garbage_bytes"] == 0


def test_rx_ns_is_that_of_the_chunk_completing_the_epoch() -> None:
    _, data = _stream(2)
    one = len(data) // 2
    dec = NmeaDecoder()
    assert dec.feed(data[: one - 5], 100) == []
    (first,) = dec.feed(data[one - 5 : one + 10], 200)
    assert first.rx_ns == 200 and dec.feed(data[one + 10 :], 300)[0].rx_ns == 300


def test_epoch_closes_on_its_last_configured_sentence_or_a_newer_epoch() -> None:
    gga_only = NmeaProtocol(("GGA",))
    data = b"".join(gga_only.encode_epoch(_epoch(T0 + k * NS_PER_S)) for k in range(2))
    dec = gga_only.decoder()
    fixes = dec.feed(data, 0)
    assert len(fixes) == 2 and fixes[0].gps_time_ns is None  # no date without RMC or ZDA
    assert fixes[0].utc_time_of_day_ns == (12 * 3600 + 34 * 60 + 56) * NS_PER_S + 200_000_000
    assert fixes[0].fix_type is None  # GGA alone cannot tell 2-D from 3-D
    # a default decoder waits for ZDA; without it, the next epoch's first sentence closes the open one
    dec = NmeaDecoder()
    assert len(dec.feed(data, 0)) == 1
    (last,) = dec.flush()
    assert last.messages == ("GGA",) and dec.flush() == []


def test_several_epochs_per_chunk_with_garbage_unknown_and_damaged_sentences() -> None:
    _, data = _stream(3)
    lines = _lines(data)
    gsv = b"$GPGSV,4,4,13,32,24,278,*41\r\n"
    bad = lines[6][:20] + b"X" + lines[6][21:]  # a flipped character: checksum fails
    cut = lines[14][:30]  # the next sentence begins before this one ended
    noise = b"\x00\xff junk \xb5b"
    stream = noise + b"".join(lines[:6]) + gsv + bad + b"".join(lines[7:14]) + cut + b"".join(lines[15:])
    dec = NmeaDecoder()
    fixes = dec.feed(stream, 7)
    assert len(fixes) == 3  # the damaged RMC and the cut GGA cost only their own values
    assert fixes[1].messages == ("VTG", "GGA", "GSA", "GST", "ZDA")
    assert fixes[2].messages == ("RMC", "VTG", "GSA", "GST", "ZDA")
    assert fixes[2].lat_deg is not None and fixes[2].alt_m is None  # position from RMC, no height
    c = dec.counters
    assert (c["unknown"], c["bad_checksum"], c["truncated"], c["garbage_bytes"]) == (1, 1, 1, len(noise))
    assert c["fixes"] == 3 and c["bytes"] == len(stream)
    assert "cut short" in dec.last_problem


def test_too_long_lines_and_unterminated_garbage_are_dropped() -> None:
    _, data = _stream(1)
    dec = NmeaDecoder()
    assert dec.feed(b"$GPTXT," + b"A" * 200 + b"*00\r\n", 0) == []
    assert dec.counters["too_long"] == 1
    assert dec.feed(b"$" + b"B" * 1000, 0) == []  # never terminated
    assert dec.counters["too_long"] == 2 and len(dec._buf) == 0
    assert len(dec.feed(data, 0)) == 1
    assert "chars" in dec.last_problem


def test_decodes_a_stream_built_by_pynmeagps() -> None:
    """Sentences from pynmeagps's own constructors (its number formatting, a real geoid separation,
    unpadded ZDA day/month, no NMEA 4.10 fields) and a u-blox M8 line with an empty course."""
    t = time(5, 44, 23, 500_000)
    pos = {"time": t, "lat": 37.7798791, "lon": -122.406792}
    gga = {"quality": 1, "numSV": 5, "HDOP": 2.58, "alt": 73.0, "altUnit": "M", "sep": -29.7, "sepUnit": "M"}
    vtg = {"cogt": 90.0, "cogtUnit": "T", "sogn": 1.73, "sognUnit": "N", "sogk": 3.204, "sogkUnit": "K"}
    gsa = {
        "opMode": "A",
        "navMode": 3,
        "svid_01": 14,
        "svid_02": 22,
        "PDOP": 6.04,
        "HDOP": 2.58,
        "VDOP": 5.46,
    }
    msgs = [
        NMEAMessage(
            "GP", "RMC", 0, **pos, status="A", spd=1.73, cog=90.0, date=date(2015, 8, 5), posMode="A"
        ),
        NMEAMessage("GP", "VTG", 0, **vtg),
        NMEAMessage("GP", "GGA", 0, **pos, **gga),
        NMEAMessage("GP", "GSA", 0, **gsa),
        NMEAMessage("GP", "GST", 0, time=t, rangeRms=1.8, stdLat=1.7, stdLong=1.3, stdAlt=2.2),
        NMEAMessage("GP", "ZDA", 0, time=t, day=5, month=8, year=2015, ltzh="00", ltzn="00"),
    ]
    stream = b"".join(m.serialize() for m in msgs)
    body = b"GPRMC,054424.00,A,3746.79173,N,12224.40646,W,0.000,,050815,,,A"
    stream += b"$%s*%02X\r\n" % (body, functools.reduce(operator.xor, body))
    dec = NmeaDecoder()
    (fix,) = dec.feed(stream, 3)
    assert fix.gps_time_ns == utc_fields_to_gps_ns(2015, 8, 5, 5, 44, 23, 500_000_000)
    assert fix.lat_deg == pytest.approx(37.7798791, abs=LATLON_TOL_DEG)
    assert fix.lon_deg == pytest.approx(-122.406792, abs=LATLON_TOL_DEG)
    assert fix.alt_m == pytest.approx(73.0 - 29.7)  # MSL + separation = ellipsoidal height
    assert fix.vel_ned_mps[0] == pytest.approx(0.0, abs=1e-9)
    assert fix.vel_ned_mps[1] == pytest.approx(3.204 * KMH_MPS)  # VTG's km/h, the finer of its two
    assert fix.pos_sigma_ned_m == (1.7, 1.3, 2.2)
    assert (fix.fix_type, fix.num_sats, fix.hdop, fix.pdop, fix.vdop) == (3, 5, 2.58, 6.04, 5.46)
    (nxt,) = dec.flush()
    assert nxt.vel_ned_mps == (0.0, 0.0, None)  # speed 0 and no course: standing still
    assert dec.counters["bad_checksum"] == 0 and dec.counters["messages"] == 7


# ---------------------------------------------------------------------------------------------
# bad input is counted, never raised


def _check_decoder_invariants(dec: NmeaDecoder, fed: int, fixes: list[DecodedFix]) -> None:
    c = dec.counters
    assert c["bytes"] == fed and c["fixes"] == len(fixes)
    assert all(v >= 0 for v in c.values())
    assert isinstance(dec.last_problem, str)
    for fix in fixes:
        assert fix.lat_deg is None or -90.0 <= fix.lat_deg <= 90.0
        assert fix.lon_deg is None or -180.0 <= fix.lon_deg <= 180.0


def _feed_in_chunks(dec: NmeaDecoder, data: bytes, seed: int) -> list[DecodedFix]:
    rng = random.Random(seed)
    out: list[DecodedFix] = []
    pos = 0
    while pos < len(data):
        n = rng.randint(1, 64)
        out += dec.feed(data[pos : pos + n], pos)
        pos += n
    return out + dec.flush()


@FUZZ
@given(st.binary(max_size=600), st.integers(0, 2**16))
def test_fuzz_random_bytes(data: bytes, seed: int) -> None:
    dec = NmeaDecoder()
    _check_decoder_invariants(dec, len(data), _feed_in_chunks(dec, data, seed))


@FUZZ
@given(
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 7)), max_size=8),
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(1, 40)), max_size=3),
    st.integers(0, 2**16),
)
def test_fuzz_bit_flips_and_truncations_of_a_valid_stream(
    flips: list[tuple[int, int]], cuts: list[tuple[int, int]], seed: int
) -> None:
    _, clean = _stream(4)
    data = bytearray(clean)
    for at, bit in flips:
        data[at % len(data)] ^= 1 << bit
    for at, n in cuts:
        del data[at % len(data) : at % len(data) + n]
    dec = NmeaDecoder()
    fixes = _feed_in_chunks(dec, bytes(data), seed)
    _check_decoder_invariants(dec, len(data), fixes)
    if not flips and not cuts:
        assert len(fixes) == 4
    damaged = sum(dec.counters[k] for k in ("bad_checksum", "truncated", "malformed", "garbage_bytes"))
    assert len(fixes) >= 4 - len(flips) - len(cuts) or damaged > 0

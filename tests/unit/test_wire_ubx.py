"""The UBX codec (hil.wire.ubx) against pyubx2, the field's parser, and against itself.

Every integer field is compared exactly with the value the test computes from the epoch; the round
trip holds within the quantisation (lat/lon 1e-7 deg, height 1 mm, velocity 1 mm/s in NAV-PVT and
1 cm/s in NAV-VELNED, NAV-COV sigmas float32, time 1 ns through NAV-PVT's UTC fields).
"""

from __future__ import annotations

import math
import random
import struct

import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from pyubx2 import UBXMessage, UBXReader
from pyubx2.ubxhelpers import calc_checksum
from pyubx2.ubxtypes_core import GET, VALCKSUM

from hil.wire import protocol
from hil.wire.base import COUNTER_NAMES, DecodedFix, ReceiverEpoch
from hil.wire.gnss_time import (
    MS_PER_WEEK,
    NS_PER_MS,
    NS_PER_S,
    NS_PER_WEEK,
    gps_ns_to_utc_fields,
    gps_week_tow,
    utc_fields_to_gps_ns,
)
from hil.wire.ubx import MAX_PAYLOAD, UbxDecoder, UbxProtocol, checksum, frame
from tests.wire_samples import T0, sample_epoch

LEGACY = UbxProtocol.LEGACY_MESSAGES
FUZZ = settings(derandomize=True, max_examples=300, deadline=None)


def _epoch(gps_ns: int = T0, **kw: object) -> ReceiverEpoch:
    return sample_epoch(gps_ns, **{**dict(vel_sigma_mps=(0.05, 0.04, 0.08), num_sats=18), **kw})


@st.composite
def epochs(draw: st.DrawFn) -> ReceiverEpoch:
    f = st.floats
    vel = st.tuples(*[f(-300.0, 300.0)] * 3)
    sigma = st.tuples(*[f(0.0, 100.0)] * 3)
    return ReceiverEpoch(
        gps_time_ns=draw(st.integers(0, 3_800_000_000 * NS_PER_S)),
        lat_deg=draw(f(-90.0, 90.0)),
        lon_deg=draw(f(-180.0, 180.0)),
        alt_m=draw(f(-1000.0, 50_000.0)),
        vel_ned_mps=draw(vel),
        pos_sigma_ned_m=draw(sigma),
        vel_sigma_mps=draw(sigma),
        fix_type=draw(st.sampled_from((0, 2, 3))),
        num_sats=draw(st.integers(0, 60)),
        hdop=draw(f(0.5, 99.99)),
        pdop=draw(f(0.5, 99.99)),
        vdop=draw(f(0.5, 99.99)),
        time_sigma_ns=draw(f(0.0, 1e6)),
    )


def _frames(data: bytes) -> list[bytes]:
    out = []
    while data:
        assert data[:2] == b"\xb5\x62"
        (length,) = struct.unpack_from("<H", data, 4)
        out.append(data[: 8 + length])
        data = data[8 + length :]
    return out


def _parse(raw: bytes) -> UBXMessage:
    return UBXReader.parse(raw, validate=VALCKSUM)  # raises on a bad checksum


def _sigma_mm(values: tuple[float, ...], n: int) -> int:
    return round(math.sqrt(sum(v * v for v in values[:n]) / n) * 1e3)


# ---------------------------------------------------------------------------------------------
# frames and the values pyubx2 reads from them


def test_frame_layout_and_checksum() -> None:
    raw = frame((0x01, 0x61), struct.pack("<I", 0x01020304))
    assert raw[:6] == b"\xb5\x62\x01\x61\x04\x00" and raw[6:10] == b"\x04\x03\x02\x01"
    assert raw[-2:] == calc_checksum(raw[2:-2]) == checksum(raw[2:-2])
    body = bytes(range(256)) * 3
    assert checksum(body) == calc_checksum(body)


def test_configuration() -> None:
    assert protocol("ubx") is UbxProtocol
    assert UbxProtocol().messages == ("NAV-PVT", "NAV-COV", "NAV-EOE")
    assert UbxProtocol(("NAV-VELNED", "NAV-POSLLH")).messages == ("NAV-POSLLH", "NAV-VELNED")
    with pytest.raises(ValueError, match="no position"):
        UbxProtocol(("NAV-COV",))
    with pytest.raises(ValueError, match="NAV-SAT"):
        UbxProtocol(("NAV-PVT", "NAV-SAT"))
    names = [_parse(r).identity for r in _frames(UbxProtocol((*LEGACY, "NAV-EOE")).encode_epoch(_epoch()))]
    assert names == ["NAV-POSLLH", "NAV-VELNED", "NAV-EOE"]


def _check_pvt(e: ReceiverEpoch, m: UBXMessage) -> None:
    y, mo, d, h, mi, s, nano = gps_ns_to_utc_fields(e.gps_time_ns)
    itow = gps_week_tow(e.gps_time_ns + NS_PER_MS // 2)[1]
    fix_ok = e.fix_type != 0
    speed = math.hypot(*e.vel_ned_mps[:2])
    head = round(e.course_deg * 1e5) % 36_000_000
    assert (m.iTOW, m.year, m.month, m.day, m.hour, m.min, m.second, m.nano) == (
        itow,
        y,
        mo,
        d,
        h,
        mi,
        s,
        nano,
    )
    assert (m.validDate, m.validTime, m.fullyResolved, m.validMag) == (1, 1, 1, 0)
    assert (m.fixType, m.gnssFixOk, m.diffSoln, m.carrSoln, m.headVehValid) == (
        e.fix_type,
        int(fix_ok),
        0,
        0,
        0,
    )
    assert (m.confirmedAvai, m.confirmedDate, m.confirmedTime, m.invalidLlh) == (1, 1, 1, 0)
    assert m.numSV == e.num_sats and m.tAcc == round(e.time_sigma_ns)
    assert round(m.lat * 1e7) == round(e.lat_deg * 1e7) and round(m.lon * 1e7) == round(e.lon_deg * 1e7)
    assert m.height == m.hMSL == round(e.alt_m * 1e3)
    assert (m.velN, m.velE, m.velD) == tuple(round(v * 1e3) for v in e.vel_ned_mps)
    assert m.gSpeed == round(speed * 1e3)
    assert round(m.headMot * 1e5) == head == round(m.headVeh * 1e5)
    assert m.hAcc == _sigma_mm(e.pos_sigma_ned_m, 2) and m.vAcc == round(e.pos_sigma_ned_m[2] * 1e3)
    assert m.sAcc == _sigma_mm(e.vel_sigma_mps, 3)
    assert 0 <= round(m.headAcc * 1e5) <= 18_000_000
    assert round(m.pDOP * 100) == round(e.pdop * 100)


def _check_cov(e: ReceiverEpoch, m: UBXMessage) -> None:
    f32 = struct.Struct("<f")

    def as_f32(x: float) -> float:
        return f32.unpack(f32.pack(x))[0]

    assert (m.version, m.posCovValid, m.velCovValid) == (0, 1, 1)
    sn, se, sd = e.pos_sigma_ned_m
    vn, ve, vd = e.vel_sigma_mps
    assert (m.posCovNN, m.posCovEE, m.posCovDD) == (as_f32(sn * sn), as_f32(se * se), as_f32(sd * sd))
    assert (m.velCovNN, m.velCovEE, m.velCovDD) == (as_f32(vn * vn), as_f32(ve * ve), as_f32(vd * vd))
    assert m.posCovNE == m.posCovND == m.posCovED == m.velCovNE == m.velCovND == m.velCovED == 0.0


def _check_legacy(e: ReceiverEpoch, pos: UBXMessage, vel: UBXMessage) -> None:
    assert round(pos.lat * 1e7) == round(e.lat_deg * 1e7) and pos.height == pos.hMSL == round(e.alt_m * 1e3)
    assert pos.hAcc == _sigma_mm(e.pos_sigma_ned_m, 2)
    assert (vel.velN, vel.velE, vel.velD) == tuple(round(v * 100) for v in e.vel_ned_mps)
    assert vel.gSpeed == round(math.hypot(*e.vel_ned_mps[:2]) * 100)
    assert vel.speed == round(math.sqrt(sum(v * v for v in e.vel_ned_mps)) * 100)
    assert round(vel.heading * 1e5) == round(e.course_deg * 1e5) % 36_000_000
    assert vel.sAcc == round(_sigma_mm(e.vel_sigma_mps, 3) / 10)
    assert pos.iTOW == vel.iTOW


@settings(derandomize=True, max_examples=200, deadline=None)
@given(epochs())
def test_every_frame_parses_in_pyubx2_to_the_same_values(e: ReceiverEpoch) -> None:
    msgs = {}
    for raw in _frames(UbxProtocol(UbxProtocol.SUPPORTED_MESSAGES).encode_epoch(e)):
        m = _parse(raw)
        msgs[m.identity] = m
    assert list(msgs) == ["NAV-POSLLH", "NAV-PVT", "NAV-VELNED", "NAV-COV", "NAV-EOE"]
    assert len({m.iTOW for m in msgs.values()}) == 1
    _check_pvt(e, msgs["NAV-PVT"])
    _check_cov(e, msgs["NAV-COV"])
    _check_legacy(e, msgs["NAV-POSLLH"], msgs["NAV-VELNED"])


@settings(derandomize=True, max_examples=100, deadline=None)
@given(st.integers(0, 3_800_000_000 * NS_PER_S), st.integers(-(2**40), 2**40))
def test_tim_tp_announces_the_next_pulse(next_pps_ns: int, q_err_ps: int) -> None:
    raw = UbxProtocol().encode_pps_announcement(next_pps_ns, q_err_ps)
    m = _parse(raw)
    week, tow_ms, sub_ns = gps_week_tow(next_pps_ns)
    assert (m.identity, m.week, m.towMS, m.timeBase, m.utc, m.timeRefGnss, m.utcStandard) == (
        "TIM-TP", week, tow_ms, 0, 1, 0, 3
    )  # fmt: skip
    assert abs(m.towSubMS - sub_ns / 1e6) <= 2**-32 + 1e-12
    assert m.qErr == max(min(q_err_ps, 2**31 - 1), -(2**31))
    dec = UbxDecoder()
    assert dec.feed(raw, 0) == [] and dec.counters["pps_announcements"] == 1
    assert dec.last_pps_gps_ns is not None and 0 <= next_pps_ns - dec.last_pps_gps_ns <= 1


def test_leap_second_in_nav_pvt() -> None:
    leap = utc_fields_to_gps_ns(2016, 12, 31, 23, 59, 60, 400_000_000)
    raw = UbxProtocol(("NAV-PVT",)).encode_epoch(_epoch(leap))
    m = _parse(raw)
    assert (m.hour, m.min, m.second, m.nano) == (23, 59, 60, 400_000_000)
    (fix,) = UbxDecoder(("NAV-PVT",)).feed(raw, 0)
    assert fix.gps_time_ns == leap


# ---------------------------------------------------------------------------------------------
# round trips through our own decoder


def _assert_round_trip(e: ReceiverEpoch, fix: DecodedFix, vel_q_mps: float) -> None:
    assert fix.lat_deg is not None and abs(fix.lat_deg - e.lat_deg) <= 0.5e-7 + 1e-12
    assert fix.lon_deg is not None and abs(fix.lon_deg - e.lon_deg) <= 0.5e-7 + 1e-12
    assert fix.alt_m is not None and abs(fix.alt_m - e.alt_m) <= 0.5e-3 + 1e-9
    for got, true in zip(fix.vel_ned_mps, e.vel_ned_mps, strict=True):
        assert got is not None and abs(got - true) <= vel_q_mps / 2 + 1e-9


@settings(derandomize=True, max_examples=200, deadline=None)
@given(epochs())
def test_encode_decode_round_trip_pvt_cov(e: ReceiverEpoch) -> None:
    p = UbxProtocol()
    dec = p.decoder()
    (fix,) = dec.feed(p.encode_epoch(e), rx_ns=9)
    assert fix.rx_ns == 9 and fix.protocol == "ubx" and fix.messages == ("NAV-PVT", "NAV-COV", "NAV-EOE")
    assert fix.gps_time_ns == e.gps_time_ns  # exact: UTC fields + nano
    _assert_round_trip(e, fix, 1e-3)
    for got, true in zip(
        fix.pos_sigma_ned_m + fix.vel_sigma_mps, e.pos_sigma_ned_m + e.vel_sigma_mps, strict=True
    ):
        assert got is not None and abs(got - true) <= 1e-7 * true + 1e-12  # float32 variance
    assert (fix.fix_type, fix.num_sats) == (e.fix_type, e.num_sats)
    assert fix.pdop is not None and abs(fix.pdop - e.pdop) <= 0.005 + 1e-9
    assert fix.hdop is None and fix.vdop is None  # NAV-PVT carries PDOP only
    assert sum(dec.counters[k] for k in COUNTER_NAMES if k not in ("bytes", "messages", "fixes")) == 0


@settings(derandomize=True, max_examples=100, deadline=None)
@given(epochs())
def test_encode_decode_round_trip_without_nav_cov(e: ReceiverEpoch) -> None:
    """NAV-PVT alone: sigmas from hAcc (north = east), vAcc and sAcc, rounded to mm."""
    p = UbxProtocol(("NAV-PVT",))
    (fix,) = p.decoder().feed(p.encode_epoch(e), rx_ns=0)
    h = math.sqrt((e.pos_sigma_ned_m[0] ** 2 + e.pos_sigma_ned_m[1] ** 2) / 2)
    assert fix.pos_sigma_ned_m == pytest.approx((h, h, e.pos_sigma_ned_m[2]), abs=0.5e-3 + 1e-9)
    s = math.sqrt(sum(v * v for v in e.vel_sigma_mps) / 3)
    assert fix.vel_sigma_mps == pytest.approx((s, s, s), abs=0.5e-3 + 1e-9)


@settings(derandomize=True, max_examples=100, deadline=None)
@given(epochs())
def test_encode_decode_round_trip_posllh_velned(e: ReceiverEpoch) -> None:
    """POSLLH + VELNED carry no date: the GPS week comes from a TIM-TP received before."""
    p = UbxProtocol(LEGACY)
    dec = p.decoder()
    tp = p.encode_pps_announcement(e.gps_time_ns // NS_PER_S * NS_PER_S + NS_PER_S)
    (fix,) = dec.feed(tp + p.encode_epoch(e), rx_ns=0)
    assert fix.messages == LEGACY
    assert fix.gps_time_ns == (e.gps_time_ns + NS_PER_MS // 2) // NS_PER_MS * NS_PER_MS  # iTOW: 1 ms
    _assert_round_trip(e, fix, 1e-2)
    assert fix.fix_type is None and fix.num_sats is None and fix.pdop is None


def test_week_from_tim_tp_across_a_week_boundary() -> None:
    p = UbxProtocol(LEGACY)
    week_start = 2300 * NS_PER_WEEK
    dec = p.decoder()
    dec.feed(p.encode_pps_announcement(week_start - NS_PER_S), 0)  # announced in the old week
    (fix,) = dec.feed(p.encode_epoch(_epoch(week_start + 200 * NS_PER_MS)), 0)  # epoch in the new week
    assert fix.gps_time_ns == week_start + 200 * NS_PER_MS
    (old,) = dec.feed(p.encode_epoch(_epoch(week_start - 2 * NS_PER_S)), 0)
    assert old.gps_time_ns == week_start - 2 * NS_PER_S
    assert UbxDecoder(LEGACY).feed(p.encode_epoch(_epoch()), 0)[0].gps_time_ns is None  # no week known yet
    assert MS_PER_WEEK == 604_800_000


def _stream(n: int = 3, messages: tuple[str, ...] | None = None) -> bytes:
    p = UbxProtocol(messages)
    return b"".join(
        p.encode_pps_announcement(T0 + (k + 1) * NS_PER_S) + p.encode_epoch(_epoch(T0 + k * NS_PER_S))
        for k in range(n)
    )


@pytest.mark.parametrize("messages", [None, ("NAV-PVT",), LEGACY])
def test_stream_split_at_every_byte_decodes_identically(messages: tuple[str, ...] | None) -> None:
    data = _stream(3, messages)
    whole = UbxDecoder(messages).feed(data, 0)
    assert len(whole) == 3
    for cut in range(len(data) + 1):
        dec = UbxDecoder(messages)
        assert dec.feed(data[:cut], 0) + dec.feed(data[cut:], 0) == whole, cut
    dec = UbxDecoder(messages)
    assert [fix for i in range(len(data)) for fix in dec.feed(data[i : i + 1], 0)] == whole
    assert dec.counters["garbage_bytes"] == 0 and dec.counters["bytes"] == len(data)


def test_rx_ns_and_epoch_closing() -> None:
    pvt_only = UbxProtocol(("NAV-PVT",))
    a, b = (pvt_only.encode_epoch(_epoch(T0 + k * NS_PER_S)) for k in range(2))
    default = UbxDecoder()  # waits for NAV-EOE, which this stream never sends
    assert default.feed(a, 1) == []
    assert default.feed(b[:-1], 2) == []  # a frame is read once its checksum is in
    (first,) = default.feed(b[-1:], 3)  # a frame of a newer iTOW closes the open epoch
    assert first.rx_ns == 3 and first.messages == ("NAV-PVT",)
    (last,) = default.flush()
    assert last.gps_time_ns == T0 + NS_PER_S and default.flush() == []
    closing = UbxDecoder(("NAV-PVT",))  # configured as PVT only: each PVT closes its epoch
    assert [f.rx_ns for f in closing.feed(a, 5) + closing.feed(b, 6)] == [5, 6]


def test_garbage_damage_and_unknown_frames_are_counted() -> None:
    data = _stream(3)
    frames = _frames(data)  # per epoch: TIM-TP, NAV-PVT, NAV-COV, NAV-EOE
    assert len(frames) == 12
    bad = bytearray(frames[5])
    bad[20] ^= 0x40  # NAV-PVT of epoch 2: checksum fails
    cut = frames[9][:40]  # NAV-PVT of epoch 3, cut short: NAV-COV follows at once
    unknown = UBXMessage("MON", "MON-HW", GET).serialize()
    short_pvt = frame((0x01, 0x07), b"\x00" * 20)  # valid checksum, too short for NAV-PVT
    too_long = b"\xb5\x62\x01\x07\xff\xff"
    noise = b"\x00\xb5\xb5 $GPGGA junk"
    stream = (
        noise + b"".join(frames[:4]) + unknown + short_pvt + too_long + frames[4] + bytes(bad)
        + b"".join(frames[6:9]) + cut + b"".join(frames[10:])
    )  # fmt: skip
    dec = UbxDecoder()
    fixes = dec.feed(stream, 0)
    assert len(fixes) == 1  # epochs 2 and 3 lost their NAV-PVT: no position, counted incomplete
    c = dec.counters
    assert (c["bad_checksum"], c["truncated"], c["unknown"], c["too_long"]) == (1, 1, 1, 1)
    assert c["malformed"] == 1 and c["incomplete"] == 2 and c["fixes"] == 1
    assert c["garbage_bytes"] >= len(noise)
    assert fixes[0].gps_time_ns == T0


def test_decodes_a_stream_built_by_pyubx2() -> None:
    """Frames from pyubx2's own constructor (a real geoid separation: hMSL != height; flags as set)."""
    itow = gps_week_tow(T0)[1]
    pvt = UBXMessage(
        "NAV", "NAV-PVT", GET, iTOW=itow, year=2024, month=5, day=6, hour=12, min=34, second=56,
        validDate=1, validTime=1, fullyResolved=1, nano=200_000_000, fixType=3, gnssFixOk=1, numSV=21,
        lon=8.5, lat=47.25, height=547_600, hMSL=499_600, hAcc=700, vAcc=1200, velN=1000, velE=-2000,
        velD=300, gSpeed=2236, headMot=296.56505, sAcc=80, headAcc=2.5, pDOP=1.25,
    )  # fmt: skip
    cov = UBXMessage(
        "NAV", "NAV-COV", GET, iTOW=itow, posCovValid=1, velCovValid=0, posCovNN=0.25, posCovEE=0.36,
        posCovDD=1.44, velCovNN=9.0,
    )  # fmt: skip
    eoe = UBXMessage("NAV", "NAV-EOE", GET, iTOW=itow)
    tp = UBXMessage("TIM", "TIM-TP", GET, towMS=itow + 800, week=gps_week_tow(T0)[0], utc=1)
    dec = UbxDecoder()
    (fix,) = dec.feed(pvt.serialize() + cov.serialize() + eoe.serialize() + tp.serialize(), 4)
    assert fix.gps_time_ns == T0 and fix.lat_deg == pytest.approx(47.25) and fix.lon_deg == pytest.approx(8.5)
    assert fix.alt_m == 547.6  # ellipsoidal height, not hMSL
    assert fix.vel_ned_mps == (1.0, -2.0, 0.3)
    assert fix.pos_sigma_ned_m == pytest.approx((0.5, 0.6, 1.2))  # from NAV-COV
    assert fix.vel_sigma_mps == (0.08, 0.08, 0.08)  # velCovValid 0: sAcc
    assert (fix.fix_type, fix.num_sats, fix.pdop) == (3, 21, 1.25)
    assert dec.last_pps_gps_ns == T0 + 800 * NS_PER_MS
    assert dec.counters["messages"] == 4 and dec.counters["bad_checksum"] == 0


# ---------------------------------------------------------------------------------------------
# bad input is counted, never raised


def _feed_in_chunks(dec: UbxDecoder, data: bytes, seed: int) -> list[DecodedFix]:
    rng = random.Random(seed)
    out: list[DecodedFix] = []
    pos = 0
    while pos < len(data):
        n = rng.randint(1, 64)
        out += dec.feed(data[pos : pos + n], pos)
        pos += n
    return out + dec.flush()


def _check_decoder_invariants(dec: UbxDecoder, fed: int, fixes: list[DecodedFix]) -> None:
    c = dec.counters
    assert c["bytes"] == fed and c["fixes"] == len(fixes)
    assert all(v >= 0 for v in c.values()) and isinstance(dec.last_problem, str)
    assert len(dec._buf) <= 8 + MAX_PAYLOAD


@FUZZ
@given(st.binary(max_size=800), st.integers(0, 2**16))
def test_fuzz_random_bytes(data: bytes, seed: int) -> None:
    dec = UbxDecoder()
    _check_decoder_invariants(dec, len(data), _feed_in_chunks(dec, data, seed))


@FUZZ
@given(
    st.sampled_from([None, ("NAV-PVT",), LEGACY]),
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(0, 7)), max_size=8),
    st.lists(st.tuples(st.integers(0, 10_000), st.integers(1, 40)), max_size=3),
    st.integers(0, 2**16),
)
def test_fuzz_bit_flips_and_truncations_of_a_valid_stream(
    messages: tuple[str, ...] | None, flips: list[tuple[int, int]], cuts: list[tuple[int, int]], seed: int
) -> None:
    data = bytearray(_stream(4, messages))
    for at, bit in flips:
        data[at % len(data)] ^= 1 << bit
    for at, n in cuts:
        del data[at % len(data) : at % len(data) + n]
    dec = UbxDecoder(messages)
    fixes = _feed_in_chunks(dec, bytes(data), seed)
    _check_decoder_invariants(dec, len(data), fixes)
    if not flips and not cuts:
        assert len(fixes) == 4

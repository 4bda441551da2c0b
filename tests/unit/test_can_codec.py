"""The DBC-built codec: bit-exact against cantools, limits, quantisation, E2E detection."""

from __future__ import annotations

import hashlib
import math
from pathlib import Path

import can
import crccheck
import numpy as np
import pytest

from hil.can import e2e
from hil.can.codec import (
    ACCEL_SATURATED,
    DEVICE_TIME_MODULO,
    GYRO_SATURATED,
    CodecError,
    DecodedSample,
    DecodedSync,
    EncodeError,
    ImuCanCodec,
    ImuFrameAssembler,
)

SEED = 20260521

# Tactical IMU of the brief: ARW 0.1 deg/sqrt(h), VRW 0.03 m/s/sqrt(h).
ARW_RAD_RTS = 0.1 * math.pi / 180 / 60
VRW_MPS_RTS = 0.03 / 60


@pytest.fixture(params=[False, True], ids=["classic", "fd"])
def codec(request: pytest.FixtureRequest) -> ImuCanCodec:
    return ImuCanCodec.from_dbc(fd=request.param)


def _feed_all(asm: ImuFrameAssembler, frames: list[can.Message]) -> list[DecodedSample | DecodedSync]:
    out: list[DecodedSample | DecodedSync] = []
    for i, f in enumerate(frames):
        f.timestamp = 1000.0 + i * 1e-4
        out.extend(asm.feed(f))
    return out


def test_crc_engine_matches_reference_crc8_sae_j1850() -> None:
    # The standard check value of CRC-8/SAE-J1850 (init 0xFF, xorout 0xFF) over "123456789".
    assert e2e.crc8_j1850_raw(b"123456789", 0xFF) ^ 0xFF == 0x4B
    data = bytes(range(40))
    assert e2e.crc8_j1850_raw(data, 0xFF) ^ 0xFF == crccheck.crc.Crc8SaeJ1850.calc(data)


def test_profile1_crc_covers_data_id_and_excludes_crc_byte() -> None:
    payload = bytearray(b"\x00\x01\x02\x03\x04\x05\x06\x07")
    # profile 1, DATAID_BOTH: register 0, over id_lo, id_hi, bytes 1..7, no final xor.
    expect = e2e.crc8_j1850_raw(bytes([0x00, 0x01]) + payload[1:], 0x00)
    assert e2e.p01_crc(0x100, payload, 8) == expect
    payload[0] = 0xAA  # the CRC byte itself is not covered
    assert e2e.p01_crc(0x100, payload, 8) == expect
    assert e2e.p01_crc(0x101, payload, 8) != expect  # a frame moved to another ID is caught


def test_counter_runs_0_to_14() -> None:
    seq = [0]
    for _ in range(16):
        seq.append(e2e.next_counter(seq[-1]))
    assert seq[:16] == [*range(15), 0]
    assert e2e.counter_delta(0, 14) == 1


def test_fast_path_is_bit_identical_to_cantools(codec: ImuCanCodec) -> None:
    rng = np.random.default_rng(SEED)
    for i in range(200):
        dth = rng.uniform(-0.4, 0.4, 3)
        dv = rng.uniform(-8.0, 8.0, 3)
        frames = codec.encode_sample(
            device_stamp_ns=int(rng.integers(0, DEVICE_TIME_MODULO)),
            dtheta_b_rad=dth,
            dvel_b_mps=dv,
            status=int(rng.integers(0, 1 << 16)) if i % 7 == 0 else 0,
        )
        for f in frames:
            ours = codec.decode(f.arbitration_id, f.data)
            ref = codec.db.decode_message(f.arbitration_id, bytes(f.data), decode_choices=False, scaling=True)
            for name, value in ours.items():
                assert value == pytest.approx(ref[name], rel=1e-12, abs=1e-15), name
            # cantools' own encoder produces the same bytes from the decoded signals
            again = codec.db.encode_message(f.arbitration_id, ref, scaling=True, strict=False)
            assert bytes(again) == bytes(f.data)


@pytest.mark.parametrize("sign", [1.0, -1.0])
def test_round_trip_at_signal_limits(codec: ImuCanCodec, sign: float) -> None:
    cases = [
        (0, [0.0] * 3, [0.0] * 3),
        (1, [sign * codec.dtheta_lsb_rad] * 3, [sign * codec.dvel_lsb_mps] * 3),
        (DEVICE_TIME_MODULO - 1, [sign * codec.dtheta_max_rad] * 3, [sign * codec.dvel_max_mps] * 3),
    ]
    got: list[DecodedSample] = []
    for t, dth, dv in cases:
        # a fresh sender/receiver pair per case: 0 -> 2^48-1 in one step would (rightly)
        # unwrap to -1, and a late receiver waits for the next status frame
        tx = ImuCanCodec.from_dbc(fd=codec.fd)
        asm = ImuFrameAssembler(tx)
        frames = tx.encode_sample(device_stamp_ns=t, dtheta_b_rad=dth, dvel_b_mps=dv, status=0x00FF)
        got += [o for o in _feed_all(asm, frames) if isinstance(o, DecodedSample)]
        assert asm.counters["saturated"] == 0
    assert [g.device_stamp_ns for g in got] == [t for t, _, _ in cases]
    for g, (_, dth, dv) in zip(got, cases, strict=True):
        assert g.dtheta_b_rad == pytest.approx(dth, abs=1e-15)
        assert g.dvel_b_mps == pytest.approx(dv, abs=1e-15)
        assert g.status == 0x00FF  # at full scale, not beyond: no saturation flag


def test_beyond_full_scale_saturates_and_flags(codec: ImuCanCodec) -> None:
    asm = ImuFrameAssembler(codec)
    frames = codec.encode_sample(
        device_stamp_ns=5, dtheta_b_rad=[1.0, -1.0, 0.0], dvel_b_mps=[0.0, 0.0, -100.0]
    )
    (s,) = _feed_all(asm, frames)
    assert isinstance(s, DecodedSample)
    assert s.dtheta_b_rad == pytest.approx([codec.dtheta_max_rad, -codec.dtheta_max_rad, 0.0])
    assert s.dvel_b_mps[2] == pytest.approx(-codec.dvel_max_mps)
    assert s.status & GYRO_SATURATED and s.status & ACCEL_SATURATED
    assert asm.counters["saturated"] == 1


def test_device_time_wraps_and_is_unwrapped(codec: ImuCanCodec) -> None:
    asm = ImuFrameAssembler(codec)
    stamps = [DEVICE_TIME_MODULO - 2_500_000, DEVICE_TIME_MODULO, DEVICE_TIME_MODULO + 2_500_000]
    frames: list[can.Message] = []
    for t in stamps:
        frames += codec.encode_sample(device_stamp_ns=t, dtheta_b_rad=[0.0] * 3, dvel_b_mps=[0.0] * 3)
    assert [s.device_stamp_ns for s in _feed_all(asm, frames)] == stamps


def test_quantisation_is_rounding_within_half_lsb_and_below_tenth_of_tactical_noise(
    codec: ImuCanCodec,
) -> None:
    rng = np.random.default_rng(SEED + 1)
    asm = ImuFrameAssembler(codec)
    err_th: list[float] = []
    err_v: list[float] = []
    for i in range(500):
        dth = rng.normal(0, 1e-3, 3)
        dv = rng.normal(0, 1e-2, 3)
        frames = codec.encode_sample(device_stamp_ns=i * 2_500_000, dtheta_b_rad=dth, dvel_b_mps=dv)
        (s,) = _feed_all(asm, frames)
        assert isinstance(s, DecodedSample)
        err_th += list(np.asarray(s.dtheta_b_rad) - dth)
        err_v += list(np.asarray(s.dvel_b_mps) - dv)
    q_th, q_v = codec.dtheta_lsb_rad, codec.dvel_lsb_mps
    assert max(abs(e) for e in err_th) <= q_th / 2 * (1 + 1e-9)
    assert max(abs(e) for e in err_v) <= q_v / 2 * (1 + 1e-9)
    # rounding, not truncation: the error is centred (truncation would bias it by q/2)
    assert abs(np.mean(err_th)) < q_th / 10 and abs(np.mean(err_v)) < q_v / 10
    # the LSB itself is below a tenth of the per-sample noise sigma = RW * sqrt(dt), up to 2 kHz
    for rate in (400.0, 1000.0, 2000.0):
        dt = 1.0 / rate
        assert q_th < 0.1 * ARW_RAD_RTS * math.sqrt(dt)
        assert q_v < 0.1 * VRW_MPS_RTS * math.sqrt(dt)


def test_frames_per_sample_and_status_frame_cadence() -> None:
    classic = ImuCanCodec.from_dbc(fd=False)
    fd = ImuCanCodec.from_dbc(fd=True)
    kw = {"dtheta_b_rad": [0.0] * 3, "dvel_b_mps": [0.0] * 3}
    assert [f.arbitration_id for f in classic.encode_sample(device_stamp_ns=0, **kw)] == [
        0x180, 0x100, 0x101, 0x102, 0x103,
    ]  # fmt: skip
    assert len(classic.encode_sample(device_stamp_ns=1, **kw)) == 4
    assert len(classic.encode_sample(device_stamp_ns=2, status=3, **kw)) == 5  # status changed
    first = fd.encode_sample(device_stamp_ns=0, **kw)
    assert [(f.arbitration_id, f.is_fd, len(f.data)) for f in first][-1] == (0x110, True, 32)
    assert len(fd.encode_sample(device_stamp_ns=1, **kw)) == 1


@pytest.mark.parametrize("bad", [float("nan"), float("inf")])
def test_non_finite_input_is_a_clear_error_and_consumes_nothing(codec: ImuCanCodec, bad: float) -> None:
    with pytest.raises(EncodeError, match="not finite"):
        codec.encode_sample(device_stamp_ns=0, dtheta_b_rad=[bad, 0, 0], dvel_b_mps=[0, 0, 0])
    with pytest.raises(EncodeError):
        codec.encode_sample(device_stamp_ns=0, dtheta_b_rad=[0, 0], dvel_b_mps=[0, 0, 0])
    with pytest.raises(EncodeError):
        codec.encode_sample(device_stamp_ns=0, dtheta_b_rad=[0] * 3, dvel_b_mps=[0] * 3, status=1 << 16)
    assert codec.samples_encoded == 0


def test_broken_dbc_is_a_codec_error(tmp_path: pytest.TempPathFactory) -> None:
    with pytest.raises(CodecError, match="not found"):
        ImuCanCodec.from_dbc("/nonexistent/imu.dbc")
    bad = tmp_path / "bad.dbc"  # type: ignore[operator]
    bad.write_text("this is not a dbc")
    with pytest.raises(CodecError):
        ImuCanCodec.from_dbc(bad)


def test_hil_dbc_env_override(monkeypatch: pytest.MonkeyPatch) -> None:
    from hil.can.codec import default_dbc_path

    monkeypatch.setenv("HIL_DBC", "/somewhere/x.dbc")
    assert str(default_dbc_path()) == "/somewhere/x.dbc"
    monkeypatch.delenv("HIL_DBC")
    assert default_dbc_path().name == "imu.dbc" and default_dbc_path().exists()


@pytest.mark.parametrize("crc_byte", [0, 3])
@pytest.mark.parametrize("length", [5, 8, 30])
def test_profile1_crc_fast_path_equals_bitwise_definition(crc_byte: int, length: int) -> None:
    data = bytearray(range(40, 72))
    for data_id in (0x100, 0x1234):
        covered = (
            bytes([data_id & 0xFF, data_id >> 8])
            + bytes(data[:crc_byte])
            + bytes(data[crc_byte + 1 : length])
        )
        assert e2e.p01_crc(data_id, data, length, crc_byte) == e2e.crc8_j1850_raw(covered, 0x00)


# -- the generated fast paths (issue 20): same frames, values, counters and errors -----------


def _scripted_stream(fd: bool) -> tuple[ImuCanCodec, list[can.Message]]:
    """600 samples with saturation on both sensors, status changes, a device-time wrap,
    unencodable samples in between, and sync frames with their re-stamped copies."""
    rng = np.random.default_rng(SEED + 2)
    codec = ImuCanCodec.from_dbc(fd=fd)
    frames: list[can.Message] = []
    t0 = DEVICE_TIME_MODULO - 300 * 2_500_000  # the device time wraps half-way
    for i in range(600):
        dth, dv = rng.normal(0, 1e-3, 3), rng.normal(0, 1e-2, 3)
        if i % 50 == 3:
            dth[i % 3] = (-1.0) ** i  # beyond full scale: saturates, flagged
        if i % 70 == 5:
            dv[(i + 1) % 3] = -100.0 * (-1.0) ** i
        t = t0 + i * 2_500_000
        kw = {"device_stamp_ns": t, "status": (i // 100) & 3}  # status changes every 100
        if i % 97 == 11:  # an unencodable sample consumes nothing
            with pytest.raises(EncodeError):
                codec.encode_sample(dtheta_b_rad=dth, dvel_b_mps=[0.0, math.nan, 0.0], **kw)
        frames += codec.encode_sample(dtheta_b_rad=dth, dvel_b_mps=list(dv), **kw)
        if i % 200 == 0:
            sync = codec.encode_sync(t)
            frames += [sync, codec.restamp_sync(sync, t + 12_345)]
    return codec, frames


@pytest.mark.parametrize(
    ("fd", "expect"), [(False, "9eaf94be8e0f5492"), (True, "fc8dc40e62e154da")], ids=["classic", "fd"]
)
def test_frames_and_decoded_samples_are_those_of_the_generic_codec(fd: bool, expect: str) -> None:
    # GIVEN the scripted stream, WHEN encoded and fed back, THEN frames, decoded items and
    # counters hash to what the generic (pre-issue-20, per-field loop) codec produced: the wire
    # protocol and the bridge's output did not move. A change here is a protocol change.
    codec, frames = _scripted_stream(fd)
    h = hashlib.sha256()
    for f in frames:
        h.update(
            repr(
                (f.arbitration_id, f.is_extended_id, f.is_fd, f.bitrate_switch, f.dlc, bytes(f.data))
            ).encode()
        )
    asm = ImuFrameAssembler(codec)
    for k, f in enumerate(frames):
        f.timestamp = 1.0 + k * 1e-4
        h.update(repr(list(asm.feed(f))).encode())  # the items, whatever sequence holds them
    h.update(repr(sorted(asm.counters.items())).encode())
    assert (codec.samples_encoded, codec.saturated_samples, asm.counters["saturated"]) == (600, 21, 21)
    assert h.hexdigest()[:16] == expect


def test_random_samples_match_cantools_and_the_bitwise_crc(codec: ImuCanCodec) -> None:
    # GIVEN random samples, a fifth of them beyond full scale on some axis
    rng = np.random.default_rng(SEED + 3)
    asm = ImuFrameAssembler(ImuCanCodec.from_dbc(fd=not codec.fd))  # the bridge's mode need not match
    sent: dict[int, int] = {}
    for i in range(400):
        dth, dv = rng.uniform(-0.3, 0.3, 3), rng.uniform(-6.0, 6.0, 3)
        if rng.random() < 0.2:
            (dth if rng.random() < 0.5 else dv)[rng.integers(3)] *= 50.0
        frames = codec.encode_sample(
            device_stamp_ns=int(rng.integers(0, 1 << 40)) + i * (1 << 41), dtheta_b_rad=dth, dvel_b_mps=dv
        )
        decoded: list[DecodedSample | DecodedSync] = []
        for f in frames:
            lay = codec.layouts[f.arbitration_id]
            # the E2E CRC from its definition, the counter one step on per identifier
            covered = bytes([f.arbitration_id & 0xFF, f.arbitration_id >> 8]) + bytes(
                f.data[1 : lay.e2e_length]
            )
            assert f.data[0] == e2e.crc8_j1850_raw(covered, 0x00)
            assert f.data[1] & 0x0F == sent.get(f.arbitration_id, 0)
            sent[f.arbitration_id] = e2e.next_counter(f.data[1] & 0x0F)
            ref = codec.db.decode_message(f.arbitration_id, bytes(f.data), decode_choices=False, scaling=True)
            assert bytes(codec.db.encode_message(f.arbitration_id, ref, scaling=True, strict=False)) == f.data
            decoded += asm.feed(f)
        # THEN the sample the assembler returns is the values cantools reads off the frames
        (s,) = decoded
        assert isinstance(s, DecodedSample)
        sig: dict[str, float] = {}
        for f in frames:
            sig.update(codec.db.decode_message(f.arbitration_id, bytes(f.data), decode_choices=False))
        assert s.dtheta_b_rad == tuple(pytest.approx(sig[f"DeltaAngle{a}"], abs=1e-15) for a in "XYZ")
        assert s.dvel_b_mps == tuple(pytest.approx(sig[f"DeltaVel{a}"], abs=1e-15) for a in "XYZ")
        gyro_sat = [abs(x) > codec.dtheta_max_rad for x in dth]
        accel_sat = [abs(x) > codec.dvel_max_mps for x in dv]
        assert [sig[f"GyroSat{a}"] for a in "XYZ"] == gyro_sat
        assert [sig[f"AccelSat{a}"] for a in "XYZ"] == accel_sat
        assert bool(s.status & GYRO_SATURATED) == any(gyro_sat)
        assert bool(s.status & ACCEL_SATURATED) == any(accel_sat)
    assert codec.saturated_samples == asm.counters["saturated"] > 40


def test_frames_are_the_messages_python_can_builds_from_keywords(codec: ImuCanCodec) -> None:
    # the encoder calls can.Message positionally (half the cost): pin every slot to the keyword form
    first = codec.encode_sample(device_stamp_ns=7, dtheta_b_rad=[1e-4] * 3, dvel_b_mps=[-1e-3] * 3, status=5)
    sync = codec.encode_sync(9)
    for f in [*first, sync, codec.restamp_sync(sync, 11)]:
        lay = codec.layouts[f.arbitration_id]
        ref = can.Message(
            arbitration_id=lay.frame_id,
            is_extended_id=False,
            is_fd=lay.is_fd,
            bitrate_switch=lay.brs,
            data=bytearray(f.data),
            dlc=lay.length,
        )
        slots = [s for s in can.Message.__slots__ if s != "__weakref__"]
        assert {s: getattr(f, s) for s in slots} == {s: getattr(ref, s) for s in slots}
        assert type(f.data) is bytearray


@pytest.mark.parametrize(
    ("dtheta", "dvel", "error", "match"),
    [
        ([0.0, "abc", 0.0], [math.nan, 0.0, 0.0], EncodeError, "dvel=nan"),  # axis X's dvel first
        ([math.inf, 0.0, 0.0], [math.nan, 0.0, 0.0], EncodeError, "dtheta=inf"),
        ([0.0, "abc", math.nan], [0.0, 0.0, 0.0], ValueError, "could not convert"),
        ([1.0, 0.0, None], [0.0, 0.0, 0.0], TypeError, "NoneType"),  # saturated, then not a number
        ([0.0, 0.0, 0.0], [0.0, 0.0, -math.inf], EncodeError, "dvel=-inf"),
        ([0.0, 0.0, 1e308], [0.0, 0.0, 0.0], OverflowError, "infinity"),  # finite, /LSB is not
    ],
)
def test_the_first_bad_value_in_axis_order_is_the_error_and_nothing_is_consumed(
    codec: ImuCanCodec, dtheta: list[object], dvel: list[object], error: type, match: str
) -> None:
    kw = {"dtheta_b_rad": [1e-5] * 3, "dvel_b_mps": [1e-3] * 3}
    twin = ImuCanCodec.from_dbc(fd=codec.fd)
    codec.encode_sample(device_stamp_ns=1, **kw)
    twin.encode_sample(device_stamp_ns=1, **kw)
    with pytest.raises(error, match=match):
        codec.encode_sample(device_stamp_ns=2, dtheta_b_rad=dtheta, dvel_b_mps=dvel)  # type: ignore[arg-type]
    assert (codec.samples_encoded, codec.saturated_samples) == (1, 0)
    after = codec.encode_sample(device_stamp_ns=3, status=1, **kw)
    assert [bytes(f.data) for f in after] == [
        bytes(f.data) for f in twin.encode_sample(device_stamp_ns=3, status=1, **kw)
    ]


@pytest.mark.parametrize("frame_length", [2, 5, 8, 9, 32])
def test_unrolled_crc_expression_equals_p01_crc(frame_length: int) -> None:
    rng = np.random.default_rng(SEED + 4)
    for data_length in range(2, frame_length + 1):
        src = e2e.p01_crc_expr(0x1A5, data_length, frame_length, "w")
        crc_of = eval(f"lambda w: {src}", dict(e2e.CRC_SCOPE))  # our own generated expression
        for _ in range(50):
            data = bytes(rng.integers(0, 256, frame_length, dtype=np.uint8))  # padding bytes too
            assert crc_of(int.from_bytes(data, "little")) == e2e.p01_crc(0x1A5, data, data_length)


@pytest.mark.parametrize("frame_length", [2, 5, 8])
def test_the_crc_of_a_block_of_words_equals_p01_crc(frame_length: int) -> None:
    """The numpy CRC the emulator's blocks use: every data length (odd ones end on a single
    byte), the bytes past the data length set, a Data ID with both bytes set."""
    rng = np.random.default_rng(SEED + 5)
    data = rng.integers(0, 256, (200, frame_length), dtype=np.uint8)
    padded = np.zeros((200, 8), dtype=np.uint8)
    padded[:, :frame_length] = data
    words = padded.view("<u8").ravel()
    for data_length in range(2, frame_length + 1):
        got = e2e.p01_crc_array(0x1A5, data_length, frame_length, words).tolist()
        assert got == [e2e.p01_crc(0x1A5, bytes(row), data_length) for row in data]
    with pytest.raises(ValueError, match="over 8 bytes"):
        e2e.p01_crc_array(0x1A5, 9, 9, words)


def test_decoded_sample_fast_constructor_is_the_dataclass() -> None:
    from hil.can.codec import _new_sample

    args = (12, (1e-6, -2e-6, 0.0), (0.1, 0.2, -9.8e-3), 0x0C, 101.5)
    fast, ref = _new_sample(*args), DecodedSample(*args)
    assert type(fast) is DecodedSample and fast == ref and hash(fast) == hash(ref)
    with pytest.raises(AttributeError):
        fast.status = 0  # type: ignore[misc]  # still frozen


def test_a_dbc_without_saturation_flags_is_refused_when_loaded_naming_them(tmp_path: Path) -> None:
    # the bridge decodes every sample's flags: a DBC without one would fail at the first frame
    from hil.can.codec import default_dbc_path

    text = default_dbc_path().read_text()
    dbc = tmp_path / "noflags.dbc"
    dbc.write_text("\n".join(line for line in text.splitlines() if "GyroSatY" not in line))
    with pytest.raises(CodecError, match="GyroSatY"):
        ImuCanCodec.from_dbc(dbc)


def test_a_block_quantised_ahead_gives_the_frames_of_sample_by_sample(codec: ImuCanCodec) -> None:
    """The IMU emulator rounds a second of samples in one numpy pass: ties at half an LSB,
    values at and beyond full scale, NaN and inf must come out as ``encode_sample``'s, the rows
    it cannot take (None) going the checked way there."""
    twin = ImuCanCodec.from_dbc(fd=codec.fd)
    rng = np.random.default_rng(SEED)
    lsb_a, lsb_v = codec.dtheta_lsb_rad, codec.dvel_lsb_mps
    dth = rng.normal(0.0, 2e-4, (64, 3))
    dv = rng.normal(0.0, 2e-2, (64, 3))
    dth[1] = np.array([0.5, 1.5, -2.5]) * lsb_a  # ties: half to even
    dv[2] = np.array([0.5, -0.5, 3.5]) * lsb_v
    dth[3, 0] = codec.dtheta_max_rad  # at full scale: in
    dth[4, 1] = codec.dtheta_max_rad * 1.5  # beyond: saturated
    dv[5, 2] = -codec.dvel_max_mps * 2
    dth[6, 2], dv[7, 0], dv[8, 1] = np.nan, np.inf, -np.inf
    raws = codec.prepare_block(np.zeros(64, dtype=np.int64), dth, dv).raws  # (the stamps unused here)
    assert [i for i, r in enumerate(raws) if r is None] == [4, 5, 6, 7, 8]
    for i in range(64):
        dev = 1_000_000_000 + i * 2_500_000
        try:
            want = [
                (f.arbitration_id, bytes(f.data))
                for f in twin.encode_sample(device_stamp_ns=dev, dtheta_b_rad=dth[i], dvel_b_mps=dv[i])
            ]
        except EncodeError:
            assert raws[i] is None and i in (6, 7, 8)
            continue
        r = raws[i]
        got = (
            codec.encode_quantised(dev, r)
            if r is not None
            else codec.encode_sample(device_stamp_ns=dev, dtheta_b_rad=dth[i], dvel_b_mps=dv[i])
        )
        assert [(f.arbitration_id, bytes(f.data)) for f in got] == want, i
    assert codec.samples_encoded == twin.samples_encoded == 61
    assert codec.saturated_samples == twin.saturated_samples == 2


def test_a_block_encoded_ahead_sends_the_frames_of_sample_by_sample(codec: ImuCanCodec) -> None:
    """The IMU emulator encodes a second of classic frames ahead (words, counters, CRCs in numpy):
    each sample sent from the block must be the frames ``encode_sample`` makes in turn --
    across the counter's wrap, the status frame's turns (every 40th, and after a status change),
    a device time past the 48-bit wrap, and the rows the block cannot take (sent the checked
    way in between without making the rest stale); after a sample refused as not encodable, whose
    counters did not advance, the rest is stale and goes the usual way. CAN FD is not prepared."""
    twin = ImuCanCodec.from_dbc(fd=codec.fd)
    rng = np.random.default_rng(SEED)
    n = 90
    dth = rng.normal(0.0, 2e-4, (n, 3))
    dv = rng.normal(0.0, 2e-2, (n, 3))
    dth[4, 1] = codec.dtheta_max_rad * 1.5  # saturated: not prepared
    dv[85, 0] = np.nan  # not encodable, refused both ways: nothing advances, the rest is stale
    dev = [(1 << 48) - 30 * 2_500_000 + i * 2_500_000 for i in range(n)]  # wraps at sample 30
    block = codec.prepare_block(np.array(dev, dtype=np.int64), dth, dv)
    prepared = 0
    for i in range(n):
        status = 3 if i == 20 else 0  # a status change: the next sample repeats the status frame
        try:
            want = [
                (f.arbitration_id, bytes(f.data))
                for f in twin.encode_sample(
                    device_stamp_ns=dev[i], dtheta_b_rad=dth[i], dvel_b_mps=dv[i], status=status
                )
            ]
        except EncodeError:
            assert i == 85 and block.raws[i] is None
            with pytest.raises(EncodeError):
                codec.encode_sample(device_stamp_ns=dev[i], dtheta_b_rad=dth[i], dvel_b_mps=dv[i])
            continue
        got = codec.encode_prepared(block, i) if status == 0 else None
        if got is None:
            got = codec.encode_sample(
                device_stamp_ns=dev[i], dtheta_b_rad=dth[i], dvel_b_mps=dv[i], status=status
            )
        else:
            prepared += 1
        assert [(f.arbitration_id, bytes(f.data)) for f in got] == want, i
    assert codec.samples_encoded == twin.samples_encoded == n - 1
    if codec.fd:
        assert block.words is None and prepared == 0
    else:
        assert prepared == 83  # 0..84 but the saturated one and the status change


def test_a_stale_block_is_refused_and_changes_nothing() -> None:
    """A block prepared before its samples' counters moved some other way is stale: refused, no
    counter or sample count advanced (the emulator then encodes the sample itself)."""
    codec = ImuCanCodec.from_dbc()
    dth, dv = np.full((3, 3), 1e-4), np.full((3, 3), 1e-2)
    stamps = np.arange(3, dtype=np.int64) * 2_500_000
    old = codec.prepare_block(stamps, dth, dv)
    new = codec.prepare_block(stamps, dth, dv)
    assert codec.encode_prepared(new, 0) is not None  # the counters move on from the same start
    counters, encoded = dict(codec._tx_counter), codec.samples_encoded
    assert codec.encode_prepared(old, 0) is None
    assert codec._tx_counter == counters and codec.samples_encoded == encoded
    assert codec.encode_prepared(old, 1) is not None  # sample 1's words: the counters now

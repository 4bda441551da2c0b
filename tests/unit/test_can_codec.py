"""The DBC-built codec: bit-exact against cantools, limits, quantisation, E2E detection."""

from __future__ import annotations

import math

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

"""The bridge's state machine rejects every kind of bad frame and keeps decoding good ones."""

from __future__ import annotations

import can
import pytest

from hil.can.codec import DecodedSample, DecodedSync, ImuCanCodec, ImuFrameAssembler


def _sample(codec: ImuCanCodec, i: int) -> list[can.Message]:
    return codec.encode_sample(
        device_stamp_ns=10_000_000 + i * 2_500_000,
        dtheta_b_rad=[i * 1e-6, -i * 1e-6, 1e-5],
        dvel_b_mps=[1e-3, 2e-3, -0.0245],
    )


def _run(asm: ImuFrameAssembler, frames: list[can.Message]) -> list[DecodedSample | DecodedSync]:
    out: list[DecodedSample | DecodedSync] = []
    for f in frames:
        out += asm.feed(f)
    return out


def _corrupt(msg: can.Message, byte: int, xor: int) -> can.Message:
    data = bytearray(msg.data)
    data[byte] ^= xor
    return can.Message(
        arbitration_id=msg.arbitration_id,
        is_extended_id=msg.is_extended_id,
        is_fd=msg.is_fd,
        bitrate_switch=msg.bitrate_switch,
        data=data,
    )


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_good_stream_decodes_every_sample_and_sync(fd: bool) -> None:
    codec = ImuCanCodec.from_dbc(fd=fd)
    asm = ImuFrameAssembler(codec)
    frames: list[can.Message] = []
    for i in range(100):
        frames += _sample(codec, i)
        if i % 40 == 0:
            frames.append(codec.encode_sync(10_000_000 + i * 2_500_000))
    out = _run(asm, frames)
    samples = [o for o in out if isinstance(o, DecodedSample)]
    syncs = [o for o in out if isinstance(o, DecodedSync)]
    assert [s.device_stamp_ns for s in samples] == [10_000_000 + i * 2_500_000 for i in range(100)]
    assert [s.device_stamp_ns for s in syncs] == [10_000_000, 110_000_000, 210_000_000]
    bad = {k: v for k, v in asm.counters.items() if k not in ("frames", "samples", "syncs", "status")}
    assert not any(bad.values()), bad


def test_each_bad_frame_kind_is_counted_and_good_samples_still_decode() -> None:
    codec = ImuCanCodec.from_dbc(fd=False)
    asm = ImuFrameAssembler(codec)
    frames: list[can.Message] = []
    frames += _sample(codec, 0)  # status + 4 parts: good
    s1 = _sample(codec, 1)
    frames += [_corrupt(s1[0], 3, 0x01), *s1[1:]]  # bad CRC in AxisX -> sample 1 incomplete
    frames += _sample(codec, 2)
    frames.append(can.Message(arbitration_id=0x555, is_extended_id=False, data=b"\x00" * 8))  # unknown id
    frames.append(
        can.Message(arbitration_id=0x100, is_extended_id=True, data=b"\x00" * 8)
    )  # extended = unknown
    frames.append(can.Message(arbitration_id=0x100, is_extended_id=False, data=b"\x00" * 5))  # bad DLC
    # counter 15 (invalid) with a valid CRC
    inval = bytearray(_sample(codec, 3)[0].data)
    inval[1] = (inval[1] & 0xF0) | 0x0F
    from hil.can.e2e import p01_crc

    inval[0] = p01_crc(0x100, inval, 8)
    frames.append(can.Message(arbitration_id=0x100, is_extended_id=False, data=inval))
    frames.append(can.Message(arbitration_id=0x100, is_extended_id=False, is_error_frame=True))
    frames.append(can.Message(arbitration_id=0x100, is_extended_id=False, is_remote_frame=True, dlc=8))
    s4 = _sample(codec, 4)  # sample 3's frames were mostly consumed above; 4 arrives whole
    frames += s4
    frames += s4[-1:]  # a repeated IMU_Time frame
    _sample(codec, 5)  # encoded but never sent: every ID jumps by 2
    frames += _sample(codec, 6)
    out = _run(asm, frames)
    stamps = [o.device_stamp_ns for o in out if isinstance(o, DecodedSample)]
    assert stamps == [10_000_000, 15_000_000, 20_000_000, 25_000_000]  # 0, 2, 4, 6
    c = asm.counters
    assert c["bad_crc"] == 1
    assert c["unknown_id"] == 2
    assert c["bad_dlc"] == 1
    assert c["bad_counter"] == 1
    assert c["error_frame"] == 1 and c["remote_frame"] == 1
    assert c["repeated"] == 1
    assert c["incomplete_sample"] >= 1
    assert c["counter_jump"] >= 4 and c["lost_frames"] >= 4
    assert asm.last_problem[0] == "counter_jump" and "lost" in asm.last_problem[1]
    assert asm.problems == sum(
        c[k] for k in ("bad_crc", "unknown_id", "bad_dlc", "bad_counter", "error_frame", "remote_frame",
                       "repeated", "incomplete_sample", "counter_jump")
    )  # fmt: skip


def test_a_lost_part_drops_only_that_sample() -> None:
    codec = ImuCanCodec.from_dbc(fd=False)
    asm = ImuFrameAssembler(codec)
    s0, s1, s2 = (_sample(codec, i) for i in range(3))
    out = _run(asm, [*s0, *[f for f in s1 if f.arbitration_id != 0x101], *s2])
    assert [o.device_stamp_ns for o in out if isinstance(o, DecodedSample)] == [10_000_000, 15_000_000]
    assert asm.counters["incomplete_sample"] == 1
    assert asm.counters["counter_jump"] == 1  # AxisY jumped from 0 to 2


def test_fd_frame_with_bad_crc_and_padding_outside_e2e() -> None:
    codec = ImuCanCodec.from_dbc(fd=True)
    asm = ImuFrameAssembler(codec)
    frames = _sample(codec, 0)
    fd_frame = frames[-1]
    assert _run(asm, [_corrupt(fd_frame, 20, 0x80)]) == []
    assert asm.counters["bad_crc"] == 1
    # the bridge also accepts classic samples on an FD codec (sender config need not match)
    classic = ImuCanCodec.from_dbc(fd=False)
    out = _run(ImuFrameAssembler(codec), _sample(classic, 1))
    assert len(out) == 1 and isinstance(out[0], DecodedSample)


def test_rx_timestamp_is_the_completing_frame() -> None:
    codec = ImuCanCodec.from_dbc(fd=False)
    asm = ImuFrameAssembler(codec)
    frames = _sample(codec, 0)
    for i, f in enumerate(frames):
        f.timestamp = 100.0 + i
    (s,) = _run(asm, frames)
    assert isinstance(s, DecodedSample) and s.rx_timestamp_s == 100.0 + len(frames) - 1

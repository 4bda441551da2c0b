"""The contract: message types, their JSON Schemas in schemas/, and the codec's validation."""

from __future__ import annotations

import json
import math

import jsonschema
import msgspec
import pytest

from hil.messages import (
    CONTRACT_TYPES,
    MAX_BATCH,
    CanFrame,
    GnssFix,
    ImuSample,
    NavSolution,
    decode,
    encode,
    encode_batch,
    json_schema,
    split_batch,
)
from hil.schemas_io import SCHEMAS_DIR, check_schemas


def test_checked_in_schemas_match_the_message_types() -> None:
    assert check_schemas() == []


def test_every_contract_type_has_a_schema_file_named_hil_type() -> None:
    names = {p.name for p in SCHEMAS_DIR.glob("hil.*.json")}
    assert names == {f"hil.{t.__name__}.json" for t in CONTRACT_TYPES}
    for t in CONTRACT_TYPES:
        assert (
            json.loads((SCHEMAS_DIR / f"hil.{t.__name__}.json").read_text())["title"] == f"hil.{t.__name__}"
        )


def _imu(**kw: object) -> ImuSample:
    base = dict(
        seq=3,
        stamp_ns=2_500_000,
        device_stamp_ns=2_500_000,
        rx_stamp_ns=2_600_000,
        dt_ns=2_500_000,
        dtheta_b_rad=[1e-5, -2e-5, 3e-6],
        dvel_b_mps=[0.01, 0.0, -0.0245],
    )
    base.update(kw)
    return ImuSample(**base)  # type: ignore[arg-type]


def test_round_trip_is_exact_and_valid_against_the_schema() -> None:
    msg = _imu()
    payload = encode(msg)
    assert decode(ImuSample, payload) == msg
    jsonschema.validate(json.loads(payload), json_schema(ImuSample))


@pytest.mark.parametrize(
    "payload, reason",
    [
        (b"\x00\xff garbage", "not JSON"),
        (b'{"seq": 1}', "missing fields"),
        (
            b'{"seq": -1, "stamp_ns": 0, "device_stamp_ns": 0, "rx_stamp_ns": 0, "dt_ns": 1, "dtheta_b_rad": [0,0,0], "dvel_b_mps": [0,0,0]}',
            "negative seq",
        ),
        (
            b'{"seq": 1, "stamp_ns": 0, "device_stamp_ns": 0, "rx_stamp_ns": 0, "dt_ns": 1, "dtheta_b_rad": [0,0], "dvel_b_mps": [0,0,0]}',
            "short vector",
        ),
        (
            b'{"seq": 1, "stamp_ns": 0, "device_stamp_ns": 0, "rx_stamp_ns": 0, "dt_ns": 1, "dtheta_b_rad": [0,null,0], "dvel_b_mps": [0,0,0]}',
            "NaN (null)",
        ),
        (
            b'{"seq": 1, "stamp_ns": 0, "device_stamp_ns": 0, "rx_stamp_ns": 0, "dt_ns": 0, "dtheta_b_rad": [0,0,0], "dvel_b_mps": [0,0,0]}',
            "zero interval",
        ),
        (
            b'{"seq": 1, "stamp_ns": 1e30, "device_stamp_ns": 0, "rx_stamp_ns": 0, "dt_ns": 1, "dtheta_b_rad": [0,0,0], "dvel_b_mps": [0,0,0]}',
            "float stamp",
        ),
    ],
)
def test_bad_payloads_are_rejected_with_a_validation_error(payload: bytes, reason: str) -> None:
    with pytest.raises((msgspec.ValidationError, msgspec.DecodeError)):
        decode(ImuSample, payload)


def test_an_older_reader_accepts_a_newer_message_with_an_appended_field() -> None:
    # GIVEN an ImuSample as a newer release might send it: one field this release does not know
    newer = json.loads(encode(_imu()))
    newer["temperature_c"] = 41.5
    # WHEN the current decoder reads it THEN the known fields arrive and the new one is ignored
    assert decode(ImuSample, json.dumps(newer).encode()) == _imu()
    # ... while what a known field must be is still checked
    newer["dt_ns"] = 0
    with pytest.raises(msgspec.ValidationError):
        decode(ImuSample, json.dumps(newer).encode())


def test_estimator_health_carries_real_numbers_and_pairs_names_with_values() -> None:
    from hil.messages import EstimatorHealth

    h = EstimatorHealth(seq=0, stamp_ns=5, estimator="kfvel", names=["gain_vel_n"], values=[0.25])
    back = decode(EstimatorHealth, encode(h))
    assert back.as_dict() == {"gain_vel_n": 0.25}
    with pytest.raises(msgspec.ValidationError):
        decode(EstimatorHealth, b'{"seq":0,"stamp_ns":0,"estimator":"x","names":["a","b"],"values":[1.0]}')


def test_nan_cannot_travel_it_is_encoded_as_null_and_rejected() -> None:
    bad = _imu(dvel_b_mps=[math.nan, 0.0, 0.0])
    with pytest.raises(msgspec.ValidationError):
        decode(ImuSample, encode(bad))


def test_schema_and_codec_agree_on_optional_fields() -> None:
    sol = NavSolution(
        seq=0,
        stamp_ns=0,
        estimator="ekf15",
        pos_ned_m=[0, 0, 0],
        vel_ned_mps=[0, 0, 0],
        q_nb=[1, 0, 0, 0],
        lat_deg=50.0,
        lon_deg=30.0,
        alt_m=200.0,
    )
    jsonschema.validate(json.loads(encode(sol)), json_schema(NavSolution))
    fix = GnssFix(
        seq=0,
        stamp_ns=0,
        device_stamp_ns=0,
        rx_stamp_ns=0,
        lat_deg=0,
        lon_deg=0,
        alt_m=0,
        pos_ned_m=[0, 0, 0],
        vel_ned_mps=[0, 0, 0],
        pos_sigma_m=[20, 20, 30],
        vel_sigma_mps=[0.2] * 3,
        fix_type=3,
        num_sats=9,
        hdop=0.9,
    )
    jsonschema.validate(json.loads(encode(fix)), json_schema(GnssFix))


def _frame(seq: int) -> CanFrame:
    return CanFrame(
        seq=seq, stamp_ns=seq * 135_000, channel="vcan0", arbitration_id=0x181 + seq % 4, data_hex="0a" * 8
    )


def test_a_batch_splits_into_the_bytes_each_message_was_sent_as() -> None:
    frames = [_frame(i) for i in range(4)]
    batch = encode_batch(frames)
    assert json.loads(batch) == [json.loads(encode(f)) for f in frames]  # a JSON array any client reads
    parts = split_batch(batch)
    assert parts == [encode(f) for f in frames]
    assert [decode(CanFrame, p) for p in parts] == frames
    single = encode(frames[0])
    assert split_batch(single) == [single]  # one message passes as it is


@pytest.mark.parametrize(
    "payload, why",
    [
        (b"[", "not a batch"),
        (b"[]", "a batch of 0"),
        (b"[" + b",".join([b"{}"] * (MAX_BATCH + 1)) + b"]", f"a batch of {MAX_BATCH + 1}"),
        (b'[{"seq": 1}', "not a batch"),
        (b"[" * 100_000, "nested too deeply"),
    ],
)
def test_a_malformed_or_oversized_batch_is_refused_by_name(payload: bytes, why: str) -> None:
    with pytest.raises(ValueError, match=why):
        split_batch(payload)


def test_a_payload_nested_too_deeply_is_a_decode_error_not_a_recursion_error() -> None:
    """msgspec raises RecursionError on ~10^5 levels of an unknown field; every subscriber
    catches DecodeError as 'invalid' (the recorder and services counted it as a bare error)."""
    import msgspec

    from hil.messages import ImuSample, decode

    with pytest.raises(msgspec.DecodeError, match="nested too deeply"):
        decode(ImuSample, b'{"a":' * 100_000)


def test_a_payload_recorded_before_a_field_was_appended_encodes_today_as_a_new_one() -> None:
    """What the reruns compare a recorded output by where its bytes differ (``encoded_today``):
    a ``GnssFix`` recorded before ``line_ns`` lacks it, today's carries its default."""
    from hil.messages import GnssFix, encode, encoded_today

    fix = GnssFix(seq=3, stamp_ns=5, device_stamp_ns=4, rx_stamp_ns=5, lat_deg=50.0, lon_deg=30.0,
                  alt_m=300.0, pos_ned_m=[1.0, 2.0, 3.0], vel_ned_mps=[0.0] * 3, pos_sigma_m=[1.0] * 3,
                  vel_sigma_mps=[0.1] * 3, fix_type=3, num_sats=9, hdop=0.9)  # fmt: skip
    today = encode(fix)
    old = msgspec.json.encode({k: v for k, v in msgspec.json.decode(today).items() if k != "line_ns"})
    assert old != today and b"line_ns" not in old
    assert encoded_today(GnssFix, old) == today
    assert encoded_today(GnssFix, b"{not json") == b"{not json"  # said as it is: the difference shows

"""Fuzz every decoder of untrusted input with hypothesis, for a bounded time: each either
returns a valid value or raises its documented, specific error -- never anything else.

Subscribers are fuzzed over a real Zenoh session in tests/integration/test_bad_input.py.
"""

from __future__ import annotations

import contextlib
import math

import can
import msgspec
import numpy as np
import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from hil.can.codec import ImuCanCodec, ImuFrameAssembler
from hil.can.frame_bus import unpack_frame
from hil.estimators.base import InitialState
from hil.fusion.core import FusionConfig, FusionCore
from hil.messages import CONTRACT_TYPES, GnssFix, ImuSample, decode, encode
from hil.nav.scenario import ScenarioError, parse_scenario
from hil.nav.sensor_specs import SpecError

FUZZ = settings(max_examples=150, deadline=None, suppress_health_check=[HealthCheck.too_slow])
FEW = settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])

json_values = st.recursive(
    st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20),
    lambda children: (
        st.lists(children, max_size=5) | st.dictionaries(st.text(max_size=10), children, max_size=6)
    ),
    max_leaves=6,
)


@pytest.mark.parametrize("cls", CONTRACT_TYPES, ids=lambda c: c.__name__)
@FUZZ
@given(payload=st.binary(max_size=400))
def test_random_bytes_never_escape_the_codec(cls: type, payload: bytes) -> None:
    with contextlib.suppress(msgspec.ValidationError, msgspec.DecodeError):
        decode(cls, payload)


@pytest.mark.parametrize("cls", CONTRACT_TYPES, ids=lambda c: c.__name__)
@FEW
@given(
    doc=st.dictionaries(
        st.sampled_from(
            [
                "seq",
                "stamp_ns",
                "sensor",
                "dt_ns",
                "pos_ned_m",
                "x",
                "q_nb",
                "dtheta_b_rad",
                "estimator",
                "state",
                "counters",
            ]
        ),
        json_values,
    )
)
def test_wrong_schema_json_is_rejected_or_valid(cls: type, doc: dict) -> None:
    payload = msgspec.json.encode(doc)
    try:
        msg = decode(cls, payload)
    except msgspec.ValidationError:
        return
    # whatever passed validation re-encodes to something that decodes to itself
    assert decode(cls, encode(msg)) == msg


_CODEC = ImuCanCodec.from_dbc()
_IDS = [*sorted(_CODEC.frame_ids), 0, 2047, 291]


@FUZZ
@given(
    frames=st.lists(
        st.tuples(st.sampled_from(_IDS), st.binary(max_size=64), st.booleans(), st.booleans()), max_size=40
    )
)
def test_frame_assembler_survives_any_frame_sequence(frames: list[tuple[int, bytes, bool, bool]]) -> None:
    asm = ImuFrameAssembler(_CODEC)
    for fid, data, err, remote in frames:
        is_fd = len(data) > 8
        msg = can.Message(
            arbitration_id=fid,
            data=data,
            is_fd=is_fd,
            is_error_frame=err,
            is_remote_frame=remote and not is_fd,
            timestamp=1.0,
        )
        for item in asm.feed(msg):
            if hasattr(item, "dtheta_b_rad"):
                assert all(math.isfinite(v) for v in (*item.dtheta_b_rad, *item.dvel_b_mps))
    assert asm.counters["frames"] == len(frames)


@FUZZ
@given(payload=st.binary(max_size=100))
def test_can_transport_payloads_decode_or_raise_value_error(payload: bytes) -> None:
    try:
        _sender, msg = unpack_frame(payload)
    except ValueError:
        return
    assert len(msg.data) <= 64


@settings(max_examples=200, deadline=None)
@given(text=st.text(max_size=300))
def test_scenario_text_parses_or_raises_scenario_error(text: str) -> None:
    with contextlib.suppress(ScenarioError, SpecError):
        parse_scenario(text)


_INIT = InitialState(
    stamp_ns=0,
    lat_rad=0.88,
    lon_rad=0.53,
    alt_m=300.0,
    origin_lat_rad=0.88,
    origin_lon_rad=0.53,
    origin_alt_m=300.0,
    vel_ned_mps=np.array([50.0, 0, 0]),
    q_nb=np.array([1.0, 0, 0, 0]),
)

finite = st.floats(min_value=-1e12, max_value=1e12, allow_nan=False, allow_infinity=False)
stamps = st.integers(min_value=-(2**40), max_value=2**50)


@st.composite
def fusion_inputs(draw: st.DrawFn) -> ImuSample | GnssFix:
    seq = draw(st.integers(min_value=0, max_value=50))
    t = draw(stamps)
    if draw(st.booleans()):
        return ImuSample(
            seq=seq,
            stamp_ns=t,
            device_stamp_ns=t,
            rx_stamp_ns=t,
            dt_ns=draw(st.integers(min_value=1, max_value=10**9)),
            dtheta_b_rad=draw(st.lists(finite, min_size=3, max_size=3)),
            dvel_b_mps=draw(st.lists(finite, min_size=3, max_size=3)),
        )
    return GnssFix(
        seq=seq,
        stamp_ns=t,
        device_stamp_ns=t,
        rx_stamp_ns=t,
        lat_deg=0,
        lon_deg=0,
        alt_m=0,
        pos_ned_m=draw(st.lists(finite, min_size=3, max_size=3)),
        vel_ned_mps=draw(st.lists(finite, min_size=3, max_size=3)),
        pos_sigma_m=draw(st.lists(st.floats(0, 1e6), min_size=3, max_size=3)),
        vel_sigma_mps=draw(st.lists(st.floats(0, 1e6), min_size=3, max_size=3)),
        fix_type=draw(st.integers(0, 5)),
        num_sats=8,
        hdop=1.0,
    )


@settings(max_examples=40, deadline=None, suppress_health_check=[HealthCheck.too_slow])
@given(inputs=st.lists(fusion_inputs(), max_size=30))
def test_fusion_never_raises_and_never_publishes_non_finite(inputs: list[ImuSample | GnssFix]) -> None:
    """Huge values, duplicated and out-of-order seq, stamps far in the future or past: every
    estimator either copes or is taken out and counted; no NaN/inf reaches a solution."""
    core = FusionCore(
        _INIT,
        FusionConfig(
            estimators=("comp1", "compvs", "cf3", "kfvel", "ekf15"), lag_ns=10_000_000, output_every=1
        ),
    )
    out = []
    for m in inputs:
        out += core.push(m)
    out += core.flush()
    for sol in out:
        vals = [*sol.pos_ned_m, *sol.vel_ned_mps, *sol.q_nb, sol.lat_deg, sol.lon_deg, sol.alt_m]
        assert all(math.isfinite(v) for v in vals)
        decode(type(sol), encode(sol))  # and it is a valid contract message

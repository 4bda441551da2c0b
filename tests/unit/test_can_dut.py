"""A device-under-test navigation box decoded with its own DBC and a signal mapping."""

from __future__ import annotations

import math
from pathlib import Path

import can
import cantools
import pytest

from hil.can.dut import DutMapping, DutMappingError, DutNavDecoder

# A made-up box in the style of automotive INS products: Motorola (big-endian) signals,
# position in 1e-7 deg, velocity in cm/s with an "up" axis, attitude in 0.01 deg.
NAVBOX_DBC = """VERSION ""
NS_ :
BS_:
BU_: NAVBOX

BO_ 1280 NAV_Position: 8 NAVBOX
 SG_ Latitude : 7|32@0- (1E-007,0) [-90|90] "deg" Vector__XXX
 SG_ Longitude : 39|32@0- (1E-007,0) [-180|180] "deg" Vector__XXX

BO_ 1281 NAV_Height: 8 NAVBOX
 SG_ Altitude : 7|32@0- (0.001,0) [-1000|10000] "m" Vector__XXX
 SG_ PosSigmaH : 39|16@0+ (0.01,0) [0|655] "m" Vector__XXX
 SG_ PosSigmaV : 55|16@0+ (0.01,0) [0|655] "m" Vector__XXX

BO_ 1282 NAV_Velocity: 6 NAVBOX
 SG_ VelNorth : 7|16@0- (0.01,0) [-327|327] "m/s" Vector__XXX
 SG_ VelEast : 23|16@0- (0.01,0) [-327|327] "m/s" Vector__XXX
 SG_ VelUp : 39|16@0- (0.01,0) [-327|327] "m/s" Vector__XXX

BO_ 1283 NAV_Attitude: 6 NAVBOX
 SG_ Roll : 7|16@0- (0.01,0) [-180|180] "deg" Vector__XXX
 SG_ Pitch : 23|16@0- (0.01,0) [-90|90] "deg" Vector__XXX
 SG_ Heading : 39|16@0+ (0.01,0) [0|360] "deg" Vector__XXX
"""

MAPPING = {
    "estimator": "dut_navbox",
    "complete_on": "NAV_Attitude",
    "max_age_ms": 50,
    "fields": {
        "lat_deg": "NAV_Position.Latitude",
        "lon_deg": "NAV_Position.Longitude",
        "alt_m": "NAV_Height.Altitude",
        "vel_n_mps": "NAV_Velocity.VelNorth",
        "vel_e_mps": "NAV_Velocity.VelEast",
        "vel_d_mps": "NAV_Velocity.VelUp",
        "roll_deg": "NAV_Attitude.Roll",
        "pitch_deg": "NAV_Attitude.Pitch",
        "yaw_deg": "NAV_Attitude.Heading",
        "pos_sigma_n_m": "NAV_Height.PosSigmaH",
        "pos_sigma_e_m": "NAV_Height.PosSigmaH",
        "pos_sigma_d_m": "NAV_Height.PosSigmaV",
    },
    "scale": {"vel_d_mps": -1.0},
}
ORIGIN = (48.0, 11.0, 500.0)


@pytest.fixture
def db() -> cantools.database.Database:
    return cantools.database.load_string(NAVBOX_DBC, database_format="dbc")


def _frames(db: cantools.database.Database, lat: float, heading: float) -> list[can.Message]:
    values = {
        "NAV_Position": {"Latitude": lat, "Longitude": 11.0},
        "NAV_Height": {"Altitude": 510.0, "PosSigmaH": 1.5, "PosSigmaV": 3.0},
        "NAV_Velocity": {"VelNorth": 10.0, "VelEast": -2.0, "VelUp": 0.5},
        "NAV_Attitude": {"Roll": 0.0, "Pitch": 0.0, "Heading": heading},
    }
    return [
        can.Message(
            arbitration_id=db.get_message_by_name(n).frame_id,
            is_extended_id=False,
            data=db.encode_message(n, v),
        )
        for n, v in values.items()
    ]


def test_dut_frames_decode_into_a_named_nav_solution(db: cantools.database.Database) -> None:
    dec = DutNavDecoder(db, DutMapping.from_dict(MAPPING), *ORIGIN)
    out = [dec.feed(f, 1_000_000 * i) for i, f in enumerate(_frames(db, 48.001, 90.0))]
    assert out[:3] == [None, None, None]
    sol = out[3]
    assert sol is not None and sol.estimator == "dut_navbox" and sol.seq == 0 and sol.stamp_ns == 3_000_000
    assert sol.lat_deg == pytest.approx(48.001, abs=1e-7)
    assert sol.pos_ned_m[0] == pytest.approx(111.2, abs=0.5)  # 0.001 deg of latitude north
    assert sol.pos_ned_m[2] == pytest.approx(-10.0, abs=0.01)  # 10 m above the origin
    assert sol.vel_ned_mps == pytest.approx([10.0, -2.0, -0.5])  # the box's "up" turned to "down"
    # heading 90 deg: q_nb is a 90 deg yaw
    assert sol.q_nb == pytest.approx([math.cos(math.pi / 4), 0.0, 0.0, math.sin(math.pi / 4)], abs=1e-4)
    assert sol.pos_sigma_m == pytest.approx([1.5, 1.5, 3.0])
    assert sol.vel_sigma_mps == []  # absent


def test_dut_bad_input_is_counted(db: cantools.database.Database) -> None:
    dec = DutNavDecoder(db, DutMapping.from_dict(MAPPING), *ORIGIN)
    frames = _frames(db, 48.0, 0.0)
    assert dec.feed(frames[3], 0) is None  # attitude before anything else
    assert dec.counters["incomplete"] == 1
    assert dec.feed(can.Message(arbitration_id=0x7FF, data=b"\x00"), 0) is None
    assert dec.feed(can.Message(arbitration_id=1280, is_extended_id=False, data=b"\x00\x01"), 0) is None
    for f in frames[:3]:
        dec.feed(f, 0)
    assert dec.feed(frames[3], 200_000_000) is None  # the others are 200 ms old
    assert (
        dec.counters["stale"] == 1 and dec.counters["unknown_id"] == 1 and dec.counters["decode_error"] == 1
    )
    assert "older than" in dec.last_error


def test_mapping_errors_name_the_problem(db: cantools.database.Database, tmp_path: Path) -> None:
    bad = dict(MAPPING, fields={**MAPPING["fields"], "lat_deg": "NAV_Position.Lat"})  # type: ignore[dict-item]
    with pytest.raises(DutMappingError, match="'Lat' is not in message 'NAV_Position'"):
        DutNavDecoder(db, DutMapping.from_dict(bad), *ORIGIN)
    fields = {k: v for k, v in MAPPING["fields"].items() if k != "yaw_deg"}  # type: ignore[attr-defined]
    with pytest.raises(DutMappingError, match="attitude"):
        DutMapping.from_dict(dict(MAPPING, fields=fields))
    with pytest.raises(DutMappingError, match="not a NavSolution input"):
        DutMapping.from_dict(dict(MAPPING, fields={**MAPPING["fields"], "speed": "NAV_Velocity.VelNorth"}))  # type: ignore[dict-item]
    toml = tmp_path / "navbox.toml"
    toml.write_text(
        'estimator = "dut_navbox"\n[fields]\n'
        + "".join(f'{k} = "{v}"\n' for k, v in MAPPING["fields"].items())  # type: ignore[attr-defined]
    )
    dbc = tmp_path / "navbox.dbc"
    dbc.write_text(NAVBOX_DBC)
    dec = DutNavDecoder.from_files(dbc, toml, ORIGIN)
    assert dec.mapping.estimator == "dut_navbox"

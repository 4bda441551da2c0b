"""Scenario files: the built-ins load, errors name the key, overrides keep source_text honest."""

from __future__ import annotations

import hashlib

import pytest

from hil.nav.scenario import (
    DEFAULT_SCENARIO,
    ScenarioError,
    builtin_scenarios,
    load_scenario,
    parse_scenario,
    scenario_overrides,
)
from hil.nav.sensor_specs import DEG, UG_MPS2

MINIMAL = """
name = "mini"
seed = 9
[initial]
speed_mps = 10.0
[[segment]]
kind = "hold"
duration_s = 20.0
"""


def test_builtins_load_and_include_the_required_set() -> None:
    names = builtin_scenarios()
    for required in ("static", "straight_level", "long_flight", "uav_survey", "car_drive"):
        assert required in names
    for n in names:
        s = load_scenario(n)
        assert s.name == n
        assert s.sha256 == hashlib.sha256(s.source_text.encode()).hexdigest()
    s = load_scenario(DEFAULT_SCENARIO)
    assert (s.duration_s, s.initial_vel_body_mps[0], s.imu.rate_hz) == (3600.0, 50.0, 400)
    assert 4500 <= load_scenario("long_flight").duration_s <= 5500
    assert any(e.kind == "gnss_outage" for e in load_scenario("car_drive").events)


def test_user_units_are_converted() -> None:
    s = parse_scenario(
        MINIMAL + '[imu]\npreset = "ideal"\ngyro_bias_instability_dph = 3.6\naccel_bias_ug = [100, 0, 0]\n'
    )
    assert s.imu.params.gyro_bias_instability_radps[0] == pytest.approx(3.6 * DEG / 3600)
    assert s.imu.params.accel_bias_mps2 == pytest.approx((100 * UG_MPS2, 0.0, 0.0))
    assert s.duration_s == 20.0  # from the profile when duration_s is absent


@pytest.mark.parametrize(
    ("extra", "fragment"),
    [
        ("speedo = 3\n", "speedo"),
        ('[imu]\npreset = "nope"\n', "nope"),
        ("[imu]\ngyro_arw = 0.1\n", "gyro_arw"),
        ('[[event]]\nkind = "gnss_outage"\nt_start_s = 5.0\n', "t_end_s"),
        ('[[segment]]\nkind = "spin"\nduration_s = 1\n', "spin"),
        ("[gnss]\nrate_hz = 50.0\n", "rate_hz"),
        # past a day, a step reads as a 48-bit device-time wrap (1e9 s: the fusion ~80 600 s ahead)
        (
            '[[event]]\nkind = "clock_step"\nt_start_s = 1.0\nsensor = "imu"\nstep_s = 1e9\n',
            r"event\[0\]\.step_s",
        ),
    ],
)
def test_bad_files_name_the_key(extra: str, fragment: str) -> None:
    with pytest.raises(ScenarioError, match=fragment):
        parse_scenario(MINIMAL + extra)


def test_reserved_clock_table_is_kept_raw() -> None:
    s = parse_scenario(MINIMAL + "[clock]\nimu_drift_ppm = 20.0\n")
    assert s.extra_tables["clock"] == {"imu_drift_ppm": 20.0}


def test_pulse_event_ends_after_tau() -> None:
    s = load_scenario("uav_survey")
    (pulse,) = [e for e in s.events if e.kind == "gnss_pulse"]
    assert pulse.t_end_s == pulse.t_start_s + 1.0
    assert pulse.params["offset_ned_m"] == pytest.approx((50.0, 0.0, 0.0))


def test_overrides_rewrite_source_text_that_reloads_to_the_same_scenario() -> None:
    s = load_scenario("car_drive")
    o = scenario_overrides(s, duration_s=60.0, imu_rate_hz=1000, gnss_rate_hz=5.0, imu_gyro_arw_dprh=0.5)
    assert (o.duration_s, o.imu.rate_hz, o.gnss.rate_hz) == (60.0, 1000, 5.0)
    assert o.sha256 != s.sha256
    again = parse_scenario(o.source_text, o.name)
    assert again == o
    assert o.events == s.events and o.segments == s.segments
    with pytest.raises(ScenarioError):
        scenario_overrides(s, colour="red")


NO_PROFILE = """
name = "seg"
[initial]
speed_mps = 20.0
"""


@pytest.mark.parametrize(
    ("segment", "message"),
    [
        (
            'kind = "turn"\nyaw_rate_dps = 0.0\nangle_deg = 90.0',
            r"segment\[0\]\.yaw_rate_dps must be non-zero",
        ),
        (
            'kind = "turn"\nyaw_rate_dps = 0.0\nduration_s = 9.0',
            r"segment\[0\]\.yaw_rate_dps must be non-zero",
        ),
        (
            'kind = "coordinated_turn"\nyaw_rate_dps = 0.0\nangle_deg = 90.0',
            r"segment\[0\]\.yaw_rate_dps must be non-zero",
        ),
        (
            'kind = "coordinated_turn"\nyaw_rate_dps = 5.0\nroll_rate_dps = 0.0\nangle_deg = 90.0',
            r"segment\[0\]\.roll_rate_dps must be > 0",
        ),
        (
            'kind = "climb"\npitch_deg = 5.0\npitch_rate_dps = -1.0\nduration_s = 20.0',
            r"segment\[0\]\.pitch_rate_dps must be > 0",
        ),
        (
            'kind = "turn"\nyaw_rate_dps = 5.0\nangle_deg = 90.0\ntransition_s = -1.0',
            r"segment\[0\]\.transition_s",
        ),
        ('kind = "rates"\nduration_s = 3.0', r"^segment\[0\] \(rates\) needs euler_rate_dps"),
        (
            'kind = "accelerate"\naccel_mps2 = 0.0\nto_speed_mps = 30.0',
            r"^segment\[0\]\.accel_mps2 must be non-zero to reach to_speed_mps",
        ),
        (
            'kind = "turn"\nyaw_rate_dps = 10.0\nangle_deg = 5.0',
            r"^segment\[0\] \(turn\): angle_deg too small",
        ),
        (
            'kind = "turn"\nyaw_rate_dps = 10.0\nduration_s = 1.5',
            r"^segment\[0\] \(turn\): duration_s too small",
        ),
        (
            'kind = "coordinated_turn"\nyaw_rate_dps = 10.0\nangle_deg = 2.0',
            r"^segment\[0\] \(coordinated_turn\): angle_deg too small",
        ),
        (
            'kind = "climb"\npitch_deg = 10.0\nduration_s = 2.0',
            r"^segment\[0\] \(climb\): duration_s 2 s is shorter than its two pitch transitions",
        ),
    ],
)
@pytest.mark.parametrize("top_duration", ["", "duration_s = 30.0\n"])
def test_a_segment_the_profile_cannot_follow_is_refused_naming_segment_and_key(
    segment: str, message: str, top_duration: str
) -> None:
    """A zero rate divided by (ZeroDivisionError), a missing euler_rate_dps (KeyError) and a
    segment too short for its transitions (a ValueError with no index) all came out raw."""
    with pytest.raises(ScenarioError, match=message):
        parse_scenario(top_duration + NO_PROFILE + "[[segment]]\n" + segment + "\n")


def test_segments_adding_up_past_the_limit_do_not_blame_a_duration_s_the_file_lacks() -> None:
    with pytest.raises(ScenarioError, match=r"^the segments add up to 2e\+06 s") as err:
        parse_scenario(NO_PROFILE + '[[segment]]\nkind = "hold"\nduration_s = 1e6\n' * 2)
    assert "duration_s must be" not in str(err.value)


def test_a_scenario_file_that_is_not_utf8_is_one_line_naming_it(tmp_path) -> None:  # type: ignore[no-untyped-def]
    bad = tmp_path / "bin.toml"
    bad.write_bytes(b"\xff\xfe\x00")
    with pytest.raises(ScenarioError, match=r"scenario file '.*bin\.toml' is not UTF-8 text"):
        load_scenario(str(bad))


def test_a_clock_table_step_past_a_day_is_refused_naming_it() -> None:
    from hil.sensors.clock import DeviceClockConfig, parse_clock_table

    table = {"steps": [{"t_s": 1.0, "step_s": -2e5}]}
    with pytest.raises(ScenarioError, match=r"clock\.imu\.steps\[0\]\.step_s must be in \[-86400, 86400\]"):
        parse_clock_table("imu", table, DeviceClockConfig())
    ok = parse_clock_table("imu", {"steps": [{"t_s": 1.0, "step_s": 86_400.0}]}, DeviceClockConfig())
    assert ok.steps[0].step_s == 86_400.0

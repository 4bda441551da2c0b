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


@pytest.mark.parametrize(
    ("extra", "said"),
    [
        ("[gnss]\npos_sigma_m = 0.0\n", r"^gnss\.pos_sigma_m must be > 0 and < 1e\+06, got 0 "),
        ("[gnss]\nvel_sigma_mps = [0.1, 0.0, 0.1]\n", r"^gnss\.vel_sigma_mps must be > 0 "),
        ("[gnss]\npos_sigma_m = 1e6\n", r"^gnss\.pos_sigma_m must be > 0 and < 1e\+06, got 1e\+06 "),
        (
            '[[event]]\nkind = "gnss_spoof"\nt_start_s = 1.0\noffset_ned_m = [1.0, 0, 0]\nsigma_m = 2e6\n',
            r"^event\[0\]\.sigma_m \(the σ the spoofed fixes claim\) must be > 0 and < 1e\+06",
        ),
    ],
)
def test_a_gnss_sigma_the_fusion_would_refuse_is_refused_by_the_loader(extra: str, said: str) -> None:
    """σ 0 loaded, and the fusion then refused every fix (rejected.implausible.gnss.sigma)."""
    from hil.fusion.core import FusionConfig, implausible
    from hil.messages import GnssFix

    with pytest.raises(ScenarioError, match=said):
        parse_scenario(MINIMAL + extra)
    sigma = 0.0 if "0.0" in extra else 2e6 if "2e6" in extra else 1e6
    fix = GnssFix(
        seq=0, stamp_ns=0, device_stamp_ns=0, rx_stamp_ns=0, lat_deg=0.0, lon_deg=0.0, alt_m=0.0,
        pos_ned_m=[0.0, 0.0, 0.0], vel_ned_mps=[0.0, 0.0, 0.0], pos_sigma_m=[sigma, 1.0, 1.0],
        vel_sigma_mps=[1.0, 1.0, 1.0], fix_type=3, num_sats=10, hdop=1.0,
    )  # fmt: skip
    assert implausible(fix, FusionConfig()) == "sigma"  # the bound is the fusion's own


@pytest.mark.parametrize(
    ("extra", "said"),
    [
        (
            '[imu]\npreset = "consumer_mems"\ngyro_arw_dprh = -1\n',
            r"^imu: 'gyro_arw_dprh' must be non-negative, got -1$",
        ),
        (
            "[imu]\naccel_vrw_mpsrh = [0.1, -2, 0.1]\n",
            r"^imu: 'accel_vrw_mpsrh' must be non-negative, got \[0\.1, -2, 0\.1\]$",
        ),
        (
            '[[event]]\nkind = "gnss_pulse"\nt_start_s = 1.0\ntau_s = 1.0\n',
            r"^event\[0\] \(gnss_pulse\) needs amplitude_m$",
        ),
        (
            '[[event]]\nkind = "gnss_latency"\nt_start_s = 1.0\n',
            r"^event\[0\] \(gnss_latency\) needs latency_s$",
        ),
        (
            '[[event]]\nkind = "gnss_jump"\nt_start_s = 1.0\n',
            r"^event\[0\] \(gnss_jump\) needs offset_ned_m$",
        ),
    ],
)
def test_an_error_names_the_user_s_key_and_value(extra: str, said: str) -> None:
    """They said the internal key in SI units (gyro_arw_rad_rts ... -0.00029...), or "must be
    a finite number, got None" of a parameter the event lacked."""
    with pytest.raises(ScenarioError, match=said):
        parse_scenario(MINIMAL + extra)

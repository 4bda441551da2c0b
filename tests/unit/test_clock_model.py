"""Device clock model: offset, drift, tick, steps, jitter as a pure function of true time;
[clock.<sensor>] parsing and its errors."""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from hil.nav.scenario import ScenarioError, load_scenario, parse_scenario
from hil.sensors.clock import ClockStep, DeviceClock, DeviceClockConfig, clock_config_for, device_clock_for
from hil.sensors.imu import sensor_rng
from hil.timesync.config import sync_config_for


def test_offset_drift_tick_and_step_without_noise() -> None:
    cfg = DeviceClockConfig(offset_s=0.5, drift_ppm=20.0, quantum_s=1e-6, steps=(ClockStep(10.0, -0.25),))
    c = DeviceClock(cfg, sensor_rng(1, "t.clock"))
    # GIVEN 20 ppm fast and 0.5 s ahead WHEN 5 s of true time pass THEN 5 s + 100 µs + 0.5 s
    assert c.device_ns(5_000_000_000) == 5_500_100_000
    assert c.device_ns(10_000_000_000) == 10_250_200_000  # the step applies from its instant on
    assert c.device_ns(1_234_567) % 1000 == 0  # floored to the 1 µs tick


def test_jitter_is_a_function_of_time_and_scalar_equals_vector() -> None:
    cfg = DeviceClockConfig(offset_s=0.01, drift_ppm=-7.0, drift_rw_ppm_per_sqrt_s=0.05, jitter_s=1e-6)
    t = np.arange(1, 20_001, dtype=np.int64) * 2_500_000
    a = DeviceClock(cfg, sensor_rng(3, "imu.clock"))
    b = DeviceClock(cfg, sensor_rng(3, "imu.clock"))
    vec = a.device_ns_array(t)
    scal = np.array([b.device_ns(int(x)) for x in t[::-1]])[::-1]  # asked in reverse order
    assert np.array_equal(vec, scal)
    ideal = t + 10_000_000 + np.floor(-7e-6 * t)
    resid = vec - ideal
    # white part ~1 µs; the wander (0.05 ppm/√s over 50 s) adds a slow part of a few µs
    assert 0.7e3 < np.std(np.diff(resid)) / np.sqrt(2) < 1.3e3
    assert np.abs(resid).max() < 100e3


def test_scenario_clock_table_overrides_defaults_and_derives_latencies() -> None:
    base = load_scenario("straight_level")
    text = base.source_text + "\n[clock.imu]\ndrift_ppm = 50.0\nsteps = [{t_s = 3.0, step_s = 0.1}]\n"
    text += "\n[clock.gnss]\ntimetag = false\n"
    s = parse_scenario(text)
    imu = clock_config_for(s, "imu")
    assert imu.drift_ppm == 50.0 and imu.offset_s == pytest.approx(0.0071)
    assert imu.steps == (ClockStep(3.0, 0.1),)
    assert imu.min_delay_s == pytest.approx(20e-6 + 4 * 135e-6)
    assert sync_config_for(s, "gnss").source == "arrival"
    assert sync_config_for(s, "gnss").min_delay_ns == round(s.gnss.latency_s * 1e9)
    assert sync_config_for(s, "imu").source == "timetag"
    assert abs(device_clock_for(s, "imu").device_ns(0) - 7_100_000) <= 3_000  # 0.5 µs jitter, 1 µs tick


@pytest.mark.parametrize(
    ("snippet", "needle"),
    [
        ("[clock.imu]\ndrift_pm = 3.0\n", "unknown key"),
        ("[clock.imu]\ntimetag = 1\n", "timetag"),
        ('[clock.imu]\nsync = "maybe"\n', "sync"),
        ("[clock.imu]\noffset_s = 0.1\nsteps = [{t_s = 0.0, step_s = -0.5}]\n", "below zero"),
        ("[clock.imu]\njitter_s = -1.0\n", "jitter_s"),
    ],
)
def test_bad_clock_tables_name_the_key(snippet: str, needle: str) -> None:
    s = parse_scenario(load_scenario("static").source_text + "\n" + snippet)
    with pytest.raises(ScenarioError, match=needle):
        clock_config_for(s, "imu")


def test_ideal_config_reads_true_time() -> None:
    c = DeviceClock(replace(DeviceClockConfig(), quantum_s=0.0), sensor_rng(0, "x"))
    assert c.device_ns(123_456_789) == 123_456_789 and c.latch_ns(5) == 5

"""GNSS emulator: error statistics, timed faults, latency, batching."""

from __future__ import annotations

from dataclasses import replace

import numpy as np

from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nav.trajectory import TruthGenerator
from hil.sensors.gnss import GnssEmulatorCore
from hil.sensors.imu import sensor_rng

NS = 1_000_000_000


def _run(s, name: str = "gnss"):  # type: ignore[no-untyped-def]
    tg = TruthGenerator(s)
    g = GnssEmulatorCore(s, tg, sensor_rng(s.seed, name))
    b = g.next_batch(tg.duration_ns)
    return b, tg.sample(b.t_valid_ns)


def test_white_error_matches_the_configured_sigma() -> None:
    # GIVEN the seed paper's receiver (σ = 20 m, 0.2 m/s), no slow component, 10 h at 1 Hz
    s = scenario_overrides(load_scenario("static"), duration_s=36000.0)
    b, truth = _run(s)
    dp = b.pos_ned_m - truth.pos_ned_m
    dv = b.vel_ned_mps - truth.vel_ned_mps
    # THEN the sample σ per axis is within 5 % of the configured value, mean ~ 0
    assert np.all(np.abs(dp.std(axis=0) / 20.0 - 1.0) < 0.05)
    assert np.all(np.abs(dv.std(axis=0) / 0.2 - 1.0) < 0.05)
    assert np.all(np.abs(dp.mean(axis=0)) < 4 * 20.0 / np.sqrt(len(dp)))


def test_slow_component_has_the_configured_amplitude_and_period() -> None:
    s = scenario_overrides(load_scenario("long_flight"), duration_s=5000.0)
    b, truth = _run(s)
    e = (b.pos_ned_m - truth.pos_ned_m)[:, 2]
    t = b.t_valid_ns / 1e9
    w = 2 * np.pi / 12660.0
    basis = np.stack([np.sin(w * t), np.cos(w * t), np.ones_like(t)], axis=-1)
    coef, *_ = np.linalg.lstsq(basis, e, rcond=None)
    assert abs(np.hypot(coef[0], coef[1]) / 15.0 - 1.0) < 0.1


def test_car_drive_faults_replay_as_scheduled() -> None:
    s = load_scenario("car_drive")
    b, truth = _run(s)
    t = b.t_valid_ns / NS
    # outages: no epochs at all inside [150, 180) and [420, 480)
    assert not np.any((t >= 150) & (t < 180)) and not np.any((t >= 420) & (t < 480))
    assert np.any((t >= 149) & (t < 150)) and np.any((t >= 180) & (t < 181))
    # the jump shifts the mean error by its offset (σ 2/2/4 m over 150 epochs)
    err = b.pos_ned_m - truth.pos_ned_m
    jump = (t >= 260) & (t < 275)
    assert np.allclose(err[jump].mean(axis=0), [12.0, -8.0, 5.0], atol=1.5)
    assert np.allclose(err[(t > 200) & (t < 259)].mean(axis=0), 0.0, atol=1.5)
    glitch = (t >= 300) & (t < 303)
    assert abs((b.vel_ned_mps - truth.vel_ned_mps)[glitch, 0].mean() - 1.5) < 0.15
    # latency 50 ms + [0, 10) ms jitter, then 250 ms + [0, 20) ms from t = 350 s
    lat = (b.t_output_ns - b.t_valid_ns) / NS
    assert np.all((lat[t < 350] >= 0.05) & (lat[t < 350] < 0.06))
    assert np.all((lat[t >= 350] >= 0.25) & (lat[t >= 350] < 0.27))
    assert np.all(b.fix_type == 3) and np.all(b.num_sats >= 4)


def test_pulse_and_lever_arm() -> None:
    # a noise-free receiver: no scenario may claim σ 0 (the fusion refuses such a fix), the
    # sensor model alone may draw none
    s = load_scenario("uav_survey")
    s = replace(s, gnss=replace(s.gnss, pos_sigma_m=(0.0, 0.0, 0.0), vel_sigma_mps=(0.0, 0.0, 0.0)))
    b, truth = _run(s)
    t = b.t_valid_ns / NS
    err = b.pos_ned_m - truth.pos_ned_m
    pulse = (t >= 500) & (t < 501)
    lever = np.linalg.norm(err[~pulse], axis=1)
    # with no noise the error is the lever arm, |l| = 0.18 m, rotated into NED
    assert np.allclose(lever, np.hypot(0.1, 0.15), atol=1e-6)
    assert np.allclose(err[pulse, 0] - err[pulse.nonzero()[0][0] - 1, 0], 50.0, atol=0.05)
    assert pulse.sum() == 5  # 5 Hz × 1 s


def test_epoch_stream_ignores_how_it_is_requested() -> None:
    s = load_scenario("car_drive")
    tg = TruthGenerator(s)
    whole = GnssEmulatorCore(s, tg, sensor_rng(5, "gnss")).next_batch(tg.duration_ns)
    g = GnssEmulatorCore(s, tg, sensor_rng(5, "gnss"))
    parts = [g.next_batch(int(x * NS)) for x in (0.0, 0.05, 0.1, 155.0, 155.0, 479.0, 1e4)]
    for f in ("t_valid_ns", "t_output_ns", "pos_ned_m", "vel_ned_mps", "lat_deg", "hdop"):
        assert np.array_equal(getattr(whole, f), np.concatenate([getattr(p, f) for p in parts]))
    assert len(parts[4].t_valid_ns) == 0

"""IMU emulator: Allan deviation reads back the configured noise; streams ignore batching."""

from __future__ import annotations

import math

import allantools
import numpy as np
import pytest

from hil.nav.earth import normal_gravity
from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nav.sensor_specs import DEG, GM_PEAK_RATIO, UG_MPS2, gauss_markov_adev_peak_ratio
from hil.nav.trajectory import TruthGenerator
from hil.sensors.imu import ImuEmulatorCore, sensor_rng


def _imu(duration_s: float, rate: int, seed: int = 11, **spec: float) -> ImuEmulatorCore:
    s = scenario_overrides(
        load_scenario("static"),
        duration_s=duration_s,
        imu_rate_hz=rate,
        imu_preset="ideal",
        seed=seed,
        **{f"imu_{k}": v for k, v in spec.items()},
    )
    return ImuEmulatorCore(s, TruthGenerator(s), sensor_rng(s.seed, "imu"))


def _adev(x: np.ndarray, rate: float, taus: list[float]) -> np.ndarray:
    t, ad, _, _ = allantools.oadev(x, rate=rate, data_type="freq", taus=np.array(taus))
    assert np.allclose(t, taus)
    return np.asarray(ad)


def test_arw_and_vrw_read_back_from_allan_deviation() -> None:
    # GIVEN white noise only: ARW 0.15 deg/√h, VRW 0.05 m/s/√h
    rate = 200
    imu = _imu(1800.0, rate, gyro_arw_dprh=0.15, accel_vrw_mpsrh=0.05)
    b = imu.next_batch(1800 * rate)
    for axis in range(3):
        # THEN σ_A(τ) = N/√τ: read N at τ = 1 s and 10 s
        g = b.gyro_radps[:, axis] - np.mean(b.gyro_radps[:, axis])
        a = b.accel_mps2[:, axis] - np.mean(b.accel_mps2[:, axis])
        n_g = _adev(g, rate, [1.0, 10.0]) * np.sqrt([1.0, 10.0])
        n_a = _adev(a, rate, [1.0, 10.0]) * np.sqrt([1.0, 10.0])
        assert np.all(np.abs(n_g / (0.15 * DEG / 60.0) - 1.0) < 0.10), n_g
        assert np.all(np.abs(n_a / (0.05 / 60.0) - 1.0) < 0.10), n_a


@pytest.mark.parametrize(
    ("key", "value", "unit"),
    [
        ("gyro_bias_instability_dph", 20.0, DEG / 3600.0),
        ("accel_bias_instability_ug", 200.0, UG_MPS2),
    ],
)
def test_bias_instability_reads_back_as_the_allan_floor(key: str, value: float, unit: float) -> None:
    # GIVEN bias instability B only, correlation time 10 s, 3 h at 100 Hz
    rate, tc = 100, 10.0
    corr_key = key.split("_")[0] + "_bias_corr_s"
    imu = _imu(3 * 3600.0, rate, **{key: value, corr_key: tc})
    b = imu.next_batch(3 * 3600 * rate)
    x = b.gyro_radps if key.startswith("gyro") else b.accel_mps2
    taus = [4.0, 8.0, 12.0, 16.0, 19.0, 22.0, 26.0, 32.0, 45.0]
    for axis in range(3):
        # THEN the Allan floor (the bump of the Gauss–Markov curve) is 0.664 B (IEEE 952)
        floor = _adev(x[:, axis] - x[:, axis].mean(), rate, taus).max()
        assert abs(floor / (0.664 * value * unit) - 1.0) < 0.10, (axis, floor / unit)


def test_the_written_out_gauss_markov_peak_ratio_is_the_formulas() -> None:
    # GM_PEAK_RATIO is a literal so that a scenario load does not import numpy; it must be the
    # formula's value to the last bit, or every IMU's bias instability draw would change
    assert gauss_markov_adev_peak_ratio() == GM_PEAK_RATIO
    assert 0.6 < GM_PEAK_RATIO < 0.65


def test_batches_of_any_size_give_the_same_stream() -> None:
    s = load_scenario("uav_survey")
    tg = TruthGenerator(s)
    whole = ImuEmulatorCore(s, tg, sensor_rng(s.seed, "imu")).next_batch(4000)
    core = ImuEmulatorCore(s, tg, sensor_rng(s.seed, "imu"))
    parts = [core.next_batch(n) for n in (1, 1, 3, 40, 15, 1940, 2000)]
    for f in ("t_ns", "dtheta_b_rad", "dvel_b_mps", "gyro_radps", "accel_mps2"):
        assert np.array_equal(getattr(whole, f), np.concatenate([getattr(p, f) for p in parts]))
    other = ImuEmulatorCore(s, tg, sensor_rng(s.seed, "imu2")).next_batch(10)
    assert not np.array_equal(other.dtheta_b_rad, whole.dtheta_b_rad[:10])


def test_seed_accel_offset_preset_is_the_papers_u() -> None:
    s = scenario_overrides(load_scenario("static"), imu_preset="seed_accel_offset", duration_s=10.0)
    b = ImuEmulatorCore(s, TruthGenerator(s), sensor_rng(1, "imu")).next_batch(4000)
    g = float(normal_gravity(math.radians(50.45), 180.0))
    assert np.allclose(b.accel_mps2.mean(axis=0), [0.005, 0.005, -g], atol=1e-12)
    assert np.allclose(b.gyro_radps.std(axis=0), 0.0, atol=1e-15)  # earth rate, no noise


def test_quantisation_keeps_the_residual_and_saturation_clips() -> None:
    lsb = 1e-6  # rad
    imu = _imu(60.0, 400, gyro_quant_urad=1.0, gyro_arw_dprh=0.5, gyro_range_dps=1e-3)
    b = imu.next_batch(24000)
    counts = b.dtheta_b_rad / lsb
    assert np.allclose(counts, np.round(counts), atol=1e-6)
    # the earth rate (~11 deg/h) is far above the 1e-3 deg/s = 3.6 deg/h range on x: clipped
    assert np.abs(b.gyro_radps).max() <= 1e-3 * DEG + lsb * 400 + 1e-15
    unq = _imu(60.0, 400, gyro_arw_dprh=0.5, gyro_range_dps=1e-3).next_batch(24000)
    # the running sum never drifts more than one LSB from the unquantised sum
    drift = np.cumsum(b.dtheta_b_rad - unq.dtheta_b_rad, axis=0)
    assert np.abs(drift).max() <= 0.5 * lsb + 1e-15

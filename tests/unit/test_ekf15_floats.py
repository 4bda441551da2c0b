"""ekf15's float shortcuts give the bits of the numpy expressions they replaced."""

from __future__ import annotations

import itertools
import math

import numpy as np
import pytest

from hil.estimators.base import ImuInput
from hil.estimators.ekf15 import (
    Ekf15,
    _mv3,
    accel_cal_augmented,
    covariance_step,
    error_dynamics,
    gyro_cal_augmented,
    kron_eye3,
    skew,
    slow_augmented,
)
from hil.nav.earth import OMEGA_IE_RADPS
from hil.nav.portable import mv
from hil.nav.scenario import load_scenario
from hil.nav.strapdown import c_nb_floats
from hil.nav.trajectory import TruthGenerator


def test_mv3_is_portable_mv_bit_for_bit_signed_zeros_included() -> None:
    rng = np.random.default_rng(15)
    for k in range(50_000):
        m = rng.normal(size=(3, 3)) * 10.0 ** rng.uniform(-6, 0)
        x = rng.normal(size=3) * 10.0 ** rng.uniform(-6, 0)
        if k % 5 == 0:
            x[rng.integers(3)] = -0.0
        if k % 7 == 0:
            x[:] = rng.choice([0.0, -0.0], size=3)
        if k % 11 == 0:
            m[rng.integers(3), rng.integers(3)] = 0.0
        want = mv(m, x)
        got = np.array(_mv3(m.tolist(), *x.tolist()))
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))


def test_kron_eye3_is_numpys_kron_signed_zeros_included() -> None:
    rng = np.random.default_rng(3)
    for w in (rng.normal(size=3), np.array([-1.0, 0.0, -0.0]), np.zeros(3)):
        want = np.kron(np.eye(3), w[None, :])
        got = kron_eye3(w)
        assert got.shape == (3, 9)
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))


def _error_dynamics_with_arrays(c_nb: np.ndarray, f_n: np.ndarray, lat_rad: float) -> np.ndarray:
    """``error_dynamics`` as it was written with small arrays (the reference for its bits)."""
    w_ie = np.array([OMEGA_IE_RADPS * math.cos(lat_rad), 0.0, -OMEGA_IE_RADPS * math.sin(lat_rad)])
    f = np.zeros((15, 15))
    f[0:3, 3:6] = np.eye(3)
    f[3:6, 6:9] = skew(f_n)
    f[3:6, 9:12] = c_nb
    f[6:9, 6:9] = -skew(w_ie)
    f[6:9, 12:15] = -c_nb
    return f


def test_error_dynamics_has_the_array_constructions_bits_signed_zeros_included() -> None:
    rng = np.random.default_rng(151)
    for k in range(5_000):
        c, f_n, lat = rng.normal(size=(3, 3)), rng.normal(size=3) * 5.0, float(rng.uniform(-1.6, 1.6))
        if k % 5 == 0:
            f_n[rng.integers(3)] = rng.choice([0.0, -0.0])
        if k % 7 == 0:
            lat = float(rng.choice([0.0, -0.0, math.pi / 2]))
        want, got = _error_dynamics_with_arrays(c, f_n, lat), error_dynamics(c, f_n, lat)
        assert np.array_equal(got, want) and np.array_equal(np.signbit(got), np.signbit(want))


@pytest.mark.parametrize(("cal", "acal", "slow"), list(itertools.product((False, True), repeat=3)))
def test_the_prediction_on_floats_is_the_augmenting_functions_bits(cal: bool, acal: bool, slow: bool) -> None:
    """ekf15's prediction (``write_dynamics``: F written into the one matrix kept for it, then
    the covariance step) gives the bytes, signed zeros included, of ``error_dynamics`` augmented
    by ``gyro_cal_augmented``, ``accel_cal_augmented`` and ``slow_augmented`` and the covariance
    step on the same inputs, at every prediction; the specific force's sum too."""
    init = TruthGenerator(load_scenario("uav_survey")).initial_state()
    est = Ekf15(
        "ekf15",
        init,
        gyro_cal_sigma=(1e-3, 1e-3) if cal else (0.0, 0.0),
        accel_cal_sigma=(1e-3, 1e-3) if acal else (0.0, 0.0),
        gnss_slow_sigma_m=2.0 if slow else 0.0,
    )
    predict = est._propagate_covariance
    checked = []

    def check() -> None:
        dt = est._pending_dt
        c9 = c_nb_floats(*est.ins.q)
        c_nb = np.array(c9).reshape(3, 3)
        pv = est._pending_dv_b
        f_b = (pv[0] / dt, pv[1] / dt, pv[2] / dt)
        f_n = _mv3((c9[0:3], c9[3:6], c9[6:9]), *f_b)
        want = error_dynamics(c_nb, f_n, est.ins.lat_rad)
        if cal:
            want = gyro_cal_augmented(want, c_nb, np.array(est._pending_dth_b) / dt)
        if acal:
            want = accel_cal_augmented(want, c_nb, np.array(f_b))
        if slow:
            want = slow_augmented(want, est._slow_w)
        _phi, want_p = covariance_step(want, dt, est.p, est._qc)
        s0, s1 = est._sf_sum.tolist()
        predict()
        assert est._f.shape == want.shape and est._f.tobytes() == want.tobytes()
        if want_p[8, 8] <= math.pi**2 / 3.0:  # no yaw clamp: the covariance step's bytes
            assert est.p.tobytes() == want_p.tobytes()
        assert est._sf_sum.tolist() == [s0 + f_n[0] * dt, s1 + f_n[1] * dt]
        checked.append(dt)

    est._propagate_covariance = check  # type: ignore[method-assign]
    rng = np.random.default_rng(8)
    for k in range(200):
        th = rng.normal(0.0, 2e-3, 3)
        if k % 9 == 0:
            th[rng.integers(3)] = -0.0
        dv = rng.normal(0.0, 3e-2, 3) + np.array((0.0, 0.0, -9.81 * 0.0025))
        est.on_imu(ImuInput(init.stamp_ns + (k + 1) * 2_500_000, 0.0025, th, dv), None)  # type: ignore[arg-type]
    assert len(checked) == 50  # every fourth sample

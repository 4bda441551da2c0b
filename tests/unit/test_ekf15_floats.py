"""ekf15's float shortcuts give the bits of the numpy expressions they replaced."""

from __future__ import annotations

import math

import numpy as np

from hil.estimators.ekf15 import _mv3, error_dynamics, kron_eye3, skew
from hil.nav.earth import OMEGA_IE_RADPS
from hil.nav.portable import mv


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

"""ekf15's float shortcuts give the bits of the numpy expressions they replaced."""

from __future__ import annotations

import numpy as np

from hil.estimators.ekf15 import _mv3, kron_eye3
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

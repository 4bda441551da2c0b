"""The hand-written replacements for two scipy.signal calls give scipy's bits exactly.

``hil sim`` and ``hil rerun`` no longer import scipy.signal (seconds per start); these hold the
replacements to the functions they replace, on the filters the rig runs and on random ones.
"""

from __future__ import annotations

import numpy as np
import pytest
from scipy import signal

from hil.estimators import lti
from hil.sensors.imu import gauss_markov

_RIG_FILTERS = [
    lti.aperiodic(2, 50.0),
    lti.aperiodic(3, 30.0),
    lti.forcing3(40.0),
    lti.forcing3(40.0).complement(),
    lti.complementary2(0.07, 0.005),
    lti.complementary3(0.07, 0.005, 1e-4),
    lti.TransferFunction((2.0,), (4.0,), "gain"),
    lti.TransferFunction((0.0, 3.0, 1.0), (2.0, 0.5, 0.25), "leading zero"),
]


def _random_filters(n: int) -> list[lti.TransferFunction]:
    g = np.random.default_rng(20)
    out = []
    for _ in range(n):
        k = int(g.integers(2, 6))
        den = tuple(float(v) for v in g.normal(size=k) * 10.0 ** g.uniform(-3, 3, size=k))
        num = tuple(float(v) for v in g.normal(size=int(g.integers(1, k + 1))))
        out.append(lti.TransferFunction(num, den, "random"))
    return out


@pytest.mark.parametrize("tf", _RIG_FILTERS + _random_filters(40))
def test_from_tf_is_scipy_tf2ss_bit_for_bit(tf: lti.TransferFunction) -> None:
    ss = lti.StateSpace.from_tf(tf)
    a, b, c, d = signal.tf2ss(np.asarray(tf.num, float), np.asarray(tf.den, float))
    assert ss.a.tobytes() == np.asarray(a, float).tobytes()
    assert ss.b.tobytes() == b[:, 0].tobytes()
    assert ss.c.tobytes() == c[0].tobytes()
    assert np.float64(ss.d).tobytes() == np.float64(d[0, 0]).tobytes()


@pytest.mark.parametrize("phi", [0.0, 0.5, 0.999975, 1.0 - 2.0**-40])
def test_gauss_markov_is_lfilter_bit_for_bit_across_batches(phi: float) -> None:
    g = np.random.default_rng(7)
    x = g.standard_normal((1000, 3)) * np.array([1e-6, 3.0, 0.0])  # a zero drive axis: signed zeros
    state = g.standard_normal(3) * np.array([1e-5, 1.0, -0.0])
    ref, _ = signal.lfilter([1.0], [1.0, -phi], x, axis=0, zi=(phi * state)[None, :])
    got, st = [], state
    for lo, hi in [(0, 1), (1, 2), (2, 400), (400, 400), (400, 1000)]:  # the emulator's 1-row calls too
        part = gauss_markov(x[lo:hi], phi, phi * st)
        if hi > lo:
            st = part[-1].copy()
        got.append(part)
    assert np.vstack(got).tobytes() == ref.tobytes()

"""Complementary GPS + accelerometer filters of seed 003, as 1-D numerics.

``θ̂ = W(s)(θ + Δ) + (1 − W(s))(a + u)/s²``: GPS (with short strong disturbances ``Δ``) is
low-passed, the double-integrated accelerometer (with zero offset ``u``) high-passed.
Realised as the observer whose transfer functions are exactly those of the paper:

    second order, x = [θ̂, V̂]:       θ̂' = V̂ + r1 e,   V̂' = a_m + r2 e,           e = z − θ̂
    third order,  x = [θ̂, V̂, û]:    θ̂' = V̂ + k1 e,   V̂' = a_m − û + k2 e,   û' = −k3 e

so ``θ̂ = W z + (1 − W) a_m / s²`` with ``W = (r1 s + r2)/(s² + r1 s + r2)`` resp.
``(k1 s² + k2 s + k3)/(s³ + k1 s² + k2 s + k3)``. The third state integrates the position
residual and so absorbs the accelerometer offset: ``1 − W = s³/(…)`` has a triple zero and the
offset term ``u s/(…)`` leaves no static error.

On the rig the high-rate path is the free INS rather than a bare accelerometer, and then
``W z + (1 − W) X_INS = X_INS − W (X_INS − z)``: the complementary filter *is* a compensation
scheme with ``F = W``. The live ``cf2``/``cf3`` estimators are built that way
(:mod:`hil.estimators.registry`); this module keeps the paper's two-input form for the
reproduction.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import signal

from hil.nav.types import F64

#: Seed 003 values: r1 = k1 = 0.07 1/s, r2 = k2 = 0.005 1/s², k3 = 1e-4 1/s³.
R1, R2, K3 = 0.07, 0.005, 1e-4


@dataclass(frozen=True)
class ComplementaryFilter:
    """Continuous observer ``ẋ = A x + B [z, a_m]``, output ``θ̂ = x[0]``."""

    a: F64
    b: F64  # (n, 2): columns GPS position, accelerometer

    @staticmethod
    def second_order(r1: float = R1, r2: float = R2) -> ComplementaryFilter:
        a = np.array([[-r1, 1.0], [-r2, 0.0]])
        b = np.array([[r1, 0.0], [r2, 1.0]])
        return ComplementaryFilter(a, b)

    @staticmethod
    def third_order(k1: float = R1, k2: float = R2, k3: float = K3) -> ComplementaryFilter:
        a = np.array([[-k1, 1.0, 0.0], [-k2, 0.0, -1.0], [k3, 0.0, 0.0]])
        b = np.array([[k1, 0.0], [k2, 1.0], [-k3, 0.0]])
        return ComplementaryFilter(a, b)

    @property
    def order(self) -> int:
        return int(self.a.shape[0])

    def discretise(self, dt_s: float) -> tuple[F64, F64]:
        """Exact ZOH ``(Φ, Γ)`` for inputs held over ``dt_s`` (see :mod:`hil.estimators.lti`)."""
        n = self.order
        ad, bd, *_ = signal.cont2discrete(
            (self.a, self.b, np.eye(n)[:1], np.zeros((1, 2))), dt_s, method="zoh"
        )
        return np.asarray(ad, float), np.asarray(bd, float)

    def run(self, z_gps_m: F64, a_meas_mps2: F64, dt_s: float) -> F64:
        """Position estimate for sampled inputs; arrays ``(n_steps, ...)`` (extra axes = runs)."""
        phi, gamma = self.discretise(dt_s)
        z = np.asarray(z_gps_m, float)
        acc = np.asarray(a_meas_mps2, float)
        x = np.zeros((self.order, *z.shape[1:]))
        out = np.empty_like(z)
        for k in range(z.shape[0]):
            out[k] = x[0]
            # x+ = Φ x + Γ [z, a]
            x = phi @ x
            x = x + np.multiply.outer(gamma[:, 0], z[k]) + np.multiply.outer(gamma[:, 1], acc[k])
        return out

    def w_num_den(self) -> tuple[F64, F64]:
        """Transfer function GPS → θ̂ (``W``) from the state space, for the tests."""
        num, den = signal.ss2tf(self.a, self.b[:, :1], np.eye(self.order)[:1], np.zeros((1, 1)))
        return np.asarray(num[0], float), np.asarray(den, float)


def pulse_peak_error(
    cf: ComplementaryFilter, amp_m: float, tau_s: float, dt_s: float = 0.01, t_end_s: float = 200.0
) -> float:
    """Peak |θ̂ − θ| for a GPS disturbance of height ``amp_m`` lasting ``tau_s`` (θ = a = 0)."""
    n = round(t_end_s / dt_s)
    t = np.arange(n) * dt_s
    z = np.where((t >= 0.0) & (t < tau_s), amp_m, 0.0)
    return float(np.max(np.abs(cf.run(z, np.zeros(n), dt_s))))


def static_error(
    cf: ComplementaryFilter, offset_mps2: float, dt_s: float = 0.1, t_end_s: float = 4000.0
) -> float:
    """Position error after ``t_end_s`` with only an accelerometer offset (θ = z = 0)."""
    n = round(t_end_s / dt_s)
    return float(cf.run(np.zeros(n), np.full(n, offset_mps2), dt_s)[-1])

"""The lecture's scalar Kalman filters (seed 001): INS error per axis as a Wiener process.

SINS + GNSS velocity: the INS velocity error of each axis is a random walk, the three axes are
uncorrelated, so the vector filter splits into independent scalar filters on the difference
``y_INS − y_GNSS = ε + v``:

    D⁻_k = D_{k−1} + σ_n²                  (extrapolated error variance)
    K_k  = D⁻_k / (D⁻_k + σ_GNSS²)
    ε̂_k  = ε̂_{k−1} + K_k (y_INS,k − y_GNSS,k − ε̂_{k−1})
    D_k  = (1 − K_k) D⁻_k

The live ``kfvel`` estimator runs this filter per axis on velocity *and* position (the
position error is modelled as a random walk too — a rig extension, the lecture only does
velocity), with ``σ_n²`` scaled to the actual time since the previous fix
(``q_rate · Δt``) and ``σ_GNSS`` taken from the receiver-reported sigma: that is the lecture's
"measurement vector of variable dimension" for the two rates — between fixes only the
prediction runs.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil.estimators.base import Estimator, GnssInput, ImuBlock, ImuInput, InitialState, aligned_nav
from hil.estimators.feedback import ClosedLoopIns
from hil.nav.types import F64, FloatNavState, NavState, nav_floats


def scalar_kf_step(eps: F64, d: F64, innov: F64, q: float | F64, r: float | F64) -> tuple[F64, F64, F64]:
    """One predict + update; arrays broadcast over axes and Monte-Carlo runs.

    Returns ``(ε̂_k, D_k, K_k)``.
    """
    d_pred = d + q  # D⁻ = D + σ_n²
    k = d_pred / (d_pred + r)  # K = D⁻ / (D⁻ + σ²)
    eps_new = eps + k * (innov - eps)  # ε̂ = ε̂ + K (y_INS − y_GNSS − ε̂)
    return eps_new, (1.0 - k) * d_pred, k  # D = (1 − K) D⁻


def steady_state(q: float, r: float) -> tuple[float, float]:
    """Steady gain and σ from the scalar Riccati equation ``D⁻² − q D⁻ − q r = 0``.

    Returns ``(K∞, σ∞ = sqrt(D∞))``.
    """
    d_pred = 0.5 * (q + math.sqrt(q * q + 4.0 * q * r))
    k = d_pred / (d_pred + r)
    return k, math.sqrt((1.0 - k) * d_pred)


def monte_carlo(
    q: float, r: float, d0: float, n_steps: int, n_runs: int, rng: np.random.Generator
) -> tuple[F64, F64]:
    """Vectorised Monte-Carlo of the lecture example: returns (sample RMS error, Riccati σ)."""
    eps = rng.normal(0.0, math.sqrt(d0), n_runs)  # true INS error
    est = np.zeros(n_runs)
    d = np.full(n_runs, d0)
    rms = np.empty(n_steps)
    sig = np.empty(n_steps)
    for k in range(n_steps):
        eps = eps + rng.normal(0.0, math.sqrt(q), n_runs)  # Wiener process
        meas = eps + rng.normal(0.0, math.sqrt(r), n_runs)
        est, d, _ = scalar_kf_step(est, d, meas, q, r)
        rms[k] = math.sqrt(float(np.mean((est - eps) ** 2)))
        sig[k] = math.sqrt(float(d[0]))
    return rms, sig


class ScalarKfEstimator(Estimator):
    """Live per-axis scalar KFs on position and velocity (registry name ``kfvel``)."""

    def __init__(
        self,
        name: str,
        init: InitialState,
        q_pos_m2ps: float = 0.1,
        q_vel_m2ps3: float = 1e-3,
        d0_pos_m2: float = 1.0,
        d0_vel_m2ps2: float = 0.01,
        feedback: dict[str, Any] | None = None,
    ) -> None:
        # Lecture: σ_n = 0.01 m/s per 0.1 s step → q_vel = 1e-4 / 0.1 = 1e-3 m²/s³.
        self.name = name
        self.q_rate = np.array([q_pos_m2ps] * 3 + [q_vel_m2ps3] * 3)
        self.eps = np.zeros(6)
        self.d = np.array([d0_pos_m2] * 3 + [d0_vel_m2ps2] * 3)
        self._d0 = self.d.copy()
        self.gain = np.zeros(6)
        self._t_last_ns = init.stamp_ns
        self._ins: NavState | None = None
        self._ins_stamp_ns = init.stamp_ns
        self._init = init  # where it stands before its first IMU step: aligned_nav
        self._count = 0
        self._max_ratio = 0.0
        # feedback form (hil.estimators.feedback): an INS of its own, reset by ε̂ at every fix
        self.loop = None if feedback is None else ClosedLoopIns(init, **feedback)

    def on_imu(self, imu: ImuInput, ins: NavState) -> None:
        self.on_imu_block(ImuBlock.of(imu, ins))

    def on_imu_block(self, block: ImuBlock) -> None:
        if self.loop is not None:
            self.loop.propagate_block(block)
        else:
            self._ins = block.ins[-1]
        self._ins_stamp_ns = block.stamps_ns[-1]

    def on_gnss(self, gnss: GnssInput, ins: NavState) -> None:
        if self.loop is not None:
            dp, dv = self.loop.antenna_difference(gnss)
            self.loop.correct(dv, gnss)
            diff = np.concatenate([dp, dv])
        else:
            dt_s = (gnss.stamp_ns - self._ins_stamp_ns) * 1e-9
            pos_ins = ins.pos_ned_m + ins.vel_ned_mps * dt_s  # INS at the time of validity
            diff = np.concatenate([pos_ins - gnss.pos_ned_m, ins.vel_ned_mps - gnss.vel_ned_mps])
        r = np.concatenate([gnss.pos_sigma_m, gnss.vel_sigma_mps]) ** 2
        q = self.q_rate * max((gnss.stamp_ns - self._t_last_ns) * 1e-9, 0.0)
        self._max_ratio = float(np.max((diff - self.eps) ** 2 / (self.d + q + r)))
        self.eps, self.d, self.gain = scalar_kf_step(self.eps, self.d, diff, q, r)
        self._t_last_ns = gnss.stamp_ns
        self._count += 1
        if self.loop is not None:  # the closed-loop Kalman reset: ε̂ into the INS, the filter at 0
            self.loop.reset(self.eps[:3], self.eps[3:])
            self.eps = np.zeros(6)

    def restart_on_gnss(self, gnss: GnssInput, ins: NavState) -> None:
        """The fusion re-initialised the free INS on this fix (its gate's rule 4, after an IMU
        fault): the error the filter estimated of the INS before is not this one's, so it starts
        again at this fix, as at its start. Open loop it corrects that free INS from now on; in the
        feedback form its own INS, which the fault left as far off, is taken from it
        (``ClosedLoopIns.reinitialise``)."""
        self.eps, self.d, self.gain = np.zeros(6), self._d0.copy(), np.zeros(6)
        if self.loop is None:
            self._ins = ins
        else:  # its own INS, as far off: taken from the free INS just re-initialised
            self.loop.reinitialise(ins)
        self.on_gnss(gnss, ins)

    def solution(self) -> NavState:
        if self.loop is not None:
            nav: NavState | None = self.loop.nav()
        else:
            nav = self._ins
        if nav is None:
            return aligned_nav(self._init)
        # Variance grows between fixes: D(t) = D_k + q_rate (t − t_k)
        var = self.d + self.q_rate * max((self._ins_stamp_ns - self._t_last_ns) * 1e-9, 0.0)
        sig = np.sqrt(var)
        e0, e1, e2, e3, e4, e5 = self.eps.tolist()
        (p0, p1, p2), (v0, v1, v2), q = nav_floats(nav)  # X_INS − ε̂ on floats: the arrays' values
        return FloatNavState(
            (p0 - e0, p1 - e1, p2 - e2),
            (v0 - e3, v1 - e4, v2 - e5),
            q,
            sig[:3].copy(),
            sig[3:].copy(),
            None if self.loop is None else self.loop.att_sigma_rad(),
        )

    def health(self) -> dict[str, float]:
        out = {
            "gnss_count": float(self._count),
            "innov_test_ratio_max": self._max_ratio,
            "gain_vel_n": float(self.gain[3]),
        }
        return out | (self.loop.health() if self.loop is not None else {})

"""The feedback (closed-loop) form of the seed estimators: the INS corrected by the estimate.

Open loop (the papers' compensation scheme) the filter only ever sees ``X_INS − X_GNSS`` of the
shared free INS and subtracts its estimate of the INS error from it; the INS itself is never
touched. That is exact linear theory while the INS error stays inside what the filter tracks:
``1 − F`` of the forcing filters removes a constant and a ramp, and leaks ``3T²·ξ̈`` of an
INS error accelerating at ``ξ̈``. A navigation-grade INS (the papers': 140 km over 5000 s) keeps
``ξ̈`` small. A consumer MEMS gyro's 0.5 °/s turn-on bias tilts the platform by 9 mrad every
second, ``ξ̈`` reaches ``g`` within minutes and the free INS is hundreds of kilometres off.

The feedback form keeps the INS inside the filter's range, as real integrations do. Each
estimator in this form owns a strapdown INS (like ekf15) and, at every GNSS fix:

1. **Reset by the filter's estimate.** The seed filter runs unchanged on ``X_INS − X_GNSS`` of
   its own INS; its estimate ``y`` (position, velocity) of that INS's error is subtracted from
   the INS, and the filter's state is moved to the one it would have had without that error
   (:meth:`hil.estimators.compensation.CompensationCore.shift`: exact for an LTI filter, so the
   solution ``X_INS − y`` does not jump and the filter stays the paper's filter). kfvel's
   scalar filters hand over ``ε̂`` and restart from zero (the closed-loop Kalman reset).
2. **Attitude and sensor biases corrected** by :class:`Corrector`, a 12-state Kalman filter on
   the same INS − GNSS velocity difference (velocity matching, the in-flight alignment of a
   strapdown INS; the seed-004 corrector model in three axes): ``δv̇ = [f×]φ + C δb_a``,
   ``φ̇ = −[ω_ie×]φ − C δb_g``, biases random constants plus a random walk. Its estimates of
   ``φ``, ``δb_g``, ``δb_a`` are fed into the INS and reset; its ``δv`` stays its own and moves
   with every velocity reset of step 1.

Why step 2, and why a Kalman filter: position/velocity resets alone are, in linear theory, the
open-loop filter again (the reset moves the filter's state exactly, step 1) and cannot stop
the tilt that drives ``ξ̈``; measured on uav_survey with its consumer IMU, compvs with resets
only is 300–580 m RMS per coordinate. The attitude must be corrected, and heading can only be
seen through horizontal specific force (turns): a fixed-gain correction perpendicular to the
specific force never reaches the body-z gyro bias in coordinated flight (the specific force is
along body z there), and a correction driven by the filter's own rate estimate lags a turn by
the filter's ~3T. A Kalman filter's covariance remembers that a leg's heading error is about
the vertical and resolves it when the bank tilts the specific force (docs/concepts.md,
"When heading is observable").

The antenna lever arm (``lever_arm_b_m``) is applied here: with an attitude of its own the
INS is compared at the antenna, as ekf15 is. Pure numerics (hil.nav.portable), no clock, no I/O.
"""

from __future__ import annotations

import math
from typing import Any

import numpy as np

from hil.estimators.base import GnssInput, ImuBlock, ImuInput, InitialState
from hil.estimators.ekf15 import _frame_terms, _mv3, _write_error_blocks, bias_walk_psd, covariance_step
from hil.nav import strapdown as _sd
from hil.nav.attitude import (
    RESET_TILT_SIGMA_RAD,
    RESET_YAW_SIGMA_RAD,
    quat_from_rotvec_floats,
    quat_multiply_floats,
    quat_normalise_floats,
)
from hil.nav.earth import ned_to_lla_one, radii_of_curvature_one
from hil.nav.portable import dot, inv, mm, mmt, mv
from hil.nav.strapdown import LazyNavState, StrapdownState, c_nb_floats, strapdown_from_initial, to_nav_state
from hil.nav.types import F64, NavState, nav_floats

_DEG = math.pi / 180.0


def _corrector_prediction(
    qw: float, qx: float, qy: float, qz: float,
    sx: float, sy: float, sz: float,
    dt: float,
    lat: float,
    p: F64,
    qc: F64,
    dv0: float, dv1: float, dv2: float,
) -> tuple[F64, float, float, float]:  # fmt: skip
    """:class:`Corrector`'s prediction over ``dt`` (``P``, and ``δv`` moved by Φ) from the INS
    attitude ``q`` and the body Δv ``s`` summed over ``dt``, on floats where the arrays cost more
    than the sums: the specific force ``C s / dt`` and ``Φ δv`` in einsum's order for a 3-vector
    (:func:`hil.estimators.ekf15._mv3`'s), F with ekf15's entries (signed zeros too), then
    :func:`covariance_step`. Its Python form is the reference; :mod:`hil.runtime.jit` compiles
    it with the compiled covariance step (tests/unit/test_jit.py holds it to Python's bits)."""
    # [δv, φ, δb_g, δb_a]: δv̇ = [f×]φ + C δb_a, φ̇ = −[ω_ie×]φ − C δb_g
    f = _write_error_blocks(np.zeros((12, 12)), 0, 3, 9, 6, _frame_terms(qw, qx, qy, qz, sx, sy, sz, dt, lat))
    phi, p_new = covariance_step(f, dt, p, qc)
    # φ, biases are zero between fixes (closed loop): only δv moves
    d0 = (phi[0, 0] * dv0 + phi[0, 2] * dv2) + phi[0, 1] * dv1 + 0.0
    d1 = (phi[1, 0] * dv0 + phi[1, 2] * dv2) + phi[1, 1] * dv1 + 0.0
    d2 = (phi[2, 0] * dv0 + phi[2, 2] * dv2) + phi[2, 1] * dv1 + 0.0
    return p_new, d0, d1, d2


class Corrector:
    """Velocity-matching Kalman filter ``[δv, φ, δb_g, δb_a]`` (12 states, module docstring).

    Conventions as ekf15's: ``δv = v_INS − v``, ``C_est = (I − [φ×]) C``, true bias = estimate
    + error. Defaults are the tactical preset's; the fusion passes the scenario IMU's figures
    (:func:`hil.estimators.tuning.feedback_params`).
    """

    def __init__(
        self,
        accel_vrw_mps_rts: float = 0.03 / 60.0,
        gyro_arw_rad_rts: float = 0.125 * _DEG / 60.0,
        accel_bias_sigma_mps2: float = 50e-6 * 9.80665,
        gyro_bias_sigma_radps: float = 0.35 * _DEG / 3600.0,
        bias_corr_s: float = 300.0,
        p0_accel_bias_mps2: float = 1e-3 * 9.80665,
        p0_gyro_bias_radps: float = 1.0 * _DEG / 3600.0,
        accel_bias_corr_s: float | None = None,
        accel_bias_rw_mps2_rts: float = 0.0,
        gyro_bias_rw_radps_rts: float = 0.0,
        p0_vel_mps: float = 0.3,
        p0_tilt_rad: float = 2e-3,
        p0_yaw_rad: float = 1e-2,
        gate_chi2: float = 16.27,
        max_rejects: int = 10,
    ) -> None:
        self._att_sigma: F64 | None = None  # √diag(P) of the attitude, until P changes
        self.p = np.diag(
            np.square(
                [p0_vel_mps] * 3
                + [p0_tilt_rad, p0_tilt_rad, p0_yaw_rad]
                + [p0_gyro_bias_radps] * 3
                + [p0_accel_bias_mps2] * 3
            )
        )
        self.p0 = self.p.copy()  # where a re-initialisation opens it back to (``reinitialise``)
        self.qc = np.diag(
            [accel_vrw_mps_rts**2] * 3
            + [gyro_arw_rad_rts**2] * 3
            + [bias_walk_psd(gyro_bias_sigma_radps, bias_corr_s, gyro_bias_rw_radps_rts)] * 3
            + [bias_walk_psd(accel_bias_sigma_mps2, accel_bias_corr_s or bias_corr_s, accel_bias_rw_mps2_rts)]
            * 3
        )
        self.dv = np.zeros(3)  # the INS velocity error it believes in (not fed back: step 1 is)
        self.gate_chi2 = gate_chi2
        self.max_rejects = max_rejects
        self.nis = 0.0
        self.rejects = 0
        self._consecutive = 0

    @property
    def p(self) -> F64:
        """The covariance of ``[δv, φ, δb_g, δb_a]``."""
        return self._p

    @p.setter
    def p(self, value: F64) -> None:
        self._p = value
        self._att_sigma = None

    def att_sigma_rad(self) -> F64:
        """1σ of the attitude error about N, E, D (read at every output, changed every
        ``cov_every`` samples and at a fix: kept until ``p`` is set again)."""
        if self._att_sigma is None:
            self._att_sigma = np.sqrt(np.diag(self._p)[3:6])
        return self._att_sigma.copy()

    def predict(
        self,
        q_nb: tuple[float, float, float, float],
        sum_dv_b: tuple[float, float, float],
        dt_s: float,
        lat_rad: float,
    ) -> None:
        """Over ``dt_s`` at attitude ``q_nb`` with the body Δv summed over it (the mean specific
        force), at latitude ``lat_rad``: one call of :func:`_corrector_prediction`, which
        :mod:`hil.runtime.jit` compiles."""
        d = self.dv.tolist()
        self.p, d0, d1, d2 = _corrector_prediction(*q_nb, *sum_dv_b, dt_s, lat_rad, self.p, self.qc, *d)
        self.dv = np.array((d0, d1, d2))

    def update(self, dv_meas: F64, sigma_mps: F64) -> F64 | None:
        """One velocity difference (INS − GNSS at the antenna) of σ ``sigma_mps`` per axis.

        Returns the increment of ``[φ, δb_g, δb_a]`` to feed back (9,), or None when the
        difference fails the χ² gate (``max_rejects`` in a row open the covariance and take it).
        """
        r = np.diag(np.square(np.asarray(sigma_mps, float)))
        y = np.asarray(dv_meas, float) - self.dv
        s_inv, self.nis = corrector_innovation(self._p, y, r)
        if self.nis > self.gate_chi2:
            self.rejects += 1
            self._consecutive += 1
            if self._consecutive <= self.max_rejects:
                return None
            self._p[0:3, 0:3] += np.diag(y * y)  # locked out: trust it again, covariance opened
            s_inv, _ = corrector_innovation(self._p, y, r)
        self._consecutive = 0
        self.p, dx = corrector_joseph(self._p, s_inv, y, r)
        self.dv = self.dv + dx[0:3]
        return dx[3:12]


def corrector_innovation(p: F64, y: F64, r: F64) -> tuple[F64, float]:
    """``S⁻¹`` and the NIS of the corrector's velocity innovation ``y`` (``H = [I 0 0 0]``:
    ``S = P_vv + R``). :mod:`hil.runtime.jit` puts its loop form in its place
    (:func:`hil.nav.kernels.corrector_innovation`) where it gives these bits."""
    s_inv = inv(p[0:3, 0:3] + r)
    return s_inv, dot(y, mv(s_inv, y))


def corrector_joseph(p: F64, s_inv: F64, y: F64, r: F64) -> tuple[F64, F64]:
    """The corrector's Joseph-form update, ``K = P H' S⁻¹``: ``(P+, δx)``. Compiled as
    :func:`corrector_innovation` is (:func:`hil.nav.kernels.corrector_joseph`)."""
    k = mm(p[:, 0:3], s_inv)
    dx = mv(k, y)
    ikh = np.eye(p.shape[0])
    ikh[:, 0:3] -= k
    p_new = mmt(mm(ikh, p), ikh) + mmt(mm(k, r), k)
    return 0.5 * (p_new + p_new.T), dx


class ClosedLoopIns:
    """The INS of one estimator in feedback form: strapdown, sensor-bias estimates, corrector.

    ``propagate`` at every IMU step; at a fix ``antenna_difference`` gives ``X_INS − X_GNSS``
    at the antenna, ``correct`` feeds the corrector's attitude/bias estimate back, ``reset``
    takes the seed filter's position/velocity estimate out of the INS.
    """

    def __init__(
        self,
        init: InitialState,
        lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        cov_every: int = 20,
        **corrector: Any,
    ) -> None:
        self._init = init
        # the state as the plain tuple the (compiled) strapdown step takes and gives, and the
        # biases as floats: per IMU sample no conversion (``state``, ``b_g``, ``b_a`` read them)
        self._st: tuple[float, ...] = tuple(strapdown_from_initial(init))
        self._bias = (0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        self._b_g = np.zeros(3)
        self._b_a = np.zeros(3)
        self.corrector = Corrector(**corrector)
        lever = np.asarray(lever_arm_b_m, dtype=float)
        self._lever: F64 | None = lever if np.any(lever) else None
        self._w_b = np.zeros(3)  # corrected body rate of the last step (the arm's velocity)
        self.cov_every = int(cov_every)
        self._pending_dv_b = [0.0, 0.0, 0.0]  # Σ Δv of the block (floats: added at IMU rate)
        self._pending_dt = 0.0
        self._pending_n = 0
        self.stamp_ns = init.stamp_ns
        self._origin = (init.origin_lat_rad, init.origin_lon_rad, init.origin_alt_m)
        self._nav: NavState = to_nav_state(self.state, init)
        self._dirty = False

    @property
    def state(self) -> StrapdownState:
        return StrapdownState.of(self._st)

    @state.setter
    def state(self, s: StrapdownState) -> None:
        self._st = tuple(s)

    @property
    def b_g(self) -> F64:
        """Gyro bias estimate (rad/s, body axes), removed from every delta-angle (assigned
        whole, never changed in place: the step reads the floats the setter keeps)."""
        return self._b_g

    @b_g.setter
    def b_g(self, value: F64) -> None:
        self._b_g = np.asarray(value, dtype=float)
        self._bias = (*self._b_g.tolist(), *self._bias[3:])

    @property
    def b_a(self) -> F64:
        """Accelerometer bias estimate (m/s², body axes), removed from every delta-velocity
        (assigned whole, as ``b_g``)."""
        return self._b_a

    @b_a.setter
    def b_a(self, value: F64) -> None:
        self._b_a = np.asarray(value, dtype=float)
        self._bias = (*self._bias[:3], *self._b_a.tolist())

    def bias_floats(self) -> tuple[float, ...]:
        """``b_g`` then ``b_a`` as the floats the strapdown run takes (the output predictor's too)."""
        return self._bias

    def propagate(self, imu: ImuInput) -> None:
        self.propagate_block(ImuBlock.of(imu))

    def propagate_block(self, block: ImuBlock) -> None:
        """The block's intervals in order, the runs between two covariance predictions each in
        one call of the strapdown loop (compiled when the kernels are; ``_sd._corrected_run``)."""
        if not len(block):
            return
        run, rows = block.strapdown_run()
        no_cal, zero = _sd.NO_CALIBRATION, (0.0, 0.0, 0.0)
        for start, stop in block.runs(self.cov_every, self._pending_n):
            pv = self._pending_dv_b
            self._st, sum_dv, _, self._pending_dt = run(
                self._st, rows, start, stop, self._bias, no_cal, no_cal, tuple(pv), zero,
                self._pending_dt, False, False, False,
            )  # fmt: skip
            self._pending_dv_b = list(sum_dv)
            self._pending_n += stop - start
            if self._pending_n >= self.cov_every:
                self._predict()
        if self._lever is not None:  # the arm's velocity: the body rate of the last interval
            bgx, bgy, bgz = self._bias[:3]
            dt, tx, ty, tz = block.rows[-1][:4]
            tx, ty, tz = tx - bgx * dt, ty - bgy * dt, tz - bgz * dt
            self._w_b = np.array((tx / dt, ty / dt, tz / dt))
        self.stamp_ns = block.stamps_ns[-1]
        self._dirty = True

    def _predict(self) -> None:
        if self._pending_n == 0:
            return
        st, pv = self._st, self._pending_dv_b
        self.corrector.predict((st[6], st[7], st[8], st[9]), (pv[0], pv[1], pv[2]), self._pending_dt, st[0])
        self._pending_dv_b = [0.0, 0.0, 0.0]
        self._pending_dt = 0.0
        self._pending_n = 0

    def nav(self) -> NavState:
        if self._dirty:
            self._nav = LazyNavState(self._st, self._origin)  # type: ignore[arg-type]  # to_nav_state's values
            self._dirty = False
        return self._nav

    def antenna_difference(self, gnss: GnssInput) -> tuple[F64, F64]:
        """``(p, v)`` of INS minus GNSS at the fix's time of validity and at the antenna."""
        # on floats, the arrays' operations in their order (``mv`` of a 3-vector: ``_mv3``)
        dt = (gnss.stamp_ns - self.stamp_ns) * 1e-9
        (p0, p1, p2), (v0, v1, v2), _ = nav_floats(self.nav())
        p0, p1, p2 = p0 + v0 * dt, p1 + v1 * dt, p2 + v2 * dt
        if self._lever is not None:
            st = self._st
            c = c_nb_floats(st[6], st[7], st[8], st[9])
            rows = (c[0:3], c[3:6], c[6:9])
            lx, ly, lz = self._lever.tolist()
            a0, a1, a2 = _mv3(rows, lx, ly, lz)
            p0, p1, p2 = p0 + a0, p1 + a1, p2 + a2
            wx, wy, wz = self._w_b.tolist()  # cross(w, lever), as hil.nav.earth.cross of one pair
            b0, b1, b2 = _mv3(rows, wy * lz - wz * ly, wz * lx - wx * lz, wx * ly - wy * lx)
            v0, v1, v2 = v0 + b0, v1 + b1, v2 + b2
        g0, g1, g2 = gnss.pos_ned_m.tolist()
        h0, h1, h2 = gnss.vel_ned_mps.tolist()
        return np.array((p0 - g0, p1 - g1, p2 - g2)), np.array((v0 - h0, v1 - h1, v2 - h2))

    def correct(self, dv: F64, gnss: GnssInput) -> None:
        """The corrector on this fix's velocity difference; its attitude/bias estimate fed back."""
        self._predict()
        dx = self.corrector.update(dv, gnss.vel_sigma_mps)
        if dx is None:
            return
        self._rotate(dx[0:3])
        self.b_g = self.b_g + dx[3:6]
        self.b_a = self.b_a + dx[6:9]
        self._dirty = True

    def _rotate(self, phi: F64) -> None:
        """C_true = (I + [φ×]) C_est: the NED side rotated by +φ (ekf15's convention), on floats
        (``quat_*_floats``: the array forms' bits)."""
        st = self._st
        px, py, pz = phi.tolist()
        rot = quat_from_rotvec_floats(px, py, pz)
        q = quat_normalise_floats(*quat_multiply_floats(*rot, st[6], st[7], st[8], st[9]))
        self._st = (*st[:6], *q, *st[10:])

    def reset(self, dp: F64, dv: F64) -> None:
        """Take an estimated position/velocity error (NED) out of the INS (on floats: the arrays'
        operations, ``radii_of_curvature_one`` for ``radii_of_curvature``)."""
        st = self._st
        lat0, lon0, alt0 = st[0], st[1], st[2]
        d0, d1, d2 = dp.tolist()
        e0, e1, e2 = dv.tolist()
        r_m, r_n = radii_of_curvature_one(lat0)
        lat = lat0 - d0 / (r_m + alt0)
        lon = lon0 - d1 / ((r_n + alt0) * math.cos(lat0))
        alt = alt0 + d2  # δp_D = −δh
        self._st = (lat, lon, alt, st[3] - e0, st[4] - e1, st[5] - e2, *st[6:])
        self.corrector.dv = self.corrector.dv - dv
        self._dirty = True

    def reinitialise(
        self,
        ins: NavState,
        tilt_sigma_rad: float = RESET_TILT_SIGMA_RAD,
        yaw_sigma_rad: float = RESET_YAW_SIGMA_RAD,
    ) -> None:
        """This INS taken from the fusion's free INS re-initialised on a fix after an IMU fault
        (position, velocity, levelled attitude: ``FusionCore._reset_free_ins``): the fault left it
        as far off as that one. Its bias estimates stay; the corrector's covariance of velocity and
        attitude is opened to what the re-initialisation knows, decorrelated from the biases, and
        the velocity error it believed in is dropped."""
        self._predict()
        lat, lon, alt = ned_to_lla_one(*ins.pos_ned_m.tolist(), *self._origin)
        v, q = ins.vel_ned_mps.tolist(), np.asarray(ins.q_nb, dtype=float).tolist()
        self._st = (lat, lon, alt, *v, *q, *self._st[10:])
        c = self.corrector
        p = c.p.copy()
        p[0:6, :] = 0.0
        p[:, 0:6] = 0.0
        tilt, yaw = tilt_sigma_rad**2, yaw_sigma_rad**2
        p[0:6, 0:6] = np.diag([*np.diag(c.p0)[0:3].tolist(), tilt, tilt, yaw])
        c.p = p
        c.dv = np.zeros(3)
        self._dirty = True

    def att_sigma_rad(self) -> F64:
        """1σ of the attitude error about N, E, D from the corrector's covariance."""
        return self.corrector.att_sigma_rad()

    def health(self) -> dict[str, float]:
        c = self.corrector
        return {
            "feedback": 1.0,
            "nis_vel": c.nis,
            "gnss_rejected": float(c.rejects),
            "accel_bias_norm_mps2": math.sqrt(dot(self.b_a, self.b_a)),
            "gyro_bias_norm_radps": math.sqrt(dot(self.b_g, self.b_g)),
            "yaw_sigma_rad": math.sqrt(float(c.p[5, 5])),
        }

"""Loosely coupled 15-state error-state EKF, closed loop on the strapdown (registry ``ekf15``).

Error state (NED, true = estimate − error for p, v; biases true = estimate + error)::

    δx = [δp (3, m), δv (3, m/s), φ (3, rad), δb_a (3, m/s²), δb_g (3, rad/s)]

with ``C_nb,est = (I − [φ×]) C_nb,true``. Linearised dynamics (Earth-rate coupling kept, the
small gravity and Coriolis error terms dropped — they matter for hours, not for a UAV flight):

    δṗ = δv
    δv̇ = [f_n×] φ + C_nb δb_a + w_a           (f_n: specific force in NED)
    φ̇  = −[ω_ie×] φ − C_nb δb_g − w_g
    δḃ = w_b                                    (random constant + random walk)

The IMU's bias is a turn-on constant (drawn once, the preset's 1 mg / 1 °/h) plus a slow
Gauss–Markov wander (instability σ, correlation time τ). The estimate is held between updates,
so the error state must not decay: a first-order Gauss–Markov ``δḃ = −δb/τ`` on the *error*
with a held estimate tells the filter the turn-on error fades in a few τ, and its bias
covariance shrinks to σ² in unobserved directions with no measurement at all (over-confident
after every turn, where tilt and horizontal accelerometer bias get separated). Here the bias
error is a random constant with a random walk of spectral density ``2σ²/τ`` (the wander's
variance over one correlation time), which never claims more than the data gave.

Rates, deliberately: the strapdown (:mod:`hil.nav.strapdown`, shared with the free INS) runs
at every IMU step with the bias estimates removed from the increments; the covariance is
propagated every ``cov_every`` IMU steps (default 4, i.e. 100 Hz at 400 Hz) with
``Φ = I + F Δ + (F Δ)²/2`` and ``Q_d = Q_c Δ`` using the mean specific force of the block — at
10 ms the neglected terms are O((FΔ)³) ~ 1e-9 — and always flushed before a GNSS update.

GNSS position and velocity are fused at their time of validity: the fusion core delivers a fix
between the IMU steps around it, so the INS is extrapolated over that sub-interval with its
velocity (``p(t_g) = p + v (t_g − t_k)``). Each of position and velocity passes an innovation
gate (normalised innovation squared ``yᵀ S⁻¹ y`` against ``gate_chi2``, χ²(3) 99.9 % by default)
before the sequential update

    S = H P H' + R;  K = P H' S⁻¹;  δx = K y;  P = (I − K H) P (I − K H)' + K R K'

after which δx is fed back into the strapdown and the biases and reset to zero. After
``max_rejects`` consecutive rejections the fix is accepted anyway (with the covariance
inflated), so a filter that diverged does not lock itself out.

GNSS slow error (optional, ``gnss_slow_sigma_m`` > 0; 21 states). A fix reports the σ of its
white noise; a receiver's slow geometry error (the seed-000 model: a sine per axis, period of
a few Schuler periods) is common to every fix. Folded into R it would be averaged away and the
filter would claim a position it cannot know. As states ``[δs (3), δṡ (3)]`` with
``δs̈ = −ω² δs`` (no process noise), prior σ² on ``s`` and (σω)² on ``ṡ``, the measurement is
``z = p + s + w`` (velocity: ``v + ṡ + w``), the filter carries ``ŝ, ṡ̂`` (rotated exactly
between updates, corrected like the other states), and its position covariance keeps what GNSS
cannot separate. Off by default (the live fusion tunes from the IMU only); the default path is
numerically the 15-state filter.

GNSS antenna lever arm (``lever_arm_b_m``, body axes from the IMU; the installation, which the
integrator measures). The fix is of the antenna, so the predicted position is
``p + Ĉ l`` and the predicted velocity ``v + Ĉ (ω̂ × l)``, with ``ω̂`` the bias-corrected body
rate of the last IMU step. With ``Ĉ = (I − [φ×]) C`` the attitude error enters both as
``[(Ĉ l)×] φ`` and ``[(Ĉ (ω̂ × l))×] φ``, and the gyro-bias error as ``−Ĉ [l×] δb_g`` in the
velocity. Zero (the default) is numerically the filter without it. The Earth and transport rate
in ``ω̂`` (ω_ib, not ω_nb) shift the velocity by ~1e-5 m/s per metre of arm: neglected.

Gyro scale factor and misalignment (optional, ``gyro_cal_sigma`` > 0; 9 more states). A tactical
gyro's 150 ppm scale factor leaves 0.5 mrad of heading after a 180° turn and a 0.5 mrad
misalignment tilts the platform by ~1.6 mrad through it: errors a 15-state filter cannot know
about, so its attitude (and then velocity) covariance is too small after every turn. As
random constants ``δe`` (the 3 × 3 error matrix ``E`` row by row, ``ω_meas = (I + E) ω + b``),
the rate error is ``δω = δb_g + N(ω) δe`` with ``N(ω) = I₃ ⊗ ωᵀ``, so
``φ̇ = −[ω_ie×] φ − C (δb_g + N(ω̄) δe)`` over a covariance block of mean body rate ``ω̄``; the
estimate ``Ê`` is removed from every increment (``Δθ − Ê Δθ``) and corrected like the biases.
Priors: the preset's scale-factor σ on the diagonal, its misalignment σ off it.

Accelerometer scale factor and misalignment (optional, ``accel_cal_sigma`` > 0; 9 more states
after the gyro's). The same construction: ``f_meas = (I + E_a) f + b_a``, the specific-force
error ``δf = δb_a + N(f) δe_a``, so ``δv̇ = [f_n×]φ + C (δb_a + N(f̄) δe_a)``; ``Ê_a`` is removed
from every increment (``Δv − Ê_a Δv``) and corrected like the biases.

Heading. GNSS sees heading only through ``δv̇ = [f_n×] φ``: a yaw error turns the horizontal
specific force into a velocity error. In level, unaccelerated motion that force is Coriolis-sized
(~4 mm/s²), so heading is unobservable and drifts with the z-gyro; a consumer gyro (0.5 °/s
turn-on bias) takes it to tens of degrees on a straight leg, where ``[f×]φ`` is no longer the
small-angle model the update assumes, and the filter read velocity noise as heading information
(its yaw σ levelled off at ~25° while the error went on to 130°). So:

- while the yaw σ exceeds ``heading_small_angle_rad`` (0.1 rad), every GNSS update is a Schmidt
  (consider) update that holds the heading part of the error state back -- yaw, the gyro bias
  about the vertical and, with calibration states, the gyro error matrix's rate error about it:
  neither corrected nor their variance reduced, so the yaw σ grows with the z-gyro's, honestly
  (capped at a heading uniform on the circle, σ = π/√3);
- meanwhile an in-motion alignment compares, from the most certain of the fixes of the last
  ``heading_align_window_s`` (5 s), the GNSS velocity change ``b`` with the integrated specific
  force in NED ``a``: a heading error δ of any size rotates one into the other, so
  ``δ = atan2(a × b, a · b)``. Once the specific force has moved the velocity enough for δ to be
  known to ``heading_align_sigma_rad`` (0.1 rad; the noise of both fixes, the tilt and horizontal
  accelerometer-bias σ over the window, the z-gyro drift over half of it), yaw is reset to it (σ
  set, yaw decorrelated: PX4's yaw reset) and velocity and position to the fix, as they were
  integrated with the wrong heading. The EKF refines heading through the rest of the manoeuvre.

A tactical IMU's yaw σ stays far below the bound, so its filter is numerically the one without
this (the golden replay is unchanged). ``heading_small_angle_rad`` ≤ 0 turns it off.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from hil.estimators.base import Estimator, GnssInput, ImuBlock, ImuInput, InitialState
from hil.nav import strapdown
from hil.nav.attitude import (
    RESET_TILT_SIGMA_RAD,
    RESET_YAW_SIGMA_RAD,
    levelled_attitude,
    quat_from_rotvec_floats,
    quat_multiply,
    quat_multiply_floats,
    quat_normalise,
    quat_normalise_floats,
)
from hil.nav.earth import OMEGA_IE_RADPS, cross, radii_of_curvature_one
from hil.nav.portable import dot, inv, mm, mmt, mv, norm, solve
from hil.nav.sensor_specs import G0_MPS2
from hil.nav.strapdown import (
    LazyNavState,
    StrapdownState,
    c_nb_floats,
    strapdown_from_initial,
    to_nav_state,
)
from hil.nav.types import F64, FloatNavState, NavState, nav_floats

_DEG = math.pi / 180.0
_RTH = 60.0  # sqrt(3600 s/h)
_YAW_VAR_MAX = math.pi**2 / 3.0  # a heading uniform on the circle: σ = π/√3 (104°)
_new_state = tuple.__new__  # a StrapdownState of the run's 16 floats, as strapdown_step_f makes it


def skew(v: F64) -> F64:
    """``[v×]`` such that ``[v×] w = v × w``."""
    return np.array([[0.0, -v[2], v[1]], [v[2], 0.0, -v[0]], [-v[1], v[0], 0.0]])


_EYE15 = np.eye(15)
_EYE15.flags.writeable = False
_F15 = np.zeros((15, 15))
_F15[0:3, 3:6] = np.eye(3)
_F15.flags.writeable = False


def kron_eye3(w: F64) -> F64:
    """``np.kron(np.eye(3), w[None, :])`` (3, 9) for a 3-vector ``w``, with kron's very entries
    (``1·w`` and ``0·w``, a signed zero where ``w`` is negative) without its general machinery."""
    w = np.asarray(w, dtype=float)
    z = 0.0 * w
    return np.concatenate((w, z, z, z, w, z, z, z, w)).reshape(3, 9)


def _mv3(m: Sequence[Sequence[float]], x: float, y: float, z: float) -> tuple[float, float, float]:
    """``mv(m, [x, y, z])`` for a 3 × 3 ``m`` (rows as float lists), in einsum's order for a
    3-vector: terms 0 and 2, then 1 (its two SIMD lanes), and the sum's zero start (``+ 0.0``
    makes a −0 +0, as einsum's accumulator does). Held to ``mv`` in tests/unit/test_ekf15_floats.py."""
    r0, r1, r2 = m
    return (
        (r0[0] * x + r0[2] * z) + r0[1] * y + 0.0,
        (r1[0] * x + r1[2] * z) + r1[1] * y + 0.0,
        (r2[0] * x + r2[2] * z) + r2[1] * y + 0.0,
    )


def kf_update(p: F64, y: F64, h: F64, r: F64) -> tuple[F64, F64, float]:
    """Joseph-form update; returns ``(δx, P+, NIS)`` for innovation ``y`` (m,), ``H`` (m, n)."""
    ph = mmt(p, h)
    s = mm(h, ph) + r  # S = H P H' + R
    s_inv = inv(s)
    nis = dot(y, mv(s_inv, y))
    k = mm(ph, s_inv)  # K = P H' S⁻¹
    ikh = np.eye(p.shape[0]) - mm(k, h)
    p_new = mmt(mm(ikh, p), ikh) + mmt(mm(k, r), k)  # P = (I − K H) P (I − K H)' + K R K'
    return mv(k, y), 0.5 * (p_new + p_new.T), nis


def error_dynamics(c_nb: F64, f_n: F64, lat_rad: float) -> F64:
    """The 15 × 15 ``F`` of the error state (module docstring), at attitude ``c_nb``, specific
    force ``f_n`` (NED) and latitude ``lat_rad``. A plain function so a peer filter (the ekf
    bench's filterpy run) can be stepped with exactly the model this filter uses."""
    w0, w2 = OMEGA_IE_RADPS * math.cos(lat_rad), -OMEGA_IE_RADPS * math.sin(lat_rad)  # ω_ie, w1 = 0
    terms = (*np.asarray(c_nb, dtype=float).ravel().tolist(), *np.asarray(f_n, dtype=float).tolist(), w0, w2)
    return _write_error_blocks(_F15.copy(), 3, 6, 9, 12, terms)  # δṗ = δv: in the template


def _write_error_blocks(f: F64, v: int, a: int, ba: int, bg: int, terms: tuple[float, ...]) -> F64:
    """The error model's input-dependent entries written into ``f`` (returned), for velocity
    error rows ``v``, attitude error rows/columns ``a`` and the accelerometer and gyro bias
    columns ``ba``, ``bg`` (ekf15's and the feedback corrector's layouts): ``δv̇ = [f_n×] φ + C
    δb_a``, ``φ̇ = −[ω_ie×] φ − C δb_g``; ``terms``: :func:`_frame_terms`'s. Skew's entries and
    the sign flips of −skew (signed zeros too) as floats; the rest of ``f`` is left as it is."""
    c = ((terms[0], terms[1], terms[2]), (terms[3], terms[4], terms[5]), (terms[6], terms[7], terms[8]))
    f0, f1, f2, w0, w2 = terms[9], terms[10], terms[11], terms[12], terms[13]
    sk = ((0.0, -f2, f1), (f2, 0.0, -f0), (-f1, f0, 0.0))
    om = ((-0.0, w2, -0.0), (-w2, -0.0, w0), (0.0, -w0, -0.0))
    for i in range(3):
        for j in range(3):
            f[v + i, a + j] = sk[i][j]
            f[v + i, ba + j] = c[i][j]
            f[a + i, a + j] = om[i][j]
            f[a + i, bg + j] = -c[i][j]
    return f


def _kron3(x: float, y: float, z: float) -> F64:
    """:func:`kron_eye3` of ``(x, y, z)`` from floats (``0.0 * w``'s signed zeros too), in a
    form :mod:`hil.runtime.jit` compiles."""
    out = np.empty((3, 9))
    w = (x, y, z)
    for r in range(3):
        for b in range(3):
            for k in range(3):
                out[r, 3 * b + k] = w[k] if b == r else 0.0 * w[k]
    return out


_Floats14 = tuple[float, ...]  # C_nb (9), the specific force (3), ω_ie N and D


def _frame_terms(
    qw: float, qx: float, qy: float, qz: float, sx: float, sy: float, sz: float, dt: float, lat: float
) -> _Floats14:  # fmt: skip
    """What an error model's F takes of the INS at a prediction, on floats: ``C_nb`` row by row,
    the specific force ``C s / dt`` (NED; ``s`` the body Δv summed over ``dt``) in einsum's order
    for a 3-vector (:func:`_mv3`'s), and ω_ie's N and D components at latitude ``lat``."""
    c0, c1, c2, c3, c4, c5, c6, c7, c8 = c_nb_floats(qw, qx, qy, qz)
    bx, by, bz = sx / dt, sy / dt, sz / dt
    f0 = (c0 * bx + c2 * bz) + c1 * by + 0.0
    f1 = (c3 * bx + c5 * bz) + c4 * by + 0.0
    f2 = (c6 * bx + c8 * bz) + c7 * by + 0.0
    w0, w2 = OMEGA_IE_RADPS * math.cos(lat), -OMEGA_IE_RADPS * math.sin(lat)  # ω_ie, w1 = 0
    return c0, c1, c2, c3, c4, c5, c6, c7, c8, f0, f1, f2, w0, w2


def write_dynamics(
    f: F64,
    qw: float, qx: float, qy: float, qz: float,
    sx: float, sy: float, sz: float,
    tx: float, ty: float, tz: float,
    dt: float,
    lat: float,
    gyro_cal: bool,
    accel_cal: bool,
    i_acal: int,
) -> tuple[float, float, float]:  # fmt: skip
    """F's changing entries written into ``f`` (the template of every state,
    :func:`dynamics_template`) from the INS attitude ``q``, latitude and the body Δv ``s`` and Δθ
    ``t`` summed over ``dt``, as :func:`error_dynamics`, :func:`gyro_cal_augmented` and
    :func:`accel_cal_augmented` build them; returns the specific force ``C s / dt`` (NED). One
    call where the blocks, their products and copies cost most of a prediction in Python; its
    Python form is the reference, :mod:`hil.runtime.jit` compiles it (with the compiled products)
    and checks it against it when loaded."""
    terms = _frame_terms(qw, qx, qy, qz, sx, sy, sz, dt, lat)
    _write_error_blocks(f, 3, 6, 9, 12, terms)
    bx, by, bz = sx / dt, sy / dt, sz / dt
    c = np.empty((3, 3))
    for i in range(3):
        for j in range(3):
            c[i, j] = terms[3 * i + j]
    if gyro_cal:  # φ̇ += −C N(ω̄) δe
        g = mm(c, _kron3(tx / dt, ty / dt, tz / dt))
        for i in range(3):
            for j in range(9):
                f[6 + i, 15 + j] = -g[i, j]
    if accel_cal:  # δv̇ += C N(f̄_b) δe_a
        a = mm(c, _kron3(bx, by, bz))
        for i in range(3):
            for j in range(9):
                f[3 + i, i_acal + j] = a[i, j]
    return terms[9], terms[10], terms[11]


def dynamics_template(gyro_cal: bool, accel_cal: bool, slow_w_radps: float) -> F64:
    """F of a state layout with its constant entries (δṗ = δv, the slow states' oscillator),
    built as :func:`error_dynamics` and the ``*_augmented`` functions build them, C-contiguous:
    what :func:`write_dynamics` writes the rest into, at every prediction."""
    zero3, zero = np.zeros((3, 3)), np.zeros(3)
    f = _F15.copy()
    if gyro_cal:
        f = gyro_cal_augmented(f, zero3, zero)
    if accel_cal:
        f = accel_cal_augmented(f, zero3, zero)
    if slow_w_radps:
        f = slow_augmented(f, slow_w_radps)
    return np.ascontiguousarray(f)


def transition(f: F64, dt_s: float) -> F64:
    """``Φ = I + F Δ + (F Δ)²/2``: at Δ = 10 ms the neglected terms are O((FΔ)³) ~ 1e-9."""
    fd = f * dt_s
    n = f.shape[0]
    eye = _EYE15 if n == 15 else np.eye(n)
    return eye + fd + 0.5 * mm(fd, fd)


def covariance_step(f: F64, dt_s: float, p: F64, qc: F64) -> tuple[F64, F64]:
    """``(Φ, Φ P Φ' + Q_c Δ)`` with ``Φ = transition(F, Δ)``: a covariance's prediction over Δ
    (ekf15's and the feedback corrector's). :mod:`hil.runtime.jit` puts a compiled twin with
    these bits in its place (:func:`hil.nav.kernels.covariance_step`)."""
    phi = transition(f, dt_s)
    return phi, mmt(mm(phi, p), phi) + qc * dt_s


def slow_augmented(f: F64, w_radps: float) -> F64:
    """``F`` with the GNSS slow-error states appended: ``δs̈ = −ω² δs`` per axis (a sine of
    angular frequency ω, the emulator's geometry component, which has no process noise)."""
    n = f.shape[0]
    out = np.zeros((n + 6, n + 6))
    out[:n, :n] = f
    out[n : n + 3, n + 3 : n + 6] = np.eye(3)
    out[n + 3 : n + 6, n : n + 3] = -(w_radps**2) * np.eye(3)
    return out


def gyro_cal_augmented(f: F64, c_nb: F64, w_b: F64) -> F64:
    """``F`` with the 9 gyro scale-factor/misalignment states appended after it:
    ``φ̇ += −C N(ω̄) δe`` with ``N(ω) = I₃ ⊗ ωᵀ`` (``δe`` is the error matrix row by row)."""
    n = f.shape[0]
    out = np.zeros((n + 9, n + 9))
    out[:n, :n] = f
    n_w = kron_eye3(w_b)  # (3, 9): E ω = N(ω) e
    out[6:9, n : n + 9] = -mm(c_nb, n_w)
    return out


def accel_cal_augmented(f: F64, c_nb: F64, f_b: F64) -> F64:
    """``F`` with the 9 accelerometer scale-factor/misalignment states appended after it:
    ``δv̇ += C N(f̄_b) δe_a`` (the specific force's error enters as the bias's does)."""
    n = f.shape[0]
    out = np.zeros((n + 9, n + 9))
    out[:n, :n] = f
    out[3:6, n : n + 9] = mm(c_nb, kron_eye3(f_b))
    return out


def bias_walk_psd(sigma: float, corr_s: float, rate_rw: float = 0.0) -> float:
    """Spectral density of a bias error's random walk: the wander's 2σ²/τ (module docstring)
    plus the sensor's rate random walk. Written so that ``rate_rw = 0`` gives the same float as
    ``2 * sigma**2 / corr_s`` (recordings made before the rate random walk rerun bit-exact)."""
    q = 2 * sigma**2 / corr_s
    return q + rate_rw**2 if rate_rw else q


class Ekf15(Estimator):
    """The 3-D error-state EKF as an :class:`~hil.estimators.base.Estimator`.

    Default noise figures are the rig's ``tactical`` IMU preset (HG1700 class).
    """

    def __init__(
        self,
        name: str,
        init: InitialState,
        accel_vrw_mps_rts: float = 0.03 / _RTH,
        gyro_arw_rad_rts: float = 0.125 * _DEG / _RTH,
        accel_bias_sigma_mps2: float = 50e-6 * 9.80665,
        gyro_bias_sigma_radps: float = 0.35 * _DEG / 3600.0,
        bias_corr_s: float = 300.0,
        p0_accel_bias_mps2: float = 1e-3 * 9.80665,
        p0_gyro_bias_radps: float = 1.0 * _DEG / 3600.0,
        p0_pos_m: float = 3.0,
        p0_vel_mps: float = 0.3,
        p0_tilt_rad: float = 2e-3,
        p0_yaw_rad: float = 1e-2,
        cov_every: int = 4,
        gate_chi2: float = 16.27,
        max_rejects: int = 10,
        gnss_slow_sigma_m: float = 0.0,
        gnss_slow_period_s: float = 12660.0,
        lever_arm_b_m: tuple[float, float, float] = (0.0, 0.0, 0.0),
        gyro_cal_sigma: tuple[float, float] = (0.0, 0.0),
        accel_cal_sigma: tuple[float, float] = (0.0, 0.0),
        heading_small_angle_rad: float = 0.1,
        heading_align_sigma_rad: float = 0.1,
        heading_align_window_s: float = 5.0,
        accel_bias_corr_s: float | None = None,
        accel_bias_rw_mps2_rts: float = 0.0,
        gyro_bias_rw_radps_rts: float = 0.0,
    ) -> None:
        self.name = name
        self._init = init
        self._origin = (init.origin_lat_rad, init.origin_lon_rad, init.origin_alt_m)
        self.ins = strapdown_from_initial(init)
        self.b_a = np.zeros(3)
        self.b_g = np.zeros(3)
        self.p = np.diag(
            np.square(
                [p0_pos_m] * 3
                + [p0_vel_mps] * 3
                + [p0_tilt_rad, p0_tilt_rad, p0_yaw_rad]
                + [p0_accel_bias_mps2] * 3  # turn-on bias, the preset's 1 mg
                + [p0_gyro_bias_radps] * 3  # and 1 deg/h
            )
        )
        self._qc = np.diag(
            [0.0] * 3
            + [accel_vrw_mps_rts**2] * 3
            + [gyro_arw_rad_rts**2] * 3
            + [bias_walk_psd(accel_bias_sigma_mps2, accel_bias_corr_s or bias_corr_s, accel_bias_rw_mps2_rts)]
            * 3
            + [bias_walk_psd(gyro_bias_sigma_radps, bias_corr_s, gyro_bias_rw_radps_rts)] * 3
        )
        # Optional states after the 15 (module docstring): gyro scale factor/misalignment [δe (9)],
        # then the GNSS slow error [δs (3), δṡ (3)]. Neither has process noise.
        sf_sigma, ma_sigma = (float(v) for v in gyro_cal_sigma)
        self._cal = sf_sigma > 0.0 or ma_sigma > 0.0
        self.e_hat = np.zeros((3, 3))  # estimated gyro error matrix E (scale factor + misalignment)
        asf_sigma, ama_sigma = (float(v) for v in accel_cal_sigma)
        self._acal = asf_sigma > 0.0 or ama_sigma > 0.0
        self.ea_hat = np.zeros((3, 3))  # and the accelerometers' E_a
        self._i_acal = 24 if self._cal else 15
        self._slow_w = 2.0 * math.pi / gnss_slow_period_s if gnss_slow_sigma_m > 0.0 else 0.0
        self._i_slow = self._i_acal + (9 if self._acal else 0)
        self.n = self._i_slow + (6 if self._slow_w else 0)
        self.s_hat = np.zeros(3)  # estimated slow error of the GNSS position, m
        self.sd_hat = np.zeros(3)  # and its rate, m/s
        p0 = np.zeros((self.n, self.n))
        p0[:15, :15] = self.p
        for on, i, sf, ma in (
            (self._cal, 15, sf_sigma, ma_sigma),
            (self._acal, self._i_acal, asf_sigma, ama_sigma),
        ):
            if on:
                e_var = np.full((3, 3), max(ma, 1e-9) ** 2)
                np.fill_diagonal(e_var, max(sf, 1e-9) ** 2)
                p0[i : i + 9, i : i + 9] = np.diag(e_var.ravel())
        if self._slow_w:
            sig, w, i = gnss_slow_sigma_m, self._slow_w, self._i_slow
            p0[i : i + 3, i : i + 3] = np.eye(3) * sig**2  # a sine of RMS σ: s and ṡ/ω uncorrelated, both σ²
            p0[i + 3 : i + 6, i + 3 : i + 6] = np.eye(3) * (sig * w) ** 2
        self.p = p0
        qc = np.zeros((self.n, self.n))
        qc[:15, :15] = self._qc
        self._qc = qc
        self._f = dynamics_template(self._cal, self._acal, self._slow_w)
        lever = np.asarray(lever_arm_b_m, dtype=float)
        self._lever: F64 | None = lever if np.any(lever) else None
        self._w_b = np.zeros(3)  # corrected body rate of the last IMU step, rad/s (for the lever arm)
        self.cov_every = int(cov_every)
        self.gate_chi2 = gate_chi2
        self.max_rejects = max_rejects
        self._pending_dt = 0.0
        self._pending_dv_b = [0.0, 0.0, 0.0]  # Σ Δv, Σ Δθ of the block (floats: added at IMU rate)
        self._pending_dth_b = [0.0, 0.0, 0.0]
        self._pending_n = 0
        self._stamp_ns = init.stamp_ns
        self._nav = to_nav_state(self.ins, init)
        self._nav_dirty = False
        self._nis_pos = 0.0
        self._nis_vel = 0.0
        self._rejects = 0
        self._consecutive = 0
        self._fused = 0
        # Heading beyond the small-angle range (module docstring, "Heading"): GNSS updates hold the
        # heading part back and an in-motion alignment over a short window of fixes resets it.
        self.heading_small_angle_rad = float(heading_small_angle_rad)
        self.heading_align_sigma_rad = float(heading_align_sigma_rad)
        self._align_window_ns = round(heading_align_window_s * 1e9)
        self._sf_sum = np.zeros(2)  # Σ horizontal specific force × dt in NED (estimated attitude), m/s
        self._align: deque[tuple[int, F64, F64, float]] = deque()  # (t_ns, v_gnss NE, Σ f dt, σ_v)
        self._heading_held = 0  # GNSS fixes whose heading part was held back
        self._heading_resets = 0
        self._f_b = (0.0, 0.0, -G0_MPS2)  # mean body specific force of the last covariance block

    # -- propagation ---------------------------------------------------------------------------
    def on_imu(self, imu: ImuInput, ins: NavState) -> None:
        self.on_imu_block(ImuBlock.of(imu, ins))

    def on_imu_block(self, block: ImuBlock) -> None:
        """The block's intervals in order, the runs between two covariance predictions each in
        one call of the strapdown loop (compiled when the kernels are); Ê Δθ and Ê_a Δv in
        einsum's order for a 3-vector (``_mv3``)."""
        if not len(block):
            return
        run, rows = block.strapdown_run()
        bias = (*self.b_g.tolist(), *self.b_a.tolist())
        no_cal = strapdown.NO_CALIBRATION
        e_g = tuple(self.e_hat.ravel().tolist()) if self._cal else no_cal
        e_a = tuple(self.ea_hat.ravel().tolist()) if self._acal else no_cal
        rate = self._cal or self._lever is not None  # only these need the body rate
        for start, stop in block.runs(self.cov_every, self._pending_n):
            pv, pt = self._pending_dv_b, self._pending_dth_b
            st, sum_dv, sum_dth, self._pending_dt = run(
                tuple(self.ins), rows, start, stop, bias, e_g, e_a, tuple(pv), tuple(pt),
                self._pending_dt, self._cal, self._acal, rate,
            )  # fmt: skip
            self.ins = _new_state(StrapdownState, st)
            self._pending_dv_b, self._pending_dth_b = list(sum_dv), list(sum_dth)
            self._pending_n += stop - start
            if self._pending_n >= self.cov_every:
                self._propagate_covariance()
        if rate:  # the body rate of the last interval
            dt, tx, ty, tz = block.rows[-1][:4]
            tx, ty, tz = tx - bias[0] * dt, ty - bias[1] * dt, tz - bias[2] * dt
            if self._cal:
                ex, ey, ez = _mv3(self.e_hat.tolist(), tx, ty, tz)
                tx, ty, tz = tx - ex, ty - ey, tz - ez
            self._w_b = np.array((tx / dt, ty / dt, tz / dt))
        self._stamp_ns = block.stamps_ns[-1]
        self._nav_dirty = True

    def _propagate_covariance(self) -> None:
        if self._pending_n == 0:
            return
        dt = self._pending_dt
        ins, pv, pt = self.ins, self._pending_dv_b, self._pending_dth_b
        # F of every state, written into the one matrix kept for it
        fn0, fn1, _ = write_dynamics(
            self._f, *ins.q, pv[0], pv[1], pv[2], pt[0], pt[1], pt[2], dt, ins.lat_rad,
            self._cal, self._acal, self._i_acal,
        )  # fmt: skip
        self._f_b = (pv[0] / dt, pv[1] / dt, pv[2] / dt)
        s0, s1 = self._sf_sum.tolist()
        self._sf_sum = np.array((s0 + fn0 * dt, s1 + fn1 * dt))
        if self._slow_w:
            c, s = math.cos(self._slow_w * dt), math.sin(self._slow_w * dt)
            self.s_hat, self.sd_hat = (
                c * self.s_hat + s / self._slow_w * self.sd_hat,
                -s * self._slow_w * self.s_hat + c * self.sd_hat,
            )
        self._predict_over(self._f, dt)
        if self.p[8, 8] > _YAW_VAR_MAX:  # beyond a uniform heading's: shrink yaw's row and column
            c = math.sqrt(_YAW_VAR_MAX / float(self.p[8, 8]))
            self.p[8, :] *= c
            self.p[:, 8] *= c
        self._pending_dt = 0.0
        self._pending_dv_b = [0.0, 0.0, 0.0]
        self._pending_dth_b = [0.0, 0.0, 0.0]
        self._pending_n = 0

    def _predict_over(self, f: F64, dt_s: float) -> None:
        """``P = Φ P Φ' + Q_d`` over ``dt_s`` with error dynamics ``f`` (``Q_d = Q_c Δ``; the error
        state itself is zero between fixes: closed loop). The ekf bench's filterpy peer
        overrides it."""
        _phi, self.p = covariance_step(f, dt_s, self.p, self._qc)

    def _update(self, y: F64, h: F64, r: F64) -> F64:
        """One measurement update of ``P`` for innovation ``y``; returns the error-state increment."""
        ddx, self.p, _ = kf_update(self.p, y, h, r)
        return ddx

    def _update_holding(self, y: F64, h: F64, r: F64, z: F64) -> F64:
        """Schmidt (consider) update: the optimal gain less its component along the orthonormal
        columns of ``z``, so those directions of the error state are neither corrected nor have
        their variance reduced; Joseph form, which is exact for any gain."""
        ph = mmt(self.p, h)
        k = mm(ph, inv(mm(h, ph) + r))
        k = k - mm(z, mm(z.T, k))
        ikh = np.eye(self.n) - mm(k, h)
        p_new = mmt(mm(ikh, self.p), ikh) + mmt(mm(k, r), k)
        self.p = 0.5 * (p_new + p_new.T)
        return mv(k, y)

    def heading_held(self) -> bool:
        """Whether GNSS updates hold heading back: its σ is beyond the range where the linear
        ``[f×]φ`` coupling holds, so a velocity mismatch would be read as heading it is not."""
        return self.heading_small_angle_rad > 0.0 and float(self.p[8, 8]) > self.heading_small_angle_rad**2

    def _heading_directions(self) -> F64:
        """Orthonormal columns spanning the heading part of the error state: yaw, the gyro bias
        about the vertical (body axes) and, with calibration states, the gyro error matrix's
        rows weighted by that axis (the rate error about the vertical)."""
        u = self.ins.c_nb()[2, :]  # NED down in body axes: C_nb' e_D
        z = np.zeros((self.n, 5 if self._cal else 2))
        z[8, 0] = 1.0
        z[12:15, 1] = u
        if self._cal:
            for j in range(3):  # δω_u = Σ_i u_i Σ_j δE_ij ω_j: e is E row by row
                z[15 + j : 24 : 3, 2 + j] = u
        return z

    def _align_heading(self, gnss: GnssInput) -> None:
        """In-motion heading alignment while heading is held: from each earlier fix within the
        window to this one, the change of GNSS velocity against the integrated specific force in
        NED. A heading error δ rotates the one into the other, whatever its size, so
        ``δ = atan2(a × b, a · b)``; when for the most certain start the specific force moved the
        velocity enough for δ to be known to ``heading_align_sigma_rad``, the yaw is reset to it
        (PX4's yaw reset: σ set, yaw decorrelated from the other states)."""
        v = np.asarray(gnss.vel_ned_mps, float)[:2]
        sv = float(max(np.asarray(gnss.vel_sigma_mps, float)[:2]))
        win = self._align
        win.append((gnss.stamp_ns, v, self._sf_sum.copy(), sv))
        while win and gnss.stamp_ns - win[0][0] > self._align_window_ns:
            win.popleft()
        d = self.p.diagonal()
        drift_var = 9.81 * 9.81 * max(d[6], d[7]) + max(d[9], d[10])  # tilt and accel-bias σ², (m/s²)²
        best: tuple[float, float, F64, F64] | None = None  # (var, var_dv, a, b) of the best start
        for t0, v0, sf0, sv0 in win:  # every start in the window: the most certain δ wins
            a = self._sf_sum - sf0  # INS: ∫ C f dt, horizontal
            b = v - v0  # GNSS: Δv (gravity and Coriolis add < 0.02 m/s over the window: neglected)
            a2 = float(a[0] * a[0] + a[1] * a[1])
            if a2 <= 0.0:
                continue
            t = (gnss.stamp_ns - t0) * 1e-9
            var_dv = sv * sv + sv0 * sv0 + drift_var * t * t
            var = var_dv / a2 + float(d[14]) * (0.5 * t) ** 2  # + the z-gyro bias's drift over it
            if best is None or var < best[0]:
                best = (var, var_dv, a, b)
        if best is None or best[0] > self.heading_align_sigma_rad**2:
            return
        var, var_dv, a, b = best
        # A rotation keeps the length: a window whose velocity change is not the specific force's
        # (a GNSS jump, a spoofed velocity) aligns nothing.
        if (math.hypot(float(a[0]), float(a[1])) - math.hypot(float(b[0]), float(b[1]))) ** 2 > 9.0 * var_dv:
            return
        delta = math.atan2(float(a[0] * b[1] - a[1] * b[0]), float(a[0] * b[0] + a[1] * b[1]))
        q_d = np.array([math.cos(0.5 * delta), 0.0, 0.0, math.sin(0.5 * delta)])
        self.ins = self.ins.replace(q_nb=quat_normalise(quat_multiply(q_d, self.ins.q_nb)))
        self.p[8, :] = 0.0
        self.p[:, 8] = 0.0
        self.p[8, 8] = var
        self._nav_dirty = True
        # The velocity and position were integrated with the wrong heading: reset them to the fix.
        pos_tov, vel_pred, _, _ = self._predict_fix(gnss)
        dx = np.zeros(self.n)
        dx[0:3] = pos_tov + self.s_hat - gnss.pos_ned_m
        dx[3:6] = vel_pred + self.sd_hat - gnss.vel_ned_mps
        self._inject(dx)
        self.p[0:6, :] = 0.0
        self.p[:, 0:6] = 0.0
        self.p[0:6, 0:6] = np.diag(np.square(np.concatenate([gnss.pos_sigma_m, gnss.vel_sigma_mps])))
        self._heading_resets += 1
        win.clear()

    # -- GNSS fusion -----------------------------------------------------------------------------
    def on_gnss(self, gnss: GnssInput, ins: NavState) -> None:
        self._propagate_covariance()
        pos_tov, vel_pred, h_pos, h_vel = self._predict_fix(gnss)
        dx = np.zeros(self.n)
        z_hold = self._heading_directions() if self.heading_held() else None
        if z_hold is not None:
            self._heading_held += 1
        else:
            self._align.clear()
        for h, y, sig, kind in (
            (h_pos, pos_tov + self.s_hat - gnss.pos_ned_m, gnss.pos_sigma_m, "pos"),
            (h_vel, vel_pred + self.sd_hat - gnss.vel_ned_mps, gnss.vel_sigma_mps, "vel"),
        ):
            r = np.diag(np.square(np.asarray(sig, float)))
            y = y - mv(h, dx)  # sequential: innovation against the already-updated error state
            s = mmt(mm(h, self.p), h) + r
            nis = dot(y, solve(s, y))
            if kind == "pos":
                self._nis_pos = nis
            else:
                self._nis_vel = nis
            if nis > self.gate_chi2:
                self._rejects += 1
                self._consecutive += 1
                if self._consecutive <= self.max_rejects:
                    continue
                # Locked out: trust the measurement again, with the covariance opened up.
                idx = np.nonzero(h[:, :6].any(axis=0))[0]
                self.p[idx, idx] += y * y
            else:
                self._consecutive = 0
            dx = dx + (self._update(y, h, r) if z_hold is None else self._update_holding(y, h, r, z_hold))
            self._fused += 1
        self._inject(dx)
        if z_hold is not None:  # every fix: the gate's S assumes the small angles this is not
            self._align_heading(gnss)

    def reset_to_gnss(self, gnss: GnssInput, accel_ned: tuple[float, float, float] | None = None) -> None:
        """Re-initialise on a fix the fusion's gate reacquired (hil.fusion.gnss_gate, rule 4).
        The INS is beyond what a linear update can pull back (a saturated IMU leaves tens of
        degrees of attitude error) and the covariance does not know it, so, as PX4's EKF2 resets
        to GNSS after its no-aiding timeout: tilt levelled from the specific force, heading from
        the ground track, position and velocity from the fix, and the covariance of all three set
        to what those sources know (decorrelated from the biases, which keep theirs).
        ``accel_ned``: the vehicle's acceleration from the GNSS velocity (the fusion's), which the
        levelling takes out of the specific force (a turn's would read as a tilt)."""
        self._propagate_covariance()
        q, tracked = levelled_attitude(self._f_b, gnss.vel_ned_mps, self.ins.q_nb, accel_ned=accel_ned)
        yaw_var = RESET_YAW_SIGMA_RAD**2 if tracked else _YAW_VAR_MAX  # no track: the heading kept, unknown
        self.ins = self.ins.replace(q_nb=quat_normalise_floats(*q.tolist()))
        self._nav_dirty = True
        pos_tov, vel_pred, _, _ = self._predict_fix(gnss)  # with the new attitude's lever arm
        dx = np.zeros(self.n)
        dx[0:3] = pos_tov + self.s_hat - gnss.pos_ned_m
        dx[3:6] = vel_pred + self.sd_hat - gnss.vel_ned_mps
        self._inject(dx)
        tilt_var = RESET_TILT_SIGMA_RAD**2
        sig = np.concatenate([gnss.pos_sigma_m, gnss.vel_sigma_mps])
        self.p[0:9, :] = 0.0
        self.p[:, 0:9] = 0.0
        self.p[0:9, 0:9] = np.diag([*np.square(sig).tolist(), tilt_var, tilt_var, yaw_var])
        self._consecutive = 0
        self._align.clear()

    def _predict_fix(self, gnss: GnssInput) -> tuple[F64, F64, F64, F64]:
        """The fix as the INS predicts it (antenna position at the time of validity, antenna
        velocity) and the measurement matrices of position and velocity."""
        nav = self._current_nav()
        lag_s = (gnss.stamp_ns - self._stamp_ns) * 1e-9
        pos_tov = nav.pos_ned_m + nav.vel_ned_mps * lag_s  # INS at the GNSS time of validity
        vel_pred = nav.vel_ned_mps
        h_pos = np.zeros((3, self.n))
        h_pos[:, 0:3] = np.eye(3)
        h_vel = np.zeros((3, self.n))
        h_vel[:, 3:6] = np.eye(3)
        if self._lever is not None:  # the fix is of the antenna: p + Ĉ l, v + Ĉ (ω̂ × l)
            c_nb = self.ins.c_nb()
            arm_n = mv(c_nb, self._lever)
            arm_rate_n = mv(c_nb, cross(self._w_b, self._lever))
            pos_tov = pos_tov + arm_n
            vel_pred = vel_pred + arm_rate_n
            h_pos[:, 6:9] = skew(arm_n)
            h_vel[:, 6:9] = skew(arm_rate_n)
            h_vel[:, 12:15] = -mm(c_nb, skew(self._lever))  # ω̂ = ω + δb_g (+ N(ω) δe)
            if self._cal:
                h_vel[:, 15:24] = mm(h_vel[:, 12:15], kron_eye3(self._w_b))
        if self._slow_w:  # z = truth + s + w: predicted z = INS + ŝ, so y = δp + δs − w
            i = self._i_slow
            h_pos[:, i : i + 3] = np.eye(3)
            h_vel[:, i + 3 : i + 6] = np.eye(3)
        return pos_tov, vel_pred, h_pos, h_vel

    def _inject(self, dx: F64) -> None:
        """Closed loop: feed δx back into the strapdown and biases, then δx ← 0."""
        if not dx.any():
            return
        s = self.ins
        # on floats, the numpy forms' operations in their order (a fix: 103 -> 24 µs)
        dp_d, dv_n, dv_e, dv_d, phi_x, phi_y, phi_z = dx[2:9].tolist()
        r_m, r_n = radii_of_curvature_one(s.lat_rad)
        # numpy scalars divided, as before: a zero divisor of a diverged state gives inf, not a raise
        lat = s.lat_rad - dx[0] / (r_m + s.alt_m)
        lon = s.lon_rad - dx[1] / ((r_n + s.alt_m) * math.cos(s.lat_rad))
        alt = s.alt_m + dp_d  # δp_D = −δh
        vn, ve, vd = s.vel
        vel = (vn - dv_n, ve - dv_e, vd - dv_d)
        # C_true = (I + [φ×]) C_est: rotate the NED side by +φ
        q = quat_normalise_floats(*quat_multiply_floats(*quat_from_rotvec_floats(phi_x, phi_y, phi_z), *s.q))
        self.ins = s.replace(lat_rad=lat, lon_rad=lon, alt_m=alt, vel_ned_mps=vel, q_nb=q)
        self.b_a = self.b_a + dx[9:12]
        self.b_g = self.b_g + dx[12:15]
        if self._cal:
            self.e_hat = self.e_hat + dx[15:24].reshape(3, 3)
        if self._acal:
            i = self._i_acal
            self.ea_hat = self.ea_hat + dx[i : i + 9].reshape(3, 3)
        if self._slow_w:
            i = self._i_slow
            self.s_hat = self.s_hat - dx[i : i + 3]
            self.sd_hat = self.sd_hat - dx[i + 3 : i + 6]
        self._nav_dirty = True

    # -- outputs ---------------------------------------------------------------------------------
    def _current_nav(self) -> NavState:
        if self._nav_dirty:
            self._nav = LazyNavState(self.ins, self._origin)  # to_nav_state's values, built on read
            self._nav_dirty = False
        return self._nav

    def solution(self) -> NavState:
        nav = self._current_nav()
        sd = np.sqrt(self.p.diagonal()[0:9])  # one ufunc call for the three σ (elementwise: same bits)
        return FloatNavState(*nav_floats(nav), sd[0:3], sd[3:6], sd[6:9])

    def health(self) -> dict[str, float]:
        return {
            "nis_pos": self._nis_pos,
            "nis_vel": self._nis_vel,
            "gnss_rejected": float(self._rejects),
            "gnss_fused": float(self._fused),
            "accel_bias_norm_mps2": norm(self.b_a),
            "gyro_bias_norm_radps": norm(self.b_g),
            "heading_held": 1.0 if self.heading_held() else 0.0,
            "heading_resets": float(self._heading_resets),
        }

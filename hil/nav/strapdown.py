"""Strapdown INS mechanisation in NED: the free inertial solution every estimator corrects.

Per IMU interval k (increments Δθ_k, Δv_k over dt), after Savage (1998) and Shin (2005):

    attitude   φ_k = Δθ_k + 1/12 Δθ_{k−1} × Δθ_k                          (coning)
               q_nb,k = q(−ζ_k) ⊗ q_nb,k−1 ⊗ q(φ_k),  ζ_k = ω_in^n(k−½) dt
    velocity   Δv_sf^b = Δv_k + ½ Δθ_k × Δv_k + 1/12 (Δθ_{k−1} × Δv_k + Δv_{k−1} × Δθ_k)
                                                                          (rotation + sculling)
               v_k = v_{k−1} + [I − ½ ζ×] C_nb,k−1 Δv_sf^b + [g_n − (2 ω_ie + ω_en) × v]_{k−½} dt
    position   h_k = h − v̄_D dt,  L_k = L + v̄_N dt/(R_M + h̄),  λ_k = λ + v̄_E dt/((R_N + h̄) cos L̄)

Mid-interval (k−½) quantities come from a first-order prediction of velocity and position, so
no older state than k−1 is needed. WGS84 normal gravity, Earth rate and transport rate come from
:mod:`hil.nav.earth` (the same model the truth generator uses).

The numerics are plain Python floats, and so is the state (:class:`StrapdownState`, 16 floats):
one core, :func:`_step`, is shared by :func:`strapdown_step` (one interval, for the live
services; :func:`strapdown_step_f` with the increments as floats, the fusion's per-IMU path) and
:func:`strapdown_run` (a whole array, for the offline executor), so all give bit-identical results.
The fusion runs :func:`_step` compiled from this same source (:mod:`hil.runtime.jit`), with the same bits.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from functools import cached_property
from operator import itemgetter
from typing import Any

import numpy as np

from hil.nav.earth import (
    _K_SOMIGLIANA,
    _M_RATIO,
    A_M,
    E2,
    GAMMA_E_MPS2,
    OMEGA_IE_RADPS,
    F,
    lla_to_ned,
    lla_to_ned_floats,
)
from hil.nav.types import F64, InitialState, NavState

_State = tuple[float, ...]  # lat, lon, h, vn, ve, vd, qw, qx, qy, qz, pθx, pθy, pθz, pvx, pvy, pvz


class StrapdownState(tuple[float, ...]):
    """INS state after an interval, as 16 plain floats (a tuple, so the core unpacks it at once):
    ``lat, lon, h, vN, vE, vD, qw, qx, qy, qz`` then the last increments ``Δθ (3), Δv (3)``
    (coning/sculling memory). Immutable: :meth:`replace` gives a changed copy.

    Plain floats rather than small numpy arrays because the fusion steps several of these per
    IMU sample and building and unpacking 3- and 4-element arrays cost more than the mechanisation
    itself. ``vel_ned_mps``, ``q_nb`` and the ``prev_*`` increments read as new arrays.
    """

    __slots__ = ()

    def __new__(
        cls,
        lat_rad: float,
        lon_rad: float,
        alt_m: float,
        vel_ned_mps: Any,
        q_nb: Any,
        prev_dtheta_b_rad: Any = (0.0, 0.0, 0.0),
        prev_dvel_b_mps: Any = (0.0, 0.0, 0.0),
    ) -> StrapdownState:
        v, q, p, u = (
            [float(x) for x in vel_ned_mps],
            [float(x) for x in q_nb],
            [float(x) for x in prev_dtheta_b_rad],
            [float(x) for x in prev_dvel_b_mps],
        )
        if (len(v), len(q), len(p), len(u)) != (3, 4, 3, 3):
            raise ValueError("a strapdown state is vel (3,), q_nb (4,), prev_dtheta (3,), prev_dvel (3,)")
        return _new(cls, (float(lat_rad), float(lon_rad), float(alt_m), *v, *q, *p, *u))

    @classmethod
    def of(cls, t: _State) -> StrapdownState:
        """From the 16 floats in the module's order (no checks: the core's own tuples)."""
        return _new(cls, t)

    lat_rad = property(itemgetter(0), doc="geodetic latitude, rad")
    lon_rad = property(itemgetter(1), doc="longitude, rad")
    alt_m = property(itemgetter(2), doc="ellipsoidal height, m")

    @property
    def vel(self) -> tuple[float, float, float]:
        """v_NED, m/s, as floats."""
        return self[3], self[4], self[5]

    @property
    def q(self) -> tuple[float, float, float, float]:
        """q_nb [w, x, y, z] as floats."""
        return self[6], self[7], self[8], self[9]

    @property
    def vel_ned_mps(self) -> F64:
        return np.array(self[3:6])

    @property
    def q_nb(self) -> F64:
        return np.array(self[6:10])

    @property
    def prev_dtheta_b_rad(self) -> F64:
        return np.array(self[10:13])

    @property
    def prev_dvel_b_mps(self) -> F64:
        return np.array(self[13:16])

    def c_nb(self) -> F64:
        """C_nb (3, 3): :func:`hil.nav.attitude.quat_to_dcm` of ``q_nb``, the same operations
        on floats (so the same bits) without the array round trip."""
        return np.array(c_nb_floats(self[6], self[7], self[8], self[9])).reshape(3, 3)

    def replace(
        self,
        lat_rad: float | None = None,
        lon_rad: float | None = None,
        alt_m: float | None = None,
        vel_ned_mps: Any = None,
        q_nb: Any = None,
    ) -> StrapdownState:
        """A copy with the given parts changed (``dataclasses.replace`` of the former dataclass)."""
        t = list(self)
        if lat_rad is not None:
            t[0] = float(lat_rad)
        if lon_rad is not None:
            t[1] = float(lon_rad)
        if alt_m is not None:
            t[2] = float(alt_m)
        if vel_ned_mps is not None:
            t[3:6] = [float(x) for x in vel_ned_mps]
        if q_nb is not None:
            t[6:10] = [float(x) for x in q_nb]
        if len(t) != 16:
            raise ValueError("vel_ned_mps must have 3 elements and q_nb 4")
        return _new(StrapdownState, t)

    def __repr__(self) -> str:
        return (
            f"StrapdownState(lat_rad={self[0]!r}, lon_rad={self[1]!r}, alt_m={self[2]!r}, "
            f"vel_ned_mps={list(self[3:6])!r}, q_nb={list(self[6:10])!r}, "
            f"prev_dtheta_b_rad={list(self[10:13])!r}, prev_dvel_b_mps={list(self[13:16])!r})"
        )


_new = tuple.__new__
_tuple = tuple  # a plain tuple of the state: what the compiled _step (hil.runtime.jit) takes


def c_nb_floats(qw: float, qx: float, qy: float, qz: float) -> tuple[float, ...]:
    """C_nb row by row (9 floats) of q_nb: quat_to_dcm's expressions in its order."""
    return (
        qw * qw + qx * qx - qy * qy - qz * qz,
        2.0 * (qx * qy - qw * qz),
        2.0 * (qx * qz + qw * qy),
        2.0 * (qx * qy + qw * qz),
        qw * qw - qx * qx + qy * qy - qz * qz,
        2.0 * (qy * qz - qw * qx),
        2.0 * (qx * qz - qw * qy),
        2.0 * (qy * qz + qw * qx),
        qw * qw - qx * qx - qy * qy + qz * qz,
    )


@dataclass(frozen=True)
class StrapdownTrack:
    """The solution after each recorded step of :func:`strapdown_run`, (m,) / (m, 3) / (m, 4)."""

    step: F64  # index of the interval after which the row was taken (1-based)
    lat_rad: F64
    lon_rad: F64
    alt_m: F64
    vel_ned_mps: F64
    q_nb: F64


def _gravity(lat: float, h: float) -> float:
    s2 = math.sin(lat) ** 2
    g0 = GAMMA_E_MPS2 * (1.0 + _K_SOMIGLIANA * s2) / math.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 / A_M * (1.0 + F + _M_RATIO - 2.0 * F * s2) * h + 3.0 * h * h / (A_M * A_M))


# constant subexpressions of earth.radii_of_curvature_one and _gravity, as Python evaluates
# them there (left to right)
_AM_1ME2 = A_M * (1.0 - E2)
_G_2A = 2.0 / A_M
_G_1 = 1.0 + F + _M_RATIO
_G_2F = 2.0 * F
_AA = A_M * A_M
_2W = 2.0 * OMEGA_IE_RADPS
_M2W = -2.0 * OMEGA_IE_RADPS


def _sq(x: float) -> float:
    """``x**2`` as Python computes it: the C library's ``pow(x, 2)``, which is not ``x * x`` in
    about one value in a thousand (the last bit). A compiler turns ``x**2`` into ``x * x``, so
    :mod:`hil.runtime.jit` compiles this name to a call of ``pow`` itself."""
    return x**2


def _rotvec_quat(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    a2 = x * x + y * y + z * z
    if a2 < 1e-16:
        c, k = 1.0 - a2 / 8.0, 0.5 - a2 / 48.0
    else:
        a = math.sqrt(a2)
        c, k = math.cos(0.5 * a), math.sin(0.5 * a) / a
    return c, k * x, k * y, k * z


def _step(st: _State, tx: float, ty: float, tz: float, ux: float, uy: float, uz: float, dt: float) -> _State:
    """One interval; see the module docstring for the equations. Pure floats for speed."""
    lat, lon, h, vn, ve, vd, qw, qx, qy, qz, px, py, pz, pux, puy, puz = st
    # C_nb,k−1
    c00 = qw * qw + qx * qx - qy * qy - qz * qz
    c01 = 2.0 * (qx * qy - qw * qz)
    c02 = 2.0 * (qx * qz + qw * qy)
    c10 = 2.0 * (qx * qy + qw * qz)
    c11 = qw * qw - qx * qx + qy * qy - qz * qz
    c12 = 2.0 * (qy * qz - qw * qx)
    c20 = 2.0 * (qx * qz - qw * qy)
    c21 = 2.0 * (qy * qz + qw * qx)
    c22 = qw * qw - qx * qx - qy * qy + qz * qz

    # Δv_sf^b = Δv + ½ Δθ×Δv + 1/12 (Δθ_{k−1}×Δv + Δv_{k−1}×Δθ)
    sx = ux + 0.5 * (ty * uz - tz * uy) + (py * uz - pz * uy + puy * tz - puz * ty) / 12.0
    sy = uy + 0.5 * (tz * ux - tx * uz) + (pz * ux - px * uz + puz * tx - pux * tz) / 12.0
    sz = uz + 0.5 * (tx * uy - ty * ux) + (px * uy - py * ux + pux * ty - puy * tx) / 12.0
    fn = c00 * sx + c01 * sy + c02 * sz
    fe = c10 * sx + c11 * sy + c12 * sz
    fd = c20 * sx + c21 * sy + c22 * sz

    # first-order prediction to mid-interval with the full g and Coriolis/centripetal terms:
    # cheaper shortcuts here (constant g, no v²/R) leave a ~1e-9 m/s² vertical bias that the
    # unstable vertical channel grows to centimetres in an hour
    # (earth.radii_of_curvature_one and _gravity written out, sharing sin L and √(1 − e² sin²L):
    # the same operations)
    s0 = math.sin(lat)
    s2 = _sq(s0)
    w = 1.0 - E2 * s2
    sw = math.sqrt(w)
    rmh0, rnh0 = _AM_1ME2 / (w * sw) + h, A_M / sw + h
    g_0 = (
        GAMMA_E_MPS2
        * (1.0 + _K_SOMIGLIANA * s2)
        / sw
        * (1.0 - _G_2A * (_G_1 - _G_2F * s2) * h + 3.0 * h * h / _AA)
    )
    o_n = _2W * math.cos(lat) + ve / rnh0
    o_e = -vn / rmh0
    o_d = _M2W * s0 - ve * math.tan(lat) / rnh0
    vn_m = vn + 0.5 * (fn - (o_e * vd - o_d * ve) * dt)
    ve_m = ve + 0.5 * (fe - (o_d * vn - o_n * vd) * dt)
    vd_m = vd + 0.5 * (fd + (g_0 - (o_n * ve - o_e * vn)) * dt)
    hdt = 0.5 * dt
    lat_m = lat + hdt * vn_m / rmh0
    h_m = h - hdt * vd_m

    # mid-interval Earth quantities: radii, gravity, ω_ie, ω_en
    sl, cl = math.sin(lat_m), math.cos(lat_m)
    s2 = _sq(sl)
    w = 1.0 - E2 * s2
    sw = math.sqrt(w)
    r_m, r_n = _AM_1ME2 / (w * sw), A_M / sw
    tl = sl / cl
    g = (
        GAMMA_E_MPS2
        * (1.0 + _K_SOMIGLIANA * s2)
        / sw
        * (1.0 - _G_2A * (_G_1 - _G_2F * s2) * h_m + 3.0 * h_m * h_m / _AA)
    )
    rmh, rnh = r_m + h_m, r_n + h_m
    wie_n, wie_d = OMEGA_IE_RADPS * cl, -OMEGA_IE_RADPS * sl
    wen_n, wen_e, wen_d = ve_m / rnh, -vn_m / rmh, -ve_m * tl / rnh
    zx, zy, zz = (wie_n + wen_n) * dt, wen_e * dt, (wie_d + wen_d) * dt
    ox, oy, oz = 2.0 * wie_n + wen_n, wen_e, 2.0 * wie_d + wen_d

    # v_k = v + [I − ½ζ×] f + [g − (2ω_ie + ω_en) × v_mid] dt
    vn_k = vn + fn - 0.5 * (zy * fd - zz * fe) - (oy * vd_m - oz * ve_m) * dt
    ve_k = ve + fe - 0.5 * (zz * fn - zx * fd) - (oz * vn_m - ox * vd_m) * dt
    vd_k = vd + fd - 0.5 * (zx * fe - zy * fn) + (g - (ox * ve_m - oy * vn_m)) * dt

    # position: trapezoidal velocity, radii at mid-interval
    vn_b, ve_b = 0.5 * (vn + vn_k), 0.5 * (ve + ve_k)
    h_k = h - 0.5 * (vd + vd_k) * dt
    lat_k = lat + vn_b * dt / rmh
    lon_k = lon + ve_b * dt / (rnh * cl)

    # attitude: n-frame rotation ζ over the interval from the mean velocity
    zx = (wie_n + ve_b / rnh) * dt
    zy = (-vn_b / rmh) * dt
    zz = (wie_d - ve_b * tl / rnh) * dt
    # φ = Δθ + 1/12 Δθ_{k−1} × Δθ
    fx = tx + (py * tz - pz * ty) / 12.0
    fy = ty + (pz * tx - px * tz) / 12.0
    fz = tz + (px * ty - py * tx) / 12.0
    bw, bx, by, bz = _rotvec_quat(fx, fy, fz)
    nw, nx, ny, nz = _rotvec_quat(-zx, -zy, -zz)
    # q ⊗ q_bb
    aw = qw * bw - qx * bx - qy * by - qz * bz
    ax = qw * bx + qx * bw + qy * bz - qz * by
    ay = qw * by - qx * bz + qy * bw + qz * bx
    az = qw * bz + qx * by - qy * bx + qz * bw
    # q_nn ⊗ (…)
    rw = nw * aw - nx * ax - ny * ay - nz * az
    rx = nw * ax + nx * aw + ny * az - nz * ay
    ry = nw * ay - nx * az + ny * aw + nz * ax
    rz = nw * az + nx * ay - ny * ax + nz * aw
    inv = 1.0 / math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    if rw < 0.0:
        inv = -inv
    return (
        lat_k,
        lon_k,
        h_k,
        vn_k,
        ve_k,
        vd_k,
        rw * inv,
        rx * inv,
        ry * inv,
        rz * inv,
        tx,
        ty,
        tz,
        ux,
        uy,
        uz,
    )


def _corrected_run(
    st: _State,
    rows: Any,
    start: int,
    stop: int,
    bias: tuple[float, float, float, float, float, float],
    e_g: tuple[float, float, float, float, float, float, float, float, float],
    e_a: tuple[float, float, float, float, float, float, float, float, float],
    sum_dv: tuple[float, float, float],
    sum_dth: tuple[float, float, float],
    sum_dt: float,
    gyro_cal: bool,
    accel_cal: bool,
    body_rate: bool,
) -> tuple[_State, tuple[float, float, float], tuple[float, float, float], float]:
    """Steps ``rows[start:stop]`` (``dt, Δθ, Δv`` each) with the sensor biases, and with
    ``gyro_cal``/``accel_cal`` the calibration matrices ``E`` (rows of 3), taken out; the sums of
    the corrected Δv, Δθ (with ``body_rate``) and dt carried on. An INS of its own's IMU steps
    between two of its covariance predictions (ekf15's, a feedback INS's), in one call, the same
    float operations in the same order as their per-interval ``on_imu``/``propagate``.

    ``rows``: Python's, a list of 7-tuples of floats (never numpy scalars: ``x**2`` of one is not
    the C library's ``pow``); compiled (:mod:`hil.runtime.jit`, with the compiled ``_step``), the
    block's (n, 7) array. A caller reads the name once and compares it with
    :data:`_PY_CORRECTED_RUN` to know which it holds (the kernels may be put in place meanwhile).
    """
    bgx, bgy, bgz, bax, bay, baz = bias
    g0, g1, g2, g3, g4, g5, g6, g7, g8 = e_g
    a0, a1, a2, a3, a4, a5, a6, a7, a8 = e_a
    pvx, pvy, pvz = sum_dv
    ptx, pty, ptz = sum_dth
    for i in range(start, stop):
        r = rows[i]
        dt = r[0]
        tx, ty, tz = r[1] - bgx * dt, r[2] - bgy * dt, r[3] - bgz * dt
        if gyro_cal:  # E Δθ in einsum's order for a 3-vector (hil.estimators.ekf15._mv3)
            ex = (g0 * tx + g2 * tz) + g1 * ty + 0.0
            ey = (g3 * tx + g5 * tz) + g4 * ty + 0.0
            ez = (g6 * tx + g8 * tz) + g7 * ty + 0.0
            tx, ty, tz = tx - ex, ty - ey, tz - ez
        ux, uy, uz = r[4] - bax * dt, r[5] - bay * dt, r[6] - baz * dt
        if accel_cal:
            ex = (a0 * ux + a2 * uz) + a1 * uy + 0.0
            ey = (a3 * ux + a5 * uz) + a4 * uy + 0.0
            ez = (a6 * ux + a8 * uz) + a7 * uy + 0.0
            ux, uy, uz = ux - ex, uy - ey, uz - ez
        st = _step(st, tx, ty, tz, ux, uy, uz, dt)
        pvx += ux
        pvy += uy
        pvz += uz
        if body_rate:
            ptx += tx
            pty += ty
            ptz += tz
        sum_dt += dt
    return st, (pvx, pvy, pvz), (ptx, pty, ptz), sum_dt


_PY_CORRECTED_RUN = _corrected_run
NO_CALIBRATION = (0.0,) * 9  # the run's E where none is estimated


def strapdown_step(s: StrapdownState, dtheta_b_rad: Any, dvel_b_mps: Any, dt_s: float) -> StrapdownState:
    """Advance by one IMU interval (increments (3,), interval dt_s). Pure: ``s`` is not changed."""
    tx, ty, tz = (float(x) for x in dtheta_b_rad)
    ux, uy, uz = (float(x) for x in dvel_b_mps)
    return _new(StrapdownState, _step(_tuple(s), tx, ty, tz, ux, uy, uz, float(dt_s)))


def strapdown_step_f(
    s: StrapdownState, tx: float, ty: float, tz: float, ux: float, uy: float, uz: float, dt_s: float
) -> StrapdownState:
    """:func:`strapdown_step` with the increments as Python floats (the fusion's per-IMU path)."""
    return _new(StrapdownState, _step(_tuple(s), tx, ty, tz, ux, uy, uz, dt_s))


def strapdown_run(
    s: StrapdownState,
    dtheta_b_rad: F64,
    dvel_b_mps: F64,
    dt_s: float,
    record_every: int = 1,
    vertical_hold: bool = False,
) -> tuple[StrapdownState, StrapdownTrack]:
    """Run many intervals ((n, 3) increments); record the solution every ``record_every`` steps.

    Same numbers as calling :func:`strapdown_step` n times. ``vertical_hold`` pins height and
    v_D to their initial values after every step — a perfect altimeter, for long free-INS tests
    of level motion: the free vertical channel diverges with an e-folding time √(R/2g) ≈ 9.5 min
    and, after a few Schuler periods, drags the horizontal channels with it.
    """
    th = np.asarray(dtheta_b_rad, dtype=float).tolist()
    dv = np.asarray(dvel_b_mps, dtype=float).tolist()
    st: _State = tuple(s)
    dt = float(dt_s)
    rows: list[_State] = []
    idx: list[int] = []
    step = _step
    h0 = st[2]
    for k in range(len(th)):
        a, b = th[k], dv[k]
        st = step(st, a[0], a[1], a[2], b[0], b[1], b[2], dt)
        if vertical_hold:
            st = (st[0], st[1], h0, st[3], st[4], 0.0, *st[6:])
        if (k + 1) % record_every == 0:
            rows.append(st)
            idx.append(k + 1)
    arr = np.array(rows, dtype=float).reshape(-1, 16)
    track = StrapdownTrack(
        np.array(idx, dtype=float), arr[:, 0], arr[:, 1], arr[:, 2], arr[:, 3:6], arr[:, 6:10]
    )
    return StrapdownState.of(st), track


def strapdown_from_initial(init: InitialState) -> StrapdownState:
    """The INS aligned to the rig's initial state (no increment memory yet)."""
    return StrapdownState(init.lat_rad, init.lon_rad, init.alt_m, init.vel_ned_mps, init.q_nb)


def to_nav_state(s: StrapdownState, origin: InitialState | tuple[float, float, float]) -> NavState:
    """NavState with NED position relative to the origin (an InitialState or (lat, lon, alt))."""
    if isinstance(origin, InitialState):
        o = (origin.origin_lat_rad, origin.origin_lon_rad, origin.origin_alt_m)
    else:
        o = origin
    pos = lla_to_ned(s[0], s[1], s[2], o[0], o[1], o[2])
    return NavState(pos_ned_m=pos, vel_ned_mps=np.array(s[3:6]), q_nb=np.array(s[6:10]))


class LazyNavState(NavState):
    """:func:`to_nav_state` of a strapdown state, each part built when it is first read.

    The fusion hands the free INS to every estimator at every IMU step, and most of them read it
    only at a GNSS fix or an output: the NED position (an ECEF round trip) and the arrays are
    then built for one step in eight, with the same values :func:`to_nav_state` gives.
    """

    def __init__(self, s: StrapdownState, origin: tuple[float, float, float]) -> None:
        # a frozen dataclass: the fields are the properties below, the inputs go in __dict__
        d = self.__dict__
        d["_s"], d["_o"] = s, origin

    @cached_property
    def _pos_floats(self) -> tuple[float, float, float]:
        s, o = self._s, self._o
        return lla_to_ned_floats(s[0], s[1], s[2], o[0], o[1], o[2])

    @cached_property
    def pos_ned_m(self) -> F64:  # type: ignore[override]
        return np.array(self._pos_floats)  # lla_to_ned's array: the same values

    @cached_property
    def vel_ned_mps(self) -> F64:  # type: ignore[override]
        return np.array(self._s[3:6])

    @cached_property
    def q_nb(self) -> F64:  # type: ignore[override]
        return np.array(self._s[6:10])

    def floats(self) -> tuple[list[float], tuple[float, ...], tuple[float, ...]]:
        """Position, velocity and attitude as Python floats (the values of the arrays; the
        position without building its array)."""
        s = self._s
        return list(self._pos_floats), s[3:6], s[6:10]

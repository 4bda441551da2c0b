"""Output predictor: the estimators' state on the delayed fusion horizon, carried to the newest
IMU sample by the IMU increments in between (PX4 EKF2's scheme, with the full correction).

The estimators run ``lag`` behind the newest IMU sample, so that a GNSS fix arriving up to
``lag`` after its time of validity is still fused there, in the total order. What the rig
publishes is the state at the newest IMU sample: each estimator's horizon solution moved forward
by the motion the IMU measured since the horizon.

That motion is integrated once for all estimators, in body axes of the horizon (IMU
pre-integration): a running sum from an anchor sample of the rotation ``q`` (anchor <- body),
the velocity increment ``V`` and its integral ``P`` (both in anchor axes, without gravity), and
the time ``T``. Between the horizon entry ``a`` and the newest ``k``::

    ΔR = q_a* ⊗ q_k       Δv = R_aᵀ (V_k − V_a)       Δp = R_aᵀ (P_k − P_a − V_a ΔT)

and for an estimator at the horizon with attitude ``C`` (body -> NED), velocity ``v`` and
position ``p``::

    q ⊗ ΔR,   v + C Δv + g ΔT,   p + v ΔT + C Δp + ½ g ΔT²

Earth rate, transport rate and Coriolis are left out over the horizon (7e-5 rad/s: 4e-5 rad and
under a millimetre over 0.5 s), gravity is the normal gravity at the initial position, and the
NED position increment is added in the origin's tangent plane (at 10 km from the origin the
frames differ by 1.6 mrad: 2 cm on 15 m of motion). The horizon's σ is reported unchanged.

Every step is a function of the IMU samples in their order and of where the horizon is; both are
a function of the fusion's total order, so ``hil rerun`` computes the same bits. The anchor moves
to the horizon every ``REANCHOR_STEPS`` samples (a deterministic count), keeping the sums small.
"""

from __future__ import annotations

import math
from collections import deque
from collections.abc import Sequence

import numpy as np

from hil.nav.attitude import quat_multiply_floats as _qmul  # the Hamilton product on floats
from hil.nav.earth import _ecef_to_lla_one, ned_to_ecef_floats  # every solution's geodesy
from hil.nav.strapdown import _rotvec_quat  # the strapdown's own rotation-vector quaternion
from hil.nav.types import F64, NavState

REANCHOR_STEPS = 4096

# stamp, T, qw, qx, qy, qz, Vx, Vy, Vz, Px, Py, Pz
_Entry = tuple[int, float, float, float, float, float, float, float, float, float, float, float]
Vec3 = tuple[float, float, float]
Quat = tuple[float, float, float, float]
Motion = tuple[float, Quat, Vec3, Vec3]  # ΔT, ΔR, Δv, Δp


def _rot(qw: float, qx: float, qy: float, qz: float, x: float, y: float, z: float) -> Vec3:
    """R(q) v: the vector in body axes, in the frame ``q`` rotates into."""
    ww, xx, yy, zz = qw * qw, qx * qx, qy * qy, qz * qz
    return (
        (ww + xx - yy - zz) * x + 2.0 * (qx * qy - qw * qz) * y + 2.0 * (qx * qz + qw * qy) * z,
        2.0 * (qx * qy + qw * qz) * x + (ww - xx + yy - zz) * y + 2.0 * (qy * qz - qw * qx) * z,
        2.0 * (qx * qz - qw * qy) * x + 2.0 * (qy * qz + qw * qx) * y + (ww - xx - yy + zz) * z,
    )


def _rot_t(qw: float, qx: float, qy: float, qz: float, x: float, y: float, z: float) -> Vec3:
    """R(q)ᵀ v."""
    return _rot(qw, -qx, -qy, -qz, x, y, z)


def without_bias(dt: float, dq: Quat, dv: Vec3, dp: Vec3, bias: tuple[F64, F64]) -> tuple[Quat, Vec3, Vec3]:
    """The motion as the IMU without its biases ``b_g``, ``b_a`` would have measured it: to
    first order in the bias and in the rotation over the window (the pre-integration's bias
    Jacobians with the body axes held, as the window turns a few degrees at most)::

        ΔR ⊗ Exp(−b_g ΔT),   Δv − b_a ΔT + (f × b_g) ΔT²/2,   Δp − b_a ΔT²/2 + (f × b_g) ΔT³/6

    with ``f = Δv / ΔT`` the mean specific force (the tilt a gyro bias builds, seen by it)."""
    gx, gy, gz = np.asarray(bias[0], dtype=np.float64).tolist()
    ax, ay, az = np.asarray(bias[1], dtype=np.float64).tolist()
    if dt <= 0.0:
        return dq, dv, dp
    r = _unbiased(dt, *dq, *dv, *dp, gx, gy, gz, ax, ay, az)
    return r[0:4], r[4:7], r[7:10]


def _unbiased(
    dt: float,
    qw: float, qx: float, qy: float, qz: float,
    vx: float, vy: float, vz: float,
    px: float, py: float, pz: float,
    gx: float, gy: float, gz: float,
    ax: float, ay: float, az: float,
) -> tuple[float, float, float, float, float, float, float, float, float, float]:  # fmt: skip
    """:func:`without_bias` on floats (``dt`` > 0): ΔR, Δv, Δp as ten floats."""
    fx, fy, fz = vx / dt, vy / dt, vz / dt
    cx, cy, cz = fy * gz - fz * gy, fz * gx - fx * gz, fx * gy - fy * gx  # f × b_g
    t2, t3 = 0.5 * dt * dt, dt * dt * dt / 6.0
    ew, ex, ey, ez = _rotvec_quat(-gx * dt, -gy * dt, -gz * dt)
    rw, rx, ry, rz = _qmul(qw, qx, qy, qz, ew, ex, ey, ez)
    return (
        rw, rx, ry, rz,
        vx - ax * dt + cx * t2, vy - ay * dt + cy * t2, vz - az * dt + cz * t2,
        px - ax * t2 + cx * t3, py - ay * t2 + cy * t3, pz - az * t2 + cz * t3,
    )  # fmt: skip


def _advance(
    tt: float,
    qw: float, qx: float, qy: float, qz: float,
    vx: float, vy: float, vz: float,
    px: float, py: float, pz: float,
    tx: float, ty: float, tz: float,
    ux: float, uy: float, uz: float,
    dt_s: float,
) -> tuple[float, float, float, float, float, float, float, float, float, float, float]:  # fmt: skip
    """One IMU interval onto the running sums ``T, q, V, P`` (:meth:`OutputPredictor.step`'s
    arithmetic on floats; :mod:`hil.runtime.jit` compiles it)."""
    # the velocity increment with the rotation over the interval (first order)
    sx = ux + 0.5 * (ty * uz - tz * uy)
    sy = uy + 0.5 * (tz * ux - tx * uz)
    sz = uz + 0.5 * (tx * uy - ty * ux)
    dx, dy, dz = _rot(qw, qx, qy, qz, sx, sy, sz)
    nx, ny, nz = vx + dx, vy + dy, vz + dz
    px += (vx + 0.5 * dx) * dt_s
    py += (vy + 0.5 * dy) * dt_s
    pz += (vz + 0.5 * dz) * dt_s
    ew, ex, ey, ez = _rotvec_quat(tx, ty, tz)
    rw, rx, ry, rz = _qmul(qw, qx, qy, qz, ew, ex, ey, ez)
    inv = 1.0 / math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    return (tt + dt_s, rw * inv, rx * inv, ry * inv, rz * inv, nx, ny, nz, px, py, pz)


def _carry(
    pn: float, pe: float, pd: float,
    vn: float, ve: float, vd: float,
    qw: float, qx: float, qy: float, qz: float,
    dt: float,
    dqw: float, dqx: float, dqy: float, dqz: float,
    dvx: float, dvy: float, dvz: float,
    dpx: float, dpy: float, dpz: float,
    g: float,
    biased: bool,
    gx: float, gy: float, gz: float,
    ax: float, ay: float, az: float,
) -> tuple[float, float, float, float, float, float, float, float, float, float]:  # fmt: skip
    """A horizon state carried over the motion (:meth:`OutputPredictor.predict_floats`'s
    arithmetic on floats, the biases taken out first when ``biased`` and ``dt`` > 0; compiled by
    :mod:`hil.runtime.jit`): position, velocity, attitude as ten floats."""
    if biased and dt > 0.0:
        dqw, dqx, dqy, dqz, dvx, dvy, dvz, dpx, dpy, dpz = _unbiased(
            dt, dqw, dqx, dqy, dqz, dvx, dvy, dvz, dpx, dpy, dpz, gx, gy, gz, ax, ay, az
        )
    cvx, cvy, cvz = _rot(qw, qx, qy, qz, dvx, dvy, dvz)
    cpx, cpy, cpz = _rot(qw, qx, qy, qz, dpx, dpy, dpz)
    rw, rx, ry, rz = _qmul(qw, qx, qy, qz, dqw, dqx, dqy, dqz)
    inv = 1.0 / math.sqrt(rw * rw + rx * rx + ry * ry + rz * rz)
    if rw < 0.0:
        inv = -inv
    return (
        pn + vn * dt + cpx, pe + ve * dt + cpy, pd + vd * dt + cpz + 0.5 * g * dt * dt,
        vn + cvx, ve + cvy, vd + cvz + g * dt,
        rw * inv, rx * inv, ry * inv, rz * inv,
    )  # fmt: skip


#: the carry's bias operands of a stream without biases (its flag says so)
NO_BIAS = (0.0,) * 6


def bias_floats(bias: tuple[F64, F64] | None) -> tuple[float, ...] | None:
    """An estimator's IMU bias estimates (``b_g``, ``b_a``) as the six floats the carry takes
    (``b_g`` then ``b_a``: ``hil.estimators.base.imu_bias_floats_of`` gives them so)."""
    if bias is None:
        return None
    return (*np.asarray(bias[0], dtype=np.float64).tolist(), *np.asarray(bias[1], dtype=np.float64).tolist())


def carry_rows(
    rows: F64,
    dt: float,
    dqw: float, dqx: float, dqy: float, dqz: float,
    dvx: float, dvy: float, dvz: float,
    dpx: float, dpy: float, dpz: float,
    g: float,
    o0: float, o1: float, o2: float,
    c00: float, c01: float, c02: float,
    c10: float, c11: float, c12: float,
    c20: float, c21: float, c22: float,
) -> F64:  # fmt: skip
    """The fusion's solutions at one IMU sample in one call (compiled by :mod:`hil.runtime.jit`):
    each row ``[p, v, q, biased, b_g, b_a]`` (17) carried over the motion as
    :meth:`OutputPredictor.predict_floats` carries it, its latitude, longitude and height as
    :func:`hil.nav.earth.ned_to_lla_one` gives them for the origin ``o`` (ECEF) and ``c`` (its
    ``C_en`` by rows), and whether the ten carried numbers are finite (1.0) or not (0.0, the
    position not converted): (k, 14)."""
    k = rows.shape[0]
    out = np.empty((k, 14))
    still = dt == 0.0 and dqw == 1.0 and dqx == 0.0 and dqy == 0.0 and dqz == 0.0
    for i in range(k):
        r = rows[i]
        if still:  # no motion: the inputs as they are
            s = (
                float(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4]),
                float(r[5]), float(r[6]), float(r[7]), float(r[8]), float(r[9]),
            )  # fmt: skip
        else:
            s = _carry(
                float(r[0]), float(r[1]), float(r[2]), float(r[3]), float(r[4]),
                float(r[5]), float(r[6]), float(r[7]), float(r[8]), float(r[9]),
                dt, dqw, dqx, dqy, dqz, dvx, dvy, dvz, dpx, dpy, dpz, g, r[10] != 0.0,
                float(r[11]), float(r[12]), float(r[13]), float(r[14]), float(r[15]), float(r[16]),
            )  # fmt: skip
        finite = True
        for j in range(10):
            out[i, j] = s[j]
            if not math.isfinite(s[j]):
                finite = False
        lat, lon, h = math.nan, math.nan, math.nan
        if finite:
            x, y, z = ned_to_ecef_floats(
                s[0], s[1], s[2], o0, o1, o2, c00, c01, c02, c10, c11, c12, c20, c21, c22
            )
            lat, lon, h = _ecef_to_lla_one(x, y, z)
        out[i, 10], out[i, 11], out[i, 12] = lat, lon, h
        out[i, 13] = 1.0 if finite else 0.0
    return out


class OutputPredictor:
    """The IMU's motion from the fusion horizon to the newest sample, and states moved by it."""

    def __init__(self, stamp_ns: int, gravity_mps2: float) -> None:
        self.g = float(gravity_mps2)
        base: _Entry = (int(stamp_ns), 0.0, 1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
        # entries from the horizon's (first) to the newest sample's (last)
        self.entries: deque[_Entry] = deque([base])
        self.seqs: deque[int] = deque([-1])  # the IMU seq of each entry (the base's: -1)
        self._since_anchor = 0

    @property
    def newest_ns(self) -> int:
        return self.entries[-1][0]

    def step(self, stamp_ns: int, dtheta: Vec3, dvel: Vec3, dt_s: float, seq: int = -1) -> None:
        """One IMU interval ending at ``stamp_ns`` (the newest: stamps only increase here)."""
        e = self.entries[-1]
        new = _advance(
            e[1], e[2], e[3], e[4], e[5], e[6], e[7], e[8], e[9], e[10], e[11], *dtheta, *dvel, dt_s
        )
        self.entries.append((int(stamp_ns), *new))
        self.seqs.append(seq)
        self._since_anchor += 1
        if self._since_anchor >= REANCHOR_STEPS:
            self._reanchor()

    def horizon_at(self, stamp_ns: int) -> None:
        """The estimators have taken every IMU sample up to ``stamp_ns``: the horizon entry is
        the newest at or before it."""
        e = self.entries
        while len(e) >= 2 and e[1][0] <= stamp_ns:
            e.popleft()
            self.seqs.popleft()

    def seq_at(self, stamp_ns: int) -> int | None:
        """The seq of the sample held at exactly ``stamp_ns`` (None: none is): whether a sample
        arriving behind the newest is a copy of one integrated (a rare path: a linear scan)."""
        for entry, seq in zip(reversed(self.entries), reversed(self.seqs), strict=True):
            if entry[0] == stamp_ns:
                return seq
            if entry[0] < stamp_ns:
                return None
        return None

    def _reanchor(self) -> None:
        """Express every entry relative to the horizon's (same motion, smaller sums)."""
        a = self.entries[0]
        _s, ta, aw, ax, ay, az, avx, avy, avz, apx, apy, apz = a
        out: deque[_Entry] = deque()
        for s, tt, qw, qx, qy, qz, vx, vy, vz, px, py, pz in self.entries:
            dt = tt - ta
            q = _qmul(aw, -ax, -ay, -az, qw, qx, qy, qz)
            v = _rot_t(aw, ax, ay, az, vx - avx, vy - avy, vz - avz)
            p = _rot_t(aw, ax, ay, az, px - apx - avx * dt, py - apy - avy * dt, pz - apz - avz * dt)
            out.append((s, dt, *q, *v, *p))
        self.entries = out
        self._since_anchor = 0

    def motion(self) -> Motion:
        """(ΔT, ΔR as a quaternion, Δv, Δp) from the horizon to the newest sample, in body axes
        of the horizon."""
        a, k = self.entries[0], self.entries[-1]
        _s, ta, aw, ax, ay, az, avx, avy, avz, apx, apy, apz = a
        _s, tk, kw, kx, ky, kz, kvx, kvy, kvz, kpx, kpy, kpz = k
        dt = tk - ta
        dq = _qmul(aw, -ax, -ay, -az, kw, kx, ky, kz)
        dv = _rot_t(aw, ax, ay, az, kvx - avx, kvy - avy, kvz - avz)
        dp = _rot_t(aw, ax, ay, az, kpx - apx - avx * dt, kpy - apy - avy * dt, kpz - apz - avz * dt)
        return dt, dq, dv, dp

    def predict(self, nav: NavState, motion: Motion, bias: tuple[F64, F64] | None = None) -> NavState:
        """``nav`` (an estimator's solution at the horizon) moved to the newest sample; with
        ``bias`` (the gyro's and accelerometer's, body axes) removed from the motion first."""
        dt, dq, _, _ = motion
        if dt == 0.0 and dq == (1.0, 0.0, 0.0, 0.0):
            return nav
        pos, vel, q = self.predict_floats(
            np.asarray(nav.pos_ned_m, dtype=np.float64).tolist(),
            np.asarray(nav.vel_ned_mps, dtype=np.float64).tolist(),
            np.asarray(nav.q_nb, dtype=np.float64).tolist(),
            motion,
            bias_floats(bias),
        )
        return NavState(
            pos_ned_m=np.array(pos),
            vel_ned_mps=np.array(vel),
            q_nb=np.array(q),
            pos_sigma_m=nav.pos_sigma_m,
            vel_sigma_mps=nav.vel_sigma_mps,
            att_sigma_rad=nav.att_sigma_rad,
        )

    def predict_floats(
        self,
        pos: Sequence[float],
        vel: Sequence[float],
        q: Sequence[float],
        motion: Motion,
        bias: tuple[float, ...] | None = None,
    ) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        """:meth:`predict` on position, velocity and attitude as Python floats (the fusion's
        output path: no arrays built to be read back), ``bias`` as its six floats (``b_g`` then
        ``b_a``); the inputs come back as they are when there is no motion."""
        dt, dq, dv, dp = motion
        if dt == 0.0 and dq == (1.0, 0.0, 0.0, 0.0):
            return pos, vel, q
        r = _carry(*pos, *vel, *q, dt, *dq, *dv, *dp, self.g, bias is not None, *(bias or NO_BIAS))
        return r[0:3], r[3:6], r[6:10]

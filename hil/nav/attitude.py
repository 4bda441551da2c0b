"""Quaternions, DCMs and Euler angles, vectorised over leading axes.

Conventions: q = [w, x, y, z], Hamilton product, ``q_nb`` rotates body vectors into NED
(v_n = q_nb ⊗ v_b ⊗ q_nb*), Euler angles are aerospace ZYX (yaw ψ, then pitch θ, then roll φ),
given and returned as [roll, pitch, yaw] in radians.
"""

from __future__ import annotations

import math
from collections.abc import Sequence

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.nav.sensor_specs import G0_MPS2

F64 = NDArray[np.float64]


def quat_multiply(p: ArrayLike, q: ArrayLike) -> F64:
    """Hamilton product p ⊗ q, (..., 4)."""
    p = np.asarray(p, dtype=float)
    q = np.asarray(q, dtype=float)
    if p.shape == (4,) and q.shape == (4,):  # one pair (a fix's attitude reset): the same
        return np.array(quat_multiply_floats(*p.tolist(), *q.tolist()))  # products, on floats
    pw, px, py, pz = p[..., 0], p[..., 1], p[..., 2], p[..., 3]
    qw, qx, qy, qz = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    return np.stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ],
        axis=-1,
    )


def quat_conjugate(q: ArrayLike) -> F64:
    """q* (the inverse for a unit quaternion)."""
    q = np.asarray(q, dtype=float)
    return q * np.array([1.0, -1.0, -1.0, -1.0])


def quat_normalise(q: ArrayLike) -> F64:
    """Unit quaternion with a non-negative scalar part (one sign, so comparisons are simple)."""
    q = np.asarray(q, dtype=float)
    q = q / np.linalg.norm(q, axis=-1, keepdims=True)
    return np.where(q[..., :1] < 0.0, -q, q)


def quat_multiply_floats(
    aw: float, ax: float, ay: float, az: float, bw: float, bx: float, by: float, bz: float
) -> tuple[float, float, float, float]:
    """``quat_multiply`` of one pair on floats: its products in its order."""
    return (
        aw * bw - ax * bx - ay * by - az * bz,
        aw * bx + ax * bw + ay * bz - az * by,
        aw * by - ax * bz + ay * bw + az * bx,
        aw * bz + ax * by - ay * bx + az * bw,
    )


def quat_normalise_floats(w: float, x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """``quat_normalise`` of one quaternion on floats, the same bits: numpy's norm of four adds
    the squares in order (``tests/unit/test_nav_earth_attitude.py``)."""
    n = math.sqrt(((w * w + x * x) + y * y) + z * z)
    if n == 0.0:  # numpy's NaN where Python would raise
        return tuple(quat_normalise(np.array((w, x, y, z))).tolist())  # type: ignore[return-value]
    w, x, y, z = w / n, x / n, y / n, z / n
    return (-w, -x, -y, -z) if w < 0.0 else (w, x, y, z)


def quat_from_rotvec_floats(x: float, y: float, z: float) -> tuple[float, float, float, float]:
    """``quat_from_rotvec`` of one vector on floats, the same bits (its ``ang**2`` is numpy's
    square, ``ang * ang``; numpy's float64 sin and cos are libm's, as math's)."""
    ang = math.sqrt((x * x + y * y) + z * z)
    if ang == math.inf:  # numpy's NaN where math's sin and cos would raise
        return tuple(quat_from_rotvec(np.array((x, y, z))).tolist())  # type: ignore[return-value]
    half = 0.5 * ang
    k = 0.5 - ang * ang / 48.0 if ang < 1e-4 else math.sin(half) / ang
    return math.cos(half), k * x, k * y, k * z


def quat_from_rotvec(phi: ArrayLike) -> F64:
    """Quaternion of the rotation vector φ (axis × angle), exact, safe near zero."""
    phi = np.asarray(phi, dtype=float)
    ang = np.linalg.norm(phi, axis=-1, keepdims=True)
    half = 0.5 * ang
    # sin(|φ|/2)/|φ| by its series below 1e-4 rad, where the direct form loses digits
    small = ang < 1e-4
    k = np.where(small, 0.5 - ang**2 / 48.0, np.sin(half) / np.where(small, 1.0, ang))
    return np.concatenate([np.cos(half), k * phi], axis=-1)


def quat_to_rotvec(q: ArrayLike) -> F64:
    """Rotation vector (..., 3) of a unit quaternion, angle in [0, π]."""
    q = quat_normalise(q)
    v = q[..., 1:]
    s = np.linalg.norm(v, axis=-1, keepdims=True)
    ang = 2.0 * np.arctan2(s, q[..., :1])
    k = np.where(s < 1e-12, 2.0, ang / np.where(s < 1e-12, 1.0, s))
    return k * v


def quat_to_dcm(q: ArrayLike) -> F64:
    """C (..., 3, 3) with v_n = C v_b for q = q_nb."""
    q = np.asarray(q, dtype=float)
    w, x, y, z = q[..., 0], q[..., 1], q[..., 2], q[..., 3]
    c = np.empty((*q.shape[:-1], 3, 3))
    c[..., 0, 0] = w * w + x * x - y * y - z * z
    c[..., 0, 1] = 2.0 * (x * y - w * z)
    c[..., 0, 2] = 2.0 * (x * z + w * y)
    c[..., 1, 0] = 2.0 * (x * y + w * z)
    c[..., 1, 1] = w * w - x * x + y * y - z * z
    c[..., 1, 2] = 2.0 * (y * z - w * x)
    c[..., 2, 0] = 2.0 * (x * z - w * y)
    c[..., 2, 1] = 2.0 * (y * z + w * x)
    c[..., 2, 2] = w * w - x * x - y * y + z * z
    return c


def dcm_to_quat(c: ArrayLike) -> F64:
    """Unit quaternion of a rotation matrix (Shepperd's method, branch per element)."""
    c = np.asarray(c, dtype=float)
    tr = c[..., 0, 0] + c[..., 1, 1] + c[..., 2, 2]
    cand = np.stack(
        [
            np.stack(
                [
                    1.0 + tr,
                    c[..., 2, 1] - c[..., 1, 2],
                    c[..., 0, 2] - c[..., 2, 0],
                    c[..., 1, 0] - c[..., 0, 1],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    c[..., 2, 1] - c[..., 1, 2],
                    1.0 + 2 * c[..., 0, 0] - tr,
                    c[..., 0, 1] + c[..., 1, 0],
                    c[..., 0, 2] + c[..., 2, 0],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    c[..., 0, 2] - c[..., 2, 0],
                    c[..., 0, 1] + c[..., 1, 0],
                    1.0 + 2 * c[..., 1, 1] - tr,
                    c[..., 1, 2] + c[..., 2, 1],
                ],
                axis=-1,
            ),
            np.stack(
                [
                    c[..., 1, 0] - c[..., 0, 1],
                    c[..., 0, 2] + c[..., 2, 0],
                    c[..., 1, 2] + c[..., 2, 1],
                    1.0 + 2 * c[..., 2, 2] - tr,
                ],
                axis=-1,
            ),
        ],
        axis=-2,
    )
    diag = np.stack([tr, c[..., 0, 0], c[..., 1, 1], c[..., 2, 2]], axis=-1)
    i = np.argmax(diag, axis=-1)
    q = np.take_along_axis(cand, i[..., None, None], axis=-2)[..., 0, :]
    return quat_normalise(q)


def euler_to_quat(euler_rad: ArrayLike) -> F64:
    """q_nb from [roll, pitch, yaw] (ZYX)."""
    e = np.asarray(euler_rad, dtype=float)
    hr, hp, hy = 0.5 * e[..., 0], 0.5 * e[..., 1], 0.5 * e[..., 2]
    cr, sr = np.cos(hr), np.sin(hr)
    cp, sp = np.cos(hp), np.sin(hp)
    cy, sy = np.cos(hy), np.sin(hy)
    return np.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        axis=-1,
    )


def euler_to_dcm(euler_rad: ArrayLike) -> F64:
    """C_nb (..., 3, 3) from [roll, pitch, yaw] (ZYX)."""
    e = np.asarray(euler_rad, dtype=float)
    cr, sr = np.cos(e[..., 0]), np.sin(e[..., 0])
    cp, sp = np.cos(e[..., 1]), np.sin(e[..., 1])
    cy, sy = np.cos(e[..., 2]), np.sin(e[..., 2])
    c = np.empty((*e.shape[:-1], 3, 3))
    c[..., 0, 0] = cp * cy
    c[..., 0, 1] = -cr * sy + sr * sp * cy
    c[..., 0, 2] = sr * sy + cr * sp * cy
    c[..., 1, 0] = cp * sy
    c[..., 1, 1] = cr * cy + sr * sp * sy
    c[..., 1, 2] = -sr * cy + cr * sp * sy
    c[..., 2, 0] = -sp
    c[..., 2, 1] = sr * cp
    c[..., 2, 2] = cr * cp
    return c


def quat_to_euler(q: ArrayLike) -> F64:
    """[roll, pitch, yaw] (ZYX) of q_nb; yaw in (−π, π]."""
    c = quat_to_dcm(q)
    roll = np.arctan2(c[..., 2, 1], c[..., 2, 2])
    pitch = -np.arcsin(np.clip(c[..., 2, 0], -1.0, 1.0))
    yaw = np.arctan2(c[..., 1, 0], c[..., 0, 0])
    return np.stack([roll, pitch, yaw], axis=-1)


def euler_rates_to_body_rate(euler_rad: ArrayLike, euler_rate_radps: ArrayLike) -> F64:
    """ω_nb^b from Euler angles and their rates (ZYX kinematics).

    p = φ̇ − ψ̇ sinθ,  q = θ̇ cosφ + ψ̇ sinφ cosθ,  r = −θ̇ sinφ + ψ̇ cosφ cosθ
    """
    e = np.asarray(euler_rad, dtype=float)
    d = np.asarray(euler_rate_radps, dtype=float)
    cr, sr = np.cos(e[..., 0]), np.sin(e[..., 0])
    cp, sp = np.cos(e[..., 1]), np.sin(e[..., 1])
    return np.stack(
        [
            d[..., 0] - d[..., 2] * sp,
            d[..., 1] * cr + d[..., 2] * sr * cp,
            -d[..., 1] * sr + d[..., 2] * cr * cp,
        ],
        axis=-1,
    )


def rotate(q: ArrayLike, v: ArrayLike) -> F64:
    """q ⊗ v ⊗ q* for vectors (..., 3), via the DCM (cheaper than two products)."""
    c = quat_to_dcm(q)
    v = np.asarray(v, dtype=float)
    return c[..., :, 0] * v[..., None, 0] + c[..., :, 1] * v[..., None, 1] + c[..., :, 2] * v[..., None, 2]


def attitude_error_rad(q_est: ArrayLike, q_true: ArrayLike) -> F64:
    """Rotation vector of q_est ⊗ q_true*, NED axes: the small-angle tilt/heading error."""
    return quat_to_rotvec(quat_multiply(q_est, quat_conjugate(q_true)))


# A re-initialisation from GNSS after an IMU fault (ekf15's ``reset_to_gnss``, the fusion's free
# INS, the feedback INS): the tilt levelled from the specific force is off by the horizontal
# acceleration over g (0.1 rad: a 1 m/s² manoeuvre); the heading taken from the ground track by
# the crab or sideslip angle (0.2 rad: beyond the small-angle bound, so held and aligned in motion
# as a heading of unknown size is), from a track of at least this speed
RESET_TILT_SIGMA_RAD = 0.1
RESET_YAW_SIGMA_RAD = 0.2
RESET_TRACK_MIN_SPEED_MPS = 5.0


# the acceleration a reset levels against: the GNSS velocity's least-squares rate over the fixes of
# the last RESET_ACCEL_SPAN_NS, taken when it stands out of its own noise (RESET_ACCEL_SIGNIFICANCE
# of its σ: a 10 Hz receiver's 0.2 m/s velocity noise is 2.8 m/s² between two fixes, 0.2 m/s² over a
# second), else a = 0: unaccelerated, the mean specific force levels the body exactly
RESET_ACCEL_SPAN_NS = 1_000_000_000
RESET_ACCEL_SIGNIFICANCE = 3.0


def velocity_rate(
    fixes: Sequence[tuple[int, Sequence[float]]], vel_sigma_mps: Sequence[float], at_ns: int | None = None
) -> tuple[float, float, float] | None:
    """The acceleration shown by GNSS velocities ``(stamp_ns, vel_ned)`` (oldest first), at
    ``at_ns`` (default the last fix's stamp): each axis's least-squares slope -- the mean over the
    fixes, half their span late -- with its horizontal part turned on by the track's turn rate to
    ``at_ns`` (in a 12 °/s turn the mean lags 6°: 0.5 m/s² of its 5 m/s²). An acceleration that
    changed within the fixes (a fit whose residuals stand out of the velocity noise:
    ``_changed``) is taken again from the newer half of them, down to three. None with fewer than
    two fixes, when they span no time, or when no axis's slope stands ``RESET_ACCEL_SIGNIFICANCE``
    σ (from ``vel_sigma_mps`` and the fixes' spread in time) out of zero."""
    while True:
        fit = _velocity_fit(fixes, vel_sigma_mps)
        if fit is None or len(fixes) < 6 or not fit[2]:
            break
        fixes = fixes[len(fixes) // 2 :]
    if fit is None:
        return None
    a, turn_rate, _changed, significant, tm = fit
    if not significant:
        return None
    if turn_rate is not None:
        t0 = fixes[-1][0]
        turn = turn_rate * (((t0 if at_ns is None else at_ns) - t0) * 1e-9 - tm)
        c, s_ = math.cos(turn), math.sin(turn)
        a = [c * a[0] - s_ * a[1], s_ * a[0] + c * a[1], a[2]]
    return (a[0], a[1], a[2])


def _velocity_fit(
    fixes: Sequence[tuple[int, Sequence[float]]], vel_sigma_mps: Sequence[float]
) -> tuple[list[float], float | None, bool, bool, float] | None:
    """The least-squares line through each axis's velocities: its slopes, the track's turn rate
    (None below ``RESET_TRACK_MIN_SPEED_MPS``), whether the residuals say the acceleration changed
    (an axis's χ² beyond its dof by ``4 sqrt(2 dof)``: in a turn at 12 °/s over a second the
    curvature stays within it), whether a slope is significant, and the fixes' mean time (s, from
    the last). None with fewer than two fixes or none spread in time."""
    n = len(fixes)
    if n < 2:
        return None
    t0 = fixes[-1][0]
    ts = [(t - t0) * 1e-9 for t, _ in fixes]
    tm = sum(ts) / n
    stt = sum((t - tm) ** 2 for t in ts)
    if stt <= 0.0:
        return None

    def line(values: list[float]) -> tuple[float, float]:
        vm = sum(values) / n
        slope = sum((t - tm) * (v - vm) for t, v in zip(ts, values, strict=True)) / stt
        return slope, sum((v - vm - slope * (t - tm)) ** 2 for t, v in zip(ts, values, strict=True))

    a, changed, significant = [], False, False
    dof = n - 2
    for axis in range(3):
        slope, rss = line([float(v[axis]) for _, v in fixes])
        sigma = float(vel_sigma_mps[axis])
        if dof > 0 and sigma > 0.0 and rss / (sigma * sigma) > dof + 4.0 * math.sqrt(2.0 * dof):
            changed = True
        if abs(slope) > RESET_ACCEL_SIGNIFICANCE * sigma / math.sqrt(stt):
            significant = True
        a.append(slope)
    turn_rate = None
    if all(math.hypot(float(v[0]), float(v[1])) >= RESET_TRACK_MIN_SPEED_MPS for _, v in fixes):
        track = [math.atan2(float(v[1]), float(v[0])) for _, v in fixes]
        unwrapped = [track[0]]
        for x in track[1:]:
            unwrapped.append(unwrapped[-1] + _wrap(x - unwrapped[-1]))
        turn_rate = line(unwrapped)[0]
    return a, turn_rate, changed, significant, tm


def levelled_attitude(
    f_b: tuple[float, float, float],
    vel_ned: ArrayLike,
    q_nb: ArrayLike,
    min_track_speed_mps: float = RESET_TRACK_MIN_SPEED_MPS,
    accel_ned: tuple[float, float, float] | None = None,
) -> tuple[F64, bool]:
    """q_nb re-initialised from what an INS can trust after an IMU fault: tilt levelled from the
    specific force, heading from the ground track (``vel_ned``) at ``min_track_speed_mps`` and
    above, else the heading ``q_nb`` has; and whether the heading came from the track.

    Levelled, ``f_b`` is taken for the body's ``-g``: true unaccelerated, 28° of roll off in a
    coordinated turn (f_b then lies along the body's z axis whatever the bank). ``accel_ned``,
    the vehicle's acceleration (the GNSS velocity's rate), gives the specific force the body
    feels, ``a - g`` in NED: roll and pitch are those that turn ``f_b`` onto it at this heading
    (``_tilt_onto``); without it, ``a = 0``."""
    vn, ve = float(np.asarray(vel_ned)[0]), float(np.asarray(vel_ned)[1])
    tracked = math.hypot(vn, ve) >= min_track_speed_mps
    yaw = math.atan2(ve, vn) if tracked else float(quat_to_euler(np.asarray(q_nb))[2])
    fx, fy, fz = f_b
    if accel_ned is None:
        roll, pitch = math.atan2(-fy, -fz), math.atan2(fx, math.hypot(fy, fz))
    else:
        roll, pitch = _tilt_onto(f_b, accel_ned, yaw)
    return euler_to_quat([roll, pitch, yaw]), tracked


def _tilt_onto(
    f_b: tuple[float, float, float], accel_ned: tuple[float, float, float], yaw: float
) -> tuple[float, float]:
    """Roll and pitch (ZYX Euler, at ``yaw``) that turn the body's specific force ``f_b`` onto
    the direction of ``a - g`` in NED: ``C_nb f_b = f_n`` with ``C_nb = Rz(yaw) Ry(pitch)
    Rx(roll)``, so ``Ry(pitch) Rx(roll) f_b = Rz(yaw)^T f_n = h``. Rx leaves the x component,
    which fixes pitch up to two values; roll then turns ``f_b``'s y, z onto ``h`` rotated back by
    that pitch. Of the pitches within ±90°, the one that leaves the body nearer upright (a
    vehicle re-initialised in flight is not on its back). Directions only: the norms differ by
    noise and by g's model."""
    fx, fy, fz = f_b
    nb = math.sqrt(fx * fx + fy * fy + fz * fz)
    an, ae, ad = accel_ned
    gn, ge, gd = an, ae, ad - G0_MPS2
    cy, sy = math.cos(yaw), math.sin(yaw)
    hx, hy, hz = cy * gn + sy * ge, -sy * gn + cy * ge, gd
    nh = math.sqrt(hx * hx + hy * hy + hz * hz)
    if nb == 0.0 or nh == 0.0:  # no direction to level on: the body level
        return 0.0, 0.0
    bx, by, bz = fx / nb, fy / nb, fz / nb
    hx, hy, hz = hx / nh, hy / nh, hz / nh
    # x: bx = hx cos(p) - hz sin(p) = r cos(p + alpha)
    r, alpha = math.hypot(hx, hz), math.atan2(hz, hx)
    c = math.acos(max(-1.0, min(1.0, bx / r))) if r > 0.0 else 0.5 * math.pi
    best: tuple[float, float, float] | None = None
    for p in (_wrap(c - alpha), _wrap(-c - alpha)):
        if abs(p) > 0.5 * math.pi:  # the body's x axis against the heading: not this yaw's
            continue
        ty, tz = hy, hx * math.sin(p) + hz * math.cos(p)
        r_ = _wrap(math.atan2(tz, ty) - math.atan2(bz, by))
        upright = math.cos(r_) * math.cos(p)  # the body's z axis on the down axis: cos(tilt)
        if best is None or upright > best[0]:
            best = (upright, r_, p)
    if best is None:  # f_n straight along the heading: no pitch within the Euler range turns f_b onto it
        return math.atan2(-fy, -fz), math.atan2(fx, math.hypot(fy, fz))
    return best[1], best[2]


def _wrap(a: float) -> float:
    """An angle in (-pi, pi]."""
    return math.atan2(math.sin(a), math.cos(a))

"""Quaternions, DCMs and Euler angles, vectorised over leading axes.

Conventions: q = [w, x, y, z], Hamilton product, ``q_nb`` rotates body vectors into NED
(v_n = q_nb ⊗ v_b ⊗ q_nb*), Euler angles are aerospace ZYX (yaw ψ, then pitch θ, then roll φ),
given and returned as [roll, pitch, yaw] in radians.
"""

from __future__ import annotations

import math

import numpy as np
from numpy.typing import ArrayLike, NDArray

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


def levelled_attitude(
    f_b: tuple[float, float, float],
    vel_ned: ArrayLike,
    q_nb: ArrayLike,
    min_track_speed_mps: float = RESET_TRACK_MIN_SPEED_MPS,
) -> tuple[F64, bool]:
    """q_nb re-initialised from what an INS can trust after an IMU fault: tilt levelled from the
    specific force (roll, pitch of ``f_b``, the body's ``-g`` when unaccelerated), heading from the
    ground track (``vel_ned``) at ``min_track_speed_mps`` and above, else the heading ``q_nb`` has;
    and whether the heading came from the track."""
    fx, fy, fz = f_b
    roll, pitch = math.atan2(-fy, -fz), math.atan2(fx, math.hypot(fy, fz))
    vn, ve = float(np.asarray(vel_ned)[0]), float(np.asarray(vel_ned)[1])
    tracked = math.hypot(vn, ve) >= min_track_speed_mps
    yaw = math.atan2(ve, vn) if tracked else float(quat_to_euler(np.asarray(q_nb))[2])
    return euler_to_quat([roll, pitch, yaw]), tracked

"""WGS84 Earth model for the NED mechanisation: constants, normal gravity, radii, lla<->ned.

Everything is vectorised over leading axes and pure. Positions are geodetic latitude/longitude
in radians and ellipsoidal height in metres; ``ned`` is the local tangent plane (North-East-Down)
at the scenario origin, computed exactly through ECEF so that ``ned_to_lla(lla_to_ned(x)) == x``
to round-off whatever the distance.
"""

from __future__ import annotations

import math
from functools import lru_cache

import numpy as np
from numpy.typing import ArrayLike, NDArray

from hil.nav.portable import atan2

F64 = NDArray[np.float64]

# WGS84 defining constants (NIMA TR8350.2)
A_M = 6378137.0  # semi-major axis
F = 1.0 / 298.257223563  # flattening
OMEGA_IE_RADPS = 7.292115e-5  # Earth rotation rate
GM_M3PS2 = 3.986004418e14
B_M = A_M * (1.0 - F)  # semi-minor axis
E2 = F * (2.0 - F)  # first eccentricity squared
EP2 = E2 / (1.0 - E2)  # second eccentricity squared

# Somigliana normal gravity (NIMA TR8350.2 eq. 4-1)
GAMMA_E_MPS2 = 9.7803253359  # at the equator
GAMMA_P_MPS2 = 9.8321849378  # at the poles
_K_SOMIGLIANA = (B_M * GAMMA_P_MPS2) / (A_M * GAMMA_E_MPS2) - 1.0
_M_RATIO = OMEGA_IE_RADPS**2 * A_M**2 * B_M / GM_M3PS2


def mat_vec(c: ArrayLike, v: ArrayLike) -> F64:
    """C v over leading axes with plain elementwise products.

    Deliberately not ``@``/einsum: BLAS picks kernels by array size, and the rig needs the same
    bits for a sample whether it is computed alone or in a batch of thousands.
    """
    c = np.asarray(c, dtype=float)
    v = np.asarray(v, dtype=float)
    return c[..., :, 0] * v[..., None, 0] + c[..., :, 1] * v[..., None, 1] + c[..., :, 2] * v[..., None, 2]


def cross(a: ArrayLike, b: ArrayLike) -> F64:
    """a × b over leading axes, elementwise (batch-size independent)."""
    a = np.asarray(a, dtype=float)
    b = np.asarray(b, dtype=float)
    if a.shape == (3,) and b.shape == (3,):  # one pair (the estimators' lever arms): the same
        a0, a1, a2 = a.tolist()  # products on floats, without the stack's machinery
        b0, b1, b2 = b.tolist()
        return np.array((a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0))
    return np.stack(
        [
            a[..., 1] * b[..., 2] - a[..., 2] * b[..., 1],
            a[..., 2] * b[..., 0] - a[..., 0] * b[..., 2],
            a[..., 0] * b[..., 1] - a[..., 1] * b[..., 0],
        ],
        axis=-1,
    )


def radii_of_curvature(lat_rad: ArrayLike) -> tuple[F64, F64]:
    """Meridian radius R_M and transverse (prime-vertical) radius R_N, both in metres.

    R_N = a / sqrt(1 - e² sin²L),  R_M = a (1 - e²) / (1 - e² sin²L)^(3/2)
    """
    s2 = np.sin(np.asarray(lat_rad, dtype=float)) ** 2
    w = 1.0 - E2 * s2
    r_n = A_M / np.sqrt(w)
    r_m = A_M * (1.0 - E2) / (w * np.sqrt(w))
    return r_m, r_n


def radii_of_curvature_one(lat_rad: float) -> tuple[float, float]:
    """``radii_of_curvature`` of one latitude on Python floats: the same IEEE operations in the
    same order (numpy's float64 sin is libm's, as math's: tests/unit/test_earth_scalar.py), at a
    fraction of numpy's per-call cost on a scalar."""
    sl = math.sin(lat_rad)
    w = 1.0 - E2 * (sl * sl)
    sw = math.sqrt(w)
    return A_M * (1.0 - E2) / (w * sw), A_M / sw


def normal_gravity(lat_rad: ArrayLike, alt_m: ArrayLike) -> F64:
    """Magnitude of normal gravity (gravitation + centrifugal), m/s², pointing down in NED.

    Somigliana on the ellipsoid, then the second-order free-air expansion in height
    (NIMA TR8350.2 eq. 4-3): γ_h = γ [1 − 2/a (1 + f + m − 2 f sin²L) h + 3 h²/a²].
    """
    s2 = np.sin(np.asarray(lat_rad, dtype=float)) ** 2
    h = np.asarray(alt_m, dtype=float)
    g0 = GAMMA_E_MPS2 * (1.0 + _K_SOMIGLIANA * s2) / np.sqrt(1.0 - E2 * s2)
    return g0 * (1.0 - 2.0 / A_M * (1.0 + F + _M_RATIO - 2.0 * F * s2) * h + 3.0 * h**2 / A_M**2)


def earth_rate_ned(lat_rad: ArrayLike) -> F64:
    """ω_ie in NED, rad/s, shape (..., 3): [Ω cos L, 0, −Ω sin L]."""
    lat = np.asarray(lat_rad, dtype=float)
    return np.stack(
        [OMEGA_IE_RADPS * np.cos(lat), np.zeros_like(lat), -OMEGA_IE_RADPS * np.sin(lat)], axis=-1
    )


def transport_rate_ned(lat_rad: ArrayLike, alt_m: ArrayLike, vel_ned_mps: ArrayLike) -> F64:
    """ω_en in NED, rad/s, (..., 3): [vE/(R_N+h), −vN/(R_M+h), −vE tan L/(R_N+h)]."""
    lat = np.asarray(lat_rad, dtype=float)
    h = np.asarray(alt_m, dtype=float)
    v = np.asarray(vel_ned_mps, dtype=float)
    r_m, r_n = radii_of_curvature(lat)
    return np.stack(
        [
            v[..., 1] / (r_n + h),
            -v[..., 0] / (r_m + h),
            -v[..., 1] * (np.sin(lat) / np.cos(lat)) / (r_n + h),  # not np.tan: SIMD-dispatched per CPU
        ],
        axis=-1,
    )


def lla_to_ecef(lat_rad: ArrayLike, lon_rad: ArrayLike, alt_m: ArrayLike) -> F64:
    """Geodetic to ECEF, metres, (..., 3)."""
    lat = np.asarray(lat_rad, dtype=float)
    lon = np.asarray(lon_rad, dtype=float)
    h = np.asarray(alt_m, dtype=float)
    _, r_n = radii_of_curvature(lat)
    cl = np.cos(lat)
    return np.stack(
        [
            (r_n + h) * cl * np.cos(lon),
            (r_n + h) * cl * np.sin(lon),
            (r_n * (1.0 - E2) + h) * np.sin(lat),
        ],
        axis=-1,
    )


def ecef_to_lla(xyz_m: ArrayLike) -> tuple[F64, F64, F64]:
    """ECEF to geodetic (lat rad, lon rad, height m); Bowring start + 2 Newton-like refinements.

    Sub-millimetre for any height from the Earth's centre region out to orbit altitudes.
    """
    p_xyz = np.asarray(xyz_m, dtype=float)
    x, y, z = p_xyz[..., 0], p_xyz[..., 1], p_xyz[..., 2]
    # math's atan2, not numpy's: every estimator's published lat/lon comes through here, and
    # numpy's arctan2 differs in the last bit between AVX-512 and AVX2 machines (hil.nav.portable)
    lon = atan2(y, x)
    p = np.hypot(x, y)
    # Bowring's parametric-latitude start, then iterate L = atan(z / (p (1 - e² R_N/(R_N+h))))
    beta = atan2(z * A_M, p * B_M)
    sb, cb = np.sin(beta), np.cos(beta)
    lat = atan2(z + EP2 * B_M * (sb * sb * sb), p - E2 * A_M * (cb * cb * cb))
    for _ in range(2):
        _, r_n = radii_of_curvature(lat)
        h = p * np.cos(lat) + z * np.sin(lat) - A_M**2 / r_n
        lat = atan2(z, p * (1.0 - E2 * r_n / (r_n + h)))
    _, r_n = radii_of_curvature(lat)
    h = p * np.cos(lat) + z * np.sin(lat) - A_M**2 / r_n
    return lat, lon, h


def dcm_ecef_to_ned(lat_rad: float, lon_rad: float) -> F64:
    """C_en: rotates ECEF vectors into the NED frame at (lat, lon)."""
    sl, cl = np.sin(lat_rad), np.cos(lat_rad)
    so, co = np.sin(lon_rad), np.cos(lon_rad)
    return np.array(
        [
            [-sl * co, -sl * so, cl],
            [-so, co, 0.0],
            [-cl * co, -cl * so, -sl],
        ]
    )


def lla_to_ned(
    lat_rad: ArrayLike,
    lon_rad: ArrayLike,
    alt_m: ArrayLike,
    origin_lat_rad: float,
    origin_lon_rad: float,
    origin_alt_m: float,
) -> F64:
    """Tangent-plane NED position (..., 3) of points relative to the origin."""
    if type(lat_rad) in _SCALARS and type(lon_rad) in _SCALARS and type(alt_m) in _SCALARS:
        return _lla_to_ned_one(
            lat_rad, lon_rad, alt_m, float(origin_lat_rad), float(origin_lon_rad), float(origin_alt_m)
        )  # type: ignore[arg-type]
    o_ecef, c_en = _origin_frame(float(origin_lat_rad), float(origin_lon_rad), float(origin_alt_m))
    d = lla_to_ecef(lat_rad, lon_rad, alt_m) - o_ecef
    return mat_vec(c_en, d)


# One point at a time (the fusion's every solution, the GNSS bridge's every fix): the array
# path's very operations on Python floats, without building 0-d arrays and stacking them (3-4x
# the cost at one point): + - * / and sqrt are IEEE the same there; numpy's float64 sin and cos
# are the C library's (its ufunc loops call libm's sin/cos, as math does: equal on millions of
# points, tests/unit/test_earth_scalar.py); hypot stays numpy's (libm's hypot, which math.hypot
# is not); atan2 is math's on both paths. Bit-identical: checked on random points against the
# array path (tests/unit/test_earth_scalar.py) and by the golden replay.
_SCALARS = (float, np.float64)
_sin, _cos, _sqrt = math.sin, math.cos, math.sqrt


def _ecef_one(lat: float, lon: float, h: float) -> tuple[float, float, float]:
    lat, lon, h = float(lat), float(lon), float(h)
    s2 = _sin(lat) ** 2
    r_n = A_M / _sqrt(1.0 - E2 * s2)
    cl = _cos(lat)
    return (
        (r_n + h) * cl * _cos(lon),
        (r_n + h) * cl * _sin(lon),
        (r_n * (1.0 - E2) + h) * _sin(lat),
    )


def _lla_to_ned_one(lat: float, lon: float, h: float, o_lat: float, o_lon: float, o_alt: float) -> F64:
    return np.array(lla_to_ned_floats(lat, lon, h, o_lat, o_lon, o_alt))


def lla_to_ned_floats(
    lat: float, lon: float, h: float, o_lat: float, o_lon: float, o_alt: float
) -> tuple[float, float, float]:
    """:func:`lla_to_ned` of one point as Python floats (the values of its array)."""
    (o0, o1, o2), c = _origin_floats(o_lat, o_lon, o_alt)
    x, y, z = _ecef_one(lat, lon, h)
    d0, d1, d2 = x - o0, y - o1, z - o2
    return (
        c[0][0] * d0 + c[0][1] * d1 + c[0][2] * d2,
        c[1][0] * d0 + c[1][1] * d1 + c[1][2] * d2,
        c[2][0] * d0 + c[2][1] * d1 + c[2][2] * d2,
    )


def _ecef_to_lla_one(x: float, y: float, z: float) -> tuple[float, float, float]:
    lon = math.atan2(y, x)
    p = float(np.hypot(np.float64(x), np.float64(y)))
    beta = math.atan2(z * A_M, p * B_M)
    sb, cb = _sin(beta), _cos(beta)
    lat = math.atan2(z + EP2 * B_M * (sb * sb * sb), p - E2 * A_M * (cb * cb * cb))
    for _ in range(2):
        sl = _sin(lat)
        r_n = A_M / _sqrt(1.0 - E2 * sl**2)
        h = p * _cos(lat) + z * sl - A_M**2 / r_n
        lat = math.atan2(z, p * (1.0 - E2 * r_n / (r_n + h)))
    sl = _sin(lat)
    r_n = A_M / _sqrt(1.0 - E2 * sl**2)
    h = p * _cos(lat) + z * sl - A_M**2 / r_n
    return lat, lon, h


@lru_cache(maxsize=64)
def _origin_floats(
    lat_rad: float, lon_rad: float, alt_m: float
) -> tuple[tuple[float, float, float], tuple[tuple[float, float, float], ...]]:
    """``_origin_frame`` as Python floats (the same values)."""
    o_ecef, c_en = _origin_frame(lat_rad, lon_rad, alt_m)
    o = (float(o_ecef[0]), float(o_ecef[1]), float(o_ecef[2]))
    return o, tuple((float(r[0]), float(r[1]), float(r[2])) for r in c_en)


def ned_to_lla(
    pos_ned_m: ArrayLike, origin_lat_rad: float, origin_lon_rad: float, origin_alt_m: float
) -> tuple[F64, F64, F64]:
    """Inverse of :func:`lla_to_ned`."""
    ned = np.asarray(pos_ned_m, dtype=float)
    if ned.shape == (3,):  # one point: the array path's operations on floats (``_SCALARS``)
        lat, lon, h = ned_to_lla_one(
            float(ned[0]), float(ned[1]), float(ned[2]), origin_lat_rad, origin_lon_rad, origin_alt_m
        )
        return np.asarray(lat), np.asarray(lon), np.float64(h)
    o_ecef, c_en = _origin_frame(float(origin_lat_rad), float(origin_lon_rad), float(origin_alt_m))
    xyz = mat_vec(c_en.T, ned) + o_ecef
    return ecef_to_lla(xyz)


def ned_to_lla_one(
    n: float, e: float, d: float, origin_lat_rad: float, origin_lon_rad: float, origin_alt_m: float
) -> tuple[float, float, float]:
    """:func:`ned_to_lla` of one point, in and out as Python floats (the same bits)."""
    o, c = _origin_floats(float(origin_lat_rad), float(origin_lon_rad), float(origin_alt_m))
    return _ecef_to_lla_one(*ned_to_ecef_floats(n, e, d, *o, *c[0], *c[1], *c[2]))


def ned_to_ecef_floats(
    n: float, e: float, d: float,
    o0: float, o1: float, o2: float,
    c00: float, c01: float, c02: float,
    c10: float, c11: float, c12: float,
    c20: float, c21: float, c22: float,
) -> tuple[float, float, float]:  # fmt: skip
    """A NED point in ECEF for the origin ``o`` (ECEF) and its ``C_en`` by rows
    (:func:`_origin_floats`): ``C_enᵀ p + o`` on floats, also compiled into the fusion's output
    call (``hil.fusion.predictor.carry_rows``)."""
    return (
        c00 * n + c10 * e + c20 * d + o0,
        c01 * n + c11 * e + c21 * d + o1,
        c02 * n + c12 * e + c22 * d + o2,
    )


@lru_cache(maxsize=64)
def _origin_frame(lat_rad: float, lon_rad: float, alt_m: float) -> tuple[F64, F64]:
    """The origin's ECEF position and C_en, computed once per origin (read-only, shared).

    A run has one origin but converts at IMU rate; the values are exactly what each call
    computed before, so caching them changes no bit of any output.
    """
    o_ecef = lla_to_ecef(lat_rad, lon_rad, alt_m)
    c_en = dcm_ecef_to_ned(lat_rad, lon_rad)
    o_ecef.flags.writeable = False
    c_en.flags.writeable = False
    return o_ecef, c_en


def schuler_period_s(lat_rad: float = 0.0, alt_m: float = 0.0) -> float:
    """2π sqrt(R/g) with R the geometric mean radius at the latitude: the INS error period."""
    r_m, r_n = radii_of_curvature(lat_rad)
    r = float(np.sqrt(r_m * r_n)) + alt_m
    return float(2.0 * np.pi * np.sqrt(r / normal_gravity(lat_rad, alt_m)))

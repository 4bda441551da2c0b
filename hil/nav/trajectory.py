"""Truth generator: the scenario's motion profile turned into position, velocity, attitude and
the ideal specific force and angular rate on WGS84.

Kinematics (as in gnss-ins-sim motion definitions): each primitive segment holds the Euler
angle accelerations and the body-frame acceleration constant, so within a segment

    e(τ) = e0 + ė0 τ + ½ ë τ²,    v_b(τ) = v_b0 + a_b τ,    v_n = C_nb(e) v_b

are closed-form, and so are ω_nb^b (Euler kinematics) and v̇_n = C_nb (ω_nb^b × v_b + a_b).
Position (lat, lon, h) integrates v_n with RK4 on knots ≤ 0.5 s that never straddle a segment
boundary, and is read between knots by cubic Hermite interpolation using the exact derivative.
The ideal IMU then follows from the NED mechanisation equations, read backwards:

    f_n = v̇_n + (2 ω_ie^n + ω_en^n) × v_n − g_n,     f_b = C_bn f_n
    ω_ib^b = ω_nb^b + C_bn (ω_ie^n + ω_en^n)

with the same Earth model as the strapdown (:mod:`hil.nav.earth`), so integrating the ideal
increments reproduces the truth. Every sample is an elementwise function of its own time, so
results do not depend on how callers batch their requests.
"""

from __future__ import annotations

import math
from types import MappingProxyType

import numpy as np

from hil.nav.attitude import euler_rates_to_body_rate, euler_to_dcm, euler_to_quat, quat_normalise
from hil.nav.earth import (
    cross,
    earth_rate_ned,
    lla_to_ned,
    mat_vec,
    normal_gravity,
    radii_of_curvature,
    radii_of_curvature_one,
    transport_rate_ned,
)
from hil.nav.scenario import KNOT_MAX_S, MotionSegment, Scenario, compile_profile
from hil.nav.types import F64, I64, InitialState, TruthBatch

_GL2 = 1.0 / math.sqrt(3.0)  # 2-point Gauss–Legendre nodes ±1/√3, weights 1


class TruthGenerator:
    """Truth for one scenario; ``sample`` is a pure function of time (any order of calls)."""

    def __init__(self, scenario: Scenario) -> None:
        # the scenario itself is not kept: one generator serves every scenario of its motion
        # (``truth_for``), whatever their seed, IMU, GNSS or events
        self.origin_lat_rad = math.radians(scenario.origin_lat_deg)
        self.origin_lon_rad = math.radians(scenario.origin_lon_deg)
        self.origin_alt_m = scenario.origin_alt_m
        self.duration_ns = round(scenario.duration_s * 1e9)
        self.primitives = compile_profile(
            scenario.segments,
            tuple(math.radians(x) for x in scenario.initial_euler_deg),  # type: ignore[arg-type]
            scenario.initial_vel_body_mps,
            scenario.duration_s,
        )
        pr = self.primitives
        self._t0 = np.array([p.t0_s for p in pr])
        self._e0 = np.array([p.euler0_rad for p in pr])
        self._de0 = np.array([p.euler_rate0_radps for p in pr])
        self._dde = np.array([p.euler_acc_radps2 for p in pr])
        self._vb0 = np.array([p.vel_body0_mps for p in pr])
        self._ab = np.array([p.accel_body_mps2 for p in pr])
        self._build_position_knots()

    # -- kinematics ------------------------------------------------------------------------

    def _kinematics(self, t_s: F64, seg: I64 | None = None) -> tuple[F64, F64, F64, F64, F64]:
        """Euler angles, C_nb, ω_nb^b, v_n, v̇_n at times t_s (within segment ``seg``)."""
        if seg is None:
            seg = np.clip(np.searchsorted(self._t0, t_s, side="right") - 1, 0, len(self._t0) - 1)
        tau = (t_s - self._t0[seg])[:, None]
        de0, dde = self._de0[seg], self._dde[seg]
        euler = self._e0[seg] + de0 * tau + 0.5 * dde * tau * tau
        euler_rate = de0 + dde * tau
        vb = self._vb0[seg] + self._ab[seg] * tau
        c_nb = euler_to_dcm(euler)
        w_nb_b = euler_rates_to_body_rate(euler, euler_rate)
        v_n = mat_vec(c_nb, vb)
        vdot_n = mat_vec(c_nb, cross(w_nb_b, vb) + self._ab[seg])
        return euler, c_nb, w_nb_b, v_n, vdot_n

    @staticmethod
    def _pos_rate(lat: float, h: float, v: list[float]) -> tuple[float, float, float]:
        """(lat, lon, h) rates in plain floats: the RK4 below calls this four times per knot, and
        numpy's per-call cost on a scalar was most of a long scenario's start-up."""
        r_m, r_n = radii_of_curvature_one(lat)
        return (v[0] / (r_m + h), v[1] / ((r_n + h) * math.cos(lat)), -v[2])

    def _build_position_knots(self) -> None:
        """RK4 of (lat, lon, h) over knots; the velocities at all stage times come in one call."""
        knots: list[F64] = []
        for p in self.primitives:
            n = max(1, math.ceil(p.duration_s / KNOT_MAX_S))
            knots.append(p.t0_s + p.duration_s * np.arange(n) / n)
        end = self.primitives[-1].t0_s + self.primitives[-1].duration_s
        t_k = np.concatenate([*knots, [end]])
        seg_k = np.searchsorted(self._t0, t_k, side="right") - 1
        seg_k = np.clip(seg_k, 0, len(self._t0) - 1)
        seg_iv = seg_k[:-1]  # each knot interval lies in the segment of its left knot
        h_k = np.diff(t_k)
        v_a = self._kinematics(t_k[:-1], seg_iv)[3]
        v_m = self._kinematics(t_k[:-1] + 0.5 * h_k, seg_iv)[3]
        v_b = self._kinematics(t_k[1:], seg_iv)[3]  # right end, still inside the left segment
        lat, lon, h = float(self.origin_lat_rad), float(self.origin_lon_rad), float(self.origin_alt_m)
        rows = [(lat, lon, h)]
        rate = self._pos_rate
        for dt, va, vm, vb in zip(h_k.tolist(), v_a.tolist(), v_m.tolist(), v_b.tolist(), strict=True):
            k1 = rate(lat, h, va)
            k2 = rate(lat + 0.5 * dt * k1[0], h + 0.5 * dt * k1[2], vm)
            k3 = rate(lat + 0.5 * dt * k2[0], h + 0.5 * dt * k2[2], vm)
            k4 = rate(lat + dt * k3[0], h + dt * k3[2], vb)
            lat += dt / 6.0 * (k1[0] + 2 * k2[0] + 2 * k3[0] + k4[0])
            lon += dt / 6.0 * (k1[1] + 2 * k2[1] + 2 * k3[1] + k4[1])
            h += dt / 6.0 * (k1[2] + 2 * k2[2] + 2 * k3[2] + k4[2])
            rows.append((lat, lon, h))
        y = np.array(rows)
        # exact derivatives at each knot, on both sides (velocity is continuous, so one set)
        r_m, r_n = radii_of_curvature(y[:, 0])
        v_all = np.concatenate([v_a, v_b[-1:]])
        dy = np.stack(
            [v_all[:, 0] / (r_m + y[:, 2]), v_all[:, 1] / ((r_n + y[:, 2]) * np.cos(y[:, 0])), -v_all[:, 2]],
            axis=-1,
        )
        self._knot_t, self._knot_y, self._knot_dy = t_k, y, dy

    def _position(self, t_s: F64) -> F64:
        """(lat, lon, h) by cubic Hermite between knots, (n, 3)."""
        j = np.clip(np.searchsorted(self._knot_t, t_s, side="right") - 1, 0, len(self._knot_t) - 2)
        t0, t1 = self._knot_t[j], self._knot_t[j + 1]
        hh = (t1 - t0)[:, None]
        s = ((t_s - t0) / (t1 - t0))[:, None]
        s2, s3 = s * s, s * s * s
        h00 = 2 * s3 - 3 * s2 + 1
        h10 = s3 - 2 * s2 + s
        h01 = -2 * s3 + 3 * s2
        h11 = s3 - s2
        return (
            h00 * self._knot_y[j]
            + h10 * hh * self._knot_dy[j]
            + h01 * self._knot_y[j + 1]
            + h11 * hh * self._knot_dy[j + 1]
        )

    def _inertial(self, t_s: F64, seg: I64 | None = None) -> tuple[F64, F64, F64, F64, F64, F64]:
        """(lat, lon, h), v_n, Euler angles, f_b, ω_ib^b, C_nb at times t_s (seconds)."""
        euler, c_nb, w_nb_b, v_n, vdot_n = self._kinematics(t_s, seg)
        lla = self._position(t_s)
        lat, h = lla[:, 0], lla[:, 2]
        w_ie = earth_rate_ned(lat)
        w_en = transport_rate_ned(lat, h, v_n)
        g = normal_gravity(lat, h)
        # f_n = v̇_n + (2ω_ie + ω_en) × v_n − g_n
        f_n = vdot_n + cross(2.0 * w_ie + w_en, v_n)
        f_n[:, 2] -= g
        c_bn = np.swapaxes(c_nb, -1, -2)
        f_b = mat_vec(c_bn, f_n)
        w_ib_b = w_nb_b + mat_vec(c_bn, w_ie + w_en)
        return lla, v_n, euler, f_b, w_ib_b, c_nb

    # -- public ------------------------------------------------------------------------------

    def sample(self, t_ns: I64) -> TruthBatch:
        """Truth at true times ``t_ns`` (int64 ns since run start, within [0, duration])."""
        t_ns = np.asarray(t_ns, dtype=np.int64)
        t_s = t_ns.astype(np.float64) * 1e-9
        lla, v_n, euler, f_b, w_ib_b, _ = self._inertial(t_s)
        pos = lla_to_ned(
            lla[:, 0], lla[:, 1], lla[:, 2], self.origin_lat_rad, self.origin_lon_rad, self.origin_alt_m
        )
        return TruthBatch(
            t_ns=t_ns,
            lat_rad=lla[:, 0],
            lon_rad=lla[:, 1],
            alt_m=lla[:, 2],
            pos_ned_m=pos,
            vel_ned_mps=v_n,
            q_nb=quat_normalise(euler_to_quat(euler)),
            f_b_mps2=f_b,
            w_ib_b_radps=w_ib_b,
        )

    def increments(self, t_start_ns: I64, t_end_ns: I64) -> tuple[F64, F64]:
        """Ideal delta-angle and delta-velocity ∫ω_ib^b dt, ∫f_b dt over [start, end], (n, 3).

        2-point Gauss–Legendre per piece; intervals that straddle a segment boundary (where
        f and ω may step) are split there, so a step is integrated exactly.
        """
        a = np.asarray(t_start_ns, dtype=np.int64).astype(np.float64) * 1e-9
        b = np.asarray(t_end_ns, dtype=np.int64).astype(np.float64) * 1e-9
        dth, dv = self._gauss(a, b)
        bounds = self._t0[1:]
        cnt = np.searchsorted(bounds, b, side="left") - np.searchsorted(bounds, a, side="right")
        for k in np.flatnonzero(cnt > 0):
            inner = bounds[(bounds > a[k]) & (bounds < b[k])]
            edges = np.concatenate([[a[k]], inner, [b[k]]])
            th, v = self._gauss(edges[:-1], edges[1:])
            dth[k], dv[k] = th.sum(axis=0), v.sum(axis=0)
        return dth, dv

    def _gauss(self, a: F64, b: F64) -> tuple[F64, F64]:
        mid, half = 0.5 * (a + b), 0.5 * (b - a)
        # evaluate each node inside the piece's own segment (the piece never straddles one)
        seg = np.clip(np.searchsorted(self._t0, mid, side="right") - 1, 0, len(self._t0) - 1)
        out_th = np.zeros((len(a), 3))
        out_v = np.zeros((len(a), 3))
        for sgn in (-1.0, 1.0):
            t = mid + sgn * _GL2 * half
            _, _, _, f_b, w_ib_b, _ = self._inertial(t, seg)
            out_th += w_ib_b * half[:, None]
            out_v += f_b * half[:, None]
        return out_th, out_v

    def initial_state(self) -> InitialState:
        """Truth at t = 0: the perfect alignment."""
        tb = self.sample(np.array([0], dtype=np.int64))
        return InitialState(
            stamp_ns=0,
            lat_rad=float(tb.lat_rad[0]),
            lon_rad=float(tb.lon_rad[0]),
            alt_m=float(tb.alt_m[0]),
            origin_lat_rad=self.origin_lat_rad,
            origin_lon_rad=self.origin_lon_rad,
            origin_alt_m=self.origin_alt_m,
            vel_ned_mps=tb.vel_ned_mps[0].copy(),
            q_nb=tb.q_nb[0].copy(),
        )


# The last few motions' generators: (the fields the generator reads, as their repr, which tells
# -0.0 from 0.0 as their bits do; the generator).
_TRUTHS: list[tuple[str, TruthGenerator]] = []
_TRUTHS_KEPT = 4


def truth_for(scenario: Scenario) -> TruthGenerator:
    """The scenario's :class:`TruthGenerator`, one per motion in a process.

    Building one integrates the whole motion profile, whatever the run's duration (its RK4's
    Python loop over 0.5 s knots: straight_level's hour ~41 ms, static's two hours ~77 ms, here).
    ``hil sim`` builds its nodes in one process, where the IMU emulator, the GNSS emulator, the
    world and the fusion each parsed the run's scenario and built their own, as ``hil rerun``
    built the fusion's twice. ``sample`` is a pure function of time, and the
    generator reads only the origin, the duration, the initial attitude and velocity and the
    segments: scenarios equal in those (their values' repr, bit for bit) share one, whatever
    else differs (seed, IMU, GNSS, events). A scenario whose fields have no faithful repr is
    not remembered (its own generator)."""
    motion = (
        scenario.origin_lat_deg,
        scenario.origin_lon_deg,
        scenario.origin_alt_m,
        scenario.duration_s,
        scenario.initial_euler_deg,
        scenario.initial_vel_body_mps,
        scenario.segments,
    )
    if not _faithful(motion):
        return TruthGenerator(scenario)
    key = repr(motion)
    for i, (k, truth) in enumerate(_TRUTHS):
        if k == key:
            if i:
                _TRUTHS.insert(0, _TRUTHS.pop(i))
            return truth
    truth = TruthGenerator(scenario)
    _TRUTHS.insert(0, (key, truth))
    del _TRUTHS[_TRUTHS_KEPT:]
    return truth


def _faithful(x: object) -> bool:
    """Values whose repr tells any two of them apart (a numpy array's elides its middle)."""
    if x is None or type(x) in (float, int, str, bool):
        return True
    if type(x) in (tuple, list):
        return all(_faithful(v) for v in x)  # type: ignore[attr-defined]
    if type(x) is MotionSegment:
        return _faithful(x.kind) and _faithful(x.params)
    if type(x) in (dict, MappingProxyType):
        return all(_faithful(k) and _faithful(v) for k, v in x.items())  # type: ignore[attr-defined]
    return False

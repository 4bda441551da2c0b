"""IMU emulator core: ideal increments from the truth plus a per-axis error model.

Measured increment over the interval ending at t_k (each sensor triad, per axis):

    Δθ̃_k = (I + S + M) Δθ_k + (b_0 + b_GM,k + b_RRW,k) dt + N √dt w_k
    b_GM,k  = φ b_GM,k−1 + σ_GM √(1 − φ²) u_k,   φ = exp(−dt/T_c)   (bias instability)
    b_RRW,k = b_RRW,k−1 + K √dt v_k                                    (rate random walk)

then saturation at the range and quantisation of the increment with the residual carried to the
next sample (as real IMUs accumulate), so quantisation noise does not build into a drift. The
true increments are exact integrals of the truth, so coning and sculling are in them; rates are
the interval averages Δθ̃/dt, Δṽ/dt (what an IMU reporting rates at its output rate gives).
S (scale factor), M (misalignment, off-diagonal) and b_0 (turn-on bias) are drawn once at
construction. Every noise source draws from its own child generator, so a batch's numbers do
not depend on how the caller slices the stream.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass

import numpy as np

from hil.nav.scenario import Scenario
from hil.nav.sensor_specs import GM_PEAK_RATIO, IEEE_BI_FACTOR
from hil.nav.trajectory import TruthGenerator
from hil.nav.types import F64, I64

_NS = 1_000_000_000


def sensor_rng(seed: int, sensor_name: str) -> np.random.Generator:
    """The generator for one sensor: SeedSequence([scenario seed, crc32(sensor name)])."""
    return np.random.default_rng(np.random.SeedSequence([seed, zlib.crc32(sensor_name.encode())]))


def gauss_markov(drive: F64, phi: float, zi: F64) -> F64:
    """``y_k = φ y_{k−1} + x_k`` over rows, in ``scipy.signal.lfilter([1], [1, −φ], x, zi=zi)``'s
    exact operation order (its direct form II transposed: ``y = z + 1·x``, ``z = 0·x − y·(−φ)``),
    so the bits are lfilter's (tests/unit/test_imu_gauss_markov.py holds it to scipy).

    Plain floats per axis: the emulator asks for one sample at a time, where lfilter's call and
    importing ``scipy.signal`` (seconds at every start) cost far more than the recursion.
    """
    neg_phi = -phi
    cols = drive.T.tolist()
    out = np.empty_like(drive)
    for axis, (xs, z) in enumerate(zip(cols, zi.tolist(), strict=True)):
        ys = []
        for x in xs:
            y = z + 1.0 * x
            z = 0.0 * x - y * neg_phi
            ys.append(y)
        out[:, axis] = ys
    return out


@dataclass(frozen=True)
class ImuBatch:
    """Consecutive IMU samples; ``t_ns`` is the true capture time (end of each interval)."""

    t_ns: I64  # (n,)
    dt_s: float
    dtheta_b_rad: F64  # (n, 3)
    dvel_b_mps: F64  # (n, 3)
    gyro_radps: F64  # (n, 3) interval-average rate = dtheta / dt
    accel_mps2: F64  # (n, 3) interval-average specific force = dvel / dt


class _Triad:
    """Error state of one sensor triad (gyro or accelerometer), SI units per axis."""

    def __init__(
        self,
        gens: list[np.random.Generator],
        dt: float,
        fixed_bias: F64,
        turn_on_sigma: F64,
        bi: F64,
        corr_s: float,
        white: F64,
        rrw: F64,
        sf_sigma: F64,
        mis_sigma: float,
        lsb: float,
        full_scale: float,
    ) -> None:
        g_const, self._g_white, self._g_gm, self._g_rrw = gens
        self.dt = dt
        # turn-on draws, in a fixed order: bias (3), scale factor (3), misalignment (6)
        self.bias_const = fixed_bias + turn_on_sigma * g_const.standard_normal(3)
        sf = sf_sigma * g_const.standard_normal(3)
        mis = mis_sigma * g_const.standard_normal(6)
        self.matrix = np.eye(3) + np.diag(sf)
        self.matrix[[0, 0, 1, 1, 2, 2], [1, 2, 0, 2, 0, 1]] = mis
        sigma_gm = IEEE_BI_FACTOR * bi / GM_PEAK_RATIO  # Allan peak of the GM = 0.664 B
        self.phi = math.exp(-dt / corr_s)  # math, not numpy: numpy's exp rounds per CPU (hil.nav.portable)
        self.gm_drive = sigma_gm * np.sqrt(1.0 - self.phi**2)
        self.gm_state = sigma_gm * self._g_gm.standard_normal(3)  # start stationary
        self.white_sigma = white * np.sqrt(dt)  # per increment
        self.rrw_step = rrw * np.sqrt(dt)
        self.rrw_state = np.zeros(3)
        self.lsb = lsb
        self.limit = full_scale * dt
        self.quant_sum = np.zeros(3)  # running Σ of unquantised increments
        self.quant_count = np.zeros(3)  # LSB counts emitted so far

    def measure(self, ideal: F64) -> F64:
        n = ideal.shape[0]
        # b_GM,k = φ b_GM,k−1 + drive u_k  (the state carries exactly across batches)
        u = self._g_gm.standard_normal((n, 3))
        gm = gauss_markov(self.gm_drive * u, self.phi, self.phi * self.gm_state)
        if n:
            self.gm_state = gm[-1].copy()
        rrw = np.cumsum(
            np.vstack([self.rrw_state, self.rrw_step * self._g_rrw.standard_normal((n, 3))]), axis=0
        )[1:]
        if n:
            self.rrw_state = rrw[-1].copy()
        white = self.white_sigma * self._g_white.standard_normal((n, 3))
        m = self.matrix
        out = (
            ideal[:, :1] * m[:, 0]
            + ideal[:, 1:2] * m[:, 1]
            + ideal[:, 2:3] * m[:, 2]
            + (self.bias_const + gm + rrw) * self.dt
            + white
        )
        out = np.clip(out, -self.limit, self.limit)
        if self.lsb > 0.0 and n:
            total = np.cumsum(np.vstack([self.quant_sum, out]), axis=0)[1:]
            count = np.round(total / self.lsb)
            out = np.diff(np.vstack([self.quant_count, count]), axis=0) * self.lsb
            self.quant_sum, self.quant_count = total[-1].copy(), count[-1].copy()
        return out


class ImuEmulatorCore:
    """Streams IMU samples for a scenario: ``next_batch(n)`` returns the next n intervals."""

    def __init__(self, scenario: Scenario, truth: TruthGenerator, rng: np.random.Generator) -> None:
        self.scenario = scenario
        self.truth = truth
        self.rate_hz = scenario.imu.rate_hz
        self.dt_s = 1.0 / self.rate_hz
        self.count = 0  # samples emitted so far
        p = scenario.imu.params
        g = rng.spawn(8)
        a = np.asarray
        self.gyro = _Triad(
            g[0:4],
            self.dt_s,
            a(p.gyro_bias_radps),
            a(p.gyro_turn_on_sigma_radps),
            a(p.gyro_bias_instability_radps),
            p.gyro_bias_corr_s,
            a(p.gyro_arw_rad_rts),
            a(p.gyro_rrw_radps_rts),
            a(p.gyro_scale_factor_sigma),
            p.gyro_misalignment_sigma_rad,
            p.gyro_quant_rad,
            p.gyro_range_radps,
        )
        self.accel = _Triad(
            g[4:8],
            self.dt_s,
            a(p.accel_bias_mps2),
            a(p.accel_turn_on_sigma_mps2),
            a(p.accel_bias_instability_mps2),
            p.accel_bias_corr_s,
            a(p.accel_vrw_mps_rts),
            a(p.accel_rrw_mps2_rts),
            a(p.accel_scale_factor_sigma),
            p.accel_misalignment_sigma_rad,
            p.accel_quant_mps,
            p.accel_range_mps2,
        )

    def sample_times_ns(self, k0: int, n: int) -> I64:
        """True end times of intervals k0+1 … k0+n: round-down of k·1e9/rate, never drifting."""
        k = np.arange(k0, k0 + n + 1, dtype=np.int64)
        return (k * _NS) // self.rate_hz

    def next_batch(self, n: int) -> ImuBatch:
        t = self.sample_times_ns(self.count, n)
        self.count += n
        dth, dv = self.truth.increments(t[:-1], t[1:])
        dth = self.gyro.measure(dth)
        dv = self.accel.measure(dv)
        return ImuBatch(
            t_ns=t[1:],
            dt_s=self.dt_s,
            dtheta_b_rad=dth,
            dvel_b_mps=dv,
            gyro_radps=dth / self.dt_s,
            accel_mps2=dv / self.dt_s,
        )

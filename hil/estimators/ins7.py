"""Seed 004: the seven-state single-channel INS error model closed with GNSS, and its KF.

State (one horizontal channel; the equations are the digest's reconstruction — the OCR lost
them — from every symbol the paper defines)::

    x = [β, ΔV, ΔS, ω_dr, Δα, ΔV_k, ΔS_k]
    dβ/dt    = ΔV / R + ω_dr        tilt error (Schuler loop with the next line)
    dΔV/dt   = −g β + Δα            velocity error
    dΔS/dt   = ΔV                   INS position error
    dω_dr/dt = −ω_dr / T_ω + q_ω    gyro drift, first-order Gauss–Markov
    dΔα/dt   = −Δα / T_α + q_α      accelerometer error, first-order Gauss–Markov
    dΔV_k/dt = 0                    systematic GNSS velocity error
    dΔS_k/dt = ΔV_k                 systematic GNSS position error

Measurement ``S* = ΔS − ΔS_k + v_S`` (INS minus GNSS position), ``v_S`` white with RMS σ_S.
The discrete model is exact: ``Φ = e^{F Δt}`` and ``Q_d`` by Van Loan's method, so the discrete
Riccati recursion *is* the covariance of the simulated filter and a Monte-Carlo of the same
model must reproduce it to sampling error (1/sqrt(2 N) relative for N runs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np
from scipy.linalg import expm

from hil.nav.types import F64

G_MPS2 = 9.81
R_EARTH_M = 6_372_000.0
STATE_NAMES = ("beta", "dV", "dS", "w_dr", "d_alpha", "dV_k", "dS_k")


@dataclass(frozen=True)
class Ins7Params:
    """Reconstructed conditions (the paper states none but R and g): a tactical-grade UAV INS.

    Gauss–Markov σ are the stationary RMS; correlation times are "long" per the paper.
    """

    dt_s: float = 1.0  # GNSS 1 Hz, one KF step per fix
    t_omega_s: float = 3600.0
    sigma_omega_radps: float = math.radians(1.0) / 3600.0  # 1 deg/h gyro drift
    t_alpha_s: float = 600.0
    sigma_alpha_mps2: float = 5e-3  # 0.5 mg accelerometer error
    sigma_s_m: float = 5.0  # GNSS position white noise
    p0_sigma: tuple[float, ...] = (
        1e-3,  # β, rad
        0.5,  # ΔV, m/s
        10.0,  # ΔS, m
        math.radians(1.0) / 3600.0,  # ω_dr
        5e-3,  # Δα
        0.002,  # ΔV_k, m/s
        2.0,  # ΔS_k, m
    )


def continuous_model(p: Ins7Params) -> tuple[F64, F64]:
    """``(F, Q)`` of ``ẋ = F x + w``, ``E[w w'] = Q δ(τ)``."""
    f = np.zeros((7, 7))
    f[0, 1] = 1.0 / R_EARTH_M  # dβ/dt = ΔV/R + ω_dr
    f[0, 3] = 1.0
    f[1, 0] = -G_MPS2  # dΔV/dt = −g β + Δα
    f[1, 4] = 1.0
    f[2, 1] = 1.0  # dΔS/dt = ΔV
    f[3, 3] = -1.0 / p.t_omega_s
    f[4, 4] = -1.0 / p.t_alpha_s
    f[6, 5] = 1.0  # dΔS_k/dt = ΔV_k
    q = np.zeros((7, 7))
    q[3, 3] = 2.0 * p.sigma_omega_radps**2 / p.t_omega_s  # keeps Var(ω_dr) = σ_ω²
    q[4, 4] = 2.0 * p.sigma_alpha_mps2**2 / p.t_alpha_s
    return f, q


def discretise(f: F64, q: F64, dt_s: float) -> tuple[F64, F64]:
    """Van Loan: ``expm([[−F, Q], [0, F']] Δt) = [[·, Φ⁻¹Q_d], [0, Φ']]``."""
    n = f.shape[0]
    m = np.zeros((2 * n, 2 * n))
    m[:n, :n] = -f
    m[:n, n:] = q
    m[n:, n:] = f.T
    e = expm(m * dt_s)
    phi = e[n:, n:].T
    qd = phi @ e[:n, n:]
    return phi, 0.5 * (qd + qd.T)


H = np.array([[0.0, 0.0, 1.0, 0.0, 0.0, 0.0, -1.0]])  # S* = ΔS − ΔS_k + v


def riccati(p: Ins7Params, n_steps: int) -> tuple[F64, F64]:
    """Discrete Riccati recursion: posterior covariances ``(n_steps, 7, 7)`` and gains ``(n_steps, 7)``.

    P⁻ = Φ P Φ' + Q_d;  S = H P⁻ H' + R;  K = P⁻ H' / S;  P = (I − K H) P⁻ (I − K H)' + K R K'
    """
    f, q = continuous_model(p)
    phi, qd = discretise(f, q, p.dt_s)
    r = p.sigma_s_m**2
    pk = np.diag(np.square(p.p0_sigma))
    covs = np.empty((n_steps, 7, 7))
    gains = np.empty((n_steps, 7))
    eye = np.eye(7)
    for k in range(n_steps):
        pk = phi @ pk @ phi.T + qd
        s = float((H @ pk @ H.T)[0, 0]) + r
        gain = (pk @ H.T)[:, 0] / s
        ikh = eye - np.outer(gain, H[0])
        pk = ikh @ pk @ ikh.T + r * np.outer(gain, gain)  # Joseph form: stays symmetric PSD
        covs[k] = pk
        gains[k] = gain
    return covs, gains


def monte_carlo(p: Ins7Params, n_steps: int, n_runs: int, rng: np.random.Generator) -> F64:
    """RMS over ``n_runs`` of the estimation error ``x − x̂`` after each update, ``(n_steps, 7)``.

    Vectorised across runs: each step is one ``(n_runs, 7) @ (7, 7)`` product for the truth and
    one for the filter, whose gains (data independent) come from :func:`riccati`.
    """
    f, q = continuous_model(p)
    phi, qd = discretise(f, q, p.dt_s)
    _, gains = riccati(p, n_steps)
    # Q_d is singular in the deterministic states: factor by eigen-decomposition.
    w, v = np.linalg.eigh(qd)
    qd_sqrt = v * np.sqrt(np.clip(w, 0.0, None))
    x = rng.standard_normal((n_runs, 7)) * np.asarray(p.p0_sigma)
    xh = np.zeros((n_runs, 7))
    rms = np.empty((n_steps, 7))
    for k in range(n_steps):
        x = x @ phi.T + rng.standard_normal((n_runs, 7)) @ qd_sqrt.T
        z = x[:, 2] - x[:, 6] + rng.normal(0.0, p.sigma_s_m, n_runs)
        xh = xh @ phi.T
        xh = xh + np.outer(z - (xh[:, 2] - xh[:, 6]), gains[k])  # x̂ += K (z − H x̂)
        rms[k] = np.sqrt(np.mean((x - xh) ** 2, axis=0))
    return rms


def time_to_operating_mode(sigma: F64, dt_s: float, tol: float = 0.1) -> float:
    """First time after which σ(t) stays within ``tol`` of its end-of-run value, seconds.

    ``sigma`` ``(n_steps, k)``: every column must have settled.
    """
    final = sigma[-1]
    outside = np.any(np.abs(sigma - final) > tol * final, axis=1)
    idx = np.nonzero(outside)[0]
    return 0.0 if idx.size == 0 else float((idx[-1] + 1) * dt_s)

"""Scalar lecture KF and the seed-004 seven-state model: steady gains and MC vs Riccati."""

from __future__ import annotations

import numpy as np
import pytest

from hil.estimators import ins7, scalar_kf


def test_lecture_steady_gain_and_sigma() -> None:
    k, sigma = scalar_kf.steady_state(0.01**2, 0.2**2)
    assert k == pytest.approx(0.0488, abs=1e-4)
    assert sigma == pytest.approx(0.044, abs=5e-4)


def test_lecture_recursion_converges_to_the_riccati_fixed_point() -> None:
    eps, d = np.zeros(1), np.array([1.0])
    for _ in range(2000):
        eps, d, k = scalar_kf.scalar_kf_step(eps, d, np.zeros(1), 1e-4, 0.04)
    k_inf, sigma = scalar_kf.steady_state(1e-4, 0.04)
    assert k[0] == pytest.approx(k_inf, rel=1e-9)
    assert np.sqrt(d[0]) == pytest.approx(sigma, rel=1e-9)


def test_lecture_monte_carlo_matches_riccati() -> None:
    rms, sig = scalar_kf.monte_carlo(1e-4, 0.04, 0.01, 600, 4000, np.random.default_rng(3))
    assert np.max(np.abs(rms[50:] / sig[50:] - 1.0)) < 0.06  # 1/sqrt(2·4000) = 1.1 % per point


def test_van_loan_matches_schuler_period() -> None:
    f, q = ins7.continuous_model(ins7.Ins7Params())
    phi, qd = ins7.discretise(f, q, 1.0)
    np.testing.assert_allclose(phi, __import__("scipy.linalg").linalg.expm(f), rtol=1e-9, atol=1e-12)
    assert np.all(np.linalg.eigvalsh(qd) > -1e-18)
    # The β–ΔV loop oscillates at ω_s = sqrt(g/R): its eigenvalues are ±j ω_s.
    w = np.sort(np.abs(np.linalg.eigvals(f[:2, :2]).imag))
    assert w[-1] == pytest.approx(np.sqrt(9.81 / 6_372_000.0), rel=1e-9)


def test_seven_state_monte_carlo_reproduces_riccati_sigma() -> None:
    """1000 runs: sample RMS vs Riccati σ, within sampling error (1/sqrt(2000) = 2.2 % per point)."""
    p = ins7.Ins7Params()
    n = 600
    covs, _ = ins7.riccati(p, n)
    sigma = np.sqrt(np.diagonal(covs, axis1=1, axis2=2))
    rms = ins7.monte_carlo(p, n, 1000, np.random.default_rng(2024))
    rel = np.abs(rms / sigma - 1.0)
    assert np.mean(rel) < 0.03
    assert np.max(rel) < 0.10
    assert np.mean(rel < 0.05) > 0.9
    # The filter converges: position σ well below the 10 m prior, tilt below 1 mrad.
    assert sigma[-1, 2] < 3.0 and sigma[-1, 0] < 6e-4


def test_seven_state_reaches_operating_mode_in_minutes() -> None:
    p = ins7.Ins7Params()
    covs, _ = ins7.riccati(p, 900)
    sigma = np.sqrt(np.diagonal(covs, axis1=1, axis2=2))
    assert 60.0 < ins7.time_to_operating_mode(sigma[:, :2], p.dt_s, tol=0.2) < 240.0


def test_seven_state_monte_carlo_has_no_systematic_bias_against_riccati() -> None:
    """Independent repeats pooled: with the same Φ, Q_d, R, P0 and gains, E[RMS²] = σ² exactly, so
    the time mean of RMS²/σ² − 1 per state is zero within its standard error over the repeats, and
    the pooled 10 000-run RMS is within a few per-point sampling σ (0.7 %) of the Riccati σ."""
    p = ins7.Ins7Params()
    n, runs, reps = 300, 1000, 10
    covs, _ = ins7.riccati(p, n)
    sig2 = np.diagonal(covs, axis1=1, axis2=2)
    m = np.empty((reps, 7))
    pooled = np.zeros((n, 7))
    for i, g in enumerate(np.random.default_rng(77).spawn(reps)):
        r = ins7.monte_carlo(p, n, runs, g)
        m[i] = np.mean(r**2 / sig2, axis=0) - 1.0
        pooled += r**2
    t = m.mean(axis=0) / (m.std(axis=0, ddof=1) / np.sqrt(reps))
    assert np.all(np.abs(t) < 4.0)
    assert np.max(np.abs(np.sqrt(pooled / reps / sig2) - 1.0)) < 0.03

"""``hil bench seeds``: every published figure of the seed papers beside the rig's reproduction.

Each experiment runs the project's own estimator numerics (the same code the live rig runs)
under the paper's conditions, or under a stated reconstruction where the paper gives none.
Prints a markdown table and writes it as the ``seeds`` section of docs/benchmarks.md;
``--plots DIR`` also writes Bode plots of every F(p) and 1 − F(p) and error-vs-time plots
(matplotlib is imported only then).
"""

from __future__ import annotations

import math
import time
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2
from scipy.stats import t as student_t

from hil.bench import command_line, write_section
from hil.bench.seeds_common import (
    SCHULER_RADPS,
    SEED_GNSS_POS_SIGMA_M,
    SEED_GNSS_RATE_HZ,
    SEED_GNSS_SLOW_AMPLITUDE_M,
    SEED_GNSS_SLOW_PERIOD_S,
    SEED_GNSS_VEL_SIGMA_MPS,
    Report,
)
from hil.bench.seeds_uav import plot_nees, plot_uav, uav_comparison
from hil.estimators import ins7, scalar_kf
from hil.estimators.compensation import VS_SCHEDULE, CompensationCore, fixed_filter
from hil.estimators.complementary import ComplementaryFilter, pulse_peak_error, static_error
from hil.estimators.lti import TransferFunction, aperiodic, complementary2, complementary3
from hil.nav.types import F64
from hil.runtime.argtypes import OneLineParser

SEED = 20240601


# ---------------------------------------------------------------------------------------------
# seed 003


def seed003(rep: Report) -> None:
    tau, amp, u = 1.0, 50.0, 0.005
    cf2, cf3 = ComplementaryFilter.second_order(), ComplementaryFilter.third_order()
    peak2 = pulse_peak_error(cf2, amp, tau)
    peak3 = pulse_peak_error(cf3, amp, tau)
    rep.add("003", "2nd order: peak error ξ_max ≈ r1 τ A", "3.5 m", f"{peak2:.2f} m")
    rep.add("003", "2nd order: suppression η = A/ξ_max", "14.3", f"{amp / peak2:.1f}")
    rep.add("003", "2nd order: static error u/r2", "1 m", f"{static_error(cf2, u):.3f} m")
    rep.add("003", "3rd order: static error", "→ 0", f"{static_error(cf3, u, t_end_s=20000.0):.1e} m")
    rep.add("003", "3rd order: peak error ≈ k1 τ A", "≈ 3.5 m", f"{peak3:.2f} m")
    rep.notes.append(
        "Seed 003: a 50 m GPS disturbance lasting 1 s on an object at rest, exact ZOH at 10 ms; "
        "r1 = k1 = 0.07, r2 = k2 = 0.005, k3 = 1e-4. ξ_max = r1 τ A is the impulse "
        "approximation; the finite 1 s pulse gives slightly less because W's impulse response "
        "decays during the pulse. Static error read after 4000 s (2nd) / 20000 s (3rd order, whose "
        "slowest pole, from k3 = 1e-4, is a few hundred seconds)."
    )


# ---------------------------------------------------------------------------------------------
# seed 000


def ins_error_000(t: F64, rate_gyro_ramp: float, dv0: float) -> tuple[F64, F64]:
    """Reconstructed INS error of Fig. 8: Schuler loop driven by a ramping gyro drift.

    β' = ΔV/R + ε̇ t, ΔV' = −g β, ΔV(0) = dv0:
    ΔV = R ε̇ (t − sin ω t / ω) + dv0 cos ω t,  ΔS = R ε̇ (t²/2 − (1 − cos ω t)/ω²) + dv0 sin ω t / ω
    (sign chosen so the error grows positive). ``rate_gyro_ramp`` is R ε̇ in m/s².
    """
    w = SCHULER_RADPS
    dv = rate_gyro_ramp * (t - np.sin(w * t) / w) + dv0 * np.cos(w * t)
    ds = rate_gyro_ramp * (t**2 / 2 - (1 - np.cos(w * t)) / w**2) + dv0 * np.sin(w * t) / w
    return ds, dv


def run_compensation(schedule: Any, xi1: F64, gnss: F64, t: F64, gnss_every: int) -> F64:
    """Error of ``X̂`` per step for INS error ``xi1`` (n, m) and GNSS error ``gnss`` (n, m)."""
    core = CompensationCore(schedule, xi1.shape[1], restart_after_s=3.0)
    err = np.empty_like(xi1)
    for k in range(t.size):
        t_ns = round(t[k] * 1e9)
        core.advance_to(t_ns)
        if k % gnss_every == 0:
            d = xi1[k] - gnss[k]  # X_INS − X_GNSS = ξ1 − ξ2
            # position channel continued with the velocity difference (INS error rate)
            slope = np.zeros_like(d)
            if d.size == 2:
                slope[0] = d[1]
            core.set_input(t_ns, d, slope)
        err[k] = xi1[k] - core.output()  # X̂ − X = ξ1 − F(ξ1 − ξ2)
    return err


def seed000(rep: Report, rng: np.random.Generator) -> None:
    dt, t_end = 0.1, 5000.0
    t = np.arange(round(t_end / dt) + 1) * dt
    t_slow = SEED_GNSS_SLOW_PERIOD_S
    # Ramp of gyro drift sized so that ΔS(5000 s) = 140 km (Fig. 8).
    w = SCHULER_RADPS
    r_eps = 140e3 / (t_end**2 / 2 - (1 - math.cos(w * t_end)) / w**2)
    ds, dv = ins_error_000(t, r_eps, 2.0)
    xi1 = np.column_stack([ds, dv])
    # GNSS: white noise sampled at 1 s (held), σ 20 m / 0.2 m/s, plus a slow DOP component.
    n_fix = int(t_end * SEED_GNSS_RATE_HZ) + 1
    white = rng.standard_normal((n_fix, 2)) * np.array([SEED_GNSS_POS_SIGMA_M, SEED_GNSS_VEL_SIGMA_MPS])
    held = white[np.minimum((t * SEED_GNSS_RATE_HZ).astype(int), n_fix - 1)]
    slow_amp = SEED_GNSS_SLOW_AMPLITUDE_M
    slow = np.column_stack(
        [
            slow_amp * np.sin(2 * math.pi * t / t_slow),
            slow_amp * 2 * math.pi / t_slow * np.cos(2 * math.pi * t / t_slow),
        ]
    )
    gnss = held + slow
    every = round(1.0 / SEED_GNSS_RATE_HZ / dt)
    results = {}
    for name, sched in (
        ("classic", ((0.0, fixed_filter("comp1")),)),
        ("comp3f", ((0.0, fixed_filter("comp3f")),)),
        ("compvs", VS_SCHEDULE),
    ):
        results[name] = run_compensation(sched, xi1, gnss, t, every)
    late = t >= 300.0
    free_max = float(np.max(np.abs(ds)))
    cl = float(np.max(np.abs(results["classic"][late, 0])))
    vs = results["compvs"][late, 0]
    vs_rms = float(np.sqrt(np.mean(vs**2)))
    f3 = results["comp3f"][late, 0]
    rep.add(
        "000", "free INS coordinate error over the run", "~140 km", f"{free_max / 1e3:.0f} km (sized to it)"
    )
    rep.add("000", "classic compensation (T = 5 s) coordinate error", "~400 m", f"max {cl:.0f} m")
    rep.add(
        "000",
        "variable-structure filter coordinate error",
        "5–10 m",
        f"RMS {vs_rms:.1f} m, 95 % {np.percentile(np.abs(vs), 95):.1f} m, max {np.max(np.abs(vs)):.1f} m",
    )
    rep.add(
        "000",
        "fixed (15p+1)/(5p+1)³ coordinate error (steady)",
        "(same as VS once settled)",
        f"RMS {np.sqrt(np.mean(f3**2)):.1f} m",
    )
    v_cl = float(np.max(np.abs(results["classic"][late, 1])))
    v_vs = float(np.sqrt(np.mean(results["compvs"][late, 1] ** 2)))
    rep.add(
        "000", "velocity channel error: classic max / VS RMS", "(not given)", f"{v_cl:.2f} / {v_vs:.3f} m/s"
    )
    # Transients: a 250 m initial INS error, no GNSS noise (Figs. 11–12).
    e0 = 250.0
    tt = np.arange(0, 100.0 + 1e-9, 0.01)
    step = np.full((tt.size, 1), e0)
    zero = np.zeros_like(step)
    settle = {}
    overshoot = {}
    curves = {}
    for name, sched in (
        ("classic", ((0.0, fixed_filter("comp1")),)),
        ("comp3f", ((0.0, fixed_filter("comp3f")),)),
        ("compvs", VS_SCHEDULE),
    ):
        err = run_compensation(sched, step, zero, tt, 100)[:, 0]
        idx = np.nonzero(np.abs(err) > 0.05 * e0)[0]
        settle[name] = (idx[-1] + 1) * 0.01
        overshoot[name] = max(0.0, -float(err.min())) / e0 * 100
        curves[name] = err
    rep.add(
        "000",
        "transient, classic (to 5 %)",
        "3T = 15 s",
        f"{settle['classic']:.1f} s, overshoot {overshoot['classic']:.0f} %",
    )
    rep.add(
        "000",
        "transient, fixed 3rd order with forcing",
        "~30 s, with overshoot",
        f"{settle['comp3f']:.1f} s, overshoot {overshoot['comp3f']:.0f} %",
    )
    rep.add(
        "000",
        "transient, variable structure",
        "no overshoot",
        f"{settle['compvs']:.1f} s, overshoot {overshoot['compvs']:.1f} %",
    )
    rep.notes.append(
        "Seed 000 (reconstruction): 5000 s run, INS updated at 10 Hz, GNSS at 1 Hz with white "
        "noise σ 20 m / 0.2 m/s held over each second plus a slow DOP component (5 m sine, period "
        "2.5 Schuler periods). The paper does not give its INS error model; ours is the Schuler "
        "loop driven by a linearly growing gyro drift, sized so that ΔS(5000 s) = 140 km, plus a "
        "2 m/s initial velocity error. The classic scheme's error is ≈ T·dξ1/dt (1 − F = Tp/(Tp+1) "
        f"lets a ramp through as T times its slope): our INS error rate reaches "
        f"{np.max(np.abs(dv)):.0f} m/s, hence ≈ {5 * np.max(np.abs(dv)):.0f} m; the paper's ~400 m "
        "implies an INS error rate of ~80 m/s at the end of its run (not stated). The VS/forcing "
        "figures are dominated by the GNSS noise passed by F (the slow component passes entirely), "
        "not by the INS error, which 1 − F removes to its second derivative."
    )
    rep.notes.append(
        "Transient: 250 m initial INS error, no GNSS noise, filter starting at rest, settling = last "
        "time |error| > 5 % of the initial error. Variable structure with the bumpless rule of "
        "docs/estimators.md (output continuous, slope carried between the forcing stages)."
    )
    rep.series["000"] = {"t": t, "free": ds, **{k: v[:, 0] for k, v in results.items()}}
    rep.series["000_transient"] = {"t": tt, **curves}


# ---------------------------------------------------------------------------------------------
# lecture (001)


def lecture(rep: Report, rng: np.random.Generator) -> None:
    q, r = 0.01**2, 0.2**2
    k_inf, sigma = scalar_kf.steady_state(q, r)
    rms, _ = scalar_kf.monte_carlo(q, r, 0.01, 2000, 1000, rng)
    rep.add("001", "steady Kalman gain K∞", "≈ 0.0488 (digest)", f"{k_inf:.4f}")
    rep.add("001", "steady σ∞ of the velocity error", "≈ 0.044 m/s (digest)", f"{sigma:.4f} m/s (Riccati)")
    rep.add(
        "001",
        "σ from 1000-run Monte-Carlo, last 500 steps",
        "—",
        f"{np.sqrt(np.mean(rms[-500:] ** 2)):.4f} m/s",
    )
    rep.notes.append("Lecture: step 0.1 s, σ_GNSS = 0.2 m/s, σ_n = 0.01 m/s per step, as given.")


# ---------------------------------------------------------------------------------------------
# seed 004


def seed004(rep: Report, rng: np.random.Generator, bias_repeats: int = 50) -> None:
    p = ins7.Ins7Params()
    n, runs = 900, 1000
    covs, _ = ins7.riccati(p, n)
    sigma = np.sqrt(np.diagonal(covs, axis1=1, axis2=2))
    t0 = time.perf_counter()
    rms = ins7.monte_carlo(p, n, runs, rng)
    mc_s = time.perf_counter() - t0
    ratio = rms / sigma
    rel = np.abs(ratio - 1.0)
    names = ins7.STATE_NAMES
    worst = ", ".join(f"{names[i]} {100 * rel[:, i].max():.1f} %" for i in range(7))
    within = 100 * float(np.mean(rel < 0.05))
    # The model is linear-Gaussian and the MC shares Φ, Q_d, R, P0 and the gains with the
    # Riccati recursion, so at each time runs·RMS²/σ² ~ χ²(runs) exactly: a per-point 95 % band.
    lo, hi = np.sqrt(chi2.ppf([0.025, 0.975], runs) / runs)
    in_band = 100 * float(np.mean((ratio >= lo) & (ratio <= hi)))
    # Systematic bias: points of one MC share its runs (strongly correlated in time), so one MC
    # cannot tell a 1 % bias from sampling noise. Independent repeats can: the time mean of
    # RMS²/σ² − 1 per state and repeat has mean 0 without a mismatch, and its spread over the
    # repeats gives the standard error.
    reps = rng.spawn(bias_repeats)
    m = np.empty((bias_repeats, 7))
    pooled = np.zeros((n, 7))
    dev_one = np.empty(bias_repeats)
    for i, g in enumerate(reps):
        r = ins7.monte_carlo(p, n, runs, g)
        m[i] = np.mean(r**2 / sigma**2, axis=0) - 1.0
        pooled += r**2
        dev_one[i] = np.mean(np.abs(r / sigma - 1.0))
    bias = m.mean(axis=0)
    se = m.std(axis=0, ddof=1) / math.sqrt(bias_repeats)
    tstat = bias / se
    # |t| the largest of 7 independent t(K−1) values exceeds by chance with probability 5 %
    t_crit = float(student_t.ppf(1 - (1 - 0.95 ** (1 / 7)) / 2, bias_repeats - 1))
    pooled_dev = np.abs(np.sqrt(pooled / bias_repeats) / sigma - 1.0)
    n_pooled = bias_repeats * runs
    iw = np.unravel_index(int(np.argmax(pooled_dev)), pooled_dev.shape)
    t_op10 = ins7.time_to_operating_mode(sigma[:, :2], p.dt_s, 0.1)
    t_op20 = ins7.time_to_operating_mode(sigma[:, :2], p.dt_s, 0.2)
    rep.add(
        "004",
        "1000-run MC RMS vs Riccati σ",
        "curves practically coincide",
        f"mean |dev| {100 * rel.mean():.1f} %, within 5 % at {within:.1f} % of (time, state) points",
    )
    rep.add(
        "004",
        f"same MC inside the 95 % sampling band of a {runs}-run RMS, "
        f"sqrt(χ²({runs})/{runs}) = [{lo:.3f}, {hi:.3f}] σ",
        "(95 % expected without a mismatch)",
        f"{in_band:.1f} % of (time, state) points",
    )
    rep.add(
        "004",
        f"mean |dev| of one {runs}-run MC, over {bias_repeats} independent repeats",
        f"{100 * math.sqrt(2 / math.pi) / math.sqrt(2 * runs):.1f} % expected from sampling alone",
        f"median {100 * np.median(dev_one):.1f} %, "
        f"range {100 * dev_one.min():.1f}–{100 * dev_one.max():.1f} %",
    )
    rep.add(
        "004",
        f"systematic bias: time mean of RMS²/σ² − 1 per state, {bias_repeats} × {runs} runs",
        "0 (MC and Riccati share Φ, Q_d, R, P0)",
        ", ".join(f"{names[i]} {100 * bias[i]:+.2f} ± {100 * se[i]:.2f} %" for i in range(7))
        + f"; largest |t| {np.max(np.abs(tstat)):.1f} (5 % chance level for the largest of 7: {t_crit:.1f})",
    )
    rep.add(
        "004",
        f"pooled {n_pooled}-run RMS vs Riccati σ, worst point",
        f"per-point sampling σ {100 / math.sqrt(2 * n_pooled):.2f} %",
        f"{100 * pooled_dev.max():.2f} % ({names[iw[1]]} at t = {(iw[0] + 1) * p.dt_s:.0f} s; "
        f"mean over points {100 * pooled_dev.mean():.2f} %)",
    )
    rep.add("004", "worst deviation per state over 900 s", "—", worst)
    rep.add(
        "004",
        "time to operating mode",
        "≈ 2 min",
        f"{t_op20:.0f} s (σ of β, ΔV within 20 % of final), {t_op10:.0f} s (10 %)",
    )
    rep.add("004", "Monte-Carlo cost, 1000 runs × 900 steps, vectorised", "—", f"{mc_s:.2f} s")
    rep.notes.append(
        "Seed 004 (reconstruction; the paper gives only R and g): GNSS 1 Hz σ_S = 5 m, gyro drift "
        "Gauss–Markov 1 °/h with T_ω = 1 h, accelerometer 0.5 mg with T_α = 600 s, priors β 1 mrad, "
        "ΔV 0.5 m/s, ΔS 10 m, ΔV_k 0.002 m/s, ΔS_k 2 m. Exact discretisation (Van Loan) used by both "
        "the Riccati recursion and the Monte-Carlo (same Φ, Q_d, P0, R, gains), so the Riccati σ is "
        f"the true σ of the simulated filter. With {runs} runs the sample RMS has a relative standard "
        f"error of 1/sqrt(2·{runs}) = {100 / math.sqrt(2 * runs):.1f} % at each time, so 'within 5 % at "
        "every time' is a 2.2-sigma band and a few excursions over 900 × 7 points are expected; the "
        "exact per-point band is the χ² one. The points of one MC are strongly correlated in time "
        "(the same runs; ΔV_k and ΔS_k have no process noise at all), so its mean |dev| varies from "
        "one MC to the next far more than independent points would: the independent repeats measure "
        "that spread and test for a systematic bias (mean ± standard error over the repeats per "
        "state; no mismatch = every |t| below the chance level). Early points are dominated by the "
        "runs' prior draws (ΔV hardly changes in the first seconds), so a pooled worst point there "
        "measures how those particular draws scatter, not the model. ΔS and ΔS_k are only separable "
        "through the Schuler dynamics, so the position σ is "
        "floored by the GNSS systematic error prior."
    )
    rep.series["004"] = {"t": np.arange(1, n + 1) * p.dt_s, "sigma": sigma, "rms": rms}


# ---------------------------------------------------------------------------------------------
# plots


def all_filters() -> list[TransferFunction]:
    fs = [fixed_filter(k) for k in ("comp1", "comp2", "comp3", "comp3f")]
    fs += [tf for _, tf in VS_SCHEDULE]
    fs += [complementary2(0.07, 0.005), complementary3(0.07, 0.005, 1e-4), aperiodic(1, 0.5)]
    seen: dict[str, TransferFunction] = {}
    for tf in fs:
        seen.setdefault(tf.label, tf)
    return list(seen.values())


def write_plots(rep: Report, out: Path) -> list[Path]:
    import matplotlib  # lazy: matplotlib costs ~1 s; only --plots draws

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt  # lazy: as above, and after the backend is chosen

    out.mkdir(parents=True, exist_ok=True)
    paths = []
    w = np.logspace(-4, 2, 600)
    fig, axes = plt.subplots(2, 2, figsize=(12, 8), sharex=True)
    for tf in all_filters():
        for col, g in enumerate((tf, tf.complement())):
            h = g.freq_response(w)
            axes[0, col].semilogx(w, 20 * np.log10(np.abs(h) + 1e-300), label=tf.label)
            axes[1, col].semilogx(w, np.degrees(np.unwrap(np.angle(h))), label=tf.label)
    axes[0, 0].set_title("F(p)")
    axes[0, 1].set_title("1 − F(p)")
    for ax in axes.flat:
        ax.grid(True, which="both", alpha=0.3)
    axes[0, 0].set_ylim(-80, 10)
    axes[0, 1].set_ylim(-120, 10)
    axes[1, 0].set_xlabel("ω, rad/s")
    axes[1, 1].set_xlabel("ω, rad/s")
    axes[0, 0].set_ylabel("magnitude, dB")
    axes[1, 0].set_ylabel("phase, deg")
    axes[0, 1].legend(fontsize=7)
    fig.tight_layout()
    paths.append(out / "bode.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    s = rep.series["000"]
    fig, axes = plt.subplots(2, 1, figsize=(11, 7))
    axes[0].plot(s["t"], s["free"] / 1e3)
    axes[0].set_ylabel("free INS error, km")
    for k in ("classic", "comp3f", "compvs"):
        axes[1].plot(s["t"], s[k], label=k, lw=0.6)
    axes[1].set_ylim(-500, 500)
    axes[1].set_ylabel("coordinate error, m")
    axes[1].set_xlabel("t, s")
    axes[1].legend()
    fig.tight_layout()
    paths.append(out / "seed000_errors.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    s = rep.series["000_transient"]
    fig, ax = plt.subplots(figsize=(9, 5))
    for k in ("classic", "comp3f", "compvs"):
        ax.plot(s["t"], s[k], label=k)
    ax.axhline(0, color="k", lw=0.5)
    ax.set_xlabel("t, s")
    ax.set_ylabel("error, m (250 m initial INS error)")
    ax.legend()
    fig.tight_layout()
    paths.append(out / "seed000_transient.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)

    s = rep.series["004"]
    fig, axes = plt.subplots(1, 3, figsize=(14, 4))
    for ax, i, unit in zip(axes, (0, 1, 2), ("rad", "m/s", "m"), strict=True):
        ax.plot(s["t"], s["sigma"][:, i], label="Riccati σ")
        ax.plot(s["t"], s["rms"][:, i], "--", label="MC RMS (1000)")
        ax.set_title(f"{ins7.STATE_NAMES[i]}, {unit}")
        ax.set_xlabel("t, s")
        ax.legend()
    fig.tight_layout()
    paths.append(out / "seed004_mc_vs_riccati.png")
    fig.savefig(paths[-1], dpi=110)
    plt.close(fig)
    if "uav" in rep.series:
        paths.append(plot_uav(rep.series["uav"], out))
        paths.append(plot_nees(rep.series["uav_nees"], out))
    return paths


def run_all(rng: np.random.Generator, uav: bool, uav_kw: dict[str, Any] | None = None) -> Report:
    rep = Report()
    seed003(rep)
    seed000(rep, rng)
    lecture(rep, rng)
    seed004(rep, rng)
    if uav:
        uav_comparison(rep, **(uav_kw or {}))
    return rep


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench seeds", description=__doc__.splitlines()[0])
    ap.add_argument("--plots", type=Path, default=None, help="write Bode and error plots into DIR")
    ap.add_argument("--seed", type=int, default=SEED, help="RNG seed (printed in the output)")
    ap.add_argument("--no-uav", action="store_true", help="skip the UAV estimator comparison")
    ap.add_argument("--nees-runs", type=int, default=26, help="UAV NEES Monte-Carlo runs (default 26)")
    ap.add_argument(
        "--nees-duration", type=float, default=320.0, help="seconds of scenario per NEES run (default 320)"
    )
    ap.add_argument(
        "--nees-ablation", action="store_true", help="also the NEES ablation sets (R inflated; clean IMU)"
    )
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch docs/benchmarks.md")
    args = ap.parse_args(argv)
    rng = np.random.default_rng(args.seed)
    uav_kw = {
        "nees_runs": args.nees_runs,
        "nees_duration_s": args.nees_duration,
        "ablation": args.nees_ablation,
    }
    rep = run_all(rng, not args.no_uav, uav_kw)
    md = rep.markdown() + f"\n\nRNG seed {args.seed}."
    print(md)
    if not args.no_write:
        write_section("seeds", md, command_line())
    if args.plots is not None:
        for p in write_plots(rep, args.plots):
            print(f"wrote {p}")
    return 0


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))

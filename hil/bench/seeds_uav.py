"""Beyond the papers: every live estimator on the UAV survey, tactical IMU, seed GNSS model.

Runs the registry's estimators side by side on one synchronised input stream (ideal timing:
IMU and GNSS stamped with their true times, GNSS delivered between the IMU steps around its
time of validity, as the fusion core does), with the free strapdown INS as the shared ``ins``.

The issue asks for the *seed* GNSS model, not the scenario's own receiver: the rig's GNSS
emulator is configured with the seed-000 figures (:data:`hil.bench.seeds_common.SEED_GNSS_RATE_HZ` and
siblings) and the scenario's GNSS fault events are dropped, so the estimators see the error
model the paper's numbers were made with. ``gnss_model="scenario"`` keeps the scenario's own
receiver (what the unit tests of ekf15 use).

The slow component is common to every GNSS fix: no GNSS-aided filter can separate it from the
truth, so :func:`run_uav` also returns it, and the bench reports each error relative to the
GNSS reference (truth + slow component) beside the error relative to the truth.
"""

from __future__ import annotations

import os
import time
import tomllib
from concurrent.futures import ProcessPoolExecutor
from dataclasses import replace
from pathlib import Path
from typing import Any

import numpy as np
from scipy.stats import chi2

from hil.bench.seeds_common import (
    SEED_GNSS_POS_SIGMA_M,
    SEED_GNSS_RATE_HZ,
    SEED_GNSS_SLOW_AMPLITUDE_M,
    SEED_GNSS_SLOW_PERIOD_S,
    SEED_GNSS_VEL_SIGMA_MPS,
    Report,
)
from hil.estimators.base import Estimator, GnssInput, ImuInput, InitialState
from hil.estimators.compensation import VS_SCHEDULE
from hil.estimators.ekf15 import Ekf15
from hil.estimators.lti import held_noise_gain
from hil.estimators.registry import make_estimator
from hil.estimators.tuning import params_for
from hil.nav.attitude import quat_to_dcm
from hil.nav.scenario import Scenario, dump_toml, load_scenario, parse_scenario, scenario_overrides
from hil.nav.strapdown import strapdown_from_initial, strapdown_step, to_nav_state
from hil.nav.trajectory import TruthGenerator
from hil.nav.types import F64, NavState
from hil.sensors.gnss import GnssEmulatorCore
from hil.sensors.imu import ImuEmulatorCore, sensor_rng

NAMES = ("comp1", "comp3f", "compvs", "cf3", "kfvel", "ekf15", "ekf15s", "ekf30")
# Bench-only variants: display name -> (registry name, tell ekf15 the GNSS receiver model, add
# the gyro scale-factor/misalignment states). ``ekf15`` is the live fusion's filter (tuned from
# the IMU, told the antenna lever arm, R from the fix's reported σ); ``ekf15s`` is the same filter
# told the receiver's slow error too (tuning.ekf15_gnss_params); ``ekf30`` also estimates the
# gyro scale factor and misalignment (15 + 9 + 6 states). ``ekf15r`` (ablation) is the tempting
# wrong fix: R inflated by the slow error's variance.
VARIANTS: dict[str, tuple[str, bool, bool]] = {
    "ekf15s": ("ekf15", True, False),
    "ekf30": ("ekf15", True, True),
    "ekf15r": ("ekf15", False, False),
}


class RInflatedEkf15(Ekf15):
    """ekf15 with the slow error's variance added to each fix's position σ² (ablation only)."""

    def __init__(self, name: str, init: InitialState, extra_var_m2: float, **params: Any) -> None:
        super().__init__(name, init, **params)
        self.extra_var_m2 = extra_var_m2

    def on_gnss(self, gnss: GnssInput, ins: NavState) -> None:
        sig = np.sqrt(np.square(gnss.pos_sigma_m) + self.extra_var_m2)
        super().on_gnss(replace(gnss, pos_sigma_m=sig), ins)


NEES_DOF = 6  # position + velocity
SETTLE_S = 60.0


# The ablation's "clean" sensors: what ekf15 does not model, set to zero.
CLEAN_IMU = {
    "gyro_scale_factor_ppm": 0.0,
    "gyro_misalignment_mrad": 0.0,
    "accel_scale_factor_ppm": 0.0,
    "accel_misalignment_mrad": 0.0,
}


def seed_gnss_scenario(
    duration_s: float | None, seed: int, imu_preset: str = "tactical", clean: bool = False
) -> Scenario:
    """uav_survey with the ``imu_preset`` IMU and the seed-000 GNSS model.

    GNSS: 1 Hz, white σ 20 m per coordinate (N, E, D) and 0.2 m/s per velocity axis, slow 5 m
    sine per axis with period 2.5 Schuler periods (random phase per axis, from the GNSS
    generator). The scenario's GNSS events (the 50 m pulse at 500 s) are dropped: they are not
    part of the seed model. Its lever arm (0.18 m) and output latency stay; with ideal timing the
    latency does not matter and 0.18 m is 1 % of the white σ.
    """
    base = load_scenario("uav_survey")
    doc = tomllib.loads(base.source_text)
    doc["seed"] = int(seed)
    if duration_s is not None:
        doc["duration_s"] = float(duration_s)
    doc["imu"]["preset"] = imu_preset
    if clean:
        doc["imu"].update(CLEAN_IMU)
        doc["gnss"]["lever_arm_b_m"] = [0.0, 0.0, 0.0]
    doc["gnss"].update(
        rate_hz=SEED_GNSS_RATE_HZ,
        pos_sigma_m=SEED_GNSS_POS_SIGMA_M,
        vel_sigma_mps=SEED_GNSS_VEL_SIGMA_MPS,
        slow_amplitude_m=SEED_GNSS_SLOW_AMPLITUDE_M,
        slow_period_s=SEED_GNSS_SLOW_PERIOD_S,
    )
    doc["event"] = [e for e in doc.get("event", []) if not str(e.get("kind", "")).startswith("gnss_")]
    if not doc["event"]:
        del doc["event"]
    text = dump_toml(doc, header=f"uav_survey (sha256 {base.sha256[:12]}) with the seed-000 GNSS model")
    return parse_scenario(text, "uav_survey_seed_gnss")


def uav_scenario(duration_s: float | None, seed: int, gnss_model: str = "seed") -> Scenario:
    """The UAV comparison's scenario: tactical IMU, GNSS per ``gnss_model`` (seed / scenario /
    seed_clean: the seed model with the errors ekf15 does not model removed)."""
    if gnss_model in ("seed", "seed_clean"):
        return seed_gnss_scenario(duration_s, seed, clean=gnss_model == "seed_clean")
    if gnss_model != "scenario":
        raise ValueError(f"gnss_model must be 'seed', 'seed_clean' or 'scenario', got {gnss_model!r}")
    kw: dict[str, Any] = {"imu_preset": "tactical", "seed": seed}
    if duration_s is not None:
        kw["duration_s"] = duration_s
    return scenario_overrides(load_scenario("uav_survey"), **kw)


def slow_component(gnss: GnssEmulatorCore, t_s: F64) -> F64:
    """The emulator's slow (geometry) position error at ``t_s``, ``(n, 3)`` (same formula)."""
    cfg = gnss.cfg
    arg = 2.0 * np.pi * np.asarray(t_s, float)[:, None] / cfg.slow_period_s + gnss.slow_phase_rad
    return np.asarray(cfg.slow_amplitude_m) * np.sin(arg)


TURN_RATE_RADPS = 0.02  # the survey's turns run at 12 deg/s (0.21 rad/s); legs at Earth rate
AFTER_TURN_S = 30.0


def after_turn(t_s: F64, rate_radps: F64) -> F64:
    """Epochs in a turn (body rate above :data:`TURN_RATE_RADPS`) or up to
    :data:`AFTER_TURN_S` after one: where errors the filter does not model (gyro and
    accelerometer scale factor and misalignment, the lever arm) are excited."""
    turning = np.asarray(rate_radps) > TURN_RATE_RADPS
    last = np.where(turning, t_s, -np.inf)
    return (t_s - np.maximum.accumulate(last)) <= AFTER_TURN_S


def run_uav(
    duration_s: float | None,
    seed: int,
    names: tuple[str, ...] = NAMES,
    gnss_model: str = "seed",
    params: dict[str, dict[str, Any]] | None = None,
    timed: bool = True,
) -> dict[str, Any]:
    """Errors of every estimator vs truth at each IMU step (decimated to 10 Hz) and EKF NEES.

    ``duration_s`` None runs the whole scenario. ``params`` default to what the fusion core
    gives (:func:`hil.estimators.tuning.params_for` of the scenario's IMU; for the
    :data:`VARIANTS`, of its IMU and GNSS). The free INS is only integrated when an estimator
    other than the EKFs needs it (they carry their own strapdown). NEES is computed for every
    estimator with a covariance ``p``. ``timed`` False skips the per-call clock reads
    (Monte-Carlo workers).
    """
    sc = uav_scenario(duration_s, seed, gnss_model)
    truth = TruthGenerator(sc)
    init = truth.initial_state()
    imu = ImuEmulatorCore(sc, truth, sensor_rng(sc.seed, "imu"))
    gnss = GnssEmulatorCore(sc, truth, sensor_rng(sc.seed, "gnss"))
    n = int(sc.duration_s * imu.rate_hz)
    batch = imu.next_batch(n)
    n = batch.t_ns.size
    fixes = gnss.next_batch(int(batch.t_ns[-1]))
    p_live = params_for(sc.imu.params, sc.gnss) if params is None else params
    ests: dict[str, Estimator] = {}
    for nm in names:
        reg, receiver, cal = VARIANTS.get(nm, (nm, False, False))
        p = p_live
        if params is None and (receiver or cal):
            p = params_for(sc.imu.params, sc.gnss, receiver_model=receiver, gyro_cal=cal)
        if nm == "ekf15r":
            var = float(np.max(sc.gnss.slow_amplitude_m)) ** 2 / 2.0
            ests[nm] = RInflatedEkf15(nm, init, var, **p_live.get("ekf15", {}))
            continue
        ests[nm] = make_estimator(reg, init, p.get(reg))
    need_ins = any(VARIANTS.get(nm, (nm,))[0] != "ekf15" for nm in names)
    free = strapdown_from_initial(init)
    ins = to_nav_state(free, init)
    dec = max(1, round(imu.rate_hz / 10))
    keep = np.arange(dec - 1, n, dec)
    tb = truth.sample(batch.t_ns[keep])
    err_pos = {nm: np.empty((keep.size, 3)) for nm in (*names, "ins")}
    err_vel = {nm: np.empty((keep.size, 3)) for nm in (*names, "ins")}
    nees = {nm: np.empty(keep.size) for nm, e in ests.items() if hasattr(e, "p")}
    nees_pv = {nm: np.empty((keep.size, 2)) for nm in nees}  # position / velocity parts, 3 dof each
    cost = dict.fromkeys(names, 0.0)
    clock = time.perf_counter if timed else (lambda: 0.0)
    g = 0
    j = 0
    for k in range(n):
        t_ns = int(batch.t_ns[k])
        if need_ins:
            free = strapdown_step(free, batch.dtheta_b_rad[k], batch.dvel_b_mps[k], batch.dt_s)
            ins = to_nav_state(free, init)
        u = ImuInput(t_ns, batch.dt_s, batch.dtheta_b_rad[k], batch.dvel_b_mps[k])
        for nm, e in ests.items():
            t0 = clock()
            e.on_imu(u, ins)
            cost[nm] += clock() - t0
        t_next = int(batch.t_ns[k + 1]) if k + 1 < n else t_ns + 1
        while g < fixes.t_valid_ns.size and fixes.t_valid_ns[g] < t_next:
            fx = GnssInput.of_batch(fixes, g)
            for nm, e in ests.items():
                t0 = clock()
                e.on_gnss(fx, ins)
                cost[nm] += clock() - t0
            g += 1
        if j < keep.size and k == keep[j]:
            err_pos["ins"][j] = ins.pos_ned_m - tb.pos_ned_m[j]
            err_vel["ins"][j] = ins.vel_ned_mps - tb.vel_ned_mps[j]
            for nm, e in ests.items():
                s = e.solution()
                err_pos[nm][j] = s.pos_ned_m - tb.pos_ned_m[j]
                err_vel[nm][j] = s.vel_ned_mps - tb.vel_ned_mps[j]
                if nm in nees:
                    p = e.p  # type: ignore[attr-defined]
                    x = np.concatenate([err_pos[nm][j], err_vel[nm][j]])
                    nees[nm][j] = float(x @ np.linalg.solve(p[:NEES_DOF, :NEES_DOF], x))
                    nees_pv[nm][j, 0] = float(x[:3] @ np.linalg.solve(p[:3, :3], x[:3]))
                    nees_pv[nm][j, 1] = float(x[3:] @ np.linalg.solve(p[3:6, 3:6], x[3:]))
            j += 1
    t_s = tb.t_ns * 1e-9
    return {
        "t": t_s,
        "pos": err_pos,
        "vel": err_vel,
        "slow": slow_component(gnss, t_s),
        "after_turn": after_turn(t_s, np.linalg.norm(tb.w_ib_b_radps, axis=1)),
        "nees": nees,
        "nees_pv": nees_pv,
        "pos_sigma_end": {nm: np.sqrt(np.diag(ests[nm].p)[:3]) for nm in nees},  # type: ignore[attr-defined]
        "cost_us": {nm: c / n * 1e6 for nm, c in cost.items()},
        "estimators": ests,
        "gyro_error_matrix": imu.gyro.matrix - np.eye(3),  # the drawn E: ω_meas = (I + E) ω + b
        "n_steps": n,
        "duration_s": sc.duration_s,
        "scenario": sc,
    }


# ---------------------------------------------------------------------------------------------
# figures


def rms(x: F64) -> float:
    return float(np.sqrt(np.mean(np.square(x))))


def horiz(x: F64) -> F64:
    """Horizontal norm of ``(n, 3)`` NED vectors."""
    return np.linalg.norm(x[:, :2], axis=1)


def nees_band(runs: int, dof: int = NEES_DOF, p: float = 0.95) -> tuple[float, float]:
    """Two-sided ``p`` band of the run-averaged NEES: ``χ²(dof·runs)/runs`` quantiles."""
    lo, hi = chi2.ppf([(1 - p) / 2, (1 + p) / 2], dof * runs) / runs
    return float(lo), float(hi)


MC_NAMES = ("ekf15", "ekf15s", "ekf30")


def _nees_worker(job: tuple[float, int, tuple[str, ...], str]) -> dict[str, Any]:
    """One Monte-Carlo run of the EKF variants ``names`` on the same inputs (paired)."""
    duration_s, seed, names, gnss_model = job
    r = run_uav(duration_s, seed, names, gnss_model, timed=False)
    late = r["t"] >= SETTLE_S
    out: dict[str, Any] = {"t": r["t"], "after_turn": r["after_turn"]}
    for nm in names:
        e = r["pos"][nm][late]
        out[nm] = {
            "nees": r["nees"][nm],
            "nees_pv": r["nees_pv"][nm],
            "hp_rms": rms(horiz(e)),
            "hp_rms_ref": rms(horiz(e - r["slow"][late])),
        }
    return out


def nees_monte_carlo(
    runs: int,
    duration_s: float,
    first_seed: int = 1000,
    workers: int = 2,
    names: tuple[str, ...] = MC_NAMES,
    gnss_model: str = "seed",
) -> dict[str, Any]:
    """Both EKF variants over ``runs`` sensor seeds (IMU and GNSS noise, slow-component phase).

    Per variant: the run-averaged NEES per epoch, the fraction of epochs after
    :data:`SETTLE_S` inside the two-sided 95 % band of that average, its time mean (and the
    position and velocity parts), and each run's horizontal RMS vs truth and vs the GNSS
    reference, so the spread over slow-component phases is visible.
    """
    jobs = [(duration_s, first_seed + i, names, gnss_model) for i in range(runs)]
    with ProcessPoolExecutor(max_workers=workers) as ex:
        out = list(ex.map(_nees_worker, jobs))
    t = out[0]["t"]
    late = t >= SETTLE_S
    lo, hi = nees_band(runs)
    res: dict[str, Any] = {"t": t, "band": (lo, hi), "runs": runs, "duration_s": duration_s}
    turn = out[0]["after_turn"]  # the same trajectory in every run
    for nm in names:
        mean = np.mean([o[nm]["nees"] for o in out], axis=0)
        pv = np.mean([o[nm]["nees_pv"] for o in out], axis=0)
        res[nm] = {
            "nees_mean": mean,
            "inside": float(np.mean((mean[late] >= lo) & (mean[late] <= hi))),
            "above": float(np.mean(mean[late] > hi)),
            "below": float(np.mean(mean[late] < lo)),
            "mean": float(np.mean(mean[late])),
            "mean_pos": float(np.mean(pv[late, 0])),
            "mean_vel": float(np.mean(pv[late, 1])),
            "mean_vel_turn": float(np.mean(pv[late & turn, 1])),
            "mean_vel_leg": float(np.mean(pv[late & ~turn, 1])),
            "hp_rms": np.array([o[nm]["hp_rms"] for o in out]),
            "hp_rms_ref": np.array([o[nm]["hp_rms_ref"] for o in out]),
        }
    return res


def _lever_worker(seed: int) -> dict[str, tuple[float, float]]:
    """ekf15 on uav_survey's own receiver (σ 1.5 m, 0.18 m arm) told the lever arm, and not."""
    sc = uav_scenario(LEVER_RUN_S, seed, "scenario")
    truth = TruthGenerator(sc)
    out: dict[str, tuple[float, float]] = {}
    for tag, p in (("told", params_for(sc.imu.params, sc.gnss)), ("not told", params_for(sc.imu.params))):
        r = run_uav(LEVER_RUN_S, seed, ("ekf15",), "scenario", params=p, timed=False)
        late = r["t"] >= SETTLE_S
        e = r["pos"]["ekf15"][late]
        tb = truth.sample(np.round(r["t"][late] * 1e9).astype(np.int64))
        along = np.sum(e * quat_to_dcm(tb.q_nb)[:, :, 0], axis=1)  # error along the body x axis
        out[tag] = (rms(horiz(e)), float(np.mean(along)))
    return out


LEVER_RUN_S = 300.0


def lever_arm_effect(runs: int = 6, first_seed: int = 10) -> dict[str, np.ndarray]:
    """Horizontal RMS and mean along-body-x error of ekf15 with and without the lever arm."""
    with ProcessPoolExecutor(max_workers=min(2, os.cpu_count() or 1)) as ex:
        out = list(ex.map(_lever_worker, range(first_seed, first_seed + runs)))
    return {tag: np.array([o[tag] for o in out]) for tag in ("told", "not told")}


def uav_comparison(
    rep: Report,
    duration_s: float | None = None,
    nees_runs: int = 26,
    nees_duration_s: float = 320.0,
    seed: int = 4,
    ablation: bool = False,
) -> None:
    """Side-by-side table (seed GNSS model, the whole uav_survey) and the EKF NEES Monte-Carlo.

    ``ablation`` adds two Monte-Carlo sets on the same seeds to attribute what NEES shows: ekf15
    with R inflated by the slow error's variance (the tempting fix), and ekf15s on sensors
    without the errors ekf15 does not model (IMU scale factor, misalignment, lever arm).
    """
    t0 = time.perf_counter()
    res = run_uav(duration_s, seed)
    wall = time.perf_counter() - t0
    late = res["t"] >= SETTLE_S
    table = _side_by_side_table(res, late)
    t1 = time.perf_counter()
    mc = nees_monte_carlo(nees_runs, nees_duration_s, workers=min(2, os.cpu_count() or 1))
    mc_wall = time.perf_counter() - t1
    run = (
        f"{res['duration_s']:.0f} s run{' (whole scenario)' if duration_s is None else ''}, "
        f"{res['n_steps']} IMU steps, {wall:.0f} s wall"
    )
    _add_accuracy_rows(rep, res, mc, late, run, f"{nees_runs} runs of {nees_duration_s:.0f} s")
    _add_lever_arm_row(rep, lever_arm_effect())
    sets = [(nm, mc[nm], "") for nm in MC_NAMES]
    if ablation:
        sets += _ablation_sets(nees_runs, nees_duration_s)
    _add_nees_rows(rep, sets, mc["band"], nees_runs)
    rep.add(
        "uav",
        "NEES Monte-Carlo cost",
        "—",
        f"{nees_runs} runs × {nees_duration_s:.0f} s × {len(MC_NAMES)} filters, 2 processes, "
        f"{mc_wall:.0f} s wall" + (" (ablation sets not included)" if ablation else ""),
    )
    rep.notes.append(_conditions_note(nees_runs, nees_duration_s) + "\n\n" + "\n".join(table))
    rep.notes.append(_nees_note())
    rep.series["uav"] = res
    rep.series["uav_nees"] = mc


def _side_by_side_table(res: dict[str, Any], late: np.ndarray) -> list[str]:
    """Markdown rows: every estimator's errors after settling, vs truth and vs the GNSS reference."""
    slow = res["slow"][late]
    lines = [
        "| estimator | horiz pos RMS m | horiz pos 95 % m | N / E RMS m | horiz pos RMS vs GNSS ref m "
        "| horiz vel RMS m/s | horiz vel 95 % m/s | cost µs/IMU step |",
        "| --- | --- | --- | --- | --- | --- | --- | --- |",
    ]
    for nm in ("ins", *NAMES):
        e = res["pos"][nm][late]
        hp = horiz(e)
        hv = horiz(res["vel"][nm][late])
        c = res["cost_us"].get(nm, float("nan"))
        lines.append(
            f"| {nm} | {rms(hp):.2f} | {np.percentile(hp, 95):.2f} | {rms(e[:, 0]):.2f} / {rms(e[:, 1]):.2f} "
            f"| {rms(horiz(e - slow)):.2f} | {rms(hv):.3f} | {np.percentile(hv, 95):.3f} | {c:.0f} |"
        )
    return lines


def _add_accuracy_rows(
    rep: Report, res: dict[str, Any], mc: dict[str, Any], late: np.ndarray, run: str, mc_runs: str
) -> None:
    """The run itself, the slow component, each EKF's position RMS (one run and the Monte-Carlo), compvs."""
    slow = res["slow"][late]
    rep.add("uav", "estimators side by side, seed GNSS model (table below)", "—", run)
    rep.add(
        "uav",
        "GNSS slow component alone, horizontal RMS over the same window",
        "—",
        f"{rms(horiz(slow)):.2f} m",
    )
    for nm, what in (
        ("ekf15", "ekf15 (15 states, the live filter)"),
        ("ekf15s", "ekf15s (+ GNSS slow states)"),
        ("ekf30", "ekf30 (+ gyro scale factor/misalignment + GNSS slow states)"),
    ):
        e = res["pos"][nm][late]
        m = mc[nm]
        rep.add(
            "uav",
            f"{what} horizontal position RMS (target ≤ 3 m)",
            "—",
            f"{rms(horiz(e)):.2f} m vs truth, {rms(horiz(e - slow)):.2f} m vs GNSS ref; "
            f"{mc_runs}: median {np.median(m['hp_rms']):.2f} m "
            f"(range {m['hp_rms'].min():.2f}–{m['hp_rms'].max():.2f} m) vs truth, median "
            f"{np.median(m['hp_rms_ref']):.2f} m vs GNSS ref",
        )
    vs = res["pos"]["compvs"][late]
    floor = SEED_GNSS_POS_SIGMA_M * held_noise_gain(VS_SCHEDULE[-1][1], 1.0 / SEED_GNSS_RATE_HZ)
    rep.add(
        "uav",
        "compvs horizontal position RMS (target ≤ 10 m)",
        "5–10 m per coordinate (seed 000)",
        f"{rms(horiz(vs)):.2f} m horizontal (N {rms(vs[:, 0]):.2f} m, E {rms(vs[:, 1]):.2f} m); "
        f"{rms(horiz(vs - slow)):.2f} m vs GNSS ref. Floor from the white noise alone (its last "
        f"stage's gain on σ {SEED_GNSS_POS_SIGMA_M:.0f} m held 1 s, lti.held_noise_gain): "
        f"{floor:.2f} m per coordinate, {floor * np.sqrt(2):.2f} m horizontal; the slow component "
        "passes F whole",
    )


def _add_lever_arm_row(rep: Report, lev: dict[str, np.ndarray]) -> None:
    """ekf15 told the antenna lever arm or not (:func:`lever_arm_effect`)."""
    told, not_told = lev["told"], lev["not told"]
    arm = uav_scenario(10.0, 1, "scenario").gnss.lever_arm_b_m
    rep.add(
        "uav",
        f"ekf15 told the antenna lever arm {tuple(arm)} m or not: uav_survey's own receiver "
        f"(σ 1.5 m), {len(told)} runs of {LEVER_RUN_S:.0f} s",
        "—",
        f"horizontal RMS {told[:, 0].mean():.3f} vs {not_told[:, 0].mean():.3f} m (better in "
        f"{int(np.sum(told[:, 0] < not_told[:, 0]))} of {len(told)} runs); mean error along body x "
        f"{told[:, 1].mean():+.3f} vs {not_told[:, 1].mean():+.3f} m (the arm's x is {arm[0]:.2f} m)",
    )


def _ablation_sets(nees_runs: int, nees_duration_s: float) -> list[tuple[str, dict[str, Any], str]]:
    """The two ablation Monte-Carlo sets: ekf15 with R inflated, ekf15s on clean sensors."""
    workers = min(2, os.cpu_count() or 1)
    mc_r = nees_monte_carlo(nees_runs, nees_duration_s, workers=workers, names=("ekf15r",))
    mc_c = nees_monte_carlo(
        nees_runs, nees_duration_s, workers=workers, names=("ekf15s",), gnss_model="seed_clean"
    )
    return [
        ("ekf15r", mc_r["ekf15r"], " (ablation: ekf15 with R + slow variance)"),
        ("ekf15s", mc_c["ekf15s"], " (ablation: IMU without scale factor/misalignment, no lever arm)"),
    ]


def _add_nees_rows(
    rep: Report, sets: list[tuple[str, dict[str, Any], str]], band: tuple[float, float], nees_runs: int
) -> None:
    """One row per Monte-Carlo set: its run-averaged NEES against the χ² band."""
    lo, hi = band
    for nm, m, what in sets:
        rep.add(
            "uav",
            f"{nm}{what} NEES (pos+vel, {NEES_DOF} dof), mean over {nees_runs} runs",
            f"95 % band χ²({NEES_DOF}·{nees_runs})/{nees_runs} = [{lo:.2f}, {hi:.2f}]",
            f"time mean {m['mean']:.2f} (position part {m['mean_pos']:.2f}, velocity part "
            f"{m['mean_vel']:.2f}, 3 expected each; velocity part {m['mean_vel_turn']:.2f} in turns and "
            f"{AFTER_TURN_S:.0f} s after, {m['mean_vel_leg']:.2f} on the legs); inside the band at "
            f"{100 * m['inside']:.0f} % of "
            f"epochs (above {100 * m['above']:.0f} %, below {100 * m['below']:.0f} %)",
        )


def _conditions_note(nees_runs: int, nees_duration_s: float) -> str:
    """How the UAV comparison was run and how to read 'vs GNSS ref' (the table follows it)."""
    return (
        "UAV: uav_survey (8 legs of 120 s at 25 m/s joined by 180° turns from t = 150 s on) with "
        "the IMU preset overridden to tactical "
        f"and the scenario's GNSS overridden by the seed-000 model: {SEED_GNSS_RATE_HZ:.0f} Hz, white "
        f"σ {SEED_GNSS_POS_SIGMA_M:.0f} m per coordinate (N, E, D) and {SEED_GNSS_VEL_SIGMA_MPS} m/s per "
        f"velocity axis, slow component {SEED_GNSS_SLOW_AMPLITUDE_M:.0f} m sine per axis with period "
        f"{SEED_GNSS_SLOW_PERIOD_S:.0f} s (2.5 Schuler periods) and a random phase per axis; the "
        "scenario's 50 m GNSS pulse is dropped, its 0.18 m antenna lever arm kept (the EKFs are told "
        "it, as the live fusion is; the compensation and complementary filters have no attitude to "
        f"apply it with). Ideal timing, errors vs truth after the first {SETTLE_S:.0f} s, decimated "
        "to 10 Hz. ekf15 is tuned from the IMU preset as the fusion core does (hil.estimators.tuning) "
        "with R from the fix's reported σ, which is the white σ only; ekf15s is the same filter also "
        "told the receiver's slow error (6 states: a sine per axis, RMS 5/√2 m, the model's period); "
        "ekf30 is ekf15s with the gyro scale factor and misalignment as 9 more random-constant "
        "states (priors the preset's 150 ppm / 0.5 mrad). "
        "'vs GNSS ref' = error minus the slow component. The slow component is common to every "
        "fix: from GNSS alone no filter can observe it, and over one run it is a nearly constant "
        "offset (the run is a small part of its period), so the RMS vs truth of any well-smoothed "
        "estimator depends on its phase (hence the Monte-Carlo spread). ekf15s can separate part of "
        "it only because the rig aligns every estimator on the truth at t = 0 (its 3 m position "
        "prior is real knowledge); that knowledge decays as the INS position uncertainty grows, "
        "towards the slow σ. Monte-Carlo: scenario seeds "
        f"1000…{999 + nees_runs} (IMU and GNSS noise and slow-component phases), the first "
        f"{nees_duration_s:.0f} s of the scenario per run; the NEES band is for the "
        f"mean of {nees_runs} independent χ²({NEES_DOF}) values."
    )


def _nees_note() -> str:
    """Why the NEES of each EKF lands where it does (the ablation rows are the evidence)."""
    return (
        "UAV NEES, why: ekf15's position part is far above 3 because the slow component is not in "
        "its model: R holds the white σ only, and a common error is averaged away as if it were "
        "white, so its position σ ends well below the error it cannot see. Inflating R by the slow "
        "variance (12.5 m² on 400 m²) does not change that (ablation rows, with --nees-ablation): "
        "the error is correlated, not white. Told the slow error as states, ekf15s's position part "
        "is consistent (below 3 by the pessimism of its 3 m alignment prior on a truth-aligned "
        "start). ekf15's and ekf15s's velocity part is the same and its excess over 3 sits in "
        f"the turns and the {AFTER_TURN_S:.0f} s after them, where the gyro scale factor (150 ppm: a "
        "180° turn alone leaves 0.5 mrad of heading error) and misalignment (0.5 mrad: ~1.6 mrad of "
        "tilt through a turn) are excited, which neither models; the ablation removes them (and the "
        "accelerometer's, and the lever arm, which every EKF now knows). ekf30 carries them as "
        "states: σ 20 m fixes calibrate them only a little (tests/unit/test_ekf15_installation.py), "
        "but its attitude and velocity covariance then hold what the turns do. Earlier causes, "
        "fixed: ekf15's bias error used to decay as Gauss–Markov while its estimate was held "
        "(over-confident after turns, docs/estimators.md), and the lever arm was not modelled. "
        "Since 2026-12-03 the bias wander is told as the emulator makes it (its Gauss–Markov σ in "
        "the prior and the walk, each sensor's own τ; found by seed004's campaign, whose IMU is "
        "all wander): on this tactical IMU, whose 1 mg / 1 °/h turn-on bias dominates the prior, "
        "the NEES moved by under 1 % (ekf15 16.49 → 16.41, ekf30 5.61 → 5.57)."
    )


def plot_uav(res: dict[str, Any], out: Path) -> Path:
    import matplotlib.pyplot as plt  # lazy: matplotlib costs ~1 s; only --plots draws

    fig, ax = plt.subplots(figsize=(11, 5))
    for nm in NAMES:
        ax.plot(res["t"], horiz(res["pos"][nm]), lw=0.6, label=nm)
    ax.plot(res["t"], horiz(res["slow"]), "k--", lw=1.0, label="GNSS slow component")
    ax.set_ylim(0, 40)
    ax.set_xlabel("t, s")
    ax.set_ylabel("horizontal position error, m")
    ax.legend()
    fig.tight_layout()
    path = out / "uav_errors.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path


def plot_nees(mc: dict[str, Any], out: Path) -> Path:
    import matplotlib.pyplot as plt  # lazy: matplotlib costs ~1 s; only --plots draws

    fig, ax = plt.subplots(figsize=(11, 4))
    for nm in MC_NAMES:
        ax.plot(mc["t"], mc[nm]["nees_mean"], lw=0.6, label=f"{nm}: mean NEES over {mc['runs']} runs")
    for b in mc["band"]:
        ax.axhline(b, color="k", ls="--", lw=0.8)
    ax.set_xlabel("t, s")
    ax.set_ylabel("NEES (6 dof)")
    ax.legend()
    fig.tight_layout()
    path = out / "uav_nees.png"
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path

"""ekf15 told the installation: the GNSS antenna lever arm and the gyro scale factor/misalignment."""

from __future__ import annotations

import math
from dataclasses import replace

import numpy as np

from hil.bench.seeds_uav import run_uav, uav_scenario
from hil.estimators.base import GnssInput
from hil.estimators.ekf15 import Ekf15
from hil.estimators.tuning import params_for
from hil.nav.attitude import euler_to_quat, quat_to_dcm
from hil.nav.trajectory import TruthGenerator
from hil.nav.types import NavState


def _filter(lever: tuple[float, float, float]) -> Ekf15:
    init = TruthGenerator(uav_scenario(10.0, 1, "scenario")).initial_state()
    init = replace(init, q_nb=euler_to_quat(np.array([0.1, -0.05, math.pi / 2])))
    return Ekf15("ekf15", init, lever_arm_b_m=lever)


def test_a_fix_of_the_antenna_is_no_innovation_once_the_lever_arm_is_known() -> None:
    lever = (1.2, 0.4, -0.6)  # large, so the effect is far above rounding
    known, unknown = _filter(lever), _filter((0.0, 0.0, 0.0))
    nav = known.solution()
    antenna = nav.pos_ned_m + quat_to_dcm(nav.q_nb) @ np.array(lever)  # at rest: no ω × l term
    fix = GnssInput(known._stamp_ns, antenna, nav.vel_ned_mps.copy(), np.full(3, 0.5), np.full(3, 0.05))
    ins = NavState(nav.pos_ned_m, nav.vel_ned_mps, nav.q_nb)
    known.on_gnss(fix, ins)
    unknown.on_gnss(fix, ins)
    assert known.health()["nis_pos"] < 1e-20
    np.testing.assert_allclose(known.solution().pos_ned_m, nav.pos_ned_m, atol=1e-9)
    # the filter that does not know the arm reads it as a position error and moves towards it
    assert unknown.health()["nis_pos"] > 0.15  # |l|² / (3² + 0.5²) m² = 0.21
    moved = unknown.solution().pos_ned_m - nav.pos_ned_m
    assert np.dot(moved, antenna - nav.pos_ned_m) > 0.5 * np.linalg.norm(antenna - nav.pos_ned_m) ** 2


def test_the_live_tuning_tells_ekf15_the_scenarios_lever_arm_and_nothing_else_new() -> None:
    sc = uav_scenario(10.0, 1, "scenario")
    p = params_for(sc.imu.params, sc.gnss)["ekf15"]
    assert p["lever_arm_b_m"] == tuple(sc.gnss.lever_arm_b_m) != (0.0, 0.0, 0.0)
    assert "gyro_cal_sigma" not in p and "gnss_slow_sigma_m" not in p
    cal = params_for(sc.imu.params, sc.gnss, gyro_cal=True)["ekf15"]["gyro_cal_sigma"]
    assert cal == (max(sc.imu.params.gyro_scale_factor_sigma), sc.imu.params.gyro_misalignment_sigma_rad)


def test_gyro_scale_factor_and_misalignment_are_estimated_through_the_turns() -> None:
    """Seed GNSS model, tactical gyro (150 ppm, 0.5 mrad): three 180° turns reveal part of the
    z-rate column of the error matrix (its posterior σ falls below the datasheet prior, which
    with no process noise it can only do through the φ̇ = −C N(ω) δe coupling), and every
    estimate is within 3σ of the drawn truth. With σ 20 m GNSS the gain is small: the states are
    there to keep the attitude covariance honest, not to calibrate the gyro."""
    r = run_uav(620.0, 3, ("ekf30",), timed=False)
    ekf = r["estimators"]["ekf30"]
    e_true = r["gyro_error_matrix"]
    sigma = np.sqrt(np.diag(ekf.p)[15:24]).reshape(3, 3)
    sf, mis = params_for(r["scenario"].imu.params, gyro_cal=True)["ekf15"]["gyro_cal_sigma"]
    # terms driven by the turn rate (about body z, and body y in the banked turn): column z
    for i, j, p0 in ((2, 2, sf), (0, 2, mis), (1, 2, mis)):
        assert sigma[i, j] < 0.95 * p0, (i, j, sigma[i, j], p0)
    assert np.all(np.abs(ekf.e_hat - e_true) < 3.0 * sigma), (ekf.e_hat - e_true) / sigma


def test_ekf30_velocity_covariance_holds_its_error_in_the_turns_where_ekf15s_does_not() -> None:
    r = run_uav(420.0, 5, ("ekf15s", "ekf30"), timed=False)
    late = (r["t"] >= 60.0) & r["after_turn"]
    parts = {nm: float(np.mean(r["nees_pv"][nm][late, 1])) for nm in ("ekf15s", "ekf30")}
    assert parts["ekf30"] < parts["ekf15s"], parts
    assert parts["ekf30"] < 4.5, parts  # 3 expected for 3 dof; one run, so a wide margin

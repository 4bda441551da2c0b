"""ekf15 told the IMU's bias wander as the emulator makes it (``imu_bias_model``).

Seed 004's sensor model (``hil/campaigns/seed004_static.toml``: no turn-on bias, only a
Gauss-Markov wander, accelerometer τ 600 s, gyro 1 h) through the emulator cores straight into
ekf15 at rest: told the wander (``gauss_markov``), the run-averaged position+velocity NEES stays
near its χ²(6) mean; told the instability B and the gyro's τ with a turn-on-only prior (the
tuning before it, ``instability``, which recordings made before it keep), the filter starts
sure of an accelerometer bias it does not know and is over-confident. Found by the seed004
campaign on the full rig (docs/estimators.md, "Tuning").
"""

from __future__ import annotations

import math
from pathlib import Path

import numpy as np
import pytest
from scipy.stats import chi2

import hil
from hil.estimators.base import GnssInput, ImuInput
from hil.estimators.ekf15 import Ekf15, bias_walk_psd
from hil.estimators.tuning import BIAS_MODELS, GAUSS_MARKOV, INSTABILITY, ekf15_params, params_for
from hil.fusion.core import FusionConfig
from hil.messages import FusionSettings, decode, encode
from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nav.sensor_specs import GM_PEAK_RATIO, IEEE_BI_FACTOR
from hil.nav.trajectory import TruthGenerator
from hil.sensors.gnss import GnssEmulatorCore
from hil.sensors.imu import ImuEmulatorCore, sensor_rng

SEED004 = str(Path(hil.__file__).parent / "campaigns" / "seed004_static.toml")
RUNS = 4
DURATION_S = 240.0


def _nees_run(job: tuple[int, str]) -> np.ndarray:
    """Position+velocity NEES at each GNSS epoch of one sensor seed."""
    seed, model = job
    sc = scenario_overrides(load_scenario(SEED004), seed=seed, duration_s=DURATION_S)
    truth = TruthGenerator(sc)
    imu = ImuEmulatorCore(sc, truth, sensor_rng(sc.seed, "imu"))
    gnss = GnssEmulatorCore(sc, truth, sensor_rng(sc.seed, "gnss"))
    n = int(sc.duration_s * imu.rate_hz)
    b = imu.next_batch(n)
    fixes = gnss.next_batch(int(b.t_ns[-1]))
    ekf = Ekf15("ekf15", truth.initial_state(), **ekf15_params(sc.imu.params, bias_model=model))
    out, g = [], 0
    for k in range(n):
        ekf.on_imu(ImuInput(int(b.t_ns[k]), b.dt_s, b.dtheta_b_rad[k], b.dvel_b_mps[k]), None)  # type: ignore[arg-type]
        t_next = int(b.t_ns[k + 1]) if k + 1 < n else int(b.t_ns[k]) + 1
        fused = False
        while g < fixes.t_valid_ns.size and fixes.t_valid_ns[g] < t_next:
            f = fixes
            ekf.on_gnss(
                GnssInput(
                    int(f.t_valid_ns[g]),
                    f.pos_ned_m[g],
                    f.vel_ned_mps[g],
                    f.pos_sigma_m[g],
                    f.vel_sigma_mps[g],
                ),
                None,
            )  # type: ignore[arg-type]
            g, fused = g + 1, True
        if fused:
            s = ekf.solution()
            tb = truth.sample(np.array([b.t_ns[k]], dtype=np.int64))
            e = np.concatenate([s.pos_ned_m - tb.pos_ned_m[0], s.vel_ned_mps - tb.vel_ned_mps[0]])
            sig = np.concatenate([s.pos_sigma_m, s.vel_sigma_mps])  # type: ignore[list-item]
            out.append(float(np.sum((e / sig) ** 2)))
    return np.array(out)


@pytest.fixture(scope="module")
def nees() -> dict[str, np.ndarray]:
    """Run-averaged NEES per 1 Hz epoch after the first 20 s, per bias model."""
    res = {}
    for model in BIAS_MODELS:
        runs = np.array([_nees_run((40 + i, model)) for i in range(RUNS)])
        res[model] = runs.mean(axis=0)[20:]
    return res


def test_told_the_wander_the_filter_is_consistent_and_before_it_was_over_confident(
    nees: dict[str, np.ndarray],
) -> None:
    lo, hi = chi2.ppf([0.025, 0.975], 6 * RUNS) / RUNS  # run-averaged NEES of an honest filter
    told, before = nees[GAUSS_MARKOV], nees[INSTABILITY]
    assert lo <= float(np.mean(told)) <= hi
    assert float(np.mean((told >= lo) & (told <= hi))) >= 0.8
    assert float(np.mean(before)) > hi, "the instability tuning was over-confident on this IMU"
    assert float(np.mean(before)) > 1.3 * float(np.mean(told))


def test_the_wander_is_in_the_prior_and_each_sensor_keeps_its_own_tau() -> None:
    imu = load_scenario(SEED004).imu.params
    p = ekf15_params(imu)
    gm = IEEE_BI_FACTOR / GM_PEAK_RATIO  # stationary σ of the emulator's Gauss-Markov per B
    assert p["p0_accel_bias_mps2"] == pytest.approx(gm * max(imu.accel_bias_instability_mps2))
    assert p["p0_gyro_bias_radps"] == pytest.approx(gm * max(imu.gyro_bias_instability_radps))
    assert (p["bias_corr_s"], p["accel_bias_corr_s"]) == (3600.0, 600.0)
    old = ekf15_params(imu, bias_model=INSTABILITY)
    assert old["p0_accel_bias_mps2"] == 1e-4  # the floor: "sure" of a bias of 0.5 mg
    assert old["accel_bias_corr_s"] == old["bias_corr_s"] == 3600.0  # the gyro's τ for both, as it ran
    # a preset with a turn-on bias: the wander adds in quadrature to it
    tac = load_scenario("straight_level").imu.params
    t = ekf15_params(tac)
    turn_on = math.hypot(max(tac.accel_bias_mps2), max(tac.accel_turn_on_sigma_mps2))
    assert t["p0_accel_bias_mps2"] == pytest.approx(
        math.hypot(turn_on, gm * max(tac.accel_bias_instability_mps2))
    )


def test_the_accelerometer_walk_uses_its_own_tau_and_the_old_float_is_kept() -> None:
    init = TruthGenerator(load_scenario(SEED004)).initial_state()
    e = Ekf15(
        "ekf15",
        init,
        accel_bias_sigma_mps2=5e-3,
        gyro_bias_sigma_radps=5e-6,
        bias_corr_s=3600.0,
        accel_bias_corr_s=600.0,
    )
    assert e._qc[9, 9] == 2 * 5e-3**2 / 600.0 and e._qc[12, 12] == 2 * 5e-6**2 / 3600.0
    old = Ekf15("ekf15", init, accel_bias_sigma_mps2=5e-3, bias_corr_s=3600.0)
    assert old._qc[9, 9] == 2 * 5e-3**2 / 3600.0  # bit for bit the expression before
    assert bias_walk_psd(5e-3, 600.0, 1e-4) == 2 * 5e-3**2 / 600.0 + 1e-8


def test_recordings_before_the_field_rerun_with_the_tuning_they_ran() -> None:
    cfg = FusionConfig(estimators=("ekf15",))
    assert cfg.imu_bias_model == GAUSS_MARKOV
    m = cfg.settings(0, 1)
    assert FusionConfig.from_settings(decode(FusionSettings, encode(m))).imu_bias_model == GAUSS_MARKOV  # type: ignore[arg-type]
    fields = {f: getattr(m, f) for f in m.__struct_fields__ if f != "imu_bias_model"}
    old = FusionSettings(**fields)  # what a recording made before the field decodes to
    assert FusionConfig.from_settings(old).imu_bias_model == INSTABILITY
    imu = load_scenario(SEED004).imu.params
    assert params_for(imu, bias_model=INSTABILITY)["ekf15"] == ekf15_params(imu, bias_model=INSTABILITY)


def test_an_unknown_bias_model_is_refused_by_name() -> None:
    with pytest.raises(ValueError, match=r"unknown IMU bias model 'gm'.*gauss_markov, instability"):
        ekf15_params(load_scenario(SEED004).imu.params, bias_model="gm")


def test_a_fresh_fusion_can_be_configured_as_an_old_recording_was() -> None:
    from hil.nodes.fusion import FusionOptions

    assert FusionOptions().config().imu_bias_model == GAUSS_MARKOV
    assert FusionOptions(imu_bias_model=INSTABILITY).config().imu_bias_model == INSTABILITY
    with pytest.raises(ValueError, match="imu_bias_model must be gauss_markov or instability; got 'gm'"):
        FusionOptions(imu_bias_model="gm")

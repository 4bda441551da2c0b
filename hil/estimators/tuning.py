"""Estimator tuning from the IMU the scenario declares: a filter told the truth about its sensor.

The rig knows the IMU's error budget (the scenario's preset and overrides), as an integrator
knows the datasheet. ekf15's priors and process noise come from it, so the same filter is
consistent on a consumer MEMS part (0.5 deg/s turn-on bias) and on a tactical one (1 deg/h).
"""

from __future__ import annotations

import math
from typing import Any

from hil.nav.scenario import GnssConfig
from hil.nav.sensor_specs import GM_PEAK_RATIO, IEEE_BI_FACTOR, ImuParams


def _rss_max(*vecs: tuple[float, float, float]) -> float:
    """Largest per-axis root-sum-square of several per-axis sigmas/offsets."""
    return max(math.sqrt(sum(v[i] ** 2 for v in vecs)) for i in range(3))


#: How the filters are told the IMU's bias wander (``FusionConfig.imu_bias_model``, journaled):
#: ``gauss_markov`` -- the emulator's own model, the stationary σ of its first-order Gauss-Markov
#: (1.0755 B) in the bias prior and in the random walk 2σ²/τ with each sensor's own τ, plus the
#: rate random walk; ``instability`` -- the recordings made before it: B itself as σ, the gyro's
#: τ for both sensors, the prior from the turn-on bias alone.
GAUSS_MARKOV, INSTABILITY = "gauss_markov", "instability"
BIAS_MODELS = (GAUSS_MARKOV, INSTABILITY)


def _gm_sigma(b: tuple[float, float, float]) -> float:
    """The largest axis's stationary σ of the Gauss-Markov the emulator realises for B (IEEE 952)."""
    return IEEE_BI_FACTOR * max(b) / GM_PEAK_RATIO


def ekf15_params(
    imu: ImuParams, gyro_cal: bool = False, accel_cal: bool = False, bias_model: str = GAUSS_MARKOV
) -> dict[str, Any]:
    """Priors and noise of ekf15 from the IMU's datasheet figures (SI).

    The bias wander (``bias_model``, see ``BIAS_MODELS``) enters as a random walk of 2σ²/τ (the
    wander's variance over one correlation time, see ekf15) and, since the emulator's wander
    starts stationary, in the bias prior beside the turn-on bias: a filter told only the turn-on
    part of an IMU whose bias is all wander (seed 004's model) starts sure of a bias it does not
    know and stays over-confident for the whole run (NEES 12-23 against 6 over 900 s).
    ARW/VRW the white noise. Floors keep an ideal IMU's filter from
    becoming overconfident (zero noise would freeze its gains). ``gyro_cal`` adds the gyro
    scale-factor/misalignment states with the datasheet's σ (9 more states; see ekf15),
    ``accel_cal`` the accelerometers' (9 more).
    """
    if bias_model not in BIAS_MODELS:
        raise ValueError(f"unknown IMU bias model {bias_model!r}: one of {', '.join(BIAS_MODELS)}")
    cal: dict[str, Any] = {}
    if gyro_cal:  # scale factor / misalignment as states: the datasheet's σ as their priors
        cal["gyro_cal_sigma"] = (max(imu.gyro_scale_factor_sigma), imu.gyro_misalignment_sigma_rad)
    if accel_cal:
        cal["accel_cal_sigma"] = (max(imu.accel_scale_factor_sigma), imu.accel_misalignment_sigma_rad)
    if bias_model == GAUSS_MARKOV:  # the wander as the emulator realises it (module comment above)
        sg, sa = _gm_sigma(imu.gyro_bias_instability_radps), _gm_sigma(imu.accel_bias_instability_mps2)
        wander_g, wander_a = (sg, sg, sg), (sa, sa, sa)  # in the prior too: it starts stationary
        accel_corr_s = float(imu.accel_bias_corr_s)
        rate_rw = (max(imu.accel_rrw_mps2_rts), max(imu.gyro_rrw_radps_rts))
    else:  # INSTABILITY: what recordings before it ran (the same floats: ekf15.bias_walk_psd)
        sg, sa = max(imu.gyro_bias_instability_radps), max(imu.accel_bias_instability_mps2)
        wander_g = wander_a = (0.0, 0.0, 0.0)
        accel_corr_s = float(imu.gyro_bias_corr_s)
        rate_rw = (0.0, 0.0)
    gyro_p0 = _rss_max(imu.gyro_bias_radps, imu.gyro_turn_on_sigma_radps, wander_g)
    accel_p0 = _rss_max(imu.accel_bias_mps2, imu.accel_turn_on_sigma_mps2, wander_a)
    return cal | {
        "accel_vrw_mps_rts": max(max(imu.accel_vrw_mps_rts), 1e-4),
        "gyro_arw_rad_rts": max(max(imu.gyro_arw_rad_rts), 1e-6),
        "accel_bias_sigma_mps2": max(sa, 1e-5),
        "gyro_bias_sigma_radps": max(sg, 1e-7),
        "bias_corr_s": float(imu.gyro_bias_corr_s),
        "accel_bias_corr_s": accel_corr_s,
        "accel_bias_rw_mps2_rts": rate_rw[0],
        "gyro_bias_rw_radps_rts": rate_rw[1],
        "p0_accel_bias_mps2": max(accel_p0, 1e-4),
        "p0_gyro_bias_radps": max(gyro_p0, 1e-6),
    }


def feedback_params(
    imu: ImuParams, gnss: GnssConfig | None = None, bias_model: str = GAUSS_MARKOV
) -> dict[str, Any]:
    """The feedback form's INS (:class:`hil.estimators.feedback.ClosedLoopIns`): its corrector
    told the IMU's datasheet figures as ekf15 is, and the antenna's lever arm."""
    out = ekf15_params(imu, bias_model=bias_model)
    if gnss is not None:
        out |= ekf15_install_params(gnss)
    return out


def ekf15_gnss_params(gnss: GnssConfig) -> dict[str, Any]:
    """The GNSS slow (geometry) error as ekf15 states, when the receiver model has one.

    A fix reports the σ of its white noise only; the slow component is common to every fix, so
    a filter that folds it into R averages it away and claims a position it cannot know. As
    states (a sine per axis: RMS amplitude/√2, the model's period) it stays in the covariance.
    """
    amp = max(gnss.slow_amplitude_m)
    if amp <= 0.0:
        return {}
    return {"gnss_slow_sigma_m": amp / math.sqrt(2.0), "gnss_slow_period_s": float(gnss.slow_period_s)}


def ekf15_install_params(gnss: GnssConfig) -> dict[str, Any]:
    """The GNSS antenna's lever arm from the IMU, body axes: measured at installation, so
    always told to the filter (the fix is of the antenna, not of the IMU)."""
    return {"lever_arm_b_m": tuple(float(v) for v in gnss.lever_arm_b_m)} if any(gnss.lever_arm_b_m) else {}


def params_for(
    imu: ImuParams,
    gnss: GnssConfig | None = None,
    *,
    receiver_model: bool = False,
    gyro_cal: bool = False,
    accel_cal: bool = False,
    feedback: tuple[str, ...] = (),
    bias_model: str = GAUSS_MARKOV,
) -> dict[str, dict[str, Any]]:
    """Per-estimator construction parameters for a rig with this IMU and GNSS installation.

    The lever arm comes with ``gnss``; ``receiver_model`` also tells ekf15 the receiver's slow
    error (bench variants), ``gyro_cal`` adds the gyro scale-factor/misalignment states,
    ``accel_cal`` the accelerometers';
    ``feedback`` names the seed estimators that run in their feedback form; ``bias_model`` how
    both are told the bias wander (``BIAS_MODELS``).
    """
    ekf = ekf15_params(imu, gyro_cal, accel_cal, bias_model)
    if gnss is not None:
        ekf |= ekf15_install_params(gnss)
        if receiver_model:
            ekf |= ekf15_gnss_params(gnss)
    out: dict[str, dict[str, Any]] = {"ekf15": ekf}
    for name in feedback:
        out[name] = {"feedback": feedback_params(imu, gnss, bias_model)}
    return out

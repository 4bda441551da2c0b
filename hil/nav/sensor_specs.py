"""Sensor error specifications: user units in, SI out, and the named IMU presets.

The scenario file speaks the units of datasheets (deg/h, µg, deg/√h, ppm, mrad); the emulators
speak SI per second. This module is the one place that converts, so a figure in a TOML file
means exactly what the datasheet means.

Bias instability convention (IEEE Std 952): the configured figure ``B`` is the flat floor of
the Allan deviation divided by 0.664. The rig realises it as a first-order Gauss–Markov process
with correlation time ``T_c`` whose Allan-deviation peak (at τ ≈ 1.89 T_c) equals 0.664 B, so
the simulated sensor reads back the configured B off its own Allan plot.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, fields, replace
from typing import Any

G0_MPS2 = 9.80665  # standard gravity, for µg and g in datasheets
DEG = math.pi / 180.0
UG_MPS2 = 1e-6 * G0_MPS2

Vec3 = tuple[float, float, float]


class SpecError(ValueError):
    """A sensor specification key or value that cannot be used."""


def gauss_markov_adev_peak_ratio() -> float:
    """max_τ σ_A(τ) / σ_GM for a first-order Gauss–Markov process (≈ 0.6174 at τ ≈ 1.89 T_c).

    σ_A²(τ) = 2σ² T/τ [1 − T/(2τ) (3 − 4e^{−τ/T} + e^{−2τ/T})]   (T = 1 here, σ = 1)
    """
    import numpy as np  # only here: the module is read by every scenario load, numpy is ~45 ms

    x = np.linspace(0.5, 5.0, 20001)
    av = 2.0 / x * (1.0 - (3.0 - 4.0 * np.exp(-x) + np.exp(-2.0 * x)) / (2.0 * x))
    return float(np.sqrt(av.max()))


# gauss_markov_adev_peak_ratio()'s value, written out so loading a scenario (every ``hil rerun``)
# does not import numpy for it; tests/unit/test_sensors_imu.py checks the two are equal
GM_PEAK_RATIO = 0.61736428290049
IEEE_BI_FACTOR = 0.664  # Allan floor of flicker bias noise = 0.664 B


@dataclass(frozen=True)
class ImuParams:
    """Resolved IMU error parameters, SI, per axis (x, y, z body). Sigmas are 1σ draws at turn-on."""

    gyro_bias_radps: Vec3 = (0.0, 0.0, 0.0)  # fixed, deterministic
    gyro_turn_on_sigma_radps: Vec3 = (0.0, 0.0, 0.0)
    gyro_bias_instability_radps: Vec3 = (0.0, 0.0, 0.0)  # B (IEEE), see module docstring
    gyro_bias_corr_s: float = 100.0
    gyro_arw_rad_rts: Vec3 = (0.0, 0.0, 0.0)  # rad/√s
    gyro_rrw_radps_rts: Vec3 = (0.0, 0.0, 0.0)  # rad/s/√s
    gyro_scale_factor_sigma: Vec3 = (0.0, 0.0, 0.0)  # dimensionless
    gyro_misalignment_sigma_rad: float = 0.0
    gyro_quant_rad: float = 0.0  # delta-angle LSB, 0 = none
    gyro_range_radps: float = math.inf
    accel_bias_mps2: Vec3 = (0.0, 0.0, 0.0)
    accel_turn_on_sigma_mps2: Vec3 = (0.0, 0.0, 0.0)
    accel_bias_instability_mps2: Vec3 = (0.0, 0.0, 0.0)
    accel_bias_corr_s: float = 100.0
    accel_vrw_mps_rts: Vec3 = (0.0, 0.0, 0.0)  # m/s/√s
    accel_rrw_mps2_rts: Vec3 = (0.0, 0.0, 0.0)  # m/s²/√s
    accel_scale_factor_sigma: Vec3 = (0.0, 0.0, 0.0)
    accel_misalignment_sigma_rad: float = 0.0
    accel_quant_mps: float = 0.0  # delta-velocity LSB
    accel_range_mps2: float = math.inf


# user key -> (ImuParams field, factor to SI, is_vector)
_RTH = 60.0  # √h in √s
USER_KEYS: dict[str, tuple[str, float, bool]] = {
    "gyro_bias_dph": ("gyro_bias_radps", DEG / 3600.0, True),
    "gyro_turn_on_dph": ("gyro_turn_on_sigma_radps", DEG / 3600.0, True),
    "gyro_bias_instability_dph": ("gyro_bias_instability_radps", DEG / 3600.0, True),
    "gyro_bias_corr_s": ("gyro_bias_corr_s", 1.0, False),
    "gyro_arw_dprh": ("gyro_arw_rad_rts", DEG / _RTH, True),
    "gyro_rrw_dphrh": ("gyro_rrw_radps_rts", DEG / 3600.0 / _RTH, True),
    "gyro_scale_factor_ppm": ("gyro_scale_factor_sigma", 1e-6, True),
    "gyro_misalignment_mrad": ("gyro_misalignment_sigma_rad", 1e-3, False),
    "gyro_quant_urad": ("gyro_quant_rad", 1e-6, False),
    "gyro_range_dps": ("gyro_range_radps", DEG, False),
    "accel_bias_ug": ("accel_bias_mps2", UG_MPS2, True),
    "accel_bias_mps2": ("accel_bias_mps2", 1.0, True),
    "accel_turn_on_ug": ("accel_turn_on_sigma_mps2", UG_MPS2, True),
    "accel_bias_instability_ug": ("accel_bias_instability_mps2", UG_MPS2, True),
    "accel_bias_corr_s": ("accel_bias_corr_s", 1.0, False),
    "accel_vrw_mpsrh": ("accel_vrw_mps_rts", 1.0 / _RTH, True),
    "accel_rrw_ugrh": ("accel_rrw_mps2_rts", UG_MPS2 / _RTH, True),
    "accel_scale_factor_ppm": ("accel_scale_factor_sigma", 1e-6, True),
    "accel_misalignment_mrad": ("accel_misalignment_sigma_rad", 1e-3, False),
    "accel_quant_mmps": ("accel_quant_mps", 1e-3, False),
    "accel_range_g": ("accel_range_mps2", G0_MPS2, False),
}

# Presets in user units. Figures are typical of the class (consumer: MPU/BMI-type MEMS;
# tactical: HG1700-class; navigation: ring-laser 1 nmi/h class), not one part's datasheet.
IMU_PRESETS: dict[str, dict[str, Any]] = {
    "ideal": {},
    "consumer_mems": {
        "gyro_turn_on_dph": 1800.0,
        "gyro_bias_instability_dph": 10.0,
        "gyro_bias_corr_s": 100.0,
        "gyro_arw_dprh": 0.3,
        "gyro_rrw_dphrh": 10.0,
        "gyro_scale_factor_ppm": 5000.0,
        "gyro_misalignment_mrad": 5.0,
        "gyro_quant_urad": 2.7,
        "gyro_range_dps": 2000.0,
        "accel_turn_on_ug": 10000.0,
        "accel_bias_instability_ug": 100.0,
        "accel_bias_corr_s": 100.0,
        "accel_vrw_mpsrh": 0.09,
        "accel_rrw_ugrh": 100.0,
        "accel_scale_factor_ppm": 5000.0,
        "accel_misalignment_mrad": 5.0,
        "accel_quant_mmps": 0.012,
        "accel_range_g": 16.0,
    },
    "tactical": {
        "gyro_turn_on_dph": 1.0,
        "gyro_bias_instability_dph": 0.35,
        "gyro_bias_corr_s": 300.0,
        "gyro_arw_dprh": 0.125,
        "gyro_rrw_dphrh": 0.1,
        "gyro_scale_factor_ppm": 150.0,
        "gyro_misalignment_mrad": 0.5,
        "gyro_quant_urad": 1.0,
        "gyro_range_dps": 1000.0,
        "accel_turn_on_ug": 1000.0,
        "accel_bias_instability_ug": 50.0,
        "accel_bias_corr_s": 300.0,
        "accel_vrw_mpsrh": 0.03,
        "accel_rrw_ugrh": 10.0,
        "accel_scale_factor_ppm": 300.0,
        "accel_misalignment_mrad": 0.5,
        "accel_quant_mmps": 0.6,
        "accel_range_g": 37.0,
    },
    "navigation": {
        "gyro_turn_on_dph": 0.01,
        "gyro_bias_instability_dph": 0.003,
        "gyro_bias_corr_s": 3600.0,
        "gyro_arw_dprh": 0.002,
        "gyro_rrw_dphrh": 0.0,
        "gyro_scale_factor_ppm": 5.0,
        "gyro_misalignment_mrad": 0.02,
        "gyro_quant_urad": 0.2,
        "gyro_range_dps": 400.0,
        "accel_turn_on_ug": 25.0,
        "accel_bias_instability_ug": 5.0,
        "accel_bias_corr_s": 3600.0,
        "accel_vrw_mpsrh": 0.002,
        "accel_rrw_ugrh": 0.0,
        "accel_scale_factor_ppm": 50.0,
        "accel_misalignment_mrad": 0.02,
        "accel_quant_mmps": 0.05,
        "accel_range_g": 30.0,
    },
    # Seed paper 003: ideal sensors except a constant accelerometer offset u = 0.005 m/s²
    # on both horizontal axes.
    "seed_accel_offset": {"accel_bias_mps2": [0.005, 0.005, 0.0]},
}


#: IMU grades, worst first. Thresholds sit between the presets' classes (decades apart), on the
#: turn-on plus in-run bias (the errors a navigation filter must carry) and the gyro scale factor.
IMU_GRADES = ("consumer", "tactical", "navigation")


def imu_grade(p: ImuParams) -> str:
    """The IMU's class from its error budget: the worse of its gyros' and accelerometers'.

    Gyro bias (fixed, turn-on, in-run, per-axis root sum square): ≥ 100 °/h or a scale factor
    ≥ 1000 ppm is consumer MEMS, ≥ 0.1 °/h tactical, below navigation grade. Accelerometer
    bias: ≥ 3 mg consumer, ≥ 100 µg tactical. An ideal IMU is navigation grade.
    """

    def rss(*vecs: Vec3) -> float:
        return max(math.sqrt(sum(v[i] ** 2 for v in vecs)) for i in range(3))

    gyro_dph = rss(p.gyro_bias_radps, p.gyro_turn_on_sigma_radps, p.gyro_bias_instability_radps) / (
        DEG / 3600
    )
    accel_ug = rss(p.accel_bias_mps2, p.accel_turn_on_sigma_mps2, p.accel_bias_instability_mps2) / UG_MPS2
    if gyro_dph >= 100.0 or max(p.gyro_scale_factor_sigma) >= 1000e-6 or accel_ug >= 3000.0:
        return "consumer"
    if gyro_dph >= 0.1 or accel_ug >= 100.0:
        return "tactical"
    return "navigation"


#: Any IMU figure beyond this (in the key's own user unit) is a typo, not a sensor.
MAX_USER_VALUE = 1e9


def _number(key: str, raw: Any) -> float:
    """A finite number within ``MAX_USER_VALUE``; a ``*_range_*`` key may also be ``inf`` (no
    saturation). NaN passed every ``< 0`` check and failed later, far from the file."""
    if isinstance(raw, bool) or not isinstance(raw, int | float):
        raise SpecError(f"{key!r} must be a number, got {raw!r}")
    v = float(raw)
    if math.isnan(v) or (math.isinf(v) and not (key.endswith("_range_dps") or key.endswith("_range_g"))):
        raise SpecError(f"{key!r} must be a finite number, got {raw!r}")
    if math.isfinite(v) and abs(v) > MAX_USER_VALUE:
        raise SpecError(f"{key!r} = {raw!r} is out of range (|value| <= {MAX_USER_VALUE:g})")
    return v


def _vec3(key: str, value: Any) -> Vec3:
    if isinstance(value, int | float) and not isinstance(value, bool):
        return (_number(key, value),) * 3
    if isinstance(value, list | tuple) and len(value) == 3:
        return (_number(key, value[0]), _number(key, value[1]), _number(key, value[2]))
    raise SpecError(f"{key!r} must be a number or a 3-list, got {value!r}")


def resolve_imu_params(preset: str, overrides: Mapping[str, Any]) -> ImuParams:
    """Preset in user units, then overrides in user units, converted to SI ImuParams."""
    if preset not in IMU_PRESETS:
        raise SpecError(f"unknown IMU preset {preset!r}; known: {sorted(IMU_PRESETS)}")
    merged = {**IMU_PRESETS[preset], **overrides}
    values: dict[str, Any] = {}
    for key, raw in merged.items():
        if key not in USER_KEYS:
            raise SpecError(f"unknown IMU key {key!r}; known: {sorted(USER_KEYS)}")
        field, k, is_vec = USER_KEYS[key]
        given = _vec3(key, raw) if is_vec else (_number(key, raw),)
        signed = field.endswith("bias_radps") or field.endswith("bias_mps2")  # a fixed bias has a sign
        if not signed and any(x < 0 for x in given):
            raise SpecError(f"{key!r} must be non-negative, got {raw!r}")  # the user's key and value
        values[field] = tuple(x * k for x in given) if is_vec else given[0] * k
    params = replace(ImuParams(), **values)
    for f in fields(params):  # what no user key reaches: a preset's own values
        v = getattr(params, f.name)
        if (
            any(x < 0 for x in (v if isinstance(v, tuple) else (v,)))
            and not f.name.endswith("bias_radps")
            and not f.name.endswith("bias_mps2")
        ):
            raise SpecError(f"{f.name} must be non-negative, got {v}")
    if params.gyro_bias_corr_s <= 0 or params.accel_bias_corr_s <= 0:
        raise SpecError(
            f"gyro_bias_corr_s and accel_bias_corr_s must be > 0, got {params.gyro_bias_corr_s:g} and "
            f"{params.accel_bias_corr_s:g}"
        )
    if params.gyro_range_radps <= 0 or params.accel_range_mps2 <= 0:
        raise SpecError("gyro_range_dps and accel_range_g must be > 0 (inf: no saturation)")
    return params

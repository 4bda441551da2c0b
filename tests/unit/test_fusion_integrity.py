"""Fusion integrity on the physics, not on mocks: the rig's IMU/GNSS cores feed the fusion core
through a 60 s GNSS outage and the seed paper's A = 50 m, tau = 1 s pulse.

GIVEN a tactical IMU, 10 Hz GNSS (sigma 2 m), an outage from 40 s to 100 s and a pulse at 120 s
WHEN ekf15 and compvs run on it
THEN the gate rejects the pulse (and health says so), the EKF's covariance contains its true
error through the outage (NEES in the chi-square bounds), it is back within 10 s of GNSS return,
compvs restarts its schedule on return, and nothing published is non-finite.
"""

from __future__ import annotations

from functools import cache

import numpy as np
from scipy import stats

from hil.fusion.core import FusionConfig, FusionCore
from hil.fusion.ideal import ideal_inputs
from hil.nav.scenario import parse_scenario
from hil.nav.trajectory import TruthGenerator

SCENARIO = """
name = "integrity"
seed = 11
duration_s = 140.0
[origin]
lat_deg = 50.45
lon_deg = 30.52
alt_m = 300.0
[initial]
attitude_deg = [0.0, 0.0, 0.0]
speed_mps = 30.0
[imu]
preset = "tactical"
rate_hz = 200
[gnss]
rate_hz = 10.0
pos_sigma_m = 2.0
vel_sigma_mps = 0.1
latency_s = 0.0
[[event]]
kind = "gnss_outage"
t_start_s = 40.0
t_end_s = 100.0
[[event]]
kind = "gnss_pulse"
t_start_s = 120.0
amplitude_m = 50.0
tau_s = 1.0
direction_ned = [1.0, 0.0, 0.0]
[[segment]]
kind = "hold"
duration_s = 20.0
[[segment]]
kind = "turn"
yaw_rate_dps = 3.0
duration_s = 30.0
[[segment]]
kind = "hold"
duration_s = 90.0
"""

OUTAGE = (40.0, 100.0)
PULSE_T = 120.0


@cache
def _run() -> dict[str, object]:
    s = parse_scenario(SCENARIO)
    truth = TruthGenerator(s)
    inputs = ideal_inputs(s, truth)
    # the estimators' own solutions, as they reach each IMU step in the total order (process()):
    # the horizon, without the output predictor's carrying forward
    cfg = FusionConfig(estimators=("ekf15", "compvs"), output_every=20, output_predictor=False)
    core = FusionCore.for_scenario(s, cfg)
    out = []
    health_before_pulse: dict[str, dict[str, float]] = {}
    compvs_restarts_in_outage = None
    for m in inputs:
        out += core.process(m)
        t = m.stamp_ns * 1e-9
        if not health_before_pulse and t >= PULSE_T - 0.5:
            health_before_pulse = core.estimator_health()
        if compvs_restarts_in_outage is None and t >= OUTAGE[1] - 1.0:
            compvs_restarts_in_outage = core.estimator_health()["compvs"]["restarts"]
    sols = [o for o in out if o.estimator == "ekf15"]
    ts = np.array([o.stamp_ns for o in sols])
    tb = truth.sample(ts)
    err = np.array([o.pos_ned_m for o in sols]) - tb.pos_ned_m
    sig = np.array([o.pos_sigma_m for o in sols])
    return {
        "t": ts * 1e-9,
        "err": err,
        "sig": sig,
        "out": out,
        "health": core.estimator_health(),
        "before_pulse": health_before_pulse,
        "compvs_restarts_in_outage": compvs_restarts_in_outage,
    }


def test_nothing_published_is_non_finite() -> None:
    for o in _run()["out"]:  # type: ignore[attr-defined]
        assert np.all(np.isfinite([*o.pos_ned_m, *o.vel_ned_mps, *o.q_nb]))


def test_innovation_gate_rejects_the_50_m_pulse_and_health_says_so() -> None:
    """The fusion's integrity gate (hil.fusion.gnss_gate) keeps the pulse from every estimator,
    ekf15 and compvs alike: each one's health counts the rejected fixes."""
    r = _run()
    for est in ("ekf15", "compvs"):
        rejected_before = r["before_pulse"][est]["gnss_gate_rejected"]  # type: ignore[index]
        rejected_after = r["health"][est]["gnss_gate_rejected"]  # type: ignore[index]
        assert rejected_after - rejected_before >= 8  # the 10 Hz fixes inside the 1 s pulse
    t, err = r["t"], r["err"]
    during = (t >= PULSE_T) & (t < PULSE_T + 3.0)  # type: ignore[operator]
    assert np.abs(err[during, 0]).max() < 5.0  # type: ignore[index] # the pulse did not pull it


def test_covariance_contains_the_error_through_the_outage() -> None:
    """Per-axis NEES of horizontal position over the outage: its mean over N samples is inside the
    two-sided 95 % chi-square band (a consistent filter), not far above it (overconfident)."""
    r = _run()
    t, err, sig = r["t"], r["err"], r["sig"]
    inside = (t > OUTAGE[0] + 1) & (t < OUTAGE[1])  # type: ignore[operator]
    nees = ((err[inside, :2] / sig[inside, :2]) ** 2).sum(axis=1)  # type: ignore[index]
    # samples along the outage are strongly correlated: judge the mean against 2 dof, loosely
    assert nees.mean() < stats.chi2.ppf(0.99, 2)
    assert np.mean(nees < stats.chi2.ppf(0.999, 2)) > 0.95
    # and the outage really hurt: the error grew beyond GNSS-aided level
    assert np.abs(err[inside, :2]).max() > 1.0  # type: ignore[index]


def test_ekf_reconverges_within_10_s_after_gnss_returns() -> None:
    r = _run()
    t, err = r["t"], r["err"]
    h = np.hypot(err[:, 0], err[:, 1])  # type: ignore[index]
    aided = (t > 20) & (t < OUTAGE[0])  # type: ignore[operator]
    level = max(3.0 * float(np.sqrt(np.mean(h[aided] ** 2))), 2.0)
    after = (t > OUTAGE[1] + 10.0) & (t < PULSE_T)  # type: ignore[operator]
    assert h[after].max() < level


def test_variable_structure_filter_restarts_its_schedule_when_gnss_returns() -> None:
    r = _run()
    assert r["health"]["compvs"]["restarts"] == r["compvs_restarts_in_outage"] + 1  # type: ignore[index,operator]


def test_an_imu_sample_is_implausible_exactly_when_a_value_is_not_finite_or_beyond_its_bound() -> None:
    """``implausible``'s unrolled common case against its definition, value by value: at and just
    beyond each bound, NaN, both infinities, with finite and infinite bounds."""
    import itertools
    import math

    from hil.fusion.core import implausible
    from hil.messages import ImuSample

    def reference(d: list[float], v: list[float], cfg: FusionConfig) -> str:
        if not all(math.isfinite(x) and abs(x) <= cfg.max_dtheta_rad for x in d):
            return "dtheta"
        if not all(math.isfinite(x) and abs(x) <= cfg.max_dvel_mps for x in v):
            return "dvel"
        return ""

    odd = [
        0.0,
        1.0,
        -1.0,
        math.nextafter(1.0, 2.0),
        -100.0,
        math.nextafter(100.0, 200.0),
        math.nan,
        math.inf,
        -math.inf,
    ]
    seen = set()
    for cfg in (FusionConfig(), FusionConfig(max_dtheta_rad=math.inf, max_dvel_mps=math.inf)):
        for x, y, axis in itertools.product(odd, odd, range(3)):
            d, v = [0.1, -0.1, 0.0], [1.0, 2.0, -3.0]
            d[axis], v[2 - axis] = x, y
            msg = ImuSample(
                seq=0,
                stamp_ns=0,
                device_stamp_ns=0,
                rx_stamp_ns=0,
                dt_ns=2_500_000,
                dtheta_b_rad=d,
                dvel_b_mps=v,
            )
            got = implausible(msg, cfg)
            assert got == reference(d, v, cfg), (d, v, cfg.max_dtheta_rad)
            seen.add(got)
    assert seen == {"", "dtheta", "dvel"}

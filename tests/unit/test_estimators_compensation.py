"""Compensation and complementary filters: transfer-function facts, ZOH, switching, live use."""

from __future__ import annotations

import numpy as np
import pytest

from hil.estimators.base import GnssInput, ImuInput, InitialState
from hil.estimators.compensation import VS_SCHEDULE, CompensationCore, fixed_filter
from hil.estimators.complementary import ComplementaryFilter, pulse_peak_error, static_error
from hil.estimators.lti import StateSpace, aperiodic, complementary2, complementary3, forcing3, ramp_hold, zoh
from hil.estimators.registry import DEFAULT_ESTIMATORS, ESTIMATORS, make_estimator
from hil.nav.types import NavState


def _zero_multiplicity(coeffs: tuple[float, ...] | np.ndarray) -> int:
    """How many trailing (constant, p, p², ...) coefficients vanish: order of the zero at p = 0."""
    c = np.asarray(coeffs, float)
    n = 0
    while n < len(c) and abs(c[len(c) - 1 - n]) < 1e-12:
        n += 1
    return n


@pytest.mark.parametrize(
    "tf",
    [
        aperiodic(1, 5.0),
        aperiodic(2, 5.0),
        aperiodic(3, 5.0),
        forcing3(5.0),
        complementary2(0.07, 0.005),
        complementary3(0.07, 0.005, 1e-4),
        *(tf for _, tf in VS_SCHEDULE),
    ],
)
def test_every_filter_passes_dc_so_true_motion_is_untouched(tf) -> None:
    assert tf.dc_gain() == pytest.approx(1.0)
    assert abs(tf.complement().freq_response(np.array([1e-9]))[0]) < 1e-6


def test_forcing_filter_complement_has_double_zero_at_origin() -> None:
    t = 5.0
    comp = forcing3(t).complement()
    # 1 − F = T² p² (T p + 3) / (T p + 1)³
    assert _zero_multiplicity(comp.num) == 2
    np.testing.assert_allclose(np.trim_zeros(np.asarray(comp.num), "b"), [t**3, 3 * t**2])


def test_classic_complement_has_single_zero_and_third_order_cf_triple() -> None:
    assert _zero_multiplicity(aperiodic(1, 5.0).complement().num) == 1
    assert _zero_multiplicity(complementary2(0.07, 0.005).complement().num) == 2
    assert _zero_multiplicity(complementary3(0.07, 0.005, 1e-4).complement().num) == 3


def test_zoh_is_exact_for_first_order_lag() -> None:
    phi, gamma = zoh(StateSpace.from_tf(aperiodic(1, 0.5)), 1.0)
    assert phi[0, 0] == pytest.approx(np.exp(-2.0))
    c = StateSpace.from_tf(aperiodic(1, 0.5)).c[0]
    assert c * gamma[0] == pytest.approx(1.0 - np.exp(-2.0))
    ss3 = StateSpace.from_tf(forcing3(3.0))
    phi3, g3 = zoh(ss3, 0.7)
    phi_r, g0, _ = ramp_hold(ss3, 0.7)
    np.testing.assert_allclose(phi_r, phi3, atol=1e-14)
    np.testing.assert_allclose(g0, g3, atol=1e-14)


def test_ramp_hold_removes_the_half_interval_lag() -> None:
    rate = 2.0
    classic = _run_core(((0.0, fixed_filter("comp1")),), lambda t: rate * t, 120.0, slope_fn=lambda t: rate)
    forcing = _run_core(((0.0, fixed_filter("comp3f")),), lambda t: rate * t, 300.0, slope_fn=lambda t: rate)
    assert classic[-1] == pytest.approx(5.0 * rate, rel=1e-9)  # 1 − F = Tp/(Tp+1): T·rate
    assert abs(forcing[-1]) < 1e-9  # double zero: the ramp is removed exactly


def _run_core(schedule, err_fn, t_end_s: float, dt_s: float = 0.01, gnss_dt_s: float = 1.0, slope_fn=None):
    core = CompensationCore(schedule, 1)
    core.advance_to(0)
    every = round(gnss_dt_s / dt_s)
    out = np.empty(round(t_end_s / dt_s) + 1)
    for k in range(out.size):
        t_ns = round(k * dt_s * 1e9)
        core.advance_to(t_ns)
        if k % every == 0:
            slope = None if slope_fn is None else np.array([slope_fn(k * dt_s)])
            core.set_input(t_ns, np.array([err_fn(k * dt_s)]), slope)
        out[k] = err_fn(k * dt_s) - core.output()[0]  # residual error [1 − F] ξ1
    return out


def _settling_s(err: np.ndarray, e0: float, dt_s: float = 0.01) -> float:
    idx = np.nonzero(np.abs(err) > 0.05 * e0)[0]
    return (idx[-1] + 1) * dt_s


def test_transients_classic_forcing_and_variable_structure() -> None:
    e0 = 250.0
    classic = _run_core(((0.0, fixed_filter("comp1")),), lambda t: e0, 60.0)
    forcing = _run_core(((0.0, fixed_filter("comp3f")),), lambda t: e0, 80.0)
    vs = _run_core(VS_SCHEDULE, lambda t: e0, 80.0)
    assert _settling_s(classic, e0) == pytest.approx(15.0, abs=0.1)  # 3 T
    assert 25.0 < _settling_s(forcing, e0) < 40.0  # paper: ~30 s
    assert -forcing.min() > 0.1 * e0  # with overshoot
    assert _settling_s(vs, e0) < 3.0
    assert -vs.min() < 0.02 * e0  # without it


def test_ramp_error_leaks_as_t_times_rate_classic_and_zero_forcing() -> None:
    rate = 2.0
    classic = _run_core(((0.0, fixed_filter("comp1")),), lambda t: rate * t, 120.0, gnss_dt_s=0.01)
    forcing = _run_core(((0.0, fixed_filter("comp3f")),), lambda t: rate * t, 300.0, gnss_dt_s=0.01)
    # T·rate, plus half a hold interval of the sampled input: rate·Δt/2
    assert classic[-1] == pytest.approx(rate * (5.0 + 0.005), rel=1e-6)
    # the ramp itself is removed; only the half-interval lag of the held samples remains
    assert forcing[-1] == pytest.approx(rate * 0.005, rel=1e-6)


def test_variable_structure_switch_is_bumpless_on_a_ramp() -> None:
    """Across the 9 s and 45 s switches (forcing → forcing) the ramp state carries over exactly."""
    core = CompensationCore(VS_SCHEDULE, 1)
    core.advance_to(0)
    rate, outputs = 3.0, {}
    for k in range(0, 60_001):
        t_ns = k * 1_000_000
        core.advance_to(t_ns)
        core.set_input(t_ns, np.array([rate * k * 1e-3]))
        outputs[k] = core.output()[0]
    for ms in (9_000, 45_000):
        jump = outputs[ms + 1] - outputs[ms]
        slope_before = outputs[ms] - outputs[ms - 1]
        assert abs(jump - slope_before) < 1e-6 * rate
    assert core.stage == 3 and core.switches == 3


def test_retroactive_input_equals_input_on_time() -> None:
    tf = fixed_filter("comp3f")
    on_time, late = CompensationCore(((0.0, tf),), 2), CompensationCore(((0.0, tf),), 2)
    for c in (on_time, late):
        c.advance_to(0)
        c.set_input(0, np.array([1.0, -2.0]))
    on_time.advance_to(1_000_000_000)
    on_time.set_input(1_000_000_000, np.array([3.0, 4.0]))
    on_time.advance_to(1_002_500_000)
    late.advance_to(1_002_500_000)
    late.set_input(1_000_000_000, np.array([3.0, 4.0]))  # fix delivered after the IMU step
    np.testing.assert_allclose(late.output(), on_time.output(), rtol=1e-12, atol=1e-12)


def test_outage_restarts_schedule_with_continuous_output() -> None:
    core = CompensationCore(VS_SCHEDULE, 1, restart_after_s=3.0)
    core.advance_to(0)
    for s in range(60):
        core.advance_to(s * 10**9)
        core.set_input(s * 10**9, np.array([10.0]))
    core.advance_to(80 * 10**9)
    before = core.output()[0]
    core.set_input(80 * 10**9, np.array([50.0]))
    assert core.restarts == 1 and core.stage == 0
    assert core.output()[0] == pytest.approx(before)


def test_seed003_second_order_peak_and_static_error() -> None:
    cf2 = ComplementaryFilter.second_order()
    assert pulse_peak_error(cf2, 50.0, 1.0) == pytest.approx(0.07 * 1.0 * 50.0, rel=0.05)
    assert static_error(cf2, 0.005) == pytest.approx(0.005 / 0.005, rel=1e-3)


def test_seed003_third_order_has_no_static_error_and_same_peak() -> None:
    cf3 = ComplementaryFilter.third_order()
    assert abs(static_error(cf3, 0.005, t_end_s=20_000.0)) < 1e-3
    assert pulse_peak_error(cf3, 50.0, 1.0) == pytest.approx(3.5, rel=0.05)
    num, den = cf3.w_num_den()
    np.testing.assert_allclose(den, [1.0, 0.07, 0.005, 1e-4])
    np.testing.assert_allclose(np.trim_zeros(num, "f"), [0.07, 0.005, 1e-4], atol=1e-12)


def _init() -> InitialState:
    return InitialState(0, 0.8, 0.5, 100.0, 0.8, 0.5, 100.0, np.zeros(3), np.array([1.0, 0, 0, 0]))


def _feed(est, seconds: float, rng: np.random.Generator, drift_mps: float = 0.5) -> list[NavState]:
    """Vehicle at rest; free INS drifts at ``drift_mps`` north; GNSS at 5 Hz, noisy."""
    sols = []
    dt_ns = 2_500_000
    for k in range(1, round(seconds * 400) + 1):
        t_ns = k * dt_ns
        ins = NavState(
            np.array([drift_mps * t_ns * 1e-9, 0, 0]), np.array([drift_mps, 0, 0]), np.array([1.0, 0, 0, 0])
        )
        est.on_imu(ImuInput(t_ns, 0.0025, np.zeros(3), np.zeros(3)), ins)
        if k % 80 == 40:
            g = GnssInput(
                t_ns - 1_000_000,
                rng.normal(0, 2.0, 3),
                rng.normal(0, 0.1, 3),
                np.full(3, 2.0),
                np.full(3, 0.1),
            )
            est.on_gnss(g, ins)
        sols.append(est.solution())
    return sols


@pytest.mark.parametrize("name", [n for n in ESTIMATORS if n != "ekf15"])
def test_live_estimators_remove_ins_drift_deterministically(name: str) -> None:
    a = _feed(make_estimator(name, _init()), 120.0, np.random.default_rng(7))
    b = _feed(make_estimator(name, _init()), 120.0, np.random.default_rng(7))
    assert all(np.array_equal(x.pos_ned_m, y.pos_ned_m) for x, y in zip(a, b, strict=True))
    final = np.array([s.pos_ned_m for s in a[-4000:]])  # last 10 s
    assert np.sqrt(np.mean(final[:, 0] ** 2)) < 10.0  # free INS is at 60 m by now


def test_registry_names_are_zenoh_safe_and_defaults_registered() -> None:
    assert set(DEFAULT_ESTIMATORS) <= set(ESTIMATORS)
    assert {"comp1", "comp3f", "compvs", "cf3", "ekf15"} <= set(DEFAULT_ESTIMATORS)
    with pytest.raises(KeyError, match="unknown estimator"):
        make_estimator("nope", _init())
    with pytest.raises(ValueError, match="Zenoh key"):
        make_estimator("Comp1", _init())


def test_held_noise_gain_is_what_the_filter_leaves_of_held_white_noise() -> None:
    """The variable-structure filter's last stage on 1 s-held white noise: the analytic floor
    matches 4000 s of the compensation core driven by it (within the sampling error), and its
    value is the one the UAV bench quotes (7.7 m per coordinate for σ 20 m)."""
    from hil.estimators.compensation import CompensationCore
    from hil.estimators.lti import held_noise_gain

    tf = forcing3(5.0)
    gain = held_noise_gain(tf, 1.0)
    assert 20.0 * gain == pytest.approx(7.72, abs=0.01)
    assert held_noise_gain(aperiodic(1, 5.0), 1.0) == pytest.approx(0.306, abs=0.001)
    core = CompensationCore(((0.0, tf),), n_channels=64)
    rng = np.random.default_rng(3)
    out = []
    for k in range(4000):
        core.set_input(k * 1_000_000_000, rng.standard_normal(64))
        for j in range(1, 10):  # read the output through the hold, as the IMU-rate estimators do
            core.advance_to(k * 1_000_000_000 + j * 100_000_000)
            if k >= 100:
                out.append(core.output().copy())
    rms = float(np.sqrt(np.mean(np.square(out))))
    assert rms == pytest.approx(gain, rel=0.03)


# -- cf3's coast through a GNSS gap ----------------------------------------------------------------

CF3 = ((0.0, complementary3(0.07, 0.005, 1e-4)),)


def _cubic_run(core: CompensationCore, gap: tuple[float, float] | None, t_end_s: float = 420.0) -> np.ndarray:
    """A noise-free INS error growing as a tilt from a gyro bias makes it (ξ = j t³/6), as the
    compensation estimator sees it: 10 Hz differences continued at their rate, output at 100 Hz;
    no fix inside ``gap``. Returns ξ − y at every 10 ms."""
    jerk = 2e-4

    def xi(t: float) -> float:
        return jerk * t**3 / 6.0

    out = []
    for k in range(round(t_end_s * 100) + 1):
        t = k * 0.01
        t_ns = k * 10_000_000
        core.advance_to(t_ns)
        if k % 10 == 0 and not (gap is not None and gap[0] <= t < gap[1]):
            core.set_input(t_ns, np.array([xi(t)]), np.array([jerk * t**2 / 2.0]))
        out.append(xi(t) - core.output()[0])
    return np.array(out)


def test_cf3_coasts_through_a_gap_on_the_ins_error_it_was_tracking() -> None:
    """The third-order loop tracks a cubic INS error with a constant innovation ē (jerk/k3);
    held through a 10 s gap, the loop goes on as if the fixes had not stopped (its integrators
    hold the error's rate and acceleration), where the last difference continued at its last
    rate (no coast) misses the error's acceleration for the whole gap and rings after it."""
    gap = (400.0, 410.0)
    tracked = _cubic_run(CompensationCore(CF3, 1), None)
    coasted = _cubic_run(CompensationCore(CF3, 1, coast_after=2.5), gap)
    held = _cubic_run(CompensationCore(CF3, 1), gap)
    window = slice(40_000, None)  # the gap and the 10 s after it
    lag = np.abs(tracked[window]).max()
    assert lag > 1.0  # the open loop's own lag on a cubic (1 − W = s³/(…)): what a gap must not add to
    assert np.abs(coasted[window] - tracked[window]).max() < 1e-3 * lag
    assert np.abs(held[window] - tracked[window]).max() > 0.05 * lag


def test_regular_fixes_never_coast_so_the_aided_output_is_unchanged() -> None:
    """A fix missing now and then (two intervals) is not a gap: bit for bit the filter without a coast."""
    rng = np.random.default_rng(3)
    plain, coast = CompensationCore(CF3, 2), CompensationCore(CF3, 2, coast_after=2.5)
    for k in range(3000):
        t_ns = k * 10_000_000
        for c in (plain, coast):
            c.advance_to(t_ns)
        if k % 10 == 0 and k % 70 != 0:
            d, s = rng.normal(0.0, 2.0, 2), rng.normal(0.0, 0.2, 2)
            for c in (plain, coast):
                c.set_input(t_ns, d, s)
        assert np.array_equal(plain.output(), coast.output())
    assert coast.coasts == 0 and not coast.coasting


def test_a_late_fix_ends_a_coast_as_one_on_time() -> None:
    """The fix that ends a gap, delivered just after the IMU step that straddles it, takes effect
    at its time of validity: the coast is stepped back to it exactly."""
    on_time, late = CompensationCore(CF3, 2, coast_after=2.5), CompensationCore(CF3, 2, coast_after=2.5)
    rng = np.random.default_rng(5)
    for k in range(0, 3000, 10):
        d, s = rng.normal(0.0, 2.0, 2), rng.normal(0.0, 0.2, 2)
        for c in (on_time, late):
            c.advance_to(k * 10_000_000)
            c.set_input(k * 10_000_000, d, s)
    t_fix = 35_000_000_000 + 3_000_000  # 5 s gap; the fix between two IMU stamps
    on_time.advance_to(t_fix)
    assert on_time.coasting
    on_time.set_input(t_fix, np.array([1.0, -2.0]), np.array([0.1, 0.0]))
    on_time.advance_to(35_010_000_000)
    late.advance_to(35_010_000_000)
    late.set_input(t_fix, np.array([1.0, -2.0]), np.array([0.1, 0.0]))
    assert not late.coasting and late.coasts == on_time.coasts == 1
    np.testing.assert_allclose(late.output(), on_time.output(), rtol=1e-12, atol=1e-12)


def test_a_coast_needs_a_strictly_proper_filter() -> None:
    with pytest.raises(ValueError, match="strictly proper"):
        CompensationCore(((0.0, aperiodic(1, 5.0)),), 1, coast_after=0.5)


def test_cf3_coasts_in_the_open_loop_only() -> None:
    """In the feedback form the corrector moves the INS behind the filter's integrators, so they
    are no model of its error in a gap: the reset, bias-corrected INS coasts instead."""
    from hil.estimators.tuning import params_for
    from hil.nav.scenario import load_scenario

    sc = load_scenario("car_drive")
    fb = params_for(sc.imu.params, sc.gnss, feedback=("cf3",))["cf3"]
    assert make_estimator("cf3", _init()).core.coast_after == 2.5  # type: ignore[attr-defined]
    assert make_estimator("cf3", _init(), fb).core.coast_after is None  # type: ignore[attr-defined]
    assert make_estimator("cf3", _init(), {"coast_after": None}).core.coast_after is None  # type: ignore[attr-defined]

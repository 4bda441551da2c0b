"""The seed estimators' feedback form and the IMU grade's choices (issue 22 items 4 and 5)."""

from __future__ import annotations

import math

import msgspec
import numpy as np
import pytest

from hil.estimators.base import GnssInput, ImuInput, InitialState
from hil.estimators.compensation import VS_SCHEDULE, CompensationCore, fixed_filter
from hil.estimators.ekf15 import covariance_step
from hil.estimators.feedback import ClosedLoopIns
from hil.estimators.lti import complementary2, complementary3
from hil.estimators.registry import DEFAULT_ESTIMATORS, FEEDBACK_CAPABLE, make_estimator
from hil.estimators.tuning import params_for
from hil.fusion.core import FusionConfig
from hil.messages import FusionSettings
from hil.nav.earth import OMEGA_IE_RADPS
from hil.nav.portable import mv
from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nav.sensor_specs import imu_grade, resolve_imu_params
from hil.nav.strapdown import c_nb_floats, strapdown_from_initial, strapdown_step, to_nav_state
from hil.nav.trajectory import TruthGenerator
from hil.nodes.fusion import FusionOptions
from hil.runtime import jit
from hil.sensors.gnss import GnssEmulatorCore
from hil.sensors.imu import ImuEmulatorCore, sensor_rng


@pytest.mark.parametrize(
    ("preset", "grade"),
    [
        ("consumer_mems", "consumer"),
        ("tactical", "tactical"),
        ("navigation", "navigation"),
        ("ideal", "navigation"),
    ],
)
def test_imu_grade_of_the_presets(preset: str, grade: str) -> None:
    assert imu_grade(resolve_imu_params(preset, {})) == grade


def test_the_imu_grade_decides_feedback_and_calibration_states() -> None:
    consumer = FusionOptions().config("consumer")
    assert consumer.feedback == tuple(e for e in DEFAULT_ESTIMATORS if e in FEEDBACK_CAPABLE)
    assert "ekf15" not in consumer.feedback and consumer.ekf_calibration == "gyro+accel"
    tactical = FusionOptions().config("tactical")
    assert tactical.feedback == () and tactical.ekf_calibration == ""
    forced = FusionOptions(feedback="none", ekf_calibration="gyro").config("consumer")
    assert forced.feedback == () and forced.ekf_calibration == "gyro"
    picked = FusionOptions(feedback="compvs,cf2").config("tactical")
    assert picked.feedback == ("compvs",)  # cf2 is not among the estimators run
    with pytest.raises(ValueError, match="no feedback form"):
        FusionOptions(feedback="ekf15")
    with pytest.raises(ValueError, match="ekf_calibration"):
        FusionOptions(ekf_calibration="accel")


def test_fusion_settings_carry_the_choices_and_old_recordings_read_as_open_loop() -> None:
    cfg = FusionConfig(estimators=("compvs", "ekf15"), feedback=("compvs",), ekf_calibration="gyro+accel")
    assert FusionConfig.from_settings(cfg.settings(0, 0)) == cfg
    old = msgspec.structs.asdict(FusionConfig(estimators=("compvs",)).settings(0, 0))
    del old["feedback"], old["ekf_calibration"]  # a recording made before them
    back = FusionConfig.from_settings(msgspec.convert(old, FusionSettings))
    assert back.feedback == () and back.ekf_calibration == ""


def test_calibration_params_by_grade() -> None:
    sc = load_scenario("uav_survey")
    p = params_for(sc.imu.params, sc.gnss, gyro_cal=True, accel_cal=True, feedback=("cf3",))
    assert p["ekf15"]["gyro_cal_sigma"][0] > 0 and p["ekf15"]["accel_cal_sigma"][0] > 0
    assert p["cf3"]["feedback"]["lever_arm_b_m"] == p["ekf15"]["lever_arm_b_m"]


@pytest.mark.parametrize(
    "schedule",
    [
        ((0.0, fixed_filter("comp3f")),),
        ((0.0, complementary2(0.07, 0.005)),),
        ((0.0, complementary3(0.07, 0.005, 1e-4)),),
        ((0.0, VS_SCHEDULE[-1][1]),),
    ],
    ids=["comp3f", "cf2", "cf3", "vs-last"],
)
def test_shift_moves_the_filter_as_if_the_input_never_had_the_ramp(schedule) -> None:
    """After ``shift(c0, c1)`` and inputs less ``c0 + c1 τ``, ``X_INS − y`` is what it was:
    the feedback reset does not move the solution of a filter that follows a ramp."""
    rng = np.random.default_rng(3)
    a, b = CompensationCore(schedule, 2), CompensationCore(schedule, 2)
    for c in (a, b):
        c.advance_to(0)
    c0, c1 = np.array([4.0, -2.0]), np.array([0.3, 0.1])
    t_shift = 20_000_000_000
    for k in range(1, 4001):  # 40 s at 100 Hz, inputs at 1 Hz with a ramp
        t_ns = k * 10_000_000
        for c in (a, b):
            c.advance_to(t_ns)
        if k % 100 == 0:
            d, s = rng.normal(0, 5, 2) + 0.2 * k * 0.01, rng.normal(0, 0.1, 2)
            a.set_input(t_ns, d, s)
            tau = max(t_ns - t_shift, 0) * 1e-9
            b.set_input(t_ns, d - (c0 + c1 * tau) * (t_ns > t_shift), s - c1 * (t_ns > t_shift))
        if t_ns == t_shift:  # the fix's input, then the reset (as the estimator does)
            b.shift(c0, c1)
        if t_ns >= t_shift:
            r = c0 + c1 * (t_ns - t_shift) * 1e-9
            np.testing.assert_allclose(b.output() + r, a.output(), atol=1e-9)
        else:
            np.testing.assert_array_equal(b.output(), a.output())


def _consumer_run(seconds: float, names: tuple[str, ...]) -> dict[str, float]:
    """uav_survey's consumer IMU and receiver straight into each estimator, open loop on a
    shared free INS or in feedback form; horizontal position RMS over the last half."""
    sc = scenario_overrides(load_scenario("uav_survey"), seed=11, duration_s=seconds)
    truth = TruthGenerator(sc)
    init = truth.initial_state()
    imu = ImuEmulatorCore(sc, truth, sensor_rng(sc.seed, "imu"))
    gnss = GnssEmulatorCore(sc, truth, sensor_rng(sc.seed, "gnss"))
    n = int(seconds * imu.rate_hz)
    batch = imu.next_batch(n)
    fixes = gnss.next_batch(int(batch.t_ns[-1]))
    fb = params_for(sc.imu.params, sc.gnss, feedback=tuple(n.removesuffix("_fb") for n in names))
    ests = {
        n: make_estimator(n.removesuffix("_fb"), init, fb[n[:-3]] if n.endswith("_fb") else {}) for n in names
    }
    free = strapdown_from_initial(init)
    keep = np.arange(n // 2, n, 40)
    tb = truth.sample(batch.t_ns[keep])
    err: dict[str, list[float]] = {n: [] for n in names}
    g = 0
    for k in range(n):
        t = int(batch.t_ns[k])
        free = strapdown_step(free, batch.dtheta_b_rad[k], batch.dvel_b_mps[k], batch.dt_s)
        ins = to_nav_state(free, init)
        inp = ImuInput(t, batch.dt_s, batch.dtheta_b_rad[k], batch.dvel_b_mps[k])
        for e in ests.values():
            e.on_imu(inp, ins)
        t_next = int(batch.t_ns[k + 1]) if k + 1 < n else t + 1
        while g < fixes.t_valid_ns.size and fixes.t_valid_ns[g] < t_next:
            fx = GnssInput.of_batch(fixes, g)
            for e in ests.values():
                e.on_gnss(fx, ins)
            g += 1
        j = np.searchsorted(keep, k)
        if j < keep.size and keep[j] == k:
            for name, e in ests.items():
                err[name].append(float(np.linalg.norm((e.solution().pos_ned_m - tb.pos_ned_m[j])[:2])))
    return {name: float(np.sqrt(np.mean(np.square(v)))) for name, v in err.items()}


def test_feedback_form_rides_a_consumer_imu_where_open_loop_leaves() -> None:
    """40 s of uav_survey's consumer MEMS: the open-loop forms run off with the free INS (its
    tilt from a 0.5 °/s gyro bias), their feedback forms stay at the receiver's metres."""
    rms = _consumer_run(40.0, ("compvs", "compvs_fb", "cf3", "cf3_fb", "kfvel", "kfvel_fb"))
    for name in ("compvs", "cf3", "kfvel"):
        assert rms[f"{name}_fb"] < 5.0, rms
        assert rms[name] > 10 * rms[f"{name}_fb"], rms


def test_ekf15_carries_accelerometer_calibration_states_and_reports_attitude_sigma() -> None:
    sc = load_scenario("uav_survey")
    init = TruthGenerator(sc).initial_state()
    p = params_for(sc.imu.params, sc.gnss, gyro_cal=True, accel_cal=True)["ekf15"]
    ekf = make_estimator("ekf15", init, p)
    assert ekf.n == 33  # type: ignore[attr-defined]  # 15 + 9 gyro + 9 accelerometer
    for k in range(1, 401):  # 1 s of level, unaccelerated increments
        ekf.on_imu(
            ImuInput(init.stamp_ns + k * 2_500_000, 0.0025, np.zeros(3), np.array([0, 0, -0.0245])), None
        )  # type: ignore[arg-type]
    sig = ekf.solution().att_sigma_rad
    assert sig is not None and sig.shape == (3,) and np.all(sig > 0)


def _corrector_prediction_with_arrays(
    q: np.ndarray, sum_dv: np.ndarray, dt: float, lat: float, p: np.ndarray, qc: np.ndarray, dv: np.ndarray
) -> tuple[np.ndarray, np.ndarray]:
    """The corrector's prediction as it was written with arrays (the reference for its bits)."""
    c_nb = np.array(c_nb_floats(*q.tolist())).reshape(3, 3)
    f_n = mv(c_nb, sum_dv / dt)
    w0, w2 = OMEGA_IE_RADPS * math.cos(lat), -OMEGA_IE_RADPS * math.sin(lat)
    f0, f1, f2 = f_n.tolist()
    f = np.zeros((12, 12))
    f[0:3, 3:6] = ((0.0, -f2, f1), (f2, 0.0, -f0), (-f1, f0, 0.0))
    f[0:3, 9:12] = c_nb
    f[3:6, 3:6] = ((-0.0, w2, -0.0), (-w2, -0.0, w0), (0.0, -w0, -0.0))
    f[3:6, 6:9] = -c_nb
    phi, p_new = covariance_step(f, dt, p, qc)
    return p_new, mv(phi[0:3, 0:3], dv)


def test_the_corrector_prediction_on_floats_is_the_array_forms_bits() -> None:
    """``_corrector_prediction`` (floats, one call, what the kernels compile) against the array
    expressions it replaced, in Python, on random attitudes, specific forces and covariances."""
    python_run = jit.python_kernel("_corrector_prediction")  # the reference, whatever was compiled
    rng = np.random.default_rng(23)
    for k in range(3000):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        sum_dv = rng.normal(0.0, 0.5, 3) + np.array((0.0, 0.0, -9.81 * 0.05))
        dt, lat = float(rng.uniform(0.01, 0.1)), float(rng.uniform(-1.5, 1.5))
        a = rng.normal(size=(12, 12)) * 10.0 ** rng.integers(-6, 0, size=(12, 12))
        p = a @ a.T
        qc = np.diag(rng.random(12) * 1e-6)
        dv = rng.normal(0.0, 0.1, 3)
        if k % 5 == 0:
            dv[rng.integers(3)] = -0.0
        want_p, want_dv = _corrector_prediction_with_arrays(q, sum_dv, dt, lat, p, qc, dv)
        got_p, *got_dv = python_run(*q.tolist(), *sum_dv.tolist(), dt, lat, p, qc, *dv.tolist())
        assert got_p.tobytes() == want_p.tobytes() and np.array(got_dv).tobytes() == want_dv.tobytes(), k


def _loop_at_random(rng: np.random.Generator, lever: bool, near: bool) -> ClosedLoopIns:
    """A feedback INS put at a random state over the whole Earth and attitude sphere, with a random
    body rate (and antenna arm); ``near``: at its origin, longitude 0 and almost still, where the
    last bits of the arm's terms and of a reset's quotients are not lost in the sums."""
    q = rng.normal(size=4)
    q /= np.linalg.norm(q)
    lat, lon, alt = (
        float(rng.uniform(-1.5, 1.5)),
        float(rng.uniform(-3.1, 3.1)),
        float(rng.uniform(-400.0, 12000.0)),
    )
    if near:
        lon = 0.0
    init = InitialState(
        stamp_ns=0,
        lat_rad=lat,
        lon_rad=lon,
        alt_m=alt,
        origin_lat_rad=lat if near else float(rng.uniform(-1.5, 1.5)),
        origin_lon_rad=lon if near else float(rng.uniform(-3.1, 3.1)),
        origin_alt_m=alt if near else float(rng.uniform(0.0, 500.0)),
        vel_ned_mps=rng.normal(0.0, 1e-4 if near else 30.0, 3),
        q_nb=q,
    )
    arm = tuple(rng.normal(0.0, 0.5, 3).tolist()) if lever else (0.0, 0.0, 0.0)
    loop = ClosedLoopIns(init, lever_arm_b_m=arm)
    loop._st = (*loop._st[:10], *rng.normal(0.0, 1e-3, 6).tolist())
    loop._w_b = rng.normal(0.0, 0.3, 3)
    loop.stamp_ns = int(rng.integers(0, 10**9))
    loop._dirty = bool(rng.integers(2))  # its nav as the lazy state or as the arrays at start
    return loop


def test_the_feedback_ins_fix_paths_on_floats_are_the_array_forms_bits() -> None:
    """A fix's antenna difference, attitude reset and position/velocity reset (floats since
    session 29) against the array expressions they replaced, on random states and fixes."""
    from hil.nav.attitude import quat_from_rotvec, quat_multiply, quat_normalise
    from hil.nav.earth import cross, radii_of_curvature

    rng = np.random.default_rng(31)
    for k in range(2000):
        near = k % 2 == 0
        loop = _loop_at_random(rng, lever=k % 3 != 0, near=near)
        fix = GnssInput(
            stamp_ns=loop.stamp_ns - int(rng.integers(0, 5 * 10**8)),
            pos_ned_m=np.zeros(3) if near else rng.normal(0.0, 2000.0, 3),
            vel_ned_mps=np.zeros(3) if near else rng.normal(0.0, 30.0, 3),
            pos_sigma_m=np.full(3, 2.0),
            vel_sigma_mps=np.full(3, 0.2),
        )
        nav = loop.nav()
        pos = nav.pos_ned_m + nav.vel_ned_mps * ((fix.stamp_ns - loop.stamp_ns) * 1e-9)
        vel = nav.vel_ned_mps
        if loop._lever is not None:
            c_nb = loop.state.c_nb()
            pos = pos + mv(c_nb, loop._lever)
            vel = vel + mv(c_nb, cross(loop._w_b, loop._lever))
        got = loop.antenna_difference(fix)
        assert got[0].tobytes() == (pos - fix.pos_ned_m).tobytes(), k
        assert got[1].tobytes() == (vel - fix.vel_ned_mps).tobytes(), k

        phi = rng.normal(0.0, 1e-6 if k % 4 == 0 else 1e-2, 3)
        s = loop.state
        want = s.replace(q_nb=quat_normalise(quat_multiply(quat_from_rotvec(phi), s.q_nb)))
        loop._rotate(phi)
        assert np.array(loop._st).tobytes() == np.array(tuple(want)).tobytes(), k

        dp, dv = rng.normal(0.0, 5.0, 3), rng.normal(0.0, 0.5, 3)
        if near:  # back to longitude 0: the quotient's bits are the new longitude's
            loop._st = (loop._st[0], 0.0, *loop._st[2:])
        s = loop.state
        r_m, r_n = radii_of_curvature(s.lat_rad)
        lat = s.lat_rad - dp[0] / (float(r_m) + s.alt_m)
        lon = s.lon_rad - dp[1] / ((float(r_n) + s.alt_m) * math.cos(s.lat_rad))
        want = s.replace(lat_rad=lat, lon_rad=lon, alt_m=s.alt_m + dp[2], vel_ned_mps=s.vel_ned_mps - dv)
        loop.reset(dp, dv)
        assert np.array(loop._st).tobytes() == np.array(tuple(want)).tobytes(), k

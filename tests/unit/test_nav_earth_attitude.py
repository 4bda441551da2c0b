"""WGS84 model and attitude maths against published values and exact identities."""

from __future__ import annotations

import math

import numpy as np

from hil.nav import attitude as att
from hil.nav import earth


def test_normal_gravity_matches_wgs84_published_values() -> None:
    # NIMA TR8350.2: γ_e = 9.7803253359, γ_p = 9.8321849378 m/s²; free-air ≈ −3.086e-6 /m
    assert math.isclose(float(earth.normal_gravity(0.0, 0.0)), 9.7803253359, abs_tol=1e-9)
    assert math.isclose(float(earth.normal_gravity(math.pi / 2, 0.0)), 9.8321849378, abs_tol=1e-9)
    grad = float(earth.normal_gravity(0.8, 1000.0) - earth.normal_gravity(0.8, 0.0)) / 1000.0
    assert math.isclose(grad, -3.086e-6, rel_tol=0.01)


def test_schuler_period_is_84_4_minutes() -> None:
    assert math.isclose(earth.schuler_period_s(math.radians(50.45)) / 60.0, 84.4, rel_tol=0.002)


def test_lla_ned_round_trip_far_from_origin() -> None:
    o = (math.radians(50.45), math.radians(30.52), 300.0)
    ned = np.array([[150e3, -80e3, 2e3], [0.0, 0.0, 0.0], [-3e3, 4e3, -500.0]])
    lat, lon, alt = earth.ned_to_lla(ned, *o)
    back = earth.lla_to_ned(lat, lon, alt, *o)
    assert np.max(np.abs(back - ned)) < 1e-6
    # one arc-minute of latitude ≈ (R_M + h) × 2.909e-4 rad ≈ 1854 m north
    d = earth.lla_to_ned(o[0] + math.radians(1 / 60), o[1], o[2], *o)
    r_m, _ = earth.radii_of_curvature(o[0])
    assert math.isclose(d[0], (float(r_m) + 300.0) * math.radians(1 / 60), rel_tol=1e-5)


def test_quaternion_euler_dcm_agree() -> None:
    rng = np.random.default_rng(7)
    e = rng.uniform([-3, -1.4, -3], [3, 1.4, 3], (100, 3))
    q = att.euler_to_quat(e)
    assert np.allclose(att.quat_to_dcm(q), att.euler_to_dcm(e), atol=1e-12)
    assert np.allclose(att.quat_to_euler(q), e, atol=1e-9)
    assert np.allclose(
        att.quat_normalise(att.dcm_to_quat(att.euler_to_dcm(e))), att.quat_normalise(q), atol=1e-12
    )


def test_rotvec_composition_and_small_angles() -> None:
    phi = np.array([[1e-9, -2e-9, 3e-9], [0.3, -0.2, 0.1], [0.0, 0.0, math.pi / 2]])
    q = att.quat_from_rotvec(phi)
    assert np.allclose(np.linalg.norm(q, axis=-1), 1.0, atol=1e-15)
    assert np.allclose(att.quat_to_rotvec(q), phi, atol=1e-15)
    # 90° about z takes body x to NED east
    assert np.allclose(att.rotate(q[2], [1.0, 0.0, 0.0]), [0.0, 1.0, 0.0], atol=1e-15)
    # two half-rotations about one axis compose to the whole
    half = att.quat_from_rotvec(phi[1] / 2)
    assert np.allclose(att.quat_multiply(half, half), q[1], atol=1e-15)


def test_quaternion_float_twins_give_the_numpy_forms_bits() -> None:
    """The float forms an EKF fix's attitude reset runs (ekf15's ``_inject``) against the numpy
    forms, bit for bit: rotation vectors across the series' 1e-4 rad switch and far above it,
    quaternions of either sign. A different summation order differs within a few hundred draws."""
    rng = np.random.default_rng(20)
    for _ in range(5000):
        phi = rng.normal(size=3) * 10.0 ** rng.uniform(-9.0, 0.5)
        q_num = att.quat_from_rotvec(phi)
        assert att.quat_from_rotvec_floats(*phi.tolist()) == tuple(q_num.tolist())
        p = rng.normal(size=4)
        assert att.quat_normalise_floats(*p.tolist()) == tuple(att.quat_normalise(p).tolist())
        prod = att.quat_multiply(q_num, p)
        assert att.quat_multiply_floats(*q_num.tolist(), *p.tolist()) == tuple(prod.tolist())


def test_the_quaternion_float_twins_keep_numpys_answer_where_math_would_raise() -> None:
    """A diverged filter's reset (an infinite rotation vector, a zero quaternion) gives numpy's
    NaN from the float forms too, not a ValueError or ZeroDivisionError."""
    import warnings

    with warnings.catch_warnings():
        warnings.simplefilter("ignore", RuntimeWarning)
        for phi in ((math.inf, 0.0, 0.0), (1.0, -math.inf, 2.0), (math.nan, 0.0, 0.0)):
            want = att.quat_from_rotvec(np.array(phi)).tolist()
            got = list(att.quat_from_rotvec_floats(*phi))
            assert np.array_equal(got, want, equal_nan=True)
        for q in ((0.0, 0.0, 0.0, 0.0), (math.inf, 0.0, 0.0, 0.0), (math.nan, 1.0, 0.0, 0.0)):
            want = att.quat_normalise(np.array(q)).tolist()
            assert np.array_equal(list(att.quat_normalise_floats(*q)), want, equal_nan=True)


def test_levelling_against_the_acceleration_recovers_any_upright_attitude() -> None:
    """``levelled_attitude`` with ``accel_ned``: the roll and pitch that turn the specific force
    onto ``a - g`` at the track's heading, for attitudes within ±46° roll, ±34° pitch and
    accelerations of 1 m/s² per axis (a coordinated 28° bank's 5.2 m/s² included); with a = 0
    the levelling on f_b alone, to rounding."""
    rng = np.random.default_rng(7)
    g = 9.80665
    cases = [
        (
            math.radians(28.0),
            0.0,
            0.4,
            np.array([-math.sin(0.4), math.cos(0.4), 0.0]) * g * math.tan(math.radians(28.0)),
        )
    ]
    for _ in range(500):
        cases.append(
            (rng.uniform(-0.8, 0.8), rng.uniform(-0.6, 0.6), rng.uniform(-3.0, 3.0), rng.normal(0.0, 1.0, 3))
        )
    for roll, pitch, yaw, a in cases:
        c = att.quat_to_dcm(att.euler_to_quat([roll, pitch, yaw]))
        f_b = c.T @ (a - np.array([0.0, 0.0, g]))
        vel = [10.0 * math.cos(yaw), 10.0 * math.sin(yaw), 0.0]
        q, tracked = att.levelled_attitude(
            tuple(f_b.tolist()), vel, [1.0, 0.0, 0.0, 0.0], accel_ned=tuple(a.tolist())
        )
        assert tracked
        np.testing.assert_allclose(att.quat_to_euler(q), [roll, pitch, yaw], atol=1e-9)
    q0, _ = att.levelled_attitude(tuple(f_b.tolist()), vel, [1.0, 0.0, 0.0, 0.0])
    q1, _ = att.levelled_attitude(tuple(f_b.tolist()), vel, [1.0, 0.0, 0.0, 0.0], accel_ned=(0.0, 0.0, 0.0))
    np.testing.assert_allclose(q0, q1, atol=1e-12)
    c = att.quat_to_dcm(att.euler_to_quat(list(cases[0][:3])))
    f_turn = c.T @ (cases[0][3] - np.array([0.0, 0.0, g]))
    q_level, _ = att.levelled_attitude(
        tuple(f_turn.tolist()), [math.cos(0.4), math.sin(0.4), 0.0], [1, 0, 0, 0], 0.5
    )
    # levelled on f_b alone, the turn's whole 28° bank is taken for level
    assert abs(att.quat_to_euler(q_level)[0]) < 1e-9


def test_the_gnss_velocitys_rate_in_a_turn_and_in_noise() -> None:
    """``velocity_rate``: a steady 12 °/s turn at 50 m/s sampled at 10 Hz over a second gives its
    centripetal acceleration at the last fix (the mean, turned on by the track's rate); velocity
    noise alone (σ 0.2 m/s, straight and level) gives None: levelled on a = 0."""
    w, speed = math.radians(12.0), 50.0
    fixes = []
    for k in range(11):
        t = k * 0.1
        psi = w * t
        fixes.append((round(t * 1e9), [speed * math.cos(psi), speed * math.sin(psi), 0.0]))
    a = att.velocity_rate(fixes, [0.2, 0.2, 0.2])
    assert a is not None
    psi_end = w * 1.0
    want = speed * w * np.array([-math.sin(psi_end), math.cos(psi_end), 0.0])
    np.testing.assert_allclose(a, want, atol=0.01 * speed * w)
    rng = np.random.default_rng(3)
    quiet = [
        (round(k * 1e8), (np.array([50.0, 0.0, 0.0]) + rng.normal(0.0, 0.2, 3)).tolist()) for k in range(11)
    ]
    assert att.velocity_rate(quiet, [0.2, 0.2, 0.2]) is None
    assert att.velocity_rate(fixes[:1], [0.2, 0.2, 0.2]) is None


def test_the_gnss_velocitys_rate_after_the_acceleration_changed_is_the_new_one() -> None:
    """QA (session 36): 8 m/s² forward, then 8 m/s² braking from half a second before the last
    fix: the line through the second's velocities has a slope near zero, and the free INS was
    levelled 28° off. Its residuals stand far out of the 0.2 m/s noise, so the rate is taken again
    from the newer half: the braking's."""
    fixes = []
    for k in range(11):
        t = k * 0.1
        v = 50.0 + 8.0 * min(t, 0.45) - 8.0 * max(0.0, t - 0.45)
        fixes.append((round(t * 1e9), [v, 0.0, 0.0]))
    a = att.velocity_rate(fixes, [0.2, 0.2, 0.2])
    assert a is not None and abs(a[0] + 8.0) < 0.5 and abs(a[1]) < 1e-9, a
    # a steady acceleration keeps the whole second (its line fits): the same 8 m/s² either way
    steady = [(round(k * 1e8), [50.0 - 0.8 * k, 0.0, 0.0]) for k in range(11)]
    b = att.velocity_rate(steady, [0.2, 0.2, 0.2])
    assert b is not None and abs(b[0] + 8.0) < 1e-9

"""Truth generator: physics of the motion it produces, and independence from batching."""

from __future__ import annotations

import dataclasses
import math

import numpy as np

from hil.nav import earth
from hil.nav.attitude import quat_to_euler
from hil.nav.scenario import MotionSegment, load_scenario, parse_scenario, scenario_overrides
from hil.nav.trajectory import TruthGenerator, truth_for

TURN = """
name = "turn"
seed = 1
[origin]
lat_deg = 45.0
alt_m = 500.0
[initial]
speed_mps = 60.0
[[segment]]
kind = "hold"
duration_s = 10.0
[[segment]]
kind = "coordinated_turn"
yaw_rate_dps = 6.0
angle_deg = 90.0
[[segment]]
kind = "turn"
yaw_rate_dps = 6.0
angle_deg = -90.0
[[segment]]
kind = "hold"
duration_s = 10.0
"""


def _s(t_s: float) -> np.ndarray:
    return np.array([round(t_s * 1e9)], dtype=np.int64)


def test_static_truth_is_gravity_and_earth_rate() -> None:
    # GIVEN a vehicle standing still, level, heading north
    tg = TruthGenerator(load_scenario("static"))
    b = tg.sample(np.linspace(0, 7200e9, 50).astype(np.int64))
    lat = math.radians(50.45)
    # THEN the accelerometers read −g and the gyros the Earth rate resolved in NED = body
    assert np.allclose(b.f_b_mps2, [0.0, 0.0, -float(earth.normal_gravity(lat, 180.0))], atol=1e-12)
    assert np.allclose(b.w_ib_b_radps, earth.earth_rate_ned(lat), atol=1e-15)
    assert np.abs(b.pos_ned_m).max() < 1e-9


def test_coordinated_turn_has_no_side_force_and_turns_the_commanded_angle() -> None:
    tg = TruthGenerator(parse_scenario(TURN))
    t_turn = 10.0 + 0.5 * 15.0  # well inside the steady part of the coordinated turn
    b = tg.sample(_s(t_turn))
    # coordinated: specific force in the body symmetry plane (only Earth-rate terms, mm/s²)
    assert abs(b.f_b_mps2[0, 1]) < 0.02
    # and the load factor is 1/cos(bank): |f| = g / cos φ, tan φ = v ω / g
    g = float(earth.normal_gravity(math.radians(45.0), b.alt_m[0]))
    bank = math.atan(60.0 * math.radians(6.0) / 9.80665)
    assert math.isclose(float(np.linalg.norm(b.f_b_mps2)), g / math.cos(bank), rel_tol=2e-3)
    assert math.isclose(quat_to_euler(b.q_nb)[0, 0], bank, rel_tol=1e-9)
    # the flat turn that follows is skidding: side force = v ω
    end1 = tg.primitives[4].t0_s  # coordinated turn = prims 1..3, flat turn = prims 4..6
    mid_flat = tg.primitives[5].t0_s + 0.5 * tg.primitives[5].duration_s
    assert math.isclose(abs(tg.sample(_s(mid_flat)).f_b_mps2[0, 1]), 60.0 * math.radians(6.0), rel_tol=2e-3)
    yaw = quat_to_euler(tg.sample(_s(end1)).q_nb)[0, 2]
    assert math.isclose(yaw, math.pi / 2, abs_tol=1e-9)
    assert abs(quat_to_euler(tg.sample(_s(tg.duration_ns / 1e9)).q_nb)[0, 2]) < 1e-9


def test_velocity_is_the_derivative_of_position() -> None:
    tg = TruthGenerator(load_scenario("uav_survey"))
    t = np.arange(0, int(600e9), int(0.01e9), dtype=np.int64)
    b = tg.sample(t)
    lat, h = b.lat_rad, b.alt_m
    r_m, r_n = earth.radii_of_curvature(lat)
    # v_N = (R_M + h) dL/dt, v_E = (R_N + h) cos L dλ/dt, v_D = −dh/dt, by central differences
    dt = 0.01
    vn = (r_m[1:-1] + h[1:-1]) * (lat[2:] - lat[:-2]) / (2 * dt)
    ve = (r_n[1:-1] + h[1:-1]) * np.cos(lat[1:-1]) * (b.lon_rad[2:] - b.lon_rad[:-2]) / (2 * dt)
    vd = -(h[2:] - h[:-2]) / (2 * dt)
    v = np.stack([vn, ve, vd], axis=-1)
    assert np.abs(v - b.vel_ned_mps[1:-1]).max() < 2e-3


def test_sample_does_not_depend_on_batching() -> None:
    tg = TruthGenerator(load_scenario("car_drive"))
    t = np.sort(np.random.default_rng(3).integers(0, tg.duration_ns, 5000)).astype(np.int64)
    whole = tg.sample(t)
    parts = [tg.sample(t[i:j]) for i, j in [(0, 1), (1, 17), (17, 2500), (2500, 5000)]]
    for f in ("pos_ned_m", "vel_ned_mps", "q_nb", "f_b_mps2", "w_ib_b_radps", "lat_rad"):
        assert np.array_equal(getattr(whole, f), np.concatenate([getattr(p, f) for p in parts]))


def test_initial_state_is_the_truth_at_zero() -> None:
    tg = TruthGenerator(load_scenario("straight_level"))
    init = tg.initial_state()
    assert init.stamp_ns == 0
    assert np.allclose(init.vel_ned_mps, [50.0, 0.0, 0.0])
    assert init.lat_rad == init.origin_lat_rad == math.radians(50.45)


def test_one_truth_generator_per_motion_in_a_process() -> None:
    # hil sim's nodes each parse the run's scenario: one generator for all of them (building it
    # integrates the whole trajectory), another for any change of the motion it reads
    base = load_scenario("uav_survey")
    again = parse_scenario(base.source_text, base.name)  # equal, not the same object
    assert again is not base
    shared = truth_for(base)
    assert truth_for(again) is shared
    assert truth_for(scenario_overrides(base, seed=base.seed + 1, imu_rate_hz=1000)) is shared
    longer = truth_for(scenario_overrides(base, duration_s=base.duration_s + 1.0))
    assert longer is not shared and longer.duration_ns == round((base.duration_s + 1.0) * 1e9)
    moved = dataclasses.replace(base, origin_alt_m=base.origin_alt_m + 1.0)
    assert truth_for(moved) is not shared
    assert truth_for(moved).initial_state().alt_m == base.origin_alt_m + 1.0
    # -0.0 is not 0.0 to the bits of what follows from it
    level = dataclasses.replace(base, initial_euler_deg=(0.0, 0.0, 0.0))
    signed = dataclasses.replace(base, initial_euler_deg=(-0.0, 0.0, 0.0))
    assert truth_for(level) is not truth_for(signed)
    # what the generator gives is what a generator of its own gives, bit for bit
    t = np.arange(0, 10_000_000_000, 7_000_000, dtype=np.int64)
    own, cached = TruthGenerator(again).sample(t), truth_for(again).sample(t)
    for f in dataclasses.fields(own):
        assert np.array_equal(getattr(own, f.name), getattr(cached, f.name))


def test_a_motion_without_a_faithful_repr_gets_a_generator_of_its_own() -> None:
    # a numpy array's repr elides its middle: two different ones could read the same
    base = load_scenario("straight_level")
    seg = base.segments[0]
    odd = dataclasses.replace(
        base, segments=(MotionSegment(seg.kind, {**seg.params, "note": np.zeros(2000)}), *base.segments[1:])
    )
    assert truth_for(odd) is not truth_for(odd)

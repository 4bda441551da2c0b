"""Strapdown INS: ideal sensors reproduce the truth; a tilt shows the Schuler oscillation."""

from __future__ import annotations

import math
import time

import numpy as np
import pytest
from scipy.optimize import least_squares

from hil.nav import earth
from hil.nav.attitude import attitude_error_rad, euler_to_quat, quat_multiply
from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nav.strapdown import (
    LazyNavState,
    strapdown_from_initial,
    strapdown_run,
    strapdown_step,
    to_nav_state,
)
from hil.nav.trajectory import TruthGenerator


def _free_ins_error(name: str, duration_s: float, rate_hz: int, every: int) -> np.ndarray:
    """Position error norm (m) of the free INS on ideal increments, every ``every`` steps."""
    s = scenario_overrides(load_scenario(name), duration_s=duration_s, imu_rate_hz=rate_hz)
    tg = TruthGenerator(s)
    n = round(duration_s * rate_hz)
    t = (np.arange(n + 1, dtype=np.int64) * 1_000_000_000) // rate_hz
    dth, dv = tg.increments(t[:-1], t[1:])
    _, tr = strapdown_run(strapdown_from_initial(tg.initial_state()), dth, dv, 1 / rate_hz, every)
    truth = tg.sample(t[tr.step.astype(int)])
    pos = earth.lla_to_ned(
        tr.lat_rad, tr.lon_rad, tr.alt_m, tg.origin_lat_rad, tg.origin_lon_rad, tg.origin_alt_m
    )
    att = np.linalg.norm(attitude_error_rad(tr.q_nb, truth.q_nb), axis=1)
    assert att.max() < 1e-6
    return np.linalg.norm(pos - truth.pos_ned_m, axis=1)


@pytest.mark.slow
def test_ideal_free_ins_stays_within_1_m_for_1_h_straight_and_level_at_400_hz() -> None:
    err = _free_ins_error("straight_level", 3600.0, 400, 4000)
    assert err.max() < 1.0


def test_ideal_free_ins_through_the_uav_survey_turns() -> None:
    # 7 × 180° coordinated turns (bank ≈ 28°) at 200 Hz; measured ≈ 0.07 m at 400 Hz, 1108 s
    err = _free_ins_error("uav_survey", load_scenario("uav_survey").duration_s, 200, 2000)
    assert err.max() < 0.3


def test_step_and_run_give_identical_numbers() -> None:
    tg = TruthGenerator(load_scenario("car_drive"))
    t = (np.arange(401, dtype=np.int64) + 12_000) * 5_000_000
    dth, dv = tg.increments(t[:-1], t[1:])
    s0 = strapdown_from_initial(tg.initial_state())
    end, _ = strapdown_run(s0, dth, dv, 0.005)
    s = s0
    for k in range(400):
        s = strapdown_step(s, dth[k], dv[k], 0.005)
    assert np.array_equal(s.q_nb, end.q_nb) and np.array_equal(s.vel_ned_mps, end.vel_ned_mps)
    assert (s.lat_rad, s.lon_rad, s.alt_m) == (end.lat_rad, end.lon_rad, end.alt_m)
    nav = to_nav_state(s, tg.initial_state())
    assert nav.pos_ned_m.shape == (3,) and nav.q_nb.shape == (4,)


def test_schuler_oscillation_from_a_1_mrad_tilt() -> None:
    # GIVEN the static scenario, ideal sensors, and the INS started with 1 mrad of roll error
    rate = 100
    duration = 2 * 5064.0
    tg = TruthGenerator(scenario_overrides(load_scenario("static"), duration_s=duration, imu_rate_hz=rate))
    n = round(duration * rate)
    t = (np.arange(n + 1, dtype=np.int64) * 1_000_000_000) // rate
    dth, dv = tg.increments(t[:-1], t[1:])
    s0 = strapdown_from_initial(tg.initial_state())
    s0 = s0.replace(q_nb=quat_multiply(euler_to_quat([1e-3, 0.0, 0.0]), s0.q_nb))
    # WHEN the free INS runs offline (height held: the free vertical channel diverges)
    wall = time.perf_counter()
    _, tr = strapdown_run(s0, dth, dv, 1 / rate, record_every=rate * 10, vertical_hold=True)
    wall = time.perf_counter() - wall
    assert duration / wall >= 100.0  # ≥ 100× real time
    # THEN the horizontal position error oscillates at the Schuler period (84.4 min), its plane
    # slowly turned by the Foucault rate; fit δN + iδE = e^{−iω_f t} (a + b cos ω_s t + c sin ω_s t)
    pos = earth.lla_to_ned(
        tr.lat_rad, tr.lon_rad, tr.alt_m, tg.origin_lat_rad, tg.origin_lon_rad, tg.origin_alt_m
    )
    z = pos[:, 0] + 1j * pos[:, 1]
    ts = tr.step / rate
    assert np.abs(z).max() > 1000.0  # a 1 mrad tilt is worth ~6.4 km of Schuler swing

    def resid(p: np.ndarray) -> np.ndarray:
        ws, wf = p
        basis = np.exp(-1j * wf * ts)[:, None] * np.stack(
            [np.ones_like(ts), np.cos(ws * ts), np.sin(ws * ts)], axis=-1
        )
        coef, *_ = np.linalg.lstsq(basis, z, rcond=None)
        r = basis @ coef - z
        return np.concatenate([r.real, r.imag])

    wf0 = earth.OMEGA_IE_RADPS * math.sin(tg.origin_lat_rad)
    fits = [least_squares(resid, [2 * math.pi / 5000.0, sgn * wf0]) for sgn in (1.0, -1.0)]
    best = min(fits, key=lambda f: f.cost)
    period_min = 2 * math.pi / best.x[0] / 60.0
    assert abs(period_min - 84.4) / 84.4 < 0.01, period_min
    assert np.sqrt(2 * best.cost / len(ts)) < 0.01 * np.abs(z).max()  # the model explains it


def test_lazy_nav_state_floats_are_its_arrays_values_read_in_either_order() -> None:
    """The position as floats (no array built) is the array's values, bit for bit, whether the
    array was read first or not."""
    rng = np.random.default_rng(12)
    origin = (0.88, 0.53, 180.0)
    for _ in range(2000):
        st = (
            float(origin[0] + rng.normal(0.0, 1e-3)),
            float(origin[1] + rng.normal(0.0, 1e-3)),
            float(rng.uniform(-100.0, 3000.0)),
            *rng.normal(0.0, 30.0, 3).tolist(),
            1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0,
        )  # fmt: skip
        floats_first = LazyNavState(st, origin).floats()[0]  # type: ignore[arg-type]
        array_first = LazyNavState(st, origin)  # type: ignore[arg-type]
        want = array_first.pos_ned_m
        assert np.array(floats_first).tobytes() == want.tobytes()
        assert np.array(array_first.floats()[0]).tobytes() == want.tobytes()

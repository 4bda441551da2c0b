"""The delayed fusion horizon and the output predictor (issue 22.1 with issue 20.4).

GIVEN the rig's own IMU and GNSS emulator cores on a turning, accelerating drive
WHEN GNSS fixes reach the fusion 0.3 s after their time of validity (beyond the 0.2 s lag the
fusion used to have, within the 0.5 s horizon it has now)
THEN every estimator fuses them at their time of validity and publishes exactly what it publishes
when the fixes arrive at once; a fix older than the horizon is refused, counted, journaled, and
its source's crossing of the bound is an event; the output predictor carries a state forward as
the strapdown does.
"""

from __future__ import annotations

from functools import cache

import numpy as np

from hil.fusion.core import FusionConfig, FusionCore
from hil.fusion.ideal import ideal_streams
from hil.fusion.predictor import OutputPredictor
from hil.messages import GnssFix, ImuSample, NavSolution, encode
from hil.nav.scenario import parse_scenario
from hil.nav.strapdown import _gravity, strapdown_from_initial, strapdown_step, to_nav_state
from hil.nav.trajectory import TruthGenerator

SCENARIO = """
name = "horizon"
seed = 7
duration_s = 40.0
[origin]
lat_deg = 50.45
lon_deg = 30.52
alt_m = 300.0
[initial]
attitude_deg = [0.0, 0.0, 0.0]
speed_mps = 15.0
[imu]
preset = "tactical"
rate_hz = 200
[gnss]
rate_hz = 10.0
pos_sigma_m = 2.0
vel_sigma_mps = 0.1
latency_s = 0.0
[[segment]]
kind = "hold"
duration_s = 10.0
[[segment]]
kind = "turn"
yaw_rate_dps = 6.0
duration_s = 15.0
[[segment]]
kind = "hold"
duration_s = 15.0
"""

ESTIMATORS = ("comp1", "compvs", "cf3", "kfvel", "ekf15")  # every kind that takes GNSS


@cache
def _inputs() -> tuple[list[ImuSample], list[GnssFix]]:
    return ideal_streams(parse_scenario(SCENARIO))


def _core(**cfg: object) -> FusionCore:
    s = parse_scenario(SCENARIO)
    return FusionCore.for_scenario(s, FusionConfig(estimators=ESTIMATORS, **cfg))  # type: ignore[arg-type]


def _live(core: FusionCore, latency_ns: int | list[int]) -> list[NavSolution]:
    """Inputs pushed in arrival order: each fix ``latency_ns`` after its time of validity."""
    imus, fixes = _inputs()
    lat = latency_ns if isinstance(latency_ns, list) else [latency_ns] * len(fixes)
    arrivals = [(m.stamp_ns, 0, i, m) for i, m in enumerate(imus)]
    arrivals += [(f.stamp_ns + lat[i], 1, i, f) for i, f in enumerate(fixes)]
    arrivals.sort(key=lambda a: a[:3])  # a fix arriving with an IMU sample comes after it
    out: list[NavSolution] = []
    for *_k, m in arrivals:
        out += core.push(m)
    return out + core.flush()


def test_fixes_later_than_the_old_lag_are_fused_exactly_as_if_on_time_by_every_estimator() -> None:
    """Bit for bit, not within a tolerance: the estimators run on the horizon, which sees the
    same inputs in the same order whether a fix came at once or 0.3 s later, and the predictor
    carries the same horizon states with the same IMU samples."""
    on_time = _live(_core(), 0)
    late = _live(_core(), 300_000_000)
    assert len(on_time) == len(late) > 0
    assert [encode(s) for s in late] == [encode(s) for s in on_time]
    # ... and the fixes matter: without them every estimator says something else
    imus, _ = _inputs()
    blind = _core()
    no_gnss = [s for m in imus for s in blind.push(m)] + blind.flush()
    last = {s.estimator: s for s in late}
    last_blind = {s.estimator: s for s in no_gnss}
    for name in ESTIMATORS:
        assert last[name].gnss_seq > 0
        assert last[name].pos_ned_m != last_blind[name].pos_ned_m, name


def test_the_fusion_before_the_horizon_dropped_those_fixes() -> None:
    """The 0.2 s watermark without predictor (the old behaviour, still selectable): every fix
    0.3 s late is behind it and journaled ``late``; the estimators coast."""
    core = _core(lag_ns=200_000_000, output_predictor=False)
    _live(core, 300_000_000)
    imus, fixes = _inputs()
    # every fix that arrives while IMU samples still come (the last few are flushed at the end)
    arrived = [f for f in fixes if f.stamp_ns + 300_000_000 <= imus[-1].stamp_ns]
    assert len(arrived) > 390
    assert core.take_dropped() == [f"late:gnss:{f.seq}" for f in arrived]


def test_a_fix_older_than_the_bound_is_refused_counted_journaled_and_the_crossing_is_an_event() -> None:
    _, fixes = _inputs()
    n = len(fixes)
    # on time, then 0.7 s late (beyond the 0.5 s bound) for fixes 100..149, then on time again
    lat = [700_000_000 if 100 <= i < 150 else 50_000_000 for i in range(n)]
    core = _core()
    out = _live(core, lat)
    dropped = core.take_dropped()
    assert dropped == [f"late:gnss:{i}" for i in range(100, 150)]
    assert core.counters["dropped_late.gnss"] == 50
    assert core.counters["latency_over_bound.gnss"] == 1  # one crossing, not one per fix
    events = core.take_latency_events()
    assert [(e.kind, e.gate) for e in events] == [
        ("latency_over_bound", "gnss"),
        ("latency_within_bound", "gnss"),
    ]
    assert "gnss:100" in events[0].detail and "0.700 s" in events[0].detail
    status = core.status_counters()
    assert status["horizon_lag_ms"] == 500
    assert status["latency_max_ms.gnss"] == 50  # what was taken in; the refused are counted apart
    # after the episode the fixes are fused again: the last output (at the last IMU sample) has
    # the horizon 0.5 s behind it, past all but the last 5-6 fixes (10 Hz, 50 ms latency)
    assert max(s.gnss_seq for s in out if s.estimator == "ekf15") >= n - 1 - 6


def test_the_output_predictor_carries_a_state_forward_as_the_strapdown_does() -> None:
    """Half a second of the turn at 200 Hz: the pre-integrated IMU applied to the horizon state
    against the full strapdown from it. What the predictor leaves out (Earth rate, transport rate,
    Coriolis at 15 m/s, gravity's change) is at most ~1e-3 m/s² over 0.5 s: 0.2 mm, 0.5 mm/s,
    4e-5 rad; the bounds are a few times that."""
    s = parse_scenario(SCENARIO)
    imus, _ = _inputs()
    init = TruthGenerator(s).initial_state()
    ins = strapdown_from_initial(init)
    origin = (init.origin_lat_rad, init.origin_lon_rad, init.origin_alt_m)
    start = 2400  # 12 s: in the turn, 15 m/s
    for m in imus[:start]:
        ins = strapdown_step(ins, m.dtheta_b_rad, m.dvel_b_mps, m.dt_ns * 1e-9)
    horizon = to_nav_state(ins, origin)
    pred = OutputPredictor(imus[start - 1].stamp_ns, _gravity(init.lat_rad, init.alt_m))
    for m in imus[start : start + 100]:
        ins = strapdown_step(ins, m.dtheta_b_rad, m.dvel_b_mps, m.dt_ns * 1e-9)
        pred.step(m.stamp_ns, tuple(m.dtheta_b_rad), tuple(m.dvel_b_mps), m.dt_ns * 1e-9)  # type: ignore[arg-type]
    want = to_nav_state(ins, origin)
    got = pred.predict(horizon, pred.motion())
    moved = np.linalg.norm(want.pos_ned_m - horizon.pos_ned_m)
    assert moved > 7.0  # it did carry it: 0.5 s at 15 m/s
    assert np.linalg.norm(got.pos_ned_m - want.pos_ned_m) < 2e-3
    assert np.linalg.norm(got.vel_ned_mps - want.vel_ned_mps) < 3e-3
    cos_half = abs(float(np.dot(got.q_nb, want.q_nb)))  # cos of half the rotation between them
    assert cos_half > np.cos(2e-4 / 2)


LATE_SCENARIO = """
name = "late_fixes"
seed = 3
duration_s = 8.0
[origin]
lat_deg = 50.45
lon_deg = 30.52
alt_m = 300.0
[initial]
attitude_deg = [0.0, 0.0, 0.0]
speed_mps = 20.0
[imu]
preset = "tactical"
rate_hz = 200
[gnss]
rate_hz = 10.0
pos_sigma_m = 2.0
vel_sigma_mps = 0.1
latency_s = 0.1
jitter_s = 0.01
[[segment]]
kind = "turn"
yaw_rate_dps = 5.0
duration_s = 8.0
[[event]]
kind = "gnss_latency"
t_start_s = 4.0
latency_s = 0.3
jitter_s = 0.02
"""


def test_rerun_verifies_a_sim_recording_whose_fixes_came_later_than_the_old_lag(tmp_path) -> None:  # type: ignore[no-untyped-def]
    """hil sim with car_drive's kind of latency event (0.3 s from 4 s on): the recording's fixes
    reach the fusion behind where the old 0.2 s watermark was, the fusion fuses them (nothing
    journaled late) and ``hil rerun --verify`` recomputes every published output bit for bit."""
    from hil.messages import FusionJournal
    from hil.record.mcapio import read_session
    from hil.record.rerun import rerun_fusion_file
    from hil.runners.sim import SimOptions, run_sim

    scen = tmp_path / "late.toml"
    scen.write_text(LATE_SCENARIO)
    path = tmp_path / "late.mcap"
    run_sim(SimOptions(scenario=str(scen), record=path, rig="late", estimators=["comp1", "kfvel", "ekf15"]))
    session = read_session(path)
    fixes = [r.decode() for r in session.records if r.topic.endswith("/synced/gnss")]
    late_arrivals = [f for f in fixes if f.rx_stamp_ns - f.stamp_ns > 250_000_000]  # type: ignore[attr-defined]
    assert len(late_arrivals) >= 20  # ~4 s of 10 Hz fixes arrived beyond the old lag
    journals = [r.decode() for r in session.records if r.topic.endswith("/fusion/journal")]
    dropped = [d for j in journals if isinstance(j, FusionJournal) for d in j.dropped]
    assert dropped == []
    res, _stream, _note = rerun_fusion_file(path)
    assert res.difference is None, res.difference
    assert res.n_recorded == res.n_recomputed > 0
    ekf = [r.decode() for r in session.records if r.topic.endswith("/nav/ekf15")]
    # the fixes of the late period were fused: the last output's horizon took all but the last
    # ~0.5 s of validity + 0.3 s of latency worth of fixes
    assert max(s.gnss_seq for s in ekf) >= max(f.seq for f in fixes) - 9  # type: ignore[attr-defined]


def test_the_predictor_after_many_reanchorings_measures_the_motion_a_fresh_one_does() -> None:
    """The running sums move their anchor to the horizon every REANCHOR_STEPS samples; after
    several moves the motion from the horizon is what a predictor started at the horizon
    measures (to rounding: 1e-9 of a 0.5 s window's metres)."""
    from hil.fusion.predictor import REANCHOR_STEPS

    imus, _ = _inputs()
    n = 3 * REANCHOR_STEPS + 57  # the drive's increments over and over, on stamps 5 ms apart
    window = 100
    samples = [(5_000_000 * (k + 1), imus[k % len(imus)]) for k in range(n)]
    long = OutputPredictor(0, 9.81)
    for k, (t, m) in enumerate(samples):
        long.step(t, tuple(m.dtheta_b_rad), tuple(m.dvel_b_mps), m.dt_ns * 1e-9)  # type: ignore[arg-type]
        if k >= window:
            long.horizon_at(samples[k - window][0])
    fresh = OutputPredictor(samples[n - 1 - window][0], 9.81)
    for t, m in samples[n - window :]:
        fresh.step(t, tuple(m.dtheta_b_rad), tuple(m.dvel_b_mps), m.dt_ns * 1e-9)  # type: ignore[arg-type]
    a, b = long.motion(), fresh.motion()
    assert len(long.entries) == window + 1
    assert abs(a[0] - b[0]) < 1e-12
    for x, y in zip(a[1:], b[1:], strict=True):
        assert np.allclose(x, y, rtol=0, atol=1e-9), (x, y)
    assert np.linalg.norm(b[3]) > 1.0  # a real motion: metres in the window


def test_the_fusion_service_publishes_the_crossing_and_states_the_bound_in_its_status() -> None:
    """The node around the core: a fix older than the horizon is an ``event/fusion`` of kind
    ``latency_over_bound`` (once), and the status counters say the bound and the refusals."""
    from hil.nodes.fusion import FusionNode, FusionOptions
    from hil.runners.sim import SimOptions, sim_run_info

    node = FusionNode(sim_run_info(SimOptions(scenario="straight_level", duration_s=5.0)), FusionOptions())
    imus, fixes = _inputs()
    outs = node.on_message("synced/imu", imus[0], imus[0].stamp_ns)
    # the first IMU sample's arrival publishes every estimator's solution there, not 0.5 s later
    assert sorted(k for k, _ in outs) == sorted(f"nav/{n}" for n in ("ins", *node.config.estimators))
    assert all(m.stamp_ns == imus[0].stamp_ns for _, m in outs)
    for m in imus[1:400]:  # 2 s of IMU
        outs += node.on_message("synced/imu", m, m.stamp_ns)
    for f in fixes[:3]:  # fixes valid at 0, 0.1, 0.2 s: 1.8 s old and more, beyond the 0.5 s bound
        outs += node.on_message("synced/gnss", f, imus[399].stamp_ns)
    events = [m for k, m in outs if k == "event/fusion"]
    assert [e.kind for e in events] == ["latency_over_bound"]
    assert "gnss:0" in events[0].detail
    counters = node.counters()
    assert counters["horizon_lag_ms"] == 500 and counters["dropped_late.gnss"] == 3


def test_an_imu_sample_behind_a_newer_one_reaches_the_horizon_not_the_predictor_and_is_journaled() -> None:
    """A time sync step can put an IMU sample behind the newest: the estimators still take it
    (in the total order, on the horizon), the predictor, past it already, does not; the journal
    names it so rerun does the same. A copy of a sample already held is a duplicate."""
    imus, _ = _inputs()
    core = _core()
    for m in imus[:100]:
        core.push(m)
    behind = imus[100]
    for m in imus[101:110]:
        core.push(m)
    core.push(behind)  # 22.5 ms behind the newest, far ahead of the 0.5 s horizon
    core.push(imus[105])  # a second copy of one the predictor holds
    j = core.journal(0, imus[109].stamp_ns)
    assert j.unpredicted == ["imu:100"] and j.dropped == ["dup:imu:105"]
    assert core.counters["unpredicted.imu"] == 1
    core.flush()
    assert core.consumed == 110  # every distinct sample reached the estimators once


def test_the_predictor_removes_an_estimators_bias_estimate_as_its_own_integration_does() -> None:
    """A consumer IMU's turn-on biases (0.5 °/s, 10 mg) over the 0.5 s window: carried with the
    raw increments the state is 0.25° and 5 cm/s off; with the estimator's bias estimate taken
    out (first order) it is what the strapdown makes of the unbiased increments, within what
    the first-order terms leave (the window turns 3°: bias × that, a few mm/s)."""
    s = parse_scenario(SCENARIO)
    imus, _ = _inputs()
    init = TruthGenerator(s).initial_state()
    origin = (init.origin_lat_rad, init.origin_lon_rad, init.origin_alt_m)
    b_g = np.array([0.5, -0.4, 0.3]) * np.pi / 180.0
    b_a = np.array([0.1, -0.08, 0.06])
    ins = strapdown_from_initial(init)
    start = 2400
    for m in imus[:start]:
        ins = strapdown_step(ins, m.dtheta_b_rad, m.dvel_b_mps, m.dt_ns * 1e-9)
    horizon = to_nav_state(ins, origin)
    pred = OutputPredictor(imus[start - 1].stamp_ns, _gravity(init.lat_rad, init.alt_m))
    for m in imus[start : start + 100]:
        dt = m.dt_ns * 1e-9
        ins = strapdown_step(ins, m.dtheta_b_rad, m.dvel_b_mps, dt)  # the true increments
        biased_th = tuple(np.asarray(m.dtheta_b_rad) + b_g * dt)
        biased_dv = tuple(np.asarray(m.dvel_b_mps) + b_a * dt)
        pred.step(m.stamp_ns, biased_th, biased_dv, dt)  # type: ignore[arg-type]
    want = to_nav_state(ins, origin)
    raw = pred.predict(horizon, pred.motion())
    fixed = pred.predict(horizon, pred.motion(), (b_g, b_a))
    assert np.linalg.norm(raw.vel_ned_mps - want.vel_ned_mps) > 0.04
    assert np.linalg.norm(fixed.vel_ned_mps - want.vel_ned_mps) < 5e-3
    assert np.linalg.norm(fixed.pos_ned_m - want.pos_ned_m) < 2e-3
    assert abs(float(np.dot(raw.q_nb, want.q_nb))) < np.cos(np.radians(0.2) / 2)  # > 0.2° apart
    assert abs(float(np.dot(fixed.q_nb, want.q_nb))) > np.cos(np.radians(0.01) / 2)


def test_the_free_ins_named_alone_runs_alone_and_a_misspelt_name_is_refused_naming_it() -> None:
    """``--estimators ins``: the free inertial solution alone (a Schuler-period check needs no
    filter); ``ins`` beside others changes nothing, since it always runs."""
    import pytest

    from hil.nodes.fusion import FusionNode, FusionOptions
    from hil.runners.sim import SimOptions, sim_run_info

    assert FusionOptions(estimators=["ins"]).config().estimators == ()
    assert FusionOptions(estimators=["ins", "ekf15"]).config().estimators == ("ekf15",)
    assert FusionOptions().config().estimators != ()  # none named: the registry's defaults
    node = FusionNode(
        sim_run_info(SimOptions(scenario="straight_level", duration_s=5.0)), FusionOptions(estimators=["ins"])
    )
    imus, _fixes = _inputs()
    outs = node.on_message("synced/imu", imus[0], imus[0].stamp_ns)
    assert [k for k, _ in outs] == ["nav/ins"]
    with pytest.raises(ValueError, match=r"unknown estimator.*'insx'"):
        FusionOptions(estimators=["insx"])


def _replayed(core: FusionCore, spoil: dict[float, object]) -> list[NavSolution]:
    """Every input through ``replay`` in the total order; at each rig second of ``spoil`` its
    function is called on the core first (a state made non-finite)."""
    imus, fixes = _inputs()
    out: list[NavSolution] = []
    for m in sorted([*imus, *fixes], key=lambda m: (m.stamp_ns, m.sensor != "imu")):
        for t, act in list(spoil.items()):
            if m.stamp_ns >= t * 1e9:
                act(core)  # type: ignore[operator]
                del spoil[t]
        out += core.replay(m)
    return out


def test_a_stream_gone_non_finite_is_counted_not_published_and_the_others_go_on() -> None:
    """The output predictor's streams are carried and converted in one call per sample: a stream
    whose state is NaN (comp1's filter) or whose attitude is all zeros (kfvel's solution: the
    carry's normalisation divides by zero, which takes that sample's streams one by one) is
    counted in ``errors.nonfinite.<name>`` and not published; every other stream is published as
    it is without the broken ones, bit for bit."""
    import math

    from hil.nav.types import FloatNavState, nav_floats

    def nan_filter(core: FusionCore) -> None:
        est = next(e for e in core._ests if e.name == "comp1")
        est.core.x = est.core.x * math.nan  # type: ignore[attr-defined]

    def zero_attitude(core: FusionCore) -> None:
        est = next(e for e in core._ests if e.name == "kfvel")
        real = est.solution

        def solution() -> FloatNavState:
            nav = real()
            pos, vel, _q = nav_floats(nav)
            return FloatNavState(pos, vel, (0.0, 0.0, 0.0, 0.0), nav.pos_sigma_m, nav.vel_sigma_mps)

        est.solution = solution  # type: ignore[method-assign]

    clean = _replayed(_core(), {})
    core = _core()
    spoilt = _replayed(core, {20.0: nan_filter, 30.0: zero_attitude})
    counters = core.status_counters()
    assert counters.get("errors.nonfinite.comp1", 0) > 100 and counters.get("errors.nonfinite.kfvel", 0) > 100
    assert not [k for k in counters if k.startswith("errors.estimator_failed")]
    assert not [s for s in spoilt if s.estimator == "comp1" and s.stamp_ns > 20e9]
    assert not [s for s in spoilt if s.estimator == "kfvel" and s.stamp_ns > 30e9]
    assert [s for s in spoilt if s.estimator == "kfvel" and 29e9 < s.stamp_ns < 30e9]
    others = [encode(s) for s in clean if s.estimator not in ("comp1", "kfvel")]
    assert (
        len(others) > 1000 and [encode(s) for s in spoilt if s.estimator not in ("comp1", "kfvel")] == others
    )

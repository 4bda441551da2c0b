"""Estimators stepped a block of IMU intervals at a time (``on_imu_block``, what the fusion core
does between two reads of them) end where one ``on_imu`` per interval (a block of one) ends, bit
for bit: the runs split at the covariance predictions, coasts and stage switches wherever a block
boundary falls. The float arithmetic itself is held to the recordings made before blocks
existed by the golden replay (tests/replay) and to Python's by tests/unit/test_jit.py."""

from __future__ import annotations

import numpy as np
import pytest

from hil.estimators.base import GnssInput, ImuBlock, ImuInput
from hil.estimators.registry import make_estimator
from hil.estimators.tuning import params_for
from hil.fusion.core import block_step_of
from hil.nav import strapdown
from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nav.strapdown import LazyNavState, strapdown_from_initial, strapdown_step_f
from hil.nav.trajectory import TruthGenerator
from hil.nav.types import nav_floats
from hil.runtime import jit
from hil.sensors.gnss import GnssEmulatorCore
from hil.sensors.imu import ImuEmulatorCore, sensor_rng

SEED_FAMILY = ("comp1", "comp3f", "compvs", "cf3", "kfvel")
OUTAGE_NS = (12_000_000_000, 17_000_000_000)  # no fixes: the filters' coasts fall due mid-block


def _bits(est: object) -> tuple[object, ...]:
    """Everything an estimator publishes, as exact values (floats compare bit for bit here:
    none is NaN, and a -0/+0 difference shows in ``tobytes``)."""
    nav = est.solution()  # type: ignore[attr-defined]
    pos, vel, q = nav_floats(nav)
    sig = [
        np.asarray(s, dtype=np.float64).tobytes()
        for s in (nav.pos_sigma_m, nav.vel_sigma_mps, nav.att_sigma_rad)
        if s is not None
    ]
    health = sorted(est.health().items())  # type: ignore[attr-defined]
    return (np.array((*pos, *vel, *q)).tobytes(), *sig, np.array([v for _, v in health]).tobytes())


@pytest.mark.parametrize("kernels", ["compiled", "python"])
def test_blocks_of_imu_intervals_leave_the_bits_of_one_step_each(
    kernels: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """uav_survey's consumer IMU and receiver, 30 s: the seed family open loop and in feedback
    form, ekf15 with gyro and accelerometer calibration; blocks of 1-30 intervals (across the
    covariance predictions' boundaries), each estimator's solution and health compared at
    every fix and at the end; a 5 s outage, so that the coasts fall due inside blocks."""
    if kernels == "compiled":
        assert jit.enable() == "compiled"
    else:  # the Python kernels, whatever this process compiled before
        monkeypatch.setattr(strapdown, "_step", jit.python_kernel("_step"))
        monkeypatch.setattr(strapdown, "_corrected_run", strapdown._PY_CORRECTED_RUN)
    sc = scenario_overrides(load_scenario("uav_survey"), seed=3, duration_s=30.0)
    truth = TruthGenerator(sc)
    init = truth.initial_state()
    imu = ImuEmulatorCore(sc, truth, sensor_rng(sc.seed, "imu"))
    gnss = GnssEmulatorCore(sc, truth, sensor_rng(sc.seed, "gnss"))
    batch = imu.next_batch(int(30.0 * imu.rate_hz))
    fixes = gnss.next_batch(int(batch.t_ns[-1]))
    fb = params_for(sc.imu.params, sc.gnss, feedback=SEED_FAMILY, gyro_cal=True, accel_cal=True)
    op = params_for(sc.imu.params, sc.gnss, feedback=(), gyro_cal=True, accel_cal=True)
    specs = [(n, fb.get(n)) for n in (*SEED_FAMILY, "ekf15")] + [(n, op.get(n)) for n in SEED_FAMILY]
    one = [make_estimator(n, init, p) for n, p in specs]
    blocked = [make_estimator(n, init, p) for n, p in specs]
    steps = [block_step_of(e) for e in blocked]
    assert all(getattr(e, "on_imu_block", None) is not None for e in blocked)  # the block paths ran
    assert any(getattr(e, "loop", None) is not None for e in blocked) and blocked[5]._cal and blocked[5]._acal  # type: ignore[attr-defined]

    rng = np.random.default_rng(5)
    free = strapdown_from_initial(init)
    origin = (init.origin_lat_rad, init.origin_lon_rad, init.origin_alt_m)
    block, size = ImuBlock(), int(rng.integers(1, 31))
    g, compared = 0, 0

    def flush() -> None:
        nonlocal block, size
        if len(block):
            for step in steps:
                step(block)
        block, size = ImuBlock(), int(rng.integers(1, 31))

    n = batch.t_ns.size
    for k in range(n):
        t = int(batch.t_ns[k])
        d = batch.dtheta_b_rad[k].tolist()
        v = batch.dvel_b_mps[k].tolist()
        free = strapdown_step_f(free, *d, *v, batch.dt_s)
        ins = LazyNavState(free, origin)
        inp = ImuInput(t, batch.dt_s, np.array(d), np.array(v))
        for e in one:
            e.on_imu(inp, ins)
        block.append(t, (batch.dt_s, *d, *v), ins)
        if len(block) >= size:
            flush()
        t_next = int(batch.t_ns[k + 1]) if k + 1 < n else t + 1
        while g < fixes.t_valid_ns.size and fixes.t_valid_ns[g] < t_next:
            if OUTAGE_NS[0] <= fixes.t_valid_ns[g] < OUTAGE_NS[1]:  # the receiver lost: coasts
                g += 1
                continue
            flush()
            for a, b in zip(one, blocked, strict=True):
                assert _bits(a) == _bits(b), f"{a.name} differs before fix {g}"  # type: ignore[attr-defined]
            fx = GnssInput.of_batch(fixes, g)
            for e in (*one, *blocked):
                e.on_gnss(fx, ins)
            g += 1
            compared += 1
    flush()
    for a, b in zip(one, blocked, strict=True):
        assert _bits(a) == _bits(b), f"{a.name} differs at the end"  # type: ignore[attr-defined]
    assert compared >= 100  # 5 Hz over 30 s less the outage: the comparison ran at every fix
    # the open-loop filters coasted (on the line, cf3 on its own loop) and so did the feedback
    # forms on the line, all but cf3's, whose INS is what coasts
    coasted = {
        f"{e.name}{'' if k > 5 else '_fb'}": e.core.coasts + e.coasts
        for k, e in enumerate(blocked)
        if hasattr(e, "core")
    }  # type: ignore[attr-defined]
    assert [n for n, c in coasted.items() if c < 1] == ["cf3_fb"], coasted

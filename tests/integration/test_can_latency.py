"""can_latency end to end. `hil sim`: the IMU's frames arrive latency + jitter·U late, in order, the
device stamps untouched, the same file for the same seed, and the time sync absorbs it (the tags
rule the mapping and decide clock steps; the added arrival delay declares none). Live
(`hil up`): the timed window and a `hil fault` command both delay the samples, are recorded as
fault_start/fault_end, and a bad command that arrives anyway is counted, not applied."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
from pathlib import Path

import numpy as np
import pytest

from hil.messages import (
    CaptureTruth,
    ClockModel,
    Event,
    FaultCommand,
    ImuSample,
    ServiceStatus,
    decode,
    encode,
)
from hil.messages import params as fault_params
from hil.nav.scenario import load_scenario
from hil.record.mcapio import Session, read_session
from hil.runners.sim import SimOptions, run_sim
from tests.conftest import REPO, hil_cmd
from tests.integration.test_supervision import Rig
from tests.load import slowdown

pytestmark = pytest.mark.slow

SCENARIO = """
name = "can_latency"
seed = 3
duration_s = 12.0

[origin]
lat_deg = 50.45
lon_deg = 30.52
alt_m = 300.0

[initial]
speed_mps = 50.0

[imu]
preset = "tactical"
rate_hz = 400

[gnss]
rate_hz = 10.0

[[segment]]
kind = "hold"
duration_s = 12.0

[[event]]
kind = "can_latency"
t_start_s = 5.0
t_end_s = 9.0
latency_s = 0.04
jitter_s = 0.02
"""


def _sim(tmp: Path, name: str) -> Session:
    scen = tmp / "can_latency.toml"
    scen.write_text(SCENARIO)
    res = run_sim(SimOptions(scenario=str(scen), record=tmp / name, rig="cl", estimators=["comp1"]))
    return read_session(res.path)


@pytest.fixture(scope="module")
def sim(tmp_path_factory: pytest.TempPathFactory) -> Session:
    return _sim(tmp_path_factory.mktemp("cl"), "cl.mcap")


def _by_capture(s: Session, rig: str, topic: str) -> dict[int, tuple[int, ImuSample]]:
    """seq -> (true capture time, message)."""
    cap = {
        r.sequence: decode(CaptureTruth, r.payload).true_stamp_ns
        for r in s.by_topic(f"hil/{rig}/capture/imu")
    }
    msgs = (decode(ImuSample, r.payload) for r in s.by_topic(f"hil/{rig}/{topic}"))
    return {m.seq: (cap[m.seq], m) for m in msgs if m.seq in cap}


def _late_ms(s: Session, rig: str, t0: float, t1: float) -> np.ndarray:
    raw = _by_capture(s, rig, "sensor/imu")
    return np.array([(m.rx_stamp_ns - t) / 1e6 for t, m in raw.values() if t0 <= t / 1e9 < t1])


def test_hil_sim_delays_the_window_in_order_and_leaves_the_device_stamps(sim: Session) -> None:
    late = _late_ms(sim, "cl", 5.0, 9.0)
    before = _late_ms(sim, "cl", 2.0, 5.0)
    assert len(late) == 1600 and len(before) == 1200  # nothing lost
    assert late.min() >= 40.0 and late.max() <= 60.0 + 1.5  # the window plus the bus's own delay
    assert 50.0 < late.mean() < 58.0, late.mean()  # uniform draw plus the order-keeping waits
    assert before.max() < 1.0  # the bus's own [clock.imu] latency only
    raw = sorted(_by_capture(sim, "cl", "sensor/imu").values())
    rx = [m.rx_stamp_ns for _t, m in raw]
    assert all(a <= b for a, b in itertools.pairwise(rx))  # arrival order = capture order
    dev = np.array([m.device_stamp_ns for _t, m in raw])
    assert np.all(np.diff(dev) > 2.4e6) and np.all(np.diff(dev) < 2.6e6)  # device clock untouched
    edges = [
        (e.kind, e.stamp_ns, json.loads(e.detail)["params"])
        for e in (decode(Event, r.payload) for r in sim.by_topic("hil/cl/event/imu_emulator"))
    ]
    p = {"latency_s": 0.04, "jitter_s": 0.02}
    assert edges == [("fault_start", 5_000_000_000, p), ("fault_end", 9_000_000_000, p)]
    st = decode(ServiceStatus, sim.by_topic("hil/cl/status/imu_emulator")[-1].payload)
    assert st.counter_map()["fault.can_latency.delayed_samples"] == 1600


def test_hil_sim_same_seed_same_delays(sim: Session, tmp_path: Path) -> None:
    again = _sim(tmp_path, "again.mcap")
    assert [r.payload for r in again.by_topic("hil/cl/sensor/imu")] == [
        r.payload for r in sim.by_topic("hil/cl/sensor/imu")
    ]


def test_time_tag_sync_absorbs_the_added_latency(sim: Session) -> None:
    """Synced stamps stay on the tag mapping through the window and after it; no step declared.

    Bound 0.5 ms (half the 1 ms tag gate): the tags are not held, but in the window the sync frame
    can queue on the bus behind released sample frames, so a tag may latch late by up to the gate
    and still be accepted; the filter moves by a fraction of that (measured: 0.10 ms max, 0.05 ms
    mean over 5-12 s, against 0.02 ms max before the window and 59 ms max before the fix).
    """
    syn = _by_capture(sim, "cl", "synced/imu")
    err_before = np.array([m.stamp_ns - t for t, m in syn.values() if 2e9 <= t < 5e9]) / 1e6
    err_in = np.array([m.stamp_ns - t for t, m in syn.values() if 5e9 <= t < 12e9]) / 1e6
    assert np.abs(err_before).max() < 0.1  # the usual error: tens of µs
    assert _late_ms(sim, "cl", 5.0, 9.0).mean() > 45.0  # while the raw arrivals are ~50 ms late
    assert len(err_in) == 2800  # nothing held back or dropped
    assert np.abs(err_in).max() < 0.5, (np.abs(err_in).mean(), np.abs(err_in).max())
    assert np.abs(err_in).mean() < 0.2
    clock = decode(ClockModel, sim.by_topic("hil/cl/clock/imu")[-1].payload)
    assert clock.steps_detected == 0 and clock.state == "locked" and clock.source == "timetag"


TIMED = """
[[event]]
kind = "can_latency"
t_start_s = 2.0
t_end_s = 3.0
latency_s = 0.05
jitter_s = 0.01
"""


def test_live_timed_and_commanded_can_latency_are_applied_and_recorded(tmp_path: Path) -> None:
    scen = tmp_path / "cl.toml"
    scen.write_text(load_scenario("straight_level").source_text + TIMED)
    out = tmp_path / "cl.mcap"
    rig = Rig("clrig", out, "--duration", "600", "--scenario", str(scen))  # stopped at 8 s or later
    rig.running_pid("imu_emulator")
    rig.reach(1.0)  # the commanded fault lands inside the run, with fixes/samples before it
    env = dict(os.environ, HIL_ZENOH_MODE="client", HIL_ZENOH_LISTEN="")
    env["HIL_ZENOH_CONNECT"] = rig.endpoint
    run = {"cwd": REPO, "env": env, "capture_output": True, "text": True, "timeout": 60}
    bad = subprocess.run(hil_cmd("fault", "can_latency", "--rig", "clrig", "--param", "latency_s=-1"), **run)
    assert bad.returncode == 2 and "latency_s and jitter_s must be >= 0" in bad.stderr, bad.stderr
    # a bad command that arrives anyway (another tool): counted by the emulator, not applied
    bad_cmd = FaultCommand(
        seq=1, stamp_ns=0, kind="can_latency", target="", params=fault_params({"latency_s": 20.0})
    )
    rig.hub.put("hil/clrig/control/fault", encode(bad_cmd))
    sent = subprocess.run(
        hil_cmd(
            "fault",
            "can_latency",
            "--rig",
            "clrig",
            "--param",
            "latency_s=0.03",
            "--duration",
            "1",
            "--wait",
            "3",  # to find the rig's subscribers on a loaded machine before the one put
        ),
        **run,
    )
    assert sent.returncode == 0, sent.stderr
    rc, stdout, stderr = rig.stop_at(max(8.0, rig.rig_time_s() + 2.0))  # the 1 s command ended
    assert rc == 0, stdout[-2000:] + stderr[-2000:]

    s = read_session(out)
    edges = [
        (e.kind, json.loads(e.detail))
        for e in (decode(Event, r.payload) for r in s.by_topic("hil/clrig/event/imu_emulator"))
    ]
    timed = [(k, d["t_start_s"], d["t_end_s"]) for k, d in edges if d["origin"] == "scenario"]
    assert timed == [("fault_start", 2.0, 3.0), ("fault_end", 2.0, 3.0)]
    cmd = [(k, d) for k, d in edges if d["origin"] == "command"]
    assert [k for k, _d in cmd] == ["fault_start", "fault_end"] and cmd[0][1]["params"] == {"latency_s": 0.03}
    t0, t1 = cmd[0][1]["t_start_s"], cmd[0][1]["t_end_s"]
    assert abs(t1 - t0 - 1.0) < 1e-6
    # timed window: every sample captured in it arrives at least 50 ms late; before it, not
    assert _late_ms(s, "clrig", 2.0, 3.0).min() >= 50.0
    # outside both windows (the commanded one lands wherever the rig was when it arrived, and
    # samples held across a window's end come out late too): not late
    quiet = [(0.5, 1.9), (3.3, 7.5)]
    lo, hi = t0 - 0.05, t1 + 0.2
    outside = np.concatenate(
        [
            _late_ms(s, "clrig", a, b)
            for qa, qb in quiet
            for a, b in ((qa, min(qb, lo)), (max(qa, hi), qb))
            if b > a
        ]
    )
    # (a live path on a shared machine: its own delay grows with the load, measured here; at
    # load 35 on 2 cores the quiet median was 131 ms, up to 990 ms)
    quiet_ms = 20.0 * slowdown()
    assert len(outside) > 400 and np.median(outside) < quiet_ms, (np.median(outside), quiet_ms)
    # commanded window: at least 30 ms late (the whole window's samples, wherever it fell)
    assert _late_ms(s, "clrig", t0, t1).min() >= 30.0
    # nothing lost, nothing reordered: the held frames came out whole and in order
    raw = sorted(_by_capture(s, "clrig", "sensor/imu").values())
    assert len(raw) == len(s.by_topic("hil/clrig/capture/imu"))
    rx = [m.rx_stamp_ns for _t, m in raw]
    assert all(a <= b for a, b in itertools.pairwise(rx))
    st = decode(ServiceStatus, s.by_topic("hil/clrig/status/imu_emulator")[-1].payload)
    assert st.counter_map().get("rejected.control.fault", 0) == 1, st.counter_map()
    # the timed window's 400 samples at least (the 1 Hz status may predate the commanded one's end)
    assert st.counter_map()["fault.can_latency.delayed_samples"] >= 400
    for log in (tmp_path / "cl.logs").glob("*.log"):
        assert "Traceback" not in log.read_text(errors="replace"), log

"""Fault injection on the live rig: timed faults from the scenario and commanded ones (`hil fault`)
are applied by the service that owns them and recorded as `fault_start`/`fault_end` events; their
effects are visible in the recording (seq gaps, CRC rejects, saturation flags, missing fixes)."""

from __future__ import annotations

import itertools
import json
import os
import subprocess
from pathlib import Path

import pytest

from hil.messages import Event, FaultCommand, GnssFix, ImuSample, ServiceStatus, decode
from hil.nav.scenario import load_scenario
from hil.record.mcapio import read_session
from tests.conftest import REPO, hil_cmd
from tests.integration.test_supervision import Rig

pytestmark = pytest.mark.slow

TIMED = """
[[event]]
kind = "imu_frame_loss"
t_start_s = 3.0
t_end_s = 4.0
percent = 25.0

[[event]]
kind = "can_burst_error"
t_start_s = 4.5
frames = 8

[[event]]
kind = "imu_saturated"
t_start_s = 5.0
t_end_s = 5.2
"""


def test_timed_and_commanded_faults_are_applied_and_recorded(tmp_path: Path) -> None:
    scen = tmp_path / "faulty.toml"
    scen.write_text(load_scenario("straight_level").source_text + TIMED)
    out = tmp_path / "f.mcap"
    rig = Rig("faultrig", out, "--duration", "600", "--scenario", str(scen))  # stopped at 11 s or later
    rig.running_pid("gnss_emulator")
    rig.reach(1.0)  # the commanded fault lands inside the run, with fixes/samples before it
    env = dict(os.environ, HIL_ZENOH_MODE="client", HIL_ZENOH_LISTEN="")
    env["HIL_ZENOH_CONNECT"] = rig.endpoint
    sent = subprocess.run(
        hil_cmd("fault", "gnss_outage", "--rig", "faultrig", "--duration", "2", "--wait", "1.5"),
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert sent.returncode == 0, sent.stderr
    bad = subprocess.run(
        hil_cmd("fault", "imu_frame_loss", "--rig", "faultrig", "--param", "percent=140"),
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert bad.returncode == 2 and "percent must be in [0, 100]" in bad.stderr
    rc, stdout, stderr = rig.stop_at(max(11.0, rig.rig_time_s() + 3.0))  # the 2 s outage ended
    assert rc == 0, stdout[-2000:] + stderr[-2000:]

    s = read_session(out)
    events = [decode(Event, r.payload) for r in s.records if r.schema == "hil.Event"]
    started = {
        (e.source, json.loads(e.detail)["kind"], json.loads(e.detail)["origin"])
        for e in events
        if e.kind == "fault_start"
    }
    assert {
        ("imu_emulator", "imu_frame_loss", "scenario"),
        ("imu_emulator", "can_burst_error", "scenario"),
        ("imu_emulator", "imu_saturated", "scenario"),
        ("gnss_emulator", "gnss_outage", "command"),
    } <= started, started
    assert any(e.kind == "fault_end" and "gnss_outage" in e.detail for e in events)
    cmds = s.by_topic("hil/faultrig/control/fault")
    assert [decode(FaultCommand, r.payload).kind for r in cmds] == ["gnss_outage"]

    # frame loss: ~25 % of the samples of [3, 4) s are a seq gap, none outside the fault windows
    cap = {r.sequence: decode(ImuSample, r.payload) for r in s.by_topic("hil/faultrig/sensor/imu")}
    lost_in = [k for k in range(1200, 1600) if k not in cap]
    assert 0.15 * 400 < len(lost_in) < 0.35 * 400, len(lost_in)
    # saturation: the samples of [5, 5.2) s carry GYRO/ACCEL_SATURATED
    sat = [m for k, m in cap.items() if 1999 <= k < 2079]  # sample k ends at (k + 1) / 400 s
    assert sat and all(m.status & 0b1100 == 0b1100 for m in sat)
    assert all(m.status & 0b1100 == 0 for k, m in cap.items() if k < 1900)
    # burst error: the bridge rejected corrupted frames on CRC, counted in its status
    bridge = [decode(ServiceStatus, r.payload) for r in s.by_topic("hil/faultrig/status/can_bridge")]
    assert bridge[-1].counter_map().get("rejected.can.bad_crc", 0) == 8, bridge[-1].counter_map()
    # commanded outage: a 2 s hole in the fixes' times of validity
    t_out = next(e.stamp_ns for e in events if e.kind == "fault_start" and "gnss_outage" in e.detail)
    valid = sorted(decode(GnssFix, r.payload).stamp_ns for r in s.by_topic("hil/faultrig/synced/gnss"))
    assert not [t for t in valid if t_out + 0.2e9 < t < t_out + 1.8e9]
    assert max(b - a for a, b in itertools.pairwise(valid)) > 1.8e9
    for log in (tmp_path / "f.logs").glob("*.log"):
        assert "Traceback" not in log.read_text(errors="replace"), log


def test_a_fault_that_nothing_receives_fails_and_says_so(zenoh_hub: str) -> None:
    """A typo in --rig, or a rig that is not running: the command went nowhere, and ``hil fault``
    said "sent" with exit 0 (a hub with no rig behind it; the live test above is the other case)."""
    proc = subprocess.run(
        hil_cmd("fault", "gnss_outage", "--rig", "nosuchrig", "--duration", "1", "--wait", "1.0"),
        cwd=REPO,
        env=dict(os.environ),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert proc.returncode == 1, proc.stdout + proc.stderr
    assert "went nowhere: nothing subscribes to hil/nosuchrig/control/fault" in proc.stderr, proc.stderr
    assert "sent" not in proc.stdout and "Traceback" not in proc.stderr

"""A device clock step during time sync's start-up hold (QA): the IMU's samples are held until the
tag filter locks, and a step in that time stamped the samples taken before it with the new
clock's mapping (100 s into the future for a -100 s step). The fusion, paced by them, then
refused every correctly stamped input: navigation stopped after ~3 s and ``hil sim`` exited 0.
Here a real ``hil sim`` of such a scenario: navigation goes on to the end, every re-stamp is
within a millisecond of the capture, and both cores rerun bit for bit."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from hil.bench.capture import restamp_errors
from hil.record.mcapio import read_session
from tests.conftest import run_hil

pytestmark = pytest.mark.slow

SCENARIO = """
name = "startup_step"
seed = 3
duration_s = {duration}

[origin]
lat_deg = 50.0
lon_deg = 30.0
alt_m = 100.0

[initial]
attitude_deg = [0.0, 0.0, 0.0]
speed_mps = 20.0

[imu]
preset = "tactical"
rate_hz = {rate}

[gnss]
rate_hz = 5.0

[[segment]]
kind = "hold"
duration_s = {duration}

[[event]]
kind = "clock_step"
t_start_s = {t_step}
sensor = "imu"
step_s = -100.0
"""


# QA's case (100 Hz, 3 s in: one tag a second, before the third), 400 Hz 1.5 s in (after the
# first tag, before the lock at 3 s), and 400 Hz 0.5 s in (before the first tag: the CAN
# decoder unwrapped samples and sync frames apart, a whole 2^48 ns wrap between them)
@pytest.mark.parametrize(("rate", "t_step"), [(100, 3.0), (400, 1.5), (400, 0.5)])
def test_navigation_goes_on_after_a_clock_step_during_the_start_up_hold(
    tmp_path: Path, rate: int, t_step: float
) -> None:
    duration = 8.0
    scen = tmp_path / "step.toml"
    scen.write_text(SCENARIO.format(duration=duration, rate=rate, t_step=t_step))
    rec = tmp_path / "step.mcap"
    proc = run_hil("sim", "--quiet", "--scenario", str(scen), "--record", str(rec), "--estimators", "ekf15")
    assert proc.returncode == 0, proc.stdout + proc.stderr
    s = read_session(rec)
    t, e = restamp_errors(s, "imu")
    assert len(e) == rate * duration
    off = np.abs(e) >= 1e6  # stamped on the other clock's mapping
    assert not off.any(), (int(off.sum()), t[off][:5])
    nav = [r.decode() for r in s.by_topic("hil/bench/nav/ekf15")]
    expected = rate * duration / 8  # one output per 8 IMU samples
    assert len(nav) >= 0.9 * expected, len(nav)
    assert nav[-1].stamp_ns >= (duration - 0.5) * 1e9  # still navigating at the end
    for core in ("timesync", "fusion"):
        proc = run_hil("rerun", str(rec), "--core", core, "--verify", timeout=120)
        assert proc.returncode == 0 and "VERIFY OK" in proc.stdout, proc.stdout + proc.stderr

"""The GNSS receiver's faults with no wire (no --gnss-protocol): the receiver's own (frozen, time
jump) are applied to its fixes; the line's cannot be and are said so (fault_ignored, a warning),
where they were once announced fault_start/fault_end as though applied."""

from __future__ import annotations

import json
from pathlib import Path
from typing import Any

from hil.faults import unwired_line_fault_warnings
from hil.nav.scenario import load_scenario
from hil.nodes.gnss_emulator import GnssEmulatorNode
from hil.runners.sim import SimOptions, sim_run_info

SCENARIO = """
name = "ev"
seed = 3
duration_s = 10.0
[initial]
speed_mps = 20.0
[gnss]
rate_hz = 5.0
[[segment]]
kind = "hold"
duration_s = 10.0
[[event]]
kind = "gnss_frozen"
t_start_s = 3.0
t_end_s = 5.0
[[event]]
kind = "gnss_line_garble"
t_start_s = 6.0
t_end_s = 7.0
[[event]]
kind = "gnss_time_jump"
t_start_s = 8.0
t_end_s = 9.0
step_s = 1.0
"""


def _run(tmp_path: Path) -> list[tuple[str, Any]]:
    path = tmp_path / "ev.toml"
    path.write_text(SCENARIO)
    node = GnssEmulatorNode(sim_run_info(SimOptions(scenario=str(path), duration_s=10.0)))
    outs: list[tuple[str, Any]] = list(node.start(0))
    while (t := node.next_tick_ns()) is not None:
        outs += node.tick(t)
    return outs


def test_frozen_and_time_jump_apply_line_faults_are_ignored_and_said(tmp_path: Path) -> None:
    outs = _run(tmp_path)
    fixes = {m.stamp_ns: m for k, m in outs if k == "sensor/gnss"}
    frozen = [m for t, m in fixes.items() if 3.2e9 <= t < 5.0e9]
    assert frozen and all(
        m.lat_deg == frozen[0].lat_deg and m.vel_ned_mps == frozen[0].vel_ned_mps for m in frozen
    )
    moving = [m.lat_deg for t, m in sorted(fixes.items()) if 5.2e9 <= t < 6.0e9]
    assert len(set(moving)) == len(moving) > 1 and frozen[0].lat_deg not in moving
    # the jump: the device stamp a second ahead of the true validity inside the window, not outside
    offset = {t: m.device_stamp_ns - t for t, m in fixes.items()}
    assert all(0.9e9 < d < 1.1e9 for t, d in offset.items() if 8.0e9 <= t < 9.0e9)
    assert all(abs(d) < 0.1e9 for t, d in offset.items() if t < 8.0e9 or t >= 9.2e9)
    events = [(m.kind, json.loads(m.detail)["kind"]) for k, m in outs if k.startswith("event/")]
    assert ("fault_ignored", "gnss_line_garble") in events
    assert ("fault_start", "gnss_line_garble") not in events and (
        "fault_end",
        "gnss_line_garble",
    ) not in events
    assert ("fault_start", "gnss_frozen") in events and ("fault_start", "gnss_time_jump") in events


def test_the_warning_names_the_line_fault_and_the_option(tmp_path: Path) -> None:
    path = tmp_path / "ev.toml"
    path.write_text(SCENARIO)
    lines = unwired_line_fault_warnings(load_scenario(str(path)).events, 10.0, "hil sim")
    assert len(lines) == 1 and lines[0].startswith("gnss_line_garble at t=6 s is not applied"), lines
    assert "--gnss-protocol" in lines[0]

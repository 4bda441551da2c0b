"""Shared fixtures: real Zenoh sessions on loopback, leak checks for child processes."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from collections.abc import Iterator
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]


def free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture
def zenoh_hub(monkeypatch: pytest.MonkeyPatch) -> Iterator[str]:
    """A real Zenoh peer listening on a free loopback port; children connect to it via env."""
    from hil.bus.session import BusConfig, open_session

    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    hub = open_session(BusConfig(mode="peer", listen=(endpoint,), connect=()))
    monkeypatch.setenv("HIL_ZENOH_MODE", "peer")
    monkeypatch.setenv("HIL_ZENOH_CONNECT", endpoint)
    monkeypatch.setenv("HIL_ZENOH_LISTEN", "tcp/127.0.0.1:0")
    try:
        yield endpoint
    finally:
        hub.close()


def hil_cmd(*args: str) -> list[str]:
    return [sys.executable, "-m", "hil.cli", *args]


def run_hil(
    *args: str, timeout: float = 300, cwd: Path | None = None, env: dict[str, str] | None = None
) -> subprocess.CompletedProcess[str]:
    e = dict(os.environ)
    e.update(env or {})
    return subprocess.run(
        hil_cmd(*args), capture_output=True, text=True, timeout=timeout, cwd=cwd or REPO, env=e
    )


SIM_RECORDING_SCENARIO = """
name = "simrec"
seed = 11
duration_s = 3.0

[origin]
lat_deg = 50.45
lon_deg = 30.52
alt_m = 300.0

[initial]
speed_mps = 20.0

[[segment]]
kind = "turn"
duration_s = 3.0
yaw_rate_dps = 10.0

[[event]]
kind = "imu_frame_loss"
t_start_s = 1.0
t_end_s = 1.5
percent = 50.0
"""


@pytest.fixture(scope="session")
def sim_recording(tmp_path_factory: pytest.TempPathFactory) -> Path:
    """A fresh 3 s ``hil sim`` recording of a turn with a timed fault (every topic of the rig,
    events and counters), made once per test session."""
    from hil.runners.sim import SimOptions, run_sim

    root = tmp_path_factory.mktemp("sim")
    scenario = root / "simrec.toml"
    scenario.write_text(SIM_RECORDING_SCENARIO)
    path = root / "sim.mcap"
    run_sim(SimOptions(scenario=str(scenario), duration_s=3.0, record=path, rig="simrec", on_warning=print))
    return path

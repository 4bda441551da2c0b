"""Recorded CAN frames leave a recording onto a real CAN transport, with their recorded spacing:
through python-can's own player (our ``.mcap`` reader plugin) and through ``hil replay --can``."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from hil.can.zenoh_bus import ZenohCanBus
from hil.messages import CanFrame, decode
from hil.record.mcapio import read_session
from tests.load import slowdown
from tests.replay.helpers import GOLDEN, LEGACY_GOLDEN, Hub

pytestmark = pytest.mark.slow


@pytest.fixture
def hub() -> Iterator[Hub]:
    h = Hub()
    try:
        yield h
    finally:
        h.close()


def recorded_frames(path: Path = GOLDEN) -> list[CanFrame]:
    return [decode(CanFrame, r.payload) for r in read_session(path).records if r.schema == "hil.CanFrame"]


@pytest.mark.parametrize("path", [GOLDEN, LEGACY_GOLDEN], ids=["current", "legacy"])
def test_python_can_logreader_reads_every_recorded_frame_on_the_wall_clock(path: Path) -> None:
    frames = recorded_frames(path)
    start = int(read_session(path).meta("hil", "start_epoch_ns"))
    if path == GOLDEN:  # (the legacy one predates start_utc: its run started at epoch 0)
        assert start >= 1_767_225_600 * 10**9  # the scenario's start_utc: 2026-01-01T00:00:00Z
    with can.LogReader(str(path)) as reader:  # resolved through the can.io.message_reader entry point
        msgs = list(reader)
    assert len(msgs) == len(frames) > 1000
    for m, f in zip(msgs, frames, strict=True):
        assert (m.arbitration_id, bytes(m.data).hex(), m.channel) == (f.arbitration_id, f.data_hex, f.channel)
        assert m.timestamp == (start + f.stamp_ns) * 1e-9  # the epoch, not seconds since the run's start


def test_an_asc_export_by_python_can_carries_the_run_s_date(tmp_path: Path) -> None:
    # WHEN python-can's own converter turns the recording into a Vector ASC log
    out = tmp_path / "frames.asc"
    proc = subprocess.run(
        [sys.executable, "-m", "can.logconvert", str(GOLDEN), str(out)],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    # THEN python-can's ASC reader gives each frame back at its time on the wall clock: the
    # export lines up with any other log of that bench and day. (python-can writes the header's
    # milliseconds unpadded -- "00:00:00.2" for 2 ms -- and reads them back as 200 ms: the
    # absolute time is good to a second there, the spacing to the microsecond.)
    start = int(read_session(GOLDEN).meta("hil", "start_epoch_ns"))
    frames = recorded_frames(GOLDEN)
    with can.ASCReader(str(out), relative_timestamp=False) as reader:
        back = list(reader)
    assert len(back) == len(frames)
    t0 = (start + frames[0].stamp_ns) * 1e-9
    assert abs(back[0].timestamp - t0) < 1.0
    for m, f in list(zip(back, frames, strict=True))[:: len(frames) // 20]:
        rel = (f.stamp_ns - frames[0].stamp_ns) * 1e-9
        assert abs((m.timestamp - back[0].timestamp) - rel) < 2e-6


def collect(bus: can.BusABC, n: int, timeout: float) -> tuple[list[can.Message], list[float]]:
    got: list[can.Message] = []
    at: list[float] = []
    deadline = time.monotonic() + timeout
    while len(got) < n and time.monotonic() < deadline:
        m = bus.recv(0.2)
        if m is not None:
            got.append(m)
            at.append(time.monotonic())
    return got, at


@pytest.mark.parametrize("player", ["python-can", "hil-replay"])
def test_recorded_frames_are_played_onto_a_bus_with_their_spacing(hub: Hub, player: str) -> None:
    # GIVEN a receiver on CAN channel vcan0 of rig "canplay" (the rig's Zenoh CAN transport)
    frames = recorded_frames()
    span_s = (frames[-1].stamp_ns - frames[0].stamp_ns) * 1e-9
    bus = ZenohCanBus("vcan0", rig="canplay", session=hub.session)
    env = hub.env()
    env["HIL_RIG"] = "canplay"
    load_before = slowdown()
    try:
        time.sleep(0.3)
        # WHEN the recording's frames are played onto that bus
        if player == "python-can":
            cmd = [sys.executable, "-m", "can.player", "-i", "hilzenoh", "-c", "vcan0", str(GOLDEN)]
        else:
            cmd = [sys.executable, "-m", "hil.cli", "replay", str(GOLDEN), "--can", "vcan0",
                   "--can-interface", "hilzenoh", "--rig", "canplay", "--topics", "/can/"]  # fmt: skip
        proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
        got, at = collect(bus, len(frames), timeout=span_s + 30)
        out, _ = proc.communicate(timeout=30)
    finally:
        bus.shutdown()
    assert proc.returncode == 0, out[-2000:]
    # THEN every frame arrives, in order, and the whole takes the recorded time (not faster)
    assert [(m.arbitration_id, bytes(m.data).hex()) for m in got] == [
        (f.arbitration_id, f.data_hex) for f in frames
    ]
    took = at[-1] - at[0]
    # slower only by what the machine's load explains (tests/load.py)
    late = (span_s * 1.5 + 0.5) * max(load_before, slowdown())
    assert took < late, (took, span_s, late)
    # not faster than recorded: each frame's arrival less its recorded offset is the player's start
    # plus a delivery delay (>= 0; a loaded machine delays the first frames as much as any), so the
    # last frame is no earlier than the earliest of the first quarter; a player 3 % fast fails this
    lag = [t - (f.stamp_ns - frames[0].stamp_ns) * 1e-9 for t, f in zip(at, frames, strict=True)]
    assert lag[-1] > min(lag[: len(lag) // 4]) - 0.015 * span_s, (took, span_s)

"""Recorded CAN frames leave a recording onto a real CAN transport, with their recorded spacing:
through python-can's own player (our ``.mcap`` reader plugin) and through ``hil replay --can``."""

from __future__ import annotations

import subprocess
import sys
import time
from collections.abc import Iterator

import can
import pytest

from hil.can.zenoh_bus import ZenohCanBus
from hil.messages import CanFrame, decode
from hil.record.mcapio import read_session
from tests.load import slowdown
from tests.replay.helpers import GOLDEN, Hub

pytestmark = pytest.mark.slow


@pytest.fixture
def hub() -> Iterator[Hub]:
    h = Hub()
    try:
        yield h
    finally:
        h.close()


def recorded_frames() -> list[CanFrame]:
    return [decode(CanFrame, r.payload) for r in read_session(GOLDEN).records if r.schema == "hil.CanFrame"]


def test_python_can_logreader_reads_every_recorded_frame() -> None:
    frames = recorded_frames()
    with can.LogReader(str(GOLDEN)) as reader:  # resolved through the can.io.message_reader entry point
        msgs = list(reader)
    assert len(msgs) == len(frames) > 1000
    for m, f in zip(msgs, frames, strict=True):
        assert (m.arbitration_id, bytes(m.data).hex(), m.channel) == (f.arbitration_id, f.data_hex, f.channel)
        assert m.timestamp == f.stamp_ns * 1e-9


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
    # not faster than recorded; slower only by what the machine's load explains (tests/load.py)
    late = (span_s * 1.5 + 0.5) * max(load_before, slowdown())
    assert span_s * 0.97 < took < late, (took, span_s, late)

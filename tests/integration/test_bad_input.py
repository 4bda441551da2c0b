"""Random bytes published to every key a service subscribes: counted in its status, and the rig
keeps running to a clean, complete recording."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from hil.bus.keys import Keys
from hil.bus.session import BusConfig, open_session
from hil.messages import ServiceStatus, decode
from hil.record.mcapio import read_session
from tests.conftest import REPO, free_port, hil_cmd

pytestmark = pytest.mark.slow

RIG = "fuzzrig"


def test_garbage_on_every_subscribed_key_is_counted_and_survived(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    hub = open_session(BusConfig(mode="peer", listen=(endpoint,), connect=()))
    statuses: dict[str, ServiceStatus] = {}
    hub.declare_subscriber(
        f"hil/{RIG}/status/*",
        lambda s: statuses.__setitem__(
            str(s.key_expr).rsplit("/", 1)[1], decode(ServiceStatus, s.payload.to_bytes())
        ),
    )
    env = dict(
        os.environ, HIL_ZENOH_MODE="peer", HIL_ZENOH_CONNECT=endpoint, HIL_ZENOH_LISTEN="tcp/127.0.0.1:0"
    )
    out = tmp_path / "fuzz.mcap"
    proc = subprocess.Popen(
        hil_cmd("up", "--duration", "12", "--record", str(out), "--quiet", "--rig", RIG),
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    try:
        deadline = time.monotonic() + 90
        while (time.monotonic() < deadline and statuses.get("imu_emulator") is None) or (
            statuses.get("imu_emulator") and statuses["imu_emulator"].state != "running"
        ):
            time.sleep(0.2)
            if time.monotonic() > deadline:
                break
        assert statuses.get("imu_emulator") and statuses["imu_emulator"].state == "running", statuses.keys()
        time.sleep(1.0)
        k = Keys(RIG)
        rng = np.random.default_rng(7)
        targets = [
            k.sensor("imu"),
            k.sensor("gnss"),
            k.synced("imu"),
            k.synced("gnss"),
            k.timetag("imu"),
            k.timetag("gnss"),
            k.run(),
            k.canbus("vcan0"),
        ]
        for key in targets:
            pub = hub.declare_publisher(key)
            for n in (0, 1, 7, 64, 300, 70_000):
                pub.put(rng.bytes(n))
            pub.put(b'{"seq": 1, "stamp_ns": "x"}')
            pub.put(b"\xff" * 16)
        time.sleep(3.0)
        rejected = {
            name: sum(v for c, v in st.counters.items() if c.startswith("rejected"))
            for name, st in statuses.items()
        }
        for svc in ("timesync", "fusion", "recorder", "can_bridge"):
            assert rejected.get(svc, 0) > 0, (svc, statuses.get(svc))
        assert all(st.state in ("running", "waiting_run") for st in statuses.values()), statuses
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
        hub.close()
    assert proc.returncode == 0, output[-4000:]
    s = read_session(out)
    assert not s.truncated
    imu = s.by_topic(f"hil/{RIG}/sensor/imu")
    seqs = [r.sequence for r in imu]
    assert len(imu) >= 0.99 * 400 * 12 and seqs == sorted(set(seqs))

"""Random bytes published to every key a service subscribes, then well-formed but bad messages
(wrong schema, NaN, huge values, duplicated and out-of-order seq, stamps far in the future or
past, oversized payloads): each is rejected with a reason counted in status, no service log holds
a traceback, no published solution is non-finite, and the rig runs to a clean, complete recording."""

from __future__ import annotations

import os
import subprocess
import time
from pathlib import Path

import msgspec
import numpy as np
import pytest
import zenoh

from hil.bus.identity import new_rig_key, rig_zid
from hil.bus.keys import Keys
from hil.bus.session import BusConfig, open_session
from hil.messages import ImuSample, NavSolution, ServiceStatus, decode, encode
from hil.record.mcapio import read_session
from tests.conftest import REPO, free_port, hil_cmd

pytestmark = pytest.mark.slow

RIG = "fuzzrig"


_SN = iter(range(1, 1 << 30))


def _publisher(hub: zenoh.Session, key: str) -> zenoh.Publisher:
    """Reliable and blocking: every bad message must reach the services to be counted. Zenoh's
    default for a put drops it when the hub's queue to a client is full -- the likely way one
    suite run on a loaded machine lost them: its fusion had counted 5 invalid inputs, had an
    empty inbox, and had no count at all for the well-formed bad ones sent after the garbage."""
    return hub.declare_publisher(
        key, reliability=zenoh.Reliability.RELIABLE, congestion_control=zenoh.CongestionControl.BLOCK
    )


def _put(pub: zenoh.Publisher, data: bytes) -> None:
    """As the rig's publishers put (hil.bus.pubsub): naming the publisher in the source info,
    which is how the rig tells its own samples from a stranger's."""
    pub.put(data, source_info=zenoh.SourceInfo(pub.id, next(_SN)))


def test_garbage_on_every_subscribed_key_is_counted_and_survived(tmp_path: Path) -> None:
    port = free_port()
    endpoint = f"tcp/127.0.0.1:{port}"
    # the garbage must come from the rig (a stranger's is refused before it is even decoded,
    # issue 18.4): the hub's session carries an id of the rig, from the key hil up is given
    key = new_rig_key()
    hub = open_session(BusConfig(mode="router", listen=(endpoint,), connect=(), extra={"id": rig_zid(key)}))
    statuses: dict[str, ServiceStatus] = {}
    hub.declare_subscriber(
        f"hil/{RIG}/status/*",
        lambda s: statuses.__setitem__(
            str(s.key_expr).rsplit("/", 1)[1], decode(ServiceStatus, s.payload.to_bytes())
        ),
    )
    env = dict(
        os.environ,
        HIL_ZENOH_MODE="client",
        HIL_ZENOH_CONNECT=endpoint,
        HIL_ZENOH_LISTEN="",
        HIL_RIG_KEY=key,
    )
    out = tmp_path / "fuzz.mcap"
    proc = subprocess.Popen(
        hil_cmd("up", "--duration", "20", "--record", str(out), "--quiet", "--rig", RIG),
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
            pub = _publisher(hub, key)
            for n in (0, 1, 7, 64, 300, 70_000):
                _put(pub, rng.bytes(n))
            _put(pub, b'{"seq": 1, "stamp_ns": "x"}')
            _put(pub, b"\xff" * 16)
        # well-formed JSON, bad content, into the fusion's inputs (and the raw sensor key)
        imu = ImuSample(
            seq=3,
            stamp_ns=10**9,
            device_stamp_ns=10**9,
            rx_stamp_ns=10**9,
            dt_ns=2_500_000,
            dtheta_b_rad=[0.0, 0.0, 0.0],
            dvel_b_mps=[0.0, 0.0, 0.0],
        )
        sync_imu = _publisher(hub, k.synced("imu"))
        bad = {
            "wrong_schema": b'{"seq": 1, "stamp_ns": 5, "kind": "x", "source": "y"}',
            "nan": encode(imu).replace(b"[0.0,0.0,0.0]", b"[NaN,0.0,0.0]", 1),
            "huge": encode(msgspec.structs.replace(imu, dtheta_b_rad=[1e300, 0.0, 0.0])),
            "duplicate_past": encode(imu),  # seq 3 at t = 1 s, long consumed
            "far_future": encode(msgspec.structs.replace(imu, seq=10**12, stamp_ns=10**18)),
            "far_past": encode(msgspec.structs.replace(imu, seq=10**12 + 1, stamp_ns=-(10**15))),
        }
        for payload in bad.values():
            _put(sync_imu, payload)
            _put(_publisher(hub, k.sensor("imu")), payload)
        reasons = (
            "rejected.synced.imu.invalid",
            "rejected.implausible.imu.dtheta",
            "rejected.future_stamp",
        )
        deadline = time.monotonic() + 30  # the fusion consumes its inbox in order: may lag on a busy host
        while time.monotonic() < deadline:
            fusion = statuses["fusion"].counter_map()
            if all(fusion.get(r, 0) >= 1 for r in reasons):
                break
            time.sleep(0.5)
        for reason in reasons:
            assert fusion.get(reason, 0) >= 1, (reason, [c for c in fusion if "drop" in c or "rej" in c])

        def rejected_by_service() -> dict[str, int]:
            return {
                name: sum(v for c, v in st.counter_map().items() if c.startswith("rejected"))
                for name, st in list(statuses.items())
            }

        deadline = time.monotonic() + 20  # statuses come at 1 Hz; a busy host delays them
        while time.monotonic() < deadline:
            rejected = rejected_by_service()
            if all(rejected.get(s, 0) > 0 for s in ("timesync", "fusion", "recorder", "can_bridge")):
                break
            time.sleep(0.5)
        for svc in ("timesync", "fusion", "recorder", "can_bridge"):
            assert rejected.get(svc, 0) > 0, (svc, statuses.get(svc))
        assert all(st.state in ("running", "waiting_run") for st in statuses.values()), statuses
        output, _ = proc.communicate(timeout=120)
    finally:
        if proc.poll() is None:
            proc.kill()
        hub.close()
    assert proc.returncode == 0, output[-4000:]
    for log in (tmp_path / "fuzz.logs").glob("*.log"):
        assert "Traceback" not in log.read_text(errors="replace"), log
    s = read_session(out)
    assert not s.truncated
    for r in s.by_topic_prefix(f"hil/{RIG}/nav/"):
        sol = decode(NavSolution, r.payload)
        assert np.isfinite([*sol.pos_ned_m, *sol.vel_ned_mps, *sol.q_nb]).all()
    imu = s.by_topic(f"hil/{RIG}/sensor/imu")
    seqs = [r.sequence for r in imu]
    real = sorted({q for q in seqs if q < 10**9})  # the injected bad samples carry seq 3 and >= 1e12
    assert len(imu) >= 0.99 * 400 * 12 and real == list(range(real[0], real[-1] + 1))

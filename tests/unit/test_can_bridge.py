"""can_bridge end to end in one process: real Zenoh sessions, the hilzenoh transport, the node."""

from __future__ import annotations

import threading
import time

import can
import pytest

from hil.bus.keys import Keys
from hil.bus.pubsub import Publisher, Stats, Subscriber
from hil.bus.session import BusConfig, open_session
from hil.can.bus import open_can_bus
from hil.can.codec import ImuCanCodec
from hil.can.node import ImuCanNode
from hil.messages import CanFrame, ImuSample, RunInfo, ServiceStatus, TimeTag
from hil.runtime.service import ServiceContext
from services.can_bridge import SERVICE, CanBridge, epoch_s_to_rig_ns


def test_rig_time_mapping_keeps_the_stamps_precision() -> None:
    start = 1_795_000_000_123_456_789
    ts = 1_795_000_001.5
    assert epoch_s_to_rig_ns(ts, start, 1.0) == 1_376_543_211
    assert epoch_s_to_rig_ns(ts, start, 2.0) == 2 * 1_376_543_211
    assert SERVICE is CanBridge and CanBridge.name == "can_bridge"


@pytest.mark.parametrize("fd", [False, True], ids=["classic", "fd"])
def test_bridge_decodes_counts_and_publishes(zenoh_hub: str, fd: bool) -> None:
    rig = f"t-bridge-{int(fd)}"
    keys = Keys(rig)
    svc_session = open_session(BusConfig.from_env())
    ctx = ServiceContext(
        name="can_bridge",
        rig=rig,
        session=svc_session,
        options={"channel": "vcan0", "interface": "hilzenoh", "fd": fd, "rate_hz": 400},
    )
    bridge = CanBridge(ctx)
    thread = threading.Thread(target=bridge.start, daemon=True)
    thread.start()

    test_session = open_session(BusConfig.from_env())
    stats = Stats()
    got: dict[str, list] = {"imu": [], "tag": [], "can": [], "status": []}
    subs = [
        Subscriber(test_session, keys.sensor("imu"), ImuSample, lambda m, _k: got["imu"].append(m), stats),
        Subscriber(test_session, keys.timetag("imu"), TimeTag, lambda m, _k: got["tag"].append(m), stats),
        Subscriber(test_session, keys.can("vcan0"), CanFrame, lambda m, _k: got["can"].append(m), stats),
        Subscriber(
            test_session,
            keys.status("can_bridge"),
            ServiceStatus,
            lambda m, _k: got["status"].append(m),
            stats,
        ),
    ]
    start_ns = time.time_ns()
    run_pub = Publisher(test_session, keys.run(), RunInfo)
    bus, desc = open_can_bus("vcan0", "hilzenoh", fd=fd, rig=rig)
    assert "hilzenoh" in desc
    try:
        deadline = time.time() + 10
        while bridge.state != "running" and time.time() < deadline:
            run_pub.put(
                RunInfo(
                    seq=run_pub.next_seq(),
                    stamp_ns=0,
                    rig=rig,
                    start_epoch_ns=start_ns,
                    speed=1.0,
                    scenario="unit",
                    scenario_sha256="0" * 64,
                    seed=1,
                    duration_s=1.0,
                    origin_lat_deg=0.0,
                    origin_lon_deg=0.0,
                    origin_alt_m=0.0,
                )
            )
            time.sleep(0.05)
        assert bridge.state == "running"
        time.sleep(0.3)  # let the bridge's CAN subscription match ours
        node = ImuCanNode(bus, ImuCanCodec.from_dbc(fd=fd), Stats())
        n = 200
        for i in range(n):
            dev = 5_000_000_000 + i * 2_500_000
            if i % 100 == 0:
                assert node.send_sync(dev)
            assert node.send_sample(dev, [1e-6 * i, 0.0, -1e-6], [0.0, 0.0, -0.0245], status=0)
        # bad frames: unknown ID, bad CRC, wrong length
        bus.send(can.Message(arbitration_id=0x7AB, is_extended_id=False, data=bytes(8)))
        bus.send(can.Message(arbitration_id=0x080, is_extended_id=False, data=bytes(8)))
        bus.send(can.Message(arbitration_id=0x103, is_extended_id=False, data=bytes(3)))
        after = 5_000_000_000 + n * 2_500_000
        assert node.send_sample(after, [0.0] * 3, [0.0] * 3)
        deadline = time.time() + 10
        while len(got["imu"]) < n + 1 and time.time() < deadline:
            time.sleep(0.05)
        time.sleep(1.2)  # one more status period
    finally:
        ctx.stop.set()
        thread.join(timeout=5)
        bus.shutdown()
        for s in subs:
            s.undeclare()
        test_session.close()
        svc_session.close()
    imu = got["imu"]
    assert len(imu) == n + 1, stats.counters
    assert [m.device_stamp_ns for m in imu] == [5_000_000_000 + i * 2_500_000 for i in range(n + 1)]
    assert [m.seq for m in imu] == list(range(n + 1))
    assert all(m.dt_ns == 2_500_000 for m in imu)
    assert imu[150].dtheta_b_rad == pytest.approx([1.5e-4, 0.0, -1e-6], abs=1e-12)
    now_rig = time.time_ns() - start_ns
    assert all(0 < m.stamp_ns == m.rx_stamp_ns < now_rig for m in imu)
    assert [t.device_stamp_ns for t in got["tag"]] == [5_000_000_000, 5_250_000_000]
    assert all(t.kind == "sync_frame" and t.sensor == "imu" for t in got["tag"])
    frames_per_sample = 1 if fd else 4
    assert len(got["can"]) >= (n + 1) * frames_per_sample + 3 + 2
    counters = got["status"][-1].counter_map()
    assert counters["rejected.can.unknown_id"] == 1
    assert counters["rejected.can.bad_crc"] == 1
    assert counters["rejected.can.bad_dlc"] == 1
    assert counters["can.samples"] == n + 1
    assert "0x103" in got["status"][-1].last_error or "0x80" in got["status"][-1].last_error

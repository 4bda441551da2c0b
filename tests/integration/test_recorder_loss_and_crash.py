"""The recorder as a real process on a real Zenoh hub: zero loss under a burst, a summary on
SIGTERM, a readable file after SIGKILL, and a clear status (not a crash) when it cannot write."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import pytest
import zenoh

from hil.bus.keys import Keys
from hil.bus.pubsub import Publisher
from hil.bus.session import BusConfig, open_session
from hil.messages import ImuSample, RunInfo, ServiceStatus, Truth, decode
from hil.record.mcapio import read_session
from tests.conftest import REPO, free_port, hil_cmd

pytestmark = pytest.mark.slow

RIG = "rectest"


class Hub:
    """A loopback Zenoh peer the recorder connects to, watching every service's status."""

    def __init__(self) -> None:
        self.endpoint = f"tcp/127.0.0.1:{free_port()}"
        self.session: zenoh.Session = open_session(
            BusConfig(mode="peer", listen=(self.endpoint,), connect=())
        )
        self.status: dict[str, ServiceStatus] = {}
        self._sub = self.session.declare_subscriber(f"hil/{RIG}/status/*", self._on_status)

    def _on_status(self, s: zenoh.Sample) -> None:
        st = decode(ServiceStatus, s.payload.to_bytes())
        self.status[st.service] = st

    def env(self) -> dict[str, str]:
        return dict(
            os.environ,
            HIL_ZENOH_MODE="peer",
            HIL_ZENOH_CONNECT=self.endpoint,
            HIL_ZENOH_LISTEN="tcp/127.0.0.1:0",
        )

    def wait(self, pred: Callable[[ServiceStatus], bool], timeout: float = 30.0) -> ServiceStatus:
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            st = self.status.get("recorder")
            if st is not None and pred(st):
                return st
            time.sleep(0.05)
        raise AssertionError(f"recorder status never matched; last: {self.status.get('recorder')}")


@pytest.fixture
def hub() -> Iterator[Hub]:
    h = Hub()
    try:
        yield h
    finally:
        h.session.close()


def start_recorder(hub: Hub, path: str, **extra: float) -> subprocess.Popen[bytes]:
    opts = json.dumps({"path": path, "drain_s": 0.3, **extra})
    proc = subprocess.Popen(
        hil_cmd("service", "recorder", "--rig", RIG, "--options", opts),
        cwd=REPO,
        env=hub.env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    hub.wait(lambda st: st.state in ("running", "degraded"))
    time.sleep(0.3)  # the advanced subscriber's declaration reaches the hub
    return proc


def run_info(seq: int) -> RunInfo:
    return RunInfo(
        seq=seq,
        stamp_ns=0,
        rig=RIG,
        start_epoch_ns=time.time_ns(),
        speed=1.0,
        scenario="straight_level",
        scenario_sha256="0" * 64,
        seed=1,
        duration_s=10.0,
        origin_lat_deg=50.0,
        origin_lon_deg=30.0,
        origin_alt_m=100.0,
    )


def imu(seq: int) -> ImuSample:
    return ImuSample(
        seq=seq,
        stamp_ns=seq * 2_500_000,
        device_stamp_ns=seq * 2_500_000,
        rx_stamp_ns=seq * 2_500_000,
        dt_ns=2_500_000,
        dtheta_b_rad=[1e-5 * seq, 2e-6, -3e-6],
        dvel_b_mps=[0.01, -0.002, -0.0245],
    )


def truth(seq: int) -> Truth:
    return Truth(
        seq=seq,
        stamp_ns=seq * 10_000_000,
        lat_deg=50.0,
        lon_deg=30.0,
        alt_m=100.0,
        pos_ned_m=[float(seq), 0.0, 0.0],
        vel_ned_mps=[10.0, 0.0, 0.0],
        q_nb=[1.0, 0.0, 0.0, 0.0],
        f_b_mps2=[0.0, 0.0, -9.81],
        w_ib_b_radps=[0.0, 0.0, 0.0],
    )


def test_burst_is_recorded_without_loss_and_sigterm_writes_the_summary(hub: Hub, tmp_path: Path) -> None:
    # GIVEN a recorder process on the hub
    path = tmp_path / "burst.mcap"
    proc = start_recorder(hub, str(path))
    k = Keys(RIG)
    run_pub = Publisher(hub.session, k.run(), RunInfo)
    pubs = {name: Publisher(hub.session, k.sensor(name), ImuSample) for name in ("imu",)}
    pubs_synced = Publisher(hub.session, k.synced("imu"), ImuSample)
    truth_pub = Publisher(hub.session, k.truth(), Truth)
    # WHEN 3 publishers send 30 000 messages as fast as Zenoh takes them (far above the rig's rate)
    run_pub.put(run_info(0))
    n = 10_000
    t0 = time.monotonic()
    for i in range(n):
        m = imu(i)
        pubs["imu"].put(m)
        pubs_synced.put(m)
        truth_pub.put(truth(i))
    burst_s = time.monotonic() - t0
    st = hub.wait(lambda st: st.counters.get("written", 0) >= 3 * n + 1, timeout=60)
    assert st.counters["missing"] == 0 and st.counters["zenoh_missed"] == 0, st.counters
    proc.send_signal(signal.SIGTERM)
    out, _ = proc.communicate(timeout=60)
    # THEN the file is complete, finished (summary + index), and says so
    assert proc.returncode == 0, out.decode()[-2000:]
    s = read_session(path)
    assert not s.truncated
    for topic in (k.sensor("imu"), k.synced("imu"), k.truth()):
        seqs = [r.sequence for r in s.by_topic(topic)]
        assert seqs == list(range(n)), (topic, len(seqs))
    comp = s.metadata["completeness"]
    assert json.loads(comp["missing"]) == 0
    assert json.loads(comp["zenoh_missed"]) == 0
    assert json.loads(comp["replay_ready"]) is True
    assert json.loads(comp["topics"])[k.truth()]["count"] == n
    print(f"burst of {3 * n} msgs in {burst_s:.2f} s ({3 * n / burst_s:.0f} msg/s) recorded with no loss")


def test_sigkill_leaves_a_file_readable_up_to_the_last_flushed_chunk(hub: Hub, tmp_path: Path) -> None:
    # GIVEN a recorder that has received 2 s of IMU traffic at 400 Hz
    path = tmp_path / "killed.mcap"
    proc = start_recorder(hub, str(path))
    k = Keys(RIG)
    Publisher(hub.session, k.run(), RunInfo).put(run_info(0))
    pub = Publisher(hub.session, k.sensor("imu"), ImuSample)
    sent_at: list[float] = []
    t0 = time.monotonic()
    i = 0
    while time.monotonic() - t0 < 2.5:
        pub.put(imu(i))
        sent_at.append(time.monotonic())
        i += 1
        time.sleep(0.0025)
    # WHEN it is killed without warning
    t_kill = time.monotonic()
    proc.send_signal(signal.SIGKILL)
    proc.wait(timeout=10)
    # THEN the file reads (no footer, no summary) and holds every sample sent more than a flush
    # period (1 s, plus scheduling margin) before the kill, contiguous from seq 0
    s = read_session(path)
    seqs = [r.sequence for r in s.by_topic(k.sensor("imu"))]
    assert "completeness" not in s.metadata  # the clean-stop summary was never written
    assert "hil" in s.metadata  # run metadata was flushed with the first chunk
    must_have = sum(1 for t in sent_at if t < t_kill - 1.5)
    assert must_have > 100
    assert len(seqs) >= must_have, (len(seqs), must_have, i)
    assert seqs == list(range(len(seqs)))


def test_unwritable_path_is_reported_in_status_and_the_process_keeps_serving(
    hub: Hub, tmp_path: Path
) -> None:
    # GIVEN a recording path whose parent is a regular file (unwritable even for root)
    blocker = tmp_path / "not_a_dir"
    blocker.write_text("x")
    target = blocker / "x.mcap"
    proc = start_recorder(hub, str(target))
    try:
        # THEN status says degraded with the path and the reason, and keeps coming
        st = hub.wait(lambda st: st.state == "degraded")
        assert str(target) in st.last_error and "exists" in st.last_error.lower(), st.last_error
        assert st.counters.get("errors.recording_path") == 1
        seq = st.seq
        hub.wait(lambda st: st.seq >= seq + 2)
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert proc.returncode == 0


@pytest.mark.skipif(not os.path.exists("/dev/full"), reason="no /dev/full")
def test_full_disk_is_reported_in_status_and_the_process_keeps_serving(hub: Hub) -> None:
    # GIVEN a recorder writing to a device that is always full
    proc = start_recorder(hub, "/dev/full")
    try:
        k = Keys(RIG)
        Publisher(hub.session, k.run(), RunInfo).put(run_info(0))
        pub = Publisher(hub.session, k.sensor("imu"), ImuSample)
        for i in range(200):
            pub.put(imu(i))
        # THEN the first flush fails: degraded, a write error counted, the reason in one line
        st = hub.wait(lambda st: st.state == "degraded", timeout=10)
        assert st.counters.get("errors.write") == 1, st.counters
        assert "No space left on device" in st.last_error, st.last_error
        # and it still accounts what it receives (a gap is still a gap), still publishing status
        for i in range(200, 300):
            pub.put(imu(i))
        hub.wait(lambda st: st.counters.get("recording") == 0 and st.seq > 2)
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert proc.returncode == 0


def test_split_by_duration_loses_nothing_and_every_part_stands_alone(hub: Hub, tmp_path: Path) -> None:
    # GIVEN a recorder that starts a new part every second
    path = tmp_path / "split.mcap"
    proc = start_recorder(hub, str(path), split_s=1.0)
    k = Keys(RIG)
    Publisher(hub.session, k.run(), RunInfo).put(run_info(0))
    pub = Publisher(hub.session, k.sensor("imu"), ImuSample)
    # WHEN 3.5 s of 400 Hz IMU traffic flow, then SIGTERM
    t0 = time.monotonic()
    i = 0
    while time.monotonic() - t0 < 3.5:
        pub.put(imu(i))
        i += 1
        time.sleep(0.0025)
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    # THEN there are several finished parts, each with the run metadata, and together every sample
    parts = sorted(tmp_path.glob("split*.mcap"))
    assert len(parts) >= 3, parts
    seqs: list[int] = []
    for n, part in enumerate(parts):
        s = read_session(part)
        assert not s.truncated and "hil" in s.metadata and "completeness" in s.metadata, part
        assert json.loads(s.metadata["completeness"]["part"]) == n
        assert any(name.startswith("scenario/") for name in s.attachments)
        seqs += [r.sequence for r in s.by_topic(k.sensor("imu"))]
    assert seqs == list(range(i))

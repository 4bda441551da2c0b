"""The recorder as a real process on a real Zenoh hub: zero loss under a burst, a summary on
SIGTERM, a readable file after SIGKILL, and a clear status (not a crash) when it cannot write."""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import msgspec
import pytest
import zenoh
from mcap.reader import make_reader

from hil.bus.keys import Keys
from hil.bus.pubsub import Publisher
from hil.bus.session import BusConfig, open_session
from hil.messages import (
    CanFrame,
    CaptureTruth,
    Event,
    ImuSample,
    RunInfo,
    ServiceStatus,
    Truth,
    decode,
    encode,
)
from hil.record.mcapio import (
    RecordingError,
    Session,
    SessionStream,
    read_session,
    split_part_path,
    split_parts,
)
from hil.runners.sim import SimOptions, run_sim
from tests.conftest import REPO, communicate_or_dump, free_port, hil_cmd

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


def start_recorder(hub: Hub, path: str, **extra: object) -> subprocess.Popen[bytes]:
    hub.status.pop("recorder", None)  # a killed one's last word must not read as this one's
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
    st = hub.wait(lambda st: st.counter_map().get("written", 0) >= 3 * n + 1, timeout=60)
    assert st.counter_map()["missing"] == 0 and st.counter_map()["zenoh_missed"] == 0, st.counter_map()
    assert st.counter_map()["zenoh_unsequenced"] == 0  # every sample carried Zenoh's sequence number
    proc.send_signal(signal.SIGTERM)
    out = communicate_or_dump(proc, 60)
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


def test_batches_are_recorded_message_by_message_and_a_bad_one_is_counted(hub: Hub, tmp_path: Path) -> None:
    """The CAN bridge puts a sample's raw frames as one batch (``Publisher.put_many``): the file
    keeps each frame as its own hil.CanFrame message, byte for byte as encoded alone; a batch
    that is not one is refused and counted, an invalid frame inside a batch is refused alone."""
    path = tmp_path / "batches.mcap"
    proc = start_recorder(hub, str(path))
    k = Keys(RIG)
    key = f"{k.root}/can/vcan0"
    Publisher(hub.session, k.run(), RunInfo).put(run_info(0))
    pub = Publisher(hub.session, key, CanFrame)
    frames = [
        CanFrame(
            seq=i, stamp_ns=i * 135_000, channel="vcan0", arbitration_id=0x181 + i % 4, data_hex="5a" * 8
        )
        for i in range(400)
    ]
    for i in range(0, 400, 4):
        pub.put_many(frames[i : i + 4])
    raw = hub.session.declare_publisher(key)
    raw.put(b"[" + encode(frames[0]))  # a cut batch
    bad = encode(frames[0]).replace(b'"data_hex":"5a', b'"data_hex":"zz')
    raw.put(b"[" + encode(frames[399]).replace(b'"seq":399', b'"seq":400') + b"," + bad + b"]")
    st = hub.wait(lambda st: st.counter_map().get("written", 0) >= 402, timeout=60)
    counters = st.counter_map()
    assert counters.get("rejected.can.invalid", 0) == 2, counters  # the cut batch, the bad frame
    proc.send_signal(signal.SIGTERM)
    out = communicate_or_dump(proc, 60)
    assert proc.returncode == 0, out.decode()[-2000:]
    s = read_session(path)
    recs = s.by_topic(key)
    assert [r.sequence for r in recs] == list(range(401))
    assert [r.payload for r in recs[:400]] == [encode(f) for f in frames]
    assert json.loads(s.metadata["completeness"]["missing"]) == 0


def test_what_is_sent_the_moment_the_recorder_says_ready_is_recorded_from_the_first_message(
    hub: Hub, tmp_path: Path
) -> None:
    """Time zero waits for the recorder's ready status, and the streams start then: a recorder
    that said "running" before its subscription reached the bus would lose the head of every
    stream, which no seq gap shows (a stream's first seq seen is its baseline)."""
    # GIVEN publishers on the hub, and a recorder process starting; its first "running" status
    # wakes this thread at once (no polling, no grace period). Plain Zenoh publishers: an
    # advanced one's cache could hand a late subscriber the head afterwards and hide the race.
    k = Keys(RIG)
    run_pub = Publisher(hub.session, k.run(), RunInfo, miss_detection=False)
    imu_pub = Publisher(hub.session, k.sensor("imu"), ImuSample, miss_detection=False)
    truth_pub = Publisher(hub.session, k.truth(), Truth, miss_detection=False)
    ready = threading.Event()

    def on_status(sample: zenoh.Sample) -> None:
        if decode(ServiceStatus, sample.payload.to_bytes()).state == "running":
            ready.set()

    watch = hub.session.declare_subscriber(f"hil/{RIG}/status/recorder", on_status)
    path = tmp_path / "head.mcap"
    opts = json.dumps({"path": str(path), "drain_s": 0.3})
    proc = subprocess.Popen(
        hil_cmd("service", "recorder", "--rig", RIG, "--options", opts),
        cwd=REPO,
        env=hub.env(),
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
    )
    try:
        assert ready.wait(60), f"the recorder never said it was running; last: {hub.status.get('recorder')}"
        # WHEN the run starts right then: its announcement and 200 messages of two streams
        run_pub.put(run_info(0))
        n = 200
        for i in range(n):
            imu_pub.put(imu(i))
            truth_pub.put(truth(i))
        with contextlib.suppress(AssertionError):  # not the verdict: the stop drains what came
            hub.wait(lambda st: st.counter_map().get("written", 0) >= 2 * n + 1, timeout=20)
    finally:
        watch.undeclare()
        proc.send_signal(signal.SIGTERM)
        out = communicate_or_dump(proc, 60)
    # THEN every stream is in the file from its first message on
    assert proc.returncode == 0, out.decode()[-2000:]
    s = read_session(path)
    assert [r.sequence for r in s.by_topic(k.run())][:1] == [0]
    for topic in (k.sensor("imu"), k.truth()):
        seqs = [r.sequence for r in s.by_topic(topic)]
        assert seqs == list(range(n)), (topic, seqs[:5], len(seqs))


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


def _flushed(path: Path, topic: str) -> int:
    """How many messages of ``topic`` a recorder's file holds so far (read as a crash leaves it)."""
    try:
        return len(read_session(path).by_topic(topic))
    except RecordingError:  # nothing flushed yet
        return 0


def _stop(proc: subprocess.Popen[bytes]) -> None:
    if proc.poll() is None:
        proc.kill()
        proc.communicate(timeout=30)


def test_a_restarted_recorder_continues_the_session_once_and_recovers_what_the_caches_hold(
    hub: Hub, tmp_path: Path
) -> None:
    # GIVEN a run at speed 2 whose time zero was 100 s ago (log time = start + 2 x the wall time
    # since: a part on the raw wall clock reads 100 s and more early), truth stamped on its rig
    # clock, and a recorder whose file holds truth 0..149 (flushed), then is SIGKILLed
    first, part = tmp_path / "s.mcap", tmp_path / "s.part1.mcap"
    k = Keys(RIG)
    run = msgspec.structs.replace(run_info(0), start_epoch_ns=time.time_ns() - 100 * 10**9, speed=2.0)
    start = run.start_epoch_ns

    def on_rig_clock(seq: int) -> Truth:
        return msgspec.structs.replace(truth(seq), stamp_ns=2 * (time.time_ns() - start))

    proc = start_recorder(hub, str(first))
    second: subprocess.Popen[bytes] | None = None
    try:
        run_pub = Publisher(hub.session, k.run(), RunInfo)
        run_pub.put(run)
        pub = Publisher(hub.session, k.truth(), Truth)  # an advanced publisher: a 256-sample cache
        for i in range(150):
            pub.put(on_rig_clock(i))
        deadline = time.monotonic() + 60
        while _flushed(first, k.truth()) < 150:
            assert time.monotonic() < deadline, "the first recorder never flushed truth 0..149"
            time.sleep(0.2)
        # no RunInfo reaches the restarted recorder (its cache goes too): the run it stamps with
        # can come from the first file alone (live, RunInfo comes at 1 Hz, after other keys' caches)
        run_pub._pub.undeclare()
        proc.send_signal(signal.SIGKILL)
        proc.wait(timeout=30)
        # WHEN truth 150..249 go out with no recorder, and a restarted one continues the session
        for i in range(150, 250):
            pub.put(on_rig_clock(i))
        restarted_wall = time.time_ns()
        second = start_recorder(hub, str(part), continues=[str(first)], resume=1)
        for i in range(250, 300):
            pub.put(on_rig_clock(i))
        hub.wait(lambda st: st.counter_map().get("written", 0) >= 150, timeout=60)
        second.send_signal(signal.SIGTERM)
        out = communicate_or_dump(second, 60)
        stopped_wall = time.time_ns()
        assert second.returncode == 0, out.decode()[-2000:]
    finally:
        _stop(proc)
        if second is not None:
            _stop(second)
    # THEN the files end to end hold truth 0..299 once each: the downtime came back from the
    # publisher's cache (asked at once, not when a heartbeat happened to come first), and the
    # cache's replay of what the first file holds was not written again
    a, b = read_session(first), read_session(part)
    seqs_a = [r.sequence for r in a.by_topic(k.truth())]
    seqs_b = [r.sequence for r in b.by_topic(k.truth())]
    assert seqs_a == list(range(150)) and seqs_b == list(range(150, 300)), (seqs_a[-3:], seqs_b[:3])
    assert [r.sequence for r in b.by_topic(k.run())] == []  # the RunInfo is in the first file only
    comp = b.metadata["completeness"]
    cont = json.loads(comp["continues"])
    # (the first file also holds the first recorder's statuses, whose cache died with it)
    held = sum(1 for r in a.records if r.schema.startswith("hil."))
    assert cont == {"files": [first.name], "messages": held, "already_recorded": 150}, (cont, held)
    # and the part's accounting covers the whole session: nothing missing, nothing twice
    tr = json.loads(comp["topics"])[k.truth()]
    assert (tr["first"], tr["last"], tr["count"], tr["missing"], tr["duplicates"]) == (0, 299, 300, 0, 0), tr
    assert json.loads(comp["replay_ready"]) is True
    _assert_the_part_is_on_the_sessions_time_base(first, b, k, run, (restarted_wall, stopped_wall))


def _assert_the_part_is_on_the_sessions_time_base(
    first: Path, b: Session, k: Keys, run: RunInfo, walls: tuple[int, int]
) -> None:
    """A restarted recorder stamps as the first did from its first message: the run (taken from
    the first file, no RunInfo having reached it) is its metadata, every publish time is the
    start epoch + the stamp (recovered ones included: before, publish = log time until a RunInfo
    came), and its log times are rig time on the date at the run's speed."""
    start, speed = run.start_epoch_ns, run.speed
    hil = b.metadata["hil"]
    assert (json.loads(hil["start_epoch_ns"]), json.loads(hil["speed"])) == (start, speed), hil
    rig = [r for r in b.records if r.schema.startswith("hil.")]
    off = [(r.topic, r.sequence) for r in rig if r.publish_time_ns != start + r.decode().stamp_ns]
    assert not off, off[:5]
    lo, hi = (start + int(speed * (w - start)) for w in walls)
    assert lo <= rig[0].log_time_ns <= hi, (rig[0].log_time_ns - lo, hi - rig[0].log_time_ns)
    assert rig[0].log_time_ns > max(r.log_time_ns for r in read_session(first).records)
    # so what it recovered from the cache (published before it started) reads as recovered, and
    # only that: the time-sync rerun excuses the re-stamps of measurements read there
    stream = SessionStream(first, follow_parts=True)
    recovered = [r.sequence for r in stream if r.topic == k.truth() and r.recovered]
    assert [p.name for p in stream.paths] == [first.name, "s.part1.mcap"]
    assert recovered == list(range(150, 250)), recovered


def test_a_publisher_that_spoke_once_before_the_recorder_listened_is_recorded(
    hub: Hub, tmp_path: Path
) -> None:
    # GIVEN a service that published its one event (as a CAN bridge does once per life) and the
    # one heartbeat that follows it, all before the recorder started (services start together)
    k = Keys(RIG)
    heartbeats: list[str] = []
    hb = hub.session.declare_subscriber(
        f"{k.event('bridge')}/@adv/pub/**", lambda s: heartbeats.append(str(s.key_expr))
    )
    try:
        pub = Publisher(hub.session, k.event("bridge"), Event)
        pub.put(Event(seq=0, stamp_ns=0, kind="can_transport", source="bridge", detail="vcan0"))
        deadline = time.monotonic() + 60
        while not heartbeats:
            assert time.monotonic() < deadline, "the publisher's heartbeat never went out"
            time.sleep(0.05)
    finally:
        hb.undeclare()
    # WHEN the recorder starts, records a while and stops
    path = tmp_path / "late.mcap"
    proc = start_recorder(hub, str(path))
    try:
        deadline = time.monotonic() + 60  # the file is flushed every second
        while not _flushed(path, k.event("bridge")):
            assert time.monotonic() < deadline, "the event never reached the file"
            time.sleep(0.2)
        proc.send_signal(signal.SIGTERM)
        out = communicate_or_dump(proc, 60)
    finally:
        _stop(proc)
    # THEN the event is in the file: the recorder asked the publisher's cache when it started
    # (before, nothing would ever have brought it: no other sample, no other heartbeat)
    assert proc.returncode == 0, out.decode()[-2000:]
    events = [r.decode() for r in read_session(path).by_topic(k.event("bridge"))]
    assert [(e.seq, e.kind) for e in events] == [(0, "can_transport")], events  # type: ignore[attr-defined]


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
        # the path, and why: a directory on its way is a file (mkdir's own word was "File exists")
        assert str(target) in st.last_error and "is a file, not a directory" in st.last_error, st.last_error
        assert st.counter_map().get("errors.recording_path") == 1
        seq = st.seq
        hub.wait(lambda st: st.seq >= seq + 2)
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert proc.returncode == 3  # it served to the end, and says by its exit code that it recorded nothing


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
        assert st.counter_map().get("errors.write") == 1, st.counter_map()
        assert "No space left on device" in st.last_error, st.last_error
        # and it still accounts what it receives (a gap is still a gap), still publishing status
        for i in range(200, 300):
            pub.put(imu(i))
        hub.wait(lambda st: st.counter_map().get("recording") == 0 and st.seq > 2)
        assert proc.poll() is None
    finally:
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=30)
    assert proc.returncode == 3  # degraded to the end: a non-zero exit, as hil up's
    assert hub.status["recorder"].state == "degraded"  # its last status too, sent after it finished


def test_split_by_duration_loses_nothing_and_every_part_stands_alone(hub: Hub, tmp_path: Path) -> None:
    # GIVEN a recorder that starts a new part every second
    path = tmp_path / "split.mcap"
    proc = start_recorder(hub, str(path), split_s=1.0)
    k = Keys(RIG)
    Publisher(hub.session, k.run(), RunInfo).put(run_info(0))
    pub = Publisher(hub.session, k.sensor("imu"), ImuSample)
    truth_pub = Publisher(hub.session, k.truth(), Truth)  # the Foxglove pose is derived from it
    # WHEN 3.5 s of 400 Hz IMU traffic (and 100 Hz truth) flow, then SIGTERM
    t0 = time.monotonic()
    i = 0
    while time.monotonic() - t0 < 3.5:
        pub.put(imu(i))
        if i % 4 == 0:
            truth_pub.put(truth(i // 4))
        i += 1
        time.sleep(0.0025)
    time.sleep(0.5)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    # THEN there are several finished parts, each with the run metadata, and together every sample
    parts = sorted(tmp_path.glob("split*.mcap"))
    assert len(parts) >= 3, parts
    # each derived Foxglove channel's MCAP sequence goes on across the parts (it restarted at 0
    # in every part, and merged parts showed dups on every /foxglove row)
    derived: dict[str, list[int]] = {}
    for part in parts:
        with open(part, "rb") as f:
            for _schema, chan, msg in make_reader(f).iter_messages(log_time_order=False):
                if chan.topic.startswith("/foxglove/"):
                    derived.setdefault(chan.topic, []).append(msg.sequence)
    assert derived, "no Foxglove channel was derived from the truth"
    for topic, sequences in derived.items():
        assert sequences == list(range(len(sequences))), (topic, sequences)
    seqs: list[int] = []
    for n, part in enumerate(parts):
        s = read_session(part)
        assert not s.truncated and "hil" in s.metadata and "completeness" in s.metadata, part
        assert json.loads(s.metadata["completeness"]["part"]) == n
        assert any(name.startswith("scenario/") for name in s.attachments)
        seqs += [r.sequence for r in s.by_topic(k.sensor("imu"))]
        if n:  # each part names the file it follows, as that file was closed
            assert s.meta("part", "previous") == parts[n - 1].name
            assert s.meta("part", "previous_bytes") == parts[n - 1].stat().st_size
    assert seqs == list(range(i))
    assert split_parts(path) == parts[1:]


def test_zenoh_recovers_samples_lost_in_transit_and_reports_what_it_cannot(hub: Hub, tmp_path: Path) -> None:
    """Loss inside Zenoh itself, made on purpose: the publishing session's egress downsampling
    interceptor drops most ``put``s of two keys (Zenoh config ``downsampling``), as a congested or
    broken link would. The rig's publishers are advanced publishers with a 256-sample cache; the
    recorder's advanced subscriber sees each gap in the Zenoh sequence and queries the cache.

    - ``capture/recoverable`` (20 puts/s pass of ~200/s): every gap is smaller than the cache, so
      every sample is recovered into the file -- nothing missing, although a plain subscriber on
      the hub received only a few percent of them. Its rate leaves a busy machine room: a gap is
      recovered only while the publisher's cache still holds it. At ~800/s, a recorder starved
      for 0.3 s lost 3 recoverable samples in a full suite run (2026-12-06); at ~200/s it would
      have to be starved for over a second;
    - ``capture/lossy`` (2 puts/s pass): gaps of hundreds of samples outrun the cache; what the
      cache no longer holds is reported by Zenoh's sample-miss listener, and exactly as many
      seqs are missing from the file: the two measures agree, per key, in status and summary.
    """
    path = tmp_path / "transit.mcap"
    proc = start_recorder(hub, str(path))
    k = Keys(RIG)
    ok_key, lossy_key = k.capture("recoverable"), k.capture("lossy")
    plain_count = {ok_key: 0, lossy_key: 0}

    def count(s: zenoh.Sample) -> None:
        plain_count[str(s.key_expr)] += 1

    counter = hub.session.declare_subscriber(f"hil/{RIG}/capture/*", count)
    rules = [{"key_expr": ok_key, "freq": 20.0}, {"key_expr": lossy_key, "freq": 2.0}]
    lossy_link = open_session(
        BusConfig(
            mode="peer",
            connect=(hub.endpoint,),
            listen=("tcp/127.0.0.1:0",),
            extra={"downsampling": [{"flows": ["egress"], "messages": ["put"], "rules": rules}]},
        )
    )
    try:
        run_pub = Publisher(hub.session, k.run(), RunInfo)
        run_pub.put(run_info(0))
        ok_pub, lossy_pub = (Publisher(lossy_link, key, CaptureTruth) for key in (ok_key, lossy_key))
        time.sleep(1.0)  # the recorder's subscription reaches the new session
        n, every = 2000, 4  # lossy ~800/s (more than the cache between two heartbeats), ok a quarter
        n_ok = n // every
        for i in range(n):  # 2.5 s
            lossy_pub.put(CaptureTruth(seq=i, stamp_ns=i, sensor="imu", true_stamp_ns=i))
            if i % every == 0:
                j = i // every
                ok_pub.put(CaptureTruth(seq=j, stamp_ns=j, sensor="imu", true_stamp_ns=j))
            time.sleep(0.001)
        # the last samples are found by the publishers' sporadic heartbeat (1 s)
        st = hub.wait(lambda st: st.counter_map().get("written", 0) >= 1 + n_ok + 100, timeout=30)
        time.sleep(2.5)
        st = hub.status["recorder"]
    finally:
        counter.undeclare()
        proc.send_signal(signal.SIGTERM)
        proc.communicate(timeout=60)
        lossy_link.close()
    assert proc.returncode == 0
    # the transport really lost them: a plain subscriber saw a few percent of the puts
    assert plain_count[ok_key] < 0.2 * n_ok and plain_count[lossy_key] < 0.05 * n, plain_count
    s = read_session(path)
    comp = s.metadata["completeness"]
    topics = json.loads(comp["topics"])
    # recoverable: every sample in the file, in order, nothing missing, no miss reported
    assert [r.sequence for r in s.by_topic(ok_key)] == list(range(n_ok))
    assert topics[ok_key]["missing"] == 0
    # lossy: Zenoh's count of what it could not recover == the seqs missing from the file
    lossy_seqs = [r.sequence for r in s.by_topic(lossy_key)]
    missing = topics[lossy_key]["missing"]
    assert missing > 100 and len(lossy_seqs) + missing == n, (len(lossy_seqs), missing)
    assert lossy_seqs == sorted(lossy_seqs) and lossy_seqs[-1] == n - 1  # the tail came by heartbeat
    assert json.loads(comp["zenoh_missed"]) == missing
    assert json.loads(comp["zenoh_missed_by_key"]) == {lossy_key: missing}
    assert json.loads(comp["zenoh_unsequenced"]) == 0
    assert json.loads(comp["replay_ready"]) is False
    assert st.counter_map()["zenoh_missed"] == missing and st.counter_map()["missing"] == missing, (
        st.counter_map()
    )
    assert "Zenoh sample miss" in st.last_error and lossy_key in st.last_error


def test_zenoh_miss_detection_can_be_turned_off(hub: Hub, tmp_path: Path) -> None:
    """``zenoh_advanced: false`` (``hil up --no-zenoh-miss-detection``): a plain subscriber, seq gaps only."""
    path = tmp_path / "plain.mcap"
    proc = start_recorder(hub, str(path), zenoh_advanced=False)
    k = Keys(RIG)
    Publisher(hub.session, k.run(), RunInfo).put(run_info(0))
    pub = Publisher(hub.session, k.sensor("imu"), ImuSample, miss_detection=False)
    for i in range(500):
        pub.put(imu(i))
    hub.wait(lambda st: st.counter_map().get("written", 0) >= 501)
    proc.send_signal(signal.SIGTERM)
    proc.communicate(timeout=60)
    comp = read_session(path).metadata["completeness"]
    assert json.loads(comp["missing"]) == 0 and json.loads(comp["replay_ready"]) is True
    assert json.loads(comp["zenoh_miss_detection"]) is False
    assert comp["method"] == "seq gaps per publisher"


def _burst(hub: Hub, n: int) -> None:
    k = Keys(RIG)
    Publisher(hub.session, k.run(), RunInfo).put(run_info(0))
    pubs = [Publisher(hub.session, key, ImuSample) for key in (k.sensor("imu"), k.synced("imu"))]
    for i in range(n):
        m = imu(i)
        for p in pubs:
            p.put(m)


def test_sigterm_during_a_backlog_still_writes_every_received_message(hub: Hub, tmp_path: Path) -> None:
    """Stopped right after a burst, while the recorder is still behind: it waits until nothing
    more arrives, writes the whole queue, then the summary. A stop that cut the backlog would
    lose the *tail* of every stream, which no seq gap shows."""
    path = tmp_path / "backlog.mcap"
    proc = start_recorder(hub, str(path))
    n = 20_000
    _burst(hub, n)
    proc.send_signal(signal.SIGTERM)  # no wait for "written": the queue is full now
    out = communicate_or_dump(proc, 60)
    assert proc.returncode == 0, out.decode()[-2000:]
    s = read_session(path)
    k = Keys(RIG)
    for topic in (k.sensor("imu"), k.synced("imu")):
        assert [r.sequence for r in s.by_topic(topic)] == list(range(n)), topic
    comp = s.metadata["completeness"]
    assert json.loads(comp["unwritten_at_stop"]) == 0 and json.loads(comp["replay_ready"]) is True


def test_a_stop_deadline_that_cuts_the_backlog_is_counted_not_silent(hub: Hub, tmp_path: Path) -> None:
    """With a stop deadline too short for the backlog (``stop_timeout_s``), what was received but
    not written is counted in the summary and the file is not replay-ready. In process, with the
    backlog queued before the writer starts: the only way to be sure there is one."""
    from hil.bus.identity import UNKNOWN
    from hil.messages import encode
    from hil.runtime.clock import wall_ns
    from hil.runtime.service import ServiceContext
    from services.recorder import Recorder

    path = tmp_path / "cut.mcap"
    opts = {"path": str(path), "drain_s": 0.0, "stop_timeout_s": 0.0}
    rec = Recorder(ServiceContext(name="recorder", rig=RIG, session=hub.session, options=opts))
    k = Keys(RIG)
    n = 10_000
    # as the Zenoh callback enqueues: (key, payload, receive wall time, publisher, origin, encoding)
    rec.queue.put("run", "", (k.run(), encode(run_info(0)), wall_ns(), "", UNKNOWN, None))
    for i in range(n):
        rec.queue.put("sensor/imu", "", (k.sensor("imu"), encode(imu(i)), wall_ns(), "", UNKNOWN, None))
    rec.setup()  # the writer starts on a backlog of n + 1 messages
    rec.teardown()  # and is stopped at once
    comp = read_session(path).metadata["completeness"]
    unwritten = json.loads(comp["unwritten_at_stop"])
    assert unwritten > 0 and json.loads(comp["replay_ready"]) is False
    assert rec.written + unwritten == n + 1  # every received message is either written or counted
    assert "not written" in rec.stats.last_error


def test_sigterm_right_after_sigcont_stops_the_recorder_with_every_message(hub: Hub, tmp_path: Path) -> None:
    """Paused (SIGSTOP) while a burst piles up, resumed and stopped at once: the kernel may hand
    the SIGTERM to any thread, and a main thread in an untimed wait never ran the handler (the
    recorder hung until SIGKILL, 2 runs in 3). It stops, and writes everything it received."""
    path = tmp_path / "paused.mcap"
    proc = start_recorder(hub, str(path))
    n = 20_000
    proc.send_signal(signal.SIGSTOP)
    sender = threading.Thread(target=_burst, args=(hub, n))
    sender.start()
    time.sleep(1.0)
    proc.send_signal(signal.SIGCONT)
    proc.send_signal(signal.SIGTERM)
    sender.join(timeout=60)
    out = communicate_or_dump(proc, 40)
    assert proc.returncode == 0, out.decode()[-2000:]
    s = read_session(path)
    k = Keys(RIG)
    for topic in (k.sensor("imu"), k.synced("imu")):
        assert [r.sequence for r in s.by_topic(topic)] == list(range(n)), topic
    assert json.loads(s.metadata["completeness"]["unwritten_at_stop"]) == 0


def test_sigusr1_prints_every_threads_stack_and_the_service_runs_on(hub: Hub, tmp_path: Path) -> None:
    """``kill -USR1`` of a service: the stack of each of its Python threads on stderr, and it goes
    on (what a test or a user sees of a service that does not stop; ``communicate_or_dump``)."""
    proc = start_recorder(hub, str(tmp_path / "usr1.mcap"))
    try:
        proc.send_signal(signal.SIGUSR1)
        time.sleep(1.0)
        assert proc.poll() is None  # still running
        proc.send_signal(signal.SIGTERM)
        out = communicate_or_dump(proc, 60).decode(errors="replace")
    finally:
        _stop(proc)
    assert proc.returncode == 0, out[-2000:]
    assert "Current thread" in out or "Thread 0x" in out, out[-2000:]
    assert "run_loop" in out and "_write_loop" in out, out[-3000:]  # the main thread and the writer


def test_a_recorder_keeps_an_earlier_recording_at_its_path(hub: Hub, tmp_path: Path) -> None:
    """A live session cannot be made again: a second ``docker compose up`` (a fixed path), or a
    recorder container restarted after a crash, once truncated the file it found there."""
    # GIVEN an earlier session at the path, split in two parts
    path = tmp_path / "session.mcap"
    earlier = tmp_path / "earlier.mcap"
    run_sim(SimOptions(duration_s=2.0, record=earlier, split_s=1.0, fusion_worker=False))
    earlier.rename(path)
    split_part_path(earlier, 1).rename(split_part_path(path, 1))
    before = [path.read_bytes(), split_part_path(path, 1).read_bytes()]
    # WHEN a recorder starts there and records a run
    proc = start_recorder(hub, str(path))
    k = Keys(RIG)
    Publisher(hub.session, k.run(), RunInfo).put(run_info(0))
    pub = Publisher(hub.session, k.sensor("imu"), ImuSample)
    for i in range(200):
        pub.put(imu(i))
    hub.wait(lambda st: st.counter_map().get("written", 0) >= 201, timeout=60)
    proc.send_signal(signal.SIGTERM)
    out = communicate_or_dump(proc, 60).decode()
    # THEN the earlier session is kept whole under the next free name, its parts with it, and said
    assert proc.returncode == 0, out[-2000:]
    kept = tmp_path / "session.1.mcap"
    assert [kept.read_bytes(), split_part_path(kept, 1).read_bytes()] == before
    assert split_parts(kept) == [split_part_path(kept, 1)]
    assert f"kept as {kept}" in out
    s = read_session(path)
    assert [r.sequence for r in s.by_topic(k.sensor("imu"))] == list(range(200))
    kept_events = [r.decode() for r in s.by_topic(f"hil/{RIG}/event/recorder")]
    assert any(e.kind == "earlier_recording_kept" and str(kept) in e.detail for e in kept_events), kept_events

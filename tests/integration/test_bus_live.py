"""One live ``hil up`` on a real Zenoh hub, looked at from outside, then its recorder SIGKILLed.

GIVEN ``hil up`` joined to a hub this test opens (``HIL_ZENOH_CONNECT``), recording with
``--record-exclude 'health/*'``
WHEN the plain zenoh-python example of docs/topics.md runs against it, a stranger publishes on
a key outside the contract, and the recorder is killed with SIGKILL mid-run
THEN the example finds every key and its type through the queryable and decodes a solution; every
service holds its liveliness token; the unknown key is in the file as raw bytes, the excluded
ones are not; the crashed file fails the plain mcap reader, ``hil recover`` makes it readable by
it (and by Foxglove's ``@mcap/core`` where ``tools/mcapjs`` is installed), says what was lost,
and ``hil rerun --verify`` (timesync and fusion) passes on the part that exists.
"""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from typing import Any

import pytest
import zenoh
from mcap.reader import make_reader
from mcap.records import Message

from hil.bus.session import BusConfig, open_session
from hil.messages import ServiceStatus, decode
from hil.record.scan import Scan
from hil.report.topics_doc import DISCOVERY_EXAMPLE
from hil.runtime.supervisor import SERVICES
from tests.conftest import REPO, free_port, hil_cmd, run_hil

pytestmark = pytest.mark.slow

RIG = "busrig"
MCAPJS = REPO / "tools" / "mcapjs"


def _counters(st: ServiceStatus) -> dict[str, int]:
    c: Any = st.counters
    return dict(c) if isinstance(c, dict) else {x.key: x.value for x in c}


@pytest.fixture(scope="module")
def live(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    tmp = tmp_path_factory.mktemp("buslive")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = open_session(BusConfig(mode="router", listen=(endpoint,), connect=()))
    statuses: dict[str, ServiceStatus] = {}
    encodings: dict[str, str] = {}
    lock = threading.Lock()

    def on_status(s: zenoh.Sample) -> None:
        st = decode(ServiceStatus, s.payload.to_bytes())
        with lock:
            statuses[st.service] = st
            encodings[str(s.key_expr)] = str(s.encoding)

    sub = hub.declare_subscriber(f"hil/{RIG}/status/*", on_status)
    fused = threading.Event()  # the fusion publishes (after time sync locks: a few seconds in)
    nav_sub = hub.declare_subscriber(f"hil/{RIG}/nav/ekf15", lambda _s: fused.set())
    imu_samples: list[list[int]] = []  # the seqs of each Zenoh sample on sensor/imu (a batch: several)

    def on_imu(s: zenoh.Sample) -> None:
        body = json.loads(s.payload.to_bytes())
        with lock:
            imu_samples.append([m["seq"] for m in body] if isinstance(body, list) else [body["seq"]])

    imu_sub = hub.declare_subscriber(f"hil/{RIG}/sensor/imu", on_imu)
    env = dict(os.environ, HIL_ZENOH_MODE="client", HIL_ZENOH_CONNECT=endpoint, HIL_ZENOH_LISTEN="")
    record = tmp / "live.mcap"
    args = ["up", "--rig", RIG, "--duration", "60", "--quiet", "--record", str(record)]
    up = subprocess.Popen(
        hil_cmd(*args, "--record-exclude", "health/*"),
        cwd=REPO,
        env=env,
        stdout=subprocess.PIPE,
        stderr=subprocess.STDOUT,
        text=True,
    )
    out: dict[str, Any] = {"record": record, "endpoint": endpoint, "tmp": tmp}
    try:
        deadline = time.monotonic() + 120
        while time.monotonic() < deadline:  # every service running, the fusion publishing
            with lock:
                running = {n for n, st in statuses.items() if st.state == "running"}
            if (
                running >= set(SERVICES)
                and fused.is_set()
                and record.exists()
                and record.stat().st_size > 50_000
            ):
                break
            assert up.poll() is None, up.communicate()[0]
            time.sleep(0.2)
        else:
            raise AssertionError(f"the rig never ran: {sorted(statuses)}")
        example = tmp / "discover.py"
        example.write_text(DISCOVERY_EXAMPLE)
        out["example"] = subprocess.run(
            [sys.executable, str(example), endpoint, RIG], capture_output=True, text=True, timeout=60
        )
        out["alive"] = sorted(
            str(r.ok.key_expr) for r in hub.liveliness().get(f"hil/{RIG}/@alive/*", timeout=5) if r.ok
        )
        raw = hub.declare_publisher(f"hil/{RIG}/custom/probe", encoding=zenoh.Encoding.TEXT_PLAIN)
        for i in range(20):
            raw.put(f"probe {i}".encode())
        deadline = time.monotonic() + 60  # the recorder wrote the probe, then flushed a chunk
        while time.monotonic() < deadline:
            with lock:
                written = _counters(statuses["recorder"]).get("raw_written", 0)
            if written >= 20:
                break
            time.sleep(0.2)
        size = record.stat().st_size
        while time.monotonic() < deadline and record.stat().st_size == size:
            time.sleep(0.2)
        assert record.stat().st_size > size, "the recorder never flushed the probe"
        with lock:
            out["encodings"] = dict(encodings)
            out["imu_samples"] = [list(x) for x in imu_samples]
            out["bridge"] = _counters(statuses["can_bridge"])
            pid = statuses["recorder"].pid
        os.kill(pid, signal.SIGKILL)  # a real crash of the live recorder, mid-run
        out["killed_size"] = record.stat().st_size
        up.send_signal(signal.SIGTERM)
        out["up_output"] = up.communicate(timeout=120)[0]
        yield out
    finally:
        if up.poll() is None:
            up.kill()
            up.communicate()
        sub.undeclare()
        nav_sub.undeclare()
        imu_sub.undeclare()
        hub.close()


def test_the_docs_example_finds_every_key_and_type_and_decodes_a_solution(live: dict[str, Any]) -> None:
    proc = live["example"]
    assert proc.returncode == 0, proc.stderr
    lines = [ln for ln in proc.stdout.splitlines() if ln.startswith("hil/")]
    table = dict(ln.split(" ", 1) for ln in lines[:-1] if ln.count(" ") == 1)
    assert len(table) > 20, proc.stdout
    assert table[f"hil/{RIG}/nav/ekf15"] == "hil.NavSolution"
    assert table[f"hil/{RIG}/sensor/imu"] == "hil.ImuSample"
    assert table[f"hil/{RIG}/synced/gnss"] == "hil.GnssFix"
    for service in SERVICES:
        assert table[f"hil/{RIG}/status/{service}"] == "hil.ServiceStatus"
    key, encoding, pos = lines[-1].split(" ", 2)
    assert key.startswith(f"hil/{RIG}/nav/") and encoding == "application/json;hil.NavSolution"
    assert len(json.loads(pos)) == 3


def test_every_service_holds_its_liveliness_token_and_types_its_samples(live: dict[str, Any]) -> None:
    assert live["alive"] == sorted(f"hil/{RIG}/@alive/{s}" for s in SERVICES)
    for key, enc in live["encodings"].items():
        assert enc == "application/json;hil.ServiceStatus", (key, enc)


def test_the_bridge_publishes_a_read_windows_imu_samples_as_one_batch_and_loses_none(
    live: dict[str, Any],
) -> None:
    """``hil up``'s default CAN read window (10 ms; straight_level's IMU at 400 Hz: ~4 samples): a
    plain subscriber gets samples batched, every seq once and in order, as the recording has them."""
    got = live["imu_samples"]
    seqs = [q for batch in got for q in batch]
    assert len(seqs) > 500, len(seqs)
    assert max(len(b) for b in got) >= 2, "no sample on sensor/imu was a batch"
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))), "a gap or a reorder on sensor/imu"
    reads = live["bridge"].get("in.can_reads", 0)
    assert reads > 0, live["bridge"]
    scan = Scan(live["record"])
    messages = [m for m in scan if isinstance(m, Message)]  # the channels are known once read
    imu_id = next(c.id for c in scan.channels.values() if c.topic == f"hil/{RIG}/sensor/imu")
    recorded = {json.loads(m.data)["seq"] for m in messages if m.channel_id == imu_id}
    assert set(seqs[: len(seqs) // 2]) <= recorded  # before the kill, everything seen was written


def test_an_unknown_key_is_recorded_raw_and_excluded_keys_are_not(live: dict[str, Any]) -> None:
    scan = Scan(live["record"])
    probe = [m for m in scan if isinstance(m, Message)]
    chans = {c.topic: c for c in scan.channels.values()}
    c = chans[f"hil/{RIG}/custom/probe"]
    assert c.schema_id == 0 and c.metadata.get("hil") == "raw"
    assert c.message_encoding.startswith("text/plain")
    data = [m.data for m in probe if m.channel_id == c.id]
    assert data == [f"probe {i}".encode() for i in range(20)]
    assert not [t for t in chans if "/health/" in t]
    assert f"hil/{RIG}/nav/ekf15" in chans


def test_hil_recover_makes_the_killed_recording_readable_and_says_what_was_lost(live: dict[str, Any]) -> None:
    crashed, fixed = live["record"], live["tmp"] / "fixed.mcap"
    with open(crashed, "rb") as f, pytest.raises(Exception):  # noqa: B017 - whatever mcap raises
        list(make_reader(f).iter_messages())
    proc = run_hil("recover", str(crashed), "-o", str(fixed), timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert "lost: " in proc.stdout and "completeness summary" in proc.stdout
    with open(fixed, "rb") as f:
        reader = make_reader(f)
        got = [(c.topic, m.data) for _s, c, m in reader.iter_messages(log_time_order=False)]
        assert {m.name for m in reader.iter_metadata()} >= {"hil", "config", "recovered"}
        assert {a.name for a in reader.iter_attachments()} >= {"can/imu.dbc"}
    scan = Scan(crashed)
    before = [(scan.channels[m.channel_id].topic, m.data) for m in scan if isinstance(m, Message)]
    assert got == before and len(got) > 1000
    if shutil.which("node") and (MCAPJS / "node_modules").is_dir():
        js = subprocess.run(["node", str(MCAPJS / "read.mjs"), str(fixed)], capture_output=True, text=True)
        assert js.returncode == 0, js.stderr
        assert json.loads(js.stdout)["messages"] == len(got)


@pytest.mark.parametrize("core", ["timesync", "fusion"])
def test_rerun_verifies_the_part_of_the_killed_recording_that_exists(live: dict[str, Any], core: str) -> None:
    proc = run_hil("rerun", str(live["record"]), "--core", core, "--verify", timeout=300)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "truncated" in proc.stdout and "VERIFY OK" in proc.stdout

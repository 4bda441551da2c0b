"""``docker compose up`` for real: build the image, run the whole stack ~30 s, stop, audit the recording.

The image is usually built already by then (``test_image``, beside the live tests; this test is
the last live one, tests/conftest.py): ``_image.ensure`` then finds its layers cached.

No image registry is reachable in CI, so the image is built on a debootstrap base with a host-side
wheelhouse (deploy/build-base-image.sh) and the router runs from the project's image
(docker-compose.local-router.yml); users get python:3.11-slim and the official zenohd. The kernel
has no CAN, so IMU and bridge use the hilzenoh transport (the compose default).
"""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest

from hil.messages import ServiceStatus, decode
from hil.record.mcapio import read_session
from tests.docker import _engine, _image
from tests.docker._recording import CONTRACT_TYPES, audit

pytestmark = [pytest.mark.docker, pytest.mark.slow, pytest.mark.timeout(900)]

RUN_S = float(os.environ.get("HIL_DOCKER_RUN_S", "30"))


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _wait_for_run(port: int, rig: str, timeout_s: float) -> float | None:
    """Seconds until ``world`` announced the run, seen from the host through the published router port."""
    import zenoh

    from hil.bus.session import BusConfig, open_session

    seen = threading.Event()
    t0 = time.monotonic()
    deadline = t0 + timeout_s
    while time.monotonic() < deadline:
        try:
            session = open_session(BusConfig(mode="client", connect=(f"tcp/127.0.0.1:{port}",), listen=()))
            break
        except Exception:
            time.sleep(0.5)
    else:
        return None
    try:

        def on_run(_s: zenoh.Sample) -> None:
            seen.set()

        sub = session.declare_subscriber(f"hil/{rig}/run", on_run)
        ok = seen.wait(max(0.0, deadline - time.monotonic()))
        sub.undeclare()
        return time.monotonic() - t0 if ok else None
    finally:
        session.close()


def test_compose_up_records_the_whole_rig(tmp_path: Path) -> None:
    figures = _image.ensure()
    compose = _engine.compose_cmd()
    assert compose is not None
    project = f"hiltest{os.getpid()}"
    port = _free_port()
    env = _image.build_env(
        COMPOSE_PROJECT_NAME=project,
        HIL_ROUTER_PORT=str(port),
        HIL_RIG="bench",
        HIL_RECORD_FILE="session.mcap",
        HIL_DURATION_S="null",
    )
    dc = [*compose, *_image.COMPOSE_FILES]
    # whether the build stage could compile the fusion's kernels ahead of time (it needs Debian's
    # mirror for a compiler): what the image itself finds, on this machine's CPU
    probe = "from hil.runtime import prebuilt; print(prebuilt.load() is not None)"
    aot = (
        _image.run(
            ["docker", "run", "--rm", "--entrypoint", "/opt/venv/bin/python", _image.IMAGE, "-c", probe],
            env,
            120,
        )
        .stdout.strip()
        .splitlines()[-1]
    )
    try:
        t = time.monotonic()
        _image.run([*dc, "up", "-d", "--no-build", "--pull", "never"], env, timeout=180)
        figures["up_s"] = time.monotonic() - t
        to_run = _wait_for_run(port, "bench", timeout_s=120)
        if to_run is None:
            logs = _image.run([*dc, "logs", "--tail", "20"], env, timeout=60, check=False).stdout
            raise AssertionError(f"world never announced the run within 120 s of up\n{logs[-4000:]}")
        figures["up_to_run_s"] = figures["up_s"] + to_run
        time.sleep(RUN_S)
        ps = _image.run([*dc, "ps", "-a", "--format", "json"], env, timeout=60).stdout
        states = [json.loads(line) for line in ps.splitlines() if line.strip()]
        running = {s["Service"]: s["State"] for s in states}
        assert all(v == "running" for v in running.values()), f"not all running after {RUN_S} s: {running}"
        t = time.monotonic()
        _image.run([*dc, "stop", "--timeout", "90"], env, timeout=300)
        figures["stop_s"] = time.monotonic() - t
        ps = _image.run([*dc, "ps", "-a", "--format", "json"], env, timeout=60).stdout
        exits = {s["Service"]: s["ExitCode"] for s in (json.loads(x) for x in ps.splitlines() if x.strip())}
        assert all(code == 0 for code in exits.values()), f"exit codes after stop: {exits}"
        rec = tmp_path / "session.mcap"
        _image.run(["docker", "cp", f"{project}-recorder-1:/data/session.mcap", str(rec)], env, timeout=120)
        logs = _image.run([*dc, "logs", "--no-color"], env, timeout=60, check=False).stdout
        (tmp_path / "compose.log").write_text(logs)
    finally:
        _image.run([*dc, "down", "-v", "--remove-orphans", "--timeout", "30"], env, timeout=300, check=False)

    info = subprocess.run(
        [sys.executable, "-m", "hil.cli", "info", str(rec), "--no-accuracy"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert info.returncode == 0, info.stderr
    a = audit(rec, validate_max=1000)
    print(f"compose figures: {json.dumps({k: round(v, 1) for k, v in figures.items()})}")
    print(f"recorded {a.total} messages: {dict(a.counts)}")
    print(info.stdout)
    assert a.has_summary, "the recorder did not finalise the MCAP on docker compose stop (no summary)"
    missing = [t for t in CONTRACT_TYPES if a.counts.get(t, 0) == 0]
    assert not missing, f"contract types missing from the recording: {missing}; got {dict(a.counts)}"
    assert not a.invalid, "messages invalid against schemas/:\n" + "\n".join(a.invalid)
    assert not a.gaps, "sequence gaps:\n" + "\n".join(a.gap_lines())
    assert a.counts["hil.ImuSample"] >= 0.8 * 400 * RUN_S, dict(a.counts)
    # the fusion ran compiled kernels, and the ones the image built ahead of time wherever its
    # build stage could make them (here it can: the mirror that made the base image gives it a
    # compiler), instead of numba compiling them beside the running fusion (11 s of a core here)
    fusion = read_session(rec).by_topic("hil/bench/status/fusion")
    last = decode(ServiceStatus, fusion[-1].payload).counter_map()
    print(f"the image holds kernels built ahead of time: {aot}")
    assert last["kernels.compiled"] == 1 and last["kernels.ahead_of_time"] == int(aot == "True"), (aot, last)

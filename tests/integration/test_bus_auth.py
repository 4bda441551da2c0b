"""Only the rig may publish (issue 18.3) and a viewer finds the rig with no environment (19.5).

GIVEN ``hil up`` with no router and no ``HIL_ZENOH_*`` in its environment
WHEN a stranger -- a plain zenoh-python session without the run's credential -- connects to the
hub (the rig's one listener: the services are its clients), subscribes to ``hil/<rig>/**`` and publishes there
THEN it is refused: it receives nothing, and nothing it put is in the recording; while
``hil monitor --rig R`` (no environment) draws the table, a zenoh program opening the endpoint
file ``hil up`` printed receives the rig's data, the files are 0600 in a 0700 directory, and they
are gone when the run ends. The same stranger on a ``--open-bus`` rig receives data: the check
can fail.
"""

from __future__ import annotations

import json
import os
import signal
import stat
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path

import pytest
import zenoh

from hil.bus.endpoint import find_rig, runtime_dir
from hil.record.mcapio import read_session
from tests.conftest import REPO, hil_cmd

pytestmark = pytest.mark.slow


def _clean_env() -> dict[str, str]:
    return {k: v for k, v in os.environ.items() if not k.startswith("HIL_ZENOH") and k != "HIL_RUNTIME_DIR"}


def _listening_ports(pid: int) -> set[int]:
    """TCP ports process ``pid`` listens on (its socket inodes against /proc/net/tcp)."""
    inodes = set()
    for fd in Path(f"/proc/{pid}/fd").iterdir():
        try:
            target = os.readlink(fd)
        except OSError:
            continue
        if target.startswith("socket:["):
            inodes.add(target[8:-1])
    ports = set()
    for table in ("tcp", "tcp6"):
        for row in Path(f"/proc/{pid}/net/{table}").read_text().splitlines()[1:]:
            f = row.split()
            if f[3] == "0A" and f[9] in inodes:  # LISTEN
                ports.add(int(f[1].rsplit(":", 1)[1], 16))
    return ports


def _children(pid: int) -> list[int]:
    text = Path(f"/proc/{pid}/task/{pid}/children").read_text()
    return [int(x) for x in text.split()]


FORGED = b"\x00forged"


class Stranger:
    """A plain zenoh-python peer with no credential, pointed at one endpoint."""

    def __init__(self, endpoint: str, rig: str) -> None:
        self.got: list[str] = []
        c = zenoh.Config()
        c.insert_json5("mode", '"peer"')
        c.insert_json5("scouting/multicast/enabled", "false")
        c.insert_json5("listen/endpoints", "[]")
        c.insert_json5("connect/endpoints", json.dumps([endpoint]))
        self.rig = rig
        self.refused = False
        self.session: zenoh.Session | None = None
        try:
            self.session = zenoh.open(c)
        except zenoh.ZError:
            self.refused = True  # "Unable to connect": the handshake failed
            return
        self.sub = self.session.declare_subscriber(f"hil/{rig}/**", self._on)

    def _on(self, s: zenoh.Sample) -> None:
        payload = s.payload.to_bytes()
        if payload != FORGED and not payload.startswith(b'{"stranger"'):  # not its own (local) puts
            self.got.append(str(s.key_expr))

    def put(self, n: int = 20) -> None:
        if self.session is not None:
            for i in range(n):
                self.session.put(f"hil/{self.rig}/event/stranger", json.dumps({"stranger": i}))
                self.session.put(f"hil/{self.rig}/sensor/gnss", FORGED)

    def peers(self) -> int:
        return 0 if self.session is None else len(list(self.session.info.peers_zid()))

    def close(self) -> None:
        if self.session is not None:
            self.sub.undeclare()
            self.session.close()
            self.session = None


@pytest.fixture
def rig_proc(tmp_path: Path) -> Iterator[tuple[subprocess.Popen[str], str, Path]]:
    procs: list[subprocess.Popen[str]] = []

    def start(rig: str, duration: float, *extra: str) -> subprocess.Popen[str]:
        p = subprocess.Popen(
            hil_cmd("up", "--rig", rig, "--duration", str(duration), "--quiet", "--record",
                    str(tmp_path / f"{rig}.mcap"), *extra),
            cwd=tmp_path, env=_clean_env(), stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True,
            start_new_session=True,
        )  # fmt: skip
        procs.append(p)
        return p

    yield start, tmp_path  # type: ignore[misc]
    for p in procs:
        if p.poll() is None:
            os.killpg(p.pid, signal.SIGKILL)
        p.wait(30)
        if p.stdout:
            p.stdout.close()


def _wait_for_rig(rig: str, proc: subprocess.Popen[str], timeout: float = 120) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        assert proc.poll() is None, proc.communicate()[0][-3000:]
        found, _ = find_rig(rig, _clean_env())
        if found is not None:
            mon = subprocess.run(
                hil_cmd("monitor", "--rig", rig, "--once"),
                cwd=REPO, env=_clean_env(), capture_output=True, text=True, timeout=60,
            )  # fmt: skip
            if mon.returncode == 0 and "running" in mon.stdout:
                return
        time.sleep(1.0)
    raise AssertionError(f"rig {rig} never came up")


def test_a_stranger_cannot_join_the_embedded_rig_but_the_monitor_can(rig_proc) -> None:  # type: ignore[no-untyped-def]
    start, tmp = rig_proc
    rig = f"auth{os.getpid()}"
    proc = start(rig, 40)
    _wait_for_rig(rig, proc)  # `hil monitor --rig R --once` with no environment: exit 0, rows running

    found, why = find_rig(rig, _clean_env())
    assert found is not None, why
    d = runtime_dir(_clean_env())
    assert stat.S_IMODE(d.stat().st_mode) == 0o700 and d.stat().st_uid == os.getuid()
    for p in (found.name_path, found.config_path, found.users_path):
        assert stat.S_IMODE(p.stat().st_mode) == 0o600, p

    # a zenoh program that opens the endpoint file (the documented way) receives the rig's data
    viewer_got: list[str] = []
    viewer = zenoh.open(zenoh.Config.from_file(str(found.name_path)))
    strangers: list[Stranger] = []
    vsub = viewer.declare_subscriber(f"hil/{rig}/**", lambda s: viewer_got.append(str(s.key_expr)))
    try:
        # the hub is the rig's one listener: the services are its clients and open no port a
        # stranger could try instead (they were peers with listeners of their own once)
        children = _children(proc.pid)
        assert len(children) >= 7, children
        service_ports: set[int] = set()
        for child in children:
            service_ports |= _listening_ports(child)
        assert service_ports == set(), service_ports
        ports = {int(found.endpoint.rsplit(":", 1)[1])}
        strangers = [Stranger(f"tcp/127.0.0.1:{port}", rig) for port in sorted(ports)]
        time.sleep(2.0)
        for s in strangers:
            s.put()
        time.sleep(3.0)
        assert len(viewer_got) > 100, len(viewer_got)
        for s, port in zip(strangers, sorted(ports), strict=True):
            assert s.refused or s.peers() == 0, port
            assert s.got == [], (port, s.got[:5])
    finally:
        for s in strangers:
            s.close()
        vsub.undeclare()
        viewer.close()
    proc.send_signal(signal.SIGINT)  # done: stop it as a user would (Ctrl-C), not at --duration
    out, _ = proc.communicate(timeout=180)
    assert proc.returncode == 0, out[-3000:]
    assert f"hil monitor --rig {rig}" in out and found.endpoint in out  # it printed its endpoint
    for p in (found.name_path, found.config_path, found.users_path):
        assert not p.exists(), p  # removed at exit
    recorded = {r.topic for r in read_session(tmp / f"{rig}.mcap").records}
    assert f"hil/{rig}/event/stranger" not in recorded
    assert f"hil/{rig}/sensor/gnss" in recorded  # the rig's own fixes are there


def test_the_same_stranger_joins_an_open_bus(rig_proc) -> None:  # type: ignore[no-untyped-def]
    start, _tmp = rig_proc
    rig = f"open{os.getpid()}"
    proc = start(rig, 20, "--open-bus")
    _wait_for_rig(rig, proc)
    found, why = find_rig(rig, _clean_env())
    assert found is not None and not found.authenticated, why
    assert not found.users_path.exists()
    s = Stranger(found.endpoint, rig)
    try:
        deadline = time.monotonic() + 20
        while len(s.got) < 50 and time.monotonic() < deadline:
            time.sleep(0.2)
        assert len(s.got) >= 50, s.got[:5]
    finally:
        s.close()
    proc.send_signal(signal.SIGINT)  # done: stop it as a user would (Ctrl-C), not at --duration
    out, _ = proc.communicate(timeout=180)
    assert proc.returncode == 0, out[-3000:]
    assert "OPEN" in out


def test_endpoint_files_refuse_a_directory_others_can_read(tmp_path: Path) -> None:
    from hil.bus.session import BusConfigError

    d = tmp_path / "rt"
    d.mkdir(mode=0o755)
    d.chmod(0o755)
    with pytest.raises(BusConfigError, match="not a private directory"):
        runtime_dir({"HIL_RUNTIME_DIR": str(d)})
    found, why = find_rig("bench", {"HIL_RUNTIME_DIR": str(d)})
    assert found is None and "not a private directory" in why

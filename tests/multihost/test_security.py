"""The secure router profile (deploy/zenoh/router-secure.json5): mutual TLS + access control.

Certificates are made with openssl at test time (throwaway, in tmp), one per role (its CN). Each
role publishes its own keys into the rig and nothing else (only the GNSS emulator on
sensor/gnss, only timesync on synced/*, only fusion on nav/<estimator>, ...); a monitor only
reads; a client without a certificate, with one from another CA, or over plain TCP cannot join.
"""

from __future__ import annotations

import json
import shutil
import socket
import subprocess
import sys
import threading
import time
from pathlib import Path
from typing import Any

import pytest

from tests.docker import _engine

pytestmark = [pytest.mark.docker, pytest.mark.timeout(180)]

REPO = Path(__file__).resolve().parents[2]
KEY = "hil/bench/truth"
ROLES = ("world", "imu-emulator", "can-bridge", "gnss-emulator", "timesync", "fusion", "recorder")
ROLES += ("operator", "monitor")


def _ssl(*args: str, cwd: Path) -> None:
    r = subprocess.run(["openssl", *args], cwd=cwd, capture_output=True, text=True, timeout=60)
    assert r.returncode == 0, r.stderr


def _ca(d: Path, name: str) -> None:
    _ssl("req", "-x509", "-newkey", "rsa:2048", "-nodes", "-days", "2", "-subj", f"/CN={name}",
         "-keyout", f"{name}.key", "-out", f"{name}.pem", cwd=d)  # fmt: skip


def _leaf(d: Path, name: str, cn: str, ca: str, san: str) -> None:
    (d / f"{name}.ext").write_text(f"subjectAltName={san}\nextendedKeyUsage=serverAuth,clientAuth\n")
    _ssl("req", "-newkey", "rsa:2048", "-nodes", "-subj", f"/CN={cn}", "-keyout", f"{name}.key",
         "-out", f"{name}.csr", cwd=d)  # fmt: skip
    _ssl("x509", "-req", "-in", f"{name}.csr", "-CA", f"{ca}.pem", "-CAkey", f"{ca}.key", "-CAcreateserial",
         "-days", "2", "-extfile", f"{name}.ext", "-out", f"{name}.pem", cwd=d)  # fmt: skip


@pytest.fixture(scope="module")
def pki(tmp_path_factory: pytest.TempPathFactory) -> Path:
    if shutil.which("openssl") is None:
        _engine.unavailable("openssl is not installed")
    d = tmp_path_factory.mktemp("tls")
    _ca(d, "ca")
    _ca(d, "rogue-ca")
    _leaf(d, "router", "router", "ca", "DNS:localhost,IP:127.0.0.1")
    for role in ROLES:
        _leaf(d, role, f"hil-{role}", "ca", f"DNS:hil-{role}")
    _leaf(d, "stranger", "hil-stranger", "ca", "DNS:hil-stranger")  # the rig's CA, no role
    _leaf(d, "rogue", "hil-gnss-emulator", "rogue-ca", "DNS:hil-gnss-emulator")
    return d


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


@pytest.fixture(scope="module")
def secure_router(pki: Path) -> tuple[int, Path]:
    text = (REPO / "deploy/zenoh/router-secure.json5").read_text().replace("/etc/hil/tls/", f"{pki}/")
    conf = pki / "router-secure.json5"
    conf.write_text(text)
    port = _free_port()
    log = open(pki / "router.log", "wb")  # noqa: SIM115
    proc = subprocess.Popen(
        [
            sys.executable,
            "-m",
            "hil.cli",
            "router",
            "--config",
            str(conf),
            "--listen",
            f"tls/127.0.0.1:{port}",
        ],
        stdout=log,
        stderr=subprocess.STDOUT,
        cwd=REPO,
    )
    deadline = time.monotonic() + 30
    while time.monotonic() < deadline:
        with socket.socket() as s:
            if s.connect_ex(("127.0.0.1", port)) == 0:
                break
        assert proc.poll() is None, (pki / "router.log").read_text()
        time.sleep(0.2)
    yield port, pki
    proc.terminate()
    proc.wait(10)
    log.close()


def _open(port: int, pki: Path, cert: str | None, ca: str = "ca", proto: str = "tls") -> Any:
    import zenoh

    c = zenoh.Config()
    c.insert_json5("mode", '"client"')
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("connect/endpoints", json.dumps([f"{proto}/localhost:{port}"]))
    if proto == "tls":
        c.insert_json5("transport/link/tls/root_ca_certificate", json.dumps(str(pki / f"{ca}.pem")))
        if cert:
            c.insert_json5("transport/link/tls/connect_private_key", json.dumps(str(pki / f"{cert}.key")))
            c.insert_json5("transport/link/tls/connect_certificate", json.dumps(str(pki / f"{cert}.pem")))
            c.insert_json5("transport/link/tls/enable_mtls", "true")
    return zenoh.open(c)


def _delivered(port: int, pki: Path, publisher: str, n: int = 20, key: str = KEY) -> int:
    """How many of ``n`` puts by ``publisher`` on ``key`` reach a rig service subscribed to it."""
    got: list[bytes] = []
    done = threading.Event()
    sub_s = _open(port, pki, "recorder")
    sub = sub_s.declare_subscriber(key, lambda s: (got.append(s.payload.to_bytes()), done.set()))
    pub_s = _open(port, pki, publisher)
    try:
        time.sleep(1.0)  # declarations propagate through the router
        for i in range(n):
            pub_s.put(key, json.dumps({"seq": i}))
            time.sleep(0.02)
        done.wait(2.0)
        time.sleep(0.5)
        return len(got)
    finally:
        sub.undeclare()
        pub_s.close()
        sub_s.close()


def test_rig_service_publishes_into_the_rig(secure_router: tuple[int, Path]) -> None:
    port, pki = secure_router
    assert _delivered(port, pki, "world") == 20


def test_certificate_outside_the_acl_cannot_publish(secure_router: tuple[int, Path]) -> None:
    port, pki = secure_router
    assert _delivered(port, pki, "monitor") == 0
    assert _delivered(port, pki, "stranger") == 0


# (role, key under hil/bench/, allowed): each role its own keys, and a neighbour's refused
ROLE_KEYS = [
    ("gnss-emulator", "sensor/gnss", True),
    ("imu-emulator", "sensor/gnss", False),
    ("timesync", "sensor/gnss", False),
    ("timesync", "synced/gnss", True),
    ("gnss-emulator", "synced/gnss", False),
    ("can-bridge", "sensor/imu", True),
    ("gnss-emulator", "sensor/imu", False),
    ("fusion", "nav/ekf15", True),
    ("gnss-emulator", "nav/ekf15", False),
    ("can-bridge", "nav/dut_navbox", True),
    ("can-bridge", "nav/ekf15", False),
    ("fusion", "nav/dut_navbox", False),
    ("recorder", "truth", False),
    ("recorder", "status/recorder", True),
    ("recorder", "status/fusion", False),
    ("operator", "control/fault", True),
    ("world", "control/fault", False),
]


@pytest.fixture(scope="module")
def role_deliveries(secure_router: tuple[int, Path]) -> dict[tuple[str, str], int]:
    """Every (role, key) of ``ROLE_KEYS`` tried at once: how many of its 20 puts reach a rig
    service subscribed to the key. One session per role and one subscriber per key, each put
    saying who sent it, so that the cases share one wait for the declarations and one for the
    deliveries (one at a time, they took ~50 s of the suite)."""
    port, pki = secure_router
    n = 20
    got: dict[tuple[str, str], int] = {case[:2]: 0 for case in ROLE_KEYS}
    lock = threading.Lock()
    expected = n * sum(1 for *_, allowed in ROLE_KEYS if allowed)
    done = threading.Event()

    def count(key: str, payload: bytes) -> None:
        by = json.loads(payload)["by"]
        with lock:
            got[(by, key)] = got.get((by, key), 0) + 1
            if sum(got.values()) >= expected:
                done.set()

    sessions: list[Any] = []
    subs: list[Any] = []
    try:
        sub_s = _open(port, pki, "recorder")
        sessions.append(sub_s)
        for key in dict.fromkeys(k for _, k, _ in ROLE_KEYS):
            subs.append(
                sub_s.declare_subscriber(
                    f"hil/bench/{key}", lambda s, key=key: count(key, s.payload.to_bytes())
                )
            )
        pubs = {role: _open(port, pki, role) for role in dict.fromkeys(r for r, _, _ in ROLE_KEYS)}
        sessions += pubs.values()
        time.sleep(1.0)  # declarations propagate through the router
        for i in range(n):
            for role, key, _ in ROLE_KEYS:
                pubs[role].put(f"hil/bench/{key}", json.dumps({"seq": i, "by": role}))
            time.sleep(0.02)
        done.wait(5.0)
        time.sleep(0.5)  # a refused put that was going to arrive after all: counted
        with lock:
            return dict(got)
    finally:
        for sub in subs:
            sub.undeclare()
        for session in sessions:
            session.close()


@pytest.mark.parametrize(("role", "key", "allowed"), ROLE_KEYS, ids=[f"{r}:{k}" for r, k, _ in ROLE_KEYS])
def test_each_role_publishes_only_its_own_keys(
    role_deliveries: dict[tuple[str, str], int], role: str, key: str, allowed: bool
) -> None:
    assert role_deliveries[(role, key)] == (20 if allowed else 0), role_deliveries


def test_monitor_may_observe_but_not_publish(secure_router: tuple[int, Path]) -> None:
    port, pki = secure_router
    got: list[bytes] = []
    mon = _open(port, pki, "monitor")
    sub = mon.declare_subscriber(KEY, lambda s: got.append(s.payload.to_bytes()))
    svc = _open(port, pki, "world")
    try:
        time.sleep(1.0)
        for i in range(10):
            svc.put(KEY, json.dumps({"seq": i}))
            time.sleep(0.02)
        time.sleep(1.0)
    finally:
        sub.undeclare()
        svc.close()
        mon.close()
    assert len(got) == 10


@pytest.mark.parametrize(
    ("cert", "ca", "proto", "why"),
    [
        (None, "ca", "tls", "no client certificate"),
        ("rogue", "ca", "tls", "certificate from another CA"),
        (None, "ca", "tcp", "plain TCP"),
    ],
)
def test_client_without_a_rig_certificate_cannot_join(
    secure_router: tuple[int, Path], cert: str | None, ca: str, proto: str, why: str
) -> None:
    port, pki = secure_router
    try:
        s = _open(port, pki, cert, ca=ca, proto=proto)
    except Exception:
        return  # refused at the handshake: the expected outcome
    try:
        assert not list(s.info.routers_zid()), f"{why}: the router accepted the session"
    finally:
        s.close()

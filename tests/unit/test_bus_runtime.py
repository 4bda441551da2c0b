"""The rig's Zenoh runtime sizing (``hil.bus.session.RIG_ZENOH_RUNTIME``).

Zenoh parses ``ZENOH_RUNTIME`` (RON) when a process opens its first session and panics on a
malformed one, so the rig's own string is checked by a real session in a fresh interpreter, with
traffic over a loopback link: it must open, carry messages, and run on the threads it names.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys

from hil.bus.session import RIG_ZENOH_RUNTIME, ZENOH_RUNTIME_ENV, use_rig_runtime
from tests.conftest import REPO

_SESSION = """
import collections, json, os, socket, threading, time
import zenoh
def conf(listen, connect):
    c = zenoh.Config()
    c.insert_json5("scouting/multicast/enabled", "false")
    c.insert_json5("listen/endpoints", json.dumps(listen))
    c.insert_json5("connect/endpoints", json.dumps(connect))
    return c
with socket.socket() as probe:
    probe.bind(("127.0.0.1", 0))
    port = probe.getsockname()[1]
a = zenoh.open(conf([f"tcp/127.0.0.1:{port}"], []))
got = threading.Event()
seen = []
sub = a.declare_subscriber("t/**", lambda s: (seen.append(s.payload.to_bytes()), got.set()))
b = zenoh.open(conf([], [f"tcp/127.0.0.1:{port}"]))
deadline = time.monotonic() + 30
while not got.is_set() and time.monotonic() < deadline:
    b.put("t/x", b"hello")
    got.wait(0.2)
names = collections.Counter(
    open(f"/proc/self/task/{t}/comm").read().strip().split("-")[0] for t in os.listdir("/proc/self/task")
)
print(json.dumps({"seen": len(seen), "links": len(list(b.info.links())), "threads": names}))
b.close()
a.close()
"""


def _run(env: dict[str, str]) -> dict[str, object]:
    out = subprocess.run(
        [sys.executable, "-c", _SESSION], cwd=REPO, env=env, capture_output=True, text=True, timeout=120
    )
    assert out.returncode == 0, out.stderr[-2000:]
    return json.loads(out.stdout.strip().splitlines()[-1])


def test_zenoh_takes_the_rigs_runtime_string_and_runs_on_the_threads_it_names() -> None:
    env = {k: v for k, v in os.environ.items() if k != ZENOH_RUNTIME_ENV}
    use_rig_runtime(env)
    assert env[ZENOH_RUNTIME_ENV] == RIG_ZENOH_RUNTIME
    res = _run(env)
    threads = res["threads"]
    assert isinstance(threads, dict) and res["seen"] and res["links"] == 1, res  # a real link carried it
    # rx, accept and net are handed over to the one app worker: none of their own threads
    assert {"rx", "acc", "net"}.isdisjoint(threads), threads
    assert threads.get("app", 0) >= 1, threads


def test_a_users_zenoh_runtime_wins() -> None:
    env = {ZENOH_RUNTIME_ENV: "(app: (worker_threads: 2))"}
    use_rig_runtime(env)
    assert env[ZENOH_RUNTIME_ENV] == "(app: (worker_threads: 2))"


_UP_ENV = """
import json, os, sys
from hil.runtime import supervisor
seen = {}
def run(self):
    seen["hub"] = os.environ.get("ZENOH_RUNTIME")
    seen["child"] = self._child_env().get("ZENOH_RUNTIME")
    return 0
supervisor.Supervisor.run = run
from hil.cli import main
main(["up", "--quiet", "--duration", "1", "--record", sys.argv[1], "--rig", "rt"])
print(json.dumps(seen))
"""


def test_hil_ups_hub_keeps_zenohs_defaults_and_its_services_get_the_rigs(tmp_path) -> None:
    """The hub routes every message of the rig: on one worker it dropped a quarter of the traffic
    at 2 kHz with CAN FD (hil/bus/session.py)."""
    env = {k: v for k, v in os.environ.items() if k != ZENOH_RUNTIME_ENV}
    out = subprocess.run(
        [sys.executable, "-c", _UP_ENV, str(tmp_path / "x.mcap")],
        cwd=REPO,
        env=env,
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert out.returncode == 0, out.stderr[-2000:]
    seen = json.loads(out.stdout.strip().splitlines()[-1])
    assert seen == {"hub": None, "child": RIG_ZENOH_RUNTIME}

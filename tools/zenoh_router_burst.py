"""A sustained burst through a Zenoh router into a real recorder: is anything lost?

    .venv/bin/python tools/zenoh_router_burst.py --publishers miss --per-key 30000 --processes 3

Starts ``hil router`` on a loopback port, a recorder process (``hil service recorder``, client of
the router) and ``--processes`` publisher processes (clients too), each putting ``--per-key``
``hil.CaptureTruth`` messages on three keys as fast as Zenoh takes them (reliable, blocking).
``--publishers miss`` declares them as the rig does (advanced, sample-miss detection, cache);
``plain`` as plain Zenoh publishers. ``--recorder plain`` gives the recorder a plain subscriber.
Each publisher stays ``--linger`` seconds after its last put; ``--wait`` seconds after they
left, the recorder is stopped and its file's completeness is printed as one
JSON line: expected, recorded, missing (seq gaps), zenoh_missed, zenoh_unsequenced.

Why through a router: a router timestamps samples that carry none, and zenoh-ext's advanced
subscriber delivers the samples of one timestamp source in increasing order only, dropping the
rest silently; samples from plain publishers on several links interleave there (see
``hil/bus/pubsub.py``). Sample-miss-detecting publishers number their samples, which the
subscriber orders per publisher instead.
"""

from __future__ import annotations

import argparse
import json
import os
import signal
import subprocess
import sys
import tempfile
import time
from pathlib import Path

RIG = "burst"

PUBLISHER = """
import sys, time
from hil.bus.keys import Keys
from hil.bus.pubsub import Publisher
from hil.bus.session import BusConfig, open_session
from hil.messages import CaptureTruth, RunInfo
endpoint, proc, n = sys.argv[1], int(sys.argv[2]), int(sys.argv[3])
miss, linger = sys.argv[4] == "miss", float(sys.argv[5])
k = Keys("burst")
s = open_session(BusConfig(mode="client", connect=(endpoint,), listen=()))
pubs = [Publisher(s, k.capture(f"p{proc}_{j}"), CaptureTruth, miss_detection=miss) for j in range(3)]
run = Publisher(s, k.run(), RunInfo, miss_detection=miss) if proc == 0 else None
time.sleep(1.5)
if run is not None:
    run.put(RunInfo(seq=0, stamp_ns=0, rig="burst", start_epoch_ns=time.time_ns(), speed=1.0,
        scenario="straight_level", scenario_sha256="0" * 64, seed=1, duration_s=1.0,
        origin_lat_deg=50.0, origin_lon_deg=30.0, origin_alt_m=100.0))
t0 = time.monotonic()
for i in range(n):
    for p in pubs:
        p.put(CaptureTruth(seq=i, stamp_ns=i * 2_500_000, sensor="imu", true_stamp_ns=i * 2_500_000 + 17))
print(f"publisher {proc}: {3 * n} messages in {time.monotonic() - t0:.2f} s", flush=True)
# Linger: a put returns once the sample is queued, and behind a slow consumer (blocking
# congestion control) thousands can still be queued here; closing the session drops them, and the
# heartbeat that would have announced them with them, so nobody could tell (seen: 831 lost with
# a 2 s linger under load). Live, heartbeats and recovery queries are answered too.
time.sleep(linger)
s.close()
"""


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--port", type=int, default=17990)
    ap.add_argument("--publishers", choices=["miss", "plain"], default="miss")
    ap.add_argument("--recorder", choices=["advanced", "plain"], default="advanced")
    ap.add_argument("--per-key", type=int, default=30_000)
    ap.add_argument("--processes", type=int, default=3)
    ap.add_argument("--wait", type=float, default=3.0, help="seconds after the publishers left, then stop")
    ap.add_argument("--linger", type=float, default=10.0, help="seconds a publisher stays after its last put")
    a = ap.parse_args()
    endpoint = f"tcp/127.0.0.1:{a.port}"
    tmp = Path(tempfile.mkdtemp(prefix="hil-burst-"))
    hil = [sys.executable, "-m", "hil.cli"]
    env = dict(os.environ, HIL_ZENOH_MODE="client", HIL_ZENOH_CONNECT=endpoint)
    env.pop("HIL_ZENOH_LISTEN", None)
    router = subprocess.Popen([*hil, "router", "--listen", endpoint], stdout=subprocess.DEVNULL)
    rec: subprocess.Popen[bytes] | None = None
    try:
        time.sleep(2.0)
        opts = {"path": str(tmp / "burst.mcap"), "drain_s": 1.0, "zenoh_advanced": a.recorder == "advanced"}
        rec = subprocess.Popen(
            [*hil, "service", "recorder", "--rig", RIG, "--options", json.dumps(opts)], env=env
        )
        time.sleep(4.0)
        args = [str(a.per_key), a.publishers, str(a.linger)]
        pubs = [
            subprocess.Popen([sys.executable, "-c", PUBLISHER, endpoint, str(i), *args], env=env)
            for i in range(a.processes)
        ]
        for p in pubs:
            p.wait()
        time.sleep(a.wait)
    finally:
        if rec is not None:
            rec.send_signal(signal.SIGTERM)
            rec.wait(120)
        router.send_signal(signal.SIGTERM)
        router.wait(30)
    from hil.record.mcapio import read_session

    s = read_session(tmp / "burst.mcap")
    comp = s.metadata.get("completeness", {})
    sys.stdout.write(
        json.dumps(
            {
                "publishers": a.publishers,
                "recorder": a.recorder,
                "expected": 3 * a.per_key * a.processes,
                "recorded": sum(1 for r in s.records if f"hil/{RIG}/capture/" in r.topic),
                "missing": json.loads(comp.get("missing", "-1")),
                "zenoh_missed": json.loads(comp.get("zenoh_missed", "-1")),
                "zenoh_unsequenced": json.loads(comp.get("zenoh_unsequenced", "-1")),
                "replay_ready": json.loads(comp.get("replay_ready", "false")),
            }
        )
        + "\n"
    )
    return 0


if __name__ == "__main__":
    sys.exit(main())

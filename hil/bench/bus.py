"""``hil bench bus``: what the rig's bus layers cost per message, against raw zenoh-python.

Two real OS processes on a loopback hub, as ``hil up`` runs its services: a sender puts
``--messages`` messages (flooded, or paced at ``--rate``), a receiver takes them. Each process
measures its own CPU time (all its threads: Zenoh's Rust runtime included) over the traffic, so
a figure is **µs of CPU per message** on each side -- robust on a loaded machine, where wall time
is mostly waiting for a core -- and the receiver's throughput. Every case runs in the same
session, alternating over ``--repeat`` rounds, and is stated as a ratio to the raw zenoh-python
pair of the same round:

- ``raw``: ``session.declare_publisher(key).put(bytes)`` and a callback that counts;
- ``raw express``: the same with ``express=True`` (no batching: one network write per message);
- ``typed``: ``hil.bus.pubsub.Publisher.put(msg)`` (JSON encode, advanced publisher with miss
  detection, rate meter) and a ``DispatchSubscriber`` (decode + validate into the type, counters)
  -- what every service's outputs and inputs go through;
- ``hilzenoh``: ``can.Bus(interface="hilzenoh")``: ``send(can.Message)`` and ``recv()`` of classic
  8-byte frames; ``hilzenoh burst``: each ``--burst`` of frames as one Zenoh message
  (``send_burst_stamped``, each frame with its wire stamp) -- the IMU emulator's and the CAN
  bridge's path (one sample's four classic frames); ``hilzenoh fd``: 64-byte FD frames.
  A hilzenoh figure is per frame.
- ``hillocal``, ``hillocal burst``, ``hillocal fd``: the same on the rig's local CAN sockets
  (:mod:`hil.can.local_bus`, what ``hil up`` on one machine uses), in a private directory the
  bench makes; no Zenoh and no hub in the path.

The payload of ``raw`` and ``typed`` is a real ``ImuSample`` (~260 bytes of JSON).
"""

from __future__ import annotations

import argparse
import json
import os
import subprocess
import sys
import tempfile
import threading
import time
from typing import Any

from hil.bench import command_line, tree_revision, write_section
from hil.bus.session import BusConfig, open_session
from hil.runtime.supervisor import free_port

KEY = "hil/benchbus/sensor/imu"
CASES = (
    "raw",
    "raw express",
    "raw direct",
    "typed",
    "hilzenoh",
    "hilzenoh burst",
    "hilzenoh fd",
    "hillocal",
    "hillocal burst",
    "hillocal fd",
)
IDLE_END_S = 3.0  # the receiver stops this long after its last message


def _sample_msg(i: int) -> Any:
    from hil.messages import ImuSample

    t = i * 2_500_000
    return ImuSample(
        seq=i,
        stamp_ns=t + 135_000,
        device_stamp_ns=t + 17,
        rx_stamp_ns=t + 135_000,
        dt_ns=2_500_000,
        dtheta_b_rad=[1.2345e-5 * (i % 97), -2.5e-6, 3.75e-6],
        dvel_b_mps=[0.0123, -0.0021, -0.024525],
    )


def _session(endpoint: str) -> Any:
    return open_session(BusConfig(mode="peer", connect=(endpoint,), listen=("tcp/127.0.0.1:0",)))


# -- the child processes ----------------------------------------------------------------------
def _receiver(case: str, endpoint: str, n: int) -> dict[str, Any]:
    import can
    import zenoh

    from hil.bus.pubsub import DispatchSubscriber, Stats
    from hil.messages import ImuSample

    session = _session(endpoint)
    state = {"n": 0, "cpu0": 0.0, "t_first": 0.0, "t_last": 0.0, "cpu_last": 0.0}
    arrivals: list[float] = []
    done = threading.Event()

    def seen(stamp: float | None = None) -> None:
        arrivals.append(time.time() if stamp is None else stamp)
        state["n"] += 1
        if state["n"] == 1:
            state["cpu0"] = time.process_time()
            state["t_first"] = time.time()
        if state["n"] >= n:
            state["t_last"] = time.time()
            state["cpu_last"] = time.process_time()
            done.set()

    closer: Any
    if case == "raw direct":
        closer = session.declare_subscriber(KEY, zenoh.handlers.Callback(lambda _s: seen(), indirect=False))
    elif case.startswith("raw"):
        closer = session.declare_subscriber(KEY, lambda _s: seen())
    elif case == "typed":
        closer = DispatchSubscriber(session, KEY, {"sensor": (ImuSample, lambda _m, _k: seen())}, Stats())
    else:
        bus = _can_bus(case, session)
        stated = case.endswith("burst")

        def pump() -> None:
            while not done.is_set():
                frame = bus.recv(timeout=0.2)
                if frame is not None:
                    # the bus's receive stamp: what a reader gets; a burst's frames carry their
                    # sender-stated wire times, so there the arrival is the latency's end
                    seen(None if stated else frame.timestamp)

        t = threading.Thread(target=pump, daemon=True)
        t.start()
        closer = bus
    _ = zenoh  # the session's module, kept imported for the callback threads
    print("ready", flush=True)
    deadline = time.monotonic() + 900
    while not done.wait(0.2):
        if _idle_for(state) > IDLE_END_S or time.monotonic() > deadline:
            break
    if not done.is_set():
        state["t_last"] = time.time()
        state["cpu_last"] = time.process_time()
    if isinstance(closer, can.BusABC):
        closer.shutdown()
    else:
        closer.undeclare()
    session.close()
    return {
        "received": state["n"],
        "cpu_s": state["cpu_last"] - state["cpu0"],
        "t_first": state["t_first"],
        "t_last": state["t_last"],
        "arrivals": arrivals,
    }


def _can_bus(case: str, session: Any) -> Any:
    """The case's python-can bus: hilzenoh on the bench's session, or hillocal in the bench's
    directory (``HIL_CAN_DIR``, set by :func:`run_case`)."""
    import can

    if case.startswith("hillocal"):
        return can.Bus(interface="hillocal", channel="vcan0", fd=True)
    return can.Bus(interface="hilzenoh", channel="vcan0", rig="benchbus", fd=True, session=session)


def _idle_for(state: dict[str, float]) -> float:
    """Seconds since the receiver's count last moved (tracked on the 0.2 s poll)."""
    now = time.time()
    if state.get("_n_prev") != state["n"]:
        state["_n_prev"] = state["n"]
        state["_t_move"] = now
    return now - state.get("_t_move", now) if state["n"] else 0.0


def _sender(case: str, endpoint: str, n: int, rate: float, burst: int) -> dict[str, Any]:
    import can
    import zenoh

    from hil.bus.pubsub import Publisher, Stats
    from hil.messages import ImuSample, encode

    session = _session(endpoint)
    msgs = [_sample_msg(i) for i in range(min(n, 1000))]
    send: Any
    bus: Any = None
    if case.startswith("raw"):
        pub = session.declare_publisher(
            KEY,
            reliability=zenoh.Reliability.RELIABLE,
            congestion_control=zenoh.CongestionControl.BLOCK,
            express=case == "raw express",
        )
        payloads = [encode(m) for m in msgs]
        send = lambda i: pub.put(payloads[i % len(payloads)])  # noqa: E731
    elif case == "typed":
        tpub = Publisher(session, KEY, ImuSample, Stats())
        send = lambda i: tpub.put(msgs[i % len(msgs)])  # noqa: E731
    else:
        fd = case.endswith(" fd")
        bus = _can_bus(case, session)
        frames = [
            can.Message(
                arbitration_id=0x180 + (i % 4),
                is_extended_id=False,
                is_fd=fd,
                bitrate_switch=fd,
                data=bytes((i + j) & 0xFF for j in range(64 if fd else 8)),
            )
            for i in range(64)
        ]
        if case.endswith("burst"):
            step = max(1, burst)

            def send(i: int) -> None:
                if i % step == 0:
                    group = [frames[(i + j) % len(frames)] for j in range(min(step, n - i))]
                    now = time.time_ns()
                    bus.send_burst_stamped(
                        group, [now - 135_000 * (len(group) - 1 - j) for j in range(len(group))]
                    )

        else:
            send = lambda i: bus.send(frames[i % len(frames)])  # noqa: E731
    print("ready", flush=True)
    sys.stdin.readline()  # "go": the receiver has matched
    period = burst / rate if rate > 0 else 0.0
    t0 = time.time()
    cpu0 = time.process_time()
    t_next = time.monotonic()
    sent = [0.0] * n
    for i in range(n):
        if period and i % burst == 0:
            t_next += period
            delay = t_next - time.monotonic()
            if delay > 0:
                time.sleep(delay)
        sent[i] = time.time()
        send(i)
    t_put = time.time()
    time.sleep(0.5)  # non-express puts leave on Zenoh's tx thread: its CPU is the sender's too
    cpu = time.process_time() - cpu0 - _idle_cpu(0.5)
    if bus is not None:
        bus.shutdown()
    session.close()
    return {"sent": n, "cpu_s": cpu, "t0": t0, "t_put": t_put, "sent_at": sent}


def _idle_cpu(_seconds: float) -> float:
    """The idle session's own CPU over a pause is below a millisecond: not subtracted."""
    return 0.0


def _child_main(argv: list[str]) -> int:
    role, case, endpoint, n, rate, burst = argv
    import hil

    print(f"bench child {role} {case}: hil from {os.path.dirname(hil.__file__)}", file=sys.stderr)
    if role == "rx":
        out = _receiver(case, endpoint, int(n))
    else:
        out = _sender(case, endpoint, int(n), float(rate), int(burst))
    print(json.dumps(out), flush=True)
    return 0


# -- the parent ---------------------------------------------------------------------------------
def _spawn(args: list[str], env: dict[str, str], tree: str) -> subprocess.Popen[str]:
    """A child running this file's code with ``tree``'s ``hil`` (an older checkout has no
    ``hil.bench.bus``; ``-m`` would import this checkout's ``hil`` from the current directory)."""
    me = os.path.abspath(__file__)
    run = f"import runpy, sys; sys.argv[1:1] = ['--_child']; runpy.run_path({me!r}, run_name='__main__')"
    p = subprocess.Popen(
        [sys.executable, "-c", run, *args],
        cwd=tree,
        stdin=subprocess.PIPE,
        stdout=subprocess.PIPE,
        text=True,
        env=env,
    )
    assert p.stdout is not None
    line = p.stdout.readline().strip()
    if line != "ready":
        p.kill()
        raise RuntimeError(f"bench child {args[:2]} did not start: {line!r}")
    return p


def run_case(
    case: str, endpoint: str, n: int, rate: float, burst: int, tree: str | None = None
) -> dict[str, float]:
    """One sender and one receiver process for ``case``; CPU per message on each side.

    ``tree``: run both children from that checkout of hil (``--versus``) instead of this one."""
    env = {k: v for k, v in os.environ.items() if not k.startswith("HIL_ZENOH")}
    tree = os.path.abspath(tree or os.getcwd())
    env["PYTHONPATH"] = tree
    can_dir = tempfile.mkdtemp(prefix="hil-benchbus-")  # 0700: the hillocal cases' directory
    env["HIL_CAN_DIR"] = can_dir
    try:
        rx = _spawn(["rx", case, endpoint, str(n), "0", "1"], env, tree)
        tx = _spawn(["tx", case, endpoint, str(n), str(rate), str(burst)], env, tree)
        time.sleep(1.0)  # the peers find each other
        assert tx.stdin is not None
        tx.stdin.write("go\n")
        tx.stdin.flush()
        tx_out, _ = tx.communicate(timeout=900)
        rx_out, _ = rx.communicate(timeout=900)
    finally:
        from hil.can.local_bus import remove_can_dir

        remove_can_dir(can_dir)
    t = json.loads(tx_out.strip().splitlines()[-1])
    r = json.loads(rx_out.strip().splitlines()[-1])
    got = r["received"]
    pairs = zip(r["arrivals"], t["sent_at"], strict=False)  # in order; a lost tail is left out
    lat = sorted(1e3 * (a - b) for a, b in pairs)
    return {
        "tx_us": 1e6 * t["cpu_s"] / n,
        "rx_us": 1e6 * r["cpu_s"] / max(1, got - 1),
        "rate": got / max(1e-9, r["t_last"] - t["t0"]),
        "lost": n - got,
        "lat_p50_ms": lat[len(lat) // 2] if lat else float("nan"),
        "lat_p99_ms": lat[min(len(lat) - 1, int(0.99 * len(lat)))] if lat else float("nan"),
    }


def _fmt_table(results: dict[str, list[dict[str, float]]]) -> list[str]:
    raw = results["raw"]
    lines = [
        "| case | sender µs CPU/msg | receiver µs CPU/msg | both | × raw | throughput msg/s | × raw "
        "| latency p50 / p99 ms | lost |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for case, runs in results.items():
        tx = _mean([r["tx_us"] for r in runs])
        rx = _mean([r["rx_us"] for r in runs])
        # ratios pair each round with the raw case of the same round, then average
        cpu_x = _mean(
            [(r["tx_us"] + r["rx_us"]) / (b["tx_us"] + b["rx_us"]) for r, b in zip(runs, raw, strict=True)]
        )
        rate_x = _mean([r["rate"] / b["rate"] for r, b in zip(runs, raw, strict=True)])
        rate = _mean([r["rate"] for r in runs])
        lost = sum(int(r["lost"]) for r in runs)
        p50 = _mean([r["lat_p50_ms"] for r in runs])
        p99 = _mean([r["lat_p99_ms"] for r in runs])
        lines.append(
            f"| {case} | {tx:.1f} | {rx:.1f} | {tx + rx:.1f} | {cpu_x:.2f} | {rate:,.0f} | {rate_x:.2f} "
            f"| {p50:.2f} / {p99:.2f} | {lost} |"
        )
    return lines


def _mean(xs: list[float]) -> float:
    return sum(xs) / len(xs)


def main(argv: list[str]) -> int:
    if argv[:1] == ["--_child"]:
        return _child_main(argv[1:])
    ap = argparse.ArgumentParser(prog="hil bench bus", description=__doc__)
    ap.add_argument("--messages", type=int, default=20000, help="messages per case and round")
    ap.add_argument("--rate", type=float, default=0.0, help="messages/s (0: as fast as Zenoh takes them)")
    ap.add_argument("--burst", type=int, default=1, help="paced: messages put back to back per period")
    ap.add_argument("--repeat", type=int, default=2, help="rounds over every case, alternating")
    ap.add_argument("--cases", default=",".join(CASES), help=f"comma-separated subset of {CASES}")
    ap.add_argument(
        "--versus",
        metavar="TREE",
        help="also run the hil cases from this checkout (a `git worktree` of an older revision): "
        "before/after in one session",
    )
    ap.add_argument("--section", default="bus", help="the docs/benchmarks.md section to write")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    a = ap.parse_args(argv)
    cases = [c.strip() for c in a.cases.split(",") if c.strip()]
    if "raw" not in cases:
        cases.insert(0, "raw")
    unknown = [c for c in cases if c not in CASES]
    if unknown:
        ap.error(f"unknown case(s) {unknown}; known: {', '.join(CASES)}")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = open_session(BusConfig(mode="peer", listen=(endpoint,), connect=()))
    load = os.getloadavg()[0]
    runs: list[tuple[str, str, str | None]] = [(c, c, None) for c in cases]
    if a.versus:
        ref = tree_revision(a.versus)
        # an older checkout has no burst case: its single-frame hilzenoh row is the "before"
        runs += [
            (f"{c} ({ref})", c, a.versus) for c in cases if not c.startswith("raw") and c != "hilzenoh burst"
        ]
    results: dict[str, list[dict[str, float]]] = {label: [] for label, _, _ in runs}
    try:
        for i in range(a.repeat):
            for label, case, tree in runs if i % 2 == 0 else runs[::-1]:
                results[label].append(run_case(case, endpoint, a.messages, a.rate, a.burst, tree))
                row = {k: round(v, 2) for k, v in results[label][-1].items()}
                print(f"round {i + 1} {label}: {row}", file=sys.stderr, flush=True)
    finally:
        hub.close()
    load_after = os.getloadavg()[0]
    pace = (
        f"paced at {a.rate:g} msg/s in bursts of {a.burst}"
        if a.rate > 0
        else "flooded (as fast as Zenoh takes them)"
    )
    body = "\n".join(
        [
            f"{a.messages} messages per case and round, {pace}, {a.repeat} rounds alternating; sender "
            "and receiver are separate processes peered through a loopback hub (as under `hil up`). "
            "CPU is each process's own (every thread, Zenoh's included) over the traffic; × raw pairs "
            "each round with that round's raw zenoh-python case.",
            "",
            *_fmt_table(results),
            "",
            f"Load average (1 min): {load:.2f} before, {load_after:.2f} after, on {os.cpu_count()} cores "
            "(whatever else ran on the machine counts in it): throughput is what a process got of the "
            "machine, CPU per message is the robust figure.",
        ]
    )
    print(body)
    if not a.no_write:
        write_section(a.section, body, command_line())
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

"""Emulator side of the vcan bench: ImuCanNode on SocketCAN at a fixed cadence, in its own process.

    python -m tests.vcan._emit --rate 100 --n 300 [--fd] [--sync-every 100]

Paces samples on an absolute schedule (no drift from sleep overshoot), prints one JSON line with
the node's counters and its measured bus load at the end.
"""

from __future__ import annotations

import argparse
import json
import sys
import time

from hil.can.bus import open_can_bus
from hil.can.codec import ImuCanCodec
from hil.can.node import ImuCanNode


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser()
    ap.add_argument("--rate", type=float, default=100.0)
    ap.add_argument("--n", type=int, default=300)
    ap.add_argument("--fd", action="store_true")
    ap.add_argument("--channel", default="vcan0")
    ap.add_argument("--sync-every", type=int, default=100)
    args = ap.parse_args(argv)
    bus, desc = open_can_bus(args.channel, None, fd=args.fd)
    node = ImuCanNode(bus, ImuCanCodec.from_dbc(fd=args.fd))
    dt_ns = round(1e9 / args.rate)
    t0 = time.monotonic() + 0.05
    load_max = 0.0
    for i in range(args.n):
        target = t0 + i / args.rate
        delay = target - time.monotonic()
        if delay > 0:
            time.sleep(delay)
        dev = 1_000_000_000 + i * dt_ns
        if args.sync_every and i % args.sync_every == 0:
            node.send_sync(dev)
        node.send_sample(dev, [1e-6 * (i % 1000), -2e-6, 3e-7], [1e-4, -2e-4, -0.0245], status=0)
        load_max = max(load_max, node.bus_load())
    elapsed = time.monotonic() - t0
    bus.shutdown()
    out = {"transport": desc, "elapsed_s": round(elapsed, 3), "bus_load_max": round(load_max, 4)}
    out.update(node.counters())
    sys.stdout.write(json.dumps(out) + "\n")
    return 0


if __name__ == "__main__":
    sys.exit(main())

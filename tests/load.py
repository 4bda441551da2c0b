"""How loaded the machine is right now, for timing bounds that hold on a busy host.

A test that bounds how long something takes states its bound for an idle machine and scales it by
``slowdown()``: the factor by which the machine is slower for us than an idle one, measured, not
guessed -- the larger of the share of a core this process gets while busy (a measured busy loop:
0.5 means we wait half the time for a core) and the run queue per core (the 1-minute load
average, which sees the other engineers' suites and any CPU hog). On an idle 2-core machine it
is 1.0; with two CPU hogs and a suite on its 2 cores it is 2-4.
"""

from __future__ import annotations

import os
import time


def cpu_share(window_s: float = 0.2) -> float:
    """Share of one core this thread got while trying to use all of it for ``window_s``."""
    t0, c0 = time.perf_counter(), time.thread_time()
    while time.perf_counter() - t0 < window_s:
        pass
    return (time.thread_time() - c0) / max(time.perf_counter() - t0, 1e-9)


def slowdown() -> float:
    """How many times slower than idle this machine is for us now (>= 1)."""
    share = cpu_share()
    queue = os.getloadavg()[0] / (os.cpu_count() or 1)
    return max(1.0, 1.0 / max(share, 0.05), queue)


def _spin(stop_at: float) -> None:
    while time.monotonic() < stop_at:
        pass


def hog(seconds: float, procs: int | None = None) -> None:
    """Keep ``procs`` cores (default: all) busy for ``seconds``: the load the suite must hold under."""
    import multiprocessing

    stop_at = time.monotonic() + seconds
    workers = [
        multiprocessing.Process(target=_spin, args=(stop_at,)) for _ in range(procs or os.cpu_count() or 1)
    ]
    for w in workers:
        w.start()
    try:
        for w in workers:
            w.join()
    finally:
        for w in workers:
            w.kill()


def main(argv: list[str] | None = None) -> int:
    """``python -m tests.load hog SECONDS [PROCS]``: a CPU hog on every core, or ``slowdown``."""
    import sys

    args = sys.argv[1:] if argv is None else argv
    if args[:1] == ["hog"] and len(args) in (2, 3):
        hog(float(args[1]), int(args[2]) if len(args) == 3 else None)
        return 0
    if args == ["slowdown"]:
        print(f"{slowdown():.2f}")
        return 0
    print("usage: python -m tests.load hog SECONDS [PROCS] | slowdown", file=sys.stderr)
    return 2


if __name__ == "__main__":
    raise SystemExit(main())

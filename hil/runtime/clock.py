"""The one module that reads the OS clock.

Rig time is integer nanoseconds since the run's start, optionally scaled (``--speed K``): the
rig clock runs K times faster than the wall clock. Cores never call this; services read it and
pass times in.
"""

from __future__ import annotations

import time


def wall_ns() -> int:
    """CLOCK_REALTIME in ns: shared by every process on a host (and across NTP-synced hosts)."""
    return time.time_ns()


class RigClock:
    """Rig time from a shared wall-clock start instant and a speed factor."""

    def __init__(self, start_epoch_ns: int, speed: float = 1.0) -> None:
        if not speed > 0:
            raise ValueError(f"speed must be > 0, got {speed}")
        self.start_epoch_ns = start_epoch_ns
        self.speed = speed

    def now_ns(self) -> int:
        return int((time.time_ns() - self.start_epoch_ns) * self.speed)

    def wall_of(self, rig_ns: int) -> float:
        """Wall-clock seconds (time.time()) at which rig time reaches ``rig_ns``."""
        return (self.start_epoch_ns + rig_ns / self.speed) / 1e9

    def sleep_until(self, rig_ns: int, stop: object | None = None, max_sleep_s: float = 0.5) -> None:
        """Sleep until rig time ``rig_ns`` (in slices, so a stop event is noticed promptly)."""
        while True:
            remaining = self.wall_of(rig_ns) - time.time()
            if remaining <= 0:
                return
            if stop is not None and getattr(stop, "is_set", lambda: False)():
                return
            time.sleep(min(remaining, max_sleep_s))


def monotonic_s() -> float:
    return time.monotonic()


def epoch_s_to_rig_ns(ts_s: float, start_epoch_ns: int, speed: float) -> int:
    """A receive stamp in epoch seconds (python-can's, the kernel's for SocketCAN) on the rig
    clock: ``(ts * 1e9 - start) * speed``, without adding float error to ``ts``'s own ~0.24 µs.

    Split the stamp into whole seconds (exact integer ns arithmetic against the start) and the
    fraction, so the subtraction of two ~1.8e18 ns numbers never happens in floating point.
    """
    whole = int(ts_s)
    frac_ns = round((ts_s - whole) * 1e9)
    wall_ns = whole * 1_000_000_000 + frac_ns - start_epoch_ns
    return wall_ns if speed == 1.0 else int(wall_ns * speed)

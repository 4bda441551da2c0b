"""Give the C heap's free pages back to the OS, so a service's RSS tracks what it holds.

Why: glibc gives each thread that mallocs its own arena (64 MiB-aligned heaps). Zenoh's Rust
threads and Python's objects over 512 B allocate there, and after a
transient backlog -- a queue peak of 700 messages, 0.14 s of a 5 kHz stream -- the arena keeps the
high-water mark: in a 12-minute soak the recorder's two busiest arenas went from ~3 to ~9 MiB
each in one burst and stayed there, free but resident (``/proc/<pid>/smaps``). That is not a
leak, but it reads as one and it costs RAM on a bench box. ``malloc_trim(0)`` (glibc >= 2.8)
walks every arena and ``madvise``s whole free pages away; nothing in use moves.

Measured on the recorder at 1 kHz (6.7 min, one trim a second): 403 trims gave back 1.4 GiB in
all, 3.6 MiB/s of C heap touched and freed again between trims. The longest
call took 26.6 ms. After the first 10 % its RSS stayed at 61-64 MiB, apart from two transient
backlogs (68 and 72 MiB). With one trim every 10 s the floor crept from 65 to 74 MiB in
12 minutes. Fixing glibc's mmap threshold (``MALLOC_MMAP_THRESHOLD_=131072``) did not help: an
8-minute run with it and 10 s trims still grew +10 % along the trend.

Elsewhere (musl, macOS) there is no such call and ``HeapTrimmer.available`` is False.
"""

from __future__ import annotations

import ctypes
import gc
import os
import time
from collections.abc import Callable

_PAGE_KIB = os.sysconf("SC_PAGE_SIZE") // 1024 if hasattr(os, "sysconf") else 4


def _load_malloc_trim() -> Callable[[int], int] | None:
    # The process's own symbols: glibc is loaded already, and ctypes.util.find_library would run
    # ldconfig in a subprocess at every service's start.
    try:
        fn = ctypes.CDLL(None).malloc_trim  # CDLL: the GIL is released for the call
    except (OSError, AttributeError):
        return None
    fn.argtypes = [ctypes.c_size_t]
    fn.restype = ctypes.c_int
    return fn  # type: ignore[no-any-return]


def rss_kib() -> int | None:
    """This process's resident set in KiB (``/proc/self/statm``); None off Linux."""
    try:
        with open("/proc/self/statm") as fh:
            return int(fh.read().split()[1]) * _PAGE_KIB
    except (OSError, ValueError, IndexError):
        return None


class HeapTrimmer:
    """Calls ``malloc_trim`` and keeps the counters a service puts in its status."""

    def __init__(self) -> None:
        self._trim = _load_malloc_trim()
        self.trims = 0
        self.released_kib = 0  # sum over trims of the RSS drop across the call
        self.max_ms = 0.0  # the longest call: it holds each arena's lock in turn

    @property
    def available(self) -> bool:
        return self._trim is not None

    def trim(self) -> int:
        """Trim now; returns the KiB of RSS the call gave back (0 where unavailable)."""
        if self._trim is None:
            return 0
        before = rss_kib()
        t0 = time.perf_counter()
        self._trim(0)
        self.max_ms = max(self.max_ms, (time.perf_counter() - t0) * 1e3)
        after = rss_kib()
        self.trims += 1
        released = max(0, before - after) if before is not None and after is not None else 0
        self.released_kib += released
        return released

    def counters(self) -> dict[str, int]:
        return {
            "heap_trims": self.trims,
            "heap_trim_released_kib": self.released_kib,
            "heap_trim_max_us": round(self.max_ms * 1e3),
            "rss_kib": rss_kib() or 0,
        }


#: Set by ``hil``'s command line (``hil.cli.main``): the process is the command's own, and what it
#: has built by its run's start lives as long as it. A library caller (a test, a notebook) keeps
#: its collector as it was: frozen objects in a cycle are never collected.
command_process = False


#: The collector's first-generation threshold in an offline run's processes (Python's is 700).
#: What ``hil sim`` holds for a window (a rig second, ~3300 messages) or ``hil rerun`` for a batch
#: (4096 inputs) is tens of thousands of tracked objects, freed together after it: at 700 the
#: collector ran ~2000 times in 120 s of straight_level, walking them, 0.27 of the sim process's
#: 5.59 s of CPU; at 50 000, 3 times and 0.02 s. Collections come as rarely as the windows end.
OFFLINE_GEN0_THRESHOLD = 50_000


def offline_collector() -> None:
    """Freeze the start-up (:func:`freeze_startup`) and raise the first generation's threshold
    (``OFFLINE_GEN0_THRESHOLD``): a process of an offline run (``hil sim``, ``hil rerun``), not
    a live service, whose latency a longer young collection would reach."""
    freeze_startup()
    gc.set_threshold(OFFLINE_GEN0_THRESHOLD, *gc.get_threshold()[1:])


def freeze_command_startup() -> None:
    """:func:`offline_collector` in a command's own process only (``command_process``)."""
    if command_process:
        offline_collector()


def freeze_startup() -> None:
    """Move everything built so far (modules, compiled kernels, the nodes and their estimators,
    all living as long as the process) out of the cyclic collector's reach: its full collections
    then scan only what the run makes. Without it ``hil rerun``'s fusion worker spent 0.56 of its
    7.6 s of CPU on 300 s of straight_level in the collector (117k objects tracked, 7 full
    collections), with it 0.19 s; a live service's pauses landed on the output's latency."""
    gc.collect()
    gc.freeze()

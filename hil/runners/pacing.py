"""Frames on time: the live runner's pacing of a node that writes CAN (the IMU emulator).

What a device under test feels of an IMU is when its frames arrive. A real IMU samples on a
hardware timer and its CAN controller puts each sample's frames on the wire back to back, one
bit time after another, starting on the sample's tick. The live runner reproduces that with:

- **a monotonic clock** (:class:`MonotonicRigClock`): rig time read from ``CLOCK_MONOTONIC``
  (anchored once to the wall-clock rig clock every service shares, re-anchored only if the wall
  clock is stepped), so an NTP step never bunches or stretches the grid;
- **compute ahead, send on time**: the runner ticks the node for a sample up to ``lookahead_s``
  before it is due (the node is pure: its output depends only on the tick's rig time, exactly as
  in ``hil sim``) and hands the frames to a sender process of their own
  (``hil.runners.can_sender``, whose one thread is :class:`PacedSender`), so the
  once-a-second physics block (tens of ms on a loaded machine) is computed while earlier samples
  still leave on time; a fault command is applied from the first sample computed after it
  (at most ``lookahead_s`` later than without look-ahead);
- **a pacing loop that sleeps coarse and spins fine** (:class:`Waiter`): ``time.sleep`` (timer
  slack set to 1 ns for the thread, where the kernel allows) to within a margin of the target,
  then a busy spin; the margin follows the measured sleep overshoot (90th percentile of the
  last 64, clamped to [20, 300] µs), so a quiet machine spins little. The spin is the CPU cost
  of precision; status reports it as ``pacing.spin_permille`` (per mille of one core);
- **the wire** (:class:`CanWire`): each frame occupies the bus for its bit time at the
  configured bit rates (ISO 11898-1, worst-case stuffing, ``hil.can.busload``; classic 1 Mbit/s,
  FD 1/5 Mbit/s), frames never overlap (first in first out), and a frame is handed to the
  transport when its last bit would have left plus the node's fixed controller/driver latency
  (``Node.can_wire_latency_ns``: the scenario's ``[clock.imu] transport_latency_s``, what
  ``hil sim``'s wire model adds). The transport is stamped with that instant (the Zenoh CAN
  transport carries it as the frame's receive stamp, as the kernel does on ``vcan``);
- **after a stall** (the host did not run the sender in time): a sample whose tick has passed
  leaves as soon as the wire is free -- late, counted in ``tx_late_samples`` when later than
  ``late_tolerance_s``, its worst lateness in ``tx_late_max_us`` -- and never faster than the
  wire carries frames: what a real IMU's transmit FIFO does when its bus was blocked.
  ``late_policy = "skip"`` models the other real design, a one-sample output register: a
  sample whose slot has passed (the next one is due) is skipped and counted
  (``tx_late_skipped_samples``); the bridge sees a counter jump, the grid is never compressed;
- **honest time tags**: a sync (time-tag) frame states, on the device clock, the instant its
  first bit left. When it cannot leave on its tick it is re-encoded with the device time of the
  instant it does leave (the codec's ``restamp_sync`` with ``CanBurst.device_clock``), and
  if the sender then misses that instant by more than ``SYNC_CLAIM_TOL_NS`` the frame is not
  sent (``tx_sync_dropped``): a wrong tag is worse than none;
- **a short scheduler time slice** at normal priority (``sched_slice_us``, 100 µs by default,
  ``short_slice``: Linux 6.12+, any user), so the sender preempts the running task on its tick;
  and the rest of the rig kept off the sender's CPU where asked (``hil up --rig-cpus``,
  ``rig_cpus_from_env``, ``pin_process``: pinning one's own processes needs no privilege);
- **optional real-time priority and CPU affinity** for the sender process
  (``rt_priority``: ``SCHED_FIFO`` at that priority; ``cpu_affinity``: CPUs to pin it to): used
  where the OS permits (root or ``CAP_SYS_NICE``), otherwise one status line says why not and
  the rig runs as before. Never required; on a loaded machine it is what keeps p99 in the tens
  of µs. The sender spins for at most the margin, and Linux's RT throttling
  (``sched_rt_runtime_us``) bounds what a real-time thread can take anyway.

Nothing here is used by ``hil sim`` (which models the wire in ``hil.runners.wire``): a
recording of ``hil sim`` is the same bit for bit.
"""

from __future__ import annotations

import contextlib
import ctypes
import math
import os
import struct
import sys
import threading
import time
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import Any, Protocol

from hil.can.busload import FD_DATA_BITRATE, NOMINAL_BITRATE, frame_bits
from hil.nodes.base import CanBurst

PR_SET_TIMERSLACK = 29  # linux/prctl.h
MIN_SPIN_NS = 20_000
MAX_SPIN_NS = 200_000
MAX_SLEEP_S = 0.1  # wake at least this often to notice a stop
SYNC_CLAIM_TOL_NS = 5_000  # a sync frame's stated departure may miss its real one by this much
LATE_POLICIES = ("send", "skip")


# -- the OS knobs: each best effort, each says why it did not work ------------------------------
def fine_timer_slack() -> str | None:
    """1 ns timer slack for the calling thread (Linux's default 50 µs rounds every sleep up)."""
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        if libc.prctl(PR_SET_TIMERSLACK, 1, 0, 0, 0) != 0:
            return f"prctl(PR_SET_TIMERSLACK): {os.strerror(ctypes.get_errno())}"
    except (OSError, AttributeError) as err:
        return f"prctl(PR_SET_TIMERSLACK) unavailable: {err}"
    return None


def realtime_priority(priority: int) -> str | None:
    """``SCHED_FIFO`` at ``priority`` for the calling thread; None, or why not."""
    if priority <= 0:
        return None
    try:
        lo, hi = os.sched_get_priority_min(os.SCHED_FIFO), os.sched_get_priority_max(os.SCHED_FIFO)
        if not lo <= priority <= hi:
            return f"rt_priority {priority} outside SCHED_FIFO's {lo}..{hi}; running without"
        os.sched_setscheduler(0, os.SCHED_FIFO, os.sched_param(priority))
    except (OSError, AttributeError) as err:
        return f"SCHED_FIFO {priority} not permitted ({err}): needs root or CAP_SYS_NICE; running without"
    return None


# struct sched_attr, the first version (linux/sched/types.h): size, policy, flags, nice,
# priority, runtime, deadline, period, util_min, util_max
_SCHED_ATTR = struct.Struct("<IIQiIQQQII")
_SYS_SCHED_SETATTR = {"x86_64": 314, "aarch64": 274}
_SYS_SCHED_GETATTR = {"x86_64": 315, "aarch64": 275}
SCHED_SLICE_MIN_US, SCHED_SLICE_MAX_US = 100, 100_000  # what the kernel accepts (EEVDF)


def short_slice(slice_us: int) -> str | None:
    """Ask the scheduler for a ``slice_us`` time slice for the calling thread (and the threads
    it starts), at normal priority; None, or why not.

    Linux's EEVDF scheduler (6.6; a slice of one's own since 6.12, any user, ``sched_setattr``'s
    ``sched_runtime`` under ``SCHED_OTHER``) gives a task with a shorter slice an earlier virtual
    deadline: woken from its sleep, it preempts the task running on its CPU instead of waiting
    for that one's slice (~1.4 ms here) to end. Nice values do not do that: they share the CPU,
    they do not make a wake-up prompt (measured: the other services at nice +10 left the p99
    where it was). The thread's policy and nice value are kept; under ``SCHED_FIFO`` it is
    left alone (a real-time thread has no slice)."""
    if slice_us <= 0:
        return None
    machine = os.uname().machine
    nr_set, nr_get = _SYS_SCHED_SETATTR.get(machine), _SYS_SCHED_GETATTR.get(machine)
    if not sys.platform.startswith("linux") or nr_set is None or nr_get is None:
        return f"sched_slice_us {slice_us}: no sched_setattr on {sys.platform} {machine}; kernel default"
    slice_ns = min(max(slice_us, SCHED_SLICE_MIN_US), SCHED_SLICE_MAX_US) * 1000
    default = "; kernel default slice"
    try:
        libc = ctypes.CDLL(None, use_errno=True)
        buf = ctypes.create_string_buffer(_SCHED_ATTR.size)
        if libc.syscall(nr_get, 0, buf, _SCHED_ATTR.size, 0) != 0:
            return f"sched_getattr: {os.strerror(ctypes.get_errno())}{default}"
        _size, policy, _flags, nice, prio, *_rest = _SCHED_ATTR.unpack(buf.raw)
        if policy != os.SCHED_OTHER:
            return None  # SCHED_FIFO (rt_priority): no slice to shorten
        want = ctypes.create_string_buffer(
            _SCHED_ATTR.pack(_SCHED_ATTR.size, policy, 0, nice, prio, slice_ns, 0, 0, 0, 0), _SCHED_ATTR.size
        )
        if libc.syscall(nr_set, 0, want, 0) != 0:
            return f"sched_setattr (slice {slice_us} µs): {os.strerror(ctypes.get_errno())}{default}"
        libc.syscall(nr_get, 0, buf, _SCHED_ATTR.size, 0)
        if _SCHED_ATTR.unpack(buf.raw)[5] != slice_ns:
            return f"sched_slice_us {slice_us}: this kernel keeps its own slices (needs Linux 6.12+)"
    except (OSError, AttributeError) as err:
        return f"sched_setattr unavailable: {err}{default}"
    return None


RIG_CPUS_ENV = "HIL_CPUS"  # hil up --rig-cpus: the CPUs of every rig process but the frame sender


def parse_cpus(text: str) -> list[int]:
    """``"0,2"`` -> [0, 2] (``""``: none), as ``--cpu-affinity``, ``--rig-cpus`` and ``HIL_CPUS``
    write them; ValueError for anything that is not CPU numbers."""
    cpus = [int(x) for x in text.split(",") if x.strip()]
    if any(c < 0 for c in cpus):
        raise ValueError(f"{text!r}: a CPU number is 0 or more")
    return cpus


def rig_cpus_from_env(env: dict[str, str] | None = None) -> str | None:
    """This process on the CPUs ``HIL_CPUS`` names ("0" or "0,2"; unset: left alone), before it
    starts a thread (threads and children inherit it); None, or why not."""
    text = (os.environ if env is None else env).get(RIG_CPUS_ENV, "").strip()
    if not text:
        return None
    try:
        cpus = parse_cpus(text)
    except ValueError:
        return f"{RIG_CPUS_ENV}={text!r} is not a list of CPU numbers; running on any CPU"
    return cpu_affinity(cpus)


def pin_process(cpus: Sequence[int]) -> tuple[set[int] | None, str | None]:
    """Every thread of this process on ``cpus`` (those that start later inherit it): the mask
    to restore (None: nothing changed), and None or why not. For ``hil up``'s own process, whose
    hub routes the rig's messages on Zenoh's threads (there already when it runs in a bench)."""
    if not cpus:
        return None, None
    try:
        old = os.sched_getaffinity(0)
        tids = [int(t) for t in os.listdir("/proc/self/task")] if os.path.isdir("/proc/self/task") else [0]
        for tid in tids:
            with contextlib.suppress(ProcessLookupError):  # a thread that ended meanwhile
                os.sched_setaffinity(tid, set(cpus))
    except (OSError, AttributeError) as err:
        return None, f"rig_cpus {list(cpus)} not applied ({err}); running on any CPU"
    return old, None


def unpin_process(mask: set[int] | None) -> None:
    """Undo :func:`pin_process` for every thread still running."""
    if mask is None:
        return
    with contextlib.suppress(OSError):
        for tid in [int(t) for t in os.listdir("/proc/self/task")]:
            with contextlib.suppress(ProcessLookupError):
                os.sched_setaffinity(tid, mask)


def cpu_affinity(cpus: Sequence[int]) -> str | None:
    """Pin the calling thread to ``cpus``; None, or why not."""
    if not cpus:
        return None
    try:
        os.sched_setaffinity(0, set(cpus))
    except (OSError, ValueError, AttributeError) as err:
        return f"cpu_affinity {list(cpus)} not applied ({err}); running unpinned"
    return None


# -- the clock ----------------------------------------------------------------------------------
class MonotonicRigClock:
    """Rig time on ``CLOCK_MONOTONIC``, anchored to the wall-clock rig clock of the run.

    ``rig = (wall - start_epoch) * speed``; the anchor is the (wall, monotonic) pair read with
    the smallest gap of a few tries. ``check()`` (call it now and then) re-anchors only if the
    wall clock moved against the monotonic one by more than ``step_ns`` (an NTP step): the slew
    of a disciplined clock moves both alike.
    """

    def __init__(self, start_epoch_ns: int, speed: float = 1.0, step_ns: int = 1_000_000) -> None:
        self.start_epoch_ns = start_epoch_ns
        self.speed = speed
        self.step_ns = step_ns
        self.steps = 0
        self._wall0, self._mono0 = self._pair()

    @staticmethod
    def _pair() -> tuple[int, int]:
        best: tuple[int, int, int] | None = None
        for _ in range(5):
            m0 = time.monotonic_ns()
            w = time.time_ns()
            m1 = time.monotonic_ns()
            if best is None or m1 - m0 < best[0]:
                best = (m1 - m0, w, (m0 + m1) // 2)
        assert best is not None
        return best[1], best[2]

    def check(self) -> bool:
        """Re-anchor if the wall clock was stepped; True if it was."""
        w, m = self._pair()
        drift = (w - self._wall0) - (m - self._mono0)
        if abs(drift) <= self.step_ns:
            return False
        self._wall0, self._mono0 = w, m
        self.steps += 1
        return True

    def rig_of_mono(self, mono_ns: int) -> int:
        wall_ns = self._wall0 - self.start_epoch_ns + (mono_ns - self._mono0)  # exact: integers
        return wall_ns if self.speed == 1.0 else int(wall_ns * self.speed)

    def mono_of_rig(self, rig_ns: int) -> int:
        """The monotonic instant rig time reaches ``rig_ns`` (rounded up: never before it)."""
        wall_ns = rig_ns if self.speed == 1.0 else math.ceil(rig_ns / self.speed)
        return self._mono0 + (self.start_epoch_ns - self._wall0) + wall_ns

    def now_ns(self) -> int:
        return self.rig_of_mono(time.monotonic_ns())

    def epoch_ns(self, rig_ns: int) -> int:
        """The wall-clock instant (epoch ns) of rig time ``rig_ns``."""
        return self.start_epoch_ns + (rig_ns if self.speed == 1.0 else round(rig_ns / self.speed))


class Waiter:
    """Sleep coarse, spin fine: ``until(mono_ns)`` returns at the target, a few µs after it.

    The spin margin tracks the sleep overshoot this thread sees (90th percentile of the last 64
    sleeps, plus 10 µs, within [``min_spin_ns``, ``max_spin_ns``]); ``spin_ns_total`` is the CPU
    the spinning cost, ``sleeps``/``spins`` how often each ran.
    """

    def __init__(
        self,
        stop: threading.Event | None = None,
        *,
        min_spin_ns: int = MIN_SPIN_NS,
        max_spin_ns: int = MAX_SPIN_NS,
        now: Callable[[], int] = time.monotonic_ns,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.stop = stop
        self.min_spin_ns = min_spin_ns
        self.max_spin_ns = max_spin_ns
        self.margin_ns = max(min_spin_ns, min(max_spin_ns, 60_000))
        self._now = now
        self._sleep = sleep
        self._over: list[int] = []
        self.spin_ns_total = 0
        self.sleeps = 0
        self.spins = 0

    def until(self, target_ns: int, spin: bool = False) -> int:
        """Wait until monotonic ``target_ns`` (or a stop); the monotonic time on return.
        ``spin``: do not sleep at all (a sender catching up: a wake-up on a loaded machine can
        cost more than the wait)."""
        now = self._now()
        while target_ns - now > (self.margin_ns if not spin else MAX_SLEEP_S * 1e9):
            if self.stop is not None and self.stop.is_set():
                return now
            want = target_ns - self.margin_ns
            self._sleep(min((want - now) * 1e-9, MAX_SLEEP_S))
            self.sleeps += 1
            after = self._now()
            if want - now <= MAX_SLEEP_S * 1e9:
                self._learn(after - want)
            now = after
        if now < target_ns:
            t0 = now
            while now < target_ns:
                now = self._now()
            self.spins += 1
            self.spin_ns_total += now - t0
        return now

    def _learn(self, overshoot_ns: int) -> None:
        self._over.append(overshoot_ns)
        if len(self._over) >= 64:
            q90 = sorted(self._over)[57]
            # spin what covers the usual overshoot; if even that is beyond the bound (a loaded
            # machine, no real-time priority), spinning buys nothing and costs the CPU the
            # scheduler then withholds: spin the minimum
            want = q90 + 10_000
            self.margin_ns = max(self.min_spin_ns, want) if want <= self.max_spin_ns else self.min_spin_ns
            self._over.clear()


# -- the wire -----------------------------------------------------------------------------------
class CanWire:
    """Bit time of a frame at the bus's rates (worst-case stuffing), cached per frame shape."""

    def __init__(
        self, nominal_bitrate: float = NOMINAL_BITRATE, data_bitrate: float = FD_DATA_BITRATE
    ) -> None:
        if not (nominal_bitrate > 0 and data_bitrate > 0):
            raise ValueError(f"bit rates must be > 0, got {nominal_bitrate}/{data_bitrate}")
        self.nominal_bitrate = nominal_bitrate
        self.data_bitrate = data_bitrate
        self._cache: dict[tuple[int, bool, bool, bool], int] = {}

    def frame_ns(self, frame: Any) -> int:
        key = (len(frame.data), frame.is_fd, frame.bitrate_switch, frame.is_extended_id)
        ns = self._cache.get(key)
        if ns is None:
            bits = frame_bits(key[0], fd=bool(key[1]), brs=bool(key[2]), extended=bool(key[3]))
            ns = self._cache[key] = round(bits.seconds(self.nominal_bitrate, self.data_bitrate) * 1e9)
        return ns


# -- the sender ---------------------------------------------------------------------------------
@dataclass(frozen=True)
class PacingConfig:
    """How the sender paces (the node's options and facts; see the module docstring)."""

    late_policy: str = "send"
    late_tolerance_ns: int = 200_000
    rt_priority: int = 0
    cpu_affinity: tuple[int, ...] = ()
    sched_slice_us: int = 0  # the sender's scheduler time slice (``short_slice``; 0: the kernel's)
    wire_latency_ns: int = 0  # the node's fixed controller/driver latency after the last bit
    period_ns: int = 0  # the sample period (the skip policy's slot; 0: none)
    bitrate: int = NOMINAL_BITRATE
    data_bitrate: int = FD_DATA_BITRATE

    def __post_init__(self) -> None:
        if self.late_policy not in LATE_POLICIES:
            raise ValueError(f"late_policy {self.late_policy!r} is not one of {', '.join(LATE_POLICIES)}")


class FrameSink(Protocol):
    """Where the sender hands frames: ``hil.can.node.CanTransmitter``."""

    @property
    def carries_stamps(self) -> bool: ...

    def send_frame(self, frame: Any, stamp_epoch_ns: int | None = None) -> bool: ...

    def send_burst(self, frames: Sequence[Any], stamps_epoch_ns: Sequence[int]) -> bool: ...

    def count_burst(self, ok: bool, sync: bool) -> None: ...


COUNTERS = (
    "tx_late_samples",
    "tx_late_max_us",
    "tx_late_skipped_samples",
    "tx_sync_restamped",
    "tx_sync_dropped",
    "pacing.clock_steps",
)
# one row per sample sent (benches): device index, tick, ideal hand-over of its first frame (on
# the ideal wire: its tick, or the end of what a perfect device sent before it on the same bus,
# e.g. the sync frame that goes first on its edge; + that frame's wire time + latency), actual
# hand-over, frames, when the node handed it over
TRACE_COLUMNS = ("index", "due_ns", "ideal_ns", "handed_ns", "frames", "submitted_ns")


class PacedSender:
    """Sends CAN bursts at their rig times, frame by frame as the wire carries them (one thread).

    ``send(burst, due_ns)`` waits until the burst's first frame is due, hands each frame to
    ``sink`` when its last bit (plus the fixed latency) would have left, and keeps the bus FIFO.
    ``restamp(frame, device_ns)``: a sync frame stating another device time (the codec's
    ``restamp_sync``), for a time tag that cannot leave on its edge.
    """

    def __init__(
        self,
        clock: MonotonicRigClock,
        cfg: PacingConfig,
        sink: FrameSink,
        restamp: Callable[[Any, int], Any] | None = None,
        stop: threading.Event | None = None,
        trace: bool = False,
    ) -> None:
        self.clock = clock
        self.cfg = cfg
        self.wire = CanWire(cfg.bitrate, cfg.data_bitrate)
        self.sink = sink
        self.restamp = restamp
        self.counts: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self.trace: list[tuple[int, ...]] | None = [] if trace else None
        self.waiter = Waiter(stop)
        self.bus_free_ns = -(2**62)
        # the wire as a device that never stalls would use it: a sample is judged late only
        # against this schedule (a sync frame sent first on the same tick delays the sample's
        # frames on a real bus too), never against a schedule moved by the host's own lateness
        self.ideal_free_ns = -(2**62)

    def counters(self, wall_s: float) -> dict[str, int]:
        out = dict(self.counts)
        out["pacing.spin_margin_us"] = self.waiter.margin_ns // 1000
        if wall_s > 0:
            out["pacing.spin_permille"] = round(1000 * self.waiter.spin_ns_total * 1e-9 / wall_s)
        return out

    def send(self, burst: CanBurst, due_ns: int, submitted_ns: int = 0, backlog: bool = False) -> None:
        """``backlog``: more bursts are already waiting -- a late burst is then sent at wire
        speed by spinning (catching up); without a backlog the node itself is behind, and
        spinning would only take CPU from it."""
        if burst.sync:
            self._send_sync(burst, due_ns)
        else:
            self._send_burst(burst, due_ns, submitted_ns, backlog)

    def _wait_hand(self, at_ns: int, catching_up: bool = False) -> int | None:
        """Wait until rig time ``at_ns``; the rig time reached, None if stopped before it."""
        target = self.clock.mono_of_rig(at_ns)
        mono = self.waiter.until(target, spin=catching_up)
        return None if mono < target else self.clock.rig_of_mono(mono)

    def _send_burst(self, burst: CanBurst, due_ns: int, submitted_ns: int, backlog: bool = False) -> None:
        """A sample's frames: from its tick (or as soon as the wire is free), back to back.

        A bus that carries stamps gets the burst in one hand-over when its last frame is done,
        each frame stamped with its own end on the wire, counted back from the hand-over (one
        wait and one transport message per sample, not one per frame: ``send_burst``);
        SocketCAN, which stamps frames as they are sent, gets each frame when it is done (the
        short gaps inside a burst are spun)."""
        if not burst.frames:
            return
        now = self.clock.now_ns()
        if self.cfg.late_policy == "skip" and self.cfg.period_ns and now - due_ns >= self.cfg.period_ns:
            self.counts["tx_late_skipped_samples"] += 1  # its slot has passed: the next one is due
            # a device that never stalls sent it
            self._on_ideal_wire(due_ns, sum(self.wire.frame_ns(f) for f in burst.frames))
            return
        # on a bus that carries stamps, at normal priority, a late burst keeps its place on the
        # wire's schedule (stamps from its tick or the previous frame, never from when this
        # process woke): a descheduled sender cannot keep up with one wake-up per sample on a
        # loaded machine, and then fell seconds behind (load 22, 400 Hz: p50 4 s late). Its
        # hand-over stays late and is counted; its stamps never bunch and are never in the future.
        relaxed = self.sink.carries_stamps and self.cfg.rt_priority == 0
        t = max(due_ns, self.bus_free_ns) if relaxed else max(due_ns, self.bus_free_ns, now)
        # catch up at wire speed by spinning only at real-time priority: at normal priority the
        # spin takes the CPU the node needs to compute the next samples (measured at load 18,
        # 400 Hz: the sender spun 45 % of the time and the node fell seconds behind)
        behind = backlog and self.cfg.rt_priority > 0 and now - due_ns > self.cfg.late_tolerance_ns
        bits_ns = [self.wire.frame_ns(frame) for frame in burst.frames]  # once per frame
        ends = []
        latency = self.cfg.wire_latency_ns
        for ns in bits_ns:
            t += ns
            ends.append(t + latency)
        ok, first = True, 0
        if self.sink.carries_stamps:
            left = self._wait_hand(ends[-1], behind)
            if left is None:
                return
            stamps = [self.clock.epoch_ns(end if relaxed else left - (ends[-1] - end)) for end in ends]
            ok = self.sink.send_burst(burst.frames, stamps)
            first = left - (ends[-1] - ends[0])
        else:
            for frame, end in zip(burst.frames, ends, strict=True):
                left = self._wait_hand(end, behind)
                if left is None:
                    return
                ok = self.sink.send_frame(frame) and ok
                first = first or left
        self.bus_free_ns = t
        self.sink.count_burst(ok, False)
        sched = self._on_ideal_wire(due_ns, sum(bits_ns))
        self._account(burst, due_ns, sched + bits_ns[0] + latency, first, submitted_ns)

    def _on_ideal_wire(self, due_ns: int, bits_ns: int) -> int:
        """Put frames of wire time ``bits_ns`` on the ideal wire from ``due_ns``; the instant
        their first bit starts."""
        sched = max(due_ns, self.ideal_free_ns)
        self.ideal_free_ns = sched + bits_ns
        return sched

    def _send_sync(self, burst: CanBurst, due_ns: int) -> None:
        """The time tag leaves on its edge, or states when it left, or does not leave.

        A bus that carries stamps (``hilzenoh``) is stamped with the instant the tag states
        (plus its wire time): the receiver's stamp and the tag agree however late the host
        hands it over. SocketCAN stamps the frame when it is sent: the hand-over must then
        meet the stated instant within ``SYNC_CLAIM_TOL_NS``, or the tag is re-stamped later
        (three tries) or dropped."""
        frames = list(burst.frames)
        self._on_ideal_wire(due_ns, self.wire.frame_ns(frames[0]))
        for _attempt in range(3):
            first = max(due_ns, self.bus_free_ns, self.clock.now_ns())
            if first != burst.capture_ns:
                restamped = self._restamped(burst, first)
                if restamped is None:
                    break
                frames = restamped
            end = first + self.wire.frame_ns(frames[0])
            at = end + self.cfg.wire_latency_ns
            left = self._wait_hand(at)
            if left is None:
                return
            if left - at <= SYNC_CLAIM_TOL_NS or self.sink.carries_stamps:
                stamp = self.clock.epoch_ns(at if self.sink.carries_stamps else left)
                ok = all([self.sink.send_frame(f, stamp) for f in frames])
                self.bus_free_ns = end
                self.sink.count_burst(ok, True)
                return
            due_ns = left  # it missed the instant it states: state a later one
        self.counts["tx_sync_dropped"] += 1

    def _restamped(self, burst: CanBurst, first_ns: int) -> list[Any] | None:
        if self.restamp is None or burst.device_clock is None:
            return None
        counter, rate, q = burst.device_clock
        dev = counter + round((first_ns - burst.capture_ns) * rate)
        frame = self.restamp(burst.frames[0], (dev // q) * q)
        if burst.corrupted:
            flip_byte(frame)
        self.counts["tx_sync_restamped"] += 1
        return [frame]

    def _account(
        self, burst: CanBurst, due_ns: int, ideal_ns: int, handed_ns: int, submitted_ns: int
    ) -> None:
        late = handed_ns - ideal_ns
        c = self.counts
        if late > self.cfg.late_tolerance_ns:
            c["tx_late_samples"] += 1
        c["tx_late_max_us"] = max(c["tx_late_max_us"], late // 1000)
        if self.trace is not None:
            self.trace.append((burst.index, due_ns, ideal_ns, handed_ns, len(burst.frames), submitted_ns))


def flip_byte(frame: Any) -> None:
    """``hil.faults.FrameCorruptor.flip`` without its imports: one data byte flipped in place."""
    data = bytearray(frame.data)
    data[min(2, len(data) - 1)] ^= 0x5A
    frame.data = data

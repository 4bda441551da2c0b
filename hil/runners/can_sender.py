"""The CAN controller of a live node that writes frames: a small process of its own.

Why a process: a Python thread shares its process's interpreter lock. The node's own thread
(physics blocks of tens of ms, Zenoh publishing), the status thread and Zenoh's callbacks all
take that lock, and on a loaded machine a thread holding it can be descheduled for tens of ms --
a sender thread then waits, and real-time priority makes it worse (priority inversion through
the lock). Measured here at load 12 on 2 cores, 400 Hz, four frames per sample: a sender thread
in the node's process was p99 41 ms late without real-time priority and ~250 ms with it; this
process alone, p99 5.5 ms without and 49 µs with ``SCHED_FIFO``.

The service process (``hil.runners.live``) starts it during set-up (``SenderProcess``), so it
imports, opens its bus (its own Zenoh session for ``hilzenoh``, or a SocketCAN socket) and builds
the codec before time zero, while the service already reports ready. It then sends it, over a
pipe, each burst with the rig time it is due (computed up to ``lookahead_s`` ahead; the bursts
computed at one wake-up of the service in one message, ``submit_many``); this process
paces them (``hil.runners.pacing.PacedSender``) and reports its counters back once a second
(merged into the service's status). SIGTERM: what was submitted still leaves at its time (at
most ``lookahead_s``); it reports its final counters, writes its trace (benches) and exits. If
the service dies, the pipe closes and this process exits with it.

    python -m hil.runners.can_sender CONFIG_JSON READ_FD WRITE_FD
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Callable
from dataclasses import asdict, replace
from multiprocessing.connection import Connection
from typing import Any

import can

from hil.runners.pacing import (
    MAX_SLEEP_S,
    TRACE_COLUMNS,
    MonotonicRigClock,
    PacedSender,
    PacingConfig,
    cpu_affinity,
    fine_timer_slack,
    realtime_priority,
    short_slice,
)
from hil.runtime.signals import EventSetter

READY_TIMEOUT_S = 30.0


def _frame_tuple(f: Any) -> tuple[int, bool, bool, bool, bytes]:
    return (f.arbitration_id, bool(f.is_extended_id), bool(f.is_fd), bool(f.bitrate_switch), bytes(f.data))


def _frame(t: tuple[int, bool, bool, bool, bytes]) -> can.Message:
    return can.Message(
        arbitration_id=t[0], is_extended_id=t[1], is_fd=t[2], bitrate_switch=t[3], data=t[4], dlc=len(t[4])
    )


def _burst_tuple(due_ns: int, submitted_ns: int, burst: Any) -> tuple[Any, ...]:
    frames = [_frame_tuple(f) for f in burst.frames]
    return (
        due_ns,
        submitted_ns,
        burst.index,
        burst.capture_ns,
        burst.sync,
        burst.device_clock,
        burst.corrupted,
        frames,
    )


class SenderProcess:
    """The service side: starts the sender process, feeds it bursts, collects its counters."""

    def __init__(
        self, config: dict[str, Any], on_note: Callable[[str], None], on_ready: Callable[[str], None]
    ) -> None:
        self.on_note = on_note
        self.on_ready = on_ready
        self.ready = threading.Event()
        self.transport = ""
        self.last_counters: dict[str, int] = {}
        self.last_error = ""
        self._done = threading.Event()
        self._closed = False
        r_items, w_items = os.pipe()
        r_back, w_back = os.pipe()
        cmd = [sys.executable, "-m", "hil.runners.can_sender", json.dumps(config), str(r_items), str(w_back)]
        self.proc = subprocess.Popen(cmd, pass_fds=(r_items, w_back), start_new_session=True)
        os.close(r_items)
        os.close(w_back)
        self._tx = Connection(w_items, readable=False)
        self._rx = Connection(r_back, writable=False)
        self._lock = threading.Lock()
        self._reader = threading.Thread(target=self._read, name="can-sender-reader", daemon=True)
        self._reader.start()

    def _read(self) -> None:
        while True:
            try:
                msg = self._rx.recv()
            except (EOFError, OSError):
                break
            kind = msg[0]
            if kind == "ready":
                self.transport = msg[1]
                self.ready.set()
                self.on_ready(msg[1])
                for note in msg[2]:
                    self.on_note(note)
            elif kind == "note":
                self.on_note(msg[1])
            elif kind in ("counters", "done"):
                self.last_counters, self.last_error = msg[1], msg[2]
                if kind == "done":
                    self._done.set()
        self.ready.set()  # gone: nobody waits for it any more
        self._done.set()

    def _send(self, msg: tuple[Any, ...]) -> bool:
        with self._lock:
            try:
                self._tx.send(msg)
            except (OSError, ValueError):  # it is gone; the service reports that through status
                return False
        return True

    def start_run(self, start_epoch_ns: int, speed: float, wire_latency_ns: int, period_ns: int) -> None:
        """The run's time zero and speed, and the node's wire latency and sample period."""
        self._send(("run", start_epoch_ns, speed, wire_latency_ns, period_ns))

    def submit_many(self, items: list[tuple[int, int, Any]]) -> bool:
        """Bursts (due, computed at, burst) in one message: one pickle and one wake-up of the
        pacing process for all of them; it sends each at its time."""
        return self._send(("bursts", [_burst_tuple(due, sub, burst) for due, sub, burst in items]))

    def alive(self) -> bool:
        return self.proc.poll() is None

    def close(self, timeout_s: float = 5.0) -> None:
        """Stop it: what was submitted leaves at its time; wait for its last counters."""
        if self._closed:
            return
        self._closed = True
        if self.proc.poll() is None:
            self.proc.send_signal(signal.SIGTERM)
            self._done.wait(timeout_s)
            try:
                self.proc.wait(timeout_s)
            except subprocess.TimeoutExpired:
                self.proc.kill()
                self.proc.wait()
        with self._lock:
            self._tx.close()
        self._reader.join(1.0)
        self._rx.close()


# -- the process --------------------------------------------------------------------------------
class _Child:
    def __init__(self, cfg: dict[str, Any], out: Connection, stop: threading.Event) -> None:
        from hil.bus.pubsub import Stats
        from hil.can.bus import open_can_bus
        from hil.can.node import CanTransmitter

        self.cfg = cfg
        self.out = out
        self.stop = stop
        self.pacing = PacingConfig(**{**cfg["pacing"], "cpu_affinity": tuple(cfg["pacing"]["cpu_affinity"])})
        # before the bus: the threads Zenoh starts with its session inherit the priority -- a
        # frame's publication waits on them (measured: puts blocked for up to 340 ms when only
        # this thread was real-time and Zenoh's I/O threads queued behind the machine's load)
        notes = [
            n
            for n in (
                fine_timer_slack(),
                realtime_priority(self.pacing.rt_priority),
                short_slice(self.pacing.sched_slice_us),
                cpu_affinity(self.pacing.cpu_affinity),
            )
            if n
        ]
        self.bus, transport = open_can_bus(
            cfg["channel"], cfg["interface"], fd=cfg["fd"], rig=cfg["rig"], receive=False
        )
        self.stats = Stats()
        self.tx = CanTransmitter(
            self.bus, self.stats, nominal_bitrate=self.pacing.bitrate, data_bitrate=self.pacing.data_bitrate
        )
        self.restamp: Callable[[Any, int], Any] | None = None
        if cfg.get("time_tags"):
            from hil.can.codec import ImuCanCodec

            self.restamp = ImuCanCodec.from_dbc(cfg.get("dbc"), fd=cfg["fd"]).restamp_sync
        self.sender: PacedSender | None = None
        self.t0 = time.monotonic()
        self.cpu0 = time.process_time()
        self.last_report = self.t0
        out.send(("ready", transport, notes))

    def counters(self) -> dict[str, int]:
        out = self.tx.counters()
        bus_counters = getattr(self.bus, "counters", None)  # the transport's own (hillocal)
        if callable(bus_counters):
            out.update(bus_counters())
        if self.sender is not None:
            out.update(self.sender.counters(time.monotonic() - self.t0))
        out["pacing.sender_cpu_permille"] = round(
            1000 * time.process_time() / max(1e-9, time.monotonic() - self.t0)
        )
        return out

    def handle(self, msg: tuple[Any, ...], backlog: bool = False) -> None:
        if msg[0] == "run":
            _, start_epoch_ns, speed, latency_ns, period_ns = msg
            pacing = replace(self.pacing, wire_latency_ns=latency_ns, period_ns=period_ns)
            clock = MonotonicRigClock(start_epoch_ns, speed)
            trace = bool(self.cfg.get("trace"))
            # no stop event for its waits: at a stop what the service computed still leaves at its
            # time (the service sent at most lookahead_s ahead; it waits for our "done")
            self.sender = PacedSender(clock, pacing, self.tx, self.restamp, None, trace)
        elif msg[0] == "bursts" and self.sender is not None:
            from hil.nodes.base import CanBurst

            items = msg[1]
            for i, (due, submitted, index, capture, sync, dclock, corrupted, frames) in enumerate(items):
                burst = CanBurst(
                    [_frame(f) for f in frames],
                    capture,
                    index,
                    sync,
                    tuple(dclock) if dclock else None,
                    corrupted,
                )
                # more of this message's bursts wait behind it: a backlog, as more messages are
                self.sender.send(burst, due, submitted, backlog or i + 1 < len(items))

    def housekeeping(self) -> None:
        t = time.monotonic()
        if t - self.last_report < 1.0:
            return
        self.last_report = t
        if self.sender is not None and self.sender.clock.check():
            self.sender.counts["pacing.clock_steps"] += 1
            self.out.send(("note", "the wall clock was stepped: pacing re-anchored to it"))
        self.out.send(("counters", self.counters(), self.stats.snapshot()[2]))

    def finish(self) -> None:
        trace = self.cfg.get("trace")
        if trace and self.sender is not None and self.sender.trace is not None:
            import numpy as np

            rows = np.asarray(self.sender.trace, dtype=np.int64).reshape(-1, len(TRACE_COLUMNS))
            np.save(trace, rows)
        self.out.send(("done", self.counters(), self.stats.snapshot()[2]))
        self.bus.shutdown()


def main(argv: list[str]) -> int:
    cfg = json.loads(argv[0])
    inbox = Connection(int(argv[1]), writable=False)
    out = Connection(int(argv[2]), readable=False)
    stop = threading.Event()
    signal.signal(signal.SIGTERM, EventSetter(stop))  # not stop.set() there: hil.runtime.signals
    signal.signal(signal.SIGINT, signal.SIG_IGN)  # the service stops us (Ctrl-C reaches the group)
    try:
        child = _Child(cfg, out, stop)
    except Exception as err:  # the bus or the DBC: the service says why and stops
        out.send(("note", f"the CAN sender could not start: {err}"))
        return 1
    while not stop.is_set():
        try:
            if inbox.poll(MAX_SLEEP_S):
                msg = inbox.recv()
                child.handle(msg, backlog=inbox.poll(0))
        except EOFError:  # the service is gone
            break
        child.housekeeping()
    # SIGTERM: what was submitted leaves at its time (the service submits at most lookahead_s ahead)
    while inbox.poll(0):
        try:
            child.handle(inbox.recv())
        except EOFError:
            break
    child.finish()
    return 0


def pacing_config_dict(cfg: PacingConfig) -> dict[str, Any]:
    return {**asdict(cfg), "cpu_affinity": list(cfg.cpu_affinity)}


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))

"""The thin process shell every rig service shares.

A service opens one Zenoh session, publishes ``ServiceStatus`` at 1 Hz, waits for the run's
``RunInfo`` (time zero, scenario, speed) from ``world``, runs its loop until SIGTERM/SIGINT, then
closes cleanly. Everything else -- the numerics -- lives in pure cores the service calls.

Every publisher a service makes here counts its ``seq`` within the process's restart generation
(``restart_generation``: ``hil up --restart`` passes the restart number as option ``resume``), so
a restarted service's status, events, frames and clock models never repeat a seq of its previous
life, and the recording's completeness reports the restart as one (``hil.record.completeness``).

The status thread also trims the C heap every ``heap_trim_s`` (option, or ``HIL_HEAP_TRIM_S`` in
the environment; default ``heap_trim_default_s``: 10 s, the recorder's 1 s; 0 turns it off;
``hil.runtime.heap`` says why), so a service's RSS shows what it holds, not the high-water mark
of its last backlog.
"""

from __future__ import annotations

import dataclasses
import faulthandler
import logging
import os
import signal
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import msgspec
import zenoh

from hil import messages
from hil.bus.describe import BusDescription
from hil.bus.identity import ZENOH_ID_ENV
from hil.bus.keys import Keys
from hil.bus.pubsub import Publisher, Stats, Subscriber
from hil.bus.session import BusConfig, open_session
from hil.messages import Event, Message, RunInfo, ServiceStatus
from hil.runtime.clock import RigClock
from hil.runtime.heap import HeapTrimmer
from hil.runtime.signals import EventSetter

log = logging.getLogger(__name__)

HEAP_TRIM_PERIOD_S = 10.0
HEAP_TRIM_ENV = "HIL_HEAP_TRIM_S"


def restart_generation(options: dict[str, Any]) -> int:
    """Which life of the service this process is: 0 at first start, N after the supervisor's N-th
    restart (it passes option ``resume`` = N). Anything else (``true`` from a hand-written
    ``--options``, garbage) counts as 1 or 0: never an exception, never a negative generation."""
    value = options.get("resume", 0)
    if isinstance(value, bool):
        return int(value)
    if isinstance(value, int) and 0 <= value < 2**30:
        return value
    return 0


def heap_trim_period(
    options: dict[str, Any], default: float = HEAP_TRIM_PERIOD_S
) -> tuple[float, str | None]:
    """Seconds between heap trims, and what was wrong with the setting if anything.

    Option ``heap_trim_s`` (``hil service --options``) first, then the environment's
    ``HIL_HEAP_TRIM_S`` (which ``hil up`` passes to every service), then ``default``; 0: never.
    """
    if "heap_trim_s" in options:
        value: Any = options["heap_trim_s"]
        where = "option heap_trim_s"
    elif os.environ.get(HEAP_TRIM_ENV, "").strip():
        text = os.environ[HEAP_TRIM_ENV].strip()
        try:
            value = float(text)
        except ValueError:
            value = text
        where = HEAP_TRIM_ENV
    else:
        return default, None
    if isinstance(value, (int, float)) and not isinstance(value, bool) and 0 <= value < 1e6:
        return float(value), None
    return default, f"{where}={value!r} is not a number of seconds in [0, 1e6); trimming every {default:g} s"


@dataclass
class ServiceContext:
    """What a service is handed: built once in ``main()``, passed everywhere else."""

    name: str
    rig: str
    session: zenoh.Session
    stats: Stats = field(default_factory=Stats)
    stop: threading.Event = field(default_factory=threading.Event)
    options: dict[str, Any] = field(default_factory=dict)

    @property
    def keys(self) -> Keys:
        return Keys(self.rig)


class Service:
    """Base class: subclasses implement ``run_loop(run, clock)`` and may override ``ready_state``."""

    name = "service"
    heap_trim_default_s = HEAP_TRIM_PERIOD_S

    def __init__(self, ctx: ServiceContext) -> None:
        self.ctx = ctx
        self.stats = ctx.stats
        self.keys = ctx.keys
        self._status_now = threading.Event()  # a state change: the status goes out at once
        self.state = "starting"
        self.clock: RigClock | None = None
        self.run_info: RunInfo | None = None
        self._t0 = time.monotonic()
        self.generation = restart_generation(ctx.options)
        self.description = BusDescription(ctx.session, ctx.rig, self.name)
        self._status_pub = Publisher(
            ctx.session, self.keys.status(self.name), ServiceStatus, reliable=True, generation=self.generation
        )
        self._event_pub = Publisher(
            ctx.session, self.keys.event(self.name), Event, stats=self.stats, generation=self.generation
        )
        self.description.add(self._status_pub.key, ServiceStatus)
        self.description.add(self._event_pub.key, Event)
        self._run_event = threading.Event()
        self._subs: list[Any] = []
        self._status_thread = threading.Thread(target=self._status_loop, name="status", daemon=True)
        self.heap = HeapTrimmer()
        self.heap_trim_s, problem = heap_trim_period(ctx.options, self.heap_trim_default_s)
        if problem:
            self.stats.error("errors.options", problem)

    @property
    def state(self) -> str:
        return self._state

    @state.setter
    def state(self, value: str) -> None:
        # "ready" reaches the supervisor and the world when it happens, not at the next 1 Hz
        # status: time zero waits for every service's readiness
        changed = getattr(self, "_state", None) != value
        self._state = value
        wake = self.__dict__.get("_status_now")
        if changed and wake is not None:
            wake.set()

    # -- helpers for subclasses -------------------------------------------------------------
    def publisher(self, key: str, cls: type[Message], **kw: Any) -> Publisher[Any]:
        kw.setdefault("generation", self.generation)
        self.description.add(key, cls)
        return Publisher(self.ctx.session, key, cls, self.stats, **kw)

    def subscribe(self, key: str, cls: type[Message], handler: Callable[[Any, str], None]) -> None:
        self._subs.append(Subscriber(self.ctx.session, key, cls, handler, self.stats))

    def rig_now_ns(self) -> int:
        return self.clock.now_ns() if self.clock else 0

    def emit_event(self, kind: str, detail: str = "") -> None:
        self._event_pub.put(
            Event(
                seq=self._event_pub.next_seq(),
                stamp_ns=self.rig_now_ns(),
                kind=kind,
                source=self.name,
                detail=detail,
            )
        )

    def extra_status(self) -> dict[str, int]:
        """Counters a subclass computes on demand (queue depths, ...)."""
        return {}

    # -- lifecycle --------------------------------------------------------------------------
    def _status_loop(self) -> None:
        first = True
        supervisor = int(os.environ.get("HIL_SUPERVISOR_PID", "0") or 0)
        next_trim = time.monotonic() + self.heap_trim_s
        while True:
            self._status_now.wait(0 if first else 1.0)
            self._status_now.clear()
            if self.ctx.stop.is_set():
                break
            first = False
            if self.heap_trim_s and time.monotonic() >= next_trim:
                next_trim = time.monotonic() + self.heap_trim_s
                self.heap.trim()
            if supervisor and os.getppid() != supervisor:
                # `hil up` is gone (killed with SIGKILL, say): an orphaned service stops itself
                # rather than run on, unsupervised and unrecorded.
                self.stats.error("errors.orphaned", f"supervisor {supervisor} is gone; stopping")
                self.ctx.stop.set()
                break
            self.publish_status(self._status_pub.next_seq())
        self.state = "stopping"
        self.publish_status(self._status_pub.next_seq())

    def publish_status(self, seq: int) -> None:
        # the state before the counters: a service records why before it says "degraded", so a
        # degraded status always carries its reason
        state = self.state
        rates, counters, last_error = self.stats.snapshot()
        counters.update(self.extra_status())
        counters.update(self.heap.counters())
        try:
            self._status_pub.put(
                ServiceStatus(
                    seq=seq,
                    stamp_ns=self.rig_now_ns(),
                    service=self.name,
                    state=state,
                    pid=os.getpid(),
                    uptime_s=round(time.monotonic() - self._t0, 3),
                    rates_hz=messages.rates(rates),
                    counters=messages.counts(counters),
                    last_error=last_error,
                )
            )
        except Exception as err:  # a closing session must not take the process down
            # its seq is spent: the gap it leaves in the recording is explained by the next status
            self.stats.error("errors.status_publish", f"status seq {seq}: {type(err).__name__}: {err}")
            log.debug("status publish failed: %s", err)

    def _on_run(self, run: RunInfo, _key: str) -> None:
        if self.run_info is None:
            self.run_info = run
            self.clock = RigClock(run.start_epoch_ns, run.speed)
            self._run_event.set()
        elif run.start_epoch_ns != self.run_info.start_epoch_ns:
            self.stats.error("errors.run_changed", "a different run was announced on this rig; ignored")

    def wait_for_run(self) -> RunInfo | None:
        """Block until ``world`` announces the run (or stop)."""
        self.subscribe(self.keys.run(), RunInfo, self._on_run)
        while not self._run_event.wait(0.1):
            if self.ctx.stop.is_set():
                return None
        return self.run_info

    def needs_run(self) -> bool:
        return True

    def start(self) -> None:
        """Run to completion: status thread, wait for the run, the loop, cleanup."""
        self.state = "starting"  # world waits for "waiting_run": only after setup() is a service ready
        self._status_thread.start()
        try:
            self._describe()
            self.setup()
            self.state = "waiting_run" if self.needs_run() else "running"
            if self.needs_run():
                run = self.wait_for_run()
                if run is None:
                    return
                self.state = "running"
                self.run_loop(run, self.clock)  # type: ignore[arg-type]
            else:
                self.run_loop(None, None)  # type: ignore[arg-type]
        finally:
            self.ctx.stop.set()
            self._status_now.set()  # the status thread ends now, not at its next second
            self.teardown()
            self._status_thread.join(timeout=2.0)
            # one more status after the teardown: what went wrong while finishing (a recorder
            # whose index no longer fits on the disk) reaches the supervisor, not only the log
            self.publish_status(self._status_pub.next_seq())
            self.description.close()

    def exit_code(self) -> int:
        """The process's exit code after ``start``: 0, or non-zero when the service failed at its
        job though it stayed up (a recorder that could not write)."""
        return 0

    def _describe(self) -> None:
        """The liveliness token and the topic queryable (``hil.bus.describe``); a bus that
        refuses them costs the description, never the service."""
        try:
            self.description.declare()
        except Exception as err:
            why = f"{type(err).__name__}: {err}"
            self.stats.error("errors.describe", f"liveliness/queryable not declared: {why}")

    def setup(self) -> None:
        """Declare subscriptions/publishers before the run starts (so nothing is missed)."""

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        """Default: event-driven services just wait for stop.

        With a timeout, in a loop: Python runs signal handlers in the main thread only, and a
        SIGTERM the kernel hands to another thread (Zenoh's, the writer's) does not interrupt a
        main thread blocked in an untimed wait -- the service then never stopped (seen on the
        recorder: SIGTERM right after SIGCONT, until the supervisor's SIGKILL).
        """
        while not self.ctx.stop.wait(0.5):
            pass

    def teardown(self) -> None:
        """Flush and close outputs."""


def install_signal_handlers(stop: threading.Event) -> None:
    """SIGTERM and SIGINT stop the service; SIGUSR1 prints the stack of every Python thread to
    stderr and lets it run on (``kill -USR1 PID``: where a service that does not stop is stuck;
    the supervisor's log and a test's captured output then hold it)."""

    handler = EventSetter(stop)  # never stop.set() in the handler: hil.runtime.signals says why
    signal.signal(signal.SIGTERM, handler)
    signal.signal(signal.SIGINT, handler)
    faulthandler.register(signal.SIGUSR1, all_threads=True)


def run_service(cls: type[Service], rig: str, options: dict[str, Any], bus: BusConfig | None = None) -> int:
    """Process entry point shared by ``hil service NAME`` and the per-service console scripts."""
    logging.basicConfig(
        level=os.environ.get("HIL_LOG", "WARNING"), format=f"[{cls.name}] %(levelname)s %(message)s"
    )
    stop = threading.Event()
    install_signal_handlers(stop)
    session = open_session(with_rig_zid(bus or BusConfig.from_env()))
    ctx = ServiceContext(name=cls.name, rig=rig, session=session, stop=stop, options=options)
    try:
        svc = cls(ctx)
        svc.start()
    finally:
        # Let reliable queues drain before the session goes (slow machines lose the tail otherwise).
        time.sleep(0.2)
        session.close()
    return svc.exit_code()


def with_rig_zid(bus: BusConfig) -> BusConfig:
    """The session config with the Zenoh id ``hil up`` chose for this process (``ZENOH_ID_ENV``),
    so the recorder knows the rig's own publishers (``hil.bus.identity``)."""
    zid = os.environ.get(ZENOH_ID_ENV, "").strip()
    if not zid:
        return bus
    return dataclasses.replace(bus, extra={**bus.extra, "id": zid})


def options_from_json(text: str | None) -> dict[str, Any]:
    """Service options as passed by the supervisor (``--options JSON``)."""
    if not text:
        return {}
    value = msgspec.json.decode(text.encode())
    if not isinstance(value, dict):
        raise ValueError("--options must be a JSON object")
    return value

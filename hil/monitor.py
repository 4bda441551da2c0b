"""``hil monitor --rig NAME``: attach to a running rig from another terminal or host, read-only.

Opens a Zenoh session from the environment (``HIL_ZENOH_MODE``/``HIL_ZENOH_CONNECT``/...: point
it at the rig's router or hub), subscribes to ``hil/<rig>/status/*``, ``nav/*``, ``truth`` and
``run``, and draws the same table as ``hil up`` (``LiveView``: one implementation). A service is
shown ``stale`` when its 1 Hz status has not arrived for ``LiveView.STALE_S``.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import IO

import zenoh

from hil.bus.keys import Keys, check_name
from hil.bus.pubsub import Stats, Subscriber
from hil.bus.session import BusConfig, open_session
from hil.messages import NavSolution, RunInfo, ServiceStatus, Truth
from hil.runtime.supervisor import LiveView, TableDrawer


@dataclass
class MonitorOptions:
    rig: str = "bench"
    duration_s: float | None = None  # None: until stopped
    interval_s: float = 1.0
    once: bool = False  # print one table after the first status and return


def connect(rig: str) -> zenoh.Session:
    """The Zenoh session that reaches a running rig from another process or host: what ``hil
    monitor`` and ``hil foxglove`` attach with (one way to find a rig, for both)."""
    check_name("rig", rig)
    return open_session(BusConfig.from_env())


def attach(session: zenoh.Session, rig: str, view: LiveView) -> list[Subscriber]:
    """Subscribe ``view`` to one rig's status, run, truth and solutions."""
    keys = Keys(rig)
    stats = Stats()
    return [
        Subscriber(session, keys.status("*"), ServiceStatus, view.on_status, stats),
        Subscriber(session, keys.run(), RunInfo, view.on_run, stats),
        Subscriber(session, keys.truth(), Truth, view.on_truth, stats),
        Subscriber(session, keys.nav("*"), NavSolution, view.on_nav, stats),
    ]


def run_monitor(
    session: zenoh.Session, opts: MonitorOptions, stop: threading.Event, out: IO[str] | None = None
) -> int:
    """Draw the table until ``stop``, the duration, or (``once``) the first status; 1 if none came."""
    view = LiveView()
    subs = attach(session, opts.rig, view)
    drawer = TableDrawer(out)
    t0 = time.monotonic()
    interval = opts.interval_s if drawer.tty or opts.once else max(opts.interval_s, 5.0)
    last = -1e9
    try:
        while not stop.wait(0.1):
            now = time.monotonic()
            if opts.duration_s is not None and now - t0 >= opts.duration_s:
                break
            if opts.once:
                if view.status and now - t0 >= opts.interval_s:
                    drawer.draw(view.table(now - t0, title=f"hil monitor {opts.rig}"))
                    return 0
                continue
            if now - last >= interval:
                last = now
                drawer.draw(view.table(now - t0, title=f"hil monitor {opts.rig}"))
    finally:
        for s in subs:
            s.undeclare()
    if not view.status:
        drawer.draw(
            f"hil monitor: no status from rig {opts.rig!r} (hil/{opts.rig}/status/*): is it running, and "
            "does HIL_ZENOH_CONNECT reach its router or hub?"
        )
        return 1
    return 0

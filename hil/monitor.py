"""``hil monitor --rig NAME``: attach to a running rig from another terminal or host, read-only.

Opens a Zenoh session (``connect``: the ``HIL_ZENOH_*`` environment when set -- a router, another
host -- else the endpoint file and per-run credential ``hil up`` leaves for its user,
``hil.bus.endpoint``), subscribes to ``hil/<rig>/status/*``, ``nav/*``, ``truth`` and
``run``, and draws the same table as ``hil up`` (``LiveView``: one implementation). A service is
shown ``stale`` when its 1 Hz status has not arrived for ``LiveView.STALE_S``.
"""

from __future__ import annotations

import threading
import time
from dataclasses import dataclass
from typing import IO

import zenoh

from hil.bus.endpoint import viewer_bus
from hil.bus.keys import Keys, check_name
from hil.bus.pubsub import Stats, Subscriber
from hil.bus.session import open_session
from hil.messages import RunInfo, ServiceStatus
from hil.runtime.supervisor import LiveView, SolutionSampler, TableDrawer


def connect(rig: str) -> zenoh.Session:
    """A session that reaches rig ``rig`` the way every viewer does (``hil monitor``, ``hil fault``,
    ``hil foxglove``): see ``hil.bus.endpoint.viewer_bus``. ``BusConfigError`` says why not."""
    check_name("rig", rig)
    cfg, _how = viewer_bus(rig)
    return open_session(cfg)


@dataclass
class MonitorOptions:
    rig: str = "bench"
    duration_s: float | None = None  # None: until stopped
    interval_s: float = 1.0
    once: bool = False  # print one table after the first status and return


def attach(session: zenoh.Session, rig: str, view: LiveView) -> tuple[list[Subscriber], SolutionSampler]:
    """Subscribe ``view`` to one rig's status and run; its truth and solutions through a
    ``SolutionSampler`` (drained before each table: no wake-up per solution, as ``hil up``)."""
    keys = Keys(rig)
    stats = Stats()
    subs = [
        Subscriber(session, keys.status("*"), ServiceStatus, view.on_status, stats),
        Subscriber(session, keys.run(), RunInfo, view.on_run, stats),
    ]
    return subs, SolutionSampler(session, keys, view, stats)


def run_monitor(
    session: zenoh.Session, opts: MonitorOptions, stop: threading.Event, out: IO[str] | None = None
) -> int:
    """Draw the table until ``stop``, the duration, or (``once``) the first status; 1 if none came."""
    view = LiveView()
    subs, sampler = attach(session, opts.rig, view)
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
                    sampler.drain()
                    drawer.draw(view.table(now - t0, title=f"hil monitor {opts.rig}"))
                    return 0
                continue
            if now - last >= interval:
                last = now
                sampler.drain()
                drawer.draw(view.table(now - t0, title=f"hil monitor {opts.rig}"))
    finally:
        for s in subs:
            s.undeclare()
        sampler.undeclare()
    if not view.status:
        _cfg, how = viewer_bus(opts.rig)
        drawer.draw(
            f"hil monitor: no status from rig {opts.rig!r} (hil/{opts.rig}/status/*) via {how}: is it "
            "running, and (on another host) does HIL_ZENOH_CONNECT reach its router?"
        )
        return 1
    return 0

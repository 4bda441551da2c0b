"""``hil sim``: the rig's nodes on a virtual clock in one process, as fast as possible.

The very node objects the live services run (``hil.nodes``) -- world, IMU emulator, CAN bridge,
GNSS emulator, time sync, fusion -- driven by a short discrete-event scheduler instead of Zenoh
and the wall clock. Every node is ticked at the rig time it asks for (``next_tick_ns``) and
handed each message it subscribes to at the instant it is published; the Zenoh bus is modelled
as instantaneous, the CAN bus by ``hil.runners.wire.CanWireModel`` (latency, per-sample extra
delay, wire time, FIFO, the sync frame's latch jitter). Events at the same rig time run in a
fixed order -- the runner's own (status, ``fault_ignored``), then node ticks in pipeline order,
then deliveries first in first out -- so the same scenario gives the same file, byte for byte.

Messages are written as they are published, in rig-time order, with ``log_time`` = the rig time
of publication, so a one-hour session never sits in memory. Each node's status goes out once a
rig second (pid 0, uptime in rig time: nothing host-dependent). ``kill_service`` has no meaning
in one process: a warning line and a ``fault_ignored`` event on ``event/sim`` say so. Every
node stops by itself at the run's end; then each is told ``finish`` (end of input) in pipeline
order at ``end + 1 ns``, so what the time sync and the fusion hold is released and journaled.
"""

from __future__ import annotations

import heapq
import sys
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil import __version__
from hil.faults import SIM_NOT_APPLICABLE, fault_detail
from hil.messages import Event, Message, RunInfo, ServiceStatus, encode
from hil.nav.scenario import load_scenario, scenario_for_run
from hil.nodes import node_class
from hil.nodes.base import CAN_RX, CAN_TX, Node, Out
from hil.nodes.can_bridge import CanBridgeNode, CanBridgeOptions
from hil.nodes.fusion import DEFAULT_LAG_S, DEFAULT_OUTPUT_EVERY, FusionNode, FusionOptions
from hil.nodes.timesync import TimeSyncNode
from hil.nodes.world import WorldNode, WorldOptions, run_info
from hil.record.mcapio import SessionWriter
from hil.runners.wire import CanWireModel
from hil.runtime.scenario_io import run_attachments
from hil.sensor_table import SENSOR_NAMES, SENSORS

__all__ = ["SimOptions", "SimResult", "not_applicable_faults", "run_sim"]
_S = 1_000_000_000
_RUNNER, _TICK, _DELIVER = 0, 1, 2  # order of events at equal rig time


@dataclass
class SimOptions:
    scenario: str = "straight_level"
    duration_s: float | None = None
    record: Path = Path("recordings/sim.mcap")
    rig: str = "sim"
    estimators: list[str] = field(default_factory=list)
    fd: bool = False
    lag_s: float = DEFAULT_LAG_S
    output_every: int = DEFAULT_OUTPUT_EVERY
    progress: bool = False
    on_progress: Any = None  # callable(rig_s_done, rig_s_total), called once per simulated second
    on_warning: Callable[[str], None] | None = None  # default: "hil sim: warning: ..." on stderr


@dataclass
class SimResult:
    path: Path
    messages: int
    duration_s: float
    wall_s: float
    warnings: list[str] = field(default_factory=list)

    @property
    def summary(self) -> str:
        x = self.duration_s / self.wall_s if self.wall_s > 0 else float("inf")
        return (
            f"hil sim: {self.duration_s:g} s of rig time in {self.wall_s:.1f} s ({x:.1f}x real time), "
            f"{self.messages} messages -> {self.path}"
        )


def _matches(pattern: list[str], key: list[str]) -> bool:
    return len(pattern) == len(key) and all(p in ("*", k) for p, k in zip(pattern, key, strict=True))


class Scheduler:
    """The discrete-event loop: node ticks, deliveries and the runner's own events in rig time."""

    def __init__(self, nodes: list[Node], write: Callable[[str, Message, int], None], wire: CanWireModel):
        self.nodes = nodes
        self.write = write
        self.wire = wire
        self._heap: list[tuple[int, int, int, int, int, Any, Any]] = []
        self._order = 0
        self._tick_at: list[int | None] = [None] * len(nodes)
        self._routes: dict[str, list[int]] = {}
        self._can_readers = [i for i, n in enumerate(nodes) if n.reads_can]
        self._can_keys = {i: f"{CAN_RX}/{getattr(nodes[i], 'channel', 'vcan0')}" for i in self._can_readers}
        self._subs = [[(inp.key.split("/"), frozenset(inp.types)) for inp in type(n).inputs] for n in nodes]

    def push(self, t_ns: int, cls: int, kind: int, a: Any, b: Any = None) -> None:
        """``kind`` 0: deliver ``b`` = (key, msg) to node ``a``; 1: a CAN frame ``b`` to node ``a``;
        2: tick node ``a`` (``b``: the time it asked for); 3: the runner's own event ``a``.
        Ticks at equal times go in node (pipeline) order, everything else first in first out."""
        rank = a if kind == 2 else self._order
        heapq.heappush(self._heap, (t_ns, cls, rank, self._order, kind, a, b))
        self._order += 1

    def _route(self, key: str) -> list[int]:
        route = self._routes.get(key)
        if route is None:
            parts = key.split("/")
            route = self._routes[key] = [
                i
                for i, subs in enumerate(self._subs)
                if any(parts[0] in kinds and _matches(p, parts) for p, kinds in subs)
            ]
        return route

    def publish(self, outs: list[Out], now_ns: int) -> None:
        for key, msg in outs:
            if key == CAN_TX:
                for rx, frame in self.wire.arrivals(msg, now_ns):
                    for i in self._can_readers:
                        self.push(rx, _DELIVER, 1, i, frame)
                continue
            self.write(key, msg, now_ns)
            for i in self._route(key):
                self.push(now_ns, _DELIVER, 0, i, (key, msg))

    def reschedule(self, i: int) -> None:
        t = self.nodes[i].next_tick_ns()
        if t is not None and t != self._tick_at[i]:
            self._tick_at[i] = t
            self.push(t, _TICK, 2, i, t)

    def run(self, on_runner_event: Callable[[int, Any], None]) -> None:
        """Until every node is done and nothing is in flight."""
        for i in range(len(self.nodes)):
            self.reschedule(i)
        heap = self._heap
        nodes = self.nodes
        while heap:
            t, _cls, _r, _o, kind, a, b = heapq.heappop(heap)
            if kind == 2:  # a tick (stale if the node asked for another time since)
                if self._tick_at[a] != b:
                    continue
                self._tick_at[a] = None
                self.publish(nodes[a].tick(t), t)
            elif kind == 0:
                key, msg = b
                self.publish(nodes[a].on_message(key, msg, t), t)
            elif kind == 1:
                self.publish(nodes[a].on_message(self._can_keys[a], b, t), t)
            else:
                on_runner_event(t, a)
                continue
            self.reschedule(a)


def sim_nodes(run: RunInfo, opts: SimOptions) -> list[Node]:
    """The rig's nodes in pipeline order, configured as ``hil up`` would configure them: the
    world, each sensor's emulator of the sensor table (a CAN device followed by the bridge that
    reads its bus), the time sync, the fusion."""
    nodes: list[Node] = [WorldNode(run, WorldOptions(announce_every_s=0.0))]
    for sensor in SENSOR_NAMES:
        cls = node_class(SENSORS[sensor].emulator)
        fields = cls.Options.__struct_fields__
        nodes.append(cls(run, cls.Options(**({"fd": opts.fd} if "fd" in fields else {}))))
        if cls.writes_can:
            nodes.append(CanBridgeNode(run, CanBridgeOptions(fd=opts.fd)))
    fusion = FusionOptions(estimators=list(opts.estimators), lag_s=opts.lag_s, output_every=opts.output_every)
    return [*nodes, TimeSyncNode(run), FusionNode(run, fusion)]


def sim_run_info(opts: SimOptions) -> RunInfo:
    """The run ``hil sim`` announces: time zero at epoch 0, speed 1, the scenario's text."""
    base = load_scenario(opts.scenario)
    return run_info(base, rig=opts.rig, start_epoch_ns=0, speed=1.0, duration_s=opts.duration_s)


class _Session:
    """The recording side of one sim: the writer, runner-owned seqs, status, progress."""

    def __init__(self, run: RunInfo, opts: SimOptions, nodes: list[Node]) -> None:
        self.root = f"hil/{run.rig}"
        self.nodes = nodes
        self.opts = opts
        self.end_ns = int(run.duration_s * 1e9)
        self.w = SessionWriter(opts.record)
        self.n_written = 0
        self._seqs: dict[str, int] = {}
        self._topics: dict[str, str] = {}

    def write(self, key: str, msg: Message, t_log: int) -> None:
        topic = self._topics.get(key)
        if topic is None:
            topic = self._topics[key] = f"{self.root}/{key}"
        self.w.write(
            topic, type(msg), encode(msg), log_time_ns=t_log, publish_time_ns=msg.stamp_ns, seq=msg.seq
        )
        self.n_written += 1

    def next_seq(self, key: str) -> int:
        n = self._seqs.get(key, 0)
        self._seqs[key] = n + 1
        return n

    def status(self, t_ns: int) -> None:
        """Each node's counters as its live service would report them; nothing host-dependent."""
        for node in self.nodes:
            key = f"status/{node.name}"
            st = ServiceStatus(
                seq=self.next_seq(key),
                stamp_ns=t_ns,
                service=node.name,
                state="running",
                pid=0,
                uptime_s=t_ns / 1e9,
                counters=node.counters(),
                last_error=node.last_error,
            )
            self.write(key, st, t_ns)

    def on_event(self, t_ns: int, what: Any) -> None:
        if what == "second":
            if t_ns < self.end_ns:
                self.status(t_ns)
            self.w.flush()
            if self.opts.on_progress is not None:
                self.opts.on_progress(min(t_ns, self.end_ns) * 1e-9, self.end_ns * 1e-9)
            return
        key = "event/sim"  # a fault_ignored
        self.write(
            key,
            Event(seq=self.next_seq(key), stamp_ns=t_ns, kind="fault_ignored", source="sim", detail=what),
            t_ns,
        )


def run_sim(opts: SimOptions) -> SimResult:
    t_wall = time.monotonic()
    run = sim_run_info(opts)
    s = scenario_for_run(run)
    nodes = sim_nodes(run, opts)
    sess = _Session(run, opts, nodes)
    _header(sess.w, run, s)
    warnings, ignored = not_applicable_faults(s.events, run.duration_s)
    for line in warnings:
        if opts.on_warning is not None:
            opts.on_warning(line)
        else:
            sys.stderr.write(f"hil sim: warning: {line}\n")
            sys.stderr.flush()
    sched = Scheduler(nodes, sess.write, CanWireModel(s))
    for t0, detail in ignored:
        sched.push(t0, _RUNNER, 3, detail)
    for k in range(1, sess.end_ns // _S + 2):
        sched.push(k * _S, _RUNNER, 3, "second")
    for node in nodes:
        sched.publish(node.start(0), 0)
    sched.run(sess.on_event)
    t_last = sess.end_ns + 1
    for node in nodes:  # end of input, in pipeline order: what one releases, the next consumes
        sched.publish(node.finish(t_last), t_last)
        sched.run(sess.on_event)
    sess.status(t_last)
    sess.w.add_metadata(
        "completeness", {"messages": sess.n_written, "missing": 0, "replay_ready": True, "topics": {}}
    )
    sess.w.close()
    return SimResult(opts.record, sess.n_written, run.duration_s, time.monotonic() - t_wall, warnings)


def _header(w: SessionWriter, run: RunInfo, s: Any) -> None:
    w.add_metadata(
        "hil",
        {
            "version": __version__,
            "rig": run.rig,
            "scenario": s.name,
            "scenario_sha256": run.scenario_sha256,
            "seed": s.seed,
            "start_epoch_ns": 0,
            "speed": 0,
            "duration_s": run.duration_s,
            "origin_lat_deg": s.origin_lat_deg,
            "origin_lon_deg": s.origin_lon_deg,
            "origin_alt_m": s.origin_alt_m,
            "executor": "sim",
        },
    )
    for name, data, media in run_attachments(run):
        w.add_attachment(name, data, media)


def not_applicable_faults(events: Any, duration_s: float) -> tuple[list[str], list[tuple[int, str]]]:
    """The scenario's timed faults ``hil sim`` cannot apply: warning lines, and (t_ns, detail) of
    the ``fault_ignored`` events that record them (only those inside the run, as live)."""
    lines: list[str] = []
    ignored: list[tuple[int, str]] = []
    for ev in events:
        if ev.kind not in SIM_NOT_APPLICABLE or ev.t_start_s > duration_s:
            continue
        t0 = round(ev.t_start_s * 1e9)
        target = ev.params.get("service", "")
        lines.append(
            f"{ev.kind} of {target!r} at t={ev.t_start_s:g} s is not applied: hil sim runs every core "
            "in one process, there is no service to kill (use hil up; recorded as event fault_ignored)"
        )
        params = {"service": target, "reason": "offline"}
        ignored.append((t0, fault_detail(ev.kind, t0, None, params, "scenario")))
    ignored.sort()
    return lines, ignored

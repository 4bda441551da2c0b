"""``hil sim``: the rig's nodes on a virtual clock in one process, as fast as possible.

The very node objects the live services run (``hil.nodes``) -- world, IMU emulator, CAN bridge,
GNSS emulator, time sync, fusion -- driven by a short discrete-event scheduler instead of Zenoh
and the wall clock. Every node is ticked at the rig time it asks for (``next_tick_ns``) and
handed each message it subscribes to at the instant it is published; the Zenoh bus is modelled
as instantaneous, the CAN bus by ``hil.runners.wire.CanWireModel`` (latency, per-sample extra
delay, wire time, FIFO, the sync frame's latch jitter). Events at the same rig time run in a
fixed order -- the runner's own (status, ``fault_ignored``), then node ticks in pipeline order,
then deliveries first in first out -- so the same scenario gives the same file, byte for byte.

Beside each message go the Foxglove well-known types derived from it (``hil.wellknown``: map
positions, frame transforms, log lines), as the live recorder writes them. Messages are written as
they are published, in rig-time order, with ``log_time`` = the scenario's
``start_utc`` + the rig time of publication (``hil.record.mcapio``: the wall-clock timeline), so a
one-hour session never sits in memory. Each node's status goes out once a
rig second (pid 0, uptime in rig time: nothing host-dependent). ``kill_service`` has no meaning
in one process: a warning line and a ``fault_ignored`` event on ``event/sim`` say so. Every
node stops by itself at the run's end; then each is told ``finish`` (end of input) in pipeline
order at ``end + 1 ns``, so what the time sync and the fusion hold is released and journaled.

With two CPUs the pipeline's tail runs in a forked worker one window behind the rest
(``hil.runners.sim_worker.RemoteTail``): the fusion, and when the fusion is light the nodes
between the CAN bridge and it too (``tail_split``: chosen to balance the two processes). The
worker runs the same node objects through a scheduler of its own, with the same inputs in the
same order; its outputs come back encoded for the file (``_Session.prepare``: their bytes and
the Foxglove messages derived from them) and join their window before it is written, so the
file is the one-process file byte for byte (``fusion_worker=False`` / ``--one-process``: one).
This process writes the file: a third process that wrote it (tried in session 24) made the sim
slower beside the worker on two CPUs (docs/benchmarks.md, session 25's reading).
"""

from __future__ import annotations

import collections
import operator
import sys
import time
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil import __version__
from hil.faults import SIM_NOT_APPLICABLE, fault_detail, unwired_line_fault_warnings
from hil.messages import Event, Message, RunInfo, ServiceStatus, counts, encode
from hil.nav.scenario import load_scenario, scenario_for_run, scenario_overrides
from hil.nodes import node_class
from hil.nodes.base import CAN_RX, CAN_TX, SERIAL_RX, SERIAL_TX, Node, Out
from hil.nodes.can_bridge import CanBridgeNode, CanBridgeOptions
from hil.nodes.fusion import DEFAULT_LAG_S, DEFAULT_OUTPUT_EVERY, FusionNode, FusionOptions
from hil.nodes.gnss_bridge import GnssBridgeNode, GnssBridgeOptions
from hil.nodes.timesync import TimeSyncNode
from hil.nodes.world import WorldNode, WorldOptions, run_info
from hil.record.keyfilter import KeyFilter
from hil.record.mcapio import (
    TIME_SEMANTICS,
    SessionWriter,
    keep_aside,
    made_by_sim,
    part_metadata,
    split_part_path,
    stale_parts_note,
    write_failed,
)
from hil.runners.sim_worker import WORKER_MIN_ESTIMATORS, RemoteTail, drive, portable, worker_possible
from hil.runners.wire import CanWireModel
from hil.runtime import jit
from hil.runtime.heap import freeze_command_startup
from hil.runtime.scenario_io import run_attachments
from hil.sensor_table import SENSOR_NAMES, SENSORS
from hil.wellknown import WellKnown, derives

__all__ = ["SimOptions", "SimResult", "not_applicable_faults", "run_sim"]
_S = 1_000_000_000


@dataclass
class SimOptions:
    scenario: str = "straight_level"
    duration_s: float | None = None
    record: Path = Path("recordings/sim.mcap")
    rig: str = "sim"
    estimators: list[str] = field(default_factory=list)
    feedback: str = "auto"  # seed estimators in feedback form (hil.nodes.fusion.FusionOptions)
    ekf_calibration: str = "auto"  # ekf15's calibration states (same)
    fd: bool = False
    gnss_protocol: list[str] = field(default_factory=list)  # the receiver on a wire: nmea, ubx
    gnss_baud: int = 115200
    gnss_messages: list[str] = field(default_factory=list)
    lag_s: float = DEFAULT_LAG_S
    output_every: int = DEFAULT_OUTPUT_EVERY
    output_predictor: bool = True  # False: the fusion publishes its horizon's state, lag_s late
    progress: bool = False
    on_progress: Any = None  # callable(rig_s_done, rig_s_total), called once per simulated second
    on_warning: Callable[[str], None] | None = None  # default: "hil sim: warning: ..." on stderr
    imu_rate_hz: int | None = None  # override the scenario's IMU rate (as hil up --imu-rate)
    split_mb: float = 0.0  # a new part (<stem>_0001.mcap, ...) after this many MB, as the recorder
    split_s: float = 0.0  # ... or after this many seconds of rig time
    record_include: list[str] = field(default_factory=list)  # hil.record.keyfilter, as the recorder
    record_exclude: list[str] = field(default_factory=list)
    # the pipeline's tail (the fusion, with a light fusion the nodes from the CAN bridge on) in a
    # second process, one window behind the rest (tail_split, hil.runners.sim_worker); the file
    # is the same byte for byte. None: when fork exists and two CPUs are available
    fusion_worker: bool | None = None
    # asked at every window boundary: True ends the run there, as its end would (``stopped_at_s``)
    stop: Callable[[], bool] | None = None


@dataclass
class SimResult:
    path: Path
    messages: int
    duration_s: float
    wall_s: float
    warnings: list[str] = field(default_factory=list)
    stopped_at_s: float | None = None  # rig time where ``stop`` ended the run (None: it ran out)
    fusion_counts: dict[str, int] = field(default_factory=dict)  # the fusion's last status counters

    @property
    def summary(self) -> str:
        done = self.duration_s if self.stopped_at_s is None else self.stopped_at_s
        x = done / self.wall_s if self.wall_s > 0 else float("inf")
        head = f"hil sim: {done:g} s of rig time"
        if self.stopped_at_s is not None:
            head = f"hil sim: stopped at {done:g} s of {self.duration_s:g} s of rig time"
        return f"{head} in {self.wall_s:.1f} s ({x:.1f}x real time), {self.messages} messages -> {self.path}"


def _matches(pattern: list[str], key: list[str]) -> bool:
    return len(pattern) == len(key) and all(p in ("*", k) for p, k in zip(pattern, key, strict=True))


class Scheduler:
    """Rig time in windows; in each, every node in pipeline order handles its window's events.

    The nodes form a pipeline (every subscription runs downstream: emulators -> bridges -> time
    sync -> fusion; checked at start), so once the nodes upstream of a node have handled a window,
    all of its inputs in that window are known: it can handle its window in one go, its ticks and
    inputs in rig-time order -- the very sequence a global event loop would hand it, and the
    stage-by-stage order that keeps each node's code and data warm (measured: interleaving every
    node per IMU sample cost this runner 20-25 % of its time). At one rig time a node's tick comes
    before its inputs, inputs come in pipeline order of their producers and then in the order
    they were published. A CAN frame or a line burst that arrives after the window waits for the
    next. Each window's messages are written sorted by log time, so the file is in rig-time order.
    """

    def __init__(
        self,
        nodes: list[Node],
        write: Callable[[list[tuple[int, int, int, str, Message]]], None],
        wire: CanWireModel,
        remote: RemoteTail | None = None,
        first_order: int = 0,
    ):
        self.nodes = nodes
        self.write = write
        self.wire = wire
        # the nodes from ``remote.split`` on, run by a worker process (``hil.runners.sim_worker``):
        # their window's outputs come back while this process works on the next window
        self.remote = remote
        self._split = remote.split if remote is not None else len(nodes)
        self._routes: dict[str, list[int]] = {}
        self._can_readers = [i for i, n in enumerate(nodes) if n.reads_can]
        self._line_readers = [i for i, n in enumerate(nodes) if n.serial == "rx"]
        self._can_keys = {i: f"{CAN_RX}/{getattr(nodes[i], 'channel', 'vcan0')}" for i in self._can_readers}
        self._subs = [[(inp.key.split("/"), frozenset(inp.types)) for inp in type(n).inputs] for n in nodes]
        # per node: its inputs not handled yet, (rig time, producer, order, key, message)
        self._inbox: list[list[tuple[int, int, int, str, Any]]] = [[] for _ in nodes]
        self._order = first_order
        self._out: list[tuple[int, int, int, str, Message]] = []  # this window's messages to write

    def _route(self, key: str) -> list[int]:
        route = self._routes.get(key)
        if route is None:
            parts = key.split("/")
            route = self._routes[key] = [
                i
                for i, subs in enumerate(self._subs)
                if any(parts[0] in kinds and _matches(p, parts) for p, kinds in subs)
            ]
            late = [self.nodes[i].name for i in route if i <= self._producer]
            if late:
                raise RuntimeError(f"{key} flows upstream to {late}: hil sim needs a pipeline of nodes")
        return route

    def publish(self, producer: int, outs: list[Out], now_ns: int) -> None:
        self._producer = producer
        inbox, routes, out = self._inbox, self._routes, self._out
        order = self._order
        for key, msg in outs:
            order += 1
            if key == CAN_TX:
                for rx, frame in self.wire.arrivals(msg, now_ns):
                    for i in self._can_readers:
                        inbox[i].append((rx, producer, order, self._can_keys[i], frame))
                continue
            if key == SERIAL_TX:  # a receiver's bytes: read whole when the last one is in
                for i in self._line_readers:
                    inbox[i].append((msg.end_ns, producer, order, f"{SERIAL_RX}/{msg.port}", msg.data))
                continue
            event = (now_ns, producer, order, key, msg)
            out.append(event)
            route = routes.get(key)
            for i in route if route is not None else self._route(key):
                inbox[i].append(event)
        self._order = order

    def window(self, t_end_ns: int) -> bool:
        """Every node handles its events before ``t_end_ns``; the messages are written. False
        once nothing is left to do (no node wants a tick, nothing is in flight)."""
        busy = self.dispatch(t_end_ns)
        out = self.take_out()
        return self.complete(out) or busy

    def dispatch(self, t_end_ns: int) -> bool:
        """Every node handles its events before ``t_end_ns`` (a remote one: they are sent to
        it). Whether one of this process's nodes wants a tick or anything is in flight."""
        busy = False
        for i, node in enumerate(self.nodes[: self._split]):
            busy = self._handle(i, node, t_end_ns) or busy
        if self.remote is not None:
            self.remote.window(self._ship(t_end_ns), t_end_ns)
        return busy or any(self._inbox)

    def _ship(self, t_end_ns: int) -> list[list[tuple[Any, ...]]]:
        """The remote nodes' inputs before ``t_end_ns``, as they cross to the worker."""
        return [[portable(e) for e in self._now(j, t_end_ns)] for j in range(self._split, len(self.nodes))]

    def run_tail(
        self, split: int, boxes: list[list[Any]], t_end_ns: int, finish_ns: int | None
    ) -> tuple[list[tuple[int, int, int, str, Message]], bool]:
        """A worker's window (``hil.runners.sim_worker.RemoteTail``): nodes ``split`` on take
        ``boxes``, their inputs from upstream, and handle the window as ``dispatch`` would here
        (then, at ``finish_ns``, are told ``finish`` in turn, as ``finish`` would). Their
        messages (``complete`` sorts them with this process's), and whether one still wants a
        tick or has input in flight."""
        for j, box in enumerate(boxes, split):
            self._inbox[j].extend(box)
        busy = False
        for i in range(split, len(self.nodes)):
            node = self.nodes[i]
            busy = self._handle(i, node, t_end_ns) or busy
            if finish_ns is not None:
                self.publish(i, node.finish(finish_ns), finish_ns)
        return self.take_out(), busy or any(self._inbox[split:])

    def take_out(self) -> list[tuple[int, int, int, str, Message]]:
        """The window's messages so far (the remote node's are added by ``complete``)."""
        out, self._out = self._out, []
        return out

    def complete(self, out: list[tuple[int, int, int, str, Message]]) -> bool:
        """The remote nodes' outputs of the window ``out`` belongs to (the oldest they were sent)
        join ``out``, which is written sorted. Whether a remote node wants a tick."""
        busy = False
        if self.remote is not None:
            busy = self._take_remote(out)
        out.sort(key=_event_order)
        self.write(out)
        return busy

    def _take_remote(self, out: list[tuple[int, int, int, str, Message]]) -> bool:
        assert self.remote is not None
        events, busy = self.remote.result()
        out.extend(events)
        return busy

    def _now(self, i: int, t_end_ns: int) -> list[tuple[int, int, int, str, Any]]:
        """Node ``i``'s inputs before ``t_end_ns``, taken from its inbox, sorted."""
        box = self._inbox[i]
        now = [e for e in box if e[0] < t_end_ns]
        if len(now) < len(box):
            self._inbox[i] = [e for e in box if e[0] >= t_end_ns]
        else:
            box.clear()
        now.sort(key=_event_order)
        return now

    def _handle(self, i: int, node: Node, t_end_ns: int) -> bool:
        now = self._now(i, t_end_ns)

        def publish(outs: list[Out], t: int) -> None:
            self.publish(i, outs, t)

        return drive(node, now, t_end_ns, publish)

    def emit(self, t_ns: int, key: str, msg: Message) -> None:
        """A message of the runner's own (``event/sim``), written in its place in rig time."""
        self._out.append((t_ns, -1, self._order, key, msg))
        self._order += 1

    def finish(self, t_ns: int, stopped: bool = False) -> None:
        """End of input, in pipeline order: what one node releases, the next still takes in.
        ``stopped``: the run ends at ``t_ns`` before its nodes are done; none of them ticks
        past it, and what is still on its way to one (a frame on the wire) stays there."""
        for i, node in enumerate(self.nodes[: self._split]):
            self._handle(i, node, t_ns + 1)  # what is still in flight for it
            self.publish(i, node.finish(t_ns), t_ns)
        if self.remote is not None:  # the same, node after node, in the worker
            self.remote.finish_request(self._ship(t_ns + 1), t_ns + 1, t_ns)
            self._take_remote(self._out)
        if not stopped:
            self.window(2**62)
            return
        out = self.take_out()
        out.sort(key=_event_order)
        self.write(out)


# (rig time, producer in pipeline order, publication order): never compares the messages
_event_order = operator.itemgetter(0, 1, 2)


def sim_nodes(run: RunInfo, opts: SimOptions) -> list[Node]:
    """The rig's nodes in pipeline order, configured as ``hil up`` would configure them: the
    world, each sensor's emulator of the sensor table (a CAN device followed by the bridge that
    reads its bus), the time sync, the fusion."""
    nodes: list[Node] = [WorldNode(run, WorldOptions(announce_every_s=0.0, truth_batch=1))]
    wire: dict[str, Any] = {
        "protocol": opts.gnss_protocol,
        "baud": opts.gnss_baud,
        "messages": opts.gnss_messages,
    }
    for sensor in SENSOR_NAMES:
        cls = node_class(SENSORS[sensor].emulator)
        fields = cls.Options.__struct_fields__
        kw: dict[str, Any] = {"fd": opts.fd} if "fd" in fields else {}
        if "pull_block_s" in fields:
            kw["pull_block_s"] = 1.0  # no commands offline: a second's epochs in one batch
        if cls.serial == "tx" and opts.gnss_protocol:
            kw.update(wire)
        nodes.append(cls(run, cls.Options(**kw)))
        if cls.writes_can:
            nodes.append(CanBridgeNode(run, CanBridgeOptions(fd=opts.fd)))
        if cls.serial == "tx" and opts.gnss_protocol:  # the line's reader: the rig's GNSS bridge
            nodes.append(GnssBridgeNode(run, GnssBridgeOptions(**wire)))
    fusion = FusionOptions(
        estimators=list(opts.estimators),
        lag_s=opts.lag_s,
        output_every=opts.output_every,
        output_predictor=opts.output_predictor,
        feedback=opts.feedback,
        ekf_calibration=opts.ekf_calibration,
    )
    return [*nodes, TimeSyncNode(run), FusionNode(run, fusion)]


def sim_run_info(opts: SimOptions) -> RunInfo:
    """The run ``hil sim`` announces: time zero at the scenario's ``start_utc``, speed 1, its text."""
    base = load_scenario(opts.scenario)
    if opts.imu_rate_hz:
        base = scenario_overrides(base, imu_rate_hz=int(opts.imu_rate_hz))
    start = base.start_utc_ns
    return run_info(
        base, rig=opts.rig, start_epoch_ns=start, speed=1.0, duration_s=opts.duration_s, imu_can_fd=opts.fd
    )


# a message as the file takes it, made by the worker that published it (``_Session.prepare``):
# (log time, producer, order, key, its class, its bytes, stamp_ns, seq, the Foxglove messages
# derived from it); a flat tuple, as it is pickled back (a NamedTuple cost ~1 µs more a side)
Prepared = tuple[int, int, int, str, type, bytes, int, int, Any]


class _Session:
    """The recording side of one sim: the writer, runner-owned seqs, status, progress."""

    def __init__(self, run: RunInfo, opts: SimOptions, nodes: list[Node]) -> None:
        self.root = f"hil/{run.rig}"
        self.nodes = nodes
        self.opts = opts
        self.end_ns = int(run.duration_s * 1e9)
        self.stopped_at_ns: int | None = None  # where ``opts.stop`` ended the run
        self.epoch_ns = run.start_epoch_ns  # rig time zero on the wall-clock timeline
        self.w = SessionWriter(opts.record)
        self.wellknown = WellKnown(start_epoch_ns=run.start_epoch_ns)  # Foxglove's types, as live
        self.keep = KeyFilter(run.rig, opts.record_include, opts.record_exclude)
        self.part = 0
        self.part_t0_ns = 0
        self.n_written = 0
        self.last_counts: dict[str, list[Any]] = {}  # each node's counters in its last status
        self._seqs: dict[str, int] = {}
        self._chans: dict[str, int | None] = {}  # per key, its channel (None: not recorded)

    def write(self, key: str, msg: Message, t_log: int) -> None:
        self.write_events(((t_log, 0, 0, key, msg),))

    def write_events(self, events: Iterable[tuple[int, int, int, str, Message] | Prepared]) -> None:
        """Messages in file order, each ``(log time, _, _, key, message)`` or ``Prepared`` (a
        window's, sorted: ``Scheduler.complete``), as columns of the writer's queue, written in
        one batch (~3000 a window)."""
        chans, epoch, w, convert = self._chans, self.epoch_ns, self.w, self.wellknown.convert
        q = w.queue
        chan_, log_, data_ = q.chans.append, q.logs.append, q.datas.append
        pub_, seq_ = q.pubs.append, q.seqs.append
        n = 0
        for ev in events:
            t_log, key, msg = ev[0], ev[3], ev[4]
            chan = chans.get(key)
            if chan is None:
                if key in chans:
                    continue  # left out by the record filter, and nothing derived from it
                chan = self._bind(key, msg)
                if chan is None:
                    continue
            log_ns = epoch + t_log
            chan_(chan)
            log_(log_ns)
            if len(ev) > 5:  # Prepared: encoded, and its Foxglove messages derived, by the worker
                data_(ev[5])  # type: ignore[misc]
                pub_(epoch + ev[6])  # type: ignore[misc]
                seq_(ev[7])  # type: ignore[misc]
                for d in ev[8]:  # type: ignore[misc]
                    w.queue_wellknown(d, log_ns)
            else:
                data_(encode(msg))  # type: ignore[arg-type]  # a Message: Prepared went above
                pub_(epoch + msg.stamp_ns)  # type: ignore[union-attr]
                seq_(msg.seq)  # type: ignore[union-attr]
                # the CAN frames, IMU samples and capture times (most of the traffic) derive
                # none: the converter is not called (test_sim_worker: the same file if it were)
                if derives(type(msg)):
                    for d in convert(key, msg, log_ns):  # type: ignore[arg-type]
                        w.queue_wellknown(d, log_ns)
            n += 1
        self.n_written += n

    def _bind(self, key: str, msg: Message | type) -> int | None:
        """The channel of ``key``, registered at its first message (or, prepared, its class)
        (None: not kept)."""
        topic = f"{self.root}/{key}"
        if self.keep.active and not self.keep.keeps(topic):
            self._chans[key] = None
            return None
        cls = msg if isinstance(msg, type) else type(msg)
        chan = self._chans[key] = self.w.channel(topic, cls)
        return chan

    def prepare(self, event: tuple[int, int, int, str, Message]) -> Prepared:
        """What ``write_events`` needs of a message, made where it was published (the worker):
        its bytes, and the Foxglove messages derived from it -- the worker's copy of the
        converter sees the keys of the worker's nodes only, as this process's sees the others'."""
        t_log, producer, order, key, msg = event
        derived: Any = ()
        if derives(type(msg)):
            derived = self.wellknown.convert(key, msg, self.epoch_ns + t_log)
        return (t_log, producer, order, key, type(msg), encode(msg), msg.stamp_ns, msg.seq, derived)

    def maybe_split(self, t_ns: int, header: Callable[[SessionWriter], None]) -> None:
        """At a window boundary, as the recorder at a flush: finish the part once it reached
        ``split_mb`` or ``split_s`` of rig time, and open the next with the same metadata."""
        o = self.opts
        due = (o.split_mb and self.w.tell() >= o.split_mb * 1e6) or (
            o.split_s and t_ns - self.part_t0_ns >= o.split_s * 1e9
        )
        if not due or t_ns > self.end_ns:
            return
        self.w.add_metadata("completeness", {**self._completeness(), "part": self.part})
        self.w.close()
        self.part += 1
        self.part_t0_ns = t_ns
        self.w = SessionWriter(split_part_path(o.record, self.part), after=self.w)
        self._chans.clear()  # the channels of the new part: registered at their first message
        self.w.add_metadata(
            "part", {"index": self.part, **part_metadata(split_part_path(o.record, self.part - 1))}
        )
        header(self.w)

    def _completeness(self) -> dict[str, Any]:
        out = {"messages": self.n_written, "missing": 0, "replay_ready": True, "topics": {}}
        if self.stopped_at_ns is not None:  # the run ended there, before its duration
            out["stopped_at_s"] = self.stopped_at_ns / 1e9
        return out

    def close(self) -> None:
        self.w.add_metadata(
            "completeness", {**self._completeness(), "part": self.part, "parts": self.part + 1}
        )
        self.w.close()

    def next_seq(self, key: str) -> int:
        n = self._seqs.get(key, 0)
        self._seqs[key] = n + 1
        return n

    def snapshot(self, remote: RemoteTail | None = None) -> list[tuple[str, list[Any], str]]:
        """Each node's name, counters and last error now (``remote``: those of the nodes it
        runs, as its worker reported them with its latest window), for ``status``."""
        nodes = self.nodes if remote is None else self.nodes[: remote.split]
        snap = [(n.name, counts(n.counters()), n.last_error) for n in nodes]
        if remote is not None:
            snap += self.remote_rows(remote)
        return snap

    @staticmethod
    def remote_rows(remote: RemoteTail) -> list[tuple[str, list[Any], str]]:
        """The worker's nodes' counters and last errors, as of its latest window taken."""
        return [(name, counts(c), err) for name, c, err in remote.snapshot()]

    def status(self, t_ns: int, snap: list[tuple[str, list[Any], str]]) -> None:
        """Each node's counters as its live service would report them; nothing host-dependent."""
        for name, node_counts, last_error in snap:
            self.last_counts[name] = node_counts
            key = f"status/{name}"
            st = ServiceStatus(
                seq=self.next_seq(key),
                stamp_ns=t_ns,
                service=name,
                state="running",
                pid=0,
                uptime_s=t_ns / 1e9,
                counters=node_counts,
                last_error=last_error,
            )
            self.write(key, st, t_ns)


def run_sim(opts: SimOptions) -> SimResult:
    t_wall = time.monotonic()
    run = sim_run_info(opts)
    s = scenario_for_run(run)
    nodes = sim_nodes(run, opts)
    use_worker = opts.fusion_worker
    if use_worker is None:
        use_worker = worker_possible()
    split = tail_split(nodes) if use_worker else len(nodes)

    def warn(line: str) -> None:
        if opts.on_warning is not None:
            opts.on_warning(line)
        else:
            sys.stderr.write(f"hil sim: warning: {line}\n")
            sys.stderr.flush()

    for line in _keep_earlier(opts.record):
        warn(line)
    sess = _Session(run, opts, nodes)

    def header(w: SessionWriter) -> None:
        _header(w, run, s)

    try:
        header(sess.w)
    except OSError as err:
        sess.w.abandon()
        raise write_failed(opts.record, err) or err from None
    warnings, ignored = not_applicable_faults(s.events, run.duration_s)
    if not opts.gnss_protocol:
        warnings += unwired_line_fault_warnings(s.events, run.duration_s, "hil sim")
    for line in warnings:
        warn(line)
    wire = CanWireModel(s)
    # the fusion's kernels compiled where it runs (the same bits either way): with a worker, in
    # the worker; this process, which runs no fusion, does not import numba
    if not use_worker:
        jit.enable()
    outs0 = [node.start(0) for node in nodes]
    freeze_command_startup()  # the nodes, the writer and the modules live as long as the run
    # forked after start; its outputs come back encoded for the file (``_Session.prepare``)
    remote = None
    if use_worker:

        def tail_scheduler() -> Scheduler:  # the worker's: its events after those made here
            return Scheduler(nodes, _unused_write, wire, first_order=_TAIL_ORDER)

        remote = RemoteTail(nodes, split, tail_scheduler, setup=jit.enable_for_run, prepare=sess.prepare)
    try:
        sched = Scheduler(nodes, sess.write_events, wire, remote)
        for i, outs in enumerate(outs0):
            sched.publish(i, outs, 0)
        _windows(sched, sess, opts, ignored, header, remote)
    except BaseException as err:
        sess.w.abandon()  # what was flushed stays readable
        failed = write_failed(opts.record, err)
        if failed is not None:
            raise failed from None
        raise
    finally:
        if remote is not None:
            remote.close()
    try:
        sess.close()
    except OSError as err:
        raise write_failed(opts.record, err) or err from None
    stopped = None if sess.stopped_at_ns is None else sess.stopped_at_ns / 1e9
    wall_s = time.monotonic() - t_wall
    fusion = {c.key: c.value for c in sess.last_counts.get("fusion", [])}
    return SimResult(opts.record, sess.n_written, run.duration_s, wall_s, warnings, stopped, fusion)


def _keep_earlier(record: Path) -> list[str]:
    """What is at ``record`` before a sim writes there. A sim's own file (finished or cut off) is
    written over: the same options make it again. Anything else, a live session first of all, is
    moved aside with its parts (``keep_aside``), as the recorder does; part names an older
    recording left are said. Returns the lines to warn with."""
    lines = []
    if record.is_file() and record.stat().st_size > 0 and not made_by_sim(record):
        kept = keep_aside(record)
        lines.append(f"{record} held a recording that no sim makes again (a live session?): kept as {kept}")
    note = stale_parts_note(record)
    if note:
        lines.append(note)
    return lines


def tail_split(nodes: list[Node]) -> int:
    """Where the worker's part of the pipeline starts, to balance the two processes (the
    world, the IMU emulator and the wire model always stay here: never a CAN writer there).

    - A fusion of several estimators in feedback form or with ekf15's calibration states (a
      consumer IMU's defaults): the fusion alone, which is then most of the work;
    - several estimators without (a tactical IMU's): everything after the CAN bridges, the GNSS
      emulator, time sync and fusion;
    - one or two (``--estimators ins``): the CAN bridges too.

    Measured on 2 CPUs (docs/benchmarks.md, session 25's reading): straight_level 300 s
    8.31-9.05 s with the GNSS emulator on against 9.63-10.65 s with the fusion alone; uav_survey
    and car_drive 120 s 3-7 % slower that way; static 300 s with ``--estimators ins`` 6.92-7.33 s
    from the CAN bridge on, 9.0-10.0 s with the fusion alone."""
    fusion = nodes[-1]
    readers = [i for i, n in enumerate(nodes) if n.reads_can]
    writers = [i for i, n in enumerate(nodes) if n.writes_can]
    after_writers = writers[-1] + 1 if writers else 0
    if not readers:
        return len(nodes) - 1
    cfg = getattr(fusion, "config", None)
    if len(getattr(cfg, "estimators", ())) >= WORKER_MIN_ESTIMATORS:
        if getattr(cfg, "feedback", ()) or getattr(cfg, "ekf_calibration", ""):
            return len(nodes) - 1
        return min(len(nodes) - 1, max(readers[-1] + 1, after_writers))
    return min(len(nodes) - 1, max(readers[0], after_writers))


# the order numbers of the worker's messages start here: after those of the same node published
# in this process before the fork (``start``), as in one process
_TAIL_ORDER = 1 << 48


def _unused_write(events: list[tuple[int, int, int, str, Message]]) -> None:
    raise AssertionError("a tail's messages go back to the sim's process, which writes them")


def _windows(
    sched: Scheduler,
    sess: _Session,
    opts: SimOptions,
    ignored: list[tuple[int, str]],
    header: Callable[[SessionWriter], None],
    remote: RemoteTail | None,
) -> None:
    """One rig second at a time until every node is done, or ``opts.stop`` says so at a window
    boundary; then the end of input, at the end of the run or there.

    A stop ends the run as its end would: the windows handed out are completed and written, then
    every node is told ``finish`` at the boundary, so the file is whole, and reruns bit for bit,
    up to there (``stopped_at_s`` in its completeness record).

    With a remote node, window *k* is written once this process has handled window *k + 1*
    and the worker has answered *k*, or once this process is ``remote.ahead()`` windows ahead
    (then it waits: a worker still starting, or slower): its status goes out with the counters
    taken when *k* was handled, so the file is the one-process file byte for byte, however far
    ahead this process ran.
    """
    ignored_at = collections.deque(ignored)
    pending: collections.deque[tuple[int, list[Any], list[tuple[str, list[Any], str]]]] = collections.deque()

    def complete(window: tuple[int, list[Any], list[tuple[str, list[Any], str]]]) -> bool:
        t, out, snap = window
        busy = sched.complete(out)
        if t < sess.end_ns:
            if remote is not None:  # their counters came with the window just completed
                snap[remote.split :] = sess.remote_rows(remote)
            sess.status(t, snap)
        sess.w.flush()
        sess.maybe_split(t, header)
        if opts.on_progress is not None:
            opts.on_progress(min(t, sess.end_ns) * 1e-9, sess.end_ns * 1e-9)
        return busy

    t = 0
    while True:
        if t and opts.stop is not None and t <= sess.end_ns and opts.stop():
            sess.stopped_at_ns = t
            break
        t += _S
        while ignored_at and ignored_at[0][0] < t:
            t0, detail = ignored_at.popleft()
            key = "event/sim"  # a timed fault hil sim cannot apply, said where it would have been
            ev = Event(seq=sess.next_seq(key), stamp_ns=t0, kind="fault_ignored", source="sim", detail=detail)
            sched.emit(t0, key, ev)
        busy = sched.dispatch(t)
        window = (t, sched.take_out(), sess.snapshot(remote) if t < sess.end_ns else [])
        if remote is None:
            busy = complete(window) or busy
        else:
            pending.append(window)
            # the oldest windows the worker has answered (or is too far behind on) are written
            # while it runs the newer ones
            while len(pending) > 1 and (len(pending) > remote.ahead() or remote.ready()):
                complete(pending.popleft())
            if not busy and t > sess.end_ns:  # the end is near: is the worker done too?
                while len(pending) > 1:
                    complete(pending.popleft())
                busy = complete(pending.popleft())
        if not busy and t > sess.end_ns:
            break
    while pending:
        complete(pending.popleft())
    t_last = (sess.end_ns if sess.stopped_at_ns is None else sess.stopped_at_ns) + 1
    sched.finish(t_last, stopped=sess.stopped_at_ns is not None)
    sess.status(t_last, sess.snapshot(remote))


def _header(w: SessionWriter, run: RunInfo, s: Any) -> None:
    w.add_metadata(
        "hil",
        {
            "version": __version__,
            "rig": run.rig,
            "scenario": s.name,
            "scenario_sha256": run.scenario_sha256,
            "seed": s.seed,
            "start_epoch_ns": run.start_epoch_ns,
            "speed": 0,
            "duration_s": run.duration_s,
            "origin_lat_deg": s.origin_lat_deg,
            "origin_lon_deg": s.origin_lon_deg,
            "origin_alt_m": s.origin_alt_m,
            "executor": "sim",
            "time_semantics": TIME_SEMANTICS,
            "time_base": "epoch",
        },
    )
    for name, data, media in run_attachments(run):
        w.add_attachment(name, data, media, log_time_ns=run.start_epoch_ns)


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

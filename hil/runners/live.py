"""The live runner: one node in its own OS process, on a Zenoh session and the wall clock.

``NodeService`` is the process shell of every node service (``hil service NAME``, one process
each under ``hil up`` or compose): it decodes the node's typed options, subscribes to the node's
inputs before the run starts (Zenoh callbacks only enqueue), waits for the run's ``RunInfo``,
builds the node, and then one thread calls it -- ``on_message`` for each input in arrival order,
``tick`` when rig time reaches ``next_tick_ns`` -- and publishes what it returns: Zenoh keys
through typed publishers (the node numbers its own seqs), frames through a ``CanTransmitter``.
Frames read off the CAN bus reach a node that ``reads_can`` with their kernel receive stamps on
the rig clock. Status (1 Hz, the node's counters beside the runner's), heap trims and the
supervisor's restart generation come from ``hil.runtime.service.Service``. At a stop, what has
arrived is still consumed (bounded by ``STOP_DRAIN_S``) and the node's ``finish`` is published.
"""

from __future__ import annotations

import argparse
import contextlib
import os
import queue
import threading
import time
import types
import typing
from collections.abc import Callable
from typing import Any, ClassVar

import can
import msgspec

from hil.bus.describe import alive_key
from hil.bus.keys import type_for_key
from hil.bus.pubsub import DispatchSubscriber, Publisher
from hil.can.bus import open_can_bus
from hil.can.node import CanTransmitter
from hil.messages import RunInfo, ServiceStatus
from hil.nav.scenario import load_scenario, scenario_overrides
from hil.nodes.base import (
    CAN_RX,
    CAN_TX,
    SERIAL_RX,
    SERIAL_TX,
    Node,
    NodeOptions,
    OptionsError,
    Out,
    decode_options,
)
from hil.nodes.world import run_info
from hil.runners.serial import LineReader, LineWriter
from hil.runtime.argtypes import OneLineParser, finite_float
from hil.runtime.clock import RigClock, epoch_s_to_rig_ns, wall_ns
from hil.runtime.service import Service, ServiceContext, run_service

STOP_DRAIN_S = 5.0  # at most this long consuming the backlog after SIGTERM
MAX_WAIT_S = 0.5  # wake at least this often to notice a stop
RECORDER_WAIT_S = 5.0  # a restarted node waits at most this long to meet the recorder


class NodeService(Service):
    """A node as a live service. Subclasses set ``node_cls`` (``service_for`` makes one)."""

    node_cls: ClassVar[type[Node]]

    def __init__(self, ctx: ServiceContext) -> None:
        self.node_cls = type(self).node_cls
        self.name = self.node_cls.name
        self.opts: NodeOptions = decode_options(self.node_cls.Options, ctx.options, self.name)
        super().__init__(ctx)
        self.inbox: queue.SimpleQueue[tuple[str, Any]] = queue.SimpleQueue()
        self.node: Node | None = None
        self.lock = threading.Lock()  # the status thread reads the node's counters
        self._pubs: dict[str, Publisher[Any]] = {}
        self._errors_seen = 0
        self.can_bus: can.BusABC | None = None
        self.can_tx: CanTransmitter | None = None
        self.transport = ""
        self.line_tx: LineWriter | None = None
        self.line_rx: LineReader | None = None

    # -- setup: subscriptions and publishers before time zero -----------------------------------
    def setup(self) -> None:
        root = self.keys.root
        for inp in self.node_cls.inputs:
            routes = {kind: (cls, self._enqueue) for kind, cls in inp.types.items()}
            # inputs come from other services: the node's own outputs on a matching key are not
            # delivered back to it (the session is this process's alone)
            sub = DispatchSubscriber(
                self.ctx.session, f"{root}/{inp.key}", routes, self.stats, remote_only=True
            )
            self._subs.append(sub)
        for key in self.node_cls.outputs:
            self._publisher(key, None)
        if self.node_cls.reads_can or self.node_cls.writes_can:
            self._open_can()
        self._open_line()

    def _open_line(self) -> None:
        """The node's serial line: a receiver's (``tx``, when its options name a protocol) or the
        bridge's (``rx``). A path that cannot be made stops the service with one line."""
        o: Any = self.opts
        if self.node_cls.serial == "tx" and getattr(o, "protocol", None):
            self.line_tx = LineWriter(
                o.baud,
                list(o.serial_links),
                tcp_listen=o.tcp_listen,
                device=o.device,
                on_error=self.stats.error,
            )
            where = [
                *o.serial_links,
                *([f"tcp {o.tcp_listen}"] if o.tcp_listen else []),
                *([o.device] if o.device else []),
            ]
            self.emit_event(
                "line", f"{'+'.join(o.protocol)} at {o.baud} baud on {', '.join(where) or 'no line'}"
            )
        elif self.node_cls.serial == "rx":
            self.line_rx = LineReader(o.baud, path=o.serial_path, tcp=o.tcp_connect)

    def _open_can(self) -> None:
        o: Any = self.opts
        self.can_bus, self.transport = open_can_bus(
            o.channel,
            o.interface,
            fd=bool(getattr(o, "fd", False)),
            rig=self.ctx.rig,
            session=self.ctx.session,
        )
        if self.node_cls.writes_can:
            self.can_tx = CanTransmitter(self.can_bus, self.stats)
        if self.node_cls.reads_can:  # the recording says which transport the bridge read
            self.emit_event("can_transport", self.transport)
        print(f"[{self.name}] CAN: {self.transport}", flush=True)  # noqa: T201 - the start-up line users need

    def _enqueue(self, msg: Any, key: str) -> None:
        # Zenoh's callback thread only enqueues: a subscription may match this node's own
        # outputs, and publishing from inside the callback could wait on the queue it drains
        self.inbox.put((key, msg))

    def _publisher(self, key: str, cls: type | None) -> Publisher[Any]:
        pub = self._pubs.get(key)
        if pub is None:
            full = f"{self.keys.root}/{key}"
            pub = self._pubs[key] = self.publisher(full, cls or type_for_key(full) or ServiceStatus)
        return pub

    # -- the loop -------------------------------------------------------------------------------
    def make_node(self, run: RunInfo) -> Node:
        return self.node_cls(run, self.opts)

    def _await_recorder(self, timeout_s: float = RECORDER_WAIT_S) -> None:
        """A restarted node's first words (``resumed``) must reach the recording.

        On the embedded peer-to-peer bus a new process meets the recorder some moments after it
        starts; a put before then is lost to the file. The recorder's liveliness token arrives with
        its subscription on the same link, so seeing the token is the signal (bounded: a rig may
        run without a recorder).
        """
        if self.name == "recorder":
            return
        key = alive_key(self.ctx.rig, "recorder")
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline and not self.ctx.stop.is_set():
            with contextlib.suppress(Exception):
                if any(r.ok is not None for r in self.ctx.session.liveliness().get(key, timeout=0.5)):
                    return
            time.sleep(0.1)

    def run_loop(self, run: RunInfo, clock: RigClock) -> None:
        node = self.make_node(run)
        with self.lock:
            self.node = node
            outs = node.start(clock.now_ns())
        if outs:
            self._await_recorder()
        self._publish(outs, "start")
        root_len = len(self.keys.root) + 1
        stop = self.ctx.stop
        while not stop.is_set():
            now = clock.now_ns()
            t_next = node.next_tick_ns()
            if t_next is not None and now >= t_next:
                with self.lock:
                    outs = node.tick(now)
                self._publish(outs, "tick")
                continue
            wait_s = (
                MAX_WAIT_S
                if t_next is None
                else min(MAX_WAIT_S, max(0.0, clock.wall_of(t_next) - time.time()))
            )
            if self.can_bus is not None and node.reads_can:
                self._read_can(node, run, wait_s)
                wait_s = 0.0
            elif self.line_rx is not None:
                self._read_line(node, run, wait_s)
                wait_s = 0.0
            try:
                key, msg = self.inbox.get(timeout=wait_s) if wait_s > 0 else self.inbox.get_nowait()
            except queue.Empty:
                continue
            with self.lock:
                outs = node.on_message(key[root_len:], msg, clock.now_ns())
            self._publish(outs, "input")
        self._drain_and_finish(node, clock, root_len)

    def _read_can(self, node: Node, run: RunInfo, wait_s: float) -> None:
        assert self.can_bus is not None
        try:
            frame = self.can_bus.recv(timeout=wait_s)
        except can.CanError as err:  # the bus went away: say so, keep trying until stopped
            self.stats.error("errors.can.recv", f"{self.transport}: {err}")
            self.ctx.stop.wait(0.2)
            return
        if frame is None:
            return
        rx_ns = epoch_s_to_rig_ns(frame.timestamp, run.start_epoch_ns, run.speed)
        with self.lock:
            outs = node.on_message(f"{CAN_RX}/{frame.channel or ''}", frame, rx_ns)
        self._publish(outs, "input")

    def _read_line(self, node: Node, run: RunInfo, wait_s: float) -> None:
        assert self.line_rx is not None
        got = self.line_rx.read(wait_s)
        if got is None:
            return
        data, t_wall_ns = got
        rx_ns = int((t_wall_ns - run.start_epoch_ns) * run.speed)
        self.stats.count_rate("in.line.bytes", len(data))
        with self.lock:
            outs = node.on_message(f"{SERIAL_RX}/{getattr(self.opts, 'port', 'gnss')}", data, rx_ns)
        self._publish(outs, "input")

    def _drain_and_finish(self, node: Node, clock: RigClock, root_len: int) -> None:
        """Stop: consume what had arrived (bounded: a node behind a backlog must still stop on
        time), then release what the node holds."""
        drain_until = time.monotonic() + STOP_DRAIN_S
        while time.monotonic() < drain_until:
            try:
                key, msg = self.inbox.get_nowait()
            except queue.Empty:
                break
            with self.lock:
                outs = node.on_message(key[root_len:], msg, clock.now_ns())
            self._publish(outs, "input")
        with self.lock:
            outs = node.finish(clock.now_ns())
        with contextlib.suppress(Exception):  # the session may be closing
            self._publish(outs, "finish")

    def _publish(self, outs: list[Out], why: str) -> None:
        for key, msg in outs:
            if key == CAN_TX:
                if self.can_tx is not None:
                    self.can_tx.send_frames(msg.frames, sync=msg.sync)
                continue
            if key == SERIAL_TX:
                if self.line_tx is not None and self.clock is not None:
                    self.line_tx.write(msg.data, self.clock.wall_of(msg.start_ns))
                continue
            self._publisher(key, type(msg)).put(msg)
        node = self.node
        if node is not None and node.errors_seen != self._errors_seen:
            self._errors_seen = node.errors_seen
            self.stats.note(node.last_error)
        self.after_outputs(why)

    def after_outputs(self, why: str) -> None:
        """A hook after each call's outputs went out (the fusion acknowledges inputs to replay)."""

    # -- status ---------------------------------------------------------------------------------
    def extra_status(self) -> dict[str, int]:
        out: dict[str, int] = {"inbox": self.inbox.qsize()}
        node = self.node
        if node is not None:
            with self.lock:
                out.update(node.counters())
        if self.can_tx is not None:
            out.update(self.can_tx.counters())
        if self.line_tx is not None:
            out.update(self.line_tx.counts)
        return out

    def teardown(self) -> None:
        if self.can_bus is not None:
            with contextlib.suppress(Exception):
                self.can_bus.shutdown()
        for line in (self.line_tx, self.line_rx):
            if line is not None:
                line.close()


class WorldService(NodeService):
    """World decides the run: it waits for the services it was told to (``wait_for``), picks
    time zero ``lead_s`` ahead on the wall clock, and then runs its node like any other."""

    def needs_run(self) -> bool:
        return False

    def setup(self) -> None:
        super().setup()
        o: Any = self.opts
        self._ready: set[str] = set()
        self._ready_event = threading.Event()
        if o.wait_for and not o.resume_run:
            self.subscribe(self.keys.status("*"), ServiceStatus, self._on_status)

    def _on_status(self, st: ServiceStatus, _key: str) -> None:
        if st.service in self.opts.wait_for and st.state in ("waiting_run", "running"):  # type: ignore[attr-defined]
            self._ready.add(st.service)
            if self._ready >= set(self.opts.wait_for):  # type: ignore[attr-defined]
                self._ready_event.set()

    def run_loop(self, _run: Any, _clock: Any) -> None:
        run = self.decide_run()
        if run is None:
            return
        self.run_info = run
        self.clock = RigClock(run.start_epoch_ns, run.speed)
        self.state = "running"
        super().run_loop(run, self.clock)

    def decide_run(self) -> RunInfo | None:
        o: Any = self.opts
        if o.resume_run:  # the same run again: time zero and scenario as announced
            return RunInfo(**o.resume_run)
        s = load_scenario(o.scenario)
        if o.imu_rate_hz:
            s = scenario_overrides(s, imu_rate_hz=int(o.imu_rate_hz))
        deadline = time.monotonic() + o.wait_timeout_s
        while o.wait_for and not self._ready_event.wait(0.1):
            if self.ctx.stop.is_set():
                return None
            if time.monotonic() > deadline:
                missing = sorted(set(o.wait_for) - self._ready)
                self.stats.error(
                    "errors.wait_for", f"started without {missing}: no status in {o.wait_timeout_s} s"
                )
                break
        if self.ctx.stop.is_set():
            return None
        # time zero on a whole second of UTC: a receiver's epochs then fall on its own grid, as a
        # real one's do on GPS time (and logs read better)
        start = -(-(wall_ns() + int(o.lead_s * 1e9)) // 1_000_000_000) * 1_000_000_000
        return run_info(s, rig=self.keys.rig, start_epoch_ns=start, speed=o.speed, duration_s=o.duration_s)


def service_for(node_cls: type[Node], base: type[NodeService] = NodeService) -> type[NodeService]:
    """The live service class of a node (what ``services/<name>.py`` exports as ``SERVICE``)."""
    name = "".join(p.capitalize() for p in node_cls.name.split("_")) + "Service"
    return types.new_class(name, (base,), {}, lambda ns: ns.update(node_cls=node_cls, name=node_cls.name))


# -- command lines: one flag per option field, defaults from the Struct --------------------------
def options_parser(
    cls: type[NodeOptions], prog: str, aliases: dict[str, str] | None = None
) -> argparse.ArgumentParser:
    """``--field-name`` for every field of ``cls`` (a list: comma-separated; a bool: a switch,
    ``--no-<name>`` when it defaults to true), plus ``--rig``; ``aliases`` maps older flags."""
    ap = OneLineParser(prog=prog)
    ap.add_argument("--rig", default=None)
    hints = typing.get_type_hints(cls)
    defaults = {f: d for f, d in zip(cls.__struct_fields__, _defaults(cls), strict=True)}
    for f in cls.__struct_fields__:
        if f == "resume" or typing.get_origin(hints[f]) is dict or dict in typing.get_args(hints[f]):
            continue
        flag = "--" + f.replace("_", "-")
        extra = [a for a, target in (aliases or {}).items() if target == f]
        hint, default = hints[f], defaults[f]
        if hint is bool:
            if default:
                ap.add_argument("--no-" + flag[2:], *extra, dest=f, action="store_false", default=True)
            else:
                ap.add_argument(flag, *extra, dest=f, action="store_true", default=False)
            continue
        names = [flag, *extra]
        ap.add_argument(*names, dest=f, default=default, type=_arg_type(hint), metavar=f.upper())
    return ap


def _defaults(cls: type[NodeOptions]) -> list[Any]:
    inst = cls()
    return [getattr(inst, f) for f in cls.__struct_fields__]


def _arg_type(hint: Any) -> Callable[[str], Any]:
    args = [a for a in typing.get_args(hint) if a is not type(None)]
    base = args[0] if args and typing.get_origin(hint) in (types.UnionType, typing.Union) else hint
    if typing.get_origin(base) is list:
        return lambda text: [x for x in text.split(",") if x]
    if base is float:
        return finite_float
    if base is int:
        return base  # type: ignore[no-any-return]
    return str


def main_for(
    service: type[NodeService], aliases: dict[str, str] | None = None
) -> Callable[[list[str] | None], int]:
    """A service module's ``main(argv)``: flags from its options, then the live runner."""

    def main(argv: list[str] | None = None) -> int:
        cls = service.node_cls.Options
        ap = options_parser(cls, f"hil service {service.node_cls.name}", aliases)
        a = ap.parse_args(argv)
        opts = {k: v for k, v in vars(a).items() if k != "rig"}
        try:
            msgspec.convert(opts, cls)
        except msgspec.ValidationError as err:
            ap.error(str(err))
        return run_service(service, a.rig or os.environ.get("HIL_RIG", "default"), opts)

    return main


__all__ = ["NodeService", "OptionsError", "WorldService", "main_for", "options_parser", "service_for"]

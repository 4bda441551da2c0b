"""The live runner: one node in its own OS process, on a Zenoh session and the wall clock.

``NodeService`` is the process shell of every node service (``hil service NAME``, one process
each under ``hil up`` or compose): it decodes the node's typed options, subscribes to the node's
inputs before the run starts (Zenoh callbacks only enqueue), waits for the run's ``RunInfo``,
builds the node, and then one thread calls it -- ``on_message_from`` for each input in arrival order,
``tick`` when rig time reaches ``next_tick_ns`` -- and publishes what it returns: Zenoh keys
through typed publishers (the node numbers its own seqs). A node that writes CAN is ticked up
to ``lookahead_s`` ahead and its frames leave through a pacing process of its own
(``hil.runners.can_sender``, ``hil.runners.pacing``: on the sample grid, at wire spacing).
Frames read off the CAN bus reach a node that ``reads_can`` with their kernel receive stamps on
the rig clock. Status (1 Hz, the node's counters beside the runner's), heap trims and the
supervisor's restart generation come from ``hil.runtime.service.Service``. At a stop, what has
arrived is still consumed (bounded by ``STOP_DRAIN_S``) and the node's ``finish`` is published.

The inbox is bounded (``hil.bus.inbox``): a lane per input kind and publisher, drop-oldest, served
in arrival order; what it drops is counted in status (``inbox.dropped.<kind>``) and handed to the
node (``on_dropped``) before the next input, so the fusion journals it.
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import threading
import time
import types
import typing
from collections import deque
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, ClassVar

import msgspec

from hil.bus.describe import alive_key
from hil.bus.identity import FOREIGN, RigIdentity
from hil.bus.inbox import BoundedInbox, key_kind
from hil.bus.keys import may_batch, type_for_key
from hil.bus.pubsub import Publisher, RawSubscriber, decode_checked
from hil.messages import Event, RunInfo, ServiceStatus, generation_seq
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
from hil.runners.pacing import MonotonicRigClock, PacingConfig
from hil.runtime.argtypes import OneLineParser, finite_float
from hil.runtime.clock import RigClock, epoch_s_to_rig_ns, wall_ns
from hil.runtime.heap import freeze_startup
from hil.runtime.service import Service, ServiceContext, run_service

if TYPE_CHECKING:
    # imported where used: python-can (~0.1 s of CPU at import), the CAN sender, the serial line
    # and the scenario loader are needed by some services only, and every service's start-up
    # (which time zero waits for) paid for all of them
    import can

    from hil.runners.can_sender import SenderProcess
    from hil.runners.serial import LineReader, LineWriter


class _Ident(msgspec.Struct):
    """What names an input in a journal; the rest of the payload is skipped unparsed."""

    seq: int
    sensor: str = ""


_IDENT = msgspec.json.Decoder(_Ident)

STOP_DRAIN_S = 5.0  # at most this long consuming the backlog after SIGTERM
MAX_WAIT_S = 0.5  # wake at least this often to notice a stop
MAX_CAN_DRAIN = 512  # frames read off the bus before their outputs go out (a bound on one batch)
MAX_INPUT_BATCH = 1024  # inputs taken in one wake-up of an input batching window (BatchedInputOptions)
MAX_QUEUED_BATCH = 64  # without a window: inputs already queued taken in one wake-up (a batch's)
PACING_TRACE_ENV = "HIL_PACING_TRACE"  # benches: a directory for <service>.npy pacing traces
RECORDER_WAIT_S = 5.0  # a restarted node waits at most this long to meet the recorder


def batch_sends(outs: list[Out]) -> list[tuple[str, Any]]:
    """The puts for outputs in order: those of a key that may batch (``hil.bus.keys.may_batch``:
    the raw CAN frames, the IMU's streams; each message of its own was routed by the hub and
    woken up for in every subscriber) as one list per key (``Publisher.put_many``) at the place
    of the key's first, as long as no output of another key comes between them -- a time tag
    made between two IMU samples still reaches time sync between them. Batches of different keys
    are independent streams and may pass each other; within a key the order is kept."""
    sends: list[tuple[str, Any]] = []
    batches: dict[str, list[Any]] = {}
    for key, msg in outs:
        if may_batch(key):
            group = batches.get(key)
            if group is None:
                group = batches[key] = []
                sends.append((key, group))
            group.append(msg)
        else:
            sends.append((key, msg))
            if batches:  # what comes after it goes after it
                batches = {}
    return sends


class NodeService(Service):
    """A node as a live service. Subclasses set ``node_cls`` (``service_for`` makes one)."""

    node_cls: ClassVar[type[Node]]

    def __init__(self, ctx: ServiceContext) -> None:
        self.node_cls = type(self).node_cls
        self.name = self.node_cls.name
        self.opts: NodeOptions = decode_options(self.node_cls.Options, ctx.options, self.name)
        super().__init__(ctx)
        # (key, payload, publisher, type): decoded when taken, so what a lane drops costs no parse
        self.inbox: BoundedInbox[tuple[str, bytes, str, type]] = BoundedInbox(
            keep_dropped=self.node_cls.journals_drops
        )
        self._root_len = len(self.keys.root) + 1
        self._refuse_foreign = self.node_cls.refuses_foreign
        self.identity = RigIdentity.from_env()
        self.node: Node | None = None
        self.lock = threading.Lock()  # the status thread reads the node's counters
        self._events_before_node = 0  # seqs of event/<name> the service took before its node
        self._pubs: dict[str, Publisher[Any]] = {}
        self._errors_seen = 0
        self.can_bus: can.BusABC | None = None
        self._can_error: type[Exception] = Exception  # python-can's, once a bus is open
        self.transport = ""
        self.line_tx: LineWriter | None = None
        self.line_rx: LineReader | None = None
        self.can_sender: SenderProcess | None = None  # a node that writes CAN: its frames' pacer
        self._mono: MonotonicRigClock | None = None
        self._sender_error = ""
        self._sender_dead = False
        self._due: deque[tuple[int, list[Out], str]] = deque()  # outputs held for their rig time
        self._bursts: list[tuple[int, int, Any]] = []  # (due, computed at, burst) not yet submitted
        self._can_batch_s = 0.0  # a CAN reader's window: its node's (run_loop)

    # -- setup: subscriptions and publishers before time zero -----------------------------------
    def setup(self) -> None:
        root = self.keys.root
        for inp in self.node_cls.inputs:
            key = f"{root}/{inp.key}"
            # inputs come from other services: the node's own outputs on a matching key are not
            # delivered back to it (the session is this process's alone)
            sub = RawSubscriber(
                self.ctx.session, key, dict(inp.types), self._enqueue, self.stats, remote_only=True
            )
            self._subs.append(sub)
        for key in self.node_cls.outputs:
            self._publisher(key, None)
        if self.node_cls.reads_can:
            self._open_can()
        if self.node_cls.writes_can:
            self._start_can_sender()
        self._open_line()

    def _open_line(self) -> None:
        """The node's serial line: a receiver's (``tx``, when its options name a protocol) or the
        bridge's (``rx``). A path that cannot be made stops the service with one line."""
        o: Any = self.opts
        if self.node_cls.serial == "tx" and getattr(o, "protocol", None):
            from hil.runners.serial import LineWriter

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
            from hil.runners.serial import LineReader

            self.line_rx = LineReader(o.baud, path=o.serial_path, tcp=o.tcp_connect)

    def _open_can(self) -> None:
        import can

        from hil.can.bus import open_can_bus

        o: Any = self.opts
        self._can_error = can.CanError
        self.can_bus, self.transport = open_can_bus(
            o.channel,
            o.interface,
            fd=bool(getattr(o, "fd", False)),
            rig=self.ctx.rig,
            session=self.ctx.session,
        )
        if self.node_cls.reads_can:  # the recording says which transport the bridge read
            self.emit_event("can_transport", self.transport)
        print(f"[{self.name}] CAN: {self.transport}", flush=True)  # noqa: T201 - the start-up line users need

    def _start_can_sender(self) -> None:
        """The node's frames leave through a pacing process of their own (``hil.runners.can_sender``),
        started now so it has its bus and codec long before time zero."""
        from hil.runners.can_sender import SenderProcess, pacing_config_dict

        o: Any = self.opts
        trace_dir = os.environ.get(PACING_TRACE_ENV)
        pacing = PacingConfig(
            late_policy=o.late_policy,
            rt_priority=int(o.rt_priority),
            cpu_affinity=tuple(o.cpu_affinity),
            sched_slice_us=int(o.sched_slice_us),
            bitrate=int(o.bitrate),
            data_bitrate=int(o.data_bitrate),
        )
        config = {
            "channel": o.channel,
            "interface": o.interface,
            "fd": bool(o.fd),
            "rig": self.ctx.rig,
            "time_tags": self.node_cls.sends_time_tags,
            "dbc": getattr(o, "dbc", None),
            "pacing": pacing_config_dict(pacing),
            "trace": os.path.join(trace_dir, f"{self.name}.npy") if trace_dir else None,
        }
        self.can_sender = SenderProcess(config, self._pacing_note, self._sender_ready)

    def _sender_ready(self, transport: str) -> None:
        self.transport = transport
        print(f"[{self.name}] CAN: {transport}", flush=True)  # noqa: T201 - the start-up line users need

    def _enqueue(self, key: str, raw: bytes, source: str, cls: type) -> None:
        # Zenoh's callback thread only enqueues: a subscription may match this node's own
        # outputs, and publishing from inside the callback could wait on the queue it drains
        kind = key_kind(key[self._root_len :])
        if self._refuse_foreign and self.identity.classify(source) == FOREIGN:
            self.stats.inc(f"rejected.foreign.{kind.replace('/', '.')}")
            return
        self.inbox.put(kind, source, (key, raw, source, cls))

    def _publisher(self, key: str, cls: type | None) -> Publisher[Any]:
        pub = self._pubs.get(key)
        if pub is None:
            full = f"{self.keys.root}/{key}"
            pub = self._pubs[key] = self.publisher(full, cls or type_for_key(full) or ServiceStatus)
        return pub

    def emit_event(self, kind: str, detail: str = "") -> None:
        """The service's own events (its line, its CAN transport, its pacing) and its node's go on
        one key, ``event/<name>``, so they share one seq counter: the node's once it exists, and
        the node's counter starts after those taken before (two counters gave duplicate seqs)."""
        key = f"event/{self.name}"
        with self.lock:
            if self.node is not None:
                seq = self.node.next_seq(key)
            else:
                seq = generation_seq(self.generation, self._events_before_node)
                self._events_before_node += 1
        self._publisher(key, Event).put(
            Event(seq=seq, stamp_ns=self.rig_now_ns(), kind=kind, source=self.name, detail=detail)
        )

    # -- the loop -------------------------------------------------------------------------------
    def make_node(self, run: RunInfo) -> Node:
        node = self.node_cls(run, self.opts)
        with self.lock:  # its events go on after the service's own (emit_event)
            node.continue_seq(f"event/{self.name}", self._events_before_node)
        return node

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
        # the CAN bridge's read window, chosen by the node (its option, else by the IMU's rate)
        self._can_batch_s = float(getattr(node, "read_window_ms", 0.0)) / 1e3
        # Everything built so far (modules, the node, its estimators) lives as long as the process:
        # out of the collector's reach, a full collection scans only what the run makes, not the
        # ~27k objects a fusion service's imports leave: pauses that landed on the output's latency.
        freeze_startup()
        if self.can_sender is not None:
            self._run_paced(node, run)
            return
        with self.lock:
            self.node = node
            outs = node.start(clock.now_ns())
        if outs:
            self._await_recorder()
        self._publish(outs, "start")
        root_len = len(self.keys.root) + 1
        stop = self.ctx.stop
        batch_s = float(getattr(self.opts, "input_batch_ms", 0.0)) / 1e3
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
            item = self.inbox.get(timeout=wait_s)
            if item is None:
                continue
            if batch_s:
                # the input batching window (BatchedInputOptions): let the inputs of the next
                # few milliseconds queue, then take them all in this one wake-up
                t_next = node.next_tick_ns()
                pause = batch_s if t_next is None else min(batch_s, clock.wall_of(t_next) - time.time())
                if pause > 0.0:
                    stop.wait(pause)
            # every input already queued is taken in this wake-up and their outputs go out together
            # (a batch of IMU samples in, a batch of synchronised ones out: ``batch_sends``); a
            # batch ends when the queue is empty or at its bound (timers and the stop are looked at
            # between batches, however fast the inputs come)
            bound = MAX_INPUT_BATCH if batch_s else MAX_QUEUED_BATCH
            taken = 0
            pending: list[Out] = []
            consumed = False  # an input decoded: published even with no outputs (after_outputs acks it)
            while item is not None:
                outs = self._consume(node, item, clock.now_ns(), root_len)
                if outs is not None:
                    pending += outs
                    consumed = True
                taken += 1
                item = self.inbox.get(timeout=0) if taken < bound else None
            if consumed:
                self._publish(pending, "input")
            if batch_s:  # in the status: inputs per wake-up = in.batched_inputs / in.batches
                self.stats.inc("in.batches")
                self.stats.inc("in.batched_inputs", taken)
        self._drain_and_finish(node, clock, root_len)

    def _consume(
        self, node: Node, item: tuple[str, bytes, str, type], now_ns: int, root_len: int
    ) -> list[Out] | None:
        """One input to the node, after the ones the inbox dropped before it (so a journal that
        names them does so in the order they were lost); None: it did not decode (counted)."""
        self._hand_dropped(node, root_len)
        key, raw, source, cls = item
        msg = decode_checked(cls, key, raw, self.stats)
        if msg is None:
            return None
        with self.lock:
            return node.on_message_from(key[root_len:], msg, now_ns, source)

    def _hand_dropped(self, node: Node, root_len: int) -> None:
        """What the inbox dropped, to a node that journals it: only the fields that name it
        (``seq``, ``sensor``; a flood drops thousands a second, a full parse each would cost
        more than the flood), quietly (a payload that does not even have those was not recorded
        either, so it needs no journal)."""
        dropped = self.inbox.take_dropped()
        if not dropped:
            return
        with self.lock:
            for key, raw, source, _cls in dropped:
                try:
                    ident = _IDENT.decode(raw)
                except (msgspec.ValidationError, msgspec.DecodeError):
                    continue
                if not ident.sensor:  # a message type's default, left out of the payload
                    ident.sensor = key.rsplit("/", 1)[-1]
                node.on_dropped(key[root_len:], ident, source)

    def _run_paced(self, node: Node, run: RunInfo) -> None:
        """A node whose frames must leave on time (``hil.runners.pacing``): ticked up to
        ``lookahead_s`` before each tick is due (its output depends on the tick's rig time only),
        its frames sent by the pacing process at their rig times, its other outputs published
        here when their time comes."""
        sender = self.can_sender
        assert sender is not None
        o: Any = self.opts
        mono = self._mono = MonotonicRigClock(run.start_epoch_ns, run.speed)
        lookahead = max(0, round(float(o.lookahead_s) * 1e9))
        # wake at most this often: the ticks that entered the look-ahead meanwhile are computed
        # together and their bursts go to the pacing process in one message; the other outputs
        # that came due are published together (up to this much after their time)
        batch = min(lookahead, round(float(o.compute_batch_ms) * 1e6))  # CanWriterOptions, >= 0
        sender.start_run(
            run.start_epoch_ns, run.speed, int(node.can_wire_latency_ns), int(getattr(node, "dt_ns", 0))
        )
        pacing = {
            "origin": "runner",  # not the node's: how the live runner paces its frames
            "rt_priority": o.rt_priority,
            "cpu_affinity": list(o.cpu_affinity),
            "sched_slice_us": o.sched_slice_us,
            "late_policy": o.late_policy,
            "lookahead_s": o.lookahead_s,
            "compute_batch_ms": batch / 1e6,
            "bitrate": o.bitrate,
            "data_bitrate": o.data_bitrate,
            "wire_latency_ns": node.can_wire_latency_ns,
        }
        with self.lock:
            self.node = node  # its counters reach the status; its event seqs are the service's
        self.emit_event("pacing", json.dumps(pacing))  # JSON, as the node's own events
        with self.lock:
            outs = node.start(mono.now_ns())
        if outs:
            self._await_recorder()
        self._route(outs, None, "start")
        root_len = len(self.keys.root) + 1
        stop = self.ctx.stop
        horizon = 0  # rig time the node has computed up to: an input applies from there on
        try:
            while not stop.is_set():
                now = mono.now_ns()
                self._publish_due(now)
                t_next = node.next_tick_ns()
                if t_next is not None and t_next <= now + lookahead:
                    with self.lock:
                        outs = node.tick(t_next)
                    horizon = max(horizon, t_next)
                    self._route(outs, t_next, "tick")
                    self.stats.inc("paced.ticks")
                    continue
                self._submit_bursts()
                due = self._next_due()
                wake = [
                    t
                    for t in (
                        None if t_next is None else t_next - lookahead + batch,
                        None if due is None else due + batch,
                    )
                    if t is not None
                ]
                wait_s = min([MAX_WAIT_S, *((w - now) * 1e-9 / run.speed for w in wake)])
                item = self.inbox.get(timeout=max(0.0, wait_s))
                self.stats.inc("paced.wakeups")
                if item is None:
                    continue
                # a fault command applies from the first sample not yet computed
                outs = self._consume(node, item, max(mono.now_ns(), horizon + 1), root_len)
                if outs is not None:
                    self._route(outs, None, "input")
            # stop: what was computed still leaves at its time (at most lookahead_s more: no seq
            # gap before the node's finish outputs), then the node finishes
            self._submit_bursts()
            while self._due:
                time.sleep(max(0.0, (self._due[0][0] - mono.now_ns()) * 1e-9 / run.speed))
                self._publish_due(mono.now_ns())
            self._drain_and_finish(node, mono, root_len)
        finally:
            sender.close()

    def _route(self, outs: list[Out], due_ns: int | None, why: str) -> None:
        """Frames to the pacing process (due at ``due_ns``, or now); the rest published at that time."""
        assert self.can_sender is not None and self._mono is not None
        now = self._mono.now_ns()
        rest: list[Out] = []
        for key, msg in outs:
            if key == CAN_TX:
                self._bursts.append((now if due_ns is None else due_ns, now, msg))
            else:
                rest.append((key, msg))
        if due_ns is None:  # not a tick's: on its way at once, behind what was computed before it
            self._submit_bursts()
        if due_ns is None or due_ns <= now:
            self._publish(rest, why)
        elif rest:
            self._due.append((due_ns, rest, why))

    def _submit_bursts(self) -> None:
        """The bursts computed since the last wake-up, to the pacing process in one message."""
        if self._bursts and self.can_sender is not None:
            self.can_sender.submit_many(self._bursts)
            self._bursts = []

    def _next_due(self) -> int | None:
        return self._due[0][0] if self._due else None

    def _publish_due(self, now_ns: int) -> None:
        """Every output group due by now in one call, so that a compute batch's capture truth
        leaves as one batch (``hil.bus.keys.BATCHED_KEYS``) in its order."""
        outs: list[Out] = []
        why = ""
        while self._due and self._due[0][0] <= now_ns:
            _, group, why = self._due.popleft()
            outs += group
        if outs:
            self._publish(outs, why)

    def _pacing_note(self, text: str) -> None:
        self.stats.note(f"pacing: {text}")
        print(f"[{self.name}] pacing: {text}", flush=True)  # noqa: T201 - an operator must see it

    def _deliver(self, outs: list[Out], why: str) -> None:
        """Outputs at the stop: frames through the pacing process when there is one."""
        if self.can_sender is not None and self._mono is not None:
            self._route(outs, None, why)
        else:
            self._publish(outs, why)

    def _read_can(self, node: Node, run: RunInfo, wait_s: float) -> None:
        assert self.can_bus is not None
        try:
            frame = self.can_bus.recv(timeout=wait_s)
        except self._can_error as err:  # the bus went away: say so, keep trying until stopped
            self.stats.error("errors.can.recv", f"{self.transport}: {err}")
            self.ctx.stop.wait(0.2)
            return
        if frame is not None and self._can_batch_s > 0.0:
            # the read window (CanBridgeNode.read_window_ms): the frames of the next few ms queue
            # on the bus, stamped as they arrive, and are read in this one wake-up
            self.ctx.stop.wait(self._can_batch_s)
            self.stats.inc("in.can_reads")
        outs: list[Out] = []
        # the frames already queued are read before any output goes out (a sample's four arrive
        # together on hilzenoh): each key's outputs then leave as one batch (_publish)
        n = 0
        while frame is not None:
            rx_ns = epoch_s_to_rig_ns(frame.timestamp, run.start_epoch_ns, run.speed)
            with self.lock:
                outs += node.on_message(f"{CAN_RX}/{frame.channel or ''}", frame, rx_ns)
            n += 1
            if n >= MAX_CAN_DRAIN:
                break  # the rest on the next call: a bound on one batch and on the outputs' delay
            try:
                frame = self.can_bus.recv(timeout=0)
            except self._can_error as err:
                self.stats.error("errors.can.recv", f"{self.transport}: {err}")
                break
        if outs:
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

    def _drain_and_finish(self, node: Node, clock: RigClock | MonotonicRigClock, root_len: int) -> None:
        """Stop: consume what had arrived (bounded: a node behind a backlog must still stop on
        time), then release what the node holds."""
        drain_until = time.monotonic() + STOP_DRAIN_S
        while time.monotonic() < drain_until:
            item = self.inbox.get(timeout=0)
            if item is None:
                break
            outs = self._consume(node, item, clock.now_ns(), root_len)
            if outs is not None:
                self._deliver(outs, "input")
        self._hand_dropped(node, root_len)
        with self.lock:
            outs = node.finish(clock.now_ns())
        with contextlib.suppress(Exception):  # the session may be closing
            self._deliver(outs, "finish")

    def _publish(self, outs: list[Out], why: str) -> None:
        """Outputs in order, those of a batched kind as batches (:func:`batch_sends`)."""
        rest: list[Out] = []
        for key, msg in outs:
            if key == CAN_TX:
                continue  # frames leave through the pacing process (_route), never from here
            if key == SERIAL_TX:
                if self.line_tx is not None and self.clock is not None:
                    self.line_tx.write(msg.data, self.clock.wall_of(msg.start_ns))
                continue
            rest.append((key, msg))
        for key, item in batch_sends(rest):
            if isinstance(item, list):
                self._publisher(key, type(item[0])).put_many(item)
            else:
                self._publisher(key, type(item)).put(item)
        node = self.node
        if node is not None and node.errors_seen != self._errors_seen:
            self._errors_seen = node.errors_seen
            self.stats.note(node.last_error)
        self.after_outputs(why)

    def after_outputs(self, why: str) -> None:
        """A hook after each call's outputs went out (the fusion acknowledges inputs to replay)."""

    # -- status ---------------------------------------------------------------------------------
    def extra_status(self) -> dict[str, int]:
        out: dict[str, int] = self.inbox.counters()
        node = self.node
        if node is not None:
            with self.lock:
                out.update(node.counters())
        bus_counters = getattr(self.can_bus, "counters", None)  # the transport's own (hillocal)
        if callable(bus_counters):
            out.update(bus_counters())
        sender = self.can_sender
        if sender is not None:
            out.update(sender.last_counters)
            if sender.last_error and sender.last_error != self._sender_error:
                self._sender_error = sender.last_error
                self.stats.note(sender.last_error)
            if not sender.alive() and not self.ctx.stop.is_set() and not self._sender_dead:
                self._sender_dead = True
                self.stats.error(
                    "errors.can_sender", f"the CAN sender process exited ({sender.proc.returncode})"
                )
        if self.line_tx is not None:
            out.update(self.line_tx.counts)
        return out

    def teardown(self) -> None:
        if self.can_sender is not None:
            self.can_sender.close()  # idempotent: a run that never started still stops it
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
        from hil.nav.scenario import load_scenario, scenario_overrides
        from hil.nodes.world import run_info

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
        return run_info(
            s,
            rig=self.keys.rig,
            start_epoch_ns=start,
            speed=o.speed,
            duration_s=o.duration_s,
            imu_can_fd=o.fd,
        )


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
        (item,) = typing.get_args(base) or (str,)
        if typing.get_origin(item) is typing.Annotated:
            item = typing.get_args(item)[0]
        conv: Callable[[str], Any] = finite_float if item is float else int if item is int else str
        return lambda text: [conv(x) for x in text.split(",") if x.strip()]
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

"""What every node is: a service's behaviour with its inputs and its time as arguments.

A node holds the logic of one rig service -- the world's truth, an emulated device with its
faults and wire encoding, a bridge's decoding, the time sync, the fusion -- and nothing of the
process around it: no Zenoh, no clock reads, no threads, no files. A runner calls it::

    node = Node(run, options)         # the run (time zero, scenario) is known
    outs = node.start(now_ns)         # once
    outs = node.on_message(key, msg, now_ns)   # an input arrived (key relative to hil/<rig>/)
    outs = node.on_message_from(key, msg, now_ns, source)  # the same, with its publisher (live)
    outs = node.tick(now_ns)          # the time it asked for (next_tick_ns()) has come
    outs = node.finish(now_ns)        # end of input: release what is held

and publishes what it returns: ``(key, message)`` pairs, the key relative to ``hil/<rig>/``, or
``(CAN_TX, CanBurst)`` for frames that leave on the CAN bus. The live runner
(``hil.runners.live``) calls it from a Zenoh session and the wall clock, the virtual-clock
runner (``hil.runners.sim``, ``hil sim``) from a scheduler, rerun from a recording; the node is
the same object in all three, so a fault, a quantisation or a decision has one implementation.

Every message a node builds carries its ``seq`` from the node's own counter per key, numbered in
the process's restart generation (``hil.messages.generation_seq``; option ``resume``), so a
restarted service never repeats a seq. Counters and the last error (``inc``/``error``) go into
the service's status; the runner adds its own (rates, transport, heap).
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass
from typing import Annotated, Any, ClassVar, Literal

import msgspec

from hil.messages import Event, Message, RunInfo, generation_seq

Out = tuple[str, Any]  # (key relative to hil/<rig>/, message) or (CAN_TX, CanBurst)
CAN_TX = "@can"  # the port of frames leaving on the CAN bus (not a Zenoh key)
CAN_RX = "@can"  # on_message key prefix of frames read off the bus: "@can/<channel>"
SERIAL_TX = "@serial"  # the port of bytes leaving on a serial line (a LineBurst)
SERIAL_RX = "@serial"  # on_message key prefix of bytes read off a line: "@serial/<port>"


@dataclass(frozen=True)
class Input:
    """A subscription: a key expression relative to ``hil/<rig>/`` and the type of each kind.

    ``types`` maps the key's first segment (``sensor``, ``timetag``, ...) to the message type
    carried there; one Input is one Zenoh subscription, so the inputs it matches reach the node
    in the order they were published (e.g. a sensor's measurements and its time tags)."""

    key: str
    types: Mapping[str, type[Message]]


class NodeOptions(msgspec.Struct, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Options every service takes (``hil service NAME --options JSON``), one default each."""

    resume: int = 0  # restart generation: hil up --restart passes N on the N-th restart
    heap_trim_s: float | None = None  # seconds between C-heap trims (None: the service's default)


class BatchedInputOptions(NodeOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Options of a node whose inputs may wait to be taken together (time sync, fusion)."""

    # After a wake-up for an input, the live runner waits this long and then takes every input
    # queued meanwhile: fewer wake-ups of the process per IMU sample for up to this much more
    # latency on its outputs (0: each input at once). At 400 Hz, 10 ms on both took the fusion
    # from 20.2 to 14.3 % of a core for a fused p99 of 40.5 ms, not 19.1 (docs/benchmarks.md, rig-batch)
    input_batch_ms: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = 0.0


class CanWriterOptions(NodeOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    """Options of a node that writes CAN: its bus, and how the live runner paces its frames
    (``hil.runners.pacing``; ``hil sim`` models the wire itself and ignores the pacing ones)."""

    channel: str = "vcan0"  # CAN channel (the live runner's bus)
    interface: str | None = None  # python-can interface; None: socketcan if the channel exists, else hilzenoh
    fd: bool = False  # CAN FD
    # nominal (arbitration) bit rate: a frame's bit time on the wire
    bitrate: Annotated[int, msgspec.Meta(ge=10_000, le=1_000_000)] = 1_000_000
    # CAN FD data-phase bit rate (frames with bit-rate switch)
    data_bitrate: Annotated[int, msgspec.Meta(ge=10_000, le=12_000_000)] = 5_000_000
    # SCHED_FIFO priority of the sending thread (0: none; needs root or CAP_SYS_NICE)
    rt_priority: Annotated[int, msgspec.Meta(ge=0, le=99)] = 0
    cpu_affinity: list[Annotated[int, msgspec.Meta(ge=0)]] = []  # CPUs of the sending thread (empty: any)
    # the sending thread's scheduler time slice at normal priority, µs (Linux 6.12+ EEVDF, any
    # user): woken on a sample's tick it preempts what runs instead of waiting for that one's
    # slice to end (hil.runners.pacing.short_slice; 400 Hz here, docs/benchmarks.md pacing-slice:
    # samples over 200 µs late 516-1223 -> 124-336 of 8000). 0: the kernel's default
    sched_slice_us: Annotated[int, msgspec.Meta(ge=0, le=100_000)] = 100
    # a sample whose tick the host missed: "send" it late (a FIFO, at wire speed) or "skip" its slot
    late_policy: Literal["send", "skip"] = "send"
    # compute a tick up to this long before it is due (a fault command applies after it); 1 s
    # absorbs a physics block computed late on a loaded machine (0.25 s did not, at load 24)
    lookahead_s: Annotated[float, msgspec.Meta(ge=0.0, le=5.0)] = 1.0
    # the live runner wakes at most this often (at most lookahead_s): the ticks that entered the
    # look-ahead meanwhile are computed together, their bursts reach the pacing process in one
    # message, and the other outputs that came due (capture truth, events) are published
    # together, up to this much after their rig time; the frames still leave on their ticks.
    # 0: a wake-up per tick and per output (two per sample). 20 ms, not 10: the 400 Hz rig took
    # 0.90-0.96x of its CPU (half the emulator's wake-ups and capture-truth messages)
    compute_batch_ms: Annotated[float, msgspec.Meta(ge=0.0, le=100.0)] = 20.0


@dataclass
class CanBurst:
    """Frames that leave the device together: one sample's, or a sync frame alone.

    ``capture_ns``: true capture time of the sample (or sync edge) they carry; ``index``: its
    device sample index; ``sync``: a sync (time-tag) frame. The live runner only sends the
    frames; the virtual-clock runner's wire model times them from these facts."""

    frames: list[Any]  # can.Message
    capture_ns: int
    index: int
    sync: bool = False
    # a sync frame: the device's counter at ``capture_ns`` (ns, no stamp jitter), its rate
    # (device ns per rig ns) and its tick (ns) -- so a frame that cannot leave on its edge can
    # state what the counter reads when it does leave (the live runner's pacing; hil sim sends
    # every frame on time and never needs it)
    device_clock: tuple[int, float, int] | None = None
    corrupted: bool = False  # a can_burst_error corrupted it (a re-stamped copy is corrupted too)


@dataclass
class LineBurst:
    """Bytes a device puts on its serial line: the first leaves at ``start_ns``, the last is done
    at ``end_ns`` (the UART's pacing). The live runner writes them at that pace; the virtual
    clock runner delivers them to the line's readers at ``end_ns``."""

    data: bytes
    start_ns: int
    end_ns: int
    port: str


class Node:
    """Base of every node: options, per-key seq counters, counters and the last error."""

    name: ClassVar[str] = "node"
    Options: ClassVar[type[NodeOptions]] = NodeOptions
    inputs: ClassVar[tuple[Input, ...]] = ()
    # frames read off the CAN bus reach on_message("@can/<channel>", frame, rx_ns) when True
    reads_can: ClassVar[bool] = False
    writes_can: ClassVar[bool] = False  # it returns (CAN_TX, CanBurst) outputs
    sends_time_tags: ClassVar[bool] = False  # some of its bursts are sync (time-tag) frames
    # "tx": it may return (SERIAL_TX, LineBurst) outputs (when its options name a protocol);
    # "rx": bytes read off its line reach on_message("@serial/<port>", data, rx_ns)
    serial: ClassVar[str] = ""
    # what this node puts on the bus that others must find declared from its start
    outputs: ClassVar[tuple[str, ...]] = ()
    # an input can move its next tick (a fault command); False: only its own ticks move it
    inputs_move_timers: ClassVar[bool] = True
    # the live runner hands it every input its bounded inbox dropped (``on_dropped``): for a
    # node whose journal must name them (the fusion); the others' drops are only counted
    journals_drops: ClassVar[bool] = False
    # the live runner refuses inputs from publishers that are not the rig's (hil.bus.identity)
    # before they reach it: a node that re-publishes under its own name (the time sync) would
    # otherwise pass a stranger's data on as the rig's
    refuses_foreign: ClassVar[bool] = False
    # the CAN path's fixed latency after a frame's last bit (controller, driver): live, the
    # runner hands each frame to the bus that long after its wire time (hil sim's wire model
    # adds the same)
    can_wire_latency_ns: int = 0

    def __init__(self, run: RunInfo, options: NodeOptions | None = None) -> None:
        self.run = run
        self.options = options if options is not None else self.Options()
        self.generation = max(0, int(self.options.resume))
        self._seq_base = generation_seq(self.generation, 0)
        self._seqs: dict[str, int] = {}
        self.counts: dict[str, int] = {}
        self.last_error = ""
        self.errors_seen = 0  # bumps with every error(), so a runner can tell a new last_error

    # -- the runner's calls ------------------------------------------------------------------
    def start(self, now_ns: int) -> list[Out]:
        return []

    def on_message(self, key: str, msg: Any, now_ns: int) -> list[Out]:
        return []

    def on_message_from(self, key: str, msg: Any, now_ns: int, source: str) -> list[Out]:
        """``on_message`` with the publisher's id (the live runner's Zenoh source id; "" offline,
        where every input is the rig's). Only a node that names its inputs (the fusion's journal)
        needs it; the others ignore it."""
        return self.on_message(key, msg, now_ns)

    def on_dropped(self, key: str, msg: Any, source: str) -> None:
        """An input the runner's bounded inbox dropped before it got here (``hil.bus.inbox``: the
        runner counts it); a node whose decisions are journaled says so in its journal."""

    def tick(self, now_ns: int) -> list[Out]:
        return []

    def next_tick_ns(self) -> int | None:
        """When the node next wants ``tick`` (rig ns), or None: only inputs wake it."""
        return None

    def finish(self, now_ns: int) -> list[Out]:
        return []

    def counters(self) -> dict[str, int]:
        """The status's counters: ``inc``/``error`` counts by default; nodes add their cores'."""
        return dict(self.counts)

    # -- helpers -----------------------------------------------------------------------------
    def next_seq(self, key: str) -> int:
        n = self._seqs.get(key, 0)
        self._seqs[key] = n + 1
        return self._seq_base | n  # generation_seq(self.generation, n)

    def continue_seq(self, key: str, taken: int) -> None:
        """Seqs ``0..taken-1`` of ``key`` were used by someone else on the same key (a live
        service's own events before its node existed): this node's count goes on from there."""
        self._seqs[key] = max(self._seqs.get(key, 0), taken)

    def inc(self, name: str, n: int = 1) -> None:
        self.counts[name] = self.counts.get(name, 0) + n

    def error(self, counter: str, message: str) -> None:
        """Count a rejected input or a failure and remember why (the status's ``last_error``)."""
        self.inc(counter)
        self.last_error = message[:500]
        self.errors_seen += 1

    def event(self, kind: str, detail: str, stamp_ns: int) -> Out:
        key = f"event/{self.name}"
        ev = Event(seq=self.next_seq(key), stamp_ns=stamp_ns, kind=kind, source=self.name, detail=detail)
        return key, ev


class OptionsError(ValueError):
    """Options that cannot be used; one line naming the field (``hil service --options``)."""


def decode_options(cls: type[NodeOptions], raw: Mapping[str, Any] | None, service: str) -> Any:
    """``raw`` (decoded ``--options`` JSON) as ``cls``; a bad or unknown field is one line."""
    try:
        return msgspec.convert(dict(raw or {}), cls)
    except msgspec.ValidationError as err:
        text = str(err)
        if "unknown field" in text:
            name = text.split("`")[1] if "`" in text else "?"
            known = ", ".join(cls.__struct_fields__)
            raise OptionsError(f"{service}: unknown option {name!r}; known options: {known}") from None
        if "at `$." in text:
            what, _, where = text.rpartition(" - at `$.")
            raise OptionsError(f"{service}: option {where.rstrip('`')}: {what}") from None
        raise OptionsError(f"{service}: {text}") from None

"""A python-can interface that carries CAN frames over the rig's Zenoh network (``hilzenoh``).

Why: this host's kernel has no SocketCAN and python-can's ``virtual`` bus stays inside one
process, yet the rig's emulator and bridge are separate processes (and containers). With this
backend the very same ``can.Bus(interface=..., channel="vcan0")`` calls work everywhere:

    bus = can.Bus(interface="hilzenoh", channel="vcan0", rig="bench1", fd=True)

Which rig: the ``rig`` keyword, which python-can also fills from its own configuration -- a
config file section (``~/.canrc``, ``~/can.conf``, ``/etc/can.conf``; ``rig = bench``), the
``CAN_CONFIG`` environment variable (JSON), a ``can.Bus(..., context="name")`` section, or
``--bus-kwargs rig=bench`` on python-can's own tools (``python -m can.logger``, ``can.viewer``)
-- then ``$HIL_RIG``, then ``default``. A bus that has neither sent nor received a frame
``no_traffic_warn_s`` (default 5 s) after it opened logs a warning on python-can's logger
(``can.hilzenoh``) naming its key, where its rig came from, and the rigs that are alive on the
network (their ``hil/<rig>/@alive/*`` liveliness tokens): the usual cause is the wrong rig.

Semantics copied from SocketCAN so code cannot tell the difference:

- one Zenoh key per channel, ``hilcan/<rig>/<channel>`` (``Keys.canbus``), reliable with blocking
  congestion control (a slow reader back-pressures the writer instead of losing frames);
- a received frame's timestamp (epoch seconds) is the instant its sender put it on the wire, when
  the sender says so (``send_stamped``: the live runner's pacing passes each frame's wire time,
  carried as the Zenoh attachment), else its arrival (``time.time()``): the first is what the
  kernel does on ``vcan`` (it stamps the frame in the sender's ``send``), and the stamp then does
  not wait for the receiving process to be scheduled. A stated stamp later than the arrival
  (clock skew between hosts) is replaced by the arrival and counted (``rx_stamp_skew``);
- a bus opened with ``receive=False`` only sends (no subscription);
- a frame sent on a bus is not received back by that bus (unless ``receive_own_messages=True``);
  other buses, in this process or another, receive it;
- a bus opened with ``fd=False`` refuses to send FD frames and does not see them (a classic
  SocketCAN socket behaves so).

What a frame costs (``hil bench bus``): Zenoh's default batching, not ``express``. A frame is
still written to the socket at once when the link is idle -- Zenoh holds a message only while
its transmit task is busy with the previous one -- so the receive stamp stays close to the send,
but frames put back to back (one sample's four) share one write and one wake-up of the reader:
express cost ~20 µs of CPU per frame on each side. Frames reach the other buses of the *same*
Zenoh session (a service's, shared) straight from ``send``; the subscription takes remote ones
only, so a sender is not woken by the echo of its own frames (it was, once per frame).

One sample's frames in one Zenoh message (``send_burst_stamped``): the live runner's pacing
hands a sample's frames over together when its last frame is done on the wire, each frame with
its own wire time -- one put, one routing through the hub and one callback in each reader, where
four puts back to back already shared Zenoh's batch and mostly one wake-up (measured: ``hil
bench bus`` case ``hilzenoh burst``, and docs/benchmarks.md ``rig-burst``: the CAN bridge ~2
points of a core lower, the rig within its spread). A receiver still gets each frame as its own
``can.Message`` with its own stamp, so readers cannot tell the difference, except that a
burst's first frames arrive together with its last (a reader that completes a sample on its
last frame loses nothing).

Wire format of one Zenoh payload (little-endian), one or more frame records back to back
(:mod:`hil.can.frame_bus`)::

    u64 sender id | u32 arbitration id | u8 flags | u8 length | data[length]
    flags: 1 extended, 2 FD, 4 bit-rate switch, 8 error-state indicator, 16 error frame, 32 remote

and the attachment, when the sender states wire times: one ``i64`` epoch-ns stamp per record, in
order. A payload with a truncated record is counted whole in ``rx_malformed`` (none of its
frames is delivered); an attachment that is not one stamp per record is not ours to read, and
the frames get their arrival as stamp.
"""

from __future__ import annotations

import contextlib
import logging
import os
import struct
import threading
import time
import weakref
from collections.abc import Sequence
from typing import Any, ClassVar

import can
import zenoh

from hil.bus.keys import Keys, check_name
from hil.bus.session import BusConfig, open_session
from hil.can.frame_bus import FrameQueueBus, unpack_frames

log = logging.getLogger("can.hilzenoh")  # python-can's logger tree, as its own interfaces

NO_TRAFFIC_WARN_S = 5.0
_STAMP = struct.Struct("<q")  # the attachment: wire time of the frame, epoch ns
FRAME_ENCODING = zenoh.Encoding.APPLICATION_OCTET_STREAM.with_schema("hilzenoh.frame")  # the format above


class _LocalBuses:
    """The buses of one Zenoh session on one key: they hand frames to each other directly."""

    _lock: ClassVar[threading.Lock] = threading.Lock()
    _groups: ClassVar[weakref.WeakValueDictionary[tuple[int, str], _LocalBuses]] = (
        weakref.WeakValueDictionary()
    )

    def __init__(self) -> None:
        self.buses: tuple[ZenohCanBus, ...] = ()  # replaced whole: send() reads it without a lock

    @classmethod
    def join(cls, session: zenoh.Session, key: str, bus: ZenohCanBus) -> _LocalBuses:
        with cls._lock:
            group = cls._groups.get((id(session), key))
            if group is None:
                group = cls._groups[(id(session), key)] = cls()
            group.buses = (*group.buses, bus)
            return group

    def leave(self, bus: ZenohCanBus) -> None:
        with self._lock:
            self.buses = tuple(b for b in self.buses if b is not bus)


class ZenohCanBus(FrameQueueBus):
    """python-can bus over Zenoh. Keyword arguments beyond python-can's own:

    - ``rig``: rig namespace of the key (default ``$HIL_RIG`` or ``"default"``);
    - ``fd``: accept and send CAN FD frames (default False);
    - ``session``: an open ``zenoh.Session`` to reuse (it is then not closed by ``shutdown``);
      otherwise one is opened from ``BusConfig.from_env()``;
    - ``receive_own_messages``: also deliver this bus's own frames (default False);
    - ``rx_queue_size``: frames held for ``recv`` before new ones are dropped and counted in
      ``rx_overflow`` (default 100 000, like a generous socket buffer);
    - ``no_traffic_warn_s``: warn when nothing was sent or received this long after opening
      (default 5; 0: never).
    """

    NAME = "hilzenoh"

    def __init__(
        self,
        channel: Any = "vcan0",
        can_filters: Any = None,
        *,
        rig: str | None = None,
        fd: bool = False,
        session: zenoh.Session | None = None,
        receive_own_messages: bool = False,
        rx_queue_size: int = 100_000,
        receive: bool = True,
        no_traffic_warn_s: float = NO_TRAFFIC_WARN_S,
        **kwargs: Any,
    ) -> None:
        self.channel = str(channel or "vcan0")
        if rig:
            self.rig, self.rig_source = str(rig), "the rig keyword or python-can's configuration"
        elif os.environ.get("HIL_RIG"):
            self.rig, self.rig_source = os.environ["HIL_RIG"], "HIL_RIG"
        else:
            self.rig, self.rig_source = "default", "nothing set (rig keyword, python-can config, HIL_RIG)"
        try:
            check_name("rig", self.rig)
        except ValueError as err:
            raise can.CanInitializationError(f"hilzenoh: {err} (from {self.rig_source})") from None
        self.key = Keys(self.rig).canbus(self.channel)
        self._init_frames(fd, receive_own_messages, rx_queue_size, self.key)
        self.rx_samples = 0  # every sample on the key, own frames included: traffic on the rig
        self._sub: Any = None
        self._own_session = session is None
        try:
            self._session = session if session is not None else open_session(BusConfig.from_env())
        except Exception as err:
            raise can.CanInitializationError(f"hilzenoh: cannot open a Zenoh session: {err}") from err
        try:
            self._pub = self._session.declare_publisher(
                self.key,
                reliability=zenoh.Reliability.RELIABLE,
                congestion_control=zenoh.CongestionControl.BLOCK,
                encoding=FRAME_ENCODING,
            )
            # remote frames only: this session's own buses get theirs from send() (_LocalBuses)
            if receive:
                self._sub = self._session.declare_subscriber(
                    self.key, self._on_sample, allowed_origin=zenoh.Locality.REMOTE
                )
        except Exception as err:
            if self._own_session:
                self._session.close()
            raise can.CanInitializationError(f"hilzenoh: cannot declare {self.key}: {err}") from err
        super().__init__(channel=self.channel, can_filters=can_filters, **kwargs)
        self._local = _LocalBuses.join(self._session, self.key, self)
        self._watch: threading.Timer | None = None
        if no_traffic_warn_s and no_traffic_warn_s > 0:
            self._watch = threading.Timer(
                float(no_traffic_warn_s), self._warn_if_silent, (no_traffic_warn_s,)
            )
            self._watch.daemon = True
            self._watch.start()

    def _warn_if_silent(self, after_s: float) -> None:
        """Nothing on the key after ``after_s``: say which key, whose rig, and which rigs are alive."""
        if self._closed.is_set() or self.rx_samples or self.tx_frames:
            return
        rigs: set[str] = set()
        try:
            for reply in self._session.liveliness().get("hil/*/@alive/*", timeout=1.0):
                if reply.ok is not None:
                    parts = str(reply.ok.key_expr).split("/")
                    if len(parts) > 1:
                        rigs.add(parts[1])
        except Exception:  # the warning goes out without the list
            rigs.clear()
        alive = (
            f"rigs alive on this network: {', '.join(sorted(rigs))}"
            if rigs
            else "no rig is alive on this network"
        )
        log.warning(
            "hilzenoh: no CAN frame on %s in %g s; rig %r comes from %s; %s",
            self.key,
            after_s,
            self.rig,
            self.rig_source,
            alive,
        )

    # Runs on a Zenoh thread: stamp first, never raise.
    def _on_sample(self, sample: zenoh.Sample) -> None:
        arrival = time.time()
        try:
            payload = sample.payload.to_bytes()
        except Exception:
            self.rx_samples += 1
            self.rx_malformed += 1
            return
        att = sample.attachment
        self._on_payload(payload, arrival, None if att is None else att.to_bytes())

    def _stamps(self, wire: bytes | None, n: int, arrival: float) -> list[float]:
        """Each frame's receive stamp: the sender's wire time (``send_stamped``,
        ``send_burst_stamped``) unless it is after the arrival (clock skew), else the arrival. An
        attachment that is not one stamp per frame is not ours to read: arrival stamps."""
        if wire is None or len(wire) != _STAMP.size * n:
            return [arrival] * n
        return [self._stamp(ns, arrival) for (ns,) in _STAMP.iter_unpack(wire)]

    def _on_payload(self, payload: bytes, arrival: float, wire: bytes | None = None) -> None:
        """Frames on the key (one, or a burst's), from Zenoh or from a bus of this session."""
        self.rx_samples += 1
        try:
            frames = unpack_frames(payload)
        except Exception:
            self.rx_malformed += 1
            return
        stamps = self._stamps(wire, len(frames), arrival)
        for (sender, msg), stamp in zip(frames, stamps, strict=True):
            self._deliver(sender, msg, stamp)

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Publish ``msg``; raises ``CanOperationError`` on a closed bus or an illegal frame."""
        self._publish(self._packed(msg), None, 1)

    def send_stamped(self, msg: can.Message, stamp_epoch_ns: int, timeout: float | None = None) -> None:
        """``send``, telling receivers the frame was on the wire at ``stamp_epoch_ns`` (their
        receive stamp; see the module docstring)."""
        self._publish(self._packed(msg), _STAMP.pack(int(stamp_epoch_ns)), 1)

    def send_burst_stamped(
        self, msgs: Sequence[can.Message], stamps_epoch_ns: Sequence[int], timeout: float | None = None
    ) -> None:
        """Frames that leave back to back (one sample's) as one Zenoh message, each with its own
        wire time: all published or none (see the module docstring)."""
        if len(msgs) != len(stamps_epoch_ns):
            raise can.CanOperationError(
                f"hilzenoh: a burst of {len(msgs)} frames with {len(stamps_epoch_ns)} stamps"
            )
        if not msgs:
            return
        payload = b"".join([self._packed(m) for m in msgs])
        self._publish(payload, struct.pack(f"<{len(msgs)}q", *stamps_epoch_ns), len(msgs))

    def _publish(self, payload: bytes, wire: bytes | None, frames: int) -> None:
        try:
            if wire is None:
                self._pub.put(payload)
            else:
                self._pub.put(payload, attachment=wire)
        except Exception as err:
            raise can.CanOperationError(f"hilzenoh: publish on {self.key} failed: {err}") from err
        self.tx_frames += frames
        buses = self._local.buses
        if len(buses) > 1 or self.receive_own_messages:
            now = time.time()
            for bus in buses:
                if bus is not self or self.receive_own_messages:
                    bus._on_payload(payload, now, wire)

    def shutdown(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._local.leave(self)
        if self._watch is not None:
            self._watch.cancel()
        super().shutdown()
        for thing in (self._sub, self._pub):
            if thing is None:
                continue
            with contextlib.suppress(Exception):  # the session may already be closing
                thing.undeclare()
        if self._own_session:
            # Reliable queues drain asynchronously; closing at once loses the tail on slow hosts.
            time.sleep(0.05)
            with contextlib.suppress(Exception):
                self._session.close()

    @staticmethod
    def _detect_available_configs() -> list[Any]:
        return [{"interface": "hilzenoh", "channel": "vcan0"}]

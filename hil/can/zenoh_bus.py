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
- a received frame is stamped on arrival with ``time.time()`` (epoch seconds), like the kernel's
  receive timestamp;
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

Wire format of one Zenoh payload (little-endian)::

    u64 sender id | u32 arbitration id | u8 flags | u8 length | data[length]
    flags: 1 extended, 2 FD, 4 bit-rate switch, 8 error-state indicator, 16 error frame, 32 remote
"""

from __future__ import annotations

import contextlib
import logging
import os
import queue
import secrets
import struct
import threading
import time
import weakref
from typing import Any, ClassVar

import can
import zenoh
from can import CanProtocol

from hil.bus.keys import Keys, check_name
from hil.bus.session import BusConfig, open_session

log = logging.getLogger("can.hilzenoh")  # python-can's logger tree, as its own interfaces

NO_TRAFFIC_WARN_S = 5.0
_HEADER = struct.Struct("<QIBB")
F_EXT, F_FD, F_BRS, F_ESI, F_ERR, F_RTR = 1, 2, 4, 8, 16, 32
FD_LENGTHS = frozenset([*range(9), 12, 16, 20, 24, 32, 48, 64])
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


def pack_frame(sender: int, msg: can.Message) -> bytes:
    """One frame as a Zenoh payload (see the module docstring)."""
    flags = (
        (F_EXT if msg.is_extended_id else 0)
        | (F_FD if msg.is_fd else 0)
        | (F_BRS if msg.bitrate_switch else 0)
        | (F_ESI if msg.error_state_indicator else 0)
        | (F_ERR if msg.is_error_frame else 0)
        | (F_RTR if msg.is_remote_frame else 0)
    )
    data = bytes(msg.data or b"")
    return _HEADER.pack(sender, msg.arbitration_id, flags, len(data)) + data


def unpack_frame(payload: bytes) -> tuple[int, can.Message]:
    """The inverse of :func:`pack_frame`; raises ``ValueError`` on a malformed payload."""
    if len(payload) < _HEADER.size:
        raise ValueError(f"CAN payload of {len(payload)} B is shorter than its {_HEADER.size} B header")
    sender, arb, flags, length = _HEADER.unpack_from(payload)
    data = payload[_HEADER.size :]
    if len(data) != length or length > 64:
        raise ValueError(f"CAN payload announces {length} data bytes, carries {len(data)}")
    msg = can.Message(
        arbitration_id=arb,
        is_extended_id=bool(flags & F_EXT),
        is_fd=bool(flags & F_FD),
        bitrate_switch=bool(flags & F_BRS),
        error_state_indicator=bool(flags & F_ESI),
        is_error_frame=bool(flags & F_ERR),
        is_remote_frame=bool(flags & F_RTR),
        data=data,
        dlc=length,
        check=False,
    )
    return sender, msg


class ZenohCanBus(can.BusABC):
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
        self.fd = bool(fd)
        self.receive_own_messages = receive_own_messages
        self.channel_info = f"hilzenoh {self.key} ({'CAN FD' if self.fd else 'CAN 2.0'})"
        self._can_protocol = CanProtocol.CAN_FD if self.fd else CanProtocol.CAN_20
        self._sender = secrets.randbits(64)
        self._rx: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self._rx_max = max(1, int(rx_queue_size))
        self._closed = threading.Event()
        self.rx_overflow = 0
        self.rx_malformed = 0
        self.rx_fd_ignored = 0
        self.tx_frames = 0
        self.rx_frames = 0
        self.rx_samples = 0  # every sample on the key, own frames included: traffic on the rig
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
        stamp = time.time()
        try:
            payload = sample.payload.to_bytes()
        except Exception:
            self.rx_samples += 1
            self.rx_malformed += 1
            return
        self._on_payload(payload, stamp)

    def _on_payload(self, payload: bytes, stamp: float) -> None:
        """A frame on the key, from Zenoh or from a bus of this session (``send``)."""
        self.rx_samples += 1
        try:
            sender, msg = unpack_frame(payload)
        except Exception:
            self.rx_malformed += 1
            return
        if sender == self._sender and not self.receive_own_messages:
            return
        if msg.is_fd and not self.fd:
            self.rx_fd_ignored += 1
            return
        msg.timestamp = stamp
        msg.channel = self.channel
        msg.is_rx = sender != self._sender
        if self._rx.qsize() >= self._rx_max:  # a bound on memory (a racing producer may pass it by one)
            self.rx_overflow += 1
            return
        self._rx.put(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._closed.is_set():
            raise can.CanOperationError("hilzenoh: bus is shut down")
        try:
            msg = self._rx.get(timeout=timeout) if timeout is None or timeout > 0 else self._rx.get_nowait()
        except queue.Empty:
            return None, False
        self.rx_frames += 1
        return msg, False

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        """Publish ``msg``; raises ``CanOperationError`` on a closed bus or an illegal frame."""
        if self._closed.is_set():
            raise can.CanOperationError("hilzenoh: bus is shut down")
        n = len(msg.data or b"")
        if msg.is_fd:
            if not self.fd:
                raise can.CanOperationError("hilzenoh: FD frame on a bus opened with fd=False")
            if n not in FD_LENGTHS:
                raise can.CanOperationError(f"hilzenoh: {n} data bytes is not a CAN FD length")
        elif n > 8:
            raise can.CanOperationError(f"hilzenoh: {n} data bytes in a classic CAN frame")
        payload = pack_frame(self._sender, msg)
        try:
            self._pub.put(payload)
        except Exception as err:
            raise can.CanOperationError(f"hilzenoh: publish on {self.key} failed: {err}") from err
        self.tx_frames += 1
        buses = self._local.buses
        if len(buses) > 1 or self.receive_own_messages:
            stamp = time.time()
            for bus in buses:
                if bus is not self or self.receive_own_messages:
                    bus._on_payload(payload, stamp)

    def shutdown(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        self._local.leave(self)
        if self._watch is not None:
            self._watch.cancel()
        super().shutdown()
        for thing in (self._sub, self._pub):
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

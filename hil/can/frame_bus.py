"""CAN frames as the rig's own python-can buses carry them (``hilzenoh`` over Zenoh,
``hillocal`` over local sockets): the frame record both put on their medium, and what both do
with frames -- the SocketCAN frame rules on the way out, the receive stamp and a bounded queue
for ``recv`` on the way in.

A frame record (little-endian)::

    u64 sender id | u32 arbitration id | u8 flags | u8 length | data[length]
    flags: 1 extended, 2 FD, 4 bit-rate switch, 8 error-state indicator, 16 error frame, 32 remote

One payload holds one record or a burst's, back to back.
"""

from __future__ import annotations

import queue
import secrets
import struct
import threading
from typing import ClassVar

import can
from can import CanProtocol

_HEADER = struct.Struct("<QIBB")
F_EXT, F_FD, F_BRS, F_ESI, F_ERR, F_RTR = 1, 2, 4, 8, 16, 32
FD_LENGTHS = frozenset([*range(9), 12, 16, 20, 24, 32, 48, 64])


def pack_frame(sender: int, msg: can.Message) -> bytes:
    """One frame's record (see the module docstring): a hilzenoh payload or part of a hillocal packet."""
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
    frames = unpack_frames(payload)
    if len(frames) != 1:
        raise ValueError(f"CAN payload carries {len(frames)} frames, not one")
    return frames[0]


def unpack_frames(payload: bytes) -> list[tuple[int, can.Message]]:
    """Every frame record of a payload (one, or a burst's); ``ValueError`` if any is malformed."""
    out: list[tuple[int, can.Message]] = []
    at, end = 0, len(payload)
    while True:
        if end - at < _HEADER.size:
            raise ValueError(
                f"CAN payload of {end} B: {end - at} B at offset {at}, short of a {_HEADER.size} B header"
            )
        sender, arb, flags, length = _HEADER.unpack_from(payload, at)
        at += _HEADER.size
        if length > 64 or at + length > end:
            raise ValueError(f"CAN payload announces {length} data bytes, carries {min(end - at, length)}")
        out.append((sender, _message(arb, flags, payload[at : at + length])))
        at += length
        if at == end:
            return out


def _message(arb: int, flags: int, data: bytes) -> can.Message:
    length = len(data)
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
    return msg


class FrameQueueBus(can.BusABC):
    """What the rig's two python-can buses share (``hilzenoh``, :mod:`hil.can.zenoh_bus`, and
    ``hillocal``, :mod:`hil.can.local_bus`): the frame rules of a SocketCAN socket on the way out, and on the
    way in a bounded queue for ``recv`` fed with each frame's stamp. A subclass sets ``NAME`` and,
    before it receives, ``channel``, ``fd``, ``receive_own_messages``, ``_sender``, ``_closed``,
    ``_rx_max`` and the counters."""

    NAME: ClassVar[str] = "hil"
    channel: str
    fd: bool
    receive_own_messages: bool
    _sender: int
    _closed: threading.Event
    _rx_max: int
    rx_overflow: int
    rx_fd_ignored: int
    rx_stamp_skew: int
    rx_frames: int

    def _init_frames(self, fd: bool, receive_own_messages: bool, rx_queue_size: int, where: str) -> None:
        """The state both buses keep: frame rules, identity, the receive queue, the counters."""
        self.fd = bool(fd)
        self.receive_own_messages = receive_own_messages
        self.channel_info = f"{self.NAME} {where} ({'CAN FD' if self.fd else 'CAN 2.0'})"
        self._can_protocol = CanProtocol.CAN_FD if self.fd else CanProtocol.CAN_20
        self._sender = secrets.randbits(64)
        self._rx: queue.SimpleQueue[can.Message] = queue.SimpleQueue()
        self._rx_max = max(1, int(rx_queue_size))
        self._closed = threading.Event()
        self.rx_overflow = 0
        self.rx_malformed = 0
        self.rx_fd_ignored = 0
        self.rx_stamp_skew = 0
        self.rx_frames = 0
        self.tx_frames = 0

    def _stamp(self, wire_ns: int | None, arrival: float) -> float:
        """A frame's receive stamp: its sender's wire time unless that is after the arrival
        (clock skew between hosts, counted), else the arrival."""
        if wire_ns is None:
            return arrival
        wire_s = wire_ns * 1e-9
        if wire_s <= arrival:
            return wire_s
        self.rx_stamp_skew += 1
        return arrival

    def _deliver(self, sender: int, msg: can.Message, stamp: float) -> None:
        """One received frame into the queue, unless this bus may not see it."""
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
            raise can.CanOperationError(f"{self.NAME}: bus is shut down")
        try:
            msg = self._rx.get(timeout=timeout) if timeout is None or timeout > 0 else self._rx.get_nowait()
        except queue.Empty:
            return None, False
        self.rx_frames += 1
        return msg, False

    def _packed(self, msg: can.Message) -> bytes:
        """The frame's record, or ``CanOperationError`` if this bus may not send it."""
        if self._closed.is_set():
            raise can.CanOperationError(f"{self.NAME}: bus is shut down")
        n = len(msg.data or b"")
        if msg.is_fd:
            if not self.fd:
                raise can.CanOperationError(f"{self.NAME}: FD frame on a bus opened with fd=False")
            if n not in FD_LENGTHS:
                raise can.CanOperationError(f"{self.NAME}: {n} data bytes is not a CAN FD length")
        elif n > 8:
            raise can.CanOperationError(f"{self.NAME}: {n} data bytes in a classic CAN frame")
        return pack_frame(self._sender, msg)

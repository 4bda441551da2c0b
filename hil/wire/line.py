"""A receiver's serial line: the UART that paces its bytes, and the reader that splits them.

``Uart`` is the transmit side as a receiver has it: bytes leave at ``baud`` (10 bits a byte:
start, 8 data, stop), one message after the other; what the line cannot carry waits in a
transmit buffer of ``tx_buffer_bytes``, and a message that does not fit in it is dropped whole
-- an overrun, counted, as a u-blox receiver drops output when its port buffer is full. Pure:
the caller says when a message is ready and gets back when its first and last byte go out.

``LineDecoder`` is the receiving side of a line that may carry NMEA and UBX together (a u-blox
port with both protocols on): it splits the stream into each protocol's messages by their start
bytes and lengths (the protocol class's ``START`` and ``message_length``), hands each to its
protocol's decoder and counts what is neither. With one protocol it is that protocol's decoder.
Each fix it returns says how many bytes of its epoch the line carried up to the end of the chunk
that completed it (``DecodedFix.line_bytes``), from the epoch's first message in any protocol
(a u-blox port sends an epoch's NMEA sentences and UBX frames back to back): the receiver's
latency ends at that first byte, and at 115200 baud the default NMEA set takes ~27 ms after it.
A line at the wrong baud rate reads as a stream of garbage with no message in it: after
``BAUD_MISMATCH_BYTES`` such bytes in a row it says so (``baud_mismatch``), once per stretch.
"""

from __future__ import annotations

from collections import deque
from dataclasses import dataclass, field, replace
from typing import Any

from hil.wire import protocol
from hil.wire.base import DecodedFix

BITS_PER_BYTE = 10  # 8N1: start bit, 8 data bits, stop bit
BAUD_MISMATCH_BYTES = 256  # this many bytes in a row with no message in them: the wrong baud rate
PLACED_MESSAGES = 64  # recent messages a decoder's positions map back from (an epoch has < 20)
SAME_EPOCH_NS = 5_000_000  # two protocols' fixes this close in GPS time are one epoch (NMEA: 10 ms digits)


def byte_time_ns(baud: int) -> float:
    """Nanoseconds one byte occupies the line at ``baud`` (8N1)."""
    return BITS_PER_BYTE * 1e9 / baud


@dataclass
class Uart:
    """The transmit side: when each message's bytes go out, and which ones overrun the buffer."""

    baud: float  # in the caller's time: a line's baud rate over ``hil up --speed`` in rig time
    tx_buffer_bytes: int = 4096
    free_at_ns: int = -(2**62)  # when the line has sent everything handed to it so far
    sent_bytes: int = 0
    overrun_bytes: int = 0
    overrun_messages: int = 0

    def queued_bytes(self, now_ns: int) -> int:
        """Bytes still waiting in the transmit buffer at ``now_ns``."""
        return max(0, int((self.free_at_ns - now_ns) / byte_time_ns(self.baud) + 0.999))

    def send(self, n_bytes: int, ready_ns: int) -> tuple[int, int] | None:
        """A message of ``n_bytes`` ready at ``ready_ns``: (first byte out, last byte done), or
        None if it overruns the transmit buffer (dropped whole, counted)."""
        if self.queued_bytes(ready_ns) + n_bytes > self.tx_buffer_bytes:
            self.overrun_bytes += n_bytes
            self.overrun_messages += 1
            return None
        start = max(ready_ns, self.free_at_ns)
        end = start + round(n_bytes * byte_time_ns(self.baud))
        self.free_at_ns = end
        self.sent_bytes += n_bytes
        return start, end

    def occupancy(self, span_ns: int) -> float:
        """Share of ``span_ns`` the line was busy, from the bytes sent over it."""
        return self.sent_bytes * byte_time_ns(self.baud) / span_ns if span_ns > 0 else 0.0


@dataclass
class LineDecoder:
    """Decode a line carrying one or more GNSS protocols; never raises on any input."""

    protocols: tuple[str, ...]
    messages: tuple[str, ...] = ()
    counters: dict[str, int] = field(default_factory=dict)
    last_problem: str = ""
    _buf: bytearray = field(default_factory=bytearray)
    _garbage_run: int = 0
    # (GPS time, first byte on the line) of recent fixes of every protocol: one epoch's
    _starts: deque[tuple[int, int]] = field(default_factory=lambda: deque(maxlen=8))
    # several protocols: per decoder, (bytes fed to it, where on the line) of its recent messages
    _placed: dict[str, deque[tuple[int, int]]] = field(default_factory=dict)
    _fed: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.decoders: dict[str, Any] = {}
        self._framing: dict[str, tuple[bytes, Any]] = {}
        for name in self.protocols:
            cls = protocol(name)
            mine = tuple(m for m in self.messages if m in cls.SUPPORTED_MESSAGES) or None
            self.decoders[name] = cls(mine).decoder()
            self._framing[name] = (cls.START, cls.message_length)
        self.counters.update(garbage_bytes=0, baud_mismatch=0, bytes=0)

    def feed(self, data: bytes, rx_ns: int) -> list[DecodedFix]:
        self.counters["bytes"] += len(data)
        before = self._valid_messages()
        if len(self.decoders) == 1:
            (dec,) = self.decoders.values()
            garbage = dec.counters.get("garbage_bytes", 0)
            out: list[DecodedFix] = dec.feed(data, rx_ns)
            self._garbage(dec.counters.get("garbage_bytes", 0) - garbage)
        else:
            self._buf += data
            out = self._split(rx_ns)
        if self._valid_messages() > before:
            self._garbage_run = 0  # a message with a valid checksum: the baud rate is right
        return self._on_line(out) if out else out

    def _place(self, name: str, line_at: int, n: int) -> None:
        """A message of ``n`` bytes at ``line_at`` on the line goes to ``name``'s decoder."""
        placed = self._placed.get(name)
        if placed is None:
            placed = self._placed[name] = deque(maxlen=PLACED_MESSAGES)
        fed = self._fed.get(name, 0)
        placed.append((fed, line_at))
        self._fed[name] = fed + n

    def _on_line_at(self, fix: DecodedFix) -> int:
        """Where on the line the fix's epoch began (-1: not known)."""
        at = fix.first_byte_at
        if at < 0 or len(self.decoders) == 1:
            return at
        for fed, line_at in reversed(self._placed.get(fix.protocol, ())):
            if fed <= at:
                return line_at + (at - fed)  # a decoder's message is fed whole: one stretch
        return -1

    def _on_line(self, fixes: list[DecodedFix]) -> list[DecodedFix]:
        """Each fix with the bytes its epoch took on the line, from the epoch's first message in
        any protocol to the end of what has been fed."""
        end = self.counters["bytes"]
        out = []
        for fix in fixes:
            first = self._on_line_at(fix)
            t = fix.gps_time_ns
            if t is not None and first >= 0:
                first = min([first, *(at for t0, at in self._starts if abs(t0 - t) < SAME_EPOCH_NS)])
                self._starts.append((t, first))
            out.append(replace(fix, first_byte_at=first, line_bytes=end - first) if first >= 0 else fix)
        return out

    def _valid_messages(self) -> int:
        return sum(int(d.counters.get("messages", 0)) for d in self.decoders.values())

    def _split(self, rx_ns: int) -> list[DecodedFix]:
        """Each message to the protocol whose start bytes it begins with (its class's ``START``
        and ``message_length``); bytes that start none are garbage."""
        buf, out = self._buf, []
        while buf:
            for name, (start, length) in self._framing.items():
                if buf[: len(start)] == start[: len(buf)]:
                    n = length(buf)
                    if n == 0:
                        return out  # the rest of the message is still on the way
                    if n > 0:
                        self._place(name, self.counters["bytes"] - len(buf), n)
                        out += self.decoders[name].feed(bytes(buf[:n]), rx_ns)
                        del buf[:n]
                        break
            else:
                skip = self._next_start(buf)
                del buf[:skip]
                self._garbage(skip)
        return out

    def _next_start(self, buf: bytearray) -> int:
        """How many bytes before the next possible start of a message (at least one)."""
        cut = [i for start, _ in self._framing.values() if (i := buf.find(start[:1], 1)) > 0]
        return min(cut) if cut else len(buf)

    def _garbage(self, n: int) -> None:
        if n <= 0:
            return
        self.counters["garbage_bytes"] += n
        before = self._garbage_run
        self._garbage_run += n
        if before < BAUD_MISMATCH_BYTES <= self._garbage_run:
            self.counters["baud_mismatch"] += 1
            self.last_problem = (
                f"{self._garbage_run} bytes in a row with no valid NMEA sentence or UBX frame: "
                "is the line at the receiver's baud rate?"
            )

    def flush(self) -> list[DecodedFix]:
        out: list[DecodedFix] = []
        for dec in self.decoders.values():
            out += dec.flush()
        return self._on_line(out)

    def all_counters(self) -> dict[str, int]:
        """This line's counters and each protocol decoder's, prefixed with its name."""
        out = dict(self.counters)
        for name, dec in self.decoders.items():
            out.update({f"{name}.{k}": v for k, v in dec.counters.items()})
        return out

    def problem(self) -> str:
        """The most specific last problem: a decoder's, else the line's."""
        for dec in self.decoders.values():
            if dec.last_problem:
                return str(dec.last_problem)
        return self.last_problem

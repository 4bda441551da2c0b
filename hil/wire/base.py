"""The types every GNSS wire protocol shares: what a receiver reports, what a decoder gets back.

The emulator states one :class:`ReceiverEpoch` per navigation epoch; a protocol turns it into the
bytes a real receiver would put on its UART (:meth:`WireProtocol.encode_epoch`), and its decoder turns
any byte stream, split anywhere and possibly damaged, back into :class:`DecodedFix` records. The
decoder never raises on input: a device under test sees bad bytes too, and the rig must count them
(``counters``) and say what the last one was (``last_problem``) rather than stop.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import ClassVar, Protocol

Vec3 = tuple[float, float, float]
OptVec3 = tuple[float | None, float | None, float | None]
NO_VEC3: OptVec3 = (None, None, None)

FIX_NONE, FIX_2D, FIX_3D = 0, 2, 3
FIX_TYPES = (FIX_NONE, FIX_2D, FIX_3D)

# every decoder has at least these counters
COUNTER_NAMES: tuple[str, ...] = (
    "bytes",  # bytes fed
    "messages",  # well-formed messages (sentences / frames) with a valid checksum
    "fixes",  # DecodedFix records returned
    "bad_checksum",  # complete message whose checksum does not match
    "truncated",  # message cut short (the next one started inside it, or no checksum)
    "unknown",  # well-formed message of a type the decoder does not read (counted, skipped)
    "garbage_bytes",  # bytes outside any message
    "too_long",  # line / frame longer than the protocol allows
    "malformed",  # valid checksum but fields that do not parse (wrong length, bad number)
    "incomplete",  # an epoch closed without a position message (nothing to report)
    "late",  # a message of an epoch already closed (reported once, not again)
)


@dataclass(frozen=True, slots=True)
class ReceiverEpoch:
    """What a GNSS receiver reports for one navigation epoch, in SI units.

    ``gps_time_ns`` is the time of validity as GPS time (ns since 1980-01-06T00:00:00, no leap
    seconds); the protocol derives UTC, GPS week and time of week from it. Course and speed over
    ground are derived from ``vel_ned_mps``, not stored, so they cannot disagree with it.
    """

    gps_time_ns: int
    lat_deg: float
    lon_deg: float
    alt_m: float  # WGS84 ellipsoidal height
    vel_ned_mps: Vec3
    pos_sigma_ned_m: Vec3  # 1 sigma per axis
    vel_sigma_mps: Vec3  # 1 sigma per axis
    fix_type: int  # 0 none, 2 2-D, 3 3-D
    num_sats: int
    hdop: float
    pdop: float
    vdop: float
    time_sigma_ns: float = 20.0  # receiver time accuracy (UBX tAcc); a typical u-blox F9 figure

    def __post_init__(self) -> None:
        if self.fix_type not in FIX_TYPES:
            raise ValueError(f"fix_type {self.fix_type} is none of {FIX_TYPES} (0 none, 2 2-D, 3 3-D)")

    @property
    def ground_speed_mps(self) -> float:
        return math.hypot(self.vel_ned_mps[0], self.vel_ned_mps[1])

    @property
    def course_deg(self) -> float:
        """Course over ground, degrees clockwise from true north in [0, 360); 0 when standing still."""
        course = math.degrees(math.atan2(self.vel_ned_mps[1], self.vel_ned_mps[0])) % 360.0
        return 0.0 if course >= 360.0 else course  # -0.0 % 360 and -1e-17 % 360 give 360.0


@dataclass(frozen=True, slots=True)
class DecodedFix:
    """One epoch as a decoder rebuilt it from the bytes; ``None`` where the protocol carries no value.

    ``rx_ns`` is the ``rx_ns`` of the chunk that completed the epoch. ``messages`` lists the message
    types that made it, in arrival order. ``gps_time_ns`` is ``None`` when the stream did not give
    a full date (e.g. NMEA without RMC/ZDA); ``utc_time_of_day_ns`` is then still known.
    ``first_byte_at`` is where its epoch's first message began among the bytes the decoder was fed
    (-1: a decoder that does not say); ``line_bytes`` (set by ``hil.wire.line.LineDecoder``) how
    many bytes the line carried from there to the end of that chunk: at the line's rate, how long
    before ``rx_ns`` the epoch's output began -- what a receiver's latency is measured to.
    """

    protocol: str
    messages: tuple[str, ...]
    rx_ns: int
    gps_time_ns: int | None
    utc_time_of_day_ns: int | None
    lat_deg: float | None
    lon_deg: float | None
    alt_m: float | None  # WGS84 ellipsoidal height
    vel_ned_mps: OptVec3
    pos_sigma_ned_m: OptVec3
    vel_sigma_mps: OptVec3
    fix_type: int | None
    num_sats: int | None
    hdop: float | None
    pdop: float | None
    vdop: float | None
    first_byte_at: int = -1  # -1: not known
    line_bytes: int = 0


class WireDecoder(Protocol):
    """A streaming decoder: bytes in any split, fixes out, bad input counted and never raised."""

    counters: dict[str, int]
    last_problem: str

    def feed(self, data: bytes, rx_ns: int) -> list[DecodedFix]: ...

    def flush(self) -> list[DecodedFix]:
        """Close the open epoch (end of stream) and return its fix, if it has a position."""
        ...


class WireProtocol(Protocol):
    """A receiver's output protocol: ``cls(messages=None, talker="GN")`` configures it."""

    name: ClassVar[str]
    DEFAULT_MESSAGES: ClassVar[tuple[str, ...]]
    SUPPORTED_MESSAGES: ClassVar[tuple[str, ...]]  # in the order a receiver sends them in an epoch
    START: ClassVar[bytes]  # the bytes every message begins with (a line may carry several protocols)
    messages: tuple[str, ...]

    @staticmethod
    def message_length(buf: bytes | bytearray) -> int:
        """Bytes of the message at the start of ``buf``; 0: not all there yet; -1: not a message."""
        ...

    def __init__(self, messages: tuple[str, ...] | None = None, talker: str = "GN") -> None: ...

    def encode_epoch(self, epoch: ReceiverEpoch) -> bytes: ...

    def encode_pps_announcement(self, next_pps_gps_ns: int, q_err_ps: int = 0) -> bytes: ...

    def decoder(self) -> WireDecoder: ...

    # optional: ``printed_time_ns(gps_ns)``, a time of validity as the protocol states it (its
    # time field's resolution); without it, to the ns


def select_messages(
    requested: tuple[str, ...] | None, default: tuple[str, ...], supported: tuple[str, ...], what: str
) -> tuple[str, ...]:
    """The configured message set in the receiver's send order; a ValueError names unsupported ones."""
    if requested is None:
        return default
    unknown = [m for m in requested if m not in supported]
    if unknown or not requested:
        raise ValueError(
            f"{what}: unsupported message(s) {unknown or '(none given)'}; supported: {supported}"
        )
    return tuple(m for m in supported if m in requested)


class StreamDecoder:
    """What every streaming decoder shares: a byte buffer fed in chunks of arbitrary size, counters,
    the last problem, and an open epoch closed at end of stream. A subclass scans for its frames
    (``_scan``) and closes epochs (``_close``); ``feed`` never raises."""

    GARBAGE: ClassVar[str] = "outside any frame"

    def __init__(self) -> None:
        self.counters: dict[str, int] = dict.fromkeys(COUNTER_NAMES, 0)
        self.last_problem = ""
        self._buf = bytearray()
        self._rx_ns = 0
        self._at = 0  # bytes fed before ``_buf[0]``
        self._msg_at = 0  # where the message being read began (set by ``_scan``)

    def problem(self, counter: str, what: str, amount: int = 1) -> None:
        self.counters[counter] += amount
        self.last_problem = what

    def feed(self, data: bytes, rx_ns: int) -> list[DecodedFix]:
        """Consume a chunk received at ``rx_ns``; return the epochs it completed. Never raises."""
        self.counters["bytes"] += len(data)
        self._rx_ns = rx_ns
        self._buf += data
        out: list[DecodedFix] = []
        used = self._scan(self._buf, out)
        del self._buf[:used]
        self._at += used
        return out

    def flush(self) -> list[DecodedFix]:
        """End of stream: close the open epoch."""
        out: list[DecodedFix] = []
        self._close(out)
        return out

    def _garbage(self, n: int) -> None:
        if n > 0:
            self.problem("garbage_bytes", f"{n} byte(s) {self.GARBAGE}", n)

    def _scan(self, buf: bytearray, out: list[DecodedFix]) -> int:
        """Decode every complete frame in ``buf`` into ``out``; return how many bytes are used up."""
        raise NotImplementedError

    def _close(self, out: list[DecodedFix]) -> None:
        raise NotImplementedError

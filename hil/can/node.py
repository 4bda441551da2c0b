"""Frames onto a CAN bus the way a device's controller sends them: robust to a full or failing bus.

A real IMU never stops because its CAN controller is busy: it retries briefly, then drops the
frame and flags it. ``CanTransmitter`` (what the live runner sends a node's frames through)
does the same: a ``can.CanOperationError`` (SocketCAN's
``ENOBUFS`` "transmit buffer full", a bus-off, a closed Zenoh session) is retried with a short
exponential back-off and, failing that, counted and dropped; the caller gets ``False`` and keeps
its cadence. The receiver then sees an incomplete sample or a counter jump, both counted there.

It also meters the bus load it causes (time the frames occupy the wire, worst-case
stuffing, over the last second) against the configured bit rates: 1 Mbit/s classic; FD 1 Mbit/s
arbitration / 5 Mbit/s data.
"""

from __future__ import annotations

import errno
import logging
import time
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any

import can

from hil.bus.pubsub import Stats
from hil.can.busload import FD_DATA_BITRATE, NOMINAL_BITRATE, frame_bits
from hil.can.codec import EncodeError, ImuCanCodec

log = logging.getLogger(__name__)

_COUNTERS = (
    "tx_frames",
    "tx_samples",
    "tx_syncs",
    "tx_retries",
    "tx_buffer_full",
    "tx_bus_error",
    "tx_dropped_frames",
    "tx_dropped_samples",
)


def _what(frames: Sequence[can.Message]) -> str:
    """What a failed transport write carried, for its error text (built only on a failure)."""
    more = f" (+{len(frames) - 1} frames)" if len(frames) > 1 else ""
    return f"send 0x{frames[0].arbitration_id:X}{more}"


class CanTransmitter:
    """Send frames onto ``bus``; what the live runner does with a node's CAN output.

    ``stats`` (the service's) receives ``can.tx.*`` counters and the last error text.
    ``retries``/``backoff_s``: attempts after the first failure, first back-off (doubling).
    ``now``: a monotonic clock in seconds (injected so tests need no wall clock).
    """

    def __init__(
        self,
        bus: can.BusABC,
        stats: Stats | None = None,
        *,
        retries: int = 3,
        backoff_s: float = 0.0005,
        send_timeout_s: float = 0.005,
        nominal_bitrate: float = NOMINAL_BITRATE,
        data_bitrate: float = FD_DATA_BITRATE,
        now: Callable[[], float] = time.monotonic,
        sleep: Callable[[float], None] = time.sleep,
    ) -> None:
        self.bus = bus
        self.stats = stats
        self.retries = retries
        self.backoff_s = backoff_s
        self.send_timeout_s = send_timeout_s
        self.nominal_bitrate = nominal_bitrate
        self.data_bitrate = data_bitrate
        self._now = now
        self._sleep = sleep
        self._counts: dict[str, int] = dict.fromkeys(_COUNTERS, 0)
        self._busy: deque[tuple[float, float]] = deque()
        self._busy_sum = 0.0
        self._busy_cache: dict[tuple[int, bool, bool], float] = {}

    def send_frames(self, frames: Sequence[can.Message], *, sync: bool = False) -> bool:
        """Send one sample's frames (or a sync frame); False (and counted) if a frame was dropped."""
        ok = True
        for frame in frames:
            ok = self._send(frame) and ok
        if ok:
            self._counts["tx_syncs" if sync else "tx_samples"] += 1
        elif not sync:
            self._count("tx_dropped_samples")
        return ok

    def send_frame(self, frame: can.Message, stamp_epoch_ns: int | None = None) -> bool:
        """Send one frame (the live runner's pacing sends a burst frame by frame, each at its wire
        time); ``stamp_epoch_ns``: that wire time, carried as the frame's receive stamp by a bus
        that can (``hilzenoh``; a kernel stamps SocketCAN frames itself). Pair with
        ``count_burst``."""
        return self._send(frame, stamp_epoch_ns)

    def send_burst(self, frames: Sequence[can.Message], stamps_epoch_ns: Sequence[int]) -> bool:
        """One sample's frames, each with its wire time (``send_frame``'s stamp): as one transport
        message where the bus can (``hilzenoh``'s ``send_burst_stamped``: one put, one routing,
        one callback in each reader for the sample), else frame by frame. Pair with
        ``count_burst``."""
        burst = getattr(self.bus, "send_burst_stamped", None)
        if burst is None:
            ok = True
            for frame, stamp in zip(frames, stamps_epoch_ns, strict=True):
                ok = self._send(frame, stamp) and ok
            return ok
        if not frames:
            return True
        return self._attempt(lambda: burst(frames, stamps_epoch_ns, timeout=self.send_timeout_s), frames)

    @property
    def carries_stamps(self) -> bool:
        """True if the bus carries the wire time ``send_frame`` is given (``hilzenoh``); a
        SocketCAN kernel stamps a frame itself, when it is sent."""
        return callable(getattr(self.bus, "send_stamped", None))

    def count_burst(self, ok: bool, sync: bool) -> None:
        """Count a burst sent with ``send_frame`` as ``send_frames`` counts one."""
        if ok:
            self._counts["tx_syncs" if sync else "tx_samples"] += 1
        elif not sync:
            self._count("tx_dropped_samples")

    def bus_load(self) -> float:
        """Fraction of the last second the bus was occupied by this node's frames (0..1+)."""
        self._trim(self._now())
        return self._busy_sum

    def counters(self) -> dict[str, int]:
        """Counters for the service status (``bus_load_permille`` included)."""
        out = dict(self._counts)
        out["bus_load_permille"] = round(self.bus_load() * 1000)
        return out

    # -- internals -----------------------------------------------------------------------
    def _count(self, name: str, message: str | None = None) -> None:
        self._counts[name] += 1
        if self.stats is not None:
            if message:
                self.stats.error(f"can.{name.replace('_', '.', 1)}", message)
            else:
                self.stats.inc(f"can.{name.replace('_', '.', 1)}")

    def _send(self, frame: can.Message, stamp_epoch_ns: int | None = None) -> bool:
        stamped = getattr(self.bus, "send_stamped", None) if stamp_epoch_ns is not None else None
        if stamped is not None:
            return self._attempt(lambda: stamped(frame, stamp_epoch_ns, timeout=self.send_timeout_s), [frame])
        return self._attempt(lambda: self.bus.send(frame, timeout=self.send_timeout_s), [frame])

    def _attempt(self, call: Callable[[], Any], frames: Sequence[can.Message]) -> bool:
        """``call`` (one transport write of ``frames``) under the retry policy: a failure is retried
        with a doubling back-off, then its frames are counted dropped."""
        delay = self.backoff_s
        for attempt in range(self.retries + 1):
            try:
                call()
            except can.CanOperationError as err:
                full = err.error_code == errno.ENOBUFS or "buffer" in str(err).lower()
                self._count("tx_buffer_full" if full else "tx_bus_error", f"{_what(frames)}: {err}")
                if attempt < self.retries:
                    self._counts["tx_retries"] += 1
                    self._sleep(delay)
                    delay *= 2
                continue
            except can.CanError as err:  # any other python-can failure: same policy
                self._count("tx_bus_error", f"{_what(frames)}: {err}")
                if attempt < self.retries:
                    self._counts["tx_retries"] += 1
                    self._sleep(delay)
                    delay *= 2
                continue
            self._counts["tx_frames"] += len(frames)
            self._account(frames)
            return True
        for _ in frames:
            self._count("tx_dropped_frames")
        return False

    def _account(self, frames: Sequence[can.Message]) -> None:
        """The wire time of frames sent together, as one entry of the last second's load."""
        busy = 0.0
        cache = self._busy_cache
        for frame in frames:
            key = (len(frame.data), bool(frame.is_fd), bool(frame.bitrate_switch))
            one = cache.get(key)
            if one is None:
                bits = frame_bits(key[0], fd=key[1], brs=key[2], extended=False)
                one = cache[key] = bits.seconds(self.nominal_bitrate, self.data_bitrate)
            busy += one
        now = self._now()
        self._busy.append((now, busy))
        self._busy_sum += busy
        self._trim(now)

    def _trim(self, now: float) -> None:
        horizon = now - 1.0
        q = self._busy
        while q and q[0][0] < horizon:
            self._busy_sum -= q.popleft()[1]
        if not q:
            self._busy_sum = 0.0


class ImuCanNode(CanTransmitter):
    """IMU samples encoded with ``codec`` and sent: a sender for tests, benches and tools (the
    rig's own emulator is ``hil.nodes.imu_emulator``, whose frames the live runner sends through
    a ``CanTransmitter``)."""

    def __init__(self, bus: can.BusABC, codec: ImuCanCodec, stats: Stats | None = None, **kw: Any) -> None:
        super().__init__(bus, stats, **kw)
        self.codec = codec
        self._counts.update(tx_encode_errors=0, tx_saturated_samples=0)

    def send_sample(
        self,
        device_stamp_ns: int,
        dtheta_b_rad: Sequence[float],
        dvel_b_mps: Sequence[float],
        status: int = 0,
    ) -> bool:
        """Encode and send one sample; False if it could not be encoded or a frame was dropped."""
        try:
            frames = self.codec.encode_sample(
                device_stamp_ns=device_stamp_ns,
                dtheta_b_rad=dtheta_b_rad,
                dvel_b_mps=dvel_b_mps,
                status=status,
            )
        except (EncodeError, TypeError, ValueError) as err:
            self._count("tx_encode_errors", f"sample not encodable: {err}")
            return False
        self._counts["tx_saturated_samples"] = self.codec.saturated_samples
        return self.send_frames(frames)

    def send_sync(self, device_stamp_ns: int) -> bool:
        """Send the time-tag frame of a sync edge at ``device_stamp_ns`` (device clock)."""
        try:
            frame = self.codec.encode_sync(device_stamp_ns)
        except (EncodeError, TypeError, ValueError) as err:
            self._count("tx_encode_errors", f"sync not encodable: {err}")
            return False
        return self.send_frames([frame], sync=True)

"""Bounded inboxes: what a service holds between Zenoh's callback threads and its one worker.

A Zenoh callback only enqueues; one thread consumes. Unbounded, that queue is a memory leak
under a flood (55,000 forged ``GnssFix`` in 8 s once grew the fusion's inbox to 57,351 and
stopped its output) and a starvation: the IMU sample that paces the fusion waited behind every
piece of GNSS junk that arrived before it.

So every input waits in a *lane* of its own kind and publisher, with a cap per kind, and the
policy is the same everywhere (``NodeService``, the recorder, the CAN bus, time sync):

- a full lane drops its **oldest** message to take the new one, and counts it
  (``inbox.dropped.<kind>`` in the service's status): the freshest data is the useful data, and
  one kind flooding never evicts another kind's messages;
- lanes are per **publisher** too (the Zenoh source id, ``hil.bus.pubsub.source_id``): a stranger
  flooding ``synced/gnss`` fills the stranger's lane, not the rig's timesync's. Past
  ``MAX_PUBLISHER_LANES`` publishers of one kind the rest share one lane, so the number of lanes
  (and the memory) stays bounded whatever a flood does;
- the worker takes messages in **arrival order** across lanes. A flooded lane holds only its
  newest ``cap`` messages, so the oldest message in it is at most ``cap / flood rate`` old: any
  other lane's message that is older is served first. The IMU's samples therefore wait behind at
  most one GNSS lane's worth of junk, whatever the flood's rate;
- the caps (``lane_cap``) come from the sensor table: a sensor that paces the fusion (the IMU)
  gets ``PACER_CAP`` (20,000: 50 s at 400 Hz, 4 s of a 5 kHz soak), every other sensor
  ``AIDING_CAP`` (500: 50 s of 10 Hz GNSS), anything else ``OTHER_CAP``.

Nothing is dropped while the worker keeps up: offline (``hil sim``) nothing queues at all, so
``hil sim`` and the golden replay are untouched. What a lane drops is kept (up to
``MAX_DROPPED_KEPT``) for the worker to hand to the node (``Node.on_dropped``), so the fusion
journals every input it never saw and ``hil rerun`` leaves out the same ones.
"""

from __future__ import annotations

import heapq
import threading
from collections import deque
from collections.abc import Callable
from typing import Generic, TypeVar

from hil.sensor_table import SENSORS

T = TypeVar("T")

PACER_CAP = 20_000
AIDING_CAP = 500
OTHER_CAP = 1_000
MAX_PUBLISHER_LANES = 8  # per kind; more publishers share one lane
MAX_DROPPED_KEPT = 100_000  # drops kept for the worker; beyond, only counted
SHARED = "*"  # the publisher of the shared lane


def lane_cap(kind: str) -> int:
    """The cap of a lane of ``kind`` (``synced/imu``, ``sensor/gnss``, ``control/fault``, ...)."""
    sensor = kind.partition("/")[2].partition("/")[0]
    spec = SENSORS.get(sensor)
    if spec is None:
        return OTHER_CAP
    return PACER_CAP if spec.paces_fusion else AIDING_CAP


def key_kind(key: str) -> str:
    """The kind of a key relative to ``hil/<rig>/``: its first two segments (``synced/gnss``)."""
    parts = key.split("/", 2)
    return "/".join(parts[:2])


class BoundedInbox(Generic[T]):
    """Lanes per (kind, publisher), each capped, drop-oldest, served in arrival order.

    Thread-safe: any number of producers (Zenoh callbacks), one consumer.
    """

    def __init__(
        self,
        cap_of: Callable[[str, str], int] = lambda kind, _publisher: lane_cap(kind),
        *,
        max_publisher_lanes: int = MAX_PUBLISHER_LANES,
        max_total: int = 0,
        keep_dropped: bool = False,
        on_drop: Callable[[str, str, T], None] | None = None,
    ) -> None:
        """``cap_of(kind, publisher)``: a lane's cap; ``max_total`` (0: none) bounds all lanes
        together (the longest lane gives up its oldest); ``on_drop(kind, publisher, item)`` is
        told of each drop (under the inbox's lock: count, do not block)."""
        self._cap_of = cap_of
        self._caps: dict[tuple[str, str], int] = {}
        self._max_pub = max_publisher_lanes
        self._max_total = max_total
        self._keep = keep_dropped
        self._on_drop = on_drop
        self._cond = threading.Condition(threading.Lock())
        self._lanes: dict[tuple[str, str], deque[tuple[int, T]]] = {}
        self._publishers: dict[str, int] = {}  # kind -> publishers with a lane of their own
        self._arrivals = 0
        self._size = 0
        self.peak = 0
        self.dropped: dict[str, int] = {}  # kind -> messages dropped
        self.dropped_unkept = 0
        self._dropped_items: list[T] = []

    def _lane(self, kind: str, publisher: str) -> tuple[deque[tuple[int, T]], int]:
        lane = self._lanes.get((kind, publisher))
        if lane is None:
            n = self._publishers.get(kind, 0)
            if n >= self._max_pub:
                publisher = SHARED
                lane = self._lanes.get((kind, SHARED))
            else:
                self._publishers[kind] = n + 1
            if lane is None:
                lane = self._lanes[(kind, publisher)] = deque()
        cap = self._caps.get((kind, publisher))
        if cap is None:
            cap = self._caps[(kind, publisher)] = max(1, int(self._cap_of(kind, publisher)))
        return lane, cap

    def put(self, kind: str, publisher: str, item: T) -> None:
        """Enqueue ``item``; a full lane first drops its oldest (counted, kept for the worker)."""
        with self._cond:
            lane, cap = self._lane(kind, publisher)
            if len(lane) >= cap:
                self._drop(kind, publisher, lane)
            elif self._max_total and self._size >= self._max_total:
                (k, pub), longest = max(self._lanes.items(), key=lambda kv: len(kv[1]))
                self._drop(k, pub, longest)
            lane.append((self._arrivals, item))
            self._arrivals += 1
            self._size += 1
            if self._size > self.peak:
                self.peak = self._size
            self._cond.notify()

    def _drop(self, kind: str, publisher: str, lane: deque[tuple[int, T]]) -> None:
        _, old = lane.popleft()
        self._size -= 1
        self.dropped[kind] = self.dropped.get(kind, 0) + 1
        if self._on_drop is not None:
            self._on_drop(kind, publisher, old)
        if self._keep:
            if len(self._dropped_items) < MAX_DROPPED_KEPT:
                self._dropped_items.append(old)
            else:
                self.dropped_unkept += 1

    def get(self, timeout: float | None = None) -> T | None:
        """The oldest message of any lane, waiting up to ``timeout`` s (0: not at all); None if
        there was none."""
        with self._cond:
            if not self._size and timeout != 0:
                self._cond.wait(timeout)
            if not self._size:
                return None
            best: deque[tuple[int, T]] | None = None
            for lane in self._lanes.values():
                if lane and (best is None or lane[0][0] < best[0][0]):
                    best = lane
            assert best is not None
            self._size -= 1
            return best.popleft()[1]

    def get_many(self, max_n: int, timeout: float | None = None) -> list[T]:
        """Up to ``max_n`` messages, oldest first across lanes (what ``get`` would give one by
        one), waiting up to ``timeout`` s for the first. One lock and one wake-up for a batch: a
        consumer that need not answer each message at once (the recorder) pays them per batch."""
        with self._cond:
            if not self._size and timeout != 0:
                self._cond.wait(timeout)
            n = min(max_n, self._size)
            if n <= 0:
                return []
            heads = [lane for lane in self._lanes.values() if lane]
            out: list[T] = []
            if len(heads) == 1:
                lane = heads[0]
                out = [lane.popleft()[1] for _ in range(n)]
            else:
                # merge the lanes' heads by arrival number (each lane is in arrival order)
                heap = [(lane[0][0], i) for i, lane in enumerate(heads)]
                heapq.heapify(heap)
                while len(out) < n:
                    _, i = heap[0]
                    lane = heads[i]
                    out.append(lane.popleft()[1])
                    if lane:
                        heapq.heapreplace(heap, (lane[0][0], i))
                    else:
                        heapq.heappop(heap)
            self._size -= n
            return out

    def take_dropped(self) -> list[T]:
        """The messages dropped since the last call (only with ``keep_dropped``)."""
        if not self._dropped_items:
            return []
        with self._cond:
            out, self._dropped_items = self._dropped_items, []
        return out

    def qsize(self) -> int:
        return self._size

    def counters(self, prefix: str = "inbox") -> dict[str, int]:
        """Depth, peak and drops per kind, as a status shows them."""
        with self._cond:
            out = {prefix: self._size, f"{prefix}.peak": self.peak, f"{prefix}.lanes": len(self._lanes)}
            for kind, n in self.dropped.items():
                out[f"{prefix}.dropped.{kind.replace('/', '.')}"] = n
            if self.dropped_unkept:
                out[f"{prefix}.dropped_unjournaled"] = self.dropped_unkept
        return out

"""Typed publish/subscribe over Zenoh with the rig's accounting built in.

A payload that does not decode is counted (``rejected.<key-kind>.<reason>``) and remembered as
the service's last error; it is never raised into Zenoh's thread. Sensor streams are declared
reliable with blocking congestion control, so a slow consumer shows as back-pressure on the
producer instead of silently lost samples.

Publishers are Zenoh *advanced* publishers with sample-miss detection (``declare_publisher``):
each sample carries the publisher's id and a sequence number, a sporadic heartbeat carries the
last one, and a small cache lets an advanced subscriber (the recorder) recover what it missed,
so Zenoh itself can say what never arrived -- a lost last sample included. It also keeps the
recorder's advanced subscriber from dropping samples: without a sequence number, a sample
routed through a router carries only the router's timestamp, and zenoh-ext's advanced subscriber
delivers timestamped samples of one timestamp source in increasing order only, silently dropping
any that two router links interleave (zenoh-ext ``advanced_subscriber.rs``, ``handle_sample``;
measured with ``tools/zenoh_router_burst.py``: 70 of 270,000 samples of plain publishers lost,
none of advanced ones, 3 runs; ``docs/recording.md``). ``HIL_ZENOH_MISS_DETECTION=0`` declares
plain publishers instead.
"""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable
from typing import Any, Generic, TypeVar

import msgspec
import zenoh
import zenoh.ext as zext

from hil.bus.describe import encoding_of
from hil.messages import MAX_BATCH, Message, decode, encode, encode_batch, generation_seq, split_batch

M = TypeVar("M", bound=Message)

MAX_PAYLOAD_BYTES = 64 * 1024  # no contract message comes near this; larger is an attack or a bug

MISS_DETECTION_ENV = "HIL_ZENOH_MISS_DETECTION"
MISS_CACHE_SAMPLES = 256  # per publisher: 0.64 s of the 400 Hz IMU stream, ~64 kB
MISS_HEARTBEAT_S = 1.0  # sporadic: sent only when the last seq changed since the previous one


def miss_detection_enabled() -> bool:
    """Whether publishers get sample-miss detection (``HIL_ZENOH_MISS_DETECTION``, default on)."""
    return os.environ.get(MISS_DETECTION_ENV, "1").strip().lower() not in ("0", "false", "no", "off")


def declare_publisher(
    session: zenoh.Session,
    key: str,
    *,
    reliable: bool = True,
    block: bool = True,
    express: bool = False,
    miss_detection: bool | None = None,
    encoding: zenoh.Encoding | None = None,
) -> zenoh.Publisher | zext.AdvancedPublisher:
    """A Zenoh publisher for rig traffic: advanced, with miss detection, unless turned off.

    ``miss_detection`` None follows ``HIL_ZENOH_MISS_DETECTION``. The extra work per put is a
    sequence number and a reference kept in the cache (``hil bench record`` measures the
    recorder and ``--afap`` replay with it on). ``encoding``: the samples' Zenoh encoding,
    ``hil.bus.describe.encoding_of(Type)`` for a contract type (``Publisher`` sets it).
    """
    reliability = zenoh.Reliability.RELIABLE if reliable else zenoh.Reliability.BEST_EFFORT
    congestion = zenoh.CongestionControl.BLOCK if block else zenoh.CongestionControl.DROP
    if not (miss_detection_enabled() if miss_detection is None else miss_detection):
        return session.declare_publisher(
            key, reliability=reliability, congestion_control=congestion, express=express, encoding=encoding
        )
    return zext.declare_advanced_publisher(
        session,
        key,
        encoding=encoding,
        reliability=reliability,
        congestion_control=congestion,
        express=express,
        cache=zext.CacheConfig(MISS_CACHE_SAMPLES),
        sample_miss_detection=zext.MissDetectionConfig(heartbeat=None, sporadic_heartbeat=MISS_HEARTBEAT_S),
    )


class Stats:
    """Thread-safe counters and rate meters that a service publishes in its status."""

    def __init__(self) -> None:
        self._lock = threading.Lock()
        self.counters: dict[str, int] = {}
        self._rate_counts: dict[str, int] = {}
        self._rate_prev: dict[str, int] = {}
        self._rate_t = time.monotonic()
        self.rates_hz: dict[str, float] = {}
        self.last_error = ""

    def inc(self, name: str, n: int = 1) -> None:
        with self._lock:
            self.counters[name] = self.counters.get(name, 0) + n

    def count_rate(self, name: str, n: int = 1) -> None:
        with self._lock:
            self._rate_counts[name] = self._rate_counts.get(name, 0) + n

    def error(self, counter: str, message: str) -> None:
        with self._lock:
            self.counters[counter] = self.counters.get(counter, 0) + 1
            self.last_error = message[:500]

    def note(self, message: str) -> None:
        """A last error counted elsewhere (a node's own counters)."""
        with self._lock:
            self.last_error = message[:500]

    def snapshot(self) -> tuple[dict[str, float], dict[str, int], str]:
        """Rates over the interval since the previous snapshot, counters, last error."""
        with self._lock:
            now = time.monotonic()
            span = max(now - self._rate_t, 1e-6)
            self.rates_hz = {
                k: round((v - self._rate_prev.get(k, 0)) / span, 2) for k, v in self._rate_counts.items()
            }
            self._rate_prev = dict(self._rate_counts)
            self._rate_t = now
            return dict(self.rates_hz), dict(self.counters), self.last_error


def source_id(sample: zenoh.Sample) -> str:
    """The publisher of a sample as Zenoh names it, ``"<zid>:<eid>"`` (its ``source_info``), or
    ``""`` when the sample carries none (a plain publisher: the rig's advanced publishers always
    do, ``declare_publisher``). Honest only as far as the bus is closed: a process that can
    publish can also copy another's source info."""
    info = sample.source_info
    if info is None:
        return ""
    sid = info.source_id
    return f"{sid.zid}:{sid.eid}"


def _kind(key: str) -> str:
    """``hil/rig/sensor/imu`` -> ``sensor.imu``: short names for counters."""
    parts = key.split("/")
    return ".".join(parts[2:]) if len(parts) > 2 else key


class Publisher(Generic[M]):
    """Publishes one contract type on one key and owns that key's per-publisher ``seq``; the
    samples' Zenoh encoding names the type (``application/json;hil.<Type>``, ``hil.bus.describe``).

    ``generation``: the process's restart generation (``hil.runtime.service.restart_generation``);
    ``next_seq`` counts within it (``hil.messages.generation_seq``), so a restarted service's
    counters continue above everything it published before instead of repeating 0, 1, 2, ...
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        cls: type[M],
        stats: Stats | None = None,
        *,
        reliable: bool = True,
        block: bool = True,
        express: bool = False,
        miss_detection: bool | None = None,
        generation: int = 0,
    ) -> None:
        self.key = key
        self.cls = cls
        self.stats = stats
        self.generation = generation
        self._seq = 0
        self._pub = declare_publisher(
            session,
            key,
            reliable=reliable,
            block=block,
            express=express,
            miss_detection=miss_detection,
            encoding=encoding_of(cls),
        )
        self._rate_name = "out." + _kind(key)
        self._plain = isinstance(self._pub, zenoh.Publisher)
        self._sn = 0

    def next_seq(self) -> int:
        seq = generation_seq(self.generation, self._seq)
        self._seq += 1
        return seq

    def put(self, msg: M) -> None:
        self.put_bytes(encode(msg))

    def put_many(self, msgs: list[M]) -> None:
        """Messages of this key that are ready together as one Zenoh sample (a JSON array of
        them, ``hil.messages.encode_batch``): one put, one routing, one wake-up of each
        subscriber instead of one per message. Subscribers that take batches split them
        (``hil.messages.split_batch``); each message keeps its own ``seq``."""
        if not msgs:
            return
        if len(msgs) == 1:
            self.put(msgs[0])
            return
        for i in range(0, len(msgs), MAX_BATCH):
            part = msgs[i : i + MAX_BATCH]
            self.put_bytes(encode_batch(part), len(part))

    def put_bytes(self, payload: bytes, n: int = 1) -> None:
        if self._plain:  # an advanced publisher names itself; a plain one is told to
            self._pub.put(payload, source_info=zenoh.SourceInfo(self._pub.id, self._sn))
            self._sn += 1
        else:
            self._pub.put(payload)
        if self.stats is not None:
            self.stats.count_rate(self._rate_name, n)

    def undeclare(self) -> None:
        self._pub.undeclare()


class Subscriber(Generic[M]):
    """Decodes one contract type; bad payloads are counted, handler errors are contained."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        cls: type[M],
        handler: Callable[[M, str], None],
        stats: Stats,
    ) -> None:
        self.cls = cls
        self.handler = handler
        self.stats = stats
        self._sub = session.declare_subscriber(key, self._on_sample)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        deliver_sample(sample, self.cls, self.handler, self.stats)

    def undeclare(self) -> None:
        self._sub.undeclare()


def deliver_sample(
    sample: zenoh.Sample, cls: type[M], handler: Callable[[M, str], None], stats: Stats
) -> None:
    """What a ``Subscriber`` does with a sample, for one taken from a Zenoh channel: each of its
    messages decoded as a ``cls`` and handed on; what fails is counted, never raised."""
    key = str(sample.key_expr)
    for raw in _payloads(sample, key, stats):
        _deliver(cls, handler, key, raw, stats)


class DispatchSubscriber:
    """One subscription, several contract types told apart by the key's kind (``hil/<rig>/<kind>/...``).

    One Zenoh subscriber means one callback thread: the samples of different keys from the same
    publisher session are handled in the order they were published -- the order the recorder
    sees -- which separate subscribers (one thread each) do not guarantee. Kinds not listed are
    ignored without decoding.

    ``remote_only``: samples published by this session itself are not delivered (Zenoh's
    ``Locality.REMOTE``). A service's inputs come from other processes; ``timesync``'s ``*/imu``
    also matches the ``synced/imu`` it publishes, and each of those echoes cost a wake-up of the
    callback thread only to be ignored.
    """

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        routes: dict[str, tuple[type[Message], Callable[[Any, str], None]]],
        stats: Stats,
        *,
        remote_only: bool = False,
    ) -> None:
        self.routes = routes
        self.stats = stats
        origin = zenoh.Locality.REMOTE if remote_only else zenoh.Locality.ANY
        self._sub = session.declare_subscriber(key, self._on_sample, allowed_origin=origin)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        parts = key.split("/")
        route = self.routes.get(parts[2]) if len(parts) > 2 else None
        if route is None:
            return
        cls, handler = route
        for raw in _payloads(sample, key, self.stats):
            _deliver(cls, handler, key, raw, self.stats)

    def undeclare(self) -> None:
        self._sub.undeclare()


def _payloads(sample: zenoh.Sample, key: str, stats: Stats) -> list[bytes]:
    """A sample's message payloads: one, or a batch's (``Publisher.put_many``); none, counted
    (``rejected.<kind>.<why>``), when the sample is too big or not a batch it claims to be."""
    kind = _kind(key)
    try:
        raw = sample.payload.to_bytes()
        if len(raw) > MAX_PAYLOAD_BYTES:
            stats.error(f"rejected.{kind}.oversized", f"{key}: payload of {len(raw)} B")
            return []
        return split_batch(raw)
    except ValueError as err:
        stats.error(f"rejected.{kind}.invalid", f"{key}: {err}")
    except Exception as err:  # never let a bad sample kill Zenoh's callback thread
        stats.error(f"rejected.{kind}.error", f"{key}: {type(err).__name__}: {err}")
    return []


def _deliver(cls: type[M], handler: Callable[[M, str], None], key: str, raw: bytes, stats: Stats) -> None:
    """One payload decoded as a ``cls`` and handed on; what fails is counted, never raised."""
    msg = decode_checked(cls, key, raw, stats)
    if msg is None:
        return
    try:
        handler(msg, key)
    except Exception as err:
        stats.error(f"errors.{_kind(key)}.handler", f"{key}: {type(err).__name__}: {err}")


def decode_checked(cls: type[M], key: str, raw: bytes, stats: Stats) -> M | None:
    """``raw`` as a ``cls``, or None with the reason counted (``rejected.<kind>.<why>``) and kept as
    the last error: what every subscriber does with a payload, wherever it decodes it."""
    kind = _kind(key)
    try:
        if len(raw) > MAX_PAYLOAD_BYTES:
            stats.error(f"rejected.{kind}.oversized", f"{key}: payload of {len(raw)} B")
            return None
        msg = decode(cls, raw)
    except (msgspec.ValidationError, msgspec.DecodeError) as err:
        stats.error(f"rejected.{kind}.invalid", f"{key}: not a valid {cls.__name__}: {err}")
        return None
    except Exception as err:
        stats.error(f"rejected.{kind}.error", f"{key}: {type(err).__name__}: {err}")
        return None
    stats.count_rate("in." + kind)
    return msg


class RawSubscriber:
    """One subscription that only hands on the undecoded payload of the kinds it routes, with its
    key and publisher (``source_id``): ``handler(key, raw, source, cls)``. For a bounded inbox
    (``hil.bus.inbox``): what a full lane drops is then never decoded, so a flood costs Zenoh's
    thread a copy of the bytes, not a parse; the consumer decodes what it keeps
    (``decode_checked``). One callback thread, so one publisher's samples keep their order."""

    def __init__(
        self,
        session: zenoh.Session,
        key: str,
        routes: dict[str, type[Message]],
        handler: Callable[[str, bytes, str, type[Message]], None],
        stats: Stats,
        *,
        remote_only: bool = False,
    ) -> None:
        self.routes = routes
        self.handler = handler
        self.stats = stats
        origin = zenoh.Locality.REMOTE if remote_only else zenoh.Locality.ANY  # as DispatchSubscriber
        self._sub = session.declare_subscriber(key, self._on_sample, allowed_origin=origin)

    def _on_sample(self, sample: zenoh.Sample) -> None:
        key = str(sample.key_expr)
        parts = key.split("/", 3)
        cls = self.routes.get(parts[2]) if len(parts) > 2 else None
        if cls is None:
            return
        try:
            source = source_id(sample)
            for raw in _payloads(sample, key, self.stats):  # a batch's messages one by one
                self.handler(key, raw, source, cls)
        except Exception as err:  # never into Zenoh's thread
            self.stats.error(f"errors.{_kind(key)}.enqueue", f"{key}: {type(err).__name__}: {err}")

    def undeclare(self) -> None:
        self._sub.undeclare()


def subscribe_raw(
    session: zenoh.Session, key: str, handler: Callable[[zenoh.Sample], Any], stats: Stats
) -> zenoh.Subscriber:
    """Undecoded subscription (the recorder), with handler errors contained and counted."""

    def on_sample(sample: zenoh.Sample) -> None:
        try:
            handler(sample)
        except Exception as err:
            stats.error("errors.raw_handler", f"{sample.key_expr}: {type(err).__name__}: {err}")

    return session.declare_subscriber(key, on_sample)

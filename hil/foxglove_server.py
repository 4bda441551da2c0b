"""A running rig in Foxglove, live: ``hil foxglove --rig R`` and ``hil up --foxglove [HOST:]PORT``.

Subscribes ``hil/<rig>/**`` on a Zenoh session (the one ``hil monitor`` opens: ``hil.monitor.connect``)
and serves it over the Foxglove WebSocket protocol with the official SDK's server
(``foxglove-sdk``, behind ``hil.foxglove_relay``, which takes the protocol under both its
subprotocol names, ``foxglove.sdk.v1`` and ``foxglove.websocket.v1``): one channel per key,
named as the key, with its ``hil.*`` JSON Schema and the payload as published, plus the
well-known types the recorder writes beside the messages (``hil.wellknown``: the one conversion),
so Foxglove's Map, 3D, Plot and Log panels show the rig as they show a recording, with the same
layout (``docs/foxglove-layout.json``). A channel is advertised when its first message arrives.

Times are those of a recording (``hil.record.mcapio``): each message goes out with log time =
the run's start epoch + its receive time on the rig clock (the wall clock before the run's
``RunInfo``). Loopback only unless a host is given. Read-only: it publishes nothing on the bus.
A key outside the contract or a payload that does not decode is counted (``counters``) and not
served; nothing a client does reaches the rig.
"""

from __future__ import annotations

import json
import threading
from dataclasses import dataclass, field
from typing import Any

import foxglove
import msgspec
import zenoh

from hil.bus.keys import Keys, type_for_key
from hil.foxglove_relay import Relay
from hil.messages import (
    Event,
    GnssFix,
    Message,
    NavSolution,
    RunInfo,
    ServiceStatus,
    Truth,
    decode,
    json_schema,
    split_batch,
)
from hil.record.mcapio import wall_clock_log_time
from hil.runtime.clock import wall_ns
from hil.wellknown import MESSAGE_ENCODING, SCHEMAS, WellKnown

DEFAULT_HOST = "127.0.0.1"
DEFAULT_PORT = 8765
UPSTREAM_HOST = "127.0.0.1"  # where the SDK's server listens, behind the relay (hil.foxglove_relay)
# the types the well-known conversion reads (the others are served without being decoded)
_DERIVES = (Truth, GnssFix, NavSolution, Event, ServiceStatus, RunInfo)


def parse_listen(text: str) -> tuple[str, int]:
    """``[HOST:]PORT`` (``[::1]:8765`` for IPv6) -> (host, port); host defaults to loopback."""
    host, sep, port = text.rpartition(":")
    if not sep:
        host, port = DEFAULT_HOST, text
    host = host.strip("[]") or DEFAULT_HOST
    if not port.isdigit() or not 0 <= int(port) <= 65535:
        raise ValueError(f"{text!r}: expected [HOST:]PORT with PORT 0-65535 (e.g. 8765 or 127.0.0.1:8765)")
    return host, int(port)


@dataclass
class FoxgloveServer:
    """One rig served to Foxglove clients. ``close()`` stops the server and the subscription."""

    session: zenoh.Session
    rig: str
    host: str = DEFAULT_HOST
    port: int = DEFAULT_PORT
    counters: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self.keys = Keys(self.rig)
        self._lock = threading.Lock()
        self._context = foxglove.Context()
        self._channels: dict[str, foxglove.Channel] = {}
        self._wellknown = WellKnown()
        self._start: int | None = None
        self._speed = 1.0
        # hil's port the relay's, which takes the protocol under both its names
        # (hil.foxglove_relay), bound first: the SDK's server then takes a free loopback port of
        # its own, which cannot be the one asked for
        try:
            self._relay = Relay(self.host, self.port)
        except OSError as err:
            raise OSError(
                f"cannot serve Foxglove on {self.host}:{self.port}: {err.strerror or err}"
            ) from None
        self.port = self._relay.port
        try:
            self._server = foxglove.start_server(
                name=f"hil rig {self.rig}", host=UPSTREAM_HOST, port=0, context=self._context
            )
        except RuntimeError as err:  # the SDK's FoxgloveError: bind failures and the like
            self._relay.close()
            raise OSError(f"cannot serve Foxglove on {UPSTREAM_HOST}: {err}") from None
        self._relay.start((UPSTREAM_HOST, int(self._server.port)))
        self._sub = self.session.declare_subscriber(self.keys.all(), self._on_sample)

    @property
    def url(self) -> str:
        host = f"[{self.host}]" if ":" in self.host else self.host
        return f"ws://{host}:{self.port}"

    def _count(self, name: str, n: int = 1) -> None:
        self.counters[name] = self.counters.get(name, 0) + n

    def _channel(self, topic: str, schema: foxglove.Schema, encoding: str) -> foxglove.Channel:
        ch = self._channels.get(topic)
        if ch is None:
            ch = self._channels[topic] = foxglove.Channel(
                topic, schema=schema, message_encoding=encoding, context=self._context
            )
        return ch

    def _on_sample(self, sample: zenoh.Sample) -> None:
        # Zenoh's thread: never raise into it
        try:
            key, payload, now = str(sample.key_expr), sample.payload.to_bytes(), wall_ns()
            try:
                parts = split_batch(payload)  # one message, or a batch's (Publisher.put_many) one by one
            except ValueError:
                self._count("rejected.invalid")
                return
            for part in parts:
                self.handle(key, part, now)
        except Exception as err:
            self._count(f"errors.{type(err).__name__}")

    def handle(self, key: str, payload: bytes, rx_wall_ns: int) -> None:
        """Serve one sample (and what it derives) to every subscribed client."""
        cls = type_for_key(key)
        if cls is None:
            self._count("rejected.unknown_key")
            return
        msg: Message | None = None
        if issubclass(cls, _DERIVES):
            try:
                msg = decode(cls, payload)
            except msgspec.DecodeError:  # ValidationError too
                self._count("rejected.invalid")
                return
        with self._lock:
            if isinstance(msg, RunInfo) and self._start is None:
                self._start, self._speed = msg.start_epoch_ns, msg.speed
            log_ns = wall_clock_log_time(rx_wall_ns, self._start, self._speed)
            name = f"hil.{cls.__name__}"
            schema = foxglove.Schema(name=name, encoding="jsonschema", data=_schema_bytes(cls))
            self._channel(key, schema, "json").log(payload, log_time=log_ns)
            self._count("messages")
            if msg is None:
                return
            for d in self._wellknown.convert(key, msg, log_ns):
                s = SCHEMAS[d.schema]
                wk = foxglove.Schema(name=s.name, encoding=s.encoding, data=s.data)
                self._channel(d.topic, wk, MESSAGE_ENCODING).log(d.data, log_time=log_ns)
                self._count("derived")

    def channels(self) -> list[str]:
        """The topics served so far."""
        with self._lock:
            return list(self._channels)

    def close(self) -> None:
        try:
            self._sub.undeclare()
        finally:
            self._relay.close()
            self._server.stop()
            for k, v in self._relay.counters.items():  # clients (and under which name), refusals
                self._count(f"relay.{k}", v)


_SCHEMA_BYTES: dict[type[Any], bytes] = {}


def _schema_bytes(cls: type[Message]) -> bytes:
    data = _SCHEMA_BYTES.get(cls)
    if data is None:
        data = _SCHEMA_BYTES[cls] = json.dumps(json_schema(cls), sort_keys=True).encode()
    return data

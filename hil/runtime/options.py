"""Every service's typed options, found by service name; and how ``hil up`` fills them.

A node service's options are its node's ``Options`` (``hil.nodes.<name>``); the recorder, the
one service that is not a node (it is the rig's sink), declares its own here. Each is a msgspec
Struct with one default per field and no unknown field: ``hil service NAME --options JSON``
(compose passes its environment through that JSON) decodes into it, and a bad or unknown option
is one line naming the field (``hil.nodes.base.decode_options``).

``hil up`` fills every field whose name it also has (``UpOptions``: ``channel``, ``fd``,
``estimators``, ``scenario``, ...), so an option added to a node with the name of an ``hil up``
flag reaches it with no code here; ``derived`` holds the few that are computed.
"""

from __future__ import annotations

from typing import Any

import msgspec

from hil.nodes import NODES, node_class
from hil.nodes.base import NodeOptions, decode_options


class RecorderOptions(NodeOptions, frozen=True, kw_only=True, forbid_unknown_fields=True):
    path: str = "recordings/session.mcap"  # the MCAP file (parts: <stem>_0001.mcap, ...)
    split_mb: float = 0.0  # start a new part after this many MB (0: one file)
    split_s: float = 0.0  # ... or after this many seconds
    zenoh_advanced: bool = True  # an advanced subscriber with sample-miss detection
    drain_s: float = 0.5  # at the stop: wait until nothing has arrived for this long ...
    drain_max_s: float = 5.0  # ... but no longer than this
    stop_timeout_s: float = 20.0  # then let the writer empty its queue for at most this long
    # Zenoh key expressions to record (empty: all) and not to record; relative to hil/<rig>/
    # (hil.record.keyfilter)
    include: list[str] = msgspec.field(default_factory=list)
    exclude: list[str] = msgspec.field(default_factory=list)
    raw_unknown: bool = True  # keys outside the contract recorded as raw bytes (else refused)
    foxglove_types: bool = True  # Foxglove's well-known types beside the messages (hil.wellknown)
    # the files this recorder's earlier lives wrote of the same session, oldest first (hil up
    # --restart): what they hold is accounted in this part's completeness and not written again
    continues: list[str] = msgspec.field(default_factory=list)


OTHER_SERVICES: dict[str, type[NodeOptions]] = {"recorder": RecorderOptions}


def options_class(service: str) -> type[NodeOptions]:
    """The options type of ``service`` (a ``KeyError`` naming the known ones otherwise)."""
    if service in OTHER_SERVICES:
        return OTHER_SERVICES[service]
    if service in NODES:
        cls: type[NodeOptions] = node_class(service).Options
        return cls
    raise KeyError(f"unknown service {service!r}; known: {', '.join([*OTHER_SERVICES, *NODES])}")


def fill_options(service: str, source: Any, derived: dict[str, Any] | None = None) -> dict[str, Any]:
    """The options of ``service`` taken from ``source``'s attributes of the same names, then
    ``derived``; checked (``OptionsError`` names the field) and returned as plain JSON data."""
    cls = options_class(service)
    raw = {f: getattr(source, f) for f in cls.__struct_fields__ if hasattr(source, f)}
    raw.update(derived or {})
    raw = {k: v for k, v in raw.items() if v is not None}  # None: not given, the service's default
    decode_options(cls, raw, service)  # refuse here, before any process starts
    return raw

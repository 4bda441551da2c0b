"""GNSS receiver wire protocols: pure codecs from a receiver's epoch to the bytes on its UART and back.

A registry by name so a scenario or node option can say ``protocol = "ubx"`` and the codec module is
imported only when used (the node that speaks NMEA need not load the UBX tables). Every protocol class
follows the contract in :mod:`hil.wire.base`.
"""

from __future__ import annotations

import importlib

from hil.wire.base import DecodedFix, ReceiverEpoch, WireDecoder, WireProtocol

__all__ = ["PROTOCOLS", "DecodedFix", "ReceiverEpoch", "WireDecoder", "WireProtocol", "protocol"]

# name -> "module:class", imported on first use
PROTOCOLS: dict[str, str] = {
    "nmea": "hil.wire.nmea:NmeaProtocol",
    "ubx": "hil.wire.ubx:UbxProtocol",
}


def protocol(name: str) -> type[WireProtocol]:
    """The protocol class registered as ``name``; a KeyError names the known ones otherwise."""
    try:
        target = PROTOCOLS[name]
    except KeyError:
        raise KeyError(
            f"unknown GNSS wire protocol {name!r}; known: {', '.join(sorted(PROTOCOLS))}"
        ) from None
    module_name, _, class_name = target.partition(":")
    cls: type[WireProtocol] = getattr(importlib.import_module(module_name), class_name)
    return cls

"""Nodes: each rig service's behaviour, written once and run by every runner.

See ``hil.nodes.base`` for the contract and ``docs/concepts.md`` ("Nodes and runners") for the
picture. ``NODES`` names them lazily (module:class), so a process imports only the node it runs.
"""

from __future__ import annotations

import importlib
from typing import Any

from hil.sensor_table import SENSORS

#: node name -> "module:Class". A sensor's emulator is named in the sensor table
#: (``hil.sensor_table``); its node lives in ``hil.nodes.<emulator>`` as ``<Camel>Node``.
NODES: dict[str, str] = {
    "world": "hil.nodes.world:WorldNode",
    "imu_emulator": "hil.nodes.imu_emulator:ImuEmulatorNode",
    "can_bridge": "hil.nodes.can_bridge:CanBridgeNode",
    "gnss_emulator": "hil.nodes.gnss_emulator:GnssEmulatorNode",
    "timesync": "hil.nodes.timesync:TimeSyncNode",
    "fusion": "hil.nodes.fusion:FusionNode",
    "dut_emulator": "hil.nodes.dut_emulator:DutEmulatorNode",
    "gnss_bridge": "hil.nodes.gnss_bridge:GnssBridgeNode",
}
for _kind in SENSORS.values():
    _camel = "".join(p.capitalize() for p in _kind.emulator.split("_"))
    NODES.setdefault(_kind.emulator, f"hil.nodes.{_kind.emulator}:{_camel}Node")


def node_class(name: str) -> Any:
    """The node class called ``name`` (imported on first use)."""
    try:
        target = NODES[name]
    except KeyError:
        raise KeyError(f"unknown node {name!r}; known: {', '.join(NODES)}") from None
    module, _, cls = target.partition(":")
    return getattr(importlib.import_module(module), cls)

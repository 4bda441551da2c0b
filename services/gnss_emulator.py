"""gnss_emulator: a receiver that outputs fixes late (latency + jitter) and raises a PPS edge.

The behaviour is ``hil.nodes.gnss_emulator.GnssEmulatorNode``, run live by ``hil.runners.live``.
"""

from __future__ import annotations

from hil.nodes.gnss_emulator import GnssEmulatorNode
from hil.runners.live import main_for, service_for

SERVICE = service_for(GnssEmulatorNode)
main = main_for(SERVICE)

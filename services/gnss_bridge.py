"""gnss_bridge: a GNSS receiver's serial line -> ``hil.GnssFix`` and the raw bytes.

The behaviour is ``hil.nodes.gnss_bridge.GnssBridgeNode``; ``hil.runners.live`` reads the line
(a pseudo-terminal, a real serial device or a TCP server: ``hil.runners.serial.LineReader``) and
hands each read over with its receive time on the rig clock.
"""

from __future__ import annotations

from hil.nodes.gnss_bridge import GnssBridgeNode
from hil.runners.live import main_for, service_for

SERVICE = service_for(GnssBridgeNode)
main = main_for(SERVICE)

"""can_bridge: CAN frames of the IMU (and of a device under test) -> contract messages.

The behaviour is ``hil.nodes.can_bridge.CanBridgeNode``; ``hil.runners.live`` reads the bus
with python-can (SocketCAN where the channel exists, else the ``hilzenoh`` transport; see
``hil.can.bus.open_can_bus``) and hands each frame over with its receive stamp on the rig clock.
"""

from __future__ import annotations

from hil.nodes.can_bridge import CanBridgeNode
from hil.runners.live import main_for, service_for
from hil.runtime.clock import epoch_s_to_rig_ns as epoch_s_to_rig_ns  # re-exported (tests, tools)

SERVICE = CanBridge = service_for(CanBridgeNode)
main = main_for(SERVICE, aliases={"--dut-mapping": "dut_mapping"})

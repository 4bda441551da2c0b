"""dut_emulator: a stand-in navigation box on the CAN bus (``hil.nodes.dut_emulator``), live."""

from __future__ import annotations

from hil.nodes.dut_emulator import DutEmulatorNode
from hil.runners.live import main_for, service_for

SERVICE = service_for(DutEmulatorNode)
main = main_for(SERVICE)

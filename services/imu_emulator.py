"""imu_emulator: an IMU as a CAN node -- samples paced on the sample clock, sent as DBC frames.

The behaviour (physics, error model, faults, DBC frames, delay line, capture truth) is
``hil.nodes.imu_emulator.ImuEmulatorNode``; ``hil.runners.live`` paces it on the rig clock and
sends its frames on the configured bus through a pacing process (``hil.runners.can_sender``:
on the sample grid, frames at wire spacing; docs/timing.md).
"""

from __future__ import annotations

from hil.nodes.imu_emulator import ImuEmulatorNode
from hil.runners.live import main_for, service_for

SERVICE = service_for(ImuEmulatorNode)
main = main_for(SERVICE)

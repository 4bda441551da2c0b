"""``hil sim``'s CAN bus: when each frame the IMU node sends reaches the bridge.

Live, the real bus (SocketCAN or the Zenoh transport) does this and the kernel stamps arrivals.
Offline the runner models it from the scenario's ``[clock.imu]`` transport terms: a sample's
frames leave together (when the node releases them), take ``transport_latency_s`` plus an
exponential extra delay of mean ``transport_jitter_s`` -- one draw per sample index, from its own
seeded stream, so the draws do not depend on which samples a fault kept off the bus -- and one
frame's wire time each, first in first out. A sync frame goes first at its edge and carries the
kernel-stamp latch jitter of the IMU's clock model; the data frames of that sample follow it. A
frame's wire time is what the live sender paces it by (``hil.runners.pacing.CanWire``: its bits
at 1 Mbit/s, an FD frame's data at 5 Mbit/s): 135 µs for the classic 8-byte frames.
"""

from __future__ import annotations

from typing import Any

from hil.nav.scenario import Scenario
from hil.nodes.base import CanBurst
from hil.runners.pacing import CanWire
from hil.sensors.clock import clock_config_for, device_clock_for
from hil.sensors.imu import sensor_rng


class CanWireModel:
    """A FIFO CAN bus between the IMU node and the bridge node (pure: no clock, seeded)."""

    def __init__(self, scenario: Scenario) -> None:
        cc = clock_config_for(scenario, "imu")
        self.latency_ns = round(cc.transport_latency_s * 1e9)
        self.jitter_ns = cc.transport_jitter_s * 1e9
        self._rng = sensor_rng(scenario.seed, "imu.transport")
        self._latch = device_clock_for(scenario, "imu")  # the receiver's kernel-stamp latch
        self._drawn = 0  # extra delays drawn so far (one per sample index)
        self._block: list[float] = []  # drawn ahead in blocks: the same stream as one at a time
        self._block_k0 = 0
        self._sync_capture: int | None = None
        self.last_rx_ns = -(2**62)
        self._bus = CanWire()  # a frame's wire time, as the live sender paces it
        self._sync_wire_ns = 0

    def _extra_ns(self, index: int) -> float:
        if self.jitter_ns <= 0:
            return 0.0
        i = index - self._block_k0
        while i >= len(self._block):  # draws go in sample-index order whatever the block size
            self._block_k0 += len(self._block)
            i = index - self._block_k0
            self._block = self._rng.exponential(self.jitter_ns, 1024).tolist()
        return self._block[i]

    def arrivals(self, burst: CanBurst, t_emit_ns: int) -> list[tuple[int, Any]]:
        """``(rx_ns, frame)`` of each frame of ``burst``, which left at ``t_emit_ns``."""
        frame_ns = self._bus.frame_ns
        wires = [frame_ns(f) for f in burst.frames]
        if burst.sync:
            self._sync_capture = burst.capture_ns
            self._sync_wire_ns = wires[0]
            nominal = [self._latch.latch_ns(burst.capture_ns) + self.latency_ns + wires[0]]
        else:
            t = t_emit_ns + self.latency_ns + round(self._extra_ns(burst.index))
            if self._sync_capture == burst.capture_ns:  # behind its sync frame
                t += self._sync_wire_ns
            nominal = []
            for w in wires:
                t += w
                nominal.append(t)
        out: list[tuple[int, Any]] = []
        for nom, w, frame in zip(nominal, wires, burst.frames, strict=False):
            rx = max(nom, self.last_rx_ns + w)  # the bus is FIFO
            self.last_rx_ns = rx
            frame.timestamp = rx * 1e-9  # python-can's receive stamp (rig seconds here)
            out.append((rx, frame))
        return out

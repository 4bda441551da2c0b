"""Device clocks: how a sensor's own clock reads true time.

The foundation's devices share the rig clock (identity); the time-tag issue adds offset, drift,
drift wander, jitter, quantisation and steps from the scenario's ``[clock.<sensor>]`` table.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Any


@dataclass
class IdealClock:
    """A device clock that reads true time exactly."""

    def device_ns(self, true_ns: int) -> int:
        return int(true_ns)


def device_clock_for(scenario: Any, sensor: str) -> IdealClock:
    """The clock model of ``sensor`` in ``scenario`` (ideal until clock tables are configured)."""
    return IdealClock()

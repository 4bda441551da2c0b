"""Time-tag synchronisation core: device clock -> rig clock, per sensor. Pure: no I/O, no clock.

The mapping is ``rig = device + offset + drift * (device - ref)``. The foundation's estimator is
``passthrough`` (devices share the rig clock); the time-tag issue adds estimators fitted on time
tags and on arrival times behind the same interface.
"""

from __future__ import annotations

from dataclasses import dataclass, field


@dataclass
class ClockMapping:
    sensor: str
    source: str = "passthrough"
    offset_ns: int = 0
    drift_ppb: float = 0.0
    ref_device_ns: int = 0
    residual_rms_ns: float = 0.0
    n_samples: int = 0
    state: str = "locked"
    steps_detected: int = 0

    def to_rig(self, device_ns: int) -> int:
        return (
            device_ns + self.offset_ns + int(round(self.drift_ppb * 1e-9 * (device_ns - self.ref_device_ns)))
        )


@dataclass
class TimeSyncCore:
    """One mapping per sensor; fed time tags and measurement arrivals, asked to re-stamp."""

    mappings: dict[str, ClockMapping] = field(default_factory=dict)

    def mapping(self, sensor: str) -> ClockMapping:
        m = self.mappings.get(sensor)
        if m is None:
            m = self.mappings[sensor] = ClockMapping(sensor)
        return m

    def on_timetag(self, sensor: str, device_ns: int, rig_latch_ns: int) -> None:
        self.mapping(sensor).n_samples += 1

    def on_arrival(self, sensor: str, device_ns: int, rx_rig_ns: int) -> None:
        """A measurement's device stamp and its arrival on the rig clock (one-way delay >= 0)."""

    def restamp(self, sensor: str, device_ns: int) -> int:
        """Rig time of validity of a measurement stamped ``device_ns`` by ``sensor``."""
        return self.mapping(sensor).to_rig(device_ns)

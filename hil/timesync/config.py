"""Per-sensor synchronisation settings from a scenario's ``[clock.<sensor>]`` tables.

The clock table describes the device (``hil.sensors.clock``) and what the rig knows about it: its
calibrated tag latency, its minimum transport delay, whether its time tags are used. This module
turns the latter into :class:`hil.timesync.core.SyncConfig`, so the live service and ``hil sim``
configure the same core the same way.
"""

from __future__ import annotations

from hil.nav.scenario import Scenario
from hil.sensor_table import SENSOR_NAMES, SENSORS
from hil.sensors.clock import clock_config_for
from hil.timesync.core import SyncConfig

SYNCED_SENSORS = SENSOR_NAMES  # every sensor of the table is synchronised
#: How long an interval sensor's measurements may wait at start for the tag filter's lock (three
#: tags; the IMU's sync frame comes once a second): past this they go with what is known.
HOLD_UNTIL_LOCKED_NS = 3_500_000_000


def is_interval_sensor(sensor: str) -> bool:
    """Its measurements are integrals over an interval (``dt_ns``), which need the clock's rate."""
    kind = SENSORS.get(sensor)
    return kind is not None and "dt_ns" in kind.message.__struct_fields__


def sync_config_for(scenario: Scenario, sensor: str, *, imu_can_fd: bool = False) -> SyncConfig:
    """The SyncConfig of one sensor: source, tag latency and minimum delay from the clock table
    (the IMU's minimum delay by its frames: ``imu_can_fd``, the run's ``RunInfo.imu_can_fd``)."""
    c = clock_config_for(scenario, sensor, imu_can_fd=imu_can_fd)
    source = c.sync or ("timetag" if c.timetag else "arrival")
    return SyncConfig(
        source=source,
        tag_latency_ns=round((c.tag_latency_s or 0.0) * 1e9),
        min_delay_ns=round((c.min_delay_s or 0.0) * 1e9),
        tag_sigma_ns=max(1_000.0, c.latch_jitter_s * 1e9 * 2),
        hold_until_locked_ns=HOLD_UNTIL_LOCKED_NS if is_interval_sensor(sensor) else 0,
    )


def sync_configs_for(scenario: Scenario, *, imu_can_fd: bool = False) -> dict[str, SyncConfig]:
    return {s: sync_config_for(scenario, s, imu_can_fd=imu_can_fd) for s in SYNCED_SENSORS}

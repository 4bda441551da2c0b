"""Every Zenoh key expression of the rig, built in one place.

Layout (``<rig>`` namespaces one bench, so a replay can run beside a live rig)::

    hil/<rig>/run                 RunInfo        run identity and time zero
    hil/<rig>/truth               Truth
    hil/<rig>/capture/<sensor>    CaptureTruth   true capture time per measurement
    hil/<rig>/can/<channel>       CanFrame       raw frames as read by the bridge
    hil/<rig>/serial/<port>       SerialChunk    raw bytes of a serial line (the GNSS receiver's)
    hil/<rig>/sensor/<sensor>     ImuSample | GnssFix | ...   raw, device-stamped (hil.sensor_table)
    hil/<rig>/timetag/<sensor>    TimeTag
    hil/<rig>/clock/<sensor>      ClockModel
    hil/<rig>/synced/<sensor>     ImuSample | GnssFix | ...   re-stamped to rig time of validity
    hil/<rig>/nav/<estimator>     NavSolution
    hil/<rig>/health/<estimator>  EstimatorHealth   innovation test ratios, NIS, gains (1 Hz)
    hil/<rig>/fusion/journal      FusionJournal
    hil/<rig>/fusion/config       FusionSettings    the fusion's configuration, at its start
    hil/<rig>/status/<service>    ServiceStatus
    hil/<rig>/event/<source>      Event
    hil/<rig>/control/fault       FaultCommand   run-time fault injection (``hil fault``)

The CAN transport that stands in for ``vcan0`` lives outside ``hil/`` (``hilcan/<rig>/<channel>``):
it carries bus traffic, not rig data, and the bridge already records every frame it reads.
"""

from __future__ import annotations

from hil.messages import (
    CanFrame,
    CaptureTruth,
    ClockModel,
    EstimatorHealth,
    Event,
    FaultCommand,
    FusionJournal,
    FusionSettings,
    Message,
    NavSolution,
    RunInfo,
    SerialChunk,
    ServiceStatus,
    TimeTag,
    Truth,
)
from hil.messages import check_name as check_name  # the rule lives with the messages that carry names
from hil.sensor_table import SENSORS

# sensor name -> raw/synced message type (the sensor table's)
SENSOR_TYPES: dict[str, type[Message]] = {name: kind.message for name, kind in SENSORS.items()}


# keys whose messages ready together may travel as one sample, a JSON array (a batch:
# ``hil.bus.pubsub.Publisher.put_many``, ``hil.messages.split_batch``): every key of these kinds
# (the raw CAN frames, ``can/<channel>``, four per IMU sample) and these keys (the samples of a
# CAN read window, their synchronised copies, the emulator's capture truth of a compute batch,
# the world's truth rows computed together: ten at 100 Hz, which went out as ten messages at
# the same instant, each routed and woken up for). Not the solutions (``nav``) nor the GNSS
# fixes: one per sample, as a client expects of a low-rate stream. Keys relative to
# ``hil/<rig>/``; docs/topics.md says it from here.
BATCHED_KINDS = frozenset({"can"})
BATCHED_KEYS = frozenset({"sensor/imu", "synced/imu", "capture/imu", "truth"})


def may_batch(key: str) -> bool:
    """Whether messages of ``key`` (relative to ``hil/<rig>/``) may travel as a batch."""
    return key in BATCHED_KEYS or key.split("/", 1)[0] in BATCHED_KINDS


class Keys:
    """Key expressions of one rig."""

    def __init__(self, rig: str) -> None:
        self.rig = check_name("rig", rig)
        self.root = f"hil/{rig}"

    def all(self) -> str:
        return f"{self.root}/**"

    def run(self) -> str:
        return f"{self.root}/run"

    def truth(self) -> str:
        return f"{self.root}/truth"

    def capture(self, sensor: str) -> str:
        return f"{self.root}/capture/{sensor}"

    def can(self, channel: str) -> str:
        return f"{self.root}/can/{channel}"

    def serial(self, port: str) -> str:
        return f"{self.root}/serial/{port}"

    def sensor(self, sensor: str) -> str:
        return f"{self.root}/sensor/{sensor}"

    def timetag(self, sensor: str) -> str:
        return f"{self.root}/timetag/{sensor}"

    def clock(self, sensor: str) -> str:
        return f"{self.root}/clock/{sensor}"

    def synced(self, sensor: str) -> str:
        return f"{self.root}/synced/{sensor}"

    def nav(self, estimator: str) -> str:
        return f"{self.root}/nav/{estimator}"

    def journal(self) -> str:
        return f"{self.root}/fusion/journal"

    def fusion_config(self) -> str:
        return f"{self.root}/fusion/config"

    def health(self, estimator: str) -> str:
        return f"{self.root}/health/{estimator}"

    def status(self, service: str) -> str:
        return f"{self.root}/status/{service}"

    def event(self, source: str) -> str:
        return f"{self.root}/event/{source}"

    def control(self, name: str) -> str:
        """Commands to the rig (``control/fault``): recorded like everything under ``hil/<rig>``."""
        return f"{self.root}/control/{name}"

    def canbus(self, channel: str) -> str:
        """The transport key of the Zenoh-backed CAN interface (not rig data)."""
        return f"hilcan/{self.rig}/{channel}"


_FIXED: dict[str, type[Message]] = {
    "run": RunInfo,
    "truth": Truth,
    "capture": CaptureTruth,
    "can": CanFrame,
    "serial": SerialChunk,
    "timetag": TimeTag,
    "clock": ClockModel,
    "nav": NavSolution,
    "health": EstimatorHealth,
    "fusion": FusionJournal,
    "status": ServiceStatus,
    "event": Event,
    "control": FaultCommand,
}


def type_for_key(key: str) -> type[Message] | None:
    """The contract type a rig key carries, or None for keys outside the contract."""
    parts = key.split("/")
    if len(parts) < 3 or parts[0] != "hil":
        return None
    kind = parts[2]
    if kind in ("sensor", "synced"):
        return SENSOR_TYPES.get(parts[3]) if len(parts) > 3 else None
    if kind == "fusion" and len(parts) > 3 and parts[3] == "config":
        return FusionSettings
    return _FIXED.get(kind)


def rig_of_key(key: str) -> str | None:
    parts = key.split("/")
    return parts[1] if len(parts) > 1 and parts[0] == "hil" else None


def rekey(key: str, rig: str) -> str:
    """The same key under another rig (replay beside a live rig)."""
    parts = key.split("/")
    if len(parts) < 2 or parts[0] != "hil":
        raise ValueError(f"key {key!r} is not a rig key (hil/<rig>/...)")
    parts[1] = check_name("rig", rig)
    return "/".join(parts)

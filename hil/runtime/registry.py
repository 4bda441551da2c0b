"""The rig's services, by name: one place that maps a name to its module."""

from __future__ import annotations

import importlib
from types import ModuleType

# Start order matters: the recorder listens before anything else speaks; world (time zero) is last.
SERVICES: dict[str, str] = {
    "recorder": "services.recorder",
    "can_bridge": "services.can_bridge",
    "timesync": "services.timesync",
    "fusion": "services.fusion",
    "imu_emulator": "services.imu_emulator",
    "gnss_emulator": "services.gnss_emulator",
    "world": "services.world",
}

# Stop order: producers first, consumers after they drained, recorder last.
STOP_STAGES: tuple[tuple[str, ...], ...] = (
    ("world", "imu_emulator", "gnss_emulator"),
    ("can_bridge",),
    ("timesync",),
    ("fusion",),
    ("recorder",),
)


class UnknownServiceError(KeyError):
    def __str__(self) -> str:
        return f"unknown service {self.args[0]!r}; known: {', '.join(SERVICES)}"


def service_module(name: str) -> ModuleType:
    if name not in SERVICES:
        raise UnknownServiceError(name)
    return importlib.import_module(SERVICES[name])

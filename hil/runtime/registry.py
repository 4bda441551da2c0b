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

# Started only on request (`hil up --dut-emulator`), but runnable alone like any service.
OPTIONAL_SERVICES: dict[str, str] = {
    "dut_emulator": "services.dut_emulator",
}

# Stop order: producers first, consumers after they drained, recorder last.
STOP_STAGES: tuple[tuple[str, ...], ...] = (
    ("world", "imu_emulator", "gnss_emulator", "dut_emulator"),
    ("can_bridge",),
    ("timesync",),
    ("fusion",),
    ("recorder",),
)


class UnknownServiceError(KeyError):
    def __str__(self) -> str:
        return f"unknown service {self.args[0]!r}; known: {', '.join([*SERVICES, *OPTIONAL_SERVICES])}"


def service_module(name: str) -> ModuleType:
    module = SERVICES.get(name) or OPTIONAL_SERVICES.get(name)
    if module is None:
        raise UnknownServiceError(name)
    return importlib.import_module(module)

"""The rig's services, by name: which run under ``hil up``, in what order they start and stop.

The emulator of every sensor in ``hil.sensor_table`` is a service of the rig (started after the
consumers, stopped first), so a sensor added to the table is started, waited for and recorded
without an edit here. ``hil service NAME`` runs ``services/<NAME>.py`` where one exists (a
process with its own command line) and otherwise the node of that name on the live runner.
"""

from __future__ import annotations

import importlib
from types import ModuleType

from hil.nodes import NODES
from hil.sensor_table import SENSOR_NAMES, SENSORS

_EMULATORS = tuple(SENSORS[s].emulator for s in SENSOR_NAMES)

# Start order matters: the recorder listens before anything else speaks; world (time zero) is last.
SERVICES: dict[str, str] = {
    "recorder": "services.recorder",
    "can_bridge": "services.can_bridge",
    "timesync": "services.timesync",
    "fusion": "services.fusion",
    **{name: f"services.{name}" for name in _EMULATORS},
    "world": "services.world",
}

# Started only on request (`hil up --dut-emulator truth`: the truth+noise stand-in for a unit;
# the GNSS receiver on a wire: `--gnss-serial`, `--gnss-tcp`, `--gnss-protocol`), but runnable
# alone like any service.
OPTIONAL_SERVICES: dict[str, str] = {
    "dut_emulator": "services.dut_emulator",
    "gnss_bridge": "services.gnss_bridge",
}

# Stop order: producers first, consumers after they drained, recorder last. "dut" is the device
# under test's own program (`hil up --dut-emulator`: examples/dut/navbox.py), a child, not a service.
STOP_STAGES: tuple[tuple[str, ...], ...] = (
    ("world", *_EMULATORS, "dut_emulator", "dut"),
    ("can_bridge", "gnss_bridge"),
    ("timesync",),
    ("fusion",),
    ("recorder",),
)


class UnknownServiceError(KeyError):
    def __str__(self) -> str:
        return f"unknown service {self.args[0]!r}; known: {', '.join([*SERVICES, *OPTIONAL_SERVICES])}"


def service_module(name: str) -> ModuleType:
    """The process entry point of ``name``: its ``services`` module (``SERVICE``, ``main``), or,
    for a node without one, a module-like view of the node on the live runner."""
    module = SERVICES.get(name) or OPTIONAL_SERVICES.get(name)
    if module is None:
        raise UnknownServiceError(name)
    try:
        return importlib.import_module(module)
    except ModuleNotFoundError as err:
        if err.name != module or name not in NODES:
            raise
    from hil.nodes import node_class
    from hil.runners.live import main_for, service_for

    generic = ModuleType(module, f"{name}: the node on the live runner")
    generic.SERVICE = service_for(node_class(name))  # type: ignore[attr-defined]
    generic.main = main_for(generic.SERVICE)  # type: ignore[attr-defined]
    return generic

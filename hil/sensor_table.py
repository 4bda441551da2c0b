"""The sensor table: every kind of measurement the rig carries, declared once.

A sensor kind names its keys (``sensor/<name>``, ``synced/<name>``, ``timetag/<name>``,
``clock/<name>``, ``capture/<name>``), its message type, its rank in the fusion's total order at
equal stamps, which node emulates it, the faults that node applies (run-time commands and the
scenario's timed events), the defaults of its ``[clock.<name>]`` table and how its time tag and
transport delay are derived. Keys (``hil.bus.keys``), time sync (``hil.timesync.config``), the
fusion's order (``hil.fusion.core``), the fault catalogue (``hil.faults``), the scenario's event
kinds (``hil.nav.scenario``), device clocks (``hil.sensors.clock``), the recorder and both
runners read it from here; adding a sensor is a row here plus its message and its emulator node
(``docs/recipes.md``, "Add a sensor").

This module sits at the bottom of the package (it imports only the messages): the functions
below take the clock configuration and the scenario duck-typed.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from dataclasses import dataclass, field
from types import MappingProxyType
from typing import Any

from hil.messages import GnssFix, ImuSample, Message

CAN_FRAME_TIME_NS = 135_000  # ~ one 8-byte classic frame at 1 Mbit/s with stuffing
IMU_FRAMES_PER_SAMPLE = 4  # classic CAN: AxisX, AxisY, AxisZ, Time (the last completes the sample)
# CAN FD: one 32-byte IMU_SampleFD frame a sample at 1 / 5 Mbit/s with stuffing
# (``hil.can.busload.frame_bits``; the live sender and ``hil sim``'s bus pace it so)
IMU_FD_FRAME_TIME_NS = 104_800


def _frame_s() -> float:
    return CAN_FRAME_TIME_NS * 1e-9


@dataclass(frozen=True)
class SensorKind:
    """One kind of measurement: what flows, who makes it, how the rig times and faults it."""

    name: str  # the key segment: sensor/<name>, synced/<name>, ...
    message: type[Message]  # raw (sensor/<name>) and re-stamped (synced/<name>) type
    rank: int  # order at equal rig stamps in the fusion's total order (lower first)
    emulator: str  # the node (and service) that emulates the device
    paces_fusion: bool = False  # its stamps move the fusion's horizon (the IMU is the clock)
    # run-time faults (``hil fault KIND``): kind -> the params a FaultCommand may carry
    commands: Mapping[str, frozenset[str]] = field(default_factory=dict)
    # timed faults in the scenario's [[event]] table: kind -> the keys the event may carry
    events: Mapping[str, frozenset[str]] = field(default_factory=dict)
    # [clock.<name>] defaults (hil.sensors.clock.DeviceClockConfig fields)
    clock: Mapping[str, Any] = field(default_factory=dict)
    # calibrated edge -> latch delay of its time tag, when [clock.<name>] does not say
    tag_latency_s: Callable[[Any, Any], float] = lambda cfg, scenario: 0.0
    # known minimum measurement -> arrival delay, when [clock.<name>] does not say: of its clock
    # config, the scenario and whether the IMU is on CAN FD (``RunInfo.imu_can_fd``)
    min_delay_s: Callable[[Any, Any, bool], float] = lambda cfg, _s, _fd: float(cfg.transport_latency_s)


def _imu_tag_latency_s(cfg: Any, _scenario: Any) -> float:
    # the sync frame goes first at its edge and is stamped by the kernel on receipt: one
    # frame's wire time plus the bus latency
    return float(cfg.transport_latency_s) + _frame_s()


def _imu_min_delay_s(cfg: Any, _scenario: Any, can_fd: bool) -> float:
    # a sample's arrival is its last frame's: four classic frames, or one CAN FD frame
    frames_ns = IMU_FD_FRAME_TIME_NS if can_fd else IMU_FRAMES_PER_SAMPLE * CAN_FRAME_TIME_NS
    return float(cfg.transport_latency_s) + frames_ns * 1e-9


def _gnss_min_delay_s(_cfg: Any, scenario: Any, _can_fd: bool) -> float:
    return float(scenario.gnss.latency_s)  # the receiver's output latency (PX4's EKF2_GPS_DELAY)


def _fs(*names: str) -> frozenset[str]:
    return frozenset(names)


_IMU_FAULTS = {
    "imu_frame_loss": _fs("percent"),
    "imu_stuck": _fs(),
    "imu_saturated": _fs(),
    "can_burst_error": _fs("frames"),
    "can_bus_off": _fs(),
    "can_latency": _fs("latency_s", "jitter_s"),
}

# the receiver's serial line and clock, when it is on a wire (hil/faults.py: LineFaults)
_GNSS_LINE_FAULTS = {
    "gnss_line_checksum": _fs("percent"),
    "gnss_line_truncate": _fs("percent"),
    "gnss_line_garble": _fs("percent"),
    "gnss_line_dropout": _fs(),
    "gnss_line_burst": _fs("bytes"),
    "gnss_time_jump": _fs("step_s"),
    "gnss_frozen": _fs(),
}

SENSORS: Mapping[str, SensorKind] = MappingProxyType(
    {
        "imu": SensorKind(
            name="imu",
            message=ImuSample,
            rank=0,
            emulator="imu_emulator",
            paces_fusion=True,
            commands=_IMU_FAULTS,
            events=_IMU_FAULTS,  # the same kinds, timed
            # a counter started 7.1 ms before the run, 20 ppm fast (a plain crystal); the sync
            # frame's kernel stamp with 5 µs; CAN data: 20 µs + exponential 10 µs beyond wire time
            clock={
                "offset_s": 0.0071,
                "drift_ppm": 20.0,
                "drift_rw_ppm_per_sqrt_s": 0.005,
                "jitter_s": 0.5e-6,
                "quantum_s": 1e-6,
                "latch_jitter_s": 5e-6,
                "transport_latency_s": 20e-6,
                "transport_jitter_s": 10e-6,
            },
            tag_latency_s=_imu_tag_latency_s,
            min_delay_s=_imu_min_delay_s,
        ),
        "gnss": SensorKind(
            name="gnss",
            message=GnssFix,
            rank=1,
            emulator="gnss_emulator",
            commands={
                "gnss_outage": _fs(),
                "gnss_jump": _fs("n_m", "e_m", "d_m"),
                "gnss_spoof": _fs("n_m", "e_m", "d_m", "sigma_m"),
                "gnss_velocity_glitch": _fs("n_mps", "e_mps", "d_mps"),
                "gnss_latency": _fs("latency_s", "jitter_s"),
                **_GNSS_LINE_FAULTS,
            },
            events={
                "gnss_outage": _fs(),
                "gnss_jump": _fs("offset_ned_m"),
                "gnss_spoof": _fs("offset_ned_m", "sigma_m"),
                "gnss_pulse": _fs("amplitude_m", "tau_s", "direction_ned"),  # scenario only
                "gnss_velocity_glitch": _fs("offset_ned_mps"),
                "gnss_latency": _fs("latency_s", "jitter_s"),
                **_GNSS_LINE_FAULTS,
            },
            # disciplined to GPS time: tiny drift, 20 ns stamp noise, 1.5 ms offset to the rig
            # clock; the PPS latched with 1 µs jitter
            clock={
                "offset_s": 0.0015,
                "drift_ppm": 0.02,
                "jitter_s": 20e-9,
                "quantum_s": 1e-9,
                "latch_jitter_s": 1e-6,
            },
            min_delay_s=_gnss_min_delay_s,
        ),
    }
)

#: The sensors in rank order (the order the fusion breaks ties in, and the runners list them in).
SENSOR_NAMES: tuple[str, ...] = tuple(sorted(SENSORS, key=lambda n: SENSORS[n].rank))

#: Fault kind -> (the service that applies it, params it takes): each sensor's run-time faults
#: (its emulator applies them), plus the two that belong to no one sensor. Here, not in
#: :mod:`hil.faults`, so that ``hil``'s command line can offer them without numpy.
FAULT_KINDS: Mapping[str, tuple[str, frozenset[str]]] = MappingProxyType(
    {
        **{kind: (s.emulator, params) for s in SENSORS.values() for kind, params in s.commands.items()},
        "clock_step": ("<target>_emulator", frozenset({"step_s"})),  # target: a sensor
        "kill_service": ("supervisor", frozenset()),  # target: a service name
    }
)


#: What ``hil.FaultCommand.duration_s`` accepts on the wire: ``hil fault --duration``'s bound too.
FAULT_MAX_DURATION_S = 1e6
#: A fault's position offset (``gnss_jump``/``gnss_spoof`` ``n_m``...): beyond the Earth's size is
#: no fault a receiver could report, only numbers that overflow what reads them.
FAULT_MAX_OFFSET_M = 1e7
#: A fault's velocity offset (``gnss_velocity_glitch`` ``n_mps``...): far beyond any vehicle's.
FAULT_MAX_OFFSET_MPS = 1e4
#: Params that count something: a whole number, not ``frames=1.5`` (``gnss_line_burst``'s
#: ``bytes`` too, checked with its range by ``hil.nav.scenario.line_burst_problem``, the scenario
#: event's check, so that a command and an event say the same)
FAULT_INTEGER_PARAMS = frozenset({"frames"})


def sensor_kind(name: str) -> SensorKind:
    """The kind of sensor ``name``; a ``KeyError`` that names the known ones otherwise."""
    try:
        return SENSORS[name]
    except KeyError:
        raise KeyError(f"unknown sensor {name!r}; known: {', '.join(SENSOR_NAMES)}") from None


UNKNOWN_RANK = 9  # a source no row names sorts after every known one
assert all(k.rank < UNKNOWN_RANK for k in SENSORS.values())


def rank_of(name: str) -> int:
    """Rank in the fusion's total order (``UNKNOWN_RANK`` for a source the table does not name)."""
    kind = SENSORS.get(name)
    return kind.rank if kind is not None else UNKNOWN_RANK

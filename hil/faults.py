"""Fault injection: which fault each service applies, and the IMU/CAN faults as a pure core.

Faults reach a device two ways, and both are recorded:

- **timed**, from the scenario's ``[[event]]`` table (``docs/scenario-format.md``): applied at the
  sample/epoch whose true time falls in the window, so a replay of the scenario applies them
  identically (decisions depend only on the scenario seed and the sample index, never on
  wall-clock timing);
- **commanded** at run time, as ``hil.FaultCommand`` on ``hil/<rig>/control/fault``
  (``hil fault --rig R KIND ...``), applied from the current rig time.

The service that applies a fault publishes ``hil.Event`` ``fault_start``/``fault_end`` on
``hil/<rig>/event/<service>`` with the fault as JSON in ``detail``.

:class:`ImuFaults` is the IMU emulator's part (no I/O, no clock): per sample it says whether
the sample is lost (``imu_frame_loss``, ``can_bus_off``), what to send instead (``imu_stuck``,
``imu_saturated``), how many frames to corrupt on the wire (``can_burst_error``: the bridge
rejects them on CRC) and how long to hold its frames (``can_latency``); :class:`FrameCorruptor`
does the corrupting, :class:`DelayLine` the holding (in order, seeded jitter). The emulator nodes
(``hil.nodes``) call them, and every runner runs those nodes, so a fault has one implementation
live, in ``hil sim`` and in replay.
:func:`device_timeline` is what each emulator announces: its own kinds plus the timed
``clock_step`` of its sensor (the step itself is applied by ``hil.sensors.clock``).

``SIM_NOT_APPLICABLE`` names the faults ``hil sim`` cannot apply (one process, nothing to kill):
it says so and records ``fault_ignored`` rather than dropping them silently.
"""

from __future__ import annotations

import json
import math
from collections import deque
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field
from typing import Any, Generic, TypeVar

import numpy as np

from hil.nav.scenario import MAX_CLOCK_STEP_S, line_burst_problem, transport_delay_problem
from hil.sensor_table import (
    FAULT_INTEGER_PARAMS,
    FAULT_KINDS,
    FAULT_MAX_DURATION_S,
    FAULT_MAX_OFFSET_M,
    FAULT_MAX_OFFSET_MPS,
    SENSORS,
)

IMU_FAULTS = frozenset(SENSORS["imu"].commands)
GNSS_FAULTS = frozenset(SENSORS["gnss"].commands)
# Announced by the emulator on its timeline: its timed kinds (the run-time ones plus scenario-only
# ones such as the seed paper's GNSS pulse) and the clock_step of its own sensor.
DEVICE_TIMED_KINDS: dict[str, frozenset[str]] = {
    name: frozenset(s.events) | {"clock_step"} for name, s in SENSORS.items()
}
# Timed faults with no meaning in `hil sim` (one process on a virtual clock): said and recorded.
SIM_NOT_APPLICABLE = frozenset({"kill_service"})
MAX_BURST_FRAMES = 100_000  # ~1 min of the 400 Hz IMU's frames; longer is a bus-off, say so
SATURATE_DTHETA_RAD = 10.0  # per sample: far beyond the DBC's full scale (0.42 rad)
SATURATE_DVEL_MPS = 1000.0  # per sample: far beyond the DBC's full scale (8.4 m/s)


class FaultError(ValueError):
    """A fault command that cannot be applied; the message says which field and why."""


T = TypeVar("T")
MAX_DURATION_S = FAULT_MAX_DURATION_S  # what hil.FaultCommand.duration_s accepts on the wire
_OFFSET_BOUNDS = {
    **dict.fromkeys(("n_m", "e_m", "d_m"), (FAULT_MAX_OFFSET_M, "m")),
    **dict.fromkeys(("n_mps", "e_mps", "d_mps"), (FAULT_MAX_OFFSET_MPS, "m/s")),
}


def check_fault(kind: str, target: str, params: Mapping[str, float], duration_s: float = 0.0) -> None:
    """Validate a command before it is sent (``hil fault``) or applied (the services)."""
    if not (math.isfinite(duration_s) and 0.0 <= duration_s <= MAX_DURATION_S):
        raise FaultError(
            f"duration must be in [0, {MAX_DURATION_S:g}] s (0: to the end / now), got {duration_s}"
        )
    if kind not in FAULT_KINDS:
        raise FaultError(f"unknown fault kind {kind!r}; known: {sorted(FAULT_KINDS)}")
    allowed = FAULT_KINDS[kind][1]
    unknown = sorted(set(params) - allowed)
    if unknown:
        raise FaultError(f"{kind}: unknown param(s) {unknown}; allowed: {sorted(allowed)}")
    if not all(np.isfinite(v) for v in params.values()):
        raise FaultError(f"{kind}: params must be finite numbers, got {dict(params)}")
    for name, v in params.items():
        if name in FAULT_INTEGER_PARAMS and not float(v).is_integer():
            raise FaultError(f"{kind}: {name} counts, so it must be a whole number, got {v:g}")
        bound, unit = _OFFSET_BOUNDS.get(name, (math.inf, ""))
        if abs(v) > bound:
            raise FaultError(f"{kind}: {name} must be in [-{bound:g}, {bound:g}] {unit}, got {v:g}")
    if kind == "clock_step" and target not in ("imu", "gnss"):
        raise FaultError("clock_step needs --target imu or --target gnss")
    if kind == "clock_step" and "step_s" not in params:
        raise FaultError("clock_step needs step_s")
    if kind == "clock_step" and not abs(params["step_s"]) <= MAX_CLOCK_STEP_S:
        raise FaultError(f"clock_step: |step_s| must be <= {MAX_CLOCK_STEP_S:g} s, got {params['step_s']:g}")
    if kind == "kill_service" and not target:
        raise FaultError("kill_service needs --target SERVICE")
    if not 0.0 <= params.get("percent", 100.0) <= 100.0:
        raise FaultError(f"{kind}: percent must be in [0, 100]")
    if kind == "gnss_spoof" and not params.get("sigma_m", 0.5) > 0:
        raise FaultError("gnss_spoof: sigma_m (the σ the spoofed fixes claim) must be > 0")
    if kind == "gnss_latency" and "latency_s" not in params:
        raise FaultError("gnss_latency needs latency_s")
    if kind == "gnss_latency" and min(params.get("latency_s", 0.0), params.get("jitter_s", 0.0)) < 0:
        raise FaultError(
            "gnss_latency: latency_s and jitter_s must be >= 0 (a fix cannot leave before it is valid)"
        )
    if kind == "can_burst_error" and not 1 <= params.get("frames", 8) <= MAX_BURST_FRAMES:
        raise FaultError(f"can_burst_error: frames must be in [1, {MAX_BURST_FRAMES}]")
    if kind == "gnss_line_burst" and (problem := line_burst_problem(params.get("bytes", 64))):
        raise FaultError(f"gnss_line_burst: {problem}")
    if kind == "can_latency":
        if "latency_s" not in params:
            raise FaultError("can_latency needs latency_s")
        problem = transport_delay_problem(params["latency_s"], params.get("jitter_s", 0.0))
        if problem:
            raise FaultError(f"can_latency: {problem}")


def command_addressee(cmd: Any, kinds: Iterable[str], sensor: str) -> tuple[bool, bool]:
    """Whether a run-time fault command is for the device of ``sensor`` (taking ``kinds``), and
    whether it is nobody's (an unknown kind, a ``clock_step`` for no sensor): a device counts a
    command nobody would take as rejected, so it never vanishes without a trace in some status."""
    mine = cmd.kind in kinds or (cmd.kind == "clock_step" and cmd.target == sensor)
    stray_step = cmd.kind == "clock_step" and cmd.target not in DEVICE_TIMED_KINDS
    nobodys = cmd.kind not in FAULT_KINDS or stray_step
    return mine, nobodys


def fault_detail(kind: str, t0_ns: int, t1_ns: int | None, params: Mapping[str, Any], origin: str) -> str:
    """The ``detail`` of a fault Event: JSON, so a report or a test can read it back."""
    return json.dumps(
        {
            "kind": kind,
            "origin": origin,
            "t_start_s": t0_ns / 1e9,
            "t_end_s": None if t1_ns is None else t1_ns / 1e9,
            "params": {k: _param_json(v) for k, v in params.items() if _param_json(v) is not None},
        },
        sort_keys=True,
    )


def _param_json(v: Any) -> Any:
    """A fault param as the event's JSON holds it: a number or a name, or a vector of numbers
    (``gnss_jump``'s ``offset_ned_m``: left out, the event said ``"params": {}`` and lost the
    offset); anything else (None) is left out."""
    if isinstance(v, int | float | str):
        return v
    if isinstance(v, list | tuple | np.ndarray) and all(
        isinstance(x, int | float | np.number) and not isinstance(x, bool) for x in v
    ):
        return [float(x) for x in v]
    return None


def _unit_hash(seed: int, k: int) -> float:
    """A uniform number in [0, 1) from (seed, k): splitmix64, so loss is order-free and replayable."""
    m = (1 << 64) - 1
    z = (seed * 0x9E3779B97F4A7C15 + k * 0xBF58476D1CE4E5B9 + 0x94D049BB133111EB) & m
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & m
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & m
    return ((z ^ (z >> 31)) >> 11) / float(1 << 53)


@dataclass
class Fault:
    """One fault window ``[t0_ns, t1_ns)`` (``t1_ns`` None: to the end)."""

    kind: str
    t0_ns: int
    t1_ns: int | None
    params: Mapping[str, Any]
    origin: str  # "scenario" | "command"
    started: bool = False
    ended: bool = False
    fired: bool = False  # a one-shot fault (can_burst_error) has been applied

    def active(self, t_ns: int) -> bool:
        return self.t0_ns <= t_ns and (self.t1_ns is None or t_ns < self.t1_ns)


@dataclass
class FaultTimeline:
    """Faults with start/end edges announced once each, as the run's time passes them."""

    faults: list[Fault] = field(default_factory=list)

    @classmethod
    def from_scenario(
        cls, events: Iterable[Any], kinds: frozenset[str], sensor: str | None = None
    ) -> FaultTimeline:
        """The scenario's ``[[event]]``s of ``kinds``; a ``clock_step`` only if it is ``sensor``'s."""
        out = cls()
        for ev in events:
            if ev.kind == "clock_step" and ev.params.get("sensor") != sensor:
                continue
            if ev.kind in kinds:
                t1 = None if ev.t_end_s is None else round(ev.t_end_s * 1e9)
                out.faults.append(Fault(ev.kind, round(ev.t_start_s * 1e9), t1, dict(ev.params), "scenario"))
        return out

    def add(self, kind: str, t0_ns: int, duration_s: float, params: Mapping[str, Any]) -> Fault:
        t1 = t0_ns + round(duration_s * 1e9) if duration_s > 0 else None
        f = Fault(kind, t0_ns, t1, dict(params), "command")
        self.faults.append(f)
        return f

    def next_edge_ns(self) -> int | None:
        """The earliest edge not yet said (a caller wakes then to announce it), or None."""
        times = [f.t0_ns for f in self.faults if not f.started]
        times += [f.t1_ns for f in self.faults if f.started and not f.ended and f.t1_ns is not None]
        return min(times) if times else None

    def edges(self, t_ns: int) -> list[tuple[str, Fault]]:
        """``("fault_start" | "fault_end", fault)`` for every edge at or before ``t_ns`` not yet said,
        in the order of their edge times (so events numbered in this order are also time-ordered)."""
        out: list[tuple[int, int, str, Fault]] = []
        for i, f in enumerate(self.faults):
            if not f.started and t_ns >= f.t0_ns:
                f.started = True
                out.append((f.t0_ns, i, "fault_start", f))
            if f.started and not f.ended and f.t1_ns is not None and t_ns >= f.t1_ns:
                f.ended = True
                out.append((f.t1_ns, i, "fault_end", f))
        out.sort(key=lambda e: (e[0], e[1]))
        return [(edge, f) for _t, _i, edge, f in out]


def device_timeline(events: Iterable[Any], sensor: str) -> FaultTimeline:
    """The timed faults the ``sensor``'s emulator announces as ``fault_start``/``fault_end``."""
    return FaultTimeline.from_scenario(events, DEVICE_TIMED_KINDS[sensor], sensor)


def edge_time_ns(edge: str, f: Fault) -> int:
    """When an edge happens: a fault's start, or its end."""
    return f.t0_ns if edge == "fault_start" or f.t1_ns is None else f.t1_ns


class FrameCorruptor:
    """``can_burst_error`` on the wire: the next ``n`` frames sent get one data byte flipped, so the
    receiver's E2E CRC rejects each of them (a burst of bit errors the controller did not catch).

    One object per transmitter, fed every frame that actually goes on the bus (a dropped sample's
    frames never reach the wire, so they do not use up the burst). Pure: no I/O, no clock.
    """

    def __init__(self) -> None:
        self.pending = 0
        self.corrupted = 0

    def arm(self, frames: int) -> None:
        self.pending += max(0, int(frames))

    def __call__(self, frame: Any) -> bool:
        """Corrupt ``frame`` (a ``can.Message``) in place if the burst is still going; True if so."""
        if self.pending <= 0:
            return False
        self.pending -= 1
        self.corrupted += 1
        self.flip(frame)
        return True

    @staticmethod
    def flip(frame: Any) -> None:
        """The corruption itself: one data byte flipped in place (the E2E CRC then fails)."""
        data = bytearray(frame.data)
        data[min(2, len(data) - 1)] ^= 0x5A
        frame.data = data


class DelayLine(Generic[T]):
    """``can_latency`` on the wire: a sample's frames leave ``latency + jitter·U`` after their
    capture (U uniform in [0, 1) from a seeded generator), never before the previous sample's.

    Why the max with the previous release: one CAN node's frames go through one transmit queue
    and the bus does not reorder them, so jitter delays a frame but cannot let it overtake an
    earlier one; a sample drawn early simply waits behind the one before it (its delay is then
    above ``latency + jitter``, never below ``latency``). Once the window ends (latency 0) the
    held frames drain in order and the next sample leaves at its capture again.

    Pure: no clock, no I/O. The caller says when it is (``due(now)``); the live emulator pushes
    each sample's frames and sends what is due, ``hil sim`` uses the same release times, so a
    scenario's delays are the same ones whichever executor runs it (same seed, same draws).
    """

    def __init__(self, rng: np.random.Generator) -> None:
        self.rng = rng
        self.last_release_ns = -(2**62)
        self._held: deque[tuple[int, T]] = deque()
        self.delayed = 0  # items pushed with a non-zero latency or jitter

    def release_ns(self, capture_ns: int, latency_ns: int, jitter_ns: int) -> int:
        """When an item captured at ``capture_ns`` leaves; draws from the generator only when
        ``jitter_ns`` > 0, so samples outside a jitter window never shift the stream."""
        extra = round(jitter_ns * float(self.rng.random())) if jitter_ns > 0 else 0
        if latency_ns or jitter_ns:
            self.delayed += 1
        t = max(self.last_release_ns, capture_ns + latency_ns + extra)
        self.last_release_ns = t
        return t

    def passes(self, capture_ns: int, latency_ns: int, jitter_ns: int) -> bool:
        """True (and accounted as a release at ``capture_ns``) when an item captured now with no
        latency leaves at once -- nothing held before it: the caller sends it without a push.
        The same release times as ``push`` + ``due(capture_ns)`` (no draw is made either way)."""
        if latency_ns or jitter_ns or self._held or self.last_release_ns > capture_ns:
            return False
        self.last_release_ns = capture_ns
        return True

    def push(self, capture_ns: int, latency_ns: int, jitter_ns: int, item: T) -> int:
        """Hold ``item`` until its release time (returned)."""
        t = self.release_ns(capture_ns, latency_ns, jitter_ns)
        self._held.append((t, item))
        return t

    def due(self, now_ns: int) -> list[T]:
        """The held items whose release time is at or before ``now_ns``, in order."""
        out: list[T] = []
        q = self._held
        while q and q[0][0] <= now_ns:
            out.append(q.popleft()[1])
        return out

    def next_release_ns(self) -> int | None:
        return self._held[0][0] if self._held else None

    def __len__(self) -> int:
        return len(self._held)


@dataclass
class ImuAction:
    """What to do with one IMU sample."""

    send: bool
    dtheta_b_rad: np.ndarray
    dvel_b_mps: np.ndarray
    corrupt_frames: int = 0  # corrupt this many of the next frames on the wire (CRC fails)
    reason: str = ""  # why not sent
    latency_ns: int = 0  # can_latency: hold the sample's frames this long after capture ...
    jitter_ns: int = 0  # ... plus up to this much more (DelayLine draws it)


class ImuFaults:
    """The IMU emulator's faults, applied per sample (index ``k``, true capture time ``t_ns``)."""

    def __init__(self, seed: int, events: Iterable[Any] = ()) -> None:
        self.seed = int(seed)
        self.timeline = device_timeline(events, "imu")
        self._stuck: tuple[np.ndarray, np.ndarray] | None = None
        self._last: tuple[np.ndarray, np.ndarray] | None = None

    def apply(self, k: int, t_ns: int, dtheta: np.ndarray, dvel: np.ndarray) -> ImuAction:
        act = ImuAction(True, dtheta, dvel)
        stuck = False
        for f in self.timeline.faults:
            if not f.active(t_ns):
                continue
            if f.kind == "can_bus_off":
                act.send, act.reason = False, "bus_off"
            elif f.kind == "imu_frame_loss":
                if _unit_hash(self.seed, k) < float(f.params.get("percent", 100.0)) / 100.0:
                    act.send, act.reason = False, "frame_loss"
            elif f.kind == "imu_stuck":
                stuck = True
            elif f.kind == "imu_saturated":
                # beyond full scale on every axis (keeping the sign): the codec clamps and flags
                act.dtheta_b_rad = np.where(dtheta >= 0, 1.0, -1.0) * SATURATE_DTHETA_RAD
                act.dvel_b_mps = np.where(dvel >= 0, 1.0, -1.0) * SATURATE_DVEL_MPS
            elif f.kind == "can_latency":  # overlapping windows add up
                act.latency_ns += round(float(f.params.get("latency_s", 0.0)) * 1e9)
                act.jitter_ns += round(float(f.params.get("jitter_s", 0.0)) * 1e9)
            elif f.kind == "can_burst_error" and not f.fired:
                act.corrupt_frames += int(f.params.get("frames", 8))
                f.fired = True
        if stuck:
            if self._stuck is None:
                self._stuck = self._last if self._last is not None else (dtheta, dvel)
            act.dtheta_b_rad, act.dvel_b_mps = self._stuck
        else:
            self._stuck = None
            self._last = (dtheta, dvel)
        return act


# -- the GNSS receiver's line ----------------------------------------------------------------
#: faults of the receiver's serial line (``gnss_emulator`` with a wire): what each does to an epoch
LINE_FAULTS = frozenset(
    {"gnss_line_checksum", "gnss_line_truncate", "gnss_line_garble", "gnss_line_dropout", "gnss_line_burst"}
)
RECEIVER_FAULTS = frozenset({"gnss_time_jump", "gnss_frozen"})
# each kind's own stream of decisions (a fixed salt: Python's str hash differs per process)
_CORRUPT_SALT = {"gnss_line_checksum": 101, "gnss_line_truncate": 202, "gnss_line_garble": 303}


@dataclass
class LineAction:
    """What to do to one epoch on the wire (decided by :meth:`LineFaults.epoch`)."""

    send: bool = True  # gnss_line_dropout: nothing on the line
    time_step_ns: int = 0  # gnss_time_jump: the reported time of validity is off by this much
    frozen: bool = False  # gnss_frozen: the receiver repeats its last position and velocity
    corrupt: str = ""  # "checksum" | "truncate" | "garble": done to the epoch's bytes
    burst_bytes: int = 0  # gnss_line_burst: this many garbage bytes go out before the epoch


class LineFaults:
    """The receiver-line faults, per epoch ``k`` at true time ``t_ns``: pure and seeded, so a
    replay of the scenario damages the same epochs the same way (``hil.faults._unit_hash``)."""

    def __init__(self, seed: int, events: Iterable[Any] = ()) -> None:
        self.seed = int(seed)
        self.timeline = FaultTimeline.from_scenario(events, LINE_FAULTS | RECEIVER_FAULTS)

    def epoch(self, k: int, t_ns: int) -> LineAction:
        act = LineAction()
        for f in self.timeline.faults:
            if not f.active(t_ns):
                continue
            p = f.params
            if f.kind == "gnss_line_dropout":
                act.send = False
            elif f.kind == "gnss_time_jump":
                act.time_step_ns += round(float(p.get("step_s", 1.0)) * 1e9)
            elif f.kind == "gnss_frozen":
                act.frozen = True
            elif f.kind == "gnss_line_burst" and not f.fired:
                act.burst_bytes += int(p.get("bytes", 64))
                f.fired = True
            elif (
                f.kind in _CORRUPT_SALT
                and _unit_hash(self.seed + _CORRUPT_SALT[f.kind], k) < float(p.get("percent", 100.0)) / 100.0
            ):
                act.corrupt = f.kind.rsplit("_", 1)[1]
        return act

    def damage(self, data: bytes, act: LineAction, k: int) -> bytes:
        """The epoch's bytes as ``act`` leaves them (a burst of garbage first, if any)."""
        out = bytearray(data)
        u = _unit_hash(self.seed + 7, k)
        if act.corrupt == "checksum" and out:
            # the last checksum of the epoch: NMEA's "*hh" hex digit, UBX's final byte
            star = out.rfind(b"*")
            i = star + 1 if star >= 0 and star + 1 < len(out) else len(out) - 1
            out[i] = ord("0") if out[i] != ord("0") else ord("1")
        elif act.corrupt == "truncate" and len(out) > 8:
            out = out[: max(4, int(len(out) * (0.2 + 0.6 * u)))]
        elif act.corrupt == "garble":
            for j in range(max(1, len(out) // 50)):
                i = int(_unit_hash(self.seed + 11 + j, k) * len(out))
                out[i] ^= 0x5A
        if act.burst_bytes:
            noise = bytes(int(_unit_hash(self.seed + 13 + j, k) * 256) for j in range(act.burst_bytes))
            out = bytearray(noise) + out
        return bytes(out)


def unwired_line_fault_warnings(events: Iterable[Any], duration_s: float, command: str) -> list[str]:
    """Warning lines for the scenario's line faults (``gnss_line_*``) a receiver on no wire cannot
    apply: ``command`` (hil sim, hil up) prints them, the emulator records ``fault_ignored``
    where each would have started (it once announced them as applied)."""
    return [
        f"{ev.kind} at t={ev.t_start_s:g} s is not applied: the GNSS receiver is on no wire "
        f"({command} --gnss-protocol nmea or ubx puts it on one; recorded as event fault_ignored)"
        for ev in events
        if ev.kind in LINE_FAULTS and ev.t_start_s <= duration_s
    ]

"""Device clocks: how a sensor's own clock reads true time, and how its data reaches the rig.

Three timelines (docs/architecture.md): *true* time (the scenario's), *device* time (each
sensor's own oscillator) and *rig* time (the fusion computer's). In this rig the rig clock is the
reference the emulators pace on, so rig time == true time and a re-stamped measurement's error is
simply ``rig stamp - true capture time``.

A device stamp of the true instant ``t`` (ns)::

    device(t) = floor_q( t + offset + drift·t + wander(t) + Σ steps(t_k <= t) + jitter(t) )

- ``offset_s``: device time at true zero (a device powered up before the run);
- ``drift_ppm``: oscillator frequency error, device runs fast by that many parts per million;
- ``drift_rw_ppm_per_sqrt_s``: random walk of that frequency (knots every second, integrated),
  so a constant-drift fit is not exactly right over long windows;
- ``jitter_s``: white stamp jitter, 1σ Gaussian, a pure function of the true instant (a hash of
  it), so the sync edge and the sample captured at the same instant carry the same stamp, and
  a stamp does not depend on the order the emulator asks for them;
- ``quantum_s``: the device counter's tick (stamps are floored to it);
- ``steps``: clock steps (a device reset, a re-sync) ``{t_s, step_s}``.

Time tags: ``latch_jitter_s`` is the rig-side latch jitter of the tag edge, 1σ (the GNSS PPS is
latched on the rig clock; the IMU's sync frame by the kernel's receive stamp, a few µs, as
python-can#1881 measures with ``candump -H``), independent of the data path's jitter;
``tag_latency_s`` is the calibrated edge -> latch delay the synchronisation compensates (for the
IMU: the sync frame's wire time plus the bus latency).
Transport (modelled by ``hil sim``; live it is the real bus): ``transport_latency_s`` plus an
exponential extra delay of mean ``transport_jitter_s`` per CAN burst; ``min_delay_s`` is the
known minimum measurement -> arrival delay that the arrival-only estimator adds back (what
PX4 calls ``EKF2_GPS_DELAY`` for a receiver). ``timetag = false`` tells timesync to ignore the
sensor's time tags and synchronise from arrival times alone; ``sync = "off"`` keeps raw arrival
stamps (the no-synchronisation baseline).

All of it comes from the scenario's ``[clock.<sensor>]`` table (reserved in
``hil.nav.scenario``); absent keys take the modest defaults of :data:`DEFAULT_CLOCKS`.
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from dataclasses import dataclass, field, replace
from functools import cache
from typing import TYPE_CHECKING, Any

from hil.nav.scenario import MAX_CLOCK_STEP_S, Scenario, ScenarioError
from hil.sensor_table import SENSORS

if TYPE_CHECKING:  # numpy is imported where a clock is drawn: the time-sync rerun reads only the configs
    import numpy as np

_M64 = (1 << 64) - 1


@dataclass(frozen=True)
class ClockStep:
    """The device clock jumps by ``step_s`` at true time ``t_s`` (a reset or a re-sync)."""

    t_s: float
    step_s: float


@dataclass(frozen=True)
class DeviceClockConfig:
    """One sensor's clock, time-tag and transport parameters (SI units, see module docstring)."""

    offset_s: float = 0.0
    drift_ppm: float = 0.0
    drift_rw_ppm_per_sqrt_s: float = 0.0
    jitter_s: float = 0.0
    quantum_s: float = 0.0
    steps: tuple[ClockStep, ...] = ()
    timetag: bool = True
    sync: str = ""  # "timetag" | "arrival" | "off"; empty: "timetag" if timetag else "arrival"
    latch_jitter_s: float = 0.0
    tag_latency_s: float | None = None  # None: derived from the transport (see resolved())
    transport_latency_s: float = 0.0
    transport_jitter_s: float = 0.0
    min_delay_s: float | None = None  # None: derived (IMU: frames' wire time; GNSS: its latency)

    @property
    def is_ideal(self) -> bool:
        return not (
            self.offset_s or self.drift_ppm or self.drift_rw_ppm_per_sqrt_s or self.jitter_s
        ) and not (self.quantum_s or self.steps)


#: Each sensor's defaults, from the sensor table (``hil.sensor_table``: why they are what they are).
DEFAULT_CLOCKS: Mapping[str, DeviceClockConfig] = {
    name: DeviceClockConfig(**kind.clock) for name, kind in SENSORS.items()
}

_KEYS = {
    "offset_s",
    "drift_ppm",
    "drift_rw_ppm_per_sqrt_s",
    "jitter_s",
    "quantum_s",
    "steps",
    "timetag",
    "sync",
    "latch_jitter_s",
    "tag_latency_s",
    "transport_latency_s",
    "transport_jitter_s",
    "min_delay_s",
}


def _num(where: str, v: Any, lo: float | None = None) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ScenarioError(f"{where} must be a finite number, got {v!r}")
    if lo is not None and v < lo:
        raise ScenarioError(f"{where} must be >= {lo}, got {v!r}")
    return float(v)


def _step_s(where: str, v: Any) -> float:
    step = _num(where, v)
    if not abs(step) <= MAX_CLOCK_STEP_S:
        raise ScenarioError(
            f"{where} must be in [-{MAX_CLOCK_STEP_S:g}, {MAX_CLOCK_STEP_S:g}] s, got {step:g}"
        )
    return step


def parse_clock_table(sensor: str, table: Mapping[str, Any], base: DeviceClockConfig) -> DeviceClockConfig:
    """``[clock.<sensor>]`` over ``base``; raises ScenarioError naming the key and the value."""
    where = f"clock.{sensor}"
    unknown = set(table) - _KEYS
    if unknown:
        raise ScenarioError(f"{where}: unknown key(s) {sorted(unknown)}; allowed: {sorted(_KEYS)}")
    kw: dict[str, Any] = {}
    for k, v in table.items():
        if k == "timetag":
            if not isinstance(v, bool):
                raise ScenarioError(f"{where}.timetag must be true or false, got {v!r}")
            kw[k] = v
        elif k == "sync":
            if v not in ("timetag", "arrival", "off"):
                raise ScenarioError(f'{where}.sync must be "timetag", "arrival" or "off", got {v!r}')
            kw[k] = v
        elif k == "steps":
            if not isinstance(v, list) or not all(isinstance(s, Mapping) for s in v):
                raise ScenarioError(f"{where}.steps must be an array of {{t_s, step_s}} tables")
            steps = []
            for i, s in enumerate(v):
                if set(s) != {"t_s", "step_s"}:
                    raise ScenarioError(f"{where}.steps[{i}] needs exactly t_s and step_s, got {sorted(s)}")
                steps.append(
                    ClockStep(
                        _num(f"{where}.steps[{i}].t_s", s["t_s"], 0.0),
                        _step_s(f"{where}.steps[{i}].step_s", s["step_s"]),
                    )
                )
            kw[k] = tuple(sorted(steps, key=lambda s: s.t_s))
        elif k in ("offset_s", "drift_ppm"):
            kw[k] = _num(f"{where}.{k}", v)
        else:
            kw[k] = _num(f"{where}.{k}", v, 0.0)
    cfg = replace(base, **kw)
    if abs(cfg.drift_ppm) > 1000:
        raise ScenarioError(f"{where}.drift_ppm={cfg.drift_ppm} is beyond any oscillator (|x| <= 1000)")
    # Device time is sent as unsigned ns (the IMU's DBC): it must never go below zero.
    level = cfg.offset_s
    for s in cfg.steps:
        level += s.step_s
        if s.t_s + level < 0:
            raise ScenarioError(f"{where}: step at t_s={s.t_s} takes device time below zero")
    return cfg


def clock_config_for(scenario: Scenario, sensor: str, *, imu_can_fd: bool = False) -> DeviceClockConfig:
    """The resolved clock config of ``sensor``: defaults, then ``[clock.<sensor>]``, then derived
    latencies (``tag_latency_s``, ``min_delay_s``: the IMU's from its frames, one on CAN FD)
    filled in."""
    tables = scenario.extra_tables.get("clock", {})
    if not isinstance(tables, Mapping):
        raise ScenarioError("[clock] must be a table of [clock.<sensor>] tables")
    raw = tables.get(sensor, {})
    if not isinstance(raw, Mapping):
        raise ScenarioError(f"clock.{sensor} must be a table")
    cfg = parse_clock_table(sensor, raw, DEFAULT_CLOCKS.get(sensor, DeviceClockConfig()))
    kind = SENSORS.get(sensor)
    if cfg.tag_latency_s is None:
        cfg = replace(cfg, tag_latency_s=kind.tag_latency_s(cfg, scenario) if kind else 0.0)
    if cfg.min_delay_s is None:
        md = kind.min_delay_s(cfg, scenario, imu_can_fd) if kind else float(cfg.transport_latency_s)
        cfg = replace(cfg, min_delay_s=md)
    return cfg


# ---------------------------------------------------------------------------------------------
# the clock itself


def _mix64(z: int) -> int:
    """splitmix64 finaliser: a well-mixed 64-bit hash of ``z`` (the jitter is a function of time)."""
    z = (z + 0x9E3779B97F4A7C15) & _M64
    z = ((z ^ (z >> 30)) * 0xBF58476D1CE4E5B9) & _M64
    z = ((z ^ (z >> 27)) * 0x94D049BB133111EB) & _M64
    return z ^ (z >> 31)


def _gauss_of(key: int, t_ns: int) -> float:
    """A standard normal draw that depends only on (key, t_ns): Box-Muller on two hashes."""
    h1 = _mix64((key ^ (t_ns & _M64)) & _M64)
    h2 = _mix64(h1)
    u1 = ((h1 >> 11) + 0.5) * 2.0**-53
    u2 = (h2 >> 11) * 2.0**-53
    return math.sqrt(-2.0 * math.log(u1)) * math.cos(2.0 * math.pi * u2)


def _mix64_array(z: np.ndarray) -> np.ndarray:
    import numpy as np

    with np.errstate(over="ignore"):
        z = z + np.uint64(0x9E3779B97F4A7C15)
        z = (z ^ (z >> np.uint64(30))) * np.uint64(0xBF58476D1CE4E5B9)
        z = (z ^ (z >> np.uint64(27))) * np.uint64(0x94D049BB133111EB)
    return z ^ (z >> np.uint64(31))


@cache
def _log_ufunc() -> np.ufunc:
    import numpy as np

    return np.frompyfunc(math.log, 1, 1)


@cache
def _cos_ufunc() -> np.ufunc:
    import numpy as np

    return np.frompyfunc(math.cos, 1, 1)


def _gauss_array(key: int, t_ns: np.ndarray) -> np.ndarray:
    import numpy as np

    h1 = _mix64_array(np.uint64(key) ^ t_ns.astype(np.int64).view(np.uint64))
    h2 = _mix64_array(h1)
    u1 = ((h1 >> np.uint64(11)).astype(np.float64) + 0.5) * 2.0**-53
    u2 = (h2 >> np.uint64(11)).astype(np.float64) * 2.0**-53
    # math.log and math.cos elementwise: numpy's are SIMD-dispatched per CPU (their last bit can
    # differ from libm's), and this must equal _gauss_of on every machine: hil sim stamps with it
    cos = np.asarray(_cos_ufunc()(2.0 * math.pi * u2), dtype=float)
    return np.sqrt(-2.0 * np.asarray(_log_ufunc()(u1), dtype=float)) * cos


@dataclass
class DeviceClock:
    """A device clock as a pure function of true time (plus lazily drawn, seeded wander knots).

    ``rng`` is used only at construction and for the wander knots, drawn in knot order, so the
    clock reads the same whatever order (or batch size) the emulator asks in.
    """

    cfg: DeviceClockConfig
    rng: np.random.Generator
    _knots_ppm: np.ndarray = field(init=False, repr=False)  # wander of interval [k, k+1) s
    _cum_ppm_s: np.ndarray = field(init=False, repr=False)  # ∫ wander up to k s
    _key_stamp: int = field(init=False, repr=False)
    _key_latch: int = field(init=False, repr=False)
    revision: int = field(default=0, init=False)  # steps added: stamps computed ahead are stale

    def __post_init__(self) -> None:
        import numpy as np

        keys = self.rng.integers(0, 2**63, size=2, dtype=np.int64)
        self._key_stamp, self._key_latch = int(keys[0]), int(keys[1])
        self._knots_ppm = np.zeros(1)
        self._cum_ppm_s = np.zeros(1)
        self._offset_ns = round(self.cfg.offset_s * 1e9)
        self._q_ns = max(1, round(self.cfg.quantum_s * 1e9))
        self._steps = [(round(s.t_s * 1e9), round(s.step_s * 1e9)) for s in self.cfg.steps]

    def _extend(self, k_max: int) -> None:
        """Draw wander knots up to second ``k_max`` (chunks of 1024, always in knot order)."""
        n = len(self._knots_ppm)
        if k_max < n:
            return
        import numpy as np

        m = ((k_max - n) // 1024 + 1) * 1024
        rw = self.cfg.drift_rw_ppm_per_sqrt_s
        inc = self.rng.standard_normal(m) * rw if rw else np.zeros(m)
        knots = self._knots_ppm[-1] + np.cumsum(inc)
        cum = self._cum_ppm_s[-1] + self._knots_ppm[-1] + np.concatenate(([0.0], np.cumsum(knots[:-1])))
        self._knots_ppm = np.concatenate((self._knots_ppm, knots))
        self._cum_ppm_s = np.concatenate((self._cum_ppm_s, cum))

    def _wander_ns(self, true_ns: int) -> float:
        if not self.cfg.drift_rw_ppm_per_sqrt_s:
            return 0.0
        t_s = max(0.0, true_ns * 1e-9)
        k = int(t_s)
        self._extend(k)
        # ppm·s = µs
        return 1e3 * (float(self._cum_ppm_s[k]) + float(self._knots_ppm[k]) * (t_s - k))

    def device_ns(self, true_ns: int) -> int:
        """The device stamp of true instant ``true_ns``."""
        t = int(true_ns)
        frac = self.cfg.drift_ppm * 1e-6 * t + self._wander_ns(t)
        if self.cfg.jitter_s:
            frac += self.cfg.jitter_s * 1e9 * _gauss_of(self._key_stamp, t)
        dev = t + self._offset_ns + math.floor(frac + 1e-6)  # 1e-6: float fuzz, not a tick
        for t_k, step in self._steps:
            if t >= t_k:
                dev += step
        return (dev // self._q_ns) * self._q_ns

    def counter(self, true_ns: int) -> tuple[int, float]:
        """What the device's counter reads at true instant ``true_ns`` (no stamp jitter, not yet
        floored to its tick) and how fast it runs there (device ns per true ns): enough to say
        what it reads a few ms later -- a time-tag frame that leaves late states when it left."""
        t = int(true_ns)
        dev = t + self._offset_ns + math.floor(self.cfg.drift_ppm * 1e-6 * t + self._wander_ns(t))
        for t_k, step in self._steps:
            if t >= t_k:
                dev += step
        rate_ppm = self.cfg.drift_ppm
        if self.cfg.drift_rw_ppm_per_sqrt_s:
            rate_ppm += float(self._knots_ppm[int(max(0.0, t * 1e-9))])
        return dev, 1.0 + rate_ppm * 1e-6

    @property
    def quantum_ns(self) -> int:
        """The device counter's tick (stamps are floored to it)."""
        return self._q_ns

    def device_ns_array(self, true_ns: np.ndarray) -> np.ndarray:
        """Vectorised :meth:`device_ns` (identical results): the IMU emulator's stamps a block
        ahead (stale once ``revision`` moves), benches and tests."""
        import numpy as np

        t = np.asarray(true_ns, dtype=np.int64)
        frac = self.cfg.drift_ppm * 1e-6 * t.astype(np.float64)
        if self.cfg.drift_rw_ppm_per_sqrt_s and len(t):
            t_s = np.maximum(0.0, t * 1e-9)
            k = t_s.astype(np.int64)
            self._extend(int(k.max()))
            frac = frac + 1e3 * (self._cum_ppm_s[k] + self._knots_ppm[k] * (t_s - k))
        if self.cfg.jitter_s:
            frac = frac + self.cfg.jitter_s * 1e9 * _gauss_array(self._key_stamp, t)
        dev = t + self._offset_ns + np.floor(frac + 1e-6).astype(np.int64)
        for t_k, step in self._steps:
            dev = dev + np.where(t >= t_k, step, 0)
        return (dev // self._q_ns) * self._q_ns

    def add_step(self, t_ns: int, step_ns: int) -> None:
        """A clock step from now on (a commanded ``clock_step`` fault)."""
        self._steps = sorted([*self._steps, (int(t_ns), int(step_ns))])
        self.revision += 1

    def latch_ns(self, true_ns: int) -> int:
        """The rig clock's latch of a time-tag edge at true instant ``true_ns`` (latch jitter)."""
        t = int(true_ns)
        if not self.cfg.latch_jitter_s:
            return t
        return t + round(self.cfg.latch_jitter_s * 1e9 * _gauss_of(self._key_latch, t))


def device_clock_for(scenario: Scenario, sensor: str) -> DeviceClock:
    """The clock model of ``sensor`` in ``scenario`` (defaults + ``[clock.<sensor>]``), seeded
    from the scenario seed and ``"<sensor>.clock"`` so each device has its own stream."""
    from hil.sensors.imu import sensor_rng

    cfg = clock_config_for(scenario, sensor)
    # timed ``clock_step`` events ([[event]], hil/faults.py) are steps like [clock.<sensor>] steps
    extra = [
        ClockStep(float(ev.t_start_s), float(ev.params["step_s"]))
        for ev in scenario.events
        if ev.kind == "clock_step" and ev.params.get("sensor") == sensor
    ]
    if extra:
        cfg = replace(cfg, steps=tuple(sorted([*cfg.steps, *extra], key=lambda s: s.t_s)))
    return DeviceClock(cfg, sensor_rng(scenario.seed, f"{sensor}.clock"))

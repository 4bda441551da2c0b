"""Scenarios: the declarative TOML that says where, how the vehicle moves, with which sensors,
and which faults happen when. The file format is documented in ``docs/scenario-format.md``.

A :class:`Scenario` is frozen and carries the exact text it came from (``source_text``, with its
``sha256``) so a recording can embed it and a replay rebuilds the very same truth and noise.
:func:`scenario_overrides` re-emits the text with the overrides applied, so that stays true.

Errors: :class:`ScenarioError` (a ``ValueError``) for anything the file says that cannot be used;
its message names the key and the value.
"""

from __future__ import annotations

import hashlib
import math
import tomllib
from collections.abc import Mapping
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from importlib import resources
from pathlib import Path
from types import MappingProxyType
from typing import Any

from hil.nav.limits import MAX_DURATION_S, MAX_GNSS_SIGMA
from hil.nav.sensor_specs import ImuParams, SpecError, resolve_imu_params
from hil.sensor_table import SENSORS

Vec3 = tuple[float, float, float]

#: Top-level tables reserved for other parts of the rig: parsed as TOML, kept raw in
#: ``Scenario.extra_tables``, not interpreted here -- the device clocks, and the section of every
#: sensor of the sensor table other than the two parsed here (its emulator reads it). Any other
#: unknown key is an error.
RESERVED_TABLES = frozenset({"clock", *(set(SENSORS) - {"imu", "gnss"})})
SEGMENT_KINDS = ("hold", "accelerate", "turn", "coordinated_turn", "climb", "rates")
DEFAULT_SCENARIO = "straight_level"


class ScenarioError(ValueError):
    """A scenario file that cannot be used; the message says which key and why."""


@dataclass(frozen=True)
class ImuConfig:
    """IMU rate and error model: the preset, the user's overrides (user units) and the SI result."""

    rate_hz: int
    preset: str
    overrides: Mapping[str, Any]
    params: ImuParams


@dataclass(frozen=True)
class GnssConfig:
    """GNSS receiver model. Sigmas are 1σ of the white component, per NED axis."""

    rate_hz: float = 1.0
    pos_sigma_m: Vec3 = (20.0, 20.0, 20.0)
    vel_sigma_mps: Vec3 = (0.2, 0.2, 0.2)
    latency_s: float = 0.0  # output time − time of validity, before jitter
    jitter_s: float = 0.0  # extra latency, uniform in [0, jitter_s)
    slow_amplitude_m: Vec3 = (0.0, 0.0, 0.0)  # slow (geometry) error amplitude per axis
    slow_period_s: float = 2.5 * 5064.0  # 2–3 Schuler periods
    lever_arm_b_m: Vec3 = (0.0, 0.0, 0.0)  # antenna position in body axes from the IMU
    num_sats: int = 10
    hdop: float = 0.9


@dataclass(frozen=True)
class ScenarioEvent:
    """A timed fault. ``t_end_s`` None means from ``t_start_s`` to the end of the run."""

    kind: str
    t_start_s: float
    t_end_s: float | None
    params: Mapping[str, Any]

    def active(self, t_s: float) -> bool:
        return self.t_start_s <= t_s and (self.t_end_s is None or t_s < self.t_end_s)


@dataclass(frozen=True)
class MotionSegment:
    """One entry of the motion profile as written (``kind`` + its parameters, user units)."""

    kind: str
    params: Mapping[str, Any]


@dataclass(frozen=True)
class Scenario:
    name: str
    seed: int
    duration_s: float
    origin_lat_deg: float
    origin_lon_deg: float
    origin_alt_m: float
    imu: ImuConfig
    gnss: GnssConfig
    events: tuple[ScenarioEvent, ...]
    source_text: str
    sha256: str
    # appended fields (defaults keep the constructor compatible)
    description: str = ""
    initial_euler_deg: Vec3 = (0.0, 0.0, 0.0)  # roll, pitch, yaw
    initial_vel_body_mps: Vec3 = (0.0, 0.0, 0.0)
    segments: tuple[MotionSegment, ...] = ()
    extra_tables: Mapping[str, Any] = field(default_factory=lambda: MappingProxyType({}))
    start_utc_ns: int = 0  # the UTC instant (ns since 1970) hil sim takes as time zero (start_utc)


#: ``hil sim``'s time zero unless the scenario says ``start_utc``: a date a receiver's clock can
#: print (GPS time, week and leap seconds all well defined), not 1970.
DEFAULT_START_UTC = "2026-01-01T00:00:00Z"


def _utc_ns(where: str, text: Any) -> int:
    """An RFC 3339 UTC instant (``2026-01-01T00:00:00Z``) as integer ns since 1970."""
    if not isinstance(text, str):
        raise ScenarioError(f'{where} must be a UTC time like "2026-01-01T12:00:00Z", got {text!r}')
    try:
        t = datetime.fromisoformat(text.replace("Z", "+00:00"))
    except ValueError as err:
        raise ScenarioError(f'{where} must be a UTC time like "2026-01-01T12:00:00Z": {err}') from None
    if t.tzinfo is None or t.utcoffset() != timedelta(0):
        raise ScenarioError(f"{where} must be UTC (end it with Z), got {text!r}")
    if not 1981 <= t.year <= 2100:
        raise ScenarioError(f"{where} must be between 1981 and 2100 (GPS time), got {text!r}")
    return (int(t.timestamp()) * 1_000_000_000) + t.microsecond * 1000


# ---------------------------------------------------------------------------------------------
# parsing


# |clock step|: a day. The IMU's wire carries device time modulo 2^48 ns (~78 h), unwrapped by the
# nearest-epoch rule, so a step near half that (~39 h) or beyond reads as a wrap and lands anywhere
# (1e9 s left the fusion ~80 600 s in the future); a reset after a day's uptime fits. The one
# bound of a clock_step event, a [clock.<sensor>] step and a hil fault clock_step.
MAX_CLOCK_STEP_S = 86_400.0


def _num(where: str, v: Any) -> float:
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise ScenarioError(f"{where} must be a finite number, got {v!r}")
    return float(v)


def _within(where: str, v: float, lo: float, hi: float) -> float:
    """``v`` if ``lo <= v <= hi``; else the one line naming the key and the range."""
    if not lo <= v <= hi:
        raise ScenarioError(f"{where} must be in [{lo:g}, {hi:g}], got {v:g}")
    return v


def _gnss_sigma(where: str, v: float) -> float:
    """A σ a GNSS fix will claim: the fusion takes a fix only with every σ in (0, MAX_GNSS_SIGMA)."""
    if not 0.0 < v < MAX_GNSS_SIGMA:
        raise ScenarioError(
            f"{where} must be > 0 and < {MAX_GNSS_SIGMA:g}, got {v:g} (the fusion refuses a fix "
            "claiming it as implausible)"
        )
    return v


def _vec3(where: str, v: Any) -> Vec3:
    if isinstance(v, int | float) and not isinstance(v, bool):
        x = _num(where, v)
        return (x, x, x)
    if not isinstance(v, list) or len(v) != 3:
        raise ScenarioError(f"{where} must be a number or a list of 3 numbers, got {v!r}")
    return (_num(where, v[0]), _num(where, v[1]), _num(where, v[2]))


def _check_keys(where: str, table: Mapping[str, Any], allowed: set[str]) -> None:
    unknown = sorted(set(table) - allowed)
    if unknown:
        raise ScenarioError(f"{where}: unknown key(s) {unknown}; allowed: {sorted(allowed)}")


_TOP_KEYS = {
    "name",
    "description",
    "seed",
    "duration_s",
    "origin",
    "initial",
    "imu",
    "gnss",
    "segment",
    "event",
    "start_utc",
}
_GNSS_KEYS = {
    "rate_hz",
    "pos_sigma_m",
    "vel_sigma_mps",
    "latency_s",
    "jitter_s",
    "slow_amplitude_m",
    "slow_period_s",
    "lever_arm_b_m",
    "num_sats",
    "hdop",
}
_SEGMENT_KEYS: dict[str, set[str]] = {
    "hold": {"duration_s"},
    "accelerate": {"duration_s", "accel_mps2", "to_speed_mps"},
    "turn": {"duration_s", "angle_deg", "yaw_rate_dps", "transition_s"},
    "coordinated_turn": {"duration_s", "angle_deg", "yaw_rate_dps", "roll_rate_dps"},
    "climb": {"duration_s", "pitch_deg", "pitch_rate_dps"},
    "rates": {"duration_s", "euler_rate_dps", "accel_body_mps2"},
}
# Timed faults: each sensor's emulator applies its own (hil/sensor_table.py); the device clocks
# take clock_step, the supervisor kill_service (hil/faults.py).
_EVENT_KEYS: dict[str, set[str]] = {
    **{kind: set(keys) for s in SENSORS.values() for kind, keys in s.events.items()},
    "clock_step": {"sensor", "step_s"},
    "kill_service": {"service"},
}
EVENT_KINDS = tuple(_EVENT_KEYS)
# the kinds _parse_event reads field by field; the others take numbers (hil/faults.py applies them)
_PARSED_KINDS = frozenset(
    {"gnss_outage", "gnss_jump", "gnss_pulse", "gnss_velocity_glitch", "gnss_latency", "imu_frame_loss"}
    | {"gnss_spoof"}
    | {"imu_stuck", "imu_saturated", "can_burst_error", "can_bus_off", "can_latency", "clock_step"}
    | {"kill_service"}
)
DEFAULT_SPOOF_SIGMA_M = 0.5  # what a gnss_spoof's fixes claim unless told: better than any receiver
# can_latency: beyond this a "latency" is an outage (and 10 s of held frames at 2 kHz is already
# 80 000 frames in the emulator's memory); refused rather than silently buffered
MAX_TRANSPORT_DELAY_S = 10.0


# gnss_line_burst: 64 KiB is over a second of a 460800-baud line (and 16 times the UART's default
# transmit buffer); the burst is built byte by byte, so a huge one hung the emulator
MAX_LINE_BURST_BYTES = 65_536


def line_burst_problem(n: float) -> str | None:
    """Why a ``gnss_line_burst`` of ``n`` bytes cannot be applied, or None; shared by the scenario
    loader and ``hil.faults.check_fault`` (one bound, the same words)."""
    if n != int(n) or not 1 <= n <= MAX_LINE_BURST_BYTES:
        return f"bytes must be a whole number in [1, {MAX_LINE_BURST_BYTES}], got {n:g}"
    return None


def transport_delay_problem(latency_s: float, jitter_s: float) -> str | None:
    """Why a ``can_latency`` (latency, jitter) pair cannot be applied, or None; shared by the
    scenario loader and ``hil.faults.check_fault`` so both refuse the same values with the same
    words."""
    if latency_s < 0 or jitter_s < 0:
        return (
            "latency_s and jitter_s must be >= 0 (a frame cannot leave before its capture), "
            f"got {latency_s}, {jitter_s}"
        )
    if latency_s + jitter_s > MAX_TRANSPORT_DELAY_S:
        return (
            f"latency_s + jitter_s must be <= {MAX_TRANSPORT_DELAY_S:g} s (longer is an outage: use "
            f"can_bus_off), got {latency_s + jitter_s:g} s"
        )
    return None


def _parse_segment(i: int, raw: Mapping[str, Any]) -> MotionSegment:
    where = f"segment[{i}]"
    kind = raw.get("kind")
    if kind not in _SEGMENT_KEYS:
        raise ScenarioError(f"{where}.kind must be one of {SEGMENT_KINDS}, got {kind!r}")
    _check_keys(where, raw, _SEGMENT_KEYS[kind] | {"kind"})
    params: dict[str, Any] = {}
    for k, v in raw.items():
        if k == "kind":
            continue
        params[k] = (
            _vec3(f"{where}.{k}", v)
            if k in ("euler_rate_dps", "accel_body_mps2")
            else (_num(f"{where}.{k}", v))
        )
    if "duration_s" in params:
        _within(f"{where}.duration_s", params["duration_s"], 0.0, MAX_DURATION_S)
    need_one = {
        "turn": ("duration_s", "angle_deg"),
        "coordinated_turn": ("duration_s", "angle_deg"),
        "accelerate": ("duration_s", "to_speed_mps"),
    }
    if kind in need_one and sum(k in params for k in need_one[kind]) != 1:
        raise ScenarioError(f"{where} ({kind}) needs exactly one of {need_one[kind]}")
    if kind in ("hold", "climb", "rates") and "duration_s" not in params:
        raise ScenarioError(f"{where} ({kind}) needs duration_s")
    if kind in ("turn", "coordinated_turn") and "yaw_rate_dps" not in params:
        raise ScenarioError(f"{where} ({kind}) needs yaw_rate_dps")
    if kind == "accelerate" and "accel_mps2" not in params:
        raise ScenarioError(f"{where} (accelerate) needs accel_mps2")
    if kind == "climb" and "pitch_deg" not in params:
        raise ScenarioError(f"{where} (climb) needs pitch_deg")
    if kind == "rates" and "euler_rate_dps" not in params:
        raise ScenarioError(f"{where} (rates) needs euler_rate_dps (e.g. [0, 0, 0] for none)")
    _check_rates(where, kind, params)
    return MotionSegment(kind, MappingProxyType(params))


def _check_rates(where: str, kind: str, params: Mapping[str, Any]) -> None:
    """Refuse the rates the profile divides by (a turn's angle over its yaw rate, a bank over its
    roll rate, a speed change over its acceleration): zero gave a ZeroDivisionError, or an
    endless segment, or a transition silently skipped."""
    if kind in ("turn", "coordinated_turn") and params["yaw_rate_dps"] == 0:
        raise ScenarioError(f"{where}.yaw_rate_dps must be non-zero (a turn turns), got 0")
    for key in ("roll_rate_dps", "pitch_rate_dps"):
        if key in params and not params[key] > 0:
            raise ScenarioError(f"{where}.{key} must be > 0 (the attitude's rate), got {params[key]:g}")
    if "transition_s" in params:
        _within(f"{where}.transition_s", params["transition_s"], 0.0, MAX_DURATION_S)
    if kind == "accelerate" and "to_speed_mps" in params and params["accel_mps2"] == 0:
        raise ScenarioError(f"{where}.accel_mps2 must be non-zero to reach to_speed_mps, got 0")


def _needs(where: str, kind: str, raw: Mapping[str, Any], key: str) -> Any:
    """``raw[key]``, a parameter an event of ``kind`` cannot do without; missing: one line saying so."""
    if key not in raw:
        raise ScenarioError(f"{where} ({kind}) needs {key}")
    return raw[key]


def _parse_event(i: int, raw: Mapping[str, Any]) -> ScenarioEvent:
    where = f"event[{i}]"
    kind = raw.get("kind")
    if kind not in _EVENT_KEYS:
        raise ScenarioError(f"{where}.kind must be one of {EVENT_KINDS}, got {kind!r}")
    _check_keys(where, raw, _EVENT_KEYS[kind] | {"kind", "t_start_s", "t_end_s"})
    if "t_start_s" not in raw:
        raise ScenarioError(f"{where} ({kind}) needs t_start_s")
    t0 = _within(f"{where}.t_start_s", _num(f"{where}.t_start_s", raw["t_start_s"]), 0.0, MAX_DURATION_S)
    t1 = _num(f"{where}.t_end_s", raw["t_end_s"]) if "t_end_s" in raw else None
    params: dict[str, Any] = {}
    if kind == "gnss_outage" and t1 is None:
        raise ScenarioError(f"{where} (gnss_outage) needs t_end_s")
    if kind in ("gnss_jump", "gnss_spoof"):
        params["offset_ned_m"] = _vec3(f"{where}.offset_ned_m", _needs(where, kind, raw, "offset_ned_m"))
    if kind == "gnss_spoof":
        params["sigma_m"] = _num(f"{where}.sigma_m", raw.get("sigma_m", DEFAULT_SPOOF_SIGMA_M))
        _gnss_sigma(f"{where}.sigma_m (the σ the spoofed fixes claim)", params["sigma_m"])
    if kind == "gnss_velocity_glitch":
        params["offset_ned_mps"] = _vec3(
            f"{where}.offset_ned_mps", _needs(where, kind, raw, "offset_ned_mps")
        )
        if t1 is None:
            raise ScenarioError(f"{where} (gnss_velocity_glitch) needs t_end_s")
    if kind == "gnss_pulse":
        a = _num(f"{where}.amplitude_m", _needs(where, kind, raw, "amplitude_m"))
        tau = _num(f"{where}.tau_s", _needs(where, kind, raw, "tau_s"))
        d = _vec3(f"{where}.direction_ned", raw.get("direction_ned", [1.0, 0.0, 0.0]))
        n = math.sqrt(sum(x * x for x in d))
        if n == 0 or tau <= 0:
            raise ScenarioError(f"{where} (gnss_pulse) needs tau_s > 0 and a non-zero direction")
        if t1 is not None:
            raise ScenarioError(f"{where} (gnss_pulse) takes tau_s, not t_end_s")
        t1 = t0 + tau
        params.update(amplitude_m=a, tau_s=tau, offset_ned_m=tuple(a * x / n for x in d))
    if kind == "gnss_latency":
        params["latency_s"] = _num(f"{where}.latency_s", _needs(where, kind, raw, "latency_s"))
        if "jitter_s" in raw:
            params["jitter_s"] = _num(f"{where}.jitter_s", raw["jitter_s"])
        if min(params["latency_s"], params.get("jitter_s", 0.0)) < 0:
            raise ScenarioError(f"{where} (gnss_latency): latency_s and jitter_s must be >= 0")
        if t1 is not None:
            raise ScenarioError(f"{where} (gnss_latency) applies from t_start_s on; drop t_end_s")
    if kind in ("imu_stuck", "imu_saturated", "can_bus_off") and t1 is None:
        raise ScenarioError(f"{where} ({kind}) needs t_end_s")
    if kind == "imu_frame_loss":
        pct = _num(f"{where}.percent", raw.get("percent", 100.0))
        if not 0.0 <= pct <= 100.0:
            raise ScenarioError(f"{where}.percent must be in [0, 100], got {pct}")
        params["percent"] = pct
    if kind == "can_burst_error":
        frames = _num(f"{where}.frames", raw.get("frames", 8))
        if not 1 <= frames <= 100_000 or t1 is not None:
            raise ScenarioError(f"{where} (can_burst_error) takes frames in [1, 100000] and no t_end_s")
        params["frames"] = int(frames)
    if kind == "can_latency":  # t_end_s optional: to the end of the run
        params["latency_s"] = _num(f"{where}.latency_s", _needs(where, kind, raw, "latency_s"))
        params["jitter_s"] = _num(f"{where}.jitter_s", raw.get("jitter_s", 0.0))
        problem = transport_delay_problem(params["latency_s"], params["jitter_s"])
        if problem:
            raise ScenarioError(f"{where} (can_latency): {problem}")
    if kind == "clock_step":
        if raw.get("sensor") not in SENSORS or t1 is not None:
            names = " or ".join(SENSORS)
            raise ScenarioError(f"{where} (clock_step) needs sensor = {names}, step_s, no t_end_s")
        step = _num(f"{where}.step_s", _needs(where, kind, raw, "step_s"))
        params.update(
            sensor=raw["sensor"], step_s=_within(f"{where}.step_s", step, -MAX_CLOCK_STEP_S, MAX_CLOCK_STEP_S)
        )
    if kind == "kill_service":
        if not isinstance(raw.get("service"), str) or t1 is not None:
            raise ScenarioError(f'{where} (kill_service) needs service = "<name>" and no t_end_s')
        params["service"] = raw["service"]
    if kind not in _PARSED_KINDS:  # any other kind's parameters are plain numbers
        params.update({k: _num(f"{where}.{k}", raw[k]) for k in _EVENT_KEYS[kind] if k in raw})
    if kind == "gnss_line_burst" and (problem := line_burst_problem(params.get("bytes", 64))):
        raise ScenarioError(f"{where}.{problem}")
    if "percent" in params and not 0.0 <= params["percent"] <= 100.0:
        raise ScenarioError(f"{where}.percent must be in [0, 100], got {params['percent']}")
    if t1 is not None and t1 <= t0:
        raise ScenarioError(f"{where}: t_end_s {t1} must be after t_start_s {t0}")
    return ScenarioEvent(kind, t0, t1, MappingProxyType(params))


def _profile_duration(segments: tuple[MotionSegment, ...], v0: float) -> float:
    """Sum of segment durations (accelerate-to-speed needs the speed, tracked along)."""
    total, v = 0.0, v0
    for s in segments:
        p = s.params
        if s.kind == "accelerate":
            d = (
                p["duration_s"]
                if "duration_s" in p
                else abs(p["to_speed_mps"] - v) / max(abs(p["accel_mps2"]), 1e-12)
            )
            v = p.get("to_speed_mps", v + p["accel_mps2"] * d)
            total += d
        elif "duration_s" in p:
            total += p["duration_s"]
        else:  # turns given by angle
            w = abs(p["yaw_rate_dps"])
            total += abs(p["angle_deg"]) / w + (p.get("transition_s", 1.0) if s.kind == "turn" else 0.0)
            if s.kind == "coordinated_turn":
                bank = math.degrees(math.atan(v * math.radians(w) / 9.80665))
                total += bank / p.get("roll_rate_dps", 10.0)
    return total


def parse_scenario(text: str, default_name: str = "scenario") -> Scenario:
    """Build a Scenario from TOML text (the one parser; :func:`load_scenario` reads a file)."""
    try:
        doc = tomllib.loads(text)
    except tomllib.TOMLDecodeError as err:
        raise ScenarioError(f"scenario {default_name!r} is not valid TOML: {err}") from err
    extra = {k: doc[k] for k in doc if k in RESERVED_TABLES}
    _check_keys("scenario", {k: v for k, v in doc.items() if k not in RESERVED_TABLES}, _TOP_KEYS)
    name = str(doc.get("name", default_name))
    seed = doc.get("seed", 0)
    if isinstance(seed, bool) or not isinstance(seed, int) or seed < 0:
        raise ScenarioError(f"seed must be a non-negative integer, got {seed!r}")

    origin = doc.get("origin", {})
    _check_keys("origin", origin, {"lat_deg", "lon_deg", "alt_m"})
    lat = _num("origin.lat_deg", origin.get("lat_deg", 0.0))
    lon = _num("origin.lon_deg", origin.get("lon_deg", 0.0))
    alt = _num("origin.alt_m", origin.get("alt_m", 0.0))
    _within("origin.lon_deg", lon, -180.0, 360.0)
    _within("origin.alt_m", alt, -11_000.0, 1e6)
    if abs(lat) >= 89.0:
        raise ScenarioError(f"origin.lat_deg {lat} too close to a pole for the NED mechanisation")

    init = doc.get("initial", {})
    _check_keys("initial", init, {"attitude_deg", "speed_mps", "velocity_body_mps"})
    euler = _vec3("initial.attitude_deg", init.get("attitude_deg", [0.0, 0.0, 0.0]))
    if "speed_mps" in init and "velocity_body_mps" in init:
        raise ScenarioError("initial: give speed_mps or velocity_body_mps, not both")
    vb = (
        (_num("initial.speed_mps", init["speed_mps"]), 0.0, 0.0)
        if "speed_mps" in init
        else (_vec3("initial.velocity_body_mps", init.get("velocity_body_mps", [0.0, 0.0, 0.0])))
    )

    imu_t = dict(doc.get("imu", {}))
    preset = str(imu_t.pop("preset", "ideal"))
    rate = imu_t.pop("rate_hz", 400)
    if isinstance(rate, bool) or not isinstance(rate, int) or not 100 <= rate <= 2000:
        raise ScenarioError(f"imu.rate_hz must be an integer in [100, 2000], got {rate!r}")
    try:
        params = resolve_imu_params(preset, imu_t)
    except SpecError as err:
        raise ScenarioError(f"imu: {err}") from err
    imu = ImuConfig(int(rate), preset, MappingProxyType(imu_t), params)

    g = doc.get("gnss", {})
    _check_keys("gnss", g, _GNSS_KEYS)
    gd = GnssConfig()
    gnss = GnssConfig(
        rate_hz=_num("gnss.rate_hz", g.get("rate_hz", gd.rate_hz)),
        pos_sigma_m=_vec3("gnss.pos_sigma_m", g.get("pos_sigma_m", list(gd.pos_sigma_m))),
        vel_sigma_mps=_vec3("gnss.vel_sigma_mps", g.get("vel_sigma_mps", list(gd.vel_sigma_mps))),
        latency_s=_num("gnss.latency_s", g.get("latency_s", gd.latency_s)),
        jitter_s=_num("gnss.jitter_s", g.get("jitter_s", gd.jitter_s)),
        slow_amplitude_m=_vec3("gnss.slow_amplitude_m", g.get("slow_amplitude_m", list(gd.slow_amplitude_m))),
        slow_period_s=_num("gnss.slow_period_s", g.get("slow_period_s", gd.slow_period_s)),
        lever_arm_b_m=_vec3("gnss.lever_arm_b_m", g.get("lever_arm_b_m", list(gd.lever_arm_b_m))),
        num_sats=int(_num("gnss.num_sats", g.get("num_sats", gd.num_sats))),
        hdop=_num("gnss.hdop", g.get("hdop", gd.hdop)),
    )
    if not 1.0 <= gnss.rate_hz <= 20.0:  # u-blox F9: up to 20 Hz navigation rate
        raise ScenarioError(f"gnss.rate_hz must be in [1, 20], got {gnss.rate_hz}")
    if gnss.latency_s < 0 or gnss.jitter_s < 0 or gnss.slow_period_s <= 0:
        raise ScenarioError("gnss.latency_s and jitter_s must be >= 0, slow_period_s > 0")
    for key in ("pos_sigma_m", "vel_sigma_mps"):
        for v in getattr(gnss, key):
            _gnss_sigma(f"gnss.{key}", v)
    for v in gnss.lever_arm_b_m:
        _within("gnss.lever_arm_b_m", v, -1000.0, 1000.0)
    _within("gnss.num_sats", gnss.num_sats, 0, 255)
    _within("gnss.hdop", gnss.hdop, 0.0, 99.99)
    _within("gnss.latency_s + jitter_s", gnss.latency_s + gnss.jitter_s, 0.0, 60.0)

    segments = tuple(_parse_segment(i, s) for i, s in enumerate(doc.get("segment", [])))
    events = tuple(_parse_event(i, e) for i, e in enumerate(doc.get("event", [])))
    if "duration_s" in doc:
        duration = _num("duration_s", doc["duration_s"])
    else:
        duration = _profile_duration(segments, math.hypot(*vb))
    if not 0 < duration <= MAX_DURATION_S:
        if "duration_s" in doc:
            raise ScenarioError(f"duration_s must be in (0, {MAX_DURATION_S:g}] s, got {duration:g}")
        raise ScenarioError(
            f"the segments add up to {duration:g} s; a run must be in (0, {MAX_DURATION_S:g}] s "
            "(set duration_s, or shorten the segments)"
        )
    # the profile itself: a turn or climb too short for its transitions is the file's fault too
    compile_profile(segments, tuple(math.radians(x) for x in euler), vb, duration)  # type: ignore[arg-type]

    return Scenario(
        name=name,
        seed=seed,
        duration_s=duration,
        origin_lat_deg=lat,
        origin_lon_deg=lon,
        origin_alt_m=alt,
        imu=imu,
        gnss=gnss,
        events=events,
        source_text=text,
        sha256=hashlib.sha256(text.encode()).hexdigest(),
        description=str(doc.get("description", "")),
        initial_euler_deg=euler,
        initial_vel_body_mps=vb,
        segments=segments,
        extra_tables=MappingProxyType(extra),
        start_utc_ns=_utc_ns("start_utc", doc.get("start_utc", DEFAULT_START_UTC)),
    )


def builtin_scenarios() -> list[str]:
    """Names of the scenarios shipped in ``hil/scenarios``."""
    root = resources.files("hil") / "scenarios"
    return sorted(p.name[:-5] for p in root.iterdir() if p.name.endswith(".toml"))


def load_scenario(name_or_path: str) -> Scenario:
    """A bare name ("straight_level") is a built-in; anything else is a path to a TOML file."""
    if "/" not in name_or_path and not name_or_path.endswith(".toml"):
        res = resources.files("hil") / "scenarios" / f"{name_or_path}.toml"
        if not res.is_file():
            raise ScenarioError(f"no built-in scenario {name_or_path!r}; built-ins: {builtin_scenarios()}")
        return parse_scenario(res.read_text(encoding="utf-8"), name_or_path)
    path = Path(name_or_path)
    try:
        text = path.read_text(encoding="utf-8")
    except OSError as err:
        raise ScenarioError(f"cannot read scenario file {str(path)!r}: {err}") from err
    except UnicodeDecodeError as err:
        raise ScenarioError(
            f"scenario file {str(path)!r} is not UTF-8 text (byte {err.start}): a scenario is a TOML file"
        ) from None
    return parse_scenario(text, path.stem)


# ---------------------------------------------------------------------------------------------
# overrides: edit the parsed document and re-emit TOML, so source_text stays the truth

_OVERRIDE_KEYS = {
    "name": ("name",),
    "seed": ("seed",),
    "duration_s": ("duration_s",),
    "imu_rate_hz": ("imu", "rate_hz"),
    "imu_preset": ("imu", "preset"),
    "gnss_rate_hz": ("gnss", "rate_hz"),
}


def _toml_value(v: Any) -> str:
    if isinstance(v, bool):
        return "true" if v else "false"
    if isinstance(v, int):
        return str(v)
    if isinstance(v, float):
        return repr(v) if math.isfinite(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else "nan"
    if isinstance(v, str):
        return '"' + v.replace("\\", "\\\\").replace('"', '\\"').replace("\n", "\\n") + '"'
    if isinstance(v, list | tuple):
        return "[" + ", ".join(_toml_value(x) for x in v) + "]"
    if isinstance(v, Mapping):
        return "{" + ", ".join(f"{k} = {_toml_value(x)}" for k, x in v.items()) + "}"
    raise TypeError(f"cannot write {type(v).__name__} to TOML")


def dump_toml(doc: Mapping[str, Any], header: str = "") -> str:
    """Minimal TOML writer for scenario documents (scalars, arrays, tables, arrays of tables)."""
    lines = [f"# {line}" for line in header.splitlines()]
    scalars = {
        k: v
        for k, v in doc.items()
        if not isinstance(v, Mapping | list)
        or (isinstance(v, list) and not (v and all(isinstance(x, Mapping) for x in v)))
    }
    lines += [f"{k} = {_toml_value(v)}" for k, v in scalars.items()]
    for k, v in doc.items():
        if isinstance(v, Mapping):
            lines += ["", f"[{k}]"]
            lines += [f"{kk} = {_toml_value(vv)}" for kk, vv in v.items()]
        elif isinstance(v, list) and v and all(isinstance(x, Mapping) for x in v):
            for item in v:
                lines += ["", f"[[{k}]]"] + [f"{kk} = {_toml_value(vv)}" for kk, vv in item.items()]
    return "\n".join(lines) + "\n"


def scenario_overrides(s: Scenario, **kw: Any) -> Scenario:
    """A copy of ``s`` with top-level settings replaced; keys: name, seed, duration_s,
    imu_rate_hz, imu_preset, gnss_rate_hz, and ``imu_<user key>`` for any IMU spec key
    (e.g. ``imu_gyro_arw_dprh=0.1``). The new ``source_text`` is the re-emitted TOML."""
    if not kw:
        return s
    doc = tomllib.loads(s.source_text)
    for k, v in kw.items():
        if k in _OVERRIDE_KEYS:
            path = _OVERRIDE_KEYS[k]
        elif k.startswith("imu_"):
            path = ("imu", k[4:])
        else:
            raise ScenarioError(f"cannot override {k!r}; allowed: {sorted(_OVERRIDE_KEYS)} or imu_*")
        tbl = doc
        for p in path[:-1]:
            tbl = tbl.setdefault(p, {})
        tbl[path[-1]] = v
    text = dump_toml(
        doc,
        header=f"{s.name} (sha256 {s.sha256[:12]}) with overrides "
        + ", ".join(f"{k}={v!r}" for k, v in sorted(kw.items())),
    )
    return parse_scenario(text, s.name)


def scenario_for_run(run: Any) -> Scenario:
    """The run's scenario (``hil.RunInfo``): its TOML text parsed, its duration applied.

    The text travels in ``RunInfo`` so services on other hosts need no shared file system, and
    the recording holds the exact text; every node and rerun rebuilds the scenario this way."""
    s = parse_scenario(run.scenario_toml, default_name=run.scenario)
    return scenario_overrides(s, duration_s=run.duration_s)


# -- the motion profile compiled (``hil.nav.trajectory`` integrates it; the loader checks it) --

KNOT_MAX_S = 0.5
G_COORD_MPS2 = 9.80665  # gravity used to size the bank of a coordinated turn


@dataclass(frozen=True)
class Primitive:
    """A segment with constant Euler acceleration and body acceleration; SI, radians."""

    t0_s: float
    duration_s: float
    euler0_rad: tuple[float, float, float]
    euler_rate0_radps: tuple[float, float, float]
    euler_acc_radps2: tuple[float, float, float]
    vel_body0_mps: tuple[float, float, float]
    accel_body_mps2: tuple[float, float, float]


def _add(a: tuple[float, ...], b: tuple[float, ...], k: float = 1.0) -> tuple[float, float, float]:
    return (a[0] + k * b[0], a[1] + k * b[1], a[2] + k * b[2])


def _turn_hold(where: str, p: Mapping[str, Any], w: float, tr: float, ramps: str, fix: str) -> float:
    """A turn's time at its full yaw rate ``w`` between the roll-in and roll-out of ``tr`` s each:
    what its angle (or duration) leaves; none left is the file's fault, named."""
    angle = "angle_deg" in p
    hold = math.radians(abs(p["angle_deg"])) / abs(w) - tr if angle else p["duration_s"] - 2.0 * tr
    if hold < 0:
        key = "angle_deg" if angle else "duration_s"
        raise ScenarioError(
            f"{where}: {key} too small for its roll-in and roll-out ({ramps}): lengthen it or {fix}"
        )
    return float(hold)


def compile_profile(
    segments: tuple[MotionSegment, ...],
    euler0_rad: tuple[float, float, float],
    vel_body0_mps: tuple[float, float, float],
    duration_s: float,
) -> tuple[Primitive, ...]:
    """Expand user segments (turns with roll-in/out, climbs with pitch transitions, …) into
    primitives, then cut or pad with a hold so they cover exactly [0, duration_s].

    A segment too short for its transitions raises :class:`ScenarioError` naming it (the loader
    compiles the profile once, so a file is refused where it is read)."""
    prims: list[Primitive] = []
    t = 0.0
    e = euler0_rad
    vb = vel_body0_mps
    zero = (0.0, 0.0, 0.0)

    def emit(
        dur: float,
        de0: tuple[float, float, float],
        dde: tuple[float, float, float],
        ab: tuple[float, float, float] = zero,
    ) -> None:
        nonlocal t, e, vb
        if dur <= 0.0:
            return
        prims.append(Primitive(t, dur, e, de0, dde, vb, ab))
        e = _add(_add(e, de0, dur), dde, 0.5 * dur * dur)
        vb = _add(vb, ab, dur)
        t += dur

    for i, seg in enumerate(segments):
        p = seg.params
        where = f"segment[{i}] ({seg.kind})"
        if seg.kind == "hold":
            emit(p["duration_s"], zero, zero)
        elif seg.kind == "accelerate":
            a = p["accel_mps2"]
            if "to_speed_mps" in p:
                dv = p["to_speed_mps"] - vb[0]
                a = math.copysign(abs(a), dv) if dv != 0 else 0.0
                dur = abs(dv) / abs(a) if a else 0.0
            else:
                dur = p["duration_s"]
            emit(dur, zero, zero, (a, 0.0, 0.0))
        elif seg.kind == "rates":
            emit(
                p["duration_s"],
                tuple(math.radians(x) for x in p["euler_rate_dps"]),  # type: ignore[arg-type]
                zero,
                p.get("accel_body_mps2", zero),
            )
        elif seg.kind == "turn":
            # flat (car-like) turn; the yaw rate ramps over transition_s so lateral accel is continuous
            w = math.radians(p["yaw_rate_dps"])
            tr = p.get("transition_s", 1.0)
            hold = _turn_hold(where, p, w, tr, f"transition_s={tr:g} s each", "shorten transition_s")
            if "angle_deg" in p and p["angle_deg"] < 0:
                w = -abs(w)
            if tr > 0:
                emit(tr, zero, (0.0, 0.0, w / tr))
            emit(hold, (0.0, 0.0, w), zero)
            if tr > 0:
                emit(tr, (0.0, 0.0, w), (0.0, 0.0, -w / tr))
        elif seg.kind == "coordinated_turn":
            # bank φ = atan(v ω / g); roll in at roll_rate while the yaw rate ramps 0 → ω
            w = math.radians(p["yaw_rate_dps"])
            if "angle_deg" in p and p["angle_deg"] < 0:
                w = -abs(w)
            v = math.hypot(*vb)
            bank = math.atan(v * w / G_COORD_MPS2)
            rr = math.radians(p.get("roll_rate_dps", 10.0))
            tr = abs(bank) / rr if rr > 0 else 0.0
            hold = _turn_hold(where, p, w, tr, f"{tr:g} s each at roll_rate_dps", "raise roll_rate_dps")
            if tr > 0:
                emit(tr, (bank / tr, 0.0, 0.0), (0.0, 0.0, w / tr))
            emit(hold, (0.0, 0.0, w), zero)
            if tr > 0:
                emit(tr, (-bank / tr, 0.0, w), (0.0, 0.0, -w / tr))
        elif seg.kind == "climb":
            gam = math.radians(p["pitch_deg"])
            rate = math.radians(p.get("pitch_rate_dps", 2.0))
            tp = abs(gam - e[1]) / rate if rate > 0 else 0.0
            hold = p["duration_s"] - 2.0 * tp
            if hold < 0:
                raise ScenarioError(
                    f"{where}: duration_s {p['duration_s']:g} s is shorter than its two pitch "
                    f"transitions ({tp:g} s each at pitch_rate_dps): lengthen it or raise pitch_rate_dps"
                )
            back = e[1]
            if tp > 0:
                emit(tp, (0.0, (gam - e[1]) / tp, 0.0), zero)
            emit(hold, zero, zero)
            if tp > 0:
                emit(tp, (0.0, (back - gam) / tp, 0.0), zero)
        else:  # pragma: no cover - the parser rejects unknown kinds
            raise ValueError(seg.kind)
    if t < duration_s:
        emit(duration_s - t, zero, zero)
    return tuple(pr for pr in prims if pr.t0_s < duration_s)

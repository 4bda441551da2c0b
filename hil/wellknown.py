"""Foxglove's well-known types from the rig's messages: the one conversion the recorder, ``hil
sim``, the live Foxglove server and the export share (pure: no I/O, no clock, no threads; the same
messages give the same bytes).

The messages are Foxglove's own, built and encoded (protobuf) with the official SDK
(``foxglove-sdk``: ``foxglove.messages``), and every channel carries the SDK's schema
(``SCHEMAS``: schema encoding ``protobuf``, a ``FileDescriptorSet``), so Foxglove's Map, 3D and
Log panels read them with no configuration.

=================================== ======================== ==================================
topic                               type                     from
=================================== ======================== ==================================
``/foxglove/fix/truth``             ``foxglove.LocationFix`` ``hil/<rig>/truth``
``/foxglove/fix/sensor/<s>``        ``foxglove.LocationFix`` ``hil/<rig>/sensor/<s>`` (a GNSS fix)
``/foxglove/fix/nav/<est>``         ``foxglove.LocationFix`` ``hil/<rig>/nav/<est>`` (every estimator)
``/foxglove/tf/truth``              ``foxglove.FrameTransform`` truth
``/foxglove/tf/sensor/<s>``         ``foxglove.FrameTransform`` the GNSS antenna (position only)
``/foxglove/tf/nav/<est>``          ``foxglove.FrameTransform`` every estimator
``/foxglove/tf_static``             ``foxglove.FrameTransform`` ``enu`` -> ``ned``, with each ``run``
``/foxglove/log``                   ``foxglove.Log``         ``event/*`` and the errors and state
                                                             changes in ``status/*``
=================================== ======================== ==================================

Poses (a fix and a transform) go out at most ``POSE_RATE_HZ`` (10 Hz) per source, decimated on
the rig-time grid (``WellKnown.pose_rate_hz``): truth is 100 Hz and each estimator 50 Hz, and at
full rate the derived messages cost ``hil sim`` ~10 % more time and its file a third more bytes.

LocationFix: latitude/longitude/altitude as the message has them; ``heading`` = yaw of ``q_nb``
(radians clockwise from north, as the schema says; none for a GNSS fix: a receiver has no
attitude); ``velocity`` in ENU (``[v_e, v_n, -v_d]``); ``position_covariance`` ENU, diagonal from
``pos_sigma_m`` (``[s_e^2, 0, 0, 0, s_n^2, 0, 0, 0, s_d^2]``, type ``DIAGONAL_KNOWN``; ``UNKNOWN``
and zeros where the source has none: truth, an estimator without covariance).

The frame tree (every parent ``enu``)::

    enu                 local tangent plane at the scenario origin: x east, y north, z up
    ├── ned             the same origin, x north, y east, z down: hil's navigation frame (static)
    ├── truth           the true vehicle body, FLU: x forward, y left, z up (ROS REP-103)
    ├── nav/<est>       each estimator's body, FLU
    └── sensor/<s>      the GNSS antenna: position only, axes parallel to enu

Conversions: a position ``p_ned = [n, e, d]`` is ``[e, n, -d]`` in ENU. hil's ``q_nb`` is
``[w, x, y, z]`` (Hamilton), rotating body vectors (FRD: x forward, y right, z down) into NED;
the transform's rotation is ``q_enu_flu = q_enu_ned ⊗ q_nb ⊗ q_frd_flu`` with ``q_enu_ned`` =
180° about ``(x + y)/√2`` and ``q_frd_flu`` = 180° about x, which works out to
``[w, x, y, z] = (1/√2) [w + z, x + y, x - y, w - z]`` of ``q_nb``, handed to Foxglove as
``{x, y, z, w}``. A level vehicle heading north is then yawed +90° about ENU's up.

Times: a message's ``timestamp`` is the run's start epoch + the source's ``stamp_ns`` (rig time),
the wall-clock timeline of the recording's ``log_time`` (``hil.record.mcapio``), where Foxglove
looks transforms up; before the start epoch is known (no ``run`` seen yet) the caller's log time.
"""

from __future__ import annotations

import math
import zlib
from dataclasses import dataclass, field
from typing import Any, NamedTuple

from foxglove.messages import (
    Color,
    FrameTransform,
    KeyValuePair,
    LocationFix,
    LocationFixPositionCovarianceType,
    Log,
    LogLevel,
    Quaternion,
    Timestamp,
    Vector3,
)

from hil.messages import Event, GnssFix, Message, NavSolution, RunInfo, ServiceStatus, Truth

PREFIX = "/foxglove/"
ROOT_FRAME = "enu"
NED_FRAME = "ned"
STATIC_TOPIC = "/foxglove/tf_static"
LOG_TOPIC = "/foxglove/log"
_S = 1_000_000_000
_R = math.sqrt(0.5)
POSE_RATE_HZ = 10.0


class Schema(NamedTuple):
    """A well-known type's schema as a channel carries it."""

    name: str
    encoding: str
    data: bytes


def _schema(cls: Any) -> Schema:
    s = cls.get_schema()
    return Schema(s.name, s.encoding, bytes(s.data))


#: schema name -> the SDK's schema (protobuf ``FileDescriptorSet``)
SCHEMAS: dict[str, Schema] = {s.name: s for s in map(_schema, (LocationFix, FrameTransform, Log))}
MESSAGE_ENCODING = "protobuf"


class Derived(NamedTuple):
    """One well-known message: its topic, schema name and encoded bytes; ``stamp_ns`` is the
    timestamp it carries (the recording's publish time)."""

    topic: str
    schema: str
    data: bytes
    stamp_ns: int


def rig_suffix(key: str) -> str:
    """``hil/<rig>/nav/ekf15`` -> ``nav/ekf15``; a key already without its root is kept."""
    if key.startswith("hil/"):
        parts = key.split("/", 2)
        return parts[2] if len(parts) > 2 else ""
    return key


def ned_to_enu(v: list[float]) -> tuple[float, float, float]:
    return v[1], v[0], -v[2]


def q_enu_flu(q_nb: list[float]) -> tuple[float, float, float, float]:
    """hil's ``q_nb`` (``[w, x, y, z]``, FRD body -> NED) as the FLU body's attitude in ENU,
    ``(w, x, y, z)`` (see the module docstring for the derivation)."""
    w, x, y, z = q_nb
    return _R * (w + z), _R * (x + y), _R * (x - y), _R * (w - z)


def yaw_rad(q_nb: list[float]) -> float:
    """Heading of ``q_nb``: radians clockwise from north in [0, 2π) (aerospace ZYX yaw)."""
    w, x, y, z = q_nb
    yaw = math.atan2(2.0 * (w * z + x * y), 1.0 - 2.0 * (y * y + z * z))
    return yaw % (2.0 * math.pi)


def _timestamp(ns: int) -> Timestamp:
    ns = max(ns, 0)
    return Timestamp(ns // _S, ns % _S)


_PALETTE = (
    (0.12, 0.47, 0.71),
    (1.0, 0.5, 0.05),
    (0.58, 0.4, 0.74),
    (0.84, 0.15, 0.16),
    (0.55, 0.34, 0.29),
    (0.89, 0.47, 0.76),
    (0.5, 0.5, 0.5),
    (0.74, 0.74, 0.13),
    (0.09, 0.75, 0.81),
)
_FIXED_COLORS = {"truth": (0.17, 0.63, 0.17), "sensor": (0.0, 0.0, 0.0)}


def color_of(frame: str) -> Color:
    """A colour per source, the same in every recording (truth green, GNSS black)."""
    kind, _, name = frame.partition("/")
    rgb = _FIXED_COLORS.get(kind) or _PALETTE[zlib.crc32(name.encode()) % len(_PALETTE)]
    return Color(r=rgb[0], g=rgb[1], b=rgb[2], a=1.0)


def _cov(sigma_ned: list[float]) -> tuple[list[float], LocationFixPositionCovarianceType]:
    if len(sigma_ned) != 3:
        return [0.0] * 9, LocationFixPositionCovarianceType.Unknown
    n, e, d = sigma_ned
    diagonal = LocationFixPositionCovarianceType.DiagonalKnown
    return [e * e, 0.0, 0.0, 0.0, n * n, 0.0, 0.0, 0.0, d * d], diagonal


def location_fix(
    frame: str,
    ts: Timestamp,
    lla: tuple[float, float, float],
    vel_ned: list[float],
    sigma_ned: list[float],
    heading: float | None,
    metadata: list[KeyValuePair] | None = None,
) -> bytes:
    cov, kind = _cov(sigma_ned)
    return LocationFix(
        timestamp=ts,
        frame_id=frame,
        latitude=lla[0],
        longitude=lla[1],
        altitude=lla[2],
        position_covariance=cov,
        position_covariance_type=kind,
        heading=heading,
        velocity=Vector3(**dict(zip("xyz", ned_to_enu(vel_ned), strict=True))),
        color=color_of(frame),
        metadata=metadata,
    ).encode()


def frame_transform(
    frame: str, ts: Timestamp, pos_ned: list[float], q_nb: list[float] | None, parent: str = ROOT_FRAME
) -> bytes:
    e, n, u = ned_to_enu(pos_ned)
    if q_nb is None:
        rot = Quaternion(x=0.0, y=0.0, z=0.0, w=1.0)
    else:
        w, x, y, z = q_enu_flu(q_nb)
        rot = Quaternion(x=x, y=y, z=z, w=w)
    return FrameTransform(
        timestamp=ts,
        parent_frame_id=parent,
        child_frame_id=frame,
        translation=Vector3(x=e, y=n, z=u),
        rotation=rot,
    ).encode()


def static_enu_to_ned(ts: Timestamp) -> bytes:
    """``ned`` in ``enu``: 180° about (x + y)/√2 (x north, y east, z down)."""
    return FrameTransform(
        timestamp=ts,
        parent_frame_id=ROOT_FRAME,
        child_frame_id=NED_FRAME,
        translation=Vector3(x=0.0, y=0.0, z=0.0),
        rotation=Quaternion(x=_R, y=_R, z=0.0, w=0.0),
    ).encode()


#: an event's kind -> its log level (anything else: INFO)
EVENT_LEVELS: dict[str, LogLevel] = {
    "fault_start": LogLevel.Warning,
    "fault_ignored": LogLevel.Warning,
    "fault_rejected": LogLevel.Warning,
    "service_restarted": LogLevel.Warning,
    "realigned": LogLevel.Warning,
    "run_failed": LogLevel.Error,
}


def log(ts: Timestamp, level: LogLevel, name: str, message: str) -> bytes:
    return Log(timestamp=ts, level=level, message=message, name=name).encode()


#: The types :meth:`WellKnown.convert` derives messages from: for any other it returns none and
#: keeps no state.
DERIVED_FROM: tuple[type[Message], ...] = (Truth, NavSolution, GnssFix, Event, ServiceStatus, RunInfo)
_DERIVES: dict[type, bool] = {}


def derives(cls: type) -> bool:
    """Whether Foxglove messages derive from a message of ``cls`` (a subclass of one of
    ``DERIVED_FROM``), one dict lookup a message: ``isinstance`` against those six msgspec types
    costs ~0.6 µs when none matches, as for a CAN frame or an IMU sample, most of the traffic."""
    got = _DERIVES.get(cls)
    if got is None:
        got = _DERIVES[cls] = issubclass(cls, DERIVED_FROM)
    return got


@dataclass
class WellKnown:
    """The conversion for one rig. It holds the run's start epoch (from the ``run`` message, or
    given) and what each service last said in its status, so a ``foxglove.Log`` says what changed
    (a new ``last_error``, a new state), not the same thing every second."""

    start_epoch_ns: int | None = None
    #: poses (fix and transform) per source at most this often, by rig time: 10 Hz draws a map and
    #: a 3D view at a tenth of the cost of truth's 100 Hz (every GNSS fix up to 10 Hz is kept)
    pose_rate_hz: float = POSE_RATE_HZ
    _status: dict[str, tuple[str, str]] = field(default_factory=dict)
    _next_ns: dict[str, int] = field(default_factory=dict)

    def _due(self, frame: str, stamp_ns: int) -> bool:
        """Deterministic decimation on the rig-time grid: the first message at or after each
        multiple of the period (``pose_rate_hz`` <= 0: every message)."""
        if self.pose_rate_hz <= 0:
            return True
        if stamp_ns < self._next_ns.get(frame, -(2**63)):
            return False
        period = round(_S / self.pose_rate_hz)
        self._next_ns[frame] = (stamp_ns // period + 1) * period
        return True

    def _ts(self, stamp_ns: int, log_time_ns: int) -> tuple[int, Timestamp]:
        t = log_time_ns if self.start_epoch_ns is None else self.start_epoch_ns + stamp_ns
        return t, _timestamp(t)

    def convert(self, key: str, msg: Message, log_time_ns: int) -> list[Derived]:
        """The well-known messages derived from ``msg`` on ``key`` (a rig key with or without its
        ``hil/<rig>/`` root); ``log_time_ns`` dates them while no start epoch is known."""
        if not derives(type(msg)):
            return []
        suffix = rig_suffix(key)
        kind = suffix.partition("/")[0]
        if isinstance(msg, Truth):
            return self._pose("truth", msg, log_time_ns) if self._due("truth", msg.stamp_ns) else []
        if isinstance(msg, NavSolution) and kind == "nav":
            return self._pose(suffix, msg, log_time_ns) if self._due(suffix, msg.stamp_ns) else []
        if isinstance(msg, GnssFix) and kind == "sensor":  # the synced copy is the same fix
            return self._gnss(suffix, msg, log_time_ns) if self._due(suffix, msg.stamp_ns) else []
        if isinstance(msg, Event):
            t, ts = self._ts(msg.stamp_ns, log_time_ns)
            text = f"{msg.kind}: {msg.detail}" if msg.detail else msg.kind
            level = EVENT_LEVELS.get(msg.kind, LogLevel.Info)
            return [Derived(LOG_TOPIC, "foxglove.Log", log(ts, level, msg.source, text), t)]
        if isinstance(msg, ServiceStatus):
            return self._status_log(msg, log_time_ns)
        if isinstance(msg, RunInfo):
            if self.start_epoch_ns is None:
                self.start_epoch_ns = msg.start_epoch_ns
            t, ts = self._ts(msg.stamp_ns, log_time_ns)
            return [Derived(STATIC_TOPIC, "foxglove.FrameTransform", static_enu_to_ned(ts), t)]
        return []

    def _pose(self, frame: str, m: Truth | NavSolution, log_time_ns: int) -> list[Derived]:
        t, ts = self._ts(m.stamp_ns, log_time_ns)
        sigma = m.pos_sigma_m if isinstance(m, NavSolution) else []
        fix = location_fix(frame, ts, (m.lat_deg, m.lon_deg, m.alt_m), m.vel_ned_mps, sigma, yaw_rad(m.q_nb))
        tf = frame_transform(frame, ts, m.pos_ned_m, m.q_nb)
        return [
            Derived(f"{PREFIX}fix/{frame}", "foxglove.LocationFix", fix, t),
            Derived(f"{PREFIX}tf/{frame}", "foxglove.FrameTransform", tf, t),
        ]

    def _gnss(self, frame: str, m: GnssFix, log_time_ns: int) -> list[Derived]:
        t, ts = self._ts(m.stamp_ns, log_time_ns)
        meta = [
            KeyValuePair(key="fix_type", value=str(m.fix_type)),
            KeyValuePair(key="num_sats", value=str(m.num_sats)),
            KeyValuePair(key="hdop", value=f"{m.hdop:g}"),
        ]
        lla = (m.lat_deg, m.lon_deg, m.alt_m)
        fix = location_fix(frame, ts, lla, m.vel_ned_mps, m.pos_sigma_m, None, meta)
        tf = frame_transform(frame, ts, m.pos_ned_m, None)
        return [
            Derived(f"{PREFIX}fix/{frame}", "foxglove.LocationFix", fix, t),
            Derived(f"{PREFIX}tf/{frame}", "foxglove.FrameTransform", tf, t),
        ]

    def _status_log(self, st: ServiceStatus, log_time_ns: int) -> list[Derived]:
        before = self._status.get(st.service)
        self._status[st.service] = (st.state, st.last_error)
        t, ts = self._ts(st.stamp_ns, log_time_ns)
        out = []
        if (before is None and st.state == "degraded") or (before is not None and before[0] != st.state):
            level = LogLevel.Error if st.state == "degraded" else LogLevel.Info
            was = f"{before[0]} -> " if before is not None else ""
            text = f"state {was}{st.state}"
            out.append(Derived(LOG_TOPIC, "foxglove.Log", log(ts, level, st.service, text), t))
        if st.last_error and (before is None or before[1] != st.last_error):
            level = LogLevel.Error if st.state == "degraded" else LogLevel.Warning
            out.append(Derived(LOG_TOPIC, "foxglove.Log", log(ts, level, st.service, st.last_error), t))
        return out

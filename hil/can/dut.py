"""Decode a real navigation box's CAN output (the device under test) into ``NavSolution``.

The box is described by *its* DBC (the user's file, used as is with cantools) plus a mapping
that says which signal feeds which ``NavSolution`` field. The decoded solution carries the
mapping's ``estimator`` name, so it lands on ``hil/<rig>/nav/<name>`` beside the rig's own
estimators and is compared with them like any other.

Mapping (a dict, typically a TOML file)::

    estimator = "dut_navbox"            # NavSolution.estimator (and the nav/<name> key)
    complete_on = "NAV_Attitude"        # frame whose arrival emits a solution (default: the
                                        # frame of the last mapped field)
    max_age_ms = 50                     # a field older than this at completion -> "stale"

    [fields]                            # NavSolution field <- "Message.Signal" (DBC names)
    lat_deg = "NAV_Position.Latitude"   # required: lat_deg, lon_deg, alt_m,
    lon_deg = "NAV_Position.Longitude"  #           vel_n_mps, vel_e_mps, vel_d_mps,
    alt_m = "NAV_Position.Altitude"     #           and an attitude:
    vel_n_mps = "NAV_Velocity.VelN"     #   roll_deg, pitch_deg, yaw_deg (ZYX Euler), or
    vel_e_mps = "NAV_Velocity.VelE"     #   qw, qx, qy, qz (q_nb, body to NED)
    vel_d_mps = "NAV_Velocity.VelD"     # optional: pos_sigma_{n,e,d}_m, vel_sigma_{n,e,d}_mps
    roll_deg = "NAV_Attitude.Roll"
    pitch_deg = "NAV_Attitude.Pitch"
    yaw_deg = "NAV_Attitude.Heading"

    [scale]                             # optional: multiply a field after DBC scaling, for a
    vel_d_mps = -1.0                    # box whose units or sign convention differ (Up -> Down)

Positions become ``pos_ned_m`` relative to the run's origin (WGS84). A frame the DBC does not
know, a frame that does not decode, a completion with a field missing or stale: counted in
``counters``, never raised.

Errors::

    ValueError
     └── DutMappingError   the mapping names a field/message/signal that does not exist
"""

from __future__ import annotations

import math
import tomllib
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any

import can

from hil.messages import NavSolution

if TYPE_CHECKING:
    import cantools  # imported where a DBC is loaded: the bridge without a unit never needs it

REQUIRED = ("lat_deg", "lon_deg", "alt_m", "vel_n_mps", "vel_e_mps", "vel_d_mps")
EULER = ("roll_deg", "pitch_deg", "yaw_deg")
QUAT = ("qw", "qx", "qy", "qz")
OPTIONAL = (
    "pos_sigma_n_m",
    "pos_sigma_e_m",
    "pos_sigma_d_m",
    "vel_sigma_n_mps",
    "vel_sigma_e_mps",
    "vel_sigma_d_mps",
)
KNOWN = frozenset(REQUIRED + EULER + QUAT + OPTIONAL)


class DutMappingError(ValueError):
    """The mapping does not fit the DBC: names the field and what is missing."""


@dataclass(frozen=True)
class DutMapping:
    estimator: str
    fields: dict[str, tuple[str, str]]  # NavSolution field -> (message, signal)
    scale: dict[str, float] = field(default_factory=dict)
    complete_on: str | None = None
    max_age_ms: float = 50.0

    @classmethod
    def from_dict(cls, raw: dict[str, Any]) -> DutMapping:
        est = str(raw.get("estimator") or "")
        if not est:
            raise DutMappingError("mapping needs an 'estimator' name")
        fields: dict[str, tuple[str, str]] = {}
        for name, ref in dict(raw.get("fields") or {}).items():
            if name not in KNOWN:
                raise DutMappingError(
                    f"field {name!r} is not a NavSolution input; use one of {sorted(KNOWN)}"
                )
            msg, dot, sig = str(ref).partition(".")
            if not dot or not msg or not sig:
                raise DutMappingError(f"field {name!r}: {ref!r} is not 'Message.Signal'")
            fields[name] = (msg, sig)
        missing = [f for f in REQUIRED if f not in fields]
        if missing:
            raise DutMappingError(f"mapping lacks required fields {missing}")
        if not (all(f in fields for f in EULER) or all(f in fields for f in QUAT)):
            raise DutMappingError(f"mapping needs an attitude: all of {list(EULER)} or all of {list(QUAT)}")
        scale = {str(k): _number(f"scale {k!r}", v) for k, v in dict(raw.get("scale") or {}).items()}
        for k in scale:
            if k not in fields:
                raise DutMappingError(f"scale for {k!r}, which is not mapped")
        return cls(
            estimator=est,
            fields=fields,
            scale=scale,
            complete_on=raw.get("complete_on"),
            max_age_ms=_number("max_age_ms", raw.get("max_age_ms", 50.0)),
        )

    @classmethod
    def from_toml(cls, path: str | Path) -> DutMapping:
        with open(path, "rb") as fh:
            return cls.from_dict(tomllib.load(fh))


def _number(what: str, v: Any) -> float:
    """A number of the mapping (``[scale] lat_deg = "abc"`` is one line, not float()'s)."""
    if isinstance(v, bool) or not isinstance(v, int | float) or not math.isfinite(v):
        raise DutMappingError(f"{what} = {v!r} is not a finite number")
    return float(v)


COUNTERS = ("frames", "unknown_id", "decode_error", "solutions", "incomplete", "stale")


class DutNavDecoder:
    """Frames of the DUT in, ``NavSolution`` out. Pure: the caller passes each frame's rig stamp."""

    def __init__(
        self,
        db: cantools.database.Database,
        mapping: DutMapping,
        origin_lat_deg: float,
        origin_lon_deg: float,
        origin_alt_m: float,
    ) -> None:
        self.db = db
        self.mapping = mapping
        self.origin = (math.radians(origin_lat_deg), math.radians(origin_lon_deg), origin_alt_m)
        self.counters: dict[str, int] = dict.fromkeys(COUNTERS, 0)
        self.last_error = ""
        self._by_message: dict[int, list[tuple[str, str]]] = {}
        last_msg = None
        for name, (mname, sig) in mapping.fields.items():
            try:
                m = db.get_message_by_name(mname)
            except KeyError:
                raise DutMappingError(f"field {name!r}: message {mname!r} is not in the DBC") from None
            if sig not in [s.name for s in m.signals]:
                raise DutMappingError(f"field {name!r}: signal {sig!r} is not in message {mname!r}")
            self._by_message.setdefault(m.frame_id, []).append((name, sig))
            last_msg = m
        trigger = mapping.complete_on or (last_msg.name if last_msg else "")
        try:
            self._trigger_id = db.get_message_by_name(trigger).frame_id
        except KeyError:
            raise DutMappingError(f"complete_on {trigger!r} is not a message of the DBC") from None
        self._values: dict[str, tuple[float, int]] = {}  # field -> (value, rig stamp ns)
        self._seq = 0
        self._euler = all(f in mapping.fields for f in EULER)

    @classmethod
    def from_files(
        cls, dbc: str | Path, mapping: str | Path, origin: tuple[float, float, float]
    ) -> DutNavDecoder:
        import cantools

        return cls(cantools.database.load_file(str(dbc)), DutMapping.from_toml(mapping), *origin)

    def _fail(self, counter: str, text: str) -> None:
        self.counters[counter] += 1
        self.last_error = text

    def feed(self, msg: can.Message, stamp_ns: int) -> NavSolution | None:
        """Consume one frame received at rig time ``stamp_ns``; a solution when one completes."""
        self.counters["frames"] += 1
        wanted = self._by_message.get(msg.arbitration_id)
        if wanted is None and msg.arbitration_id != self._trigger_id:
            self.counters["unknown_id"] += 1
            return None
        try:
            decoded = self.db.decode_message(msg.arbitration_id, bytes(msg.data), decode_choices=False)
        except Exception as err:  # cantools: wrong length, bad mux, ...
            self._fail("decode_error", f"0x{msg.arbitration_id:X} [{len(msg.data)}]: {err}")
            return None
        for name, sig in wanted or ():
            value = float(decoded[sig]) * self.mapping.scale.get(name, 1.0)
            if not math.isfinite(value):
                self._fail("decode_error", f"{name} = {value} from {sig}")
                return None
            self._values[name] = (value, stamp_ns)
        if msg.arbitration_id != self._trigger_id:
            return None
        return self._solution(stamp_ns)

    def _solution(self, stamp_ns: int) -> NavSolution | None:
        v = self._values
        need = REQUIRED + (EULER if self._euler else QUAT)
        missing = [f for f in need if f not in v]
        if missing:
            self._fail("incomplete", f"no value yet for {missing}")
            return None
        max_age = self.mapping.max_age_ms * 1e6
        stale = [f for f in need if stamp_ns - v[f][1] > max_age]
        if stale:
            self._fail("stale", f"older than {self.mapping.max_age_ms} ms: {stale}")
            return None
        from hil.nav.attitude import euler_to_quat, quat_normalise
        from hil.nav.earth import lla_to_ned

        lat, lon, alt = v["lat_deg"][0], v["lon_deg"][0], v["alt_m"][0]
        pos = lla_to_ned(math.radians(lat), math.radians(lon), alt, *self.origin)
        if self._euler:
            q = euler_to_quat([math.radians(v[f][0]) for f in EULER])
        else:
            q = quat_normalise([v[f][0] for f in QUAT])

        def opt(names: tuple[str, str, str]) -> list[float]:
            return [v[n][0] for n in names] if all(n in v for n in names) else []

        sol = NavSolution(
            seq=self._seq,
            stamp_ns=stamp_ns,
            estimator=self.mapping.estimator,
            pos_ned_m=[float(x) for x in pos],
            vel_ned_mps=[v["vel_n_mps"][0], v["vel_e_mps"][0], v["vel_d_mps"][0]],
            q_nb=[float(x) for x in q],
            lat_deg=lat,
            lon_deg=lon,
            alt_m=alt,
            pos_sigma_m=opt(("pos_sigma_n_m", "pos_sigma_e_m", "pos_sigma_d_m")),
            vel_sigma_mps=opt(("vel_sigma_n_mps", "vel_sigma_e_mps", "vel_sigma_d_mps")),
        )
        self._seq += 1
        self.counters["solutions"] += 1
        return sol

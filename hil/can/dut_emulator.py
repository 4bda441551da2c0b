"""An emulated device under test: truth plus its own errors, encoded with the DUT's DBC.

The inverse of :class:`hil.can.dut.DutNavDecoder` -- the same mapping read backwards -- so the
bench can show a "real unit" being scored against truth with no hardware. Pure: no I/O.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import TYPE_CHECKING

import can
import numpy as np

from hil.can.dut import EULER, DutMapping
from hil.nav.attitude import quat_to_euler

if TYPE_CHECKING:
    import cantools  # imported where a DBC is loaded (load_dut)


def load_dut(mapping_path: str | Path) -> tuple[cantools.database.Database, DutMapping]:
    """The mapping TOML and the DBC it names (``dbc = "..."``, relative to the mapping file),
    checked against each other: every problem is one ``ValueError`` naming the file, so
    ``hil up --dut`` refuses it before anything starts and ``can_bridge``/``dut_emulator`` say
    it in one line rather than die with cantools' traceback."""
    import tomllib

    import cantools

    from hil.can.dut import DutNavDecoder
    from hil.messages import check_name

    p = Path(mapping_path)
    try:
        with open(p, "rb") as fh:
            raw = tomllib.load(fh)
    except OSError as err:
        raise ValueError(f"{p}: cannot read the DUT mapping ({err.strerror or err})") from None
    except (tomllib.TOMLDecodeError, UnicodeDecodeError) as err:
        raise ValueError(f"{p}: not a TOML DUT mapping: {err}") from None
    dbc = raw.get("dbc")
    if not dbc:
        raise ValueError(f'{p}: the DUT mapping needs `dbc = "file.dbc"` naming the unit\'s DBC')
    dbc_path = (p.parent / str(dbc)).resolve()
    if not dbc_path.is_file():
        raise ValueError(f"{p}: DBC {dbc_path} not found")
    try:
        db = cantools.database.load_file(str(dbc_path))
    except Exception as err:  # cantools: UnsupportedDatabaseFormatError, ParseError, ...
        first = (str(err).strip().splitlines() or [type(err).__name__])[0]
        raise ValueError(f"{p}: DBC {dbc_path} does not parse as a DBC: {first[:300]}") from None
    try:
        mapping = DutMapping.from_dict(raw)
        check_name("estimator", mapping.estimator)  # its key: nav/<estimator>
        DutNavDecoder(db, mapping, 0.0, 0.0, 0.0)  # every field's message and signal in the DBC
    except ValueError as err:
        raise ValueError(f"{p}: {err}") from None
    return db, mapping


class DutNavEncoder:
    """Solutions in, the unit's frames out (trigger frame last, as a real unit closes a cycle)."""

    def __init__(self, db: cantools.database.Database, mapping: DutMapping) -> None:
        self.db = db
        self.mapping = mapping
        self._messages: dict[str, list[tuple[str, str]]] = {}
        for name, (mname, sig) in mapping.fields.items():
            self._messages.setdefault(mname, []).append((name, sig))
        trigger = mapping.complete_on or list(self._messages)[-1]
        self._order = [m for m in self._messages if m != trigger] + [trigger]

    def encode(self, values: dict[str, float]) -> list[can.Message]:
        out = []
        for mname in self._order:
            msg = self.db.get_message_by_name(mname)
            data = {s.name: 0 for s in msg.signals}
            for name, sig in self._messages.get(mname, ()):
                data[sig] = values[name] / self.mapping.scale.get(name, 1.0)
            payload = msg.encode(data, scaling=True, strict=False)
            out.append(
                can.Message(arbitration_id=msg.frame_id, data=payload, is_extended_id=msg.is_extended_frame)
            )
        return out

    @staticmethod
    def values_from_truth(
        lat_deg: float,
        lon_deg: float,
        alt_m: float,
        vel_ned_mps: np.ndarray,
        q_nb: np.ndarray,
        pos_err_ned_m: np.ndarray,
        sigma_h_m: float,
        sigma_v_m: float,
    ) -> dict[str, float]:
        """Field values of a unit whose position is off by ``pos_err_ned_m``."""
        from hil.nav.earth import radii_of_curvature

        r_n, r_e = radii_of_curvature(math.radians(lat_deg))
        lat = lat_deg + math.degrees(pos_err_ned_m[0] / (float(r_n) + alt_m))
        lon = lon_deg + math.degrees(
            pos_err_ned_m[1] / ((float(r_e) + alt_m) * math.cos(math.radians(lat_deg)))
        )
        roll, pitch, yaw = (math.degrees(float(a)) for a in quat_to_euler(q_nb))
        v = {
            "lat_deg": lat,
            "lon_deg": lon,
            "alt_m": alt_m - float(pos_err_ned_m[2]),
            "vel_n_mps": float(vel_ned_mps[0]),
            "vel_e_mps": float(vel_ned_mps[1]),
            "vel_d_mps": float(vel_ned_mps[2]),
            "roll_deg": roll,
            "pitch_deg": pitch,
            "yaw_deg": yaw % 360.0,
            "pos_sigma_n_m": sigma_h_m,
            "pos_sigma_e_m": sigma_h_m,
            "pos_sigma_d_m": sigma_v_m,
        }
        assert set(EULER) <= set(v)
        return v

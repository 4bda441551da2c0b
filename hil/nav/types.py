"""Array containers shared by the navigation cores, the emulators and the estimators.

They live at the bottom layer so the navigation code (strapdown, trajectory) and the estimators
built on it share them without nav importing the estimators.

Shapes: ``n`` samples along axis 0. Frames: ``ned`` = local North-East-Down of the scenario
origin, ``b`` = body (x forward, y right, z down). Stamps are integer nanoseconds since run start.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import NDArray

F64 = NDArray[np.float64]
I64 = NDArray[np.int64]


@dataclass(frozen=True)
class TruthBatch:
    """True vehicle state at ``t_ns`` (true time)."""

    t_ns: I64  # (n,)
    lat_rad: F64  # (n,)
    lon_rad: F64  # (n,)
    alt_m: F64  # (n,) WGS84 ellipsoidal height
    pos_ned_m: F64  # (n, 3) relative to the scenario origin
    vel_ned_mps: F64  # (n, 3)
    q_nb: F64  # (n, 4) [w, x, y, z], body -> NED
    f_b_mps2: F64  # (n, 3) specific force in body axes
    w_ib_b_radps: F64  # (n, 3) inertial angular rate in body axes


@dataclass(frozen=True)
class NavState:
    """One estimator's solution; sigmas are None where the estimator has no covariance."""

    pos_ned_m: F64  # (3,)
    vel_ned_mps: F64  # (3,)
    q_nb: F64  # (4,)
    pos_sigma_m: F64 | None = None  # (3,)
    vel_sigma_mps: F64 | None = None  # (3,)
    att_sigma_rad: F64 | None = None  # (3,) attitude error about N, E, D: tilt, tilt, heading


class FloatNavState(NavState):
    """A solution whose position, velocity and attitude were computed as Python floats: the
    arrays are built when first read. The fusion publishes them as floats (the output
    predictor moves them on floats) at every output of every estimator, where building three
    arrays to read them back cost more than the arithmetic. Same values either way."""

    def __init__(
        self,
        pos_ned_m: Sequence[float],
        vel_ned_mps: Sequence[float],
        q_nb: Sequence[float],
        pos_sigma_m: F64 | None = None,
        vel_sigma_mps: F64 | None = None,
        att_sigma_rad: F64 | None = None,
    ) -> None:
        # a frozen dataclass: the fields are the properties below and __dict__ entries
        d = self.__dict__
        d["_pvq"] = (pos_ned_m, vel_ned_mps, q_nb)
        d["pos_sigma_m"], d["vel_sigma_mps"], d["att_sigma_rad"] = pos_sigma_m, vel_sigma_mps, att_sigma_rad

    @cached_property
    def pos_ned_m(self) -> F64:  # type: ignore[override]
        return np.array(self._pvq[0], dtype=np.float64)

    @cached_property
    def vel_ned_mps(self) -> F64:  # type: ignore[override]
        return np.array(self._pvq[1], dtype=np.float64)

    @cached_property
    def q_nb(self) -> F64:  # type: ignore[override]
        return np.array(self._pvq[2], dtype=np.float64)

    def floats(self) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
        """Position, velocity and attitude as given (Python floats)."""
        return self._pvq  # type: ignore[no-any-return]


def nav_floats(nav: Any) -> tuple[Sequence[float], Sequence[float], Sequence[float]]:
    """Position, velocity and attitude of a solution as Python floats: its own where it keeps
    floats (``floats()``: :class:`FloatNavState`, the strapdown's lazy state), else its arrays'."""
    get = getattr(nav, "floats", None)
    if get is not None:
        return get()  # type: ignore[no-any-return]
    return (
        np.asarray(nav.pos_ned_m, dtype=np.float64).tolist(),
        np.asarray(nav.vel_ned_mps, dtype=np.float64).tolist(),
        np.asarray(nav.q_nb, dtype=np.float64).tolist(),
    )


@dataclass(frozen=True)
class InitialState:
    """Where every estimator and the free INS start: the alignment the rig hands out at run start."""

    stamp_ns: int
    lat_rad: float
    lon_rad: float
    alt_m: float
    origin_lat_rad: float
    origin_lon_rad: float
    origin_alt_m: float
    vel_ned_mps: F64  # (3,)
    q_nb: F64  # (4,)

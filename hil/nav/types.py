"""Array containers shared by the navigation cores, the emulators and the estimators.

They live at the bottom layer so the navigation code (strapdown, trajectory) and the estimators
built on it share them without nav importing the estimators.

Shapes: ``n`` samples along axis 0. Frames: ``ned`` = local North-East-Down of the scenario
origin, ``b`` = body (x forward, y right, z down). Stamps are integer nanoseconds since run start.
"""

from __future__ import annotations

from dataclasses import dataclass

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

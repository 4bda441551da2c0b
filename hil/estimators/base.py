"""The contract every fusion estimator keeps, so the fusion core can run them side by side.

An estimator is a small state machine with no I/O and no clock: the fusion core feeds it
synchronised inputs in a total order (rig time of validity, then source, then seq) and reads
its solution. The same object runs live, in ``hil sim`` and in ``hil rerun``; given the same
input sequence it must produce bit-identical outputs (no global RNG, no dict-order tricks,
no threading).
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from hil.nav.types import F64, NavState
from hil.nav.types import InitialState as InitialState  # re-exported: nav needs it, below us


@dataclass(frozen=True)
class ImuInput:
    """One IMU interval ending at ``stamp_ns`` (rig time of validity)."""

    stamp_ns: int
    dt_s: float
    dtheta_b_rad: F64  # (3,) delta-angle over the interval
    dvel_b_mps: F64  # (3,) delta-velocity over the interval


@dataclass(frozen=True)
class GnssInput:
    """One GNSS fix valid at ``stamp_ns`` (rig time of validity, earlier than its arrival)."""

    stamp_ns: int
    pos_ned_m: F64  # (3,)
    vel_ned_mps: F64  # (3,)
    pos_sigma_m: F64  # (3,) receiver-reported 1-sigma, N E D
    vel_sigma_mps: F64  # (3,)


class Estimator(Protocol):
    """What the fusion core calls. ``ins`` is the shared free (uncorrected) INS after this step."""

    name: str

    def on_imu(self, imu: ImuInput, ins: NavState) -> None: ...

    def on_gnss(self, gnss: GnssInput, ins: NavState) -> None: ...

    def solution(self) -> NavState: ...

    def health(self) -> dict[str, float]:
        """Innovation test ratios, rejected-measurement counters, ... for the status topic."""
        ...

"""The contract every fusion estimator keeps, so the fusion core can run them side by side.

An estimator is a small state machine with no I/O and no clock: the fusion core feeds it
synchronised inputs in a total order (rig time of validity, then source, then seq) and reads
its solution. The same object runs live, in ``hil sim`` and in ``hil rerun``; given the same
input sequence it must produce bit-identical outputs (no global RNG, no dict-order tricks,
no threading).
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from hil.nav.types import F64, NavState
from hil.nav.types import InitialState as InitialState  # re-exported: nav needs it, below us


@dataclass(frozen=True)
class ImuInput:
    """One IMU interval ending at ``stamp_ns`` (rig time of validity)."""

    stamp_ns: int
    dt_s: float
    dtheta_b_rad: F64  # (3,) delta-angle over the interval
    dvel_b_mps: F64  # (3,) delta-velocity over the interval

    @cached_property
    def increments(self) -> tuple[float, float, float, float, float, float]:
        """Delta-angle and delta-velocity as six Python floats, made once for every estimator
        that steps a strapdown on them (six per sample on a consumer IMU: the same values as
        ``float(dtheta_b_rad[i])``, without a numpy scalar each)."""
        tx, ty, tz = np.asarray(self.dtheta_b_rad, dtype=np.float64).tolist()
        ux, uy, uz = np.asarray(self.dvel_b_mps, dtype=np.float64).tolist()
        return tx, ty, tz, ux, uy, uz


@dataclass(frozen=True)
class GnssInput:
    """One GNSS fix valid at ``stamp_ns`` (rig time of validity, earlier than its arrival)."""

    stamp_ns: int
    pos_ned_m: F64  # (3,)
    vel_ned_mps: F64  # (3,)
    pos_sigma_m: F64  # (3,) receiver-reported 1-sigma, N E D
    vel_sigma_mps: F64  # (3,)


class Estimator:
    """Base of every estimator: what the fusion core calls, with a no-op per measurement kind.

    ``on_imu`` propagates (every estimator must); ``on_<sensor>`` takes a measurement of that
    kind of ``hil.sensor_table`` and by default does nothing, so a sensor added to the table
    reaches the estimators that define its handler and leaves the others untouched.
    ``ins`` is the shared free (uncorrected) INS after this step.
    """

    name: str = "estimator"

    def on_imu(self, imu: ImuInput, ins: NavState) -> None:
        raise NotImplementedError(f"{type(self).__name__} must propagate on every IMU step")

    def on_gnss(self, gnss: GnssInput, ins: NavState) -> None:
        """No-op: an estimator that does not fuse GNSS ignores it."""

    def solution(self) -> NavState:
        raise NotImplementedError(f"{type(self).__name__} must say where it thinks it is")

    def health(self) -> dict[str, float]:
        """Innovation test ratios, NIS, gains, bias norms, counts: published as ``hil.EstimatorHealth``."""
        return {}

    def imu_bias(self) -> tuple[F64, F64] | None:
        """The gyro (rad/s) and accelerometer (m/s²) biases this estimator removes from the IMU
        increments, in body axes, or None if it removes none: the output predictor removes them
        too when it carries the estimator's state forward. Found as ``b_g``/``b_a`` on the
        estimator (ekf15) or on its feedback INS (``loop``, the seed family in feedback form)."""
        return imu_bias_of(self)

    def handler(self, sensor: str) -> Callable[[Any, NavState], None] | None:
        """The method taking ``sensor``'s measurements, or None if this estimator takes none
        (the base class's no-op, or no ``on_<sensor>`` at all): resolved once, not per input."""
        fn = getattr(type(self), f"on_{sensor}", None)
        if fn is None or fn is getattr(Estimator, f"on_{sensor}", None):
            return None
        bound: Callable[[Any, NavState], None] = getattr(self, f"on_{sensor}")
        return bound


def imu_bias_of(est: Any) -> tuple[F64, F64] | None:
    """``Estimator.imu_bias`` for any object keeping the contract (see there)."""
    for holder in (est, getattr(est, "loop", None)):
        b_g, b_a = getattr(holder, "b_g", None), getattr(holder, "b_a", None)
        if b_g is not None and b_a is not None:
            return np.asarray(b_g, dtype=np.float64), np.asarray(b_a, dtype=np.float64)
    return None


def gnss_input(msg: Any) -> GnssInput | None:
    """A GNSS fix as estimators take it; None if it is no position fix (fix type below 2D)."""
    if msg.fix_type < MIN_GNSS_FIX_TYPE:
        return None
    return GnssInput(
        stamp_ns=msg.stamp_ns,
        pos_ned_m=np.asarray(msg.pos_ned_m, dtype=np.float64),
        vel_ned_mps=np.asarray(msg.vel_ned_mps, dtype=np.float64),
        pos_sigma_m=np.asarray(msg.pos_sigma_m, dtype=np.float64),
        vel_sigma_mps=np.asarray(msg.vel_sigma_mps, dtype=np.float64),
    )


MIN_GNSS_FIX_TYPE = 2
#: sensor -> the measurement as estimators take it (None: refused, counted by the fusion as
#: ``<sensor>.unusable``). A sensor without an entry reaches its handlers as the message itself.
INPUTS: dict[str, Callable[[Any], Any]] = {"gnss": gnss_input}

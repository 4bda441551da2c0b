"""The contract every fusion estimator keeps, so the fusion core can run them side by side.

An estimator is a small state machine with no I/O and no clock: the fusion core feeds it
synchronised inputs in a total order (rig time of validity, then source, then seq) and reads
its solution. The same object runs live, in ``hil sim`` and in ``hil rerun``; given the same
input sequence it must produce bit-identical outputs (no global RNG, no dict-order tricks,
no threading).
"""

from __future__ import annotations

from collections.abc import Callable, Iterator
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np

from hil.nav import strapdown
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


class ImuBlock:
    """IMU intervals in the total order, handed to the estimators together (``on_imu_block``).

    The fusion core defers its estimators' IMU steps until something reads them (a solution, an
    aiding measurement, health): between two outputs at 400 Hz that is ~8 samples, and one call per
    estimator for the run of them, with one compiled loop inside, replaces eight calls of Python
    glue each. ``rows`` holds per interval ``dt_s`` then the six increments (Δθ, Δv) as the floats
    ``ImuInput.increments`` gives; ``ins`` the shared free INS after each interval.
    """

    __slots__ = ("_array", "_inputs", "ins", "rows", "stamps_ns")

    def __init__(self) -> None:
        self.stamps_ns: list[int] = []
        self.rows: list[tuple[float, float, float, float, float, float, float]] = []
        self.ins: list[NavState] = []
        self._inputs: list[ImuInput] | None = None
        self._array: F64 | None = None

    @classmethod
    def of(cls, imu: ImuInput, ins: NavState | None = None) -> ImuBlock:
        """One interval as a block: an estimator's ``on_imu`` is its ``on_imu_block`` of one."""
        block = cls()
        block.append(imu.stamp_ns, (imu.dt_s, *imu.increments), ins)  # type: ignore[arg-type]
        return block

    def __len__(self) -> int:
        return len(self.stamps_ns)

    def append(
        self, stamp_ns: int, row: tuple[float, float, float, float, float, float, float], ins: NavState
    ) -> None:
        self.stamps_ns.append(stamp_ns)
        self.rows.append(row)
        self.ins.append(ins)

    def inputs(self) -> list[ImuInput]:
        """Each interval as the ``ImuInput`` a per-sample ``on_imu`` takes (made once, shared)."""
        if self._inputs is None:
            self._inputs = [
                ImuInput(t, r[0], np.array(r[1:4], dtype=np.float64), np.array(r[4:7], dtype=np.float64))
                for t, r in zip(self.stamps_ns, self.rows, strict=True)
            ]
        return self._inputs

    def strapdown_run(self) -> tuple[Callable[..., Any], Any]:
        """The strapdown run kernel in place (:func:`hil.nav.strapdown._corrected_run`, read
        once: the compiled one may be put in place meanwhile) and the rows as it takes them."""
        run = strapdown._corrected_run
        return run, (self.rows if run is strapdown._PY_CORRECTED_RUN else self.array())

    def runs(self, every: int, pending: int) -> Iterator[tuple[int, int]]:
        """``(start, stop)`` of the runs between two covariance predictions made every ``every``
        intervals, ``pending`` of them taken since the last one (the caller predicts after each
        run that reaches ``every``, which starts the count again)."""
        start, n = 0, len(self.stamps_ns)
        while start < n:
            stop = min(n, start + max(1, every - pending))
            yield start, stop
            pending = 0 if pending + stop - start >= every else pending + stop - start
            start = stop

    def array(self) -> F64:
        """``rows`` as a C-contiguous (n, 7) float64 array (what a compiled loop takes)."""
        if self._array is None:
            self._array = np.array(self.rows, dtype=np.float64).reshape(len(self.rows), 7)
        return self._array


@dataclass(frozen=True)
class GnssInput:
    """One GNSS fix valid at ``stamp_ns`` (rig time of validity, earlier than its arrival)."""

    stamp_ns: int
    pos_ned_m: F64  # (3,)
    vel_ned_mps: F64  # (3,)
    pos_sigma_m: F64  # (3,) receiver-reported 1-sigma, N E D
    vel_sigma_mps: F64  # (3,)

    @classmethod
    def of_batch(cls, fixes: Any, i: int) -> GnssInput:
        """Fix ``i`` of a receiver model's batch (``hil.sensors.gnss.GnssBatch``), as estimators
        take it: what a bench or test feeding estimators directly hands them."""
        return cls(
            int(fixes.t_valid_ns[i]),
            fixes.pos_ned_m[i],
            fixes.vel_ned_mps[i],
            fixes.pos_sigma_m[i],
            fixes.vel_sigma_mps[i],
        )


class Estimator:
    """Base of every estimator: what the fusion core calls, with a no-op per measurement kind.

    ``on_imu`` propagates (every estimator must); ``on_<sensor>`` takes a measurement of that
    kind of ``hil.sensor_table`` and by default does nothing, so a sensor added to the table
    reaches the estimators that define its handler and leaves the others untouched.
    ``ins`` is the shared free (uncorrected) INS after this step. An estimator may also define
    ``on_imu_block(block)``, taking an :class:`ImuBlock` of intervals at once (one compiled loop for
    the run of them); it must leave the state ``on_imu`` of each would (the fusion core calls it
    where defined: ``hil.fusion.core.block_step_of``).
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


def _bias_holder(est: Any) -> Any:
    """Where ``est`` keeps its IMU bias estimates: itself (ekf15) or its feedback INS (``loop``);
    None if it keeps none."""
    for holder in (est, getattr(est, "loop", None)):
        if getattr(holder, "b_g", None) is not None and getattr(holder, "b_a", None) is not None:
            return holder
    return None


def imu_bias_of(est: Any) -> tuple[F64, F64] | None:
    """``Estimator.imu_bias`` for any object keeping the contract (see there)."""
    holder = _bias_holder(est)
    if holder is None:
        return None
    return np.asarray(holder.b_g, dtype=np.float64), np.asarray(holder.b_a, dtype=np.float64)


def imu_bias_floats_of(est: Any) -> tuple[float, ...] | None:
    """:func:`imu_bias_of` as the six floats the output predictor takes (``b_g`` then ``b_a``),
    read where its holder keeps them as floats (``bias_floats``: a feedback INS) -- at every
    output of every estimator, where two arrays built to be read back cost more."""
    holder = _bias_holder(est)
    if holder is None:
        return None
    kept = getattr(holder, "bias_floats", None)
    if kept is not None:
        return kept()  # type: ignore[no-any-return]
    g, a = imu_bias_of(holder)  # type: ignore[misc]
    return (*g.tolist(), *a.tolist())


def aligned_nav(init: InitialState) -> NavState:
    """Where the alignment puts the vehicle, in the origin's NED: what an estimator that reads
    the free INS only at its IMU steps solves before its first one (the first ``lag`` of a run).

    At run start that is the origin (exact zeros, as before); a fusion restarted mid-run is
    aligned hundreds of metres from it (``FusionCore.for_scenario``'s ``align_ns``), and the
    origin there was a wrong solution the output predictor carried for the whole lag."""
    at = (init.lat_rad, init.lon_rad, init.alt_m)
    if at == (init.origin_lat_rad, init.origin_lon_rad, init.origin_alt_m):
        pos = np.zeros(3)
    else:
        pos = strapdown.to_nav_state(strapdown.strapdown_from_initial(init), init).pos_ned_m
    vel = np.asarray(init.vel_ned_mps, dtype=np.float64).copy()
    return NavState(pos, vel, np.asarray(init.q_nb, dtype=np.float64).copy())


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

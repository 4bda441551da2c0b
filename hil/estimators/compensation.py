"""Compensation scheme (seed 000, Filyashkin & Demyanchuk): ``X̂ = X_INS − F(p)(X_INS − X_GNSS)``.

With ``X_INS = X + ξ1`` and ``X_GNSS = X + ξ2`` the output is ``X̂ = X + [1 − F]ξ1 + F ξ2``: the
true motion ``X`` passes untouched, ``F`` (low pass) keeps the slow INS error ``ξ1`` and rejects
the fast GNSS noise ``ξ2``. The filter runs per axis on the six channels
``[pos N, pos E, pos D, vel N, vel E, vel D]``; its output ``y = F·d`` is the INS error estimate.

Two rates, handled deliberately:

* the filter **input** ``d = X_INS − X_GNSS`` exists only at GNSS epochs (1–10 Hz). It is formed
  at the GNSS *time of validity* (INS position extrapolated to that instant with the INS
  velocity) and continued until the next epoch as a ramp: position channels with the
  INS-minus-GNSS velocity difference as slope (the INS position error rate), velocity channels
  held. Holding the position difference would lag a drifting INS error by half a GNSS interval;
* the filter **state** is advanced to every IMU stamp (400 Hz) with the exact ZOH transition for
  that step (:mod:`hil.estimators.lti`), so the published solution is valid at the IMU stamp.
  The input change is placed at the GNSS time of validity exactly: if the fix is later than the
  state, the state is first advanced to it; if it is earlier (the fusion core may deliver it just
  after the IMU step that straddles it), the state is corrected retroactively with
  ``x += Γ0(δ)(d_new − d_old(t_g)) + Γ1(δ)(s_new − s_old)``, exact for an LTI filter.

**Coast through a GNSS gap** (``coast_after``, cf3's default, open loop only): continuing the
last difference at its last rate feeds a third-order loop one fix's noise (σ of a position, and
of a velocity times the gap) for the whole gap, and the loop, whose poles are 40 s slow, carries
it long after the fixes return. So once the input is ``coast_after`` expected intervals overdue,
the filter coasts as a complementary filter does in a gap (seed 003's loop form ``y = (k1/s +
k2/s² + k3/s³)·e``, ``e = u − y``): its integrators -- the INS error's rate and acceleration --
are held and extrapolated, and the innovation ``e`` is held at its recent mean ``ē`` (over
``innovation_tau_s``) instead of the last noisy one: ``u = y + ē``, ``ẋ = (A + B C) x + B ē``,
exact per step. In steady state on a cubic INS error (a tilt growing from a gyro bias) the loop
runs on a constant innovation (jerk/k3), so with ``ē`` it goes on as if the fixes had not
stopped; with ``ē`` = 0 (a pure integrator hold) it would drop the cubic term. τ = 3 s (30 fixes
at 10 Hz) is short enough to follow the innovation while the slow loop is still settling: over
12 seeds of the gate scenario it took the gap's window error from 3.23 to 3.22 m RMS over the
seeds, lower on 9 of 12 (5 s: 3.35 m, 6 of 12; 10 s: 3.63 m). The first fix back ends the coast
at its time of validity (stepped back to it exactly if it arrives after the IMU step that
straddles it). Regular fixes never reach the threshold, so the aided output is bit for bit the
filter without a coast. Strictly proper filters only (``y`` must not read ``u``).

Variable structure (the paper's time-scheduled table, restarting when GNSS returns after an
outage) and its **bumpless transfer**: at each structure switch the new state is chosen so that
the new filter is in the steady state it would have reached while tracking the straight line
through the old output ``y`` with the old output slope ``ẏ``:

    y_new = y_old,   ẏ_new = ẏ_old (only if the old structure has relative degree ≥ 2),
    y_new^(k) = 0 for k ≥ 2,        solved as  O_new x_new = targets − (input feed-through)

where ``O = [C; C A; C A²]`` is the new structure's observability matrix and the feed-through
terms are evaluated for the ramp input ``u(t) = y + ẏ t``. The output is therefore continuous at
every switch, and its slope is continuous too when the old structure smooths it (the forcing
filters, relative degree 2). The slope of the 1/(0.5p+1) start-up stage is
``(u − y)/0.5 s`` — raw GNSS noise amplified — so it is not carried (slope 0 instead). For the
forcing filters (``1 − F`` has a double zero) this state is exactly the ramp-tracking steady
state, so the switch injects no transient at all into a ramp-like INS error.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from hil.estimators.base import Estimator, GnssInput, ImuBlock, ImuInput, InitialState, aligned_nav
from hil.estimators.feedback import ClosedLoopIns
from hil.estimators.lti import (
    StateSpace,
    TransferFunction,
    aperiodic,
    complementary2,
    complementary3,
    forcing3,
    shared_zoh_cache,
    stacked_step,
)
from hil.nav.portable import c_einsum, dot, mv, norm, solve
from hil.nav.types import F64, FloatNavState, NavState, nav_floats

#: The variable-structure table of seed 000: (time since (re)start of fusion in s, F(p)).
#: The last numerator (15 p + 1) is reconstructed from the 3 T p + 1 pattern (OCR lost it).
VS_SCHEDULE: tuple[tuple[float, TransferFunction], ...] = (
    (0.0, aperiodic(1, 0.5)),
    (1.5, forcing3(1.0)),
    (9.0, forcing3(3.0)),
    (45.0, forcing3(5.0)),
)


def _ramp_step(m: F64, x: F64, u: F64, s: F64, h_s: float) -> None:
    """One step of the filter's state under the ramp input ``u + s τ``, exact over ``h``, in
    place: ``x ← Φ(h) x + Γ0(h) u + Γ1(h) s`` for ``m = [Φ | Γ0 | Γ1]``, as one product
    (stacked_step's order), and ``u ←`` the input ``u + s h`` at the step's end. Runs at IMU rate
    for every channel set; :mod:`hil.runtime.jit` puts its loop form
    (:func:`hil.nav.kernels.ramp_step`) in its place. ``x`` and ``u`` are the core's own arrays
    (every other change of them makes new ones), so no one else sees them change."""
    n = x.shape[0]
    z = np.empty((n + 2, x.shape[1]))
    z[:n] = x
    z[n] = u
    z[n + 1] = s
    x[...] = c_einsum("ij,jk->ik", m, z)
    u += s * h_s


def _filter_output(x: F64, c: F64, d: float, u: F64) -> F64:
    """``y = C x + D u`` per channel (``x`` (n, channels), ``u`` (channels,)): read at every
    published solution; :mod:`hil.runtime.jit` puts its loop form
    (:func:`hil.nav.kernels.filter_output`) in its place where it gives these bits."""
    return mv(x.T, c) + d * u


def relative_degree(tf: TransferFunction) -> int:
    """deg(den) − deg(num): how many output derivatives are free of the raw input."""
    num = np.trim_zeros(np.asarray(tf.num, float), "f")
    return len(tf.den) - len(num)


@dataclass(frozen=True)
class Stage:
    """One structure of a (possibly variable-structure) compensation filter."""

    start_s: float
    tf: TransferFunction
    ss: StateSpace


class CompensationCore:
    """``y = F(p)·d`` on ``n_channels`` independent channels, advanced on integer-ns stamps.

    Pure numerics: no clock, no I/O. ``x`` has shape ``(n, n_channels)``, ``u`` ``(n_channels,)``.
    The schedule's clock starts at the first input and restarts when an input arrives more than
    ``restart_after_s`` after the previous one (GNSS back after an outage).
    """

    def __init__(
        self,
        schedule: Sequence[tuple[float, TransferFunction]],
        n_channels: int,
        restart_after_s: float | None = None,
        coast_after: float | None = None,
        innovation_tau_s: float = 3.0,
    ) -> None:
        if not schedule or schedule[0][0] != 0.0:
            raise ValueError(f"schedule must start at 0 s, got {[s for s, _ in schedule]}")
        self.stages = tuple(Stage(s, tf, StateSpace.from_tf(tf)) for s, tf in schedule)
        self._caches = tuple(shared_zoh_cache(st.ss) for st in self.stages)
        if coast_after is not None and (
            not coast_after > 1.0 or not innovation_tau_s > 0.0 or any(st.ss.d != 0.0 for st in self.stages)
        ):
            raise ValueError(
                f"a coast needs coast_after > 1 input interval (got {coast_after!r}), innovation_tau_s > 0 "
                f"(got {innovation_tau_s!r}) and strictly proper filters"
            )
        self.coast_after = coast_after
        self.innovation_tau_s = innovation_tau_s
        # the coast: the loop driven by its held mean innovation ē, u = y + ē: ẋ = (A + B C) x + B ē
        coast_ss = [StateSpace(s.ss.a + np.outer(s.ss.b, s.ss.c), s.ss.b, s.ss.c, 0.0) for s in self.stages]
        self._coast_caches = tuple(shared_zoh_cache(ss, ramp=False) for ss in coast_ss)
        self._ramp_states = tuple(_ramp_state_terms(st.ss) for st in self.stages)
        self._start_offsets_ns = tuple(round(st.start_s * 1e9) for st in self.stages)
        self.restart_after_ns = None if restart_after_s is None else round(restart_after_s * 1e9)
        self.n_channels = n_channels
        self.stage = 0
        self.x: F64 = np.zeros((self.stages[0].ss.order, n_channels))
        self.u: F64 = np.zeros(n_channels)
        self.slope: F64 = np.zeros(n_channels)
        self.t_ns: int | None = None
        self.t_start_ns: int | None = None
        self.t_last_input_ns: int | None = None
        self.restarts = 0
        self.switches = 0
        self.coasting = False
        self.holding_line = False  # on hold_line's line since an overdue input (the estimator's)
        self.coasts = 0
        self._interval_ns: int | None = None  # the input interval expected (see _coast_start_ns)
        self._coast_from_ns: int | None = None
        self.innovation_mean: F64 = np.zeros(n_channels)  # ē: the innovation u − y, averaged over τ

    # -- propagation ---------------------------------------------------------------------------
    def _step(self, h_ns: int) -> None:
        if self.coasting:
            self._coast_step(h_ns)
            return
        _ramp_step(self._caches[self.stage].stacked(h_ns), self.x, self.u, self.slope, h_ns * 1e-9)

    def _coast_step(self, h_ns: int) -> None:
        """``x+ = Φc(h) x + Γc(h) ē`` (h < 0 steps back exactly). The held ramp ``u, s`` stays as
        it was when the coast began: a strictly proper filter's output does not read it."""
        self.x = stacked_step(self._coast_caches[self.stage].stacked(h_ns), self.x, self.innovation_mean)

    def _next_boundary_ns(self) -> int | None:
        if self.t_start_ns is None or self.stage + 1 >= len(self.stages):
            return None
        return self.t_start_ns + self._start_offsets_ns[self.stage + 1]

    def _coast_start_ns(self) -> int | None:
        """When the input is overdue: ``coast_after`` expected intervals after the last one."""
        if self.coasting or self.coast_after is None or self._interval_ns is None:
            return None
        assert self.t_last_input_ns is not None
        return self.t_last_input_ns + round(self.coast_after * self._interval_ns)

    def advance_to(self, t_ns: int) -> None:
        """Propagate the state to ``t_ns`` with the held input, switching structure on time."""
        if self.t_ns is None:
            self.t_ns = t_ns
            return
        if t_ns <= self.t_ns:
            return
        boundary = self._next_boundary_ns()
        coast = self._coast_start_ns()
        if (boundary is None or boundary > t_ns) and (coast is None or coast > t_ns):
            self._step(t_ns - self.t_ns)  # the IMU-rate case: neither a switch nor a coast falls due
            self.t_ns = t_ns
            return
        while t_ns > self.t_ns:
            boundary = self._next_boundary_ns()
            coast = self._coast_start_ns()
            t_end = min(t for t in (t_ns, boundary, coast) if t is not None)
            if t_end > self.t_ns:
                self._step(t_end - self.t_ns)
                self.t_ns = t_end
            if coast is not None and t_end == coast:
                self.coasting = True
                self.coasts += 1
                self._coast_from_ns = max(coast, self.t_ns)
            if boundary is not None and t_end == boundary:
                self.switch_to(self.stage + 1)

    def advance_run(self, stamps_ns: Sequence[int], start: int, until_ns: int | None) -> int:
        """``advance_to`` of ``stamps_ns[start:]`` in turn while each is a plain IMU-rate step
        (before the next structure switch and the next coast, at or before ``until_ns``), their
        conditions checked once for the run (per stamp they cost more than the compiled step);
        the index of the first stamp not taken (the caller takes it with ``advance_to``, which
        handles what falls due)."""
        t = self.t_ns
        if t is None or self.coasting:
            return start
        boundary, coast = self._next_boundary_ns(), self._coast_start_ns()
        ends = [x for x in (boundary, coast) if x is not None]
        end = min(ends) if ends else None  # the first instant a step may not reach
        stacked, step = self._caches[self.stage].stacked, _ramp_step
        x, u, slope = self.x, self.u, self.slope  # stepped in place
        stop = start
        for stamp in stamps_ns[start:]:
            if (end is not None and stamp >= end) or (until_ns is not None and stamp > until_ns):
                break
            if stamp > t:
                step(stacked(stamp - t), x, u, slope, (stamp - t) * 1e-9)
                t = stamp
            stop += 1
        self.t_ns = t
        return stop

    # -- inputs ----------------------------------------------------------------------------------
    def set_input(self, t_ns: int, d: F64, slope: F64 | None = None) -> None:
        """The difference ``d = X_INS − X_GNSS`` at ``t_ns``, continued as ``d + slope (t − t_ns)``.

        ``slope`` (per second) defaults to 0 (zero-order hold).
        """
        d = np.asarray(d, dtype=float)
        s = np.zeros_like(d) if slope is None else np.asarray(slope, dtype=float)
        restart = (
            self.t_last_input_ns is not None
            and self.restart_after_ns is not None
            and t_ns - self.t_last_input_ns > self.restart_after_ns
        )
        if self.t_ns is not None and t_ns >= self.t_ns:
            self.advance_to(t_ns)  # a coast that falls due before the input starts first
        t_resume = self._end_coast(t_ns) if self.coasting else None
        self._learn_interval(t_ns, ended_coast=t_resume is not None or self.holding_line)
        self.holding_line = False
        if self.coast_after is not None and self._interval_ns is not None:
            # per input, the weight of one nominal interval in τ (an outage's length is not a
            # weight: the first fix after it is one fix); y at the state's stamp, which is the
            # fix's or at most one IMU step after it
            w = 1.0 - math.exp(-self._interval_ns * 1e-9 / self.innovation_tau_s)
            self.innovation_mean = self.innovation_mean + w * (d - self.output() - self.innovation_mean)
        if self.t_ns is None or t_ns >= self.t_ns:
            self.advance_to(t_ns)
        else:
            # Input change in the past by δ: the input since t_g was u_old(t_g) + s_old τ and
            # should have been d + s τ, so x += Γ0(δ)(d − u_old(t_g)) + Γ1(δ)(s − s_old).
            delta_ns = self.t_ns - t_ns
            _, gamma0, gamma1 = self._caches[self.stage].get(delta_ns)
            u_old_at_tg = self.u - self.slope * (delta_ns * 1e-9)
            self.x = self.x + np.outer(gamma0, d - u_old_at_tg) + np.outer(gamma1, s - self.slope)
            d = d + s * (delta_ns * 1e-9)
        if self.t_start_ns is None:
            self.t_start_ns = t_ns
        elif restart:
            self.t_start_ns = t_ns
            self.restarts += 1
            if len(self.stages) > 1:
                self.switch_to(0)
        self.u = d.copy()
        self.slope = s.copy()
        self.t_last_input_ns = t_ns
        if t_resume is not None:
            self.advance_to(t_resume)

    def _end_coast(self, t_ns: int) -> int:
        """Leave the coast for an input at ``t_ns``; returns the state's stamp to come back to.

        An input stamped before the state (delivered just after the IMU step that straddles it)
        rewinds the coast to it exactly -- ``Φ_coast(−δ)``, or to where the coast began if that
        is later -- so the input then takes effect at its time of validity as it always does.
        """
        assert self.t_ns is not None and self._coast_from_ns is not None
        t_now = self.t_ns
        t_back = max(t_ns, self._coast_from_ns)
        if t_back < t_now:
            self._coast_step(t_back - t_now)
            self.t_ns = t_back
        self.coasting = False
        return t_now

    def _learn_interval(self, t_ns: int, ended_coast: bool) -> None:
        """The input interval a coast waits for: the last one, unless it ended a coast (an
        outage); then at most twice the one expected before, so a lower rate is learnt in a few
        inputs and an outage is not taken for one."""
        if self.t_last_input_ns is None or t_ns <= self.t_last_input_ns:
            return
        gap = t_ns - self.t_last_input_ns
        if ended_coast and self._interval_ns is not None:
            gap = min(gap, 2 * self._interval_ns)
        self._interval_ns = gap

    def shift(self, c0: F64, c1: F64) -> None:
        """The input drops by ``c0 + c1 τ`` from now on (the INS was reset by that much): move the
        state to the one the filter would have had for an input without it.

        The filter is linear, so subtracting the steady state it reaches on the ramp input
        ``c0 + c1 t`` (``x_p = −A⁻¹B c0 − A⁻²B c1``) from its state and the ramp from its held
        input leaves its response to everything else untouched: the solution ``X_INS − y`` with
        the reset INS is the one it would have been, for every filter of this module.
        """
        a1b, a2b = self._ramp_states[self.stage]
        self.x = self.x + a1b[:, None] * c0[None, :] + a2b[:, None] * c1[None, :]
        self.u = self.u - c0
        self.slope = self.slope - c1

    # -- outputs ---------------------------------------------------------------------------------
    def output(self) -> F64:
        """``y = C x + D u``: the INS error estimate per channel."""
        ss = self.stages[self.stage].ss
        return _filter_output(self.x, ss.c, ss.d, self.u)

    def switch_to(self, stage: int) -> None:
        """Bumpless structure switch (see module docstring for the rule and why)."""
        old = self.stages[self.stage]
        y = self.output()
        # ẏ = C A x when C B = 0 and D = 0 (relative degree ≥ 2); else not carried (0)
        ca = mv(old.ss.a.T, old.ss.c)  # row C A
        ydot = mv(self.x.T, ca) if relative_degree(old.tf) >= 2 else np.zeros_like(y)
        self._settle_on_line(stage, y, ydot)
        self.switches += 1

    def hold_line(self, t_ns: int, y: F64, ydot: F64) -> None:
        """From ``t_ns`` on, the input is the line ``y + ẏ (t − t_ns)`` and the state the one the
        filter has after tracking it (the switch's steady state): the output continues along the
        line. For a GNSS gap (:class:`CompensationEstimator`); the schedule's clock and the
        restart rule still go by the last real input."""
        self.advance_to(t_ns)
        y, ydot = np.asarray(y, dtype=float), np.asarray(ydot, dtype=float)
        self._settle_on_line(self.stage, y, ydot)
        self.u = y.copy()
        self.slope = ydot.copy()
        self.holding_line = True

    def overdue_ns(self, intervals: float) -> int | None:
        """When the next input is ``intervals`` expected input intervals late (None: no interval
        learnt yet, or already on a held line)."""
        if self.holding_line or self.coasting or self._interval_ns is None or self.t_last_input_ns is None:
            return None
        return self.t_last_input_ns + round(intervals * self._interval_ns)

    def _settle_on_line(self, stage: int, y: F64, ydot: F64) -> None:
        new = self.stages[stage]
        n = new.ss.order
        targets = np.zeros((n, self.n_channels))
        targets[0] = y
        if n > 1:
            targets[1] = ydot
        # Feed-through of the ramp input u(t) = y + ẏ t into y^(k):
        #   y^(k) = C A^k x + Σ_{j<k} C A^{k-1-j} B u^(j) + D u^(k),  u^(0) = y, u^(1) = ẏ
        a, b, c, dd = new.ss.a, new.ss.b, new.ss.c, new.ss.d
        u_derivs = (y, ydot)
        cak = [c]
        for _ in range(n):
            cak.append(mv(a.T, cak[-1]))
        for k in range(n):
            feed = dd * u_derivs[k] if k < 2 else np.zeros_like(y)
            for j in range(min(k, 2)):
                feed = feed + dot(cak[k - 1 - j], b) * u_derivs[j]
            targets[k] = targets[k] - feed
        self.x = solve(new.ss.observability(), targets)
        self.stage = stage


def _ramp_state_terms(ss: StateSpace) -> tuple[F64, F64]:
    """``(A⁻¹B, A⁻²B)``: the steady state on a ramp input is ``−A⁻¹B u − A⁻²B u̇``."""
    a1b = solve(ss.a, ss.b)
    return a1b, solve(ss.a, a1b)


#: A GNSS gap is this many of the receiver's fix intervals without a fix (10 Hz: 0.25 s).
COAST_AFTER_INTERVALS = 2.5


def seconds_since(t_ns: int, t0_ns: int | None) -> float:
    return float("nan") if t0_ns is None else (t_ns - t0_ns) * 1e-9


class CompensationEstimator(Estimator):
    """Live compensation scheme on position and velocity, every axis on its own.

    Open loop (``feedback`` None, the papers' form): the corrected solution is ``X̂ = X_INS − y``
    of the shared free INS at the last IMU stamp; attitude is the free INS's (the scheme
    estimates no attitude error). Feedback form (``feedback`` the parameters of
    :class:`hil.estimators.feedback.ClosedLoopIns`): the same filter on an INS of its own that
    its estimate resets and a velocity-matching corrector keeps level (module
    :mod:`hil.estimators.feedback`). No covariance either way, so sigmas are ``None``.
    """

    def __init__(
        self,
        name: str,
        init: InitialState,
        schedule: Sequence[tuple[float, TransferFunction]],
        restart_after_s: float | None = 3.0,
        feedback: dict[str, Any] | None = None,
        coast_after: float | None = None,
        innovation_tau_s: float = 3.0,
        line_coast: bool = True,
    ) -> None:
        self.name = name
        # Two coasts through a GNSS gap. ``line_coast``: on the line the velocity channels'
        # estimate draws (``_coast``), every filter's by default. ``coast_after`` (cf3): the
        # third-order loop on its own integrators and mean innovation (``CompensationCore``),
        # in the open loop only: there the filter is the only model of the INS error. In the
        # feedback form the corrector changes the INS behind the filter's integrators (they are
        # no model of it: coasting on them took cf3 from 2.3 m to 8.2 m in car_drive's tunnel),
        # and the INS, reset and bias-corrected, is itself what coasts.
        self.line_coast = line_coast and coast_after is None
        coast = coast_after if feedback is None else None
        self._core_args = (schedule, 6, restart_after_s, coast, innovation_tau_s)
        self.core = CompensationCore(*self._core_args)
        self.core.advance_to(init.stamp_ns)
        self.loop = None if feedback is None else ClosedLoopIns(init, **feedback)
        self._ins: NavState | None = None
        self._ins_stamp_ns = init.stamp_ns
        self._init = init  # where it stands before its first IMU step: aligned_nav
        self._gnss_count = 0
        self._last_diff_pos_m = 0.0
        self.coasts = 0

    def on_imu(self, imu: ImuInput, ins: NavState) -> None:
        self.on_imu_block(ImuBlock.of(imu, ins))

    def on_imu_block(self, block: ImuBlock) -> None:
        """The block's intervals in order: the filter stepped per interval (its coast can fall due
        between two), the feedback INS in one call for the block (the two share nothing)."""
        core, line_coast, stamps = self.core, self.line_coast, block.stamps_ns
        i, n = 0, len(stamps)
        while i < n:
            t_c = core.overdue_ns(COAST_AFTER_INTERVALS) if line_coast else None
            i = core.advance_run(stamps, i, t_c)  # the plain steps, up to what falls due
            if i == n:
                break
            if t_c is not None and stamps[i] > t_c:
                self._coast(t_c)
            core.advance_to(stamps[i])
            i += 1
        if self.loop is not None:
            self.loop.propagate_block(block)
            return
        self._ins = block.ins[-1]
        self._ins_stamp_ns = block.stamps_ns[-1]

    def on_gnss(self, gnss: GnssInput, ins: NavState) -> None:
        if self.loop is not None:
            self._on_gnss_feedback(gnss, self.loop)
            return
        # INS position at the GNSS time of validity: p(t_g) ≈ p(t_imu) + v (t_g − t_imu)
        dt_s = (gnss.stamp_ns - self._ins_stamp_ns) * 1e-9
        pos_ins = ins.pos_ned_m + ins.vel_ned_mps * dt_s
        dv = ins.vel_ned_mps - gnss.vel_ned_mps
        self._input(gnss, pos_ins - gnss.pos_ned_m, dv)

    def restart_on_gnss(self, gnss: GnssInput, ins: NavState) -> None:
        """The fusion re-initialised the free INS on this fix (its gate's rule 4, after an IMU
        fault): the error the filter estimated of the INS before is not this one's, so it starts
        again at this fix, as at its start. Open loop it corrects that free INS from now on; in the
        feedback form its own INS, which the fault left as far off, is taken from it
        (``ClosedLoopIns.reinitialise``)."""
        self.core = CompensationCore(*self._core_args)
        self.core.advance_to(gnss.stamp_ns)
        if self.loop is None:
            self._ins = ins
        else:  # its own INS, as far off: taken from the free INS just re-initialised
            self.loop.reinitialise(ins)
        self.on_gnss(gnss, ins)

    def _input(self, gnss: GnssInput, dp: F64, dv: F64) -> None:
        d = np.concatenate([dp, dv])
        # Between fixes the position difference drifts at the velocity difference (the INS
        # position error rate): continue it as a ramp rather than holding it.
        self.core.set_input(gnss.stamp_ns, d, np.concatenate([dv, np.zeros(3)]))
        self._gnss_count += 1
        self._last_diff_pos_m = norm(dp)

    def _coast(self, t_c: int) -> None:
        """GNSS gap: the last fix's difference, continued as a ramp, carries that one fix's noise
        (σ of the receiver, metres) and its velocity difference's (σ 0.2 m/s: metres after 10 s)
        into every second of the gap, and the filter converges onto it. Continue instead on the
        filter's own estimate: the position error on the line the velocity channels' estimate of
        the INS velocity error draws (δṗ = δv, the INS error dynamics to first order), the velocity
        error held. That is what the filter had learnt from every fix before, not from the last."""
        self.core.advance_to(t_c)
        y = self.core.output()
        self.core.hold_line(t_c, y, np.concatenate([y[3:], np.zeros(3)]))
        self.coasts += 1

    def _on_gnss_feedback(self, gnss: GnssInput, loop: ClosedLoopIns) -> None:
        """Feedback form: corrector, the filter on its own INS, then the INS reset by ``y``."""
        dp, dv = loop.antenna_difference(gnss)
        loop.correct(dv, gnss)
        self._input(gnss, dp, dv)
        y = self.core.output()
        loop.reset(y[:3], y[3:])
        # the INS position error now grows slower by y_vel: a ramp out of the position channels
        self.core.shift(y, np.concatenate([y[3:], np.zeros(3)]))

    def solution(self) -> NavState:
        att_sigma = None
        if self.loop is not None:
            nav = self.loop.nav()
            att_sigma = self.loop.att_sigma_rad()
        elif self._ins is None:
            return aligned_nav(self._init)
        else:
            nav = self._ins
        y0, y1, y2, y3, y4, y5 = self.core.output().tolist()
        (p0, p1, p2), (v0, v1, v2), q = nav_floats(nav)  # X_INS − y on floats: the arrays' values
        return FloatNavState(
            (p0 - y0, p1 - y1, p2 - y2), (v0 - y3, v1 - y4, v2 - y5), q, att_sigma_rad=att_sigma
        )

    def health(self) -> dict[str, float]:
        core = self.core
        out = {
            "gnss_count": float(self._gnss_count),
            "stage": float(core.stage),
            "restarts": float(core.restarts),
            "since_start_s": seconds_since(core.t_ns or 0, core.t_start_ns),
            "ins_minus_gnss_pos_m": self._last_diff_pos_m,
            "coasting": float(self.core.holding_line),
            "coasts": float(self.coasts),
        }
        if core.coast_after is not None:
            out |= {"coasting": float(core.coasting), "coasts": float(core.coasts)}
        return out | (self.loop.health() if self.loop is not None else {})


#: Fixed filters by registry name (classic T = 5 s as in the paper; the higher orders share T).
def fixed_filter(kind: str, t_s: float = 5.0) -> TransferFunction:
    """The fixed-structure compensation filters of seed 000 by short name."""
    if kind == "comp1":
        return aperiodic(1, t_s)
    if kind == "comp2":
        return aperiodic(2, t_s)
    if kind == "comp3":
        return aperiodic(3, t_s)
    if kind == "comp3f":
        return forcing3(t_s)
    raise KeyError(f"unknown fixed compensation filter {kind!r}")


__all__ = [
    "VS_SCHEDULE",
    "CompensationCore",
    "CompensationEstimator",
    "complementary2",
    "complementary3",
    "fixed_filter",
    "relative_degree",
]

"""GNSS integrity at the fusion's ingress: a fix reaches no estimator unless the INS agrees with it.

A fix is a claim -- a position, a velocity and the σ the receiver says they have -- and anything
on the bus can make one. Three rules, applied by the fusion core around every estimator's GNSS
update (``FusionCore``; the estimators themselves are untouched):

1. **σ floored at the receiver model.** A fix's claimed σ is never smaller than the scenario's
   receiver model (``[gnss]`` ``pos_sigma_m``/``vel_sigma_mps``, plus the RMS of its slow error):
   a spoofer's "σ 0.5 m" buys it nothing. Every estimator gets the floored σ.
2. **An innovation gate against the INS prediction.** The fix is compared with where the
   navigation says the antenna is at the fix's time of validity: ``y = z − (p + v·Δt + C_nb·l)``
   and ``y_v = z_v − v``, each normalised per axis by ``S = R_floored + P`` (normalised innovation
   squared, ``NIS = Σ y²/S``); the fix passes when both NIS are within ``chi2``.
   *Whose* prediction: the **reference** estimator (``ekf15`` by default) when it runs and has a
   covariance -- one consistent verdict for every estimator, so a compensation filter that cannot
   know its own error (no covariance) is protected by the estimator that can, and after an
   outage it takes the returning fixes as soon as the reference's grown covariance admits them.
   Without a reference, each estimator is gated on its **own** prediction with
   ``P = max(σ_est², m) + g(Δt)``: ``m`` the running mean of its accepted innovations' excess
   over R (what it actually achieves), ``g`` the unaided growth ``(a Δt²/2)²`` (velocity:
   ``(a Δt)²``) since its last accepted fix, ``a`` from the IMU's datasheet bias figures.
3. **Persistent inconsistency is an alarm, not a lock-out.** A publisher's fixes rejected for
   ``alarm_after`` of rig time raise a ``gnss_integrity_alarm`` event (a GNSS integrity alarm, as
   a receiver's RAIM says "do not use") -- per publisher, so a stranger's spoof alongside the
   genuine receiver (whose fixes pass) is an alarm too; once no publisher has such a run (its fix
   passes, or it has sent nothing rejected for ``alarm_after``), a ``gnss_integrity_restored``. After
   ``reacquire_after`` of unbroken rejection the gate lets fixes through again (counted as
   ``reacquired``): a navigator that disagrees with GNSS for that long is more likely the one
   that is wrong.
4. **A reacquired fix re-initialises the navigation** (``reset``; off in recordings made before
   it). Letting one fix through is not enough: a filter whose INS has diverged rejects it in
   its own gate, the next fix is rejected here again and the clock restarts -- GNSS locked out
   for good. So the reacquiring fix goes to every estimator, and those that can
   (``reset_to_gnss``: ekf15) reset position and velocity to it with their covariance opened, as
   PX4's EKF2 resets to GNSS after its no-aiding timeout; the fusion re-initialises the free INS
   on it too, and the open-loop filters that correct the free INS start again on it
   (``restart_on_gnss``); the next fixes are judged on the reset prediction. The same, without
   waiting: an IMU sample flagged saturated or faulty (``note_imu_fault``) makes the INS no
   witness of anything until a fix has been taken after it, so the first fix ``IMU_SETTLE_NS``
   after the last flagged sample reacquires at once (the fixes before it are held: counted in
   ``held``, neither used nor held against GNSS) -- if it continues the GNSS track before the
   fault (``reset_checks_track``: the last fix taken, carried by its velocity, within
   ``TRACK_SIGMAS`` σ and ``TRACK_ACCEL_MPS2``; a fix off it, a spoof that began inside the fault,
   is rejected and the next one on it reacquires) -- unless GNSS was under suspicion when the
   fault came (its fixes being rejected: a spoof the gate was holding out would otherwise be
   taken as the reset's truth, and the alarm cleared by the next spoofed fix; with
   ``reset_checks_track``, that fix's publisher's fixes: a stranger's beside the genuine receiver
   do not hold the receiver's out). Then nothing is a
   witness: the fixes are judged as before, and only the ``reacquire_after`` of unbroken
   rejection lets one through, the alarm raised meanwhile. Each
   reacquisition is a ``gnss_integrity_reacquired`` event; an alarm it interrupts clears only
   when a fix passes the gate on its own (``gnss_integrity_restored``).

Pure and deterministic: the verdicts depend only on the inputs in the total order, so ``hil
rerun`` reproduces them; the fusion journals each rejected fix (``FusionJournal.gated``) and
counts them (status ``gnss_gate.rejected.<estimator>``, ``health/<estimator>``).
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from hil.estimators.base import GnssInput
from hil.nav.attitude import quat_to_dcm
from hil.nav.portable import dot, mv
from hil.nav.types import F64, NavState, nav_floats

G0 = 9.80665
UNAIDED_WINDOW_S = 60.0  # tilt a gyro bias builds unaided over this long sets the fallback growth
EWMA_ALPHA = 0.1  # weight of one accepted innovation in an estimator's achieved-error mean
IMU_SETTLE_NS = 50_000_000  # clean IMU after a flagged sample before a fix may re-initialise on it
_MAX_PUBLISHERS = 1024  # publishers a gate track names in a run of rejections
# the GNSS track check of a fix after an IMU fault: the vehicle's acceleration bound (2 g) and
# the σ per axis beyond which its position or velocity does not continue the last fix taken
TRACK_ACCEL_MPS2 = 2.0 * 9.80665
TRACK_SIGMAS = 5.0


def _fl(v: Any) -> list[float]:
    """A vector as Python floats: an array's ``tolist``, or any sequence's values as floats."""
    return v.tolist() if type(v) is np.ndarray else [float(x) for x in v]  # type: ignore[no-any-return]


def _maximum(a: float, b: float) -> float:
    """``np.maximum`` of two floats: a NaN wins, and a tie keeps ``a`` (as numpy's does)."""
    return a if a >= b or a != a else b


def _recip(d: float) -> float:
    """``1.0 / d`` as numpy divides: ±inf for a zero (a fix that claims σ 0 with the floor off),
    where Python would raise."""
    return 1.0 / d if d != 0.0 else math.copysign(math.inf, d)


def _fix_of(gnss: GnssInput) -> tuple[int, list[float], list[float], list[float], list[float]]:
    """A fix as a gate track keeps it (``GateTrack.last_fix``)."""
    return (
        gnss.stamp_ns,
        _fl(gnss.pos_ned_m),
        _fl(gnss.vel_ned_mps),
        _fl(gnss.pos_sigma_m),
        _fl(gnss.vel_sigma_mps),
    )


def _ewma(mean: F64, excess: list[float]) -> F64:
    """``(1 − α) m + α max(excess, 0)`` per axis on floats (numpy's operations, in its order)."""
    keep, a = 1.0 - EWMA_ALPHA, EWMA_ALPHA
    return np.array([keep * m + a * _maximum(e, 0.0) for m, e in zip(mean.tolist(), excess, strict=True)])


@dataclass(frozen=True)
class ReceiverModel:
    """What the scenario says its receiver does: the floors of R, the antenna's lever arm, and
    how fast a navigation without GNSS drifts (for the self gates)."""

    pos_var_floor_m2: F64  # (3,) σ² of the white noise plus the slow error's mean square
    vel_var_floor_m2ps2: F64  # (3,)
    lever_arm_b_m: F64  # (3,)
    unaided_accel_mps2: float
    period_ns: int = 100_000_000  # between two epochs of the receiver

    @classmethod
    def for_scenario(cls, scenario: Any) -> ReceiverModel:
        g = scenario.gnss
        slow = np.square(np.asarray(g.slow_amplitude_m, dtype=np.float64)) / 2.0
        imu = scenario.imu.params
        accel = max(
            math.hypot(a, b) for a, b in zip(imu.accel_bias_mps2, imu.accel_turn_on_sigma_mps2, strict=True)
        )
        gyro = max(
            math.hypot(a, b) for a, b in zip(imu.gyro_bias_radps, imu.gyro_turn_on_sigma_radps, strict=True)
        )
        return cls(
            pos_var_floor_m2=np.square(np.asarray(g.pos_sigma_m, dtype=np.float64)) + slow,
            vel_var_floor_m2ps2=np.square(np.asarray(g.vel_sigma_mps, dtype=np.float64))
            + slow * (2.0 * math.pi / g.slow_period_s) ** 2,
            lever_arm_b_m=np.asarray(g.lever_arm_b_m, dtype=np.float64),
            unaided_accel_mps2=max(0.05, accel + G0 * gyro * UNAIDED_WINDOW_S),
            period_ns=round(1e9 / g.rate_hz),
        )


@dataclass(frozen=True)
class GateSettings:
    chi2: float  # NIS bound per test (position, velocity; 3 dof); 0: no gate
    alarm_after_ns: int
    reacquire_after_ns: int
    reference: str  # the estimator whose prediction and covariance decide for all ("": none)
    floor_sigma: bool  # rule 1
    reset: bool = False  # rule 4 (False: a recording made before it, one fix let through)
    reset_needs_trust: bool = False  # rule 4's IMU fault only with GNSS trusted (False: before it)
    # rule 4's fix after an IMU fault must agree with the GNSS track before the fault (the last fix
    # taken, carried by its velocity within TRACK_ACCEL_MPS2): else it is held and counted as
    # rejected (False: recordings before it, where the first fix after the fault was the truth)
    reset_checks_track: bool = False


@dataclass
class GateTrack:
    """One gate's history: the reference's (deciding for all) or one estimator's own."""

    name: str
    accepted: int = 0
    rejected: int = 0
    reacquired: int = 0
    held: int = 0  # fixes held while the INS had a flagged IMU sample not yet followed by a fix
    last_ratio: float = 0.0  # the last fix's max NIS / chi2
    last_accept_ns: int | None = None
    last_reset_ns: int | None = None  # stamp of the last fix that re-initialised (rule 4)
    reject_since_ns: int | None = None  # stamp of the first fix of the current rejection run
    # per publisher: [first, last] stamp of its current run of rejected fixes (for the alarm)
    runs: dict[str, list[int]] = field(default_factory=dict)
    # the last fix taken (accepted or reacquired): stamp, position, velocity and their σ, the
    # GNSS track a fix after an IMU fault is checked against (``reset_checks_track``)
    last_fix: tuple[int, list[float], list[float], list[float], list[float]] | None = None
    # the publishers whose fixes the current run of rejections holds (``reset_checks_track``: the
    # suspicion an IMU fault meets is theirs, not a genuine receiver's beside a stranger)
    rejected_by: set[str] = field(default_factory=set)
    alarmed: bool = False
    alarm_since_ns: int = 0
    m_pos: F64 = field(default_factory=lambda: np.zeros(3))
    m_vel: F64 = field(default_factory=lambda: np.zeros(3))


@dataclass(frozen=True)
class Transition:
    """An alarm raised or cleared: the fusion publishes it as an ``hil.Event``."""

    kind: str  # "gnss_integrity_alarm" | "gnss_integrity_restored" | "gnss_integrity_reacquired"
    gate: str
    stamp_ns: int
    detail: str


class GnssGate:
    """The fusion core's GNSS guard: floors σ, decides which estimators take a fix, keeps counts."""

    def __init__(self, settings: GateSettings, model: ReceiverModel) -> None:
        self.settings = settings
        self.model = model
        self.tracks: dict[str, GateTrack] = {}
        self.decided_by: dict[str, str] = {}  # estimator -> the gate that decided its last fix
        self.reference_ok: bool | None = None  # the reference's verdict on the last fix, for all
        self.transitions: list[Transition] = []
        self.imu_fault_ns: int | None = None  # the last IMU sample flagged saturated or faulty
        self.reset: set[str] = set()  # the estimators the last fix re-initialises (rule 4)

    @property
    def enabled(self) -> bool:
        return self.settings.chi2 > 0.0

    def note_imu_fault(self, stamp_ns: int) -> None:
        """An IMU sample the device flagged (saturated, built-in-test fault): the INS integrated
        increments that are not the motion, so its prediction judges no fix (rule 4)."""
        if self.settings.reset:
            self.imu_fault_ns = stamp_ns

    def floor(self, gnss: GnssInput) -> GnssInput:
        """The fix with its σ never below the receiver model's (rule 1)."""
        if not self.settings.floor_sigma:
            return gnss
        m = self.model
        # on floats: numpy's square, maximum and sqrt of each axis, the same bits (a fix: 29 -> 10 µs)
        pos_in, vel_in = _fl(gnss.pos_sigma_m), _fl(gnss.vel_sigma_mps)
        pos = [
            math.sqrt(_maximum(s * s, f)) for s, f in zip(pos_in, m.pos_var_floor_m2.tolist(), strict=True)
        ]
        vel = [
            math.sqrt(_maximum(s * s, f)) for s, f in zip(vel_in, m.vel_var_floor_m2ps2.tolist(), strict=True)
        ]
        if all(a == b for a, b in zip(pos + vel, pos_in + vel_in, strict=True)):  # NaN: never equal
            return gnss
        return GnssInput(gnss.stamp_ns, gnss.pos_ned_m, gnss.vel_ned_mps, np.array(pos), np.array(vel))

    def verdicts(
        self,
        gnss: GnssInput,
        names: list[str],
        solution: Callable[[str], NavState | None],
        imu_stamp_ns: int,
        publisher: str = "",
        relayed: tuple[bool | None, bool] | None = None,
    ) -> dict[str, bool]:
        """Which of the estimators ``names`` take ``gnss`` (already floored); ``solution(name)``
        is an estimator's solution at the last IMU stamp (None: it has none, it failed);
        ``publisher`` who sent it ("" offline: one receiver).

        ``reference_ok`` says afterwards what the reference decided for all (None: it did not,
        each decided on its own). ``relayed``: that verdict of another core that runs the
        reference on the same inputs (a split ``hil rerun``): ``(ok, reset)`` decides for all as
        the reference would have, and re-initialises them all where it did (rule 4), ``(None,
        False)`` lets each decide on its own, as there."""
        ref = self.settings.reference
        self.reset = set()
        if relayed is not None:
            ok_all = self.reference_ok = relayed[0]
            if ok_all is not None:
                self.decided_by.update((n, ref) for n in names)
                if relayed[1]:
                    self.reset.update(names)
                return {n: ok_all for n in names}
        else:
            sol = solution(ref) if ref in names else None
            self.reference_ok = None
            if sol is not None and sol.pos_sigma_m is not None and sol.vel_sigma_mps is not None:
                tr = self._track(ref)
                ok = self._decide(tr, gnss, sol, imu_stamp_ns, own=False, publisher=publisher)
                self.decided_by.update((n, ref) for n in names)
                self.reference_ok = ok
                if ok and tr.last_reset_ns == gnss.stamp_ns:
                    self.reset.update(names)
                return {n: ok for n in names}
        out: dict[str, bool] = {}
        for n in names:
            sol = solution(n)
            if sol is None:
                out[n] = False
                continue
            self.decided_by[n] = n
            tr = self._track(n)
            out[n] = self._decide(tr, gnss, sol, imu_stamp_ns, own=True, publisher=publisher)
            if out[n] and tr.last_reset_ns == gnss.stamp_ns:
                self.reset.add(n)
        return out

    def _track(self, name: str) -> GateTrack:
        tr = self.tracks.get(name)
        if tr is None:
            tr = self.tracks[name] = GateTrack(name)
        return tr

    def _decide(
        self, tr: GateTrack, gnss: GnssInput, sol: NavState, imu_ns: int, own: bool, publisher: str
    ) -> bool:
        # Per axis on floats, numpy's elementwise operations in their order (the same bits; a
        # fix's reference verdict 74 -> 60 µs in a rerun); the two sums stay einsum's (``dot``).
        dt_s = (gnss.stamp_ns - imu_ns) * 1e-9
        pos, vel, _q = nav_floats(sol)
        pred = [p + v * dt_s for p, v in zip(pos, vel, strict=True)]
        lever = self.model.lever_arm_b_m
        if lever.any():
            pred = [p + a for p, a in zip(pred, mv(quat_to_dcm(sol.q_nb), lever).tolist(), strict=True)]
        y_p = [z - p for z, p in zip(_fl(gnss.pos_ned_m), pred, strict=True)]
        y_v = [z - v for z, v in zip(_fl(gnss.vel_ned_mps), vel, strict=True)]
        p_p = [0.0] * 3 if sol.pos_sigma_m is None else [s * s for s in _fl(sol.pos_sigma_m)]
        p_v = [0.0] * 3 if sol.vel_sigma_mps is None else [s * s for s in _fl(sol.vel_sigma_mps)]
        if own:  # what the estimator achieves, and what it may have drifted since its last fix
            last = tr.last_accept_ns
            since_s = 0.0 if last is None else max(0.0, (gnss.stamp_ns - last) * 1e-9)
            a = self.model.unaided_accel_mps2
            g_p, g_v = (0.5 * a * since_s * since_s) ** 2, (a * since_s) ** 2
            p_p = [_maximum(p, m) + g_p for p, m in zip(p_p, tr.m_pos.tolist(), strict=True)]
            p_v = [_maximum(p, m) + g_v for p, m in zip(p_v, tr.m_vel.tolist(), strict=True)]
        r_p = [s * s for s in _fl(gnss.pos_sigma_m)]
        r_v = [s * s for s in _fl(gnss.vel_sigma_mps)]
        yy_p, yy_v = [y * y for y in y_p], [y * y for y in y_v]
        nis_p = dot(np.array(yy_p), np.array([_recip(r + p) for r, p in zip(r_p, p_p, strict=True)]))
        nis_v = dot(np.array(yy_v), np.array([_recip(r + p) for r, p in zip(r_v, p_v, strict=True)]))
        chi2 = self.settings.chi2
        tr.last_ratio = max(nis_p, nis_v) / chi2
        ok = nis_p <= chi2 and nis_v <= chi2
        since = tr.reject_since_ns
        if self.settings.reset:
            why = self._reacquire_reason(tr, gnss, ok, publisher)
            if why == "held":
                tr.held += 1
                return False
            if why == "off_track":
                ok = False
            elif why:
                self._reacquire(tr, gnss, why)
                return True
        elif not ok and since is not None and gnss.stamp_ns - since >= self.settings.reacquire_after_ns:
            ok = True
            tr.reacquired += 1
        if ok:
            excess_p = [y - r for y, r in zip(yy_p, r_p, strict=True)]
            excess_v = [y - r for y, r in zip(yy_v, r_v, strict=True)]
            self._accepted(tr, gnss, excess_p, excess_v)
        else:
            self._rejected(tr, gnss.stamp_ns, publisher)
        self._alarm(tr, gnss.stamp_ns, publisher, ok)
        return ok

    def _reacquire_reason(self, tr: GateTrack, gnss: GnssInput, ok: bool, publisher: str) -> str:
        """Why this fix re-initialises the navigation (rule 4): "imu_fault" (a flagged IMU sample
        since the last fix taken) or "rejected" (rejection for too long); "held" if it must wait
        (within the settle after the fault), "off_track" if it is to be rejected whatever the INS
        says (after the fault, with ``reset_checks_track``, a fix that does not continue the GNSS
        track: a spoof that began inside the fault; the next that does re-initialises); "" if
        none of these. With the track check, GNSS is under suspicion for this fix's publisher's
        rejections only: a stranger's spoof beside the genuine receiver does not hold the
        receiver's fix out (QA, session 36: 30 s of lock-out, ekf15 2.4 km off)."""
        stamp_ns = gnss.stamp_ns
        fault = self.imu_fault_ns
        since = tr.reject_since_ns
        checks = self.settings.reset_checks_track
        too_long = since is not None and stamp_ns - since >= self.settings.reacquire_after_ns
        # GNSS under suspicion when the fault came: rejections that began before it (those after
        # it, with the track check, are its own: fixes off the track)
        suspect = (
            since is not None
            and self.settings.reset_needs_trust
            and not (checks and fault is not None and since > fault)
            and (not checks or publisher in tr.rejected_by)
        )
        if fault is not None and (tr.last_accept_ns is None or fault >= tr.last_accept_ns) and not suspect:
            if stamp_ns - fault < IMU_SETTLE_NS:
                return "held"
            if not (checks and self._off_track(tr, gnss)):
                return "imu_fault"
            return "rejected" if too_long else "off_track"
        return "rejected" if not ok and too_long else ""

    def _off_track(self, tr: GateTrack, gnss: GnssInput) -> bool:
        """Whether ``gnss`` does not continue the last fix taken: its position beyond that fix
        carried by its velocity, or its velocity beyond that fix's, by more than
        ``TRACK_SIGMAS`` σ per axis (the two fixes' σ) plus what ``TRACK_ACCEL_MPS2`` makes of the
        time between (½aΔt², aΔt). The receiver is not the IMU: its track is a witness the fault
        left, and a spoof that jumps 500 m is off it."""
        last = tr.last_fix
        if last is None:
            return False
        dt = (gnss.stamp_ns - last[0]) * 1e-9
        if dt <= 0.0:
            return False
        a = TRACK_ACCEL_MPS2
        pos, vel = _fl(gnss.pos_ned_m), _fl(gnss.vel_ned_mps)
        ps, vs = _fl(gnss.pos_sigma_m), _fl(gnss.vel_sigma_mps)
        for i in range(3):
            bound_p = TRACK_SIGMAS * math.hypot(ps[i], last[3][i]) + 0.5 * a * dt * dt
            bound_v = TRACK_SIGMAS * math.hypot(vs[i], last[4][i]) + a * dt
            if abs(pos[i] - (last[1][i] + last[2][i] * dt)) > bound_p or abs(vel[i] - last[2][i]) > bound_v:
                return True
        return False

    def _reacquire(self, tr: GateTrack, gnss: GnssInput, why: str) -> None:
        """Take the fix as a re-initialisation: no innovation of it is an achieved error, and a
        raised alarm stays raised until a fix passes on the reset prediction."""
        stamp_ns = gnss.stamp_ns
        since = tr.reject_since_ns if why == "rejected" else self.imu_fault_ns
        tr.last_fix = _fix_of(gnss)
        tr.reacquired += 1
        tr.accepted += 1
        tr.last_accept_ns = tr.last_reset_ns = stamp_ns
        tr.reject_since_ns = None
        tr.rejected_by.clear()
        detail: dict[str, object] = {"gate": tr.name, "reason": why, "reset": True}
        detail["reacquired"] = tr.reacquired
        if why == "rejected" and since is not None:
            detail["rejected_for_s"] = round((stamp_ns - since) / 1e9, 3)
        elif since is not None:
            detail["imu_fault_last_s"] = round(since / 1e9, 3)
            detail["held"] = tr.held
        kind = "gnss_integrity_reacquired"
        self.transitions.append(Transition(kind, tr.name, stamp_ns, json.dumps(detail)))

    def _accepted(self, tr: GateTrack, gnss: GnssInput, excess_p: list[float], excess_v: list[float]) -> None:
        tr.accepted += 1
        tr.last_accept_ns = gnss.stamp_ns
        if self.settings.reset_checks_track:
            tr.last_fix = _fix_of(gnss)
        tr.m_pos = _ewma(tr.m_pos, excess_p)
        tr.m_vel = _ewma(tr.m_vel, excess_v)
        tr.reject_since_ns = None
        tr.rejected_by.clear()

    def _rejected(self, tr: GateTrack, stamp_ns: int, publisher: str) -> None:
        tr.rejected += 1
        if tr.reject_since_ns is None:
            tr.reject_since_ns = stamp_ns
        if len(tr.rejected_by) < _MAX_PUBLISHERS:  # bounded whatever a flood names
            tr.rejected_by.add(publisher)

    def _alarm(self, tr: GateTrack, stamp_ns: int, publisher: str, ok: bool) -> None:
        """Raise or clear the alarm on the publishers' runs of rejected fixes (rule 3)."""
        after = self.settings.alarm_after_ns
        for src in [s for s, (_first, last) in tr.runs.items() if stamp_ns - last > after]:
            del tr.runs[src]  # silent for alarm_after: its run has ended
        if ok:
            tr.runs.pop(publisher, None)
        else:
            tr.runs[publisher] = [tr.runs.get(publisher, [stamp_ns])[0], stamp_ns]
        long_runs = {s: first for s, (first, last) in tr.runs.items() if last - first >= after}
        if long_runs and not tr.alarmed:
            tr.alarmed = True
            tr.alarm_since_ns = min(long_runs.values())
            detail = json.dumps(
                {
                    "gate": tr.name,
                    "since_s": round(tr.alarm_since_ns / 1e9, 3),
                    "publishers": sorted(long_runs),
                    "nis_over_chi2": round(tr.last_ratio, 1),
                    "rejected": tr.rejected,
                }
            )
            self.transitions.append(Transition("gnss_integrity_alarm", tr.name, stamp_ns, detail))
        elif not long_runs and tr.alarmed:
            tr.alarmed = False
            lasted = (stamp_ns - tr.alarm_since_ns) / 1e9
            detail = json.dumps(
                {"gate": tr.name, "rejected_for_s": round(lasted, 3), "reacquired": tr.reacquired}
            )
            self.transitions.append(Transition("gnss_integrity_restored", tr.name, stamp_ns, detail))

    def take_transitions(self) -> list[Transition]:
        out, self.transitions = self.transitions, []
        return out

    def health(self, name: str) -> dict[str, float]:
        """What ``health/<name>`` adds: the gate that decides for ``name`` and its counts."""
        tr = self.tracks.get(self.decided_by.get(name, name))
        if tr is None:
            return {}
        return {
            "gnss_gate_rejected": float(tr.rejected),
            "gnss_gate_ratio": tr.last_ratio,
            "gnss_gate_alarm": 1.0 if tr.alarmed else 0.0,
        }

"""Accuracy and timing metrics of a session: errors vs truth, their statistics, fault windows.

Errors are taken at each solution's stamp against truth interpolated there (position and
velocity linearly, attitude by normalised linear interpolation of the quaternion, sign-aligned):
truth is 100 Hz, so the interpolation error is far below any estimator's.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from hil.report.data import ReportData, Series, scenario_text
from hil.runtime.scenario_io import scenario_from_text

RECOVERY_S = 10.0  # after a fault window, errors are not yet held against convergence
CONVERGED_FACTOR = 2.0  # converged: below this many times the error's median over the last half
CONVERGED_FLOOR_M = 1.0


@dataclass
class Errors:
    """One estimator against truth: ``t_s`` (n,), ``pos_ned`` / ``vel_ned`` (n, 3), ``att_deg`` (n,)."""

    t_s: np.ndarray
    pos_ned: np.ndarray
    vel_ned: np.ndarray
    att_deg: np.ndarray

    @property
    def horiz_m(self) -> np.ndarray:
        return np.hypot(self.pos_ned[:, 0], self.pos_ned[:, 1])

    @property
    def vel_mps(self) -> np.ndarray:
        return np.linalg.norm(self.vel_ned, axis=1)


@dataclass
class Stats:
    n: int
    rms: float
    p95: float
    max: float
    final: float


@dataclass
class EstimatorStats:
    name: str
    horiz: Stats
    vert: Stats
    vel: Stats
    att: Stats
    convergence_s: float | None  # None: never stays converged


@dataclass
class FaultWindow:
    kind: str
    t0_s: float
    t1_s: float | None  # None: a step change (a line, not a span)
    label: str


def stats(x: np.ndarray) -> Stats:
    a = np.abs(x[np.isfinite(x)])
    if a.size == 0:
        return Stats(0, math.nan, math.nan, math.nan, math.nan)
    return Stats(
        int(a.size),
        float(np.sqrt(np.mean(a**2))),
        float(np.percentile(a, 95)),
        float(a.max()),
        float(a[-1]),
    )


def quat_mul(p: np.ndarray, q: np.ndarray) -> np.ndarray:
    """Hamilton product of (n, 4) [w x y z] arrays."""
    pw, px, py, pz = p.T
    qw, qx, qy, qz = q.T
    return np.column_stack(
        [
            pw * qw - px * qx - py * qy - pz * qz,
            pw * qx + px * qw + py * qz - pz * qy,
            pw * qy - px * qz + py * qw + pz * qx,
            pw * qz + px * qy - py * qx + pz * qw,
        ]
    )


def interp_truth(truth: Series, t_ns: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Truth at ``t_ns`` (inside its span only): (mask, pos (m, 3), vel (m, 3), q (m, 4))."""
    tt = truth.t_ns.astype(np.float64)
    ok = (t_ns >= truth.t_ns[0]) & (t_ns <= truth.t_ns[-1])
    t = t_ns[ok].astype(np.float64)
    pos = np.column_stack([np.interp(t, tt, truth.pos[:, i]) for i in range(3)])
    vel = np.column_stack([np.interp(t, tt, truth.vel[:, i]) for i in range(3)])
    k = np.clip(np.searchsorted(tt, t, side="right") - 1, 0, len(tt) - 2)
    a = ((t - tt[k]) / np.maximum(tt[k + 1] - tt[k], 1.0))[:, None]
    q0, q1 = truth.q[k], truth.q[k + 1]
    q1 = np.where((np.sum(q0 * q1, axis=1) < 0)[:, None], -q1, q1)
    q = (1 - a) * q0 + a * q1
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    return ok, pos, vel, q


def errors(truth: Series, est: Series) -> Errors | None:
    ok, pos, vel, q = interp_truth(truth, est.t_ns)
    if not ok.any():
        return None
    qe = est.q[ok] / np.linalg.norm(est.q[ok], axis=1, keepdims=True)
    conj = q * np.array([1.0, -1.0, -1.0, -1.0])
    dq = quat_mul(qe, conj)
    att = np.degrees(2.0 * np.arccos(np.clip(np.abs(dq[:, 0]), 0.0, 1.0)))
    return Errors(est.t_ns[ok] * 1e-9, est.pos[ok] - pos, est.vel[ok] - vel, att)


def fault_windows(d: ReportData) -> tuple[list[FaultWindow], list[str]]:
    """Scenario events (from the recorded scenario text) and recorded ``hil.Event``s as windows."""
    notes: list[str] = []
    out: list[FaultWindow] = []
    text = scenario_text(d)
    if text:
        try:
            sc = scenario_from_text(text, d.run.scenario if d.run else "scenario")
        except ValueError as err:
            notes.append(
                f"the recorded scenario text does not parse, fault markers from it are missing: {err}"
            )
        else:
            end_s = d.run.duration_s if d.run is not None else None
            later = [ev for ev in sc.events if end_s is not None and ev.t_start_s >= end_s]
            if later:  # a run shorter than its scenario: those never happened
                notes.append(
                    f"{len(later)} of the scenario's faults start after the run's {end_s:g} s "
                    f"(from {min(ev.t_start_s for ev in later):g} s): not in this run, not shown"
                )
            for ev in sc.events:
                if ev in later:
                    continue
                t1 = ev.t_end_s
                if t1 is None and ev.kind == "gnss_pulse":
                    t1 = ev.t_start_s + float(ev.params.get("tau_s", 1.0))
                span = f"{ev.t_start_s:g}–{t1:g} s" if t1 is not None else f"from {ev.t_start_s:g} s"
                out.append(FaultWindow(ev.kind, ev.t_start_s, t1, f"{ev.kind} {span}"))
    else:
        notes.append("no scenario text in the recording: scenario fault markers are missing")
    for e in d.events:
        if e.kind == "fusion_config":
            continue
        t = e.stamp_ns * 1e-9
        out.append(FaultWindow(e.kind, t, None, f"{e.kind} ({e.source}) at {t:.1f} s {e.detail[:60]}"))
    return out, notes


def gnss_bound_m(d: ReportData) -> float | None:
    """95 % horizontal radius of the scenario's GNSS white noise (2.45 σ, Rayleigh), if known."""
    text = scenario_text(d)
    if not text:
        return None
    try:
        sigma = scenario_from_text(text).gnss.pos_sigma_m
    except (ValueError, AttributeError):
        return None
    s = np.atleast_1d(np.asarray(sigma, float))
    return float(2.45 * np.hypot(s[0], s[1 % s.size]) / np.sqrt(2.0))


def convergence_s(err: Errors, windows: list[FaultWindow], cap_m: float | None = None) -> float | None:
    """First time after which the horizontal error stays below the bound, fault windows excused.

    Bound: ``CONVERGED_FACTOR`` × the median horizontal error over the last half of the run, at
    least ``CONVERGED_FLOOR_M`` and at most ``cap_m`` (the GNSS 95 % radius: an estimator that
    never gets inside it has not converged). Samples inside a fault window or within
    ``RECOVERY_S`` after it are not held against the estimator.
    """
    h = err.horiz_m
    t = err.t_s
    if h.size < 4:
        return None
    bound = max(CONVERGED_FACTOR * float(np.median(h[h.size // 2 :])), CONVERGED_FLOOR_M)
    if cap_m is not None:
        bound = min(bound, max(cap_m, CONVERGED_FLOOR_M))
    excused = np.zeros(h.size, bool)
    for w in windows:
        t1 = (w.t1_s if w.t1_s is not None else w.t0_s) + RECOVERY_S
        excused |= (t >= w.t0_s) & (t < t1)
    bad = (h > bound) & ~excused
    if not bad.any():
        return float(t[0])
    last_bad = int(np.nonzero(bad)[0][-1])
    if last_bad + 1 >= h.size:
        return None
    return float(t[last_bad + 1])


def estimator_stats(
    name: str, e: Errors, windows: list[FaultWindow], cap_m: float | None = None
) -> EstimatorStats:
    return EstimatorStats(
        name,
        stats(e.horiz_m),
        stats(e.pos_ned[:, 2]),
        stats(e.vel_mps),
        stats(e.att_deg),
        convergence_s(e, windows, cap_m),
    )

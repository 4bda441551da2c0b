"""One run's statistics per estimator: what a worker sends back instead of the recording.

Errors are horizontal position errors at each solution's stamp against truth interpolated there
(``hil info``'s ``estimator_errors`` and the HTML report do the same). Per estimator and run:

- ``h_rms_m``, ``h_p95_m``, ``h_max_m``, ``h_final_m`` over the solutions after ``settle_s``
  (0: the whole run, the figures ``hil info`` prints);
- ``conv_s``, the convergence time of the HTML report (``hil.report.metrics.convergence_s``): the
  first time after which the horizontal error stays below max(2 x its median over the last half
  of the run, 1 m), capped at the GNSS 95 % radius, fault windows and 10 s after them excused;
  None (NaN in a table) when it never stays there;
- where the estimator reports a covariance (``pos_sigma_m``/``vel_sigma_mps``: ekf15), NEES of
  position and velocity, 6 dof, from the per-axis sigmas ``NavSolution`` carries. The solution
  holds the diagonal only, so the NEES ignores cross-correlations: its mean is exact (each term
  has expectation 1 for a consistent filter whatever the correlations), its spread is not
  exactly chi-square(6). ``nees_in_band`` is the fraction of epochs (after ``settle_s``) inside
  the two-sided 95 % band of chi-square(6);
- thin series on a grid of ``series_dt_s`` (1 s; coarser for runs over 1000 s): horizontal error,
  horizontal sigma and NEES, so a campaign's report can average over runs per epoch (the
  run-averaged NEES against its band, the Monte-Carlo RMS against the filter's sigma).
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import msgspec
import numpy as np

from hil.fusion.core import FREE_INS
from hil.nav.scenario import Scenario
from hil.record.mcapio import Record
from hil.report.metrics import Errors, FaultWindow, convergence_s

NEES_DOF = 6
MAX_SERIES_POINTS = 1000
_CHI2_6_BAND = (1.2373442457912035, 14.449375335447922)  # chi2.ppf([0.025, 0.975], 6)


class _TruthLite(msgspec.Struct):
    stamp_ns: int
    pos_ned_m: tuple[float, float, float]
    vel_ned_mps: tuple[float, float, float]


class _NavLite(msgspec.Struct):
    stamp_ns: int
    estimator: str
    pos_ned_m: tuple[float, float, float]
    vel_ned_mps: tuple[float, float, float]
    # [] (or null, in recordings from before the Foxglove-first schemas) when absent
    pos_sigma_m: list[float] | None = None
    vel_sigma_mps: list[float] | None = None


_TRUTH = msgspec.json.Decoder(_TruthLite)
_NAV = msgspec.json.Decoder(_NavLite)


@dataclass
class Collected:
    """Truth and the solutions of the estimators asked for, gathered from a stream of records
    (or of recomputed solutions) with only the fields the statistics need."""

    want: frozenset[str] | None  # None: every estimator but the free INS
    truth_t: list[int] = field(default_factory=list)
    truth_pos: list[tuple[float, float, float]] = field(default_factory=list)
    truth_vel: list[tuple[float, float, float]] = field(default_factory=list)
    nav: dict[str, list[Any]] = field(default_factory=dict)

    def record(self, r: Record) -> None:
        t = r.topic
        if t.endswith("/truth"):
            m = _TRUTH.decode(r.payload)
            self.truth_t.append(m.stamp_ns)
            self.truth_pos.append(m.pos_ned_m)
            self.truth_vel.append(m.vel_ned_mps)
        elif "/nav/" in t:
            self.solution(_NAV.decode(r.payload))

    def solution(self, s: Any) -> None:
        """A ``NavSolution`` (or its light twin): kept if its estimator is wanted."""
        name = s.estimator
        if (self.want is None and name != FREE_INS) or (self.want is not None and name in self.want):
            self.nav.setdefault(name, []).append(s)


def collect(records: Iterable[Record], want: frozenset[str] | None) -> Collected:
    c = Collected(want)
    for r in records:
        c.record(r)
    return c


def scenario_windows(sc: Scenario) -> list[FaultWindow]:
    """The scenario's fault events as the HTML report's windows (convergence excuses them)."""
    out = []
    for ev in sc.events:
        t1 = ev.t_end_s
        if t1 is None and ev.kind == "gnss_pulse":
            t1 = ev.t_start_s + float(ev.params.get("tau_s", 1.0))
        out.append(FaultWindow(ev.kind, ev.t_start_s, t1, ev.kind))
    return out


def gnss_bound(sc: Scenario) -> float:
    """95 % horizontal radius of the scenario's GNSS white noise (2.45 sigma, Rayleigh)."""
    s = sc.gnss.pos_sigma_m
    return float(2.45 * math.hypot(s[0], s[1]) / math.sqrt(2.0))


def _num(x: float) -> float | None:
    return None if not math.isfinite(x) else float(f"{x:.6g}")


def _series(t_s: np.ndarray, y: np.ndarray, dt_s: float) -> list[float | None]:
    """``y`` at the first solution at or after each grid time k·dt (k = 1, 2, ...)."""
    if t_s.size == 0:
        return []
    grid = np.arange(1, int(t_s[-1] / dt_s + 1e-9) + 1) * dt_s
    idx = np.searchsorted(t_s, grid - 1e-9)
    idx = idx[idx < t_s.size]
    return [_num(float(v)) for v in y[idx]]


def series_step_s(duration_s: float) -> float:
    return float(max(1.0, math.ceil(duration_s / MAX_SERIES_POINTS)))


def empty_stats() -> dict[str, Any]:
    """The statistics columns of a run that produced none (failed, or no solution)."""
    return {
        "n": 0,
        "h_rms_m": None,
        "h_p95_m": None,
        "h_max_m": None,
        "h_final_m": None,
        "conv_s": None,
        "nees_mean": None,
        "nees_pos_mean": None,
        "nees_vel_mean": None,
        "nees_in_band": None,
        "series_dt_s": None,
        "series_h_err_m": [],
        "series_h_sigma_m": [],
        "series_nees": [],
    }


def estimator_stats(
    c: Collected, name: str, *, settle_s: float, windows: list[FaultWindow], cap_m: float | None
) -> dict[str, Any]:
    """The statistics columns of one estimator of one run (see the module docstring)."""
    rows = c.nav.get(name, [])
    out = empty_stats()
    if len(c.truth_t) < 2 or not rows:
        return out
    tt = np.asarray(c.truth_t, dtype=np.float64)
    t = np.array([s.stamp_ns for s in rows], dtype=np.float64)
    ok = (t >= tt[0]) & (t <= tt[-1])
    if not ok.any():
        return out
    t = t[ok]
    pos = np.array([s.pos_ned_m for s in rows], dtype=np.float64)[ok]
    vel = np.array([s.vel_ned_mps for s in rows], dtype=np.float64)[ok]
    tp, tv = np.asarray(c.truth_pos), np.asarray(c.truth_vel)
    e_pos = pos - np.column_stack([np.interp(t, tt, tp[:, i]) for i in range(3)])
    e_vel = vel - np.column_stack([np.interp(t, tt, tv[:, i]) for i in range(3)])
    h = np.hypot(e_pos[:, 0], e_pos[:, 1])
    t_s = t * 1e-9
    late = t_s >= settle_s
    if late.any():
        hl = h[late]
        out.update(
            n=int(late.sum()),
            h_rms_m=_num(float(np.sqrt(np.mean(hl**2)))),
            h_p95_m=_num(float(np.percentile(hl, 95))),
            h_max_m=_num(float(hl.max())),
            h_final_m=_num(float(hl[-1])),
        )
    err = Errors(t_s, e_pos, e_vel, np.zeros(t_s.size))
    conv = convergence_s(err, windows, cap_m)
    dt = series_step_s(float(t_s[-1]))
    out.update(
        conv_s=None if conv is None else _num(conv), series_dt_s=dt, series_h_err_m=_series(t_s, h, dt)
    )
    sig = [s for s in rows if s.pos_sigma_m and s.vel_sigma_mps]
    if len(sig) == len(rows):
        ps = np.array([s.pos_sigma_m for s in rows], dtype=np.float64)[ok]
        vs = np.array([s.vel_sigma_mps for s in rows], dtype=np.float64)[ok]
        with np.errstate(divide="ignore", invalid="ignore"):
            n_pos = np.sum((e_pos / ps) ** 2, axis=1)
            n_vel = np.sum((e_vel / vs) ** 2, axis=1)
        nees = n_pos + n_vel
        lo, hi = _CHI2_6_BAND
        if late.any():
            nl = nees[late]
            out.update(
                nees_mean=_num(float(np.mean(nl))),
                nees_pos_mean=_num(float(np.mean(n_pos[late]))),
                nees_vel_mean=_num(float(np.mean(n_vel[late]))),
                nees_in_band=_num(float(np.mean((nl >= lo) & (nl <= hi)))),
            )
        out.update(
            series_h_sigma_m=_series(t_s, np.hypot(ps[:, 0], ps[:, 1]), dt),
            series_nees=_series(t_s, nees, dt),
        )
    return out

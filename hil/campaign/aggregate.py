"""A campaign's rows reduced per estimator: distributions over runs, the run-averaged NEES
against its band, the Monte-Carlo RMS against the filter's own sigma, and the paired
differences between two campaigns. Pure numpy/scipy: the report draws what this computes.
"""

from __future__ import annotations

import math
from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

import numpy as np
from scipy.stats import chi2, wilcoxon

from hil.campaign.execute import OK

NEES_DOF = 6


def _f(rows: Iterable[dict[str, Any]], col: str) -> np.ndarray:
    return np.array([np.nan if r.get(col) is None else float(r[col]) for r in rows], dtype=np.float64)


def group_of(r: dict[str, Any]) -> tuple[str, str, str, str]:
    """Rows are judged per (scenario, fault set, configuration, estimator)."""
    return (r.get("scenario") or "", r.get("faults") or "", r.get("config") or "", r.get("estimator") or "")


def group_label(g: tuple[str, str, str, str], varying: tuple[bool, bool, bool]) -> str:
    """The group's name with only the parts that vary in the campaign (and the estimator)."""
    parts = [p for p, v in zip(g[:3], varying, strict=True) if v]
    return " / ".join([*parts, g[3]])


def varying_parts(rows: list[dict[str, Any]]) -> tuple[bool, bool, bool]:
    return tuple(len({group_of(r)[i] for r in rows}) > 1 for i in range(3))  # type: ignore[return-value]


def _stack(rows: list[dict[str, Any]], col: str) -> np.ndarray | None:
    """Runs x epochs of one series column (cut to the shortest run), None if any run has none."""
    series = [r.get(col) or [] for r in rows]
    n = min((len(s) for s in series), default=0)
    if n == 0:
        return None
    return np.array([[np.nan if v is None else v for v in s[:n]] for s in series], dtype=np.float64)


@dataclass
class Consistency:
    """Per epoch over the runs: mean NEES and its band; Monte-Carlo RMS and the filter's sigma."""

    t_s: np.ndarray
    nees_mean: np.ndarray | None
    band: tuple[float, float]
    inside: float  # fraction of epochs after settle with the mean NEES inside the band
    above: float
    below: float
    rms_m: np.ndarray  # sqrt(mean over runs of h^2)
    sigma_m: np.ndarray | None  # sqrt(mean over runs of sigma_h^2)
    ratio_band: tuple[float, float]  # 95 % band of rms/sigma for this many runs (2 dof per run)
    ratio_inside: float


def consistency(rows: list[dict[str, Any]], settle_s: float) -> Consistency | None:
    """The seed papers' Monte-Carlo checks over a group's runs (None with fewer than 2 runs).

    NEES: the mean over N runs of a chi-square(6) is chi-square(6N)/N, whose two-sided 95 % band
    is where the per-epoch mean must lie 95 % of the time for a consistent filter (seeds_uav's
    test, with the diagonal NEES of :mod:`hil.campaign.metrics`). RMS vs sigma (seed 004): the
    horizontal error's RMS over runs against the RMS of the filter's horizontal sigma; with
    equal N and E sigmas, N·RMS²/sigma² is chi-square(2N), hence the ratio's band.
    """
    if len(rows) < 2:
        return None
    h = _stack(rows, "series_h_err_m")
    if h is None:
        return None
    dt = float(rows[0].get("series_dt_s") or 1.0)
    n_runs, n_t = h.shape
    t = np.arange(1, n_t + 1) * dt
    late = t >= settle_s
    rms = np.sqrt(np.nanmean(h**2, axis=0))
    nees = _stack(rows, "series_nees")
    sig = _stack(rows, "series_h_sigma_m")
    lo, hi = (float(x) for x in chi2.ppf([0.025, 0.975], NEES_DOF * n_runs) / n_runs)
    rlo, rhi = (float(x) for x in np.sqrt(chi2.ppf([0.025, 0.975], 2 * n_runs) / (2 * n_runs)))
    c = Consistency(t, None, (lo, hi), math.nan, math.nan, math.nan, rms, None, (rlo, rhi), math.nan)
    if nees is not None and nees.shape[1] >= n_t and late.any():
        m = np.nanmean(nees[:, :n_t], axis=0)
        c.nees_mean = m
        c.inside = float(np.mean((m[late] >= lo) & (m[late] <= hi)))
        c.above = float(np.mean(m[late] > hi))
        c.below = float(np.mean(m[late] < lo))
    if sig is not None and sig.shape[1] >= n_t and late.any():
        s = np.sqrt(np.nanmean(sig[:, :n_t] ** 2, axis=0))
        c.sigma_m = s
        with np.errstate(divide="ignore", invalid="ignore"):
            ratio = rms[late] / s[late]
        c.ratio_inside = float(np.mean((ratio >= rlo) & (ratio <= rhi)))
    return c


@dataclass
class GroupSummary:
    group: tuple[str, str, str, str]
    label: str
    rows: list[dict[str, Any]]  # every latest row of the group, any status
    ok: list[dict[str, Any]] = field(default_factory=list)
    consistency: Consistency | None = None

    def col(self, name: str) -> np.ndarray:
        return _f(self.ok, name)

    def worst(self, k: int = 5) -> list[dict[str, Any]]:
        """The ``k`` runs with the largest horizontal RMS (ok runs only)."""
        have = [r for r in self.ok if r.get("h_rms_m") is not None]
        return sorted(have, key=lambda r: -float(r["h_rms_m"]))[:k]


def summarise(rows: list[dict[str, Any]], settle_s: float) -> list[GroupSummary]:
    """Every group's rows, its ok runs and their consistency, in a stable order."""
    varying = varying_parts(rows)
    groups: dict[tuple[str, str, str, str], list[dict[str, Any]]] = {}
    for r in rows:
        groups.setdefault(group_of(r), []).append(r)
    out = []
    for g in sorted(groups):
        s = GroupSummary(g, group_label(g, varying), groups[g])
        s.ok = [r for r in s.rows if r["status"] == OK and r.get("h_rms_m") is not None]
        s.consistency = consistency(s.ok, settle_s)
        out.append(s)
    return out


def pct(x: np.ndarray, q: float) -> float:
    x = x[np.isfinite(x)]
    return float(np.percentile(x, q)) if x.size else math.nan


@dataclass
class Paired:
    """One group's per-run differences between two campaigns (after − before)."""

    label: str
    pairs: list[tuple[dict[str, Any], dict[str, Any]]]  # (before, after), same run key

    def delta(self, col: str) -> np.ndarray:
        return _f((a for _b, a in self.pairs), col) - _f((b for b, _a in self.pairs), col)

    def p_value(self, col: str = "h_rms_m") -> float:
        """Wilcoxon signed-rank test of the paired differences (NaN when it cannot be run)."""
        d = self.delta(col)
        d = d[np.isfinite(d) & (d != 0)]
        if d.size < 5:
            return math.nan
        return float(wilcoxon(d).pvalue)


def _situation(r: dict[str, Any]) -> tuple[Any, ...]:
    """What a run faced, whatever the configuration: kind, scenario, seed, faults, recording."""
    return (r["kind"], r.get("scenario"), r.get("seed"), r.get("faults"), r.get("recording"), r["estimator"])


def _usable(rows: list[dict[str, Any]]) -> list[dict[str, Any]]:
    return [r for r in rows if r["status"] == OK and r.get("h_rms_m") is not None]


def _unique(rows: list[dict[str, Any]]) -> dict[tuple[Any, ...], dict[str, Any]]:
    seen: dict[tuple[Any, ...], list[dict[str, Any]]] = {}
    for r in rows:
        seen.setdefault(_situation(r), []).append(r)
    return {k: v[0] for k, v in seen.items() if len(v) == 1}


def pair(before: list[dict[str, Any]], after: list[dict[str, Any]]) -> tuple[list[Paired], str]:
    """Rows of the same run and estimator, both ok, grouped like :func:`summarise`; and how.

    By key (the same definition: a code change between two campaigns of one spec). If no key is
    common, by situation -- scenario, seed, fault set, recording, estimator -- where each is
    unique on both sides: the same runs under another configuration or statistics window.
    """
    old, new = _usable(before), _usable(after)
    by_key = {(r["key"], r["estimator"]): r for r in old}
    matched = [(by_key[(r["key"], r["estimator"])], r) for r in new if (r["key"], r["estimator"]) in by_key]
    how = "key"
    if not matched:
        o, n = _unique(old), _unique(new)
        matched = [(o[k], r) for k, r in n.items() if k in o]
        how = "situation"
    varying = varying_parts(after)
    groups: dict[tuple[str, str, str, str], list[tuple[dict[str, Any], dict[str, Any]]]] = {}
    for b, a in matched:
        groups.setdefault(group_of(a), []).append((b, a))
    paired = [
        Paired(group_label(g, varying), sorted(p, key=lambda ba: ba[1]["run"]))
        for g, p in sorted(groups.items())
    ]
    return paired, how

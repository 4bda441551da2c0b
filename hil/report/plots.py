"""The report's figures as PNG bytes (matplotlib, Agg backend, no display, no network).

Long series are decimated before plotting: a track keeps every k-th point (at most
``MAX_POINTS``); an error magnitude keeps the maximum of each bin, so a spike is never hidden.
"""

from __future__ import annotations

import io
from collections.abc import Sequence

import matplotlib

matplotlib.use("Agg")

import matplotlib.pyplot as plt
import numpy as np
from matplotlib.figure import Figure

from hil.report.metrics import Errors, FaultWindow

MAX_POINTS = 3000
FREE_INS = "ins"
DPI = 90


def colours(names: Sequence[str]) -> dict[str, str]:
    cmap = plt.get_cmap("tab10")
    out = {}
    i = 0
    for n in names:
        if n == FREE_INS:
            out[n] = "#888888"
        else:
            out[n] = matplotlib.colors.to_hex(cmap(i % 10))
            i += 1
    return out


def thin(*arrays: np.ndarray, max_points: int = MAX_POINTS) -> list[np.ndarray]:
    """Every k-th row so that at most ``max_points`` remain (the last one kept)."""
    n = arrays[0].shape[0]
    if n <= max_points:
        return list(arrays)
    idx = np.unique(np.r_[np.arange(0, n, int(np.ceil(n / max_points))), n - 1])
    return [a[idx] for a in arrays]


def envelope(t: np.ndarray, y: np.ndarray, max_points: int = MAX_POINTS) -> tuple[np.ndarray, np.ndarray]:
    """Max of |y| per bin: the curve a reader needs for an error magnitude."""
    n = t.shape[0]
    if n <= max_points:
        return t, np.abs(y)
    k = int(np.ceil(n / max_points))
    m = (n // k) * k
    tb = t[:m].reshape(-1, k)[:, 0]
    yb = np.abs(y[:m]).reshape(-1, k).max(axis=1)
    if m < n:
        tb = np.r_[tb, t[m]]
        yb = np.r_[yb, np.abs(y[m:]).max()]
    return tb, yb


def png(fig: Figure) -> bytes:
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=DPI, bbox_inches="tight")
    plt.close(fig)
    return buf.getvalue()


def mark_faults(ax: plt.Axes, windows: Sequence[FaultWindow], t_max: float | None = None) -> None:
    for w in windows:
        if t_max is not None and w.t0_s > t_max:
            continue
        if w.t1_s is not None:
            ax.axvspan(w.t0_s, w.t1_s, color="#d62728", alpha=0.12, lw=0)
        else:
            ax.axvline(w.t0_s, color="#d62728", lw=0.8, ls=":")


def _ylim(ax: plt.Axes, series: dict[str, np.ndarray]) -> None:
    """Scale to the estimators, not to a diverging free INS (which then leaves the plot)."""
    vals = [np.percentile(v, 99.5) for k, v in series.items() if k != FREE_INS and v.size]
    if vals and max(vals) > 0:
        ax.set_ylim(0, 1.15 * max(vals))


def trajectory(
    truth_pos: np.ndarray | None,
    gnss_pos: np.ndarray,
    nav: dict[str, np.ndarray],
    windows: Sequence[FaultWindow] = (),
) -> bytes:
    fig, ax = plt.subplots(figsize=(9, 7))
    col = colours(list(nav))
    if gnss_pos.size:
        (g,) = thin(gnss_pos)
        ax.plot(g[:, 1], g[:, 0], ".", ms=2.5, color="#bbbbbb", label="GNSS fixes", zorder=1)
    for name, p in nav.items():
        (pp,) = thin(p)
        ax.plot(
            pp[:, 1],
            pp[:, 0],
            lw=1.0,
            color=col[name],
            label=name,
            zorder=2,
            ls="--" if name == FREE_INS else "-",
        )
    if truth_pos is not None and truth_pos.size:
        (tp,) = thin(truth_pos)
        ax.plot(tp[:, 1], tp[:, 0], lw=2.2, color="black", label="truth", zorder=3, alpha=0.8)
        ax.plot(tp[0, 1], tp[0, 0], "o", color="black", ms=6)
        # frame the truth (a diverging free INS would shrink the map to a dot)
        pad = 0.15 * max(np.ptp(tp[:, 0]), np.ptp(tp[:, 1]), 50.0)
        cx, cy = (tp[:, 1].min() + tp[:, 1].max()) / 2, (tp[:, 0].min() + tp[:, 0].max()) / 2
        half = max(np.ptp(tp[:, 1]), np.ptp(tp[:, 0])) / 2 + pad
        ax.set_xlim(cx - half, cx + half)
        ax.set_ylim(cy - half, cy + half)
        ax.set_aspect("equal", adjustable="box")
    else:
        ax.set_aspect("equal", adjustable="datalim")
    ax.set_xlabel("east [m]")
    ax.set_ylabel("north [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("Trajectory (NED about the scenario origin)")
    return png(fig)


def error_overview(errs: dict[str, Errors], windows: Sequence[FaultWindow]) -> bytes:
    """Horizontal, vertical, velocity and attitude error vs time, every estimator overlaid."""
    col = colours(list(errs))
    fig, axes = plt.subplots(4, 1, figsize=(11, 11), sharex=True, layout="constrained")
    panels = [
        ("horizontal position error [m]", lambda e: e.horiz_m),
        ("vertical position error |D| [m]", lambda e: e.pos_ned[:, 2]),
        ("velocity error |v| [m/s]", lambda e: e.vel_mps),
        ("attitude error [deg]", lambda e: e.att_deg),
    ]
    t_max = max(float(e.t_s[-1]) for e in errs.values())
    for ax, (label, f) in zip(axes, panels, strict=True):
        shown: dict[str, np.ndarray] = {}
        for name, e in errs.items():
            t, y = envelope(e.t_s, f(e))
            shown[name] = y
            ax.plot(t, y, lw=0.9, color=col[name], label=name, ls="--" if name == FREE_INS else "-")
        mark_faults(ax, windows, t_max)
        _ylim(ax, shown)
        ax.set_xlim(0, t_max)
        ax.set_ylabel(label, fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[0].legend(loc="upper right", fontsize=8, ncol=min(4, len(errs)))
    axes[-1].set_xlabel("time [s]")
    fig.suptitle("Error vs truth (shaded: scenario faults; max per plotted bin)")
    return png(fig)


def error_per_estimator(errs: dict[str, Errors], windows: Sequence[FaultWindow]) -> bytes:
    """The papers' figure: N, E, D position error of each estimator on its own axes."""
    names = list(errs)
    t_max = max(float(e.t_s[-1]) for e in errs.values())
    fig, axes = plt.subplots(
        len(names), 1, figsize=(11, 1.9 * len(names) + 0.8), sharex=True, squeeze=False, layout="constrained"
    )
    for ax, name in zip(axes[:, 0], names, strict=True):
        e = errs[name]
        t, p = thin(e.t_s, e.pos_ned)
        for i, (axis, c) in enumerate(zip("NED", ("#1f77b4", "#2ca02c", "#9467bd"), strict=True)):
            ax.plot(t, p[:, i], lw=0.8, color=c, label=f"δ{axis}")
        mark_faults(ax, windows, t_max)
        ax.set_xlim(0, t_max)
        lim = np.percentile(np.abs(p), 99.5) if p.size else 1.0
        ax.set_ylim(-1.15 * lim - 0.1, 1.15 * lim + 0.1)
        ax.set_ylabel(f"{name} [m]", fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[0, 0].legend(loc="upper right", fontsize=8, ncol=3)
    axes[-1, 0].set_xlabel("time [s]")
    fig.suptitle("Position error N / E / D per estimator")
    return png(fig)


def timesync(t_s: dict[str, np.ndarray], err_us: dict[str, np.ndarray]) -> bytes:
    fig, axes = plt.subplots(
        len(t_s), 1, figsize=(11, 2.6 * len(t_s) + 0.5), sharex=True, squeeze=False, layout="constrained"
    )
    for ax, sensor in zip(axes[:, 0], sorted(t_s), strict=True):
        t, y = thin(t_s[sensor], err_us[sensor])
        ax.plot(t, y, ".", ms=1.5, color="#1f77b4")
        ax.axhline(0, color="black", lw=0.6)
        ax.set_ylabel(f"{sensor} [µs]", fontsize=9)
        ax.grid(True, alpha=0.3)
    axes[-1, 0].set_xlabel("true capture time [s]")
    fig.suptitle("Time-sync error: synchronised stamp − true capture time")
    return png(fig)


def can_load(series: dict[str, tuple[np.ndarray, np.ndarray]]) -> bytes:
    fig, ax = plt.subplots(figsize=(11, 3.2))
    for name, (t, load) in series.items():
        tt, ll = thin(t, load)
        ax.plot(tt, 100 * ll, lw=1.0, label=name, drawstyle="steps-post")
    ax.set_ylim(bottom=0)
    ax.set_xlabel("time [s]")
    ax.set_ylabel("bus load [%]")
    ax.grid(True, alpha=0.3)
    ax.legend(loc="best", fontsize=8)
    ax.set_title("CAN bus load (per second, worst-case stuffing, 1 Mbit/s nominal)")
    return png(fig)

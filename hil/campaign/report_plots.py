"""The campaign report's figures as PNG bytes (matplotlib, Agg, the HTML report's colours)."""

from __future__ import annotations

import matplotlib.pyplot as plt
import numpy as np

from hil.campaign.aggregate import GroupSummary, Paired
from hil.report.plots import colours, png  # also selects the Agg backend


def rms_distribution(groups: list[GroupSummary]) -> bytes:
    """Box plot of each group's horizontal RMS over runs, every run a dot, and its ECDF."""
    have = [s for s in groups if s.ok]
    col = colours([s.label for s in have])
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, max(3.0, 0.45 * len(have) + 1.5)), layout="constrained")
    data = [s.col("h_rms_m") for s in have]
    ax.boxplot(data, orientation="horizontal", showfliers=False, widths=0.6)
    rng = np.random.default_rng(0)  # jitter only: the same page every time
    for i, (s, x) in enumerate(zip(have, data, strict=True), start=1):
        ax.plot(x, i + 0.15 * rng.uniform(-1, 1, x.size), ".", ms=3, alpha=0.5, color=col[s.label])
        xs = np.sort(x[np.isfinite(x)])
        ax2.step(
            xs, np.arange(1, xs.size + 1) / max(xs.size, 1), where="post", color=col[s.label], label=s.label
        )
    ax.set_yticks(range(1, len(have) + 1), [s.label for s in have], fontsize=8)
    ax.set_xlabel("horizontal RMS per run [m]")
    ax.grid(True, axis="x", alpha=0.3)
    ax2.set_xlabel("horizontal RMS per run [m]")
    ax2.set_ylabel("fraction of runs ≤")
    ax2.grid(True, alpha=0.3)
    ax2.legend(fontsize=7, loc="lower right")
    if data and max(np.nanmax(x) for x in data if x.size) > 20 * max(np.nanmin(x) for x in data if x.size):
        ax.set_xscale("log")
        ax2.set_xscale("log")
    return png(fig)


def convergence_distribution(groups: list[GroupSummary]) -> bytes:
    have = [s for s in groups if np.isfinite(s.col("conv_s")).any()]
    fig, ax = plt.subplots(figsize=(12, max(2.5, 0.45 * len(have) + 1.2)), layout="constrained")
    ax.boxplot(
        [s.col("conv_s")[np.isfinite(s.col("conv_s"))] for s in have], orientation="horizontal", widths=0.6
    )
    ax.set_yticks(range(1, len(have) + 1), [s.label for s in have], fontsize=8)
    ax.set_xlabel("convergence time per run [s] (runs that never converge left out)")
    ax.grid(True, axis="x", alpha=0.3)
    return png(fig)


def nees_over_time(groups: list[GroupSummary]) -> bytes:
    """The run-averaged NEES per epoch of each group with its chi-square band."""
    col = colours([s.label for s in groups])
    fig, ax = plt.subplots(figsize=(12, 4.5), layout="constrained")
    for s in groups:
        c = s.consistency
        assert c is not None and c.nees_mean is not None
        ax.plot(
            c.t_s[: c.nees_mean.size],
            c.nees_mean,
            lw=0.8,
            color=col[s.label],
            label=f"{s.label} ({len(s.ok)} runs)",
        )
        for b in c.band:
            ax.axhline(b, color=col[s.label], ls="--", lw=0.7)
    ax.axhline(6.0, color="k", lw=0.6, ls=":")
    ax.set_yscale("log")
    ax.set_xlabel("t [s]")
    ax.set_ylabel("mean NEES over runs (6 dof; dashed: 95 % band)")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    return png(fig)


def rms_vs_sigma(groups: list[GroupSummary]) -> bytes:
    """Seed 004's check: the Monte-Carlo RMS of the horizontal error against the filter's sigma."""
    col = colours([s.label for s in groups])
    fig, (ax, ax2) = plt.subplots(2, 1, figsize=(12, 7), sharex=True, layout="constrained")
    for s in groups:
        c = s.consistency
        assert c is not None
        ax.plot(c.t_s, c.rms_m, lw=1.0, color=col[s.label], label=f"{s.label}: MC RMS ({len(s.ok)} runs)")
        if c.sigma_m is not None:
            ax.plot(
                c.t_s,
                c.sigma_m,
                lw=1.0,
                ls="--",
                color=col[s.label],
                label=f"{s.label}: filter σ (RMS over runs)",
            )
            with np.errstate(divide="ignore", invalid="ignore"):
                ax2.plot(c.t_s, c.rms_m / c.sigma_m, lw=0.8, color=col[s.label])
            for b in c.ratio_band:
                ax2.axhline(b, color=col[s.label], ls="--", lw=0.7)
    ax.set_ylabel("horizontal error [m]")
    ax.set_yscale("log")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=8)
    ax2.axhline(1.0, color="k", lw=0.6, ls=":")
    ax2.set_ylabel("MC RMS / σ (dashed: 95 % band)")
    ax2.set_xlabel("t [s]")
    ax2.grid(True, alpha=0.3)
    return png(fig)


def paired_scatter(paired: list[Paired]) -> bytes:
    """Each run's RMS before against after (below the diagonal: better), and the differences."""
    col = colours([p.label for p in paired])
    fig, (ax, ax2) = plt.subplots(1, 2, figsize=(12, 5), layout="constrained")
    lo, hi = np.inf, 0.0
    for p in paired:
        b = np.array([x["h_rms_m"] for x, _ in p.pairs], float)
        a = np.array([y["h_rms_m"] for _, y in p.pairs], float)
        ax.plot(b, a, ".", ms=4, color=col[p.label], label=p.label)
        lo, hi = min(lo, float(np.nanmin([b, a]))), max(hi, float(np.nanmax([b, a])))
        d = a - b
        ax2.hist(d[np.isfinite(d)], bins=30, histtype="step", color=col[p.label], label=p.label)
    ax.plot([lo, hi], [lo, hi], "k--", lw=0.7)
    ax.set_xlabel("horizontal RMS before [m]")
    ax.set_ylabel("horizontal RMS after [m]")
    ax.grid(True, alpha=0.3)
    ax.legend(fontsize=7)
    ax2.axvline(0.0, color="k", lw=0.7)
    ax2.set_xlabel("after − before [m]")
    ax2.set_ylabel("runs")
    ax2.grid(True, alpha=0.3)
    return png(fig)

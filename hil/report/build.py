"""``hil report FILE --out DIR``: one self-contained HTML page plus the PNGs it embeds.

Every section degrades to a note when its inputs are missing (no truth, no GNSS, no capture
times, no CAN, a truncated file): a report is always written. Images are base64 data URIs and
the CSS is inline, so the page makes no network request.
"""

from __future__ import annotations

import base64
import html
import math
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil import __version__
from hil.record.mcapio import RecordingError
from hil.report import plots
from hil.report.data import ReportData, load
from hil.report.metrics import (
    Errors,
    EstimatorStats,
    FaultWindow,
    errors,
    estimator_stats,
    fault_windows,
    gnss_bound_m,
)

ProgressFn = Callable[[float, str], None]  # (fraction 0..1, stage)


@dataclass
class ReportResult:
    html_path: Path
    pngs: list[Path]
    notes: list[str]
    stats: list[EstimatorStats]
    timings_s: dict[str, float] = field(default_factory=dict)


@dataclass
class _Section:
    id: str
    title: str
    body: str


def _f(x: float, digits: int = 2) -> str:
    return "–" if x is None or (isinstance(x, float) and math.isnan(x)) else f"{x:.{digits}f}"


def _table(head: list[str], rows: list[list[str]], cls: str = "") -> str:
    h = "".join(f"<th>{html.escape(c)}</th>" for c in head)
    body = "".join("<tr>" + "".join(f"<td>{c}</td>" for c in r) + "</tr>" for r in rows)
    return f'<table class="{cls}"><thead><tr>{h}</tr></thead><tbody>{body}</tbody></table>'


def _img(data: bytes, alt: str) -> str:
    return f'<img alt="{html.escape(alt)}" src="data:image/png;base64,{base64.b64encode(data).decode()}">'


def _note(text: str) -> str:
    return f'<p class="note">{html.escape(text)}</p>'


CSS = """
body{font-family:system-ui,-apple-system,Segoe UI,Roboto,sans-serif;margin:0;color:#222;background:#fafafa}
header{background:#1d3557;color:#fff;padding:14px 28px}
header h1{margin:0;font-size:22px} header p{margin:4px 0 0;font-size:13px;opacity:.85}
nav{padding:6px 28px;background:#e9eef4;font-size:13px} nav a{margin-right:14px;color:#1d3557}
main{padding:8px 28px 40px;max-width:1280px}
section{background:#fff;border:1px solid #ddd;border-radius:6px;padding:10px 18px;margin:16px 0}
h2{font-size:18px;margin:6px 0 10px;color:#1d3557}
table{border-collapse:collapse;font-size:13px;margin:6px 0}
th,td{border:1px solid #ccc;padding:3px 8px;text-align:right} th{background:#f0f3f7}
td:first-child,th:first-child{text-align:left}
img{max-width:100%;height:auto;display:block;margin:8px 0}
.note{background:#fff6e0;border-left:4px solid #e0a800;padding:6px 10px;font-size:13px}
.warn td{background:#fdecea}
.small{font-size:12px;color:#555}
"""


@dataclass
class _Draft:
    """The page being assembled: sections and notes in page order, the PNGs written beside it.

    Each section builder appends to it, so the order of the calls in :func:`build_report` is the
    order of the page.
    """

    out: Path
    progress: ProgressFn | None
    notes: list[str] = field(default_factory=list)
    sections: list[_Section] = field(default_factory=list)
    pngs: list[Path] = field(default_factory=list)

    def step(self, frac: float, stage: str) -> None:
        if self.progress is not None:
            self.progress(frac, stage)

    def figure(self, name: str, data: bytes, alt: str) -> str:
        """Write ``name.png`` beside the page and return the same image inline."""
        p = self.out / f"{name}.png"
        p.write_bytes(data)
        self.pngs.append(p)
        return _img(data, alt)

    def add(self, anchor: str, title: str, body: str) -> None:
        self.sections.append(_Section(anchor, title, body))


def build_report(path: str | Path, out_dir: str | Path, progress: ProgressFn | None = None) -> ReportResult:
    """Read ``path``, write ``out_dir/report.html`` and ``out_dir/*.png``."""
    out = Path(out_dir)
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as err:  # a file in the way, a read-only disk: one line, before the reading
        raise RecordingError(f"cannot write the report under {out}: {err.strerror}") from err
    timings: dict[str, float] = {}
    t0 = time.monotonic()
    page = _Draft(out, progress)
    d = load(path, lambda done, total: page.step(0.7 * done / max(total, 1), "reading"))
    timings["read"] = time.monotonic() - t0
    page.notes.extend(d.notes)
    windows, wnotes = fault_windows(d)
    page.notes.extend(wnotes)
    errs = _errors(d, page.notes)
    cap = gnss_bound_m(d)
    stats = [estimator_stats(n, e, windows, cap) for n, e in errs.items()]

    t1 = time.monotonic()
    page.step(0.72, "plotting")
    _trajectory_section(page, d)
    page.step(0.78, "plotting")
    if errs:
        _accuracy_sections(page, errs, stats, windows, cap)
    if windows:
        _faults_section(page, windows)
    page.step(0.9, "plotting")
    _timesync_section(page, d)
    page.step(0.95, "plotting")
    _can_section(page, d)
    if d.topics:
        _topics_section(page, d)
    if d.status:
        _services_section(page, d)
    timings["plots"] = time.monotonic() - t1
    page.step(0.98, "writing")
    html_path = out / "report.html"
    html_path.write_text(_page(d, page.sections, page.notes), encoding="utf-8")
    timings["total"] = time.monotonic() - t0
    page.step(1.0, "done")
    return ReportResult(html_path, page.pngs, page.notes, stats, timings)


def _errors(d: ReportData, notes: list[str]) -> dict[str, Errors]:
    """Each estimator's errors against truth; why there are none goes to ``notes``."""
    errs: dict[str, Errors] = {}
    if d.truth is None:
        notes.append("no truth (hil/<rig>/truth) in this recording: accuracy is not computed")
    elif not d.nav:
        notes.append("no estimator output (hil/<rig>/nav/*) in this recording: accuracy is not computed")
    else:
        for name, s in d.nav.items():
            e = errors(d.truth, s)
            if e is None:
                notes.append(f"estimator {name}: no solution inside the truth's time span")
            else:
                errs[name] = e
    return errs


def _trajectory_section(page: _Draft, d: ReportData) -> None:
    """The map: truth, GNSS fixes and every estimator, with what is missing said above it."""
    if d.truth is None and not d.nav and not d.gnss_pos.size:
        page.notes.append("nothing to draw on a map: no truth, no estimator output, no GNSS fixes")
        return
    body = page.figure(
        "trajectory",
        plots.trajectory(
            d.truth.pos if d.truth is not None else None, d.gnss_pos, {n: s.pos for n, s in d.nav.items()}
        ),
        "trajectory map",
    )
    if not d.gnss_pos.size:
        body = _note("no GNSS fixes in this recording") + body
    if d.truth is None:
        body = _note("no truth: the map shows the estimators only") + body
    page.add("trajectory", "Trajectory", body)


_STATS_HEAD = [
    "estimator",
    "horiz RMS m",
    "horiz 95% m",
    "horiz max m",
    "horiz final m",
    "vert RMS m",
    "vel RMS m/s",
    "vel 95% m/s",
    "att RMS °",
    "att max °",
    "converged at s",
    "n",
]


def _stats_row(s: EstimatorStats) -> list[str]:
    conv = _f(s.convergence_s, 1) if s.convergence_s is not None else "never"
    return [
        html.escape(s.name),
        _f(s.horiz.rms),
        _f(s.horiz.p95),
        _f(s.horiz.max),
        _f(s.horiz.final),
        _f(s.vert.rms),
        _f(s.vel.rms, 3),
        _f(s.vel.p95, 3),
        _f(s.att.rms, 3),
        _f(s.att.max, 3),
        conv,
        str(s.horiz.n),
    ]


def _accuracy_sections(
    page: _Draft,
    errs: dict[str, Errors],
    stats: list[EstimatorStats],
    windows: list[FaultWindow],
    cap: float | None,
) -> None:
    """The statistics table and the error-vs-time figures."""
    table = _table(_STATS_HEAD, [_stats_row(s) for s in stats])
    expl = (
        '<p class="small">Errors at every solution stamp against truth interpolated there. '
        "Converged at: the first time after which the horizontal error stays below 2× its median over "
        "the last half of the run (at least 1 m, at most the GNSS 95 % radius of the scenario"
        + (f", {cap:.0f} m" if cap else "")
        + "); samples during a scenario fault and 10 s after it are "
        f"excused. <code>{plots.FREE_INS}</code> is the free (unaided) INS, for reference.</p>"
    )
    page.add("stats", "Statistics", table + expl)
    page.step(0.8, "plotting")
    body = page.figure("errors", plots.error_overview(errs, windows), "error vs time")
    page.step(0.86, "plotting")
    body += page.figure("errors_ned", plots.error_per_estimator(errs, windows), "N/E/D error per estimator")
    page.add("errors", "Error vs time", body)


def _faults_section(page: _Draft, windows: list[FaultWindow]) -> None:
    rows = [
        [
            html.escape(w.kind),
            _f(w.t0_s, 1),
            _f(w.t1_s, 1) if w.t1_s is not None else "–",
            html.escape(w.label),
        ]
        for w in windows
    ]
    page.add("faults", "Faults and events", _table(["kind", "start s", "end s", "what"], rows))


def _timesync_section(page: _Draft, d: ReportData) -> None:
    """Synced stamp minus true capture time per sensor, from the recorded capture truth."""
    if not d.sync_err_ns:
        page.notes.append(
            "no time-sync error: the recording lacks synced/<sensor> or capture/<sensor> (hil.CaptureTruth)"
        )
        return
    rows = []
    for sensor in sorted(d.sync_err_ns):
        e_us = d.sync_err_ns[sensor] * 1e-3
        rows.append(
            [
                html.escape(sensor),
                str(e_us.size),
                _f(float(np.mean(e_us)), 1),
                _f(float(np.sqrt(np.mean(e_us**2))), 1),
                _f(float(np.percentile(np.abs(e_us), 95)), 1),
                _f(float(np.max(np.abs(e_us))), 1),
                str(d.sync_unmatched.get(sensor, 0)),
            ]
        )
    body = _table(["sensor", "matched", "mean µs", "RMS µs", "95% |e| µs", "max |e| µs", "unmatched"], rows)
    body += page.figure(
        "timesync",
        plots.timesync(
            {k: v * 1e-9 for k, v in d.sync_t_ns.items()}, {k: v * 1e-3 for k, v in d.sync_err_ns.items()}
        ),
        "time-sync error",
    )
    page.add("timesync", "Time synchronisation", body)


def _can_section(page: _Draft, d: ReportData) -> None:
    """Bus load computed from the recorded frames beside the emulators' own counters."""
    can_series: dict[str, tuple[np.ndarray, np.ndarray]] = {
        f"{ch} (from frames)": v for ch, v in d.can_load.items()
    }
    can_series.update({f"{svc} (status)": v for svc, v in d.status_load.items()})
    if not can_series:
        page.notes.append("no CAN frames (hil.CanFrame) and no bus-load counters in this recording")
        return
    rows = [
        [
            html.escape(name),
            _f(100 * float(np.mean(v[1])), 2),
            _f(100 * float(np.max(v[1])), 2),
            str(v[1].size),
        ]
        for name, v in can_series.items()
    ]
    body = _table(["source", "mean load %", "peak load %", "seconds"], rows)
    body += (
        '<p class="small">From frames: bits on the wire per second (ISO 11898-1 frame format, '
        "worst-case stuffing) / 1 Mbit/s nominal (FD data phase at 5 Mbit/s). "
        "Status: the emulator's own <code>bus_load_permille</code> counter.</p>"
    )
    body += page.figure("can_load", plots.can_load(can_series), "CAN bus load")
    page.add("can", "CAN bus load", body)


def _topics_section(page: _Draft, d: ReportData) -> None:
    """Per-topic rate and loss; publisher restarts get their own column only when there are any."""
    rows = []
    restarted = [t for t in d.topics if t.restarts]
    for t in d.topics:
        row = [
            html.escape(t.topic),
            html.escape(t.schema),
            str(t.count),
            _f(t.rate_hz, 2),
            str(t.missing),
            _f(t.loss_pct, 3),
            str(t.duplicates),
            str(t.undecodable),
        ]
        if restarted:
            row.append(str(t.restarts))
        rows.append(row)
    head = ["topic", "type", "count", "rate Hz", "missing", "loss %", "duplicates", "undecodable"]
    body = _table(head + (["restarts"] if restarted else []), rows)
    lossy = [t.topic for t in d.topics if t.missing or t.undecodable]
    if lossy:
        body = _note(f"loss on {len(lossy)} topic(s): {', '.join(lossy[:8])}") + body
    if restarted:
        names = ", ".join(t.topic for t in restarted[:8])
        body = _note(f"{len(restarted)} publisher(s) restarted during the recording: {names}") + body
    body += (
        '<p class="small">Rate over each stream\'s own times (time of validity, the MCAP publish '
        "time), not when the recorder took it; missing from gaps in each publisher's "
        "<code>seq</code>; a restarted service counts again in a new generation "
        "(a restart, not loss: see <code>hil.record.completeness</code>).</p>"
    )
    page.add("topics", "Message rates and loss", body)


def _services_section(page: _Draft, d: ReportData) -> None:
    rows = []
    for name, st in sorted(d.status.items()):
        rej = sum(c.value for c in st.counters if c.key.startswith("rejected"))
        rows.append(
            [
                html.escape(name),
                html.escape(st.state),
                _f(st.uptime_s, 1),
                str(rej),
                html.escape(st.last_error[:120]),
            ]
        )
    page.add(
        "services",
        "Services (last status)",
        _table(["service", "state", "uptime s", "rejected", "last error"], rows),
    )


def _page(d: ReportData, sections: list[_Section], notes: list[str]) -> str:
    t0, t1 = d.span_ns()
    meta = d.metadata.get("hil", {})
    run = d.run
    rig = run.rig if run else meta.get("rig", "?")
    scen = run.scenario if run else meta.get("scenario", "?")
    seed = run.seed if run else meta.get("seed", "?")
    facts = (
        f"{html.escape(d.path.name)} · rig {html.escape(str(rig))} · scenario {html.escape(str(scen))} · "
        f"seed {html.escape(str(seed))} · executor {html.escape(meta.get('executor', '?'))} · "
        f"{(t1 - t0) * 1e-9:.1f} s · {d.messages} messages"
    )
    links = "".join(f'<a href="#{s.id}">{html.escape(s.title)}</a>' for s in sections)
    note_html = ""
    if notes:
        note_html = '<section id="notes"><h2>Notes</h2>' + "".join(_note(n) for n in notes) + "</section>"
    body = "".join(
        f'<section id="{s.id}"><h2>{html.escape(s.title)}</h2>{s.body}</section>' for s in sections
    )
    return (
        '<!DOCTYPE html>\n<html lang="en"><head><meta charset="utf-8">'
        f"<title>hil report – {html.escape(d.path.name)}</title>"
        '<meta name="viewport" content="width=device-width, initial-scale=1">'
        '<link rel="icon" href="data:,">'
        f"<style>{CSS}</style></head><body>"
        f"<header><h1>hil report</h1><p>{facts}</p></header><nav>{links}</nav><main>"
        f"{note_html}{body}"
        f'<p class="small">Generated by hil {html.escape(__version__)} (<code>hil report</code>).</p>'
        "</main></body></html>\n"
    )

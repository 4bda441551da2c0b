"""Attacks on the live rig beside an unattacked run of the same seed (issue 18's Measure).

    hil bench attack [--duration 30] [--start 10] [--flood-n 20000] [--flood-s 5] [--spoof-s 10]

Three real-time ``hil up`` runs of one scenario and seed, each its own OS processes on a Zenoh
router the bench opens (as a user who opens the bus to other processes would):

- **clean**: nothing but the rig;
- **flood**: ``tools/bus_attack.py`` -- a plain zenoh-python process that is not the rig's --
  sends ``--flood-n`` valid-looking fixes in ``--flood-s`` seconds (issue 18: 20,000 in 5 s), half
  on ``synced/gnss`` (the fusion's input) and half on ``sensor/gnss`` (the time sync's), from rig
  time ``--start``;
- **spoof**: the receiver itself is spoofed (the scenario's ``gnss_spoof``: 500 m north claiming
  σ 0.5 m for ``--spoof-s`` seconds from ``--start``), which only the integrity gate can stop.

Figures from each recording: the fused output's rate (ekf15 solutions per rig second) and its
latency (recorder receive time minus the solution's stamp, both rig time) before, during and in
the two seconds after the attack; every estimator's horizontal RMS against truth over the attack
window and the 10 s after it, as a ratio to the clean run; the fusion's inbox peak and resident
memory (``status/fusion``), what was refused and gated, the recorder's loss and the exit code.
"""

from __future__ import annotations

import argparse
import json
import os
import socket
import subprocess
import sys
import tempfile
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np

from hil.bench import command_line, write_section

NS = 1_000_000_000
RIG = "atk"
ESTIMATOR_ORDER = ("ekf15", "kfvel", "cf3", "comp1", "comp3f", "compvs", "ins")


def _free_port() -> int:
    with socket.socket() as s:
        s.bind(("127.0.0.1", 0))
        return int(s.getsockname()[1])


def _attack_tool() -> Path:
    import hil

    tool = Path(hil.__file__).resolve().parents[1] / "tools" / "bus_attack.py"
    if not tool.exists():
        raise SystemExit(f"hil bench attack: {tool} not found (run from a checkout of the repository)")
    return tool


@dataclass
class Run:
    name: str
    rc: int = -1
    console: str = ""
    sent: dict[str, Any] = field(default_factory=dict)
    window: tuple[float, float] = (0.0, 0.0)  # the attack, rig seconds
    rate: dict[str, float] = field(default_factory=dict)  # ekf15 outputs per rig second
    latency_ms: dict[str, tuple[float, float]] = field(default_factory=dict)  # p50, p99
    h_rms_m: dict[str, float] = field(default_factory=dict)
    counters: dict[str, int] = field(default_factory=dict)
    rss_kib: tuple[int, int] = (0, 0)  # before the attack, the run's peak
    missing: int = -1


def _scenario(base: str, spoof: tuple[float, float] | None, seed_offset: int = 0) -> str:
    from hil.nav.scenario import load_scenario, scenario_overrides

    s = load_scenario(base)
    text = scenario_overrides(s, seed=s.seed + seed_offset).source_text if seed_offset else s.source_text
    if spoof is not None:
        text += (
            f'\n[[event]]\nkind = "gnss_spoof"\nt_start_s = {spoof[0]}\nt_end_s = {spoof[1]}\n'
            "offset_ned_m = [500.0, 0.0, 0.0]\nsigma_m = 0.5\n"
        )
    return text


def live(
    name: str, scenario_text: str, duration_s: float, flood: tuple[float, int, float] | None, tmp: Path
) -> Path:
    """One ``hil up`` on a router of the bench's; with ``flood`` = (start s, n, seconds), the
    stranger floods it. Returns the recording."""
    from hil.bus.session import BusConfig, open_session

    scenario = tmp / f"{name}.toml"
    scenario.write_text(scenario_text, encoding="utf-8")
    out = tmp / f"{name}.mcap"
    endpoint = f"tcp/127.0.0.1:{_free_port()}"
    hub = open_session(BusConfig(mode="router", listen=(endpoint,), connect=()))
    env = dict(os.environ, HIL_ZENOH_MODE="client", HIL_ZENOH_CONNECT=endpoint, HIL_ZENOH_LISTEN="")
    procs: list[subprocess.Popen[str]] = []
    try:
        cmd = [
            sys.executable,
            "-m",
            "hil.cli",
            "up",
            "--scenario",
            str(scenario),
            "--duration",
            f"{duration_s:g}",
        ]
        cmd += ["--record", str(out), "--quiet", "--rig", RIG]
        up = subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env)
        procs.append(up)
        attacker = None
        if flood is not None:
            start, n, seconds = flood
            acmd = [sys.executable, str(_attack_tool()), "--connect", endpoint, "--rig", RIG]
            acmd += [
                "--start-after",
                f"{start:g}",
                "--wait",
                "120",
                "flood",
                "--n",
                str(n // 2),  # per key
                "--seconds",
                f"{seconds:g}",
            ]
            attacker = subprocess.Popen(acmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
            procs.append(attacker)
        console, _ = up.communicate(timeout=duration_s + 180)
        sent: dict[str, Any] = {}
        if attacker is not None:
            a_out, a_err = attacker.communicate(timeout=120)
            if attacker.returncode != 0:
                raise RuntimeError(f"bus_attack.py exited {attacker.returncode}: {a_err.strip()[-400:]}")
            sent = json.loads(a_out.strip().splitlines()[-1])
        (tmp / f"{name}.json").write_text(json.dumps({"rc": up.returncode, "console": console, "sent": sent}))
        return out
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
        hub.close()


def score(name: str, path: Path, window: tuple[float, float]) -> Run:
    """The figures of one recording (see the module docstring)."""
    from hil.messages import NavSolution
    from hil.record.mcapio import read_session

    meta = json.loads(path.with_suffix(".json").read_text())
    run = Run(name, rc=int(meta["rc"]), console=meta["console"], sent=meta["sent"], window=window)
    s = read_session(path)
    run.missing = int(s.meta("completeness", "missing", -1))
    t0, t1 = window
    truth = [r.decode() for r in s.by_topic(f"hil/{RIG}/truth") if not r.foreign]
    tt = np.array([m.stamp_ns for m in truth], dtype=np.float64)
    tn = np.array([m.pos_ned_m[0] for m in truth])
    te = np.array([m.pos_ned_m[1] for m in truth])
    sols: dict[str, list[tuple[int, int, float, float]]] = {}
    for r in s.by_topic_prefix(f"hil/{RIG}/nav/"):
        m = r.decode()
        if r.foreign or not isinstance(m, NavSolution):
            continue
        # publish time is the stamp on the recording's UTC timeline: receive minus it is latency
        rx_rig_ns = m.stamp_ns + (r.log_time_ns - r.publish_time_ns)
        sols.setdefault(m.estimator, []).append((m.stamp_ns, rx_rig_ns, m.pos_ned_m[0], m.pos_ned_m[1]))
    for est, rows in sols.items():
        a = np.array(rows, dtype=np.float64)
        m = (a[:, 0] >= t0 * NS) & (a[:, 0] < (t1 + 10.0) * NS)
        if m.any():
            dn = a[m, 2] - np.interp(a[m, 0], tt, tn)
            de = a[m, 3] - np.interp(a[m, 0], tt, te)
            run.h_rms_m[est] = float(np.sqrt(np.mean(dn**2 + de**2)))
    ekf = np.array(sols.get("ekf15", []), dtype=np.float64).reshape(-1, 4)
    stamp, log = ekf[:, 0] / NS, ekf[:, 1] / NS
    spans = {
        "before": (max(2.0, t0 - 5.0), t0),
        "attack": (t0, t1),
        "0-1 s after": (t1, t1 + 1.0),
        "1-2 s after": (t1 + 1.0, t1 + 2.0),
    }
    for key, (a, b) in spans.items():
        # rate by receive time (what a consumer sees arrive), latency of what arrived then
        m = (log >= a) & (log < b)
        run.rate[key] = float(m.sum() / (b - a))
        lat = (log[m] - stamp[m]) * 1e3
        run.latency_ms[key] = (
            (float(np.percentile(lat, 50)), float(np.percentile(lat, 99))) if m.any() else (float("nan"),) * 2
        )
    status = [r.decode() for r in s.by_topic(f"hil/{RIG}/status/fusion") if not r.foreign]
    peak: dict[str, int] = {}
    rss_before, rss_peak = 0, 0
    for st in status:
        c = st.counter_map()
        for k, v in c.items():
            if k == "inbox.peak" or k.startswith(("rejected.foreign", "gnss_gate.rejected", "inbox.dropped")):
                peak[k] = max(peak.get(k, 0), int(v))
        rss = int(c.get("rss_kib", 0))
        rss_peak = max(rss_peak, rss)
        if st.stamp_ns < t0 * NS:
            rss_before = rss
    for st in (r.decode() for r in s.by_topic(f"hil/{RIG}/status/recorder") if not r.foreign):
        peak["recorder.dropped_rig"] = max(
            peak.get("recorder.dropped_rig", 0), int(st.counter_map().get("dropped_rig", 0))
        )
    run.counters, run.rss_kib = peak, (rss_before, rss_peak)
    return run


def offline_ratios(
    scenario: str, seeds: int, t0: float, spoof_s: float, duration_s: float, imu_rate: int | None
) -> tuple[dict[str, dict[str, float]], str]:
    """The spoof (and, beside it, an outage of the same window) through the fusion core on the
    emulator cores with ideal timing, ``seeds`` sensor seeds: each estimator's horizontal RMS over
    the window and the 10 s after it, pooled over the seeds, per case. What the live runs measure,
    without the bus and the machine's load."""
    from hil.estimators.registry import DEFAULT_ESTIMATORS
    from hil.fusion.core import FusionConfig, FusionCore
    from hil.fusion.ideal import ideal_inputs
    from hil.nav.scenario import parse_scenario, scenario_overrides
    from hil.nav.trajectory import TruthGenerator

    base = _scenario(scenario, None)
    events = {
        "clean": "",
        "outage": f'\n[[event]]\nkind = "gnss_outage"\nt_start_s = {t0}\nt_end_s = {t0 + spoof_s}\n',
        "spoof": _scenario(scenario, (t0, t0 + spoof_s))[len(base) :],
    }
    sq: dict[str, dict[str, list[float]]] = {c: {} for c in events}
    s0 = parse_scenario(base)
    for k in range(seeds):
        for case, ev in events.items():
            kw: dict[str, Any] = {"seed": s0.seed + k, "duration_s": duration_s}
            if imu_rate:
                kw["imu_rate_hz"] = imu_rate
            s = scenario_overrides(parse_scenario(base + ev), **kw)
            truth = TruthGenerator(s)
            core = FusionCore.for_scenario(s, FusionConfig(estimators=DEFAULT_ESTIMATORS, output_every=10))
            out = [o for m in ideal_inputs(s, truth) for o in core.push(m, "receiver")] + core.flush()
            by: dict[str, list[Any]] = {}
            for o in out:
                by.setdefault(o.estimator, []).append(o)
            for name, sols in by.items():
                t = np.array([o.stamp_ns for o in sols])
                w = (t >= t0 * NS) & (t < (t0 + spoof_s + 10.0) * NS)
                err = np.array([o.pos_ned_m[:2] for o in sols])[w] - truth.sample(t[w]).pos_ned_m[:, :2]
                sq[case].setdefault(name, []).append(float(np.mean(np.sum(err**2, axis=1))))
    rms = {c: {n: float(np.sqrt(np.mean(v))) for n, v in d.items()} for c, d in sq.items()}
    how = (
        f"`{scenario}` for {duration_s:g} s, {seeds} sensor seeds from the scenario's, "
        f"IMU {imu_rate or s0.imu.rate_hz} Hz, the gap/spoof at {t0:g}-{t0 + spoof_s:g} s"
    )
    return rms, how


def offline_section(rms: dict[str, dict[str, float]], how: str) -> str:
    clean = rms["clean"]
    ests = [e for e in ESTIMATOR_ORDER if e in clean] + sorted(set(clean) - set(ESTIMATOR_ORDER))
    lines = [
        f"### Offline: the fusion core on ideal inputs ({how})",
        "",
        "Horizontal RMS (m) over the spoof window and the 10 s after it, pooled over the seeds; "
        "ratio to clean. The spoof is rejected by the gate, so it costs what an outage does.",
        "",
        "| estimator | clean | outage | spoof |",
        "| --- | ---: | ---: | ---: |",
    ]
    for e in ests:
        a = clean[e]
        cells = [f"{rms[c][e]:.2f} ({rms[c][e] / a:.2f}×)" for c in ("outage", "spoof")]
        lines.append(f"| {e} | {a:.2f} | " + " | ".join(cells) + " |")
    return "\n".join(lines)


def seeds_section(spoofed: list[Run], clean: list[Run], scenario: str) -> str:
    """The live spoof over several sensor seeds: per estimator the RMS pooled over the seeds (mean
    of the squares), attacked against clean over the same window, and the per-seed ratios."""
    ests = [e for e in ESTIMATOR_ORDER if e in clean[0].h_rms_m]
    lines = [
        f"**The live spoof over {len(spoofed)} sensor seeds** (`{scenario}`'s seed + 0..{len(spoofed) - 1}, "
        "a clean and a spoofed `hil up` each): horizontal RMS over the spoof and the 10 s after it, "
        "pooled over the seeds; the per-seed ratios beside it.",
        "",
        "| estimator | clean | spoof | ratio | per seed |",
        "| --- | ---: | ---: | ---: | --- |",
    ]
    for e in ests:
        a = np.array([r.h_rms_m.get(e, np.nan) for r in clean])
        b = np.array([r.h_rms_m.get(e, np.nan) for r in spoofed])
        pa, pb = float(np.sqrt(np.mean(a**2))), float(np.sqrt(np.mean(b**2)))
        per = ", ".join(f"{x:.2f}" for x in b / a)
        lines.append(f"| {e} | {pa:.2f} | {pb:.2f} | {pb / pa:.2f}× | {per} |")
    return "\n".join(lines)


def _fmt(x: float, nd: int = 1) -> str:
    return "–" if not np.isfinite(x) else f"{x:.{nd}f}"


def section(runs: list[Run], baselines: dict[str, Run], note: str) -> str:
    """``baselines``: the clean run scored over each attacked run's window, by its name."""
    clean = runs[0]
    lines = [note, "", "**Fused output (ekf15), by the recorder's receive time:** rate in solutions "
             "per second; latency p50 / p99 in ms (receive minus stamp).", "",
             "| run | attack (rig s) | exit | missing | " + " | ".join(clean.rate) + " |",
             "| --- | --- | ---: | ---: | " + " | ".join("---:" for _ in clean.rate) + " |"]  # fmt: skip
    for r in runs:
        cells = [
            f"{r.rate[k]:.0f}/s, {_fmt(r.latency_ms[k][0])} / {_fmt(r.latency_ms[k][1])} ms"
            for k in clean.rate
        ]
        win = f"{r.window[0]:g}–{r.window[1]:g}" if r.name != "clean" else "(none)"
        lines.append(f"| {r.name} | {win} | {r.rc} | {r.missing} | " + " | ".join(cells) + " |")
    ests = [e for e in ESTIMATOR_ORDER if e in clean.h_rms_m] + sorted(
        set(clean.h_rms_m) - set(ESTIMATOR_ORDER)
    )
    lines += ["", "**Horizontal RMS over the attack window and the 10 s after it** (m), beside the clean "
              "run's over the same window; ratio attacked / clean:", "",
              "| estimator | " + " | ".join(f"clean, {r.name}'s window | {r.name}" for r in runs[1:]) + " |",
              "| --- | " + " | ".join("---: | ---:" for _ in runs[1:]) + " |"]  # fmt: skip
    for e in ests:
        cells = []
        for r in runs[1:]:
            a = baselines[r.name].h_rms_m.get(e, float("nan"))
            b = r.h_rms_m.get(e, float("nan"))
            cells.append(f"{_fmt(a, 2)} | {_fmt(b, 2)} ({_fmt(b / a, 2)}×)")
        lines.append(f"| {e} | " + " | ".join(cells) + " |")
    lines += ["", "**The fusion's status and the recorder** (largest value over the run):", "",
              "| run | inbox peak | RSS before → peak (MiB) | refused (foreign) | gated (ekf15) "
              "| recorder dropped |",
              "| --- | ---: | ---: | ---: | ---: | ---: |"]  # fmt: skip
    for r in runs:
        c = r.counters
        foreign = sum(v for k, v in c.items() if k.startswith("rejected.foreign"))
        lines.append(
            f"| {r.name} | {c.get('inbox.peak', 0)} | "
            f"{r.rss_kib[0] / 1024:.1f} → {r.rss_kib[1] / 1024:.1f} | "
            f"{foreign} | {c.get('gnss_gate.rejected.ekf15', 0)} | {c.get('recorder.dropped_rig', 0)} |"
        )
    flood = next((r for r in runs if r.name == "flood"), None)
    if flood is not None and flood.sent:
        sent = flood.sent.get("sent", {})
        lines += ["", f"The stranger sent {', '.join(f'{v} on {k}' for k, v in sent.items())}."]
    return "\n".join(lines)


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="hil bench attack", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="straight_level")
    ap.add_argument("--duration", type=float, default=30.0, help="rig seconds per run")
    ap.add_argument("--start", type=float, default=10.0, help="rig time the attacks start")
    ap.add_argument("--flood-n", type=int, default=20_000, help="fixes in the flood (half on each key)")
    ap.add_argument("--flood-s", type=float, default=5.0, help="the flood's length (s)")
    ap.add_argument("--spoof-s", type=float, default=10.0, help="the receiver spoof's length (s)")
    ap.add_argument("--offline-seeds", type=int, default=6, help="seeds of the offline section (0: none)")
    ap.add_argument("--offline-duration", type=float, default=50.0, help="the offline runs' length (s)")
    ap.add_argument("--offline-imu-rate", type=int, default=100, help="the offline runs' IMU rate (Hz)")
    ap.add_argument("--no-live", action="store_true", help="only the offline section")
    ap.add_argument(
        "--live-seeds", type=int, default=1, help="sensor seeds of the live spoof (clean + spoof each)"
    )
    ap.add_argument("--keep", type=Path, default=None, help="keep the recordings in this directory")
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch docs/benchmarks.md")
    a = ap.parse_args(argv)
    for what, v in (
        ("--duration", a.duration),
        ("--start", a.start),
        ("--flood-s", a.flood_s),
        ("--spoof-s", a.spoof_s),
    ):
        if not np.isfinite(v) or v <= 0:
            ap.error(f"{what} must be a positive number of seconds, not {v}")
    if a.start + max(a.flood_s, a.spoof_s) + 3.0 > a.duration:
        ap.error(
            f"--duration {a.duration:g} ends before the attack and the 3 s after it "
            f"({a.start:g} + the attack + 3)"
        )
    if a.flood_n < 2:
        ap.error(f"--flood-n must be at least 2 (half go on each key), not {a.flood_n}")
    if a.live_seeds < 1:
        ap.error(f"--live-seeds must be at least 1, not {a.live_seeds}")
    if a.offline_seeds < 0 or a.offline_duration < 2.0 * (a.spoof_s + 10.0):
        ap.error("--offline-seeds must be >= 0 and --offline-duration at least twice the spoof + 10 s")
    parts: list[str] = []
    if a.offline_seeds:
        t0 = a.offline_duration / 2.0  # the window ends 10 s after the spoof, before the run
        rms, how = offline_ratios(
            a.scenario, a.offline_seeds, t0, a.spoof_s, a.offline_duration, a.offline_imu_rate
        )
        parts.append(offline_section(rms, how))
    bad: list[str] = []
    if not a.no_live:
        load0 = os.getloadavg()
        spoof = (a.start, a.start + a.spoof_s)
        more_spoof: list[Run] = []
        more_clean: list[Run] = []
        with tempfile.TemporaryDirectory(prefix="hil-attack-") as d:
            tmp = a.keep or Path(d)
            tmp.mkdir(parents=True, exist_ok=True)
            flood = (a.start, a.flood_n, a.flood_s)
            paths = {
                "clean": live("clean", _scenario(a.scenario, None), a.duration, None, tmp),
                "flood": live("flood", _scenario(a.scenario, None), a.duration, flood, tmp),
                "spoof": live("spoof", _scenario(a.scenario, spoof), a.duration, None, tmp),
            }
            runs = [score("clean", paths["clean"], (a.start, a.start + a.flood_s))]
            fl = json.loads(paths["flood"].with_suffix(".json").read_text())["sent"]
            flood_win = (fl["first_rig_ns"] / NS, fl["last_rig_ns"] / NS) if fl else flood[::2]
            runs.append(score("flood", paths["flood"], flood_win))
            runs.append(score("spoof", paths["spoof"], spoof))
            baselines = {r.name: score("clean", paths["clean"], r.window) for r in runs[1:]}
            for k in range(1, a.live_seeds):  # the spoof again on more sensor seeds, each with its clean run
                pair = {
                    case: live(f"{case}{k}", _scenario(a.scenario, win, k), a.duration, None, tmp)
                    for case, win in (("clean", None), ("spoof", spoof))
                }
                more_spoof.append(score("spoof", pair["spoof"], spoof))
                more_clean.append(score("clean", pair["clean"], spoof))
        load1 = os.getloadavg()
        note = (
            f"`{a.scenario}`, {a.duration:g} s per run, one seed; flood: {a.flood_n} fixes in "
            f"{a.flood_s:g} s from a stranger on the bus; spoof: the receiver, 500 m north claiming "
            f"σ 0.5 m for {a.spoof_s:g} s. The clean run's figures use the flood's window. Load "
            f"average (1 min) {load0[0]:.2f} before, {load1[0]:.2f} after, on {os.cpu_count()} cores."
        )
        parts.append("### Live `hil up`\n\n" + section(runs, baselines, note))
        if more_spoof:
            parts.append(seeds_section([runs[2], *more_spoof], [baselines["spoof"], *more_clean], a.scenario))
        bad = [r.name for r in [*runs, *more_spoof, *more_clean] if r.rc != 0]
    md = "\n\n".join(parts)
    print(md)
    if bad:
        print(f"hil bench attack: runs that did not exit 0: {', '.join(bad)}", file=sys.stderr)
    if not a.no_write:
        write_section("attack", md, command_line())
    return 1 if bad else 0

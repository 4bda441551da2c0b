"""``hil bench pacing``: when the live IMU emulator's CAN frames leave, against the ideal grid.

Runs ``hil up`` (every service its own process, the CAN transport of this machine) with the IMU
emulator's pacing process tracing every sample it sends (``HIL_PACING_TRACE``), then reports:

- **lateness** of each sample's first frame, handed to the bus, against its ideal instant (the
  sample's tick, or the end of the sync frame a device sends first on its edge, + that frame's
  bit time on the wire + the controller latency): p50/p99/max, the
  first sample alone (bus and codec are ready before time zero), and how many were more than
  200 µs late;
- **bursts**: samples handed over less than half a period after the previous one (a compressed
  grid; the pacing never does it unless a stall left a FIFO of samples behind);
- **live sync**: the synced IMU stamps against the emulator's capture truth (matched by
  ``seq``), RMS/max from 5 s on -- issue 22's "live sync" figure, beside ``hil bench timesync``'s
  modelled streams;
- the services' start-to-ready times and the emulator's CPU (its sender process included).

The machine's load average is stated: on a shared 2-core machine the tail is the scheduler's.
"""

from __future__ import annotations

import argparse
import os
import tempfile
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from hil.bench import command_line, write_section
from hil.record.mcapio import read_session
from hil.runners.pacing import TRACE_COLUMNS, parse_cpus
from hil.runtime.supervisor import Supervisor, UpOptions

RIG = "benchpace"
SYNC_SETTLE_S = 5.0  # live sync figures from this rig time on (the clock model converges first)


@dataclass
class LiveRun:
    """What one live run measured."""

    rate_hz: float
    duration_s: float
    load_before: float
    trace: np.ndarray  # TRACE_COLUMNS rows, one per sample sent
    counters: dict[str, int]
    sync_err_ns: np.ndarray  # synced IMU stamp - true capture, from SYNC_SETTLE_S on
    ready_s: dict[str, float] = field(default_factory=dict)
    cpu_share: float = 0.0  # the IMU emulator's share of one core (its sender process included)
    rc: int = 0
    failures: list[str] = field(default_factory=list)


def run_live(
    duration_s: float,
    scenario: str = "straight_level",
    rate_hz: int | None = None,
    rt_priority: int = 0,
    cpu_affinity: list[int] | None = None,
    fd: bool = False,
    sched_slice_us: int = 100,
    rig_cpus: list[int] | None = None,
) -> LiveRun:
    """``hil up`` for ``duration_s`` with the pacing traced; the recording read back."""
    from hil.bench.capture import restamp_errors

    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as d:
        rec = Path(d) / "bench.mcap"
        old = os.environ.get("HIL_PACING_TRACE")
        os.environ["HIL_PACING_TRACE"] = d
        try:
            sup = Supervisor(
                UpOptions(
                    scenario=scenario,
                    duration_s=duration_s,
                    record=rec,
                    rig=RIG,
                    live=False,
                    log_dir=Path(d) / "logs",
                    imu_rate_hz=rate_hz,
                    rt_priority=rt_priority,
                    cpu_affinity=list(cpu_affinity or []),
                    sched_slice_us=sched_slice_us,
                    rig_cpus=list(rig_cpus or []),
                    fd=fd,
                )
            )
            rc = sup.run()
        finally:
            if old is None:
                os.environ.pop("HIL_PACING_TRACE", None)
            else:
                os.environ["HIL_PACING_TRACE"] = old
        trace_path = Path(d) / "imu_emulator.npy"
        trace = (
            np.load(trace_path) if trace_path.exists() else np.zeros((0, len(TRACE_COLUMNS)), dtype=np.int64)
        )
        sync = np.zeros(0, dtype=np.int64)
        counters: dict[str, int] = {}
        if rec.exists():
            s = read_session(rec)
            t, e = restamp_errors(s, "imu")
            sync = e[t >= SYNC_SETTLE_S]
            counters = _last_counters(s)
    period = trace[1:, 1] - trace[:-1, 1] if len(trace) > 1 else np.zeros(0)
    rate = 1e9 / float(np.median(period)) if len(period) else float(rate_hz or 0)
    cpu = sup.cpu_s.get("imu_emulator", 0.0) / sup.cpu_window_s if sup.cpu_window_s > 0 else 0.0
    return LiveRun(
        rate, duration_s, load_before, trace, counters, sync, sup.ready_s(), cpu, rc, list(sup.failures)
    )


def _last_counters(session: object) -> dict[str, int]:
    """The IMU emulator's last status counters in the recording."""
    last: dict[str, int] = {}
    for r in session.records:  # type: ignore[attr-defined]
        if r.topic.endswith("/status/imu_emulator"):
            last = r.decode().counter_map()
    return last


def timing_rows(run: LiveRun) -> dict[str, str]:
    """The lateness distribution of one run, in µs."""
    tr = run.trace
    if not len(tr):
        return {"samples": "0"}
    cols = {c: i for i, c in enumerate(TRACE_COLUMNS)}
    late_us = (tr[:, cols["handed_ns"]] - tr[:, cols["ideal_ns"]]) * 1e-3
    handed = tr[:, cols["handed_ns"]]
    period = float(np.median(np.diff(tr[:, cols["due_ns"]]))) if len(tr) > 1 else 0.0
    bursts = int(np.sum(np.diff(handed) < period / 2)) if period > 0 else 0
    return {
        "samples": str(len(tr)),
        "p50 µs": f"{np.percentile(late_us, 50):.1f}",
        "p99 µs": f"{np.percentile(late_us, 99):.1f}",
        "p99.9 µs": f"{np.percentile(late_us, 99.9):.1f}",
        "max µs": f"{late_us.max():.0f}",
        "> 200 µs": str(int(np.sum(late_us > 200))),
        "first sample µs": f"{late_us[0]:.1f}",
        "bursts": str(bursts),
    }


def sync_row(run: LiveRun) -> dict[str, str]:
    e = run.sync_err_ns.astype(np.float64) * 1e-3
    if not len(e):
        return {"synced samples": "0"}
    return {
        "synced samples": str(len(e)),
        "RMS µs": f"{np.sqrt(np.mean(e**2)):.2f}",
        "mean µs": f"{e.mean():.2f}",
        "p99 |e| µs": f"{np.percentile(np.abs(e), 99):.2f}",
        "max |e| µs": f"{np.abs(e).max():.1f}",
    }


def md_table(rows: list[dict[str, str]]) -> str:
    head = list(rows[0])
    out = ["| " + " | ".join(head) + " |", "| " + " | ".join(["---"] + ["---:"] * (len(head) - 1)) + " |"]
    out += ["| " + " | ".join(r.get(h, "") for h in head) + " |" for r in rows]
    return "\n".join(out)


def describe(run: LiveRun, label: str) -> dict[str, str]:
    c = run.counters
    return {
        "run": label,
        "load (1 min)": f"{run.load_before:.2f}",
        **timing_rows(run),
        "late counted": str(c.get("tx_late_samples", "")),
        "sync re-stamped": str(c.get("tx_sync_restamped", "")),
        "spin ‰": str(c.get("pacing.spin_permille", "")),
        "IMU CPU %": f"{100 * run.cpu_share:.1f}",
    }


def main(argv: list[str]) -> int:
    ap = argparse.ArgumentParser(prog="hil bench pacing")
    ap.add_argument("--duration", type=float, default=30.0, help="seconds of each live run")
    ap.add_argument("--rates", default="100,400", help="IMU rates (Hz), one live run each")
    ap.add_argument("--scenario", default="straight_level")
    ap.add_argument(
        "--rt-priorities", default="0", help="SCHED_FIFO priorities of the sender, one run each (0: none)"
    )
    ap.add_argument(
        "--slices",
        default="100",
        help="the sender's scheduler time slices at normal priority (µs; 0: the kernel's), one run each",
    )
    ap.add_argument("--cpu-affinity", default="", help="CPUs of the sender (hil up --cpu-affinity)")
    ap.add_argument("--rig-cpus", default="", help="CPUs of the rest of the rig (hil up --rig-cpus)")
    ap.add_argument("--repeat", type=int, default=1, help="rounds of every run (alternating)")
    ap.add_argument("--section", default="pacing", help="the docs/benchmarks.md section to write")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    a = ap.parse_args(argv)
    rows, syncs, ready_lines = [], [], []
    try:
        slices = [int(x) for x in a.slices.split(",") if x]
        sender_cpus, rig_cpus = parse_cpus(a.cpu_affinity), parse_cpus(a.rig_cpus)
        runs = [
            (int(r), int(p), sl)
            for _round in range(max(1, a.repeat))
            for p in a.rt_priorities.split(",")
            if p
            for r in a.rates.split(",")
            if r
            for sl in (slices if not int(p) else [0])  # a real-time sender has no slice
        ]
    except ValueError as err:
        print(f"hil bench pacing: --rates, --rt-priorities, --slices and the CPU lists take integers: {err}")
        return 2
    for rate, prio, sl in runs:
        run = run_live(a.duration, a.scenario, rate, prio, sender_cpus, sched_slice_us=sl, rig_cpus=rig_cpus)
        if run.rc != 0:
            print("\n".join(run.failures))
            return run.rc
        label = f"{rate} Hz, " + (
            f"SCHED_FIFO {prio}" if prio else f"normal priority, slice {sl} µs" if sl else "normal priority"
        )
        rows.append(describe(run, label))
        syncs.append({"run": label, **sync_row(run)})
        ready = ", ".join(f"{n} {s:.2f}" for n, s in sorted(run.ready_s.items(), key=lambda kv: -kv[1]))
        ready_lines.append(f"- {label}: {ready}")
    body = "\n".join(
        [
            f"`hil up` (scenario `{a.scenario}`, every service its own process, classic CAN on this "
            f"machine's transport) for {a.duration:g} s per rate. Lateness = when the IMU emulator's "
            "pacing process handed a sample's first frame to the bus, minus its ideal instant (the "
            "sample's tick -- on a sync edge the end of the sync frame, which goes first -- + the "
            "frame's bit time at 1 Mbit/s + the controller latency), "
            "`CLOCK_MONOTONIC` on the host. 'bursts' = samples handed over less than half a period "
            "after the previous one. Load = the 1-minute load average just before the run (the "
            "rig's own processes and whatever else ran on the machine). 'slice' = the pacing "
            "process's scheduler time slice at normal priority (`--sched-slice-us`, "
            "`hil.runners.pacing.short_slice`; without it, the kernel's default)."
            + (f" The sender on CPU(s) {a.cpu_affinity}." if sender_cpus else "")
            + (f" The rest of the rig, the hub included, on CPU(s) {a.rig_cpus}." if rig_cpus else ""),
            "",
            md_table(rows),
            "",
            f"Live sync (issue 22): synced IMU stamp (`synced/imu`) − the emulator's true capture time "
            f"(`capture/imu`, matched by seq), from {SYNC_SETTLE_S:g} s on; the modelled streams are in "
            "the `timesync` section (`hil bench timesync`, whose `--live` adds this row there):",
            "",
            md_table(syncs),
            "",
            "Seconds from each service's process start to its first ready status:",
            "",
            *ready_lines,
        ]
    )
    print(body)
    if not a.no_write:
        write_section(a.section, body, command_line())
    return 0

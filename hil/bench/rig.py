"""``hil bench rig``: the live rig for real -- CPU per service and end-to-end latency.

Runs ``hil up`` (every service its own process, real Zenoh, the CAN transport of this machine)
for ``--duration`` seconds, then reads the recording: latency from an IMU sample's true capture
to each hop's arrival at the recorder (raw sample, synchronised sample, fused output), median and
p99, and the CPU share of every service over the run.
"""

from __future__ import annotations

import argparse
import os
import re
import subprocess
import sys
import tempfile
from pathlib import Path
from typing import Any

import numpy as np

from hil.bench import command_line, tree_revision, write_section
from hil.bench.horizon import STARTUP_S  # the IMU is held until time sync locks (~3 s), then late
from hil.record.info import channel_infos
from hil.record.mcapio import read_session
from hil.runners.pacing import parse_cpus
from hil.runtime.argtypes import OneLineParser, bounded_float, duration_s
from hil.runtime.supervisor import Supervisor, UpOptions


def hop_latencies_ms(path: Path, rig: str, skip_s: float = 0.0) -> dict[str, np.ndarray]:
    """Recorder arrival (log time, rig clock) minus the sample's true capture time, per hop, of
    what was captured ``skip_s`` or more after the run's first capture."""
    s = read_session(path)
    capture = {r.sequence: r.publish_time_ns for r in s.by_topic(f"hil/{rig}/capture/imu")}
    t0 = min(capture.values(), default=0) + round(skip_s * 1e9)
    out: dict[str, np.ndarray] = {}
    for label, topic in (("raw IMU sample (sensor/imu)", "sensor/imu"), ("synced IMU sample", "synced/imu")):
        recs = s.by_topic(f"hil/{rig}/{topic}")
        lat = [r.log_time_ns - capture[r.sequence] for r in recs if capture.get(r.sequence, -1) >= t0]
        out[label] = np.array(lat, dtype=np.float64) * 1e-6
    for est in sorted({r.topic.rsplit("/", 1)[1] for r in s.by_topic_prefix(f"hil/{rig}/nav/")}):
        recs = s.by_topic(f"hil/{rig}/nav/{est}")
        # a solution's stamp is the time of validity of the IMU sample it was computed at
        lat = [r.log_time_ns - r.publish_time_ns for r in recs if r.publish_time_ns >= t0]
        out[f"fused output nav/{est}"] = np.array(lat, dtype=np.float64) * 1e-6
    return out


def _one_rig(a: argparse.Namespace, rig: str, batch_ms: float = 0.0) -> tuple[int, list[str]]:
    """``hil up`` of one rig for ``--duration`` s: its figures as markdown lines (rc, lines)."""
    rc, lines, _ = _measure_rig(a, rig, batch_ms)
    return rc, lines


def _measure_rig(
    a: argparse.Namespace, rig: str, batch_ms: float = 0.0
) -> tuple[int, list[str], dict[str, Any]]:
    """:func:`_one_rig`, and its figures as numbers (CPU per service, fused latency)."""
    load_before = os.getloadavg()[0]
    sleep_us, handoff_us = wakeup_cost_us()
    with tempfile.TemporaryDirectory() as d:
        rec = Path(d) / "bench.mcap"
        sup = Supervisor(
            UpOptions(
                scenario=a.scenario,
                duration_s=a.duration,
                record=rec,
                rig=rig,
                fd=a.fd,
                imu_rate_hz=a.imu_rate,
                input_batch_ms=batch_ms,
                can_batch_ms=a.can_batch_ms,
                cpu_affinity=a.cpu_list,
                rig_cpus=a.rig_cpu_list,
                live=False,
                log_dir=Path(d) / "logs",
            )
        )
        rc = sup.run()
        if rc != 0:
            return rc, sup.failures, {}
        infos = channel_infos(read_session(rec))
        lat = hop_latencies_ms(rec, rig, STARTUP_S)
        whole = hop_latencies_ms(rec, rig)
    n_proc = len(sup.children)
    gaps = sum(c.missing for c in infos)
    n_msgs = sum(c.count for c in infos)
    imu = next(c for c in infos if c.topic.endswith("/sensor/imu"))
    gnss = next(c for c in infos if c.topic.endswith("/sensor/gnss"))
    can = "CAN FD" if a.fd else "classic CAN"
    lines = [
        f"`hil up` for {a.duration:g} s, scenario `{a.scenario}`, {can}, rig `{rig}`: {n_proc} processes, "
        f"{n_msgs} messages recorded, "
        f"IMU {imu.count} samples ({imu.count / a.duration:.1f} Hz), GNSS {gnss.count} fixes, "
        f"sequence gaps: **{gaps}**.",
        "",
        "| service | CPU s | share of one core | wake-ups/s |",
        "| --- | ---: | ---: | ---: |",
    ]
    win = sup.cpu_window_s
    for name, u in sorted(sup.usage.items(), key=lambda kv: -kv[1].cpu_s):
        lines.append(f"| {name} | {u.cpu_s:.2f} | {100 * u.cpu_s / win:.1f} % | {u.wakeups / win:.0f} |")
    total = sum(u.cpu_s for u in sup.usage.values())
    woken = sum(u.wakeups for u in sup.usage.values())
    lines.append(f"| **all** | {total:.2f} | **{100 * total / win:.1f} %** | {woken / win:.0f} |")
    lines += [
        "",
        f"CPU per IMU sample over the rig: {1e3 * total / max(1, imu.count):.2f} ms; wake-ups per IMU "
        f"sample: {woken / max(1, imu.count):.1f}.",
        "",
        f"Wake-ups = the voluntary context switches of every thread of the service (Zenoh's "
        f"included): each time one blocked and was woken. What one costs on this machine, measured "
        f"just before the run: **{sleep_us:.1f} µs** of CPU for a thread's 0.5 ms sleep and its "
        f"wake-up, **{handoff_us:.1f} µs** more when one thread hands an item to another that "
        f"waits for it (`hil.bench.rig.wakeup_cost_us`); at the first figure the rig's wake-ups "
        f"alone come to ~{100 * woken / win * sleep_us * 1e-6:.1f} % of a core.",
    ]
    lines += [
        "",
        f"Latency from an IMU sample's true capture to its arrival at the recorder (ms), of what was "
        f"captured after the first {STARTUP_S:g} s; the whole run's tail beside it (start-up: the IMU is "
        "held until time sync locks, then arrives late by design):",
        "",
        "| hop | n | median | p99 | max | whole run: p99 | max |",
        "| --- | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for label, v in lat.items():
        w = whole[label]
        if len(v):
            lines.append(
                f"| {label} | {len(v)} | {np.median(v):.2f} | {np.percentile(v, 99):.2f} | {v.max():.2f} "
                f"| {np.percentile(w, 99):.2f} | {w.max():.2f} |"
            )
    lines += [
        "",
        "The estimators run on the fusion's delayed horizon (`lag_s`, default 0.5 s): inputs are consumed "
        "in the total order once every GNSS fix that could still be valid before them has had time to "
        "arrive, which is what makes the fusion deterministic and GNSS fused at its time of validity; the "
        "output predictor publishes at each IMU sample's arrival (docs/concepts.md, Fusion).",
        f"Load average (1 min) just before the run: {load_before:.2f} on {os.cpu_count()} cores; the tail "
        "(p99, max) is sensitive to other work on the machine.",
    ]
    fused = np.concatenate([v for k, v in lat.items() if k.startswith("fused")] or [np.zeros(0)])
    figures = {
        "cpu": {k: v / sup.cpu_window_s for k, v in sup.cpu_s.items()},
        "all": total / sup.cpu_window_s,
        "per_sample_ms": 1e3 * total / max(1, imu.count),
        "fused": fused,
        "gaps": gaps,
        "load": load_before,
    }
    return 0, lines, figures


def wakeup_cost_us(n: int = 1000, sleep_s: float = 0.0005) -> tuple[float, float]:
    """CPU per wake-up on this machine, in µs: (a thread sleeping ``sleep_s`` and woken by its
    timer, the extra of a hand-over to a second thread blocked on a queue). Bare metal takes a
    few µs; a VM whose timer and wake-up interrupts exit to the hypervisor takes tens, and a live
    rig wakes thousands of times a second (docs/benchmarks.md, session 40)."""
    import queue
    import threading
    import time

    t0 = time.process_time()
    for _ in range(n):
        time.sleep(sleep_s)
    sleep_us = (time.process_time() - t0) / n * 1e6
    q: queue.SimpleQueue[int] = queue.SimpleQueue()

    def take() -> None:
        for _ in range(n):
            q.get()

    t = threading.Thread(target=take, name="wakeup-cost", daemon=True)
    t0 = time.process_time()
    t.start()
    for i in range(n):
        q.put(i)
        time.sleep(sleep_s)  # the taker is blocked again before the next put
    t.join(timeout=60.0)
    both_us = (time.process_time() - t0) / n * 1e6
    return sleep_us, max(0.0, both_us - sleep_us)


def _batch_windows(a: argparse.Namespace, windows: list[float]) -> tuple[int, list[str]]:
    """The same rig once per input batching window, ``--repeat`` rounds alternating: CPU against
    fused-output latency, as ratios against the first window measured in the same run."""
    rows: dict[float, list[dict[str, Any]]] = {w: [] for w in windows}
    for _ in range(a.repeat):
        for w in windows:
            rc, lines, fig = _measure_rig(a, a.rig, w)
            if rc != 0:
                return rc, lines
            rows[w].append(fig)
    base = windows[0]

    def mean(w: float, f: Any) -> float:
        return float(np.mean([f(x) for x in rows[w]]))

    out = [
        f"`hil up` for {a.duration:g} s, scenario `{a.scenario}`, IMU {a.imu_rate or 'the scenario'} Hz, "
        f"once per window and {a.repeat} round(s) alternating (`--input-batch-ms`: time sync and the fusion "
        "take their inputs in batches this far apart). CPU as a share of one core (mean over rounds); "
        f"fused-output latency after the first {STARTUP_S:g} s over every estimator and round.",
        "",
        "| window ms | fusion | timesync | all | CPU per IMU sample ms | vs first | fused latency median ms "
        "| p99 ms | max ms | gaps |",
        "| ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: | ---: |",
    ]
    for w in windows:
        lat = np.concatenate([x["fused"] for x in rows[w]])
        out.append(
            f"| {w:g} | {100 * mean(w, lambda x: x['cpu'].get('fusion', 0.0)):.1f} % "
            f"| {100 * mean(w, lambda x: x['cpu'].get('timesync', 0.0)):.1f} % "
            f"| {100 * mean(w, lambda x: x['all']):.1f} % | {mean(w, lambda x: x['per_sample_ms']):.2f} "
            f"| {mean(w, lambda x: x['per_sample_ms']) / mean(base, lambda x: x['per_sample_ms']):.3f} "
            f"| {np.median(lat):.2f} | {np.percentile(lat, 99):.2f} | {lat.max():.2f} "
            f"| {sum(x['gaps'] for x in rows[w])} |"
        )
    loads = [x["load"] for r in rows.values() for x in r]
    out += [
        "",
        f"Load average (1 min) before each run: {min(loads):.2f}-{max(loads):.2f} on {os.cpu_count()} cores.",
    ]
    return 0, out


_RUN = "import sys; from hil.cli import main; sys.argv[0] = 'hil'; raise SystemExit(main())"
# (an older tree's table has no wake-ups column)
_CPU_ROW = re.compile(r"^\s+(\w+)\s+([0-9.]+) s\s+([0-9.]+) %(?:\s+[0-9]+ wake-ups/s)?$")
_CPU_HEAD = re.compile(r"^CPU over ([0-9.]+) s of wall time")


def _up_args(a: argparse.Namespace, rig: str, rec: Path, this_tree: bool = True) -> list[str]:
    args = ["up", "--quiet", "--duration", str(a.duration), "--scenario", a.scenario, "--rig", rig]
    args += ["--record", str(rec), *(["--imu-rate", str(a.imu_rate)] if a.imu_rate else [])]
    if this_tree and a.can_batch_ms != UpOptions.can_batch_ms:  # an older tree may not know it
        args += ["--can-batch-ms", str(a.can_batch_ms)]
    return [*args, "--fd"] if a.fd else args


def _cpu_of(out: str) -> tuple[float, dict[str, float]]:
    """``hil up``'s closing CPU table: (wall seconds, CPU seconds per row)."""
    window, cpu = 0.0, {}
    for line in out.splitlines():
        if m := _CPU_HEAD.match(line):
            window = float(m.group(1))
        elif (m := _CPU_ROW.match(line)) and m.group(1) != "all":
            cpu[m.group(1)] = float(m.group(2))
    return window, cpu


def _measure_rigs(
    a: argparse.Namespace, runs: list[tuple[str, str | None]]
) -> tuple[int, list[Any], list[str]]:
    """``hil up`` of each rig, each with its own hub (``tree``: that checkout's code runs it). The
    rigs of one checkout run at once; checkouts in turn, in the order of ``runs`` (two revisions
    at once would starve each other unevenly: the faster one gets more of the machine). Rows
    (rig, tree, wall s, CPU s per service, IMU samples, gaps), and notes; on failure the lines
    that say why."""
    with tempfile.TemporaryDirectory() as d:
        procs: list[subprocess.Popen[str]] = []
        outs: list[str] = []
        order = [r for group in dict.fromkeys(tree for _, tree in runs) for r in runs if r[1] == group]
        for group in dict.fromkeys(tree for _, tree in order):
            started = []
            for rig, tree in order:
                if tree != group:
                    continue
                env = {k: v for k, v in os.environ.items() if not k.startswith("HIL_")}
                env["PYTHONPATH"] = tree or os.getcwd()
                cmd = [sys.executable, "-c", _RUN, *_up_args(a, rig, Path(d) / f"{rig}.mcap", tree is None)]
                started.append(
                    subprocess.Popen(
                        cmd, cwd=tree, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True, env=env
                    )
                )
            procs += started
            outs += [p.communicate()[0] for p in started]
        rows = []
        where: list[str] = []
        for (rig, tree), p, out in zip(order, procs, outs, strict=True):
            if not (Path(d) / f"{rig}.mcap").is_file():
                return p.returncode or 1, [], [f"rig {rig}: hil up failed:", *out.splitlines()[-20:]]
            if p.returncode != 0:  # e.g. a service fell behind and lost samples: still a row
                where.append(f"rig {rig}: hil up exited {p.returncode}")
            infos = channel_infos(read_session(Path(d) / f"{rig}.mcap"))
            window, cpu = _cpu_of(out)
            imu = next(c for c in infos if c.topic.endswith("/sensor/imu"))
            rows.append((rig, tree, window, cpu, imu.count, sum(c.missing for c in infos)))
            lossy = [f"{c.topic.split('/', 2)[-1]} {c.missing}" for c in infos if c.missing]
            if lossy:
                where.append(f"rig {rig}: sequence gaps in " + ", ".join(lossy))
    rank = {r: i for i, r in enumerate(runs)}
    rows.sort(key=lambda r: rank[(r[0], r[1])])
    return 0, rows, where


def _rigs_at_once(a: argparse.Namespace, runs: list[tuple[str, str | None]]) -> tuple[int, list[str]]:
    """The rigs of ``runs`` (see ``_measure_rigs``), ``--repeat`` rounds with the checkouts'
    order alternating (round 2 runs the reference first: a drift in the machine's load then
    weighs on both alike); one table row per rig and round, and with ``--versus`` the CPU per
    IMU sample of this tree over the reference's, per round and over all."""
    load_before = os.getloadavg()[0]
    rows: list[Any] = []
    where: list[str] = []
    for i in range(a.repeat):
        ordered = runs if i % 2 == 0 else sorted(runs, key=lambda r: r[1] is None)
        rc, got, notes = _measure_rigs(a, ordered)
        if rc != 0:
            return rc, notes
        rows += [(*r, i + 1) for r in got]
        where += [f"round {i + 1}: {n}" if a.repeat > 1 else n for n in notes]
    names = sorted({n for r in rows for n in r[3]}, key=lambda n: -max(r[3].get(n, 0.0) for r in rows))
    can = "CAN FD" if a.fd else "classic CAN"
    rounds = f", {a.repeat} rounds with the checkouts' order alternating" if a.repeat > 1 else ""
    lines = [
        f"{len(runs)} rigs (one checkout's at once, checkouts in turn{rounds}), each `hil up` with its "
        f"own hub, {a.duration:g} s of "
        f"`{a.scenario}`, {can}; share of one core per service (`hil up`'s CPU table), IMU samples "
        "recorded and sequence gaps over every recorded topic:",
        "",
        "| rig | code | round | IMU Hz | gaps | "
        + " | ".join(names)
        + " | **all** | ms CPU per IMU sample |",
        "| --- | --- | ---: | ---: | ---: | " + " | ".join("---:" for _ in names) + " | ---: | ---: |",
    ]
    per_sample: dict[tuple[bool, int], list[float]] = {}
    for rig, tree, window, cpu, n_imu, gaps, rnd in rows:
        share = [f"{100 * cpu.get(n, 0.0) / window:.1f} %" if n in cpu else "-" for n in names]
        code = tree_revision(tree) if tree else tree_revision(os.getcwd())
        ms = 1e3 * sum(cpu.values()) / max(1, n_imu)
        per_sample.setdefault((tree is None, rnd), []).append(ms)
        lines.append(
            f"| {rig} | {code} | {rnd} | {n_imu / a.duration:.1f} | {gaps} | "
            + " | ".join(share)
            + f" | **{100 * sum(cpu.values()) / window:.1f} %**"
            + f" | {ms:.2f} |"
        )
    lines += ["", *where] if where else []
    if a.versus:
        ratios = [
            float(np.mean(per_sample[(True, r)])) / float(np.mean(per_sample[(False, r)]))
            for r in range(1, a.repeat + 1)
        ]
        mine = float(np.mean([v for (t, _), vs in per_sample.items() if t for v in vs]))
        ref = float(np.mean([v for (t, _), vs in per_sample.items() if not t for v in vs]))
        lines += [
            "",
            f"CPU per IMU sample, this tree over {tree_revision(a.versus)}: **{mine / ref:.3f}** "
            f"({mine:.2f} vs {ref:.2f} ms over {a.repeat} round(s); per round "
            + ", ".join(f"{x:.3f}" for x in ratios)
            + ").",
        ]
    lines += [
        "",
        f"Load average (1 min) just before the run: {load_before:.2f} on {os.cpu_count()} cores (the rigs "
        "themselves and whatever else ran); an older revision's table may lack the supervisor row. "
        "A rig starved of CPU sends fewer samples than its rate: CPU per IMU sample (every process of "
        "the rig over the samples recorded) is the figure to compare.",
    ]
    return 0, lines


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench rig")
    ap.add_argument("--duration", type=duration_s, default=60.0)
    ap.add_argument("--scenario", default="straight_level")
    ap.add_argument("--imu-rate", type=int, default=None, help="IMU rate in Hz (default: the scenario's)")
    ap.add_argument("--fd", action="store_true", help="CAN FD: one frame per IMU sample")
    ap.add_argument("--rig", default="benchrig", help="the rig's name (keys hil/<rig>/...)")
    ap.add_argument("--rigs", type=int, default=1, help="this many rigs at once on this machine (a, b, ...)")
    ap.add_argument(
        "--versus",
        metavar="TREE",
        help="then the same rig(s) from this checkout (a `git worktree` of an older revision): "
        "before/after in one run",
    )
    ap.add_argument(
        "--input-batch-ms",
        default="0",
        help="time sync's and the fusion's input batching window, ms; several (0,10): the rig once "
        "per window, compared (section rig-batch unless --section)",
    )
    ap.add_argument(
        "--can-batch-ms",
        type=bounded_float(0.0, 100.0, unit="ms"),
        default=UpOptions.can_batch_ms,
        help="the CAN bridge's read window, ms (hil up --can-batch-ms; default its default)",
    )
    ap.add_argument(
        "--repeat",
        type=int,
        default=1,
        help="rounds of the windows, or of the rigs with --versus, alternating",
    )
    ap.add_argument("--cpu-affinity", default="", help="CPUs of the IMU's frame sender (as hil up's)")
    ap.add_argument("--rig-cpus", default="", help="CPUs of the rest of the rig (hil up --rig-cpus)")
    ap.add_argument("--section", default=None, help="the docs/benchmarks.md section to write")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    a = ap.parse_args(argv)
    if a.rigs < 1 or a.rigs > 8:
        ap.error(f"--rigs {a.rigs}: use 1 to 8")
    try:
        a.cpu_list, a.rig_cpu_list = parse_cpus(a.cpu_affinity), parse_cpus(a.rig_cpus)
    except ValueError:
        ap.error("--cpu-affinity and --rig-cpus take CPU numbers, e.g. 1 or 0,1")
    if (a.cpu_list or a.rig_cpu_list) and (a.rigs != 1 or a.versus):
        ap.error("--cpu-affinity and --rig-cpus place one rig of this tree: not with --rigs or --versus")
    try:
        windows = [float(x) for x in a.input_batch_ms.split(",") if x.strip()]
    except ValueError:
        ap.error(f"--input-batch-ms {a.input_batch_ms!r}: give numbers of ms, comma-separated")
    if not windows or any(not 0.0 <= w <= 100.0 for w in windows):
        ap.error(f"--input-batch-ms {a.input_batch_ms!r}: each window in [0, 100] ms")
    if not 1 <= a.repeat <= 20:
        ap.error(f"--repeat {a.repeat}: use 1 to 20")
    if len(windows) > 1 or windows[0]:
        if a.rigs != 1 or a.versus:
            ap.error("--input-batch-ms measures one rig: not with --rigs or --versus")
        a.section = a.section or "rig-batch"
        rc, lines = _batch_windows(a, windows)
    elif a.rigs == 1 and not a.versus:
        rc, lines = _one_rig(a, a.rig, windows[0])
        if a.cpu_list or a.rig_cpu_list:
            lines = [
                f"The IMU's frame sender on CPU(s) {a.cpu_affinity or 'any'}, the rest of the rig "
                f"(the hub included) on CPU(s) {a.rig_cpus or 'any'} (`hil up --cpu-affinity --rig-cpus`).",
                "",
                *lines,
            ]
    else:
        runs: list[tuple[str, str | None]] = [(chr(97 + i), None) for i in range(a.rigs)]
        if a.versus:
            runs += [(f"ref{chr(97 + i)}", a.versus) for i in range(a.rigs)]
        rc, lines = _rigs_at_once(a, runs)
    body = "\n".join(lines)
    print(body)
    if rc != 0:
        return rc
    if not a.no_write:
        write_section(a.section or "rig", body, command_line())
    return 0


if __name__ == "__main__":
    raise SystemExit(main(sys.argv[1:]))

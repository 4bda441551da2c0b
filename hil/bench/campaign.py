"""``hil bench campaign``: what running on Dask costs and gains, on one small campaign.

The same runs (``--runs`` x ``--duration`` s of ``--scenario``, compvs and ekf15) four ways:

1. directly in this process, one after another: ``run_sim`` to a temporary MCAP (what ``hil
   sim`` does) and then the run's statistics -- the reference;
2. as a campaign on a local Dask cluster of 1 worker process, 2, and (if the machine has the
   cores) more: runs per minute and the scaling ratio against 1 worker. Cluster start-up and
   the workers' first imports are timed apart (paid once per campaign, not per run);
3. the overhead per task: (campaign wall on 1 worker - direct wall) / runs, and the ratio, and
   the same in the worker process's CPU (``cpu_s``), which other work on the machine hardly moves;
4. 2 workers again with one worker process SIGKILLed when the first run comes back: every run
   must still come back ok (the test suite asserts the same, tests/unit/test_campaign_dask.py).

1 and 2 are repeated ``--repeat`` times, interleaved, and each is reported by its best (fastest)
repeat and its median: on a machine shared with other work the wall clock swings with the load,
and the best repeat is the one least disturbed. Each campaign writes a fresh directory, so
nothing is skipped as already done. Writes the ``campaign`` section of docs/benchmarks.md with
the command and the load averages seen.
"""

from __future__ import annotations

import argparse
import logging
import os
import shutil
import signal
import statistics
import tempfile
import time
from pathlib import Path
from typing import Any

from hil.bench import command_line, write_section
from hil.campaign.driver import DriverOptions, run_campaign
from hil.campaign.execute import OK, sim_recording, sim_statistics
from hil.campaign.results import read_results
from hil.campaign.runs import RunSpec, derive_runs
from hil.campaign.spec import CampaignSpec, spec_from_dict
from hil.runtime.argtypes import OneLineParser, bounded_int, duration_s

ESTIMATORS = ["compvs", "ekf15"]


def _spec(scenario: str, runs: int, duration_s: float) -> CampaignSpec:
    doc = {
        "name": "bench",
        "seed": 2026,
        "runs": runs,
        "duration_s": duration_s,
        "configs": {"bench": {"estimators": ESTIMATORS}},
        "sim": {"scenarios": [scenario]},
    }
    return spec_from_dict(doc, Path.cwd())


def direct(runs: list[RunSpec]) -> dict[str, float]:
    """Seconds in run_sim, in run_sim + statistics (wall) and the CPU of both, in this process."""
    t_sim = t_all = 0.0
    c0 = time.process_time()
    with tempfile.TemporaryDirectory(prefix="hil-bench-campaign-") as tmp:
        for run in runs:
            t0 = time.perf_counter()
            # as a task does: only what the statistics read is recorded
            warnings = sim_recording(run, Path(tmp) / "run.mcap", Path(tmp), everything=False)
            t1 = time.perf_counter()
            rows = sim_statistics(run, Path(tmp) / "run.mcap", warnings)
            t2 = time.perf_counter()
            assert all(r["status"] == OK for r in rows), rows
            t_sim += t1 - t0
            t_all += t2 - t0
    return {"sim_s": t_sim, "all_s": t_all, "cpu_s": time.process_time() - c0, "startup_s": 0.0}


def _warm(client: Any) -> None:
    """Each worker imports the campaign code once (what its first task would pay)."""
    from hil.campaign.execute import code_fingerprint

    client.run(code_fingerprint)


def _idle_cpu_fraction(client: Any, wait_s: float = 10.0) -> float:
    """CPU a worker process spends with no task (heartbeats, monitors), per second of wall."""
    a: dict[str, float] = client.run(time.process_time)
    time.sleep(wait_s)
    b: dict[str, float] = client.run(time.process_time)
    return sum(b[k] - a[k] for k in a) / len(a) / wait_s


def on_cluster(
    spec: CampaignSpec, workers: int, kill: bool = False, idle_probe: bool = False
) -> dict[str, Any]:
    """One fresh campaign on a new local cluster of ``workers`` processes; its timings."""
    from dask.distributed import Client, LocalCluster

    t0 = time.perf_counter()
    cluster = LocalCluster(
        n_workers=workers,
        threads_per_worker=1,
        processes=True,
        dashboard_address=":0",
        silence_logs=logging.ERROR,
    )
    client = Client(cluster, set_as_default=False)
    out = Path(tempfile.mkdtemp(prefix="hil-bench-campaign-"))
    killed: list[int] = []

    def kill_one(_run: RunSpec, _rows: list[dict[str, Any]]) -> None:
        busy = sorted(w for w, keys in client.processing().items() if keys)
        if kill and not killed and busy:
            pid = client.run(os.getpid, workers=[busy[0]])[busy[0]]
            os.kill(pid, signal.SIGKILL)
            killed.append(pid)

    try:
        _warm(client)
        idle = _idle_cpu_fraction(client) if idle_probe and workers == 1 else None
        t1 = time.perf_counter()
        opts = DriverOptions(
            out_dir=out, scheduler=cluster.scheduler_address, progress=False, on_rows=kill_one
        )
        res = run_campaign(spec, opts)
        t2 = time.perf_counter()
        rows = read_results(out).table()
    finally:
        client.close()
        cluster.close()
        shutil.rmtree(out, ignore_errors=True)
    return {
        "workers": workers,
        "startup_s": t1 - t0,
        "wall_s": t2 - t1,
        "ok": res.counts.get(OK, 0),
        "lost": sum(v for k, v in res.counts.items() if k != OK),
        "killed": len(killed),
        "idle_cpu": idle,
        "cpu_s": sum(r.get("cpu_s") or 0.0 for r in rows) / len(ESTIMATORS),  # one row per estimator
    }


def _best(ms: list[dict[str, Any]]) -> dict[str, Any]:
    """The fastest repeat, with the median wall and CPU over the repeats beside it."""
    b = dict(min(ms, key=lambda m: m["wall_s"]))
    b["median_wall_s"] = statistics.median(m["wall_s"] for m in ms)
    b["median_cpu_s"] = statistics.median(m["cpu_s"] for m in ms)
    return b


def _markdown(a: argparse.Namespace, d: dict[str, Any], rows: list[dict[str, Any]], loads: list[str]) -> str:
    n = a.runs
    one = next(r for r in rows if r["workers"] == 1 and not r["killed"])
    rate1 = 60 * n / one["wall_s"]
    lines = [
        f"The same {n} runs of `{a.scenario}`, {a.duration:g} s each, estimators {', '.join(ESTIMATORS)} "
        "(each run: hil sim to a temporary MCAP, its statistics, the file deleted); best of "
        f"{a.repeat} interleaved repeats (median beside it).",
        "",
        "| how | wall s: best (median) | runs/min | vs 1 worker | CPU s per run | start-up s | runs ok |",
        "| --- | --- | --- | --- | --- | --- | --- |",
        "| directly: run_sim only (what the statistics read recorded, as a task) "
        f"| {d['sim_s']:.1f} ({d['median_sim_s']:.1f}) "
        f"| {60 * n / d['sim_s']:.1f} | – | – | – | {n}/{n} |",
        f"| directly: run_sim + statistics | {d['wall_s']:.1f} ({d['median_wall_s']:.1f}) "
        f"| {60 * n / d['wall_s']:.1f} | – | {d['median_cpu_s'] / n:.2f} | – | {n}/{n} |",
    ]
    for r in rows:
        rate = 60 * n / r["wall_s"]
        what = f"campaign, {r['workers']} worker(s)" + (", one SIGKILLed mid-campaign" if r["killed"] else "")
        med = f" ({r['median_wall_s']:.1f})" if "median_wall_s" in r else ""
        cpu = r.get("median_cpu_s", r["cpu_s"])
        lines.append(
            f"| {what} | {r['wall_s']:.1f}{med} | {rate:.1f} | {rate / rate1:.2f}x | {cpu / n:.2f} "
            f"| {r['startup_s']:.1f} | {r['ok']}/{n} ({r['lost']} without a result) |"
        )
    lines += [
        "",
        *_overhead_lines(d, one, n),
        "",
        _conditions(loads, any(r["killed"] for r in rows), max(r["workers"] for r in rows)),
    ]
    return "\n".join(lines)


def _overhead_lines(d: dict[str, Any], one: dict[str, Any], n: int) -> list[str]:
    idle = one.get("idle_cpu") or 0.0
    d_cpu = one["median_cpu_s"] / n - d["median_cpu_s"] / n
    return [
        "Overhead per task, campaign on 1 worker against the same runs directly (statistics included), "
        f"best repeats: {(one['wall_s'] - d['wall_s']) / n:+.2f} s of wall per run (ratio "
        f"{one['wall_s'] / d['wall_s']:.2f}; against plain run_sim, i.e. hil sim: "
        f"{one['wall_s'] / d['sim_s']:.2f}); medians: {d_cpu:+.2f} s "
        "of the worker's CPU per run. CPU s per run is the worker process's CPU time over its runs (the "
        "`cpu_s` column): what a run costs whatever else the machine does. An idle worker process "
        f"spends {100 * idle:.1f} % of a core on its own (heartbeats, memory and system monitors), "
        f"{idle * one['wall_s'] / n:.2f} s over the {one['wall_s'] / n:.1f} s of wall a run took here. "
        "Start-up (a new local cluster and every worker's first import of the rig) is paid once per "
        "campaign.",
    ]


def _conditions(loads: list[str], killed: bool, workers: int) -> str:
    cores = os.cpu_count() or 1
    text = (
        f"Load average (1 min) at the start and after each repeat: {', '.join(loads)}, on {cores} cores; "
        f"the campaign's own processes count in it (up to {workers} workers busy). Wall-clock figures and "
        "the scaling are bounded by the cores the machine leaves free, not by Dask; on an idle machine "
        "with more cores the ratio approaches the worker count (runs are independent, a run's result is "
        "a few kB)."
    )
    if max(float(x) for x in loads[1:] or loads) >= cores + 1:
        text += (
            " Here the load average stayed above the core count plus one through the repeats: other work "
            "held cores, a second worker shared CPU with the first and with it, and the scaling ratio "
            "above measures that load, not Dask. Rerun on an idle machine to measure the scaling."
        )
    if killed:
        text += (
            " The killed-worker row (one repeat): the scheduler reran the dead worker's run elsewhere; no "
            "run was lost, the cost is that run's time again and a worker restart."
        )
    return text


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench campaign", description=__doc__.splitlines()[0])
    ap.add_argument("--scenario", default="uav_survey")
    ap.add_argument("--runs", type=bounded_int(1, 100_000), default=8)
    ap.add_argument("--duration", type=duration_s, default=10.0, help="rig seconds per run")
    ap.add_argument(
        "--repeat", type=bounded_int(1, 100), default=3, help="interleaved repeats; the best is reported"
    )
    ap.add_argument("--max-workers", type=bounded_int(1, 1024), default=os.cpu_count() or 1)
    ap.add_argument("--no-write", action="store_true", help="print only, do not touch docs/benchmarks.md")
    a = ap.parse_args(argv)
    spec = _spec(a.scenario, a.runs, a.duration)
    runs = derive_runs(spec)
    loads = [f"{os.getloadavg()[0]:.1f}"]
    sizes = sorted({1, 2, *(w for w in (4, 8, 16) if w <= a.max_workers)} & set(range(1, a.max_workers + 1)))
    direct_ms: list[dict[str, Any]] = []
    by_size: dict[int, list[dict[str, Any]]] = {w: [] for w in sizes}
    for rep in range(a.repeat):
        direct_ms.append(direct(runs))
        for w in sizes:
            by_size[w].append(on_cluster(spec, w, idle_probe=rep == 0))
        loads.append(f"{os.getloadavg()[0]:.1f}")
        print(
            f"repeat {rep + 1}: direct {direct_ms[-1]}, " + str({w: m[-1] for w, m in by_size.items()}),
            flush=True,
        )
    d = _best([{**m, "wall_s": m["all_s"]} for m in direct_ms])
    d["sim_s"] = min(m["sim_s"] for m in direct_ms)
    d["median_sim_s"] = statistics.median(m["sim_s"] for m in direct_ms)
    rows = [_best(by_size[w]) for w in sizes]
    rows[0]["idle_cpu"] = next(m["idle_cpu"] for m in by_size[1] if m["idle_cpu"] is not None)
    if a.max_workers >= 2:
        rows.append(on_cluster(spec, 2, kill=True))
        loads.append(f"{os.getloadavg()[0]:.1f}")
    md = _markdown(a, d, rows, loads)
    print(md)
    if not a.no_write:
        write_section("campaign", md, command_line())
    return 0 if all(r["ok"] == a.runs for r in rows) else 1


if __name__ == "__main__":
    import sys

    raise SystemExit(main(sys.argv[1:]))

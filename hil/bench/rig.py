"""``hil bench rig``: the live rig for real -- CPU per service and end-to-end latency.

Runs ``hil up`` (every service its own process, real Zenoh, the CAN transport of this machine)
for ``--duration`` seconds, then reads the recording: latency from an IMU sample's true capture
to each hop's arrival at the recorder (raw sample, synchronised sample, fused output), median and
p99, and the CPU share of every service over the run.
"""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np

from hil.bench import command_line, write_section
from hil.record.info import channel_infos
from hil.record.mcapio import read_session
from hil.runtime.argtypes import OneLineParser, duration_s
from hil.runtime.supervisor import Supervisor, UpOptions


def hop_latencies_ms(path: Path, rig: str) -> dict[str, np.ndarray]:
    """Recorder arrival (log time, rig clock) minus the sample's true capture time, per hop."""
    s = read_session(path)
    capture = {r.sequence: r.publish_time_ns for r in s.by_topic(f"hil/{rig}/capture/imu")}
    out: dict[str, np.ndarray] = {}
    for label, topic in (("raw IMU sample (sensor/imu)", "sensor/imu"), ("synced IMU sample", "synced/imu")):
        recs = s.by_topic(f"hil/{rig}/{topic}")
        lat = [r.log_time_ns - capture[r.sequence] for r in recs if r.sequence in capture]
        out[label] = np.array(lat, dtype=np.float64) * 1e-6
    for est in sorted({r.topic.rsplit("/", 1)[1] for r in s.by_topic_prefix(f"hil/{rig}/nav/")}):
        recs = s.by_topic(f"hil/{rig}/nav/{est}")
        # a solution's stamp is the time of validity of the IMU sample it was computed at
        lat = [r.log_time_ns - r.publish_time_ns for r in recs]
        out[f"fused output nav/{est}"] = np.array(lat, dtype=np.float64) * 1e-6
    return out


def main(argv: list[str]) -> int:
    ap = OneLineParser(prog="hil bench rig")
    ap.add_argument("--duration", type=duration_s, default=60.0)
    ap.add_argument("--scenario", default="straight_level")
    ap.add_argument("--no-write", action="store_true", help="print only; leave docs/benchmarks.md alone")
    a = ap.parse_args(argv)
    rig = "benchrig"
    load_before = os.getloadavg()[0]
    with tempfile.TemporaryDirectory() as d:
        rec = Path(d) / "bench.mcap"
        sup = Supervisor(
            UpOptions(
                scenario=a.scenario,
                duration_s=a.duration,
                record=rec,
                rig=rig,
                live=False,
                log_dir=Path(d) / "logs",
            )
        )
        rc = sup.run()
        if rc != 0:
            print("\n".join(sup.failures))
            return rc
        infos = channel_infos(read_session(rec))
        lat = hop_latencies_ms(rec, rig)
    n_proc = len(sup.children)
    gaps = sum(c.missing for c in infos)
    n_msgs = sum(c.count for c in infos)
    imu = next(c for c in infos if c.topic.endswith("/sensor/imu"))
    gnss = next(c for c in infos if c.topic.endswith("/sensor/gnss"))
    lines = [
        f"`hil up` for {a.duration:g} s, scenario `{a.scenario}`: {n_proc} processes, "
        f"{n_msgs} messages recorded, "
        f"IMU {imu.count} samples ({imu.count / a.duration:.1f} Hz), GNSS {gnss.count} fixes, "
        f"sequence gaps: **{gaps}**.",
        "",
        "| service | CPU s | share of one core |",
        "| --- | ---: | ---: |",
    ]
    for name, cpu in sorted(sup.cpu_s.items(), key=lambda kv: -kv[1]):
        lines.append(f"| {name} | {cpu:.2f} | {100 * cpu / sup.cpu_window_s:.1f} % |")
    lines += [
        "",
        "Latency from an IMU sample's true capture to its arrival at the recorder (ms):",
        "",
        "| hop | n | median | p99 | max |",
        "| --- | ---: | ---: | ---: | ---: |",
    ]
    for label, v in lat.items():
        if len(v):
            lines.append(
                f"| {label} | {len(v)} | {np.median(v):.2f} | {np.percentile(v, 99):.2f} | {v.max():.2f} |"
            )
    lines += [
        "",
        "The fused outputs lag by the fusion's watermark (`lag_s`, default 0.2 s): inputs are consumed in "
        "the total order once every GNSS fix that could still be valid before them has had time to arrive, "
        "which is what makes the fusion deterministic and GNSS fused at its time of validity.",
    ]
    lines.append(
        f"Load average (1 min) just before the run: {load_before:.2f} on {os.cpu_count()} cores; the tail "
        "(p99, max) is sensitive to other work on the machine. The first second holds the start-up transient."
    )
    body = "\n".join(lines)
    print(body)
    if not a.no_write:
        write_section("rig", body, command_line())
    return 0

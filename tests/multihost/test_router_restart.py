"""The rig across three hosts (network namespaces) through one router, which is killed and restarted
mid-run: services reconnect, the recorder resumes, and the outage shows as reported seq gaps."""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest

from hil.record.mcapio import rig_time_ns
from tests.docker._recording import audit
from tests.multihost._netns import Hosts, require_netns, three_hosts

pytestmark = [pytest.mark.docker, pytest.mark.slow, pytest.mark.timeout(400)]

REPO = Path(__file__).resolve().parents[2]
RIG = "mh"
EMULATOR_HOST = ("can_bridge", "imu_emulator", "gnss_emulator", "world")
FUSION_HOST = ("recorder", "timesync", "fusion")
STOP_ORDER = (
    ("world", "imu_emulator", "gnss_emulator"),
    ("can_bridge",),
    ("timesync",),
    ("fusion",),
    ("recorder",),
)

MONITOR = """
import json, sys, time, zenoh
from hil.bus.session import BusConfig, open_session
s = open_session(BusConfig.from_env())
out = open(sys.argv[1], "a", buffering=1)
def on(sample):
    out.write(json.dumps({"key": str(sample.key_expr), "t": time.time()}) + "\\n")
sub = s.declare_subscriber(sys.argv[2], on)
while True:
    time.sleep(1)
"""


class Rig:
    def __init__(self, hosts: Hosts, tmp: Path) -> None:
        self.hosts = hosts
        self.tmp = tmp
        self.procs: dict[str, subprocess.Popen[bytes]] = {}
        self.record = tmp / "multihost.mcap"

    def env(self, router_ip: str) -> dict[str, str]:
        env = dict(os.environ)
        env.update(
            HIL_ZENOH_MODE="client",
            HIL_ZENOH_CONNECT=f"tcp/{router_ip}:7447",
            HIL_ZENOH_CONFIG=str(REPO / "deploy/zenoh/client.json5"),
            PYTHONUNBUFFERED="1",
        )
        return env

    def spawn(self, name: str, ns: str, cmd: list[str], env: dict[str, str] | None = None) -> None:
        log = open(self.tmp / f"{name}.log", "ab")  # noqa: SIM115 - closed with the process
        self.procs[name] = subprocess.Popen(
            [*self.hosts.exec_prefix(ns), *cmd], stdout=log, stderr=subprocess.STDOUT, env=env, cwd=REPO
        )

    def start_router(self) -> None:
        cmd = [sys.executable, "-m", "hil.cli", "router", "--config", str(REPO / "deploy/zenoh/router.json5")]
        cmd += ["--listen", "tcp/0.0.0.0:7447"]  # the config listens on loopback unless told otherwise
        self.spawn("router", self.hosts.router, cmd)

    def start_service(self, name: str, options: dict[str, object]) -> None:
        host, ip = (
            (self.hosts.emulators, self.hosts.router_ip_for_emulators)
            if name in EMULATOR_HOST
            else (self.hosts.fusion, self.hosts.router_ip_for_fusion)
        )
        cmd = [
            sys.executable,
            "-m",
            "hil.cli",
            "service",
            name,
            "--rig",
            RIG,
            "--options",
            json.dumps(options),
        ]
        self.spawn(name, host, cmd, self.env(ip))

    def stop(self, name: str, timeout: float = 30.0) -> int | None:
        p = self.procs.get(name)
        if p is None or p.poll() is not None:
            return None if p is None else p.returncode
        p.send_signal(signal.SIGTERM)
        try:
            return p.wait(timeout)
        except subprocess.TimeoutExpired:
            p.kill()
            return p.wait(10)

    def kill_all(self) -> None:
        for p in self.procs.values():
            if p.poll() is None:
                p.kill()
                p.wait(10)

    def log_tail(self) -> str:
        return "\n".join(
            f"--- {p.name}\n" + p.read_text(errors="replace")[-1500:] for p in sorted(self.tmp.glob("*.log"))
        )


def _wait_lines(path: Path, key_part: str, timeout_s: float, after: float = 0.0) -> float | None:
    deadline = time.monotonic() + timeout_s
    while time.monotonic() < deadline:
        if path.exists():
            for line in path.read_text().splitlines():
                try:
                    rec = json.loads(line)
                except ValueError:
                    continue
                if key_part in rec["key"] and rec["t"] > after:
                    return float(rec["t"])
        time.sleep(0.5)
    return None


def test_rig_across_hosts_survives_a_router_restart(tmp_path: Path) -> None:
    require_netns()
    with three_hosts() as hosts:
        rig = Rig(hosts, tmp_path)
        try:
            rig.start_router()
            time.sleep(1.0)
            rig.start_service("recorder", {"path": str(rig.record)})
            rig.start_service("timesync", {})
            rig.start_service("fusion", {})
            rig.start_service("can_bridge", {"channel": "vcan0", "interface": "hilzenoh"})
            rig.start_service("imu_emulator", {"channel": "vcan0", "interface": "hilzenoh"})
            rig.start_service("gnss_emulator", {})
            others = [n for n in (*FUSION_HOST, *EMULATOR_HOST) if n != "world"]
            rig.start_service("world", {"scenario": "straight_level", "duration_s": 120, "wait_for": others})
            # a monitor on the fusion host sees what crosses the router
            seen = tmp_path / "monitor.jsonl"
            mon_cmd = [sys.executable, "-c", MONITOR, str(seen), f"hil/{RIG}/**"]
            rig.spawn("monitor", hosts.fusion, mon_cmd, rig.env(hosts.router_ip_for_fusion))
            t_run = _wait_lines(seen, f"hil/{RIG}/run", timeout_s=90)
            assert t_run is not None, "world never announced the run across hosts\n" + rig.log_tail()
            assert _wait_lines(seen, f"hil/{RIG}/nav/", timeout_s=30), "no fusion output\n" + rig.log_tail()
            time.sleep(8.0)

            rig.procs["router"].kill()  # the router host dies
            rig.procs["router"].wait(10)
            t_kill = time.time()
            time.sleep(4.0)
            rig.start_router()
            t_restart = time.time()
            t_back = _wait_lines(seen, f"hil/{RIG}/truth", timeout_s=60, after=t_restart)
            assert t_back is not None, (
                "truth never crossed the router again after its restart\n" + rig.log_tail()
            )
            reconnect_s = t_back - t_restart
            assert _wait_lines(seen, f"hil/{RIG}/nav/", timeout_s=30, after=t_restart), rig.log_tail()
            time.sleep(10.0)
            for name, p in rig.procs.items():
                assert p.poll() is None, f"{name} died (exit {p.returncode})\n{rig.log_tail()}"
            rig.stop("monitor", 5)
            for stage in STOP_ORDER:
                codes = {n: rig.stop(n, 60 if n == "recorder" else 20) for n in stage}
                assert all(c == 0 for c in codes.values()), f"exit codes {codes}\n{rig.log_tail()}"
            rig.stop("router", 10)
        finally:
            rig.kill_all()

    a = audit(rig.record, validate_max=200)
    assert a.has_summary, "recorder did not finalise"
    info = subprocess.run(
        [sys.executable, "-m", "hil.cli", "info", str(rig.record), "--no-accuracy"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    print(f"router down {t_restart - t_kill:.1f} s, traffic back {reconnect_s:.1f} s after restart")
    print(info.stdout)
    # recorder resumed: it holds emulator-host and fusion-host messages after the restart
    from mcap.reader import make_reader

    after: dict[str, int] = {}
    with open(rig.record, "rb") as fh:
        reader = make_reader(fh)
        meta = {m.name: m.metadata for m in reader.iter_metadata()}
        # log_time is start epoch + rig time (hil.record.mcapio): back to the rig clock
        start_epoch_ns = int(json.loads(meta["hil"]["start_epoch_ns"]))
        restart_rig_ns = int((t_restart + 1.0) * 1e9) - start_epoch_ns
        for _s, ch, msg in reader.iter_messages(log_time_order=False):
            if rig_time_ns(msg.log_time, start_epoch_ns) > restart_rig_ns:
                kind = ch.topic.split("/")[2]
                after[kind] = after.get(kind, 0) + 1
    for kind in ("truth", "sensor", "can", "nav", "status"):
        assert after.get(kind, 0) > 0, f"nothing recorded on {kind} after the router restart: {after}"
    # what a publisher's cache (256 messages) still held is recovered after the restart, what
    # it no longer held is reported, not hidden. Truth goes out ten rows a message, so its cache
    # spans ~25 s and an outage shorter than that (4 s down, then the reconnect) leaves no hole
    # in it; the raw IMU samples go out ~4 a message at 400 Hz, a cache of ~2.6 s: the rest of
    # the outage is a seq gap of at least a second of samples
    outage_s = t_back - t_kill
    truth_gaps = a.gaps.get(f"hil/{RIG}/truth", [])
    truth_lost = sum(n - p - 1 for p, n in truth_gaps)
    assert truth_lost <= 100 * max(0.0, outage_s - 20.0), f"truth not recovered: {truth_gaps[:5]}"
    imu_gaps = a.gaps.get(f"hil/{RIG}/sensor/imu", [])
    biggest = max((n - p - 1 for p, n in imu_gaps), default=0)
    assert biggest >= 400 * 1.0, f"no IMU gap for the outage: {imu_gaps[:5]}"
    completeness = a.metadata.get("completeness", {})
    assert int(completeness.get("missing", "0")) >= biggest, completeness.get("missing")
    assert "gaps" in info.stdout and info.returncode == 0

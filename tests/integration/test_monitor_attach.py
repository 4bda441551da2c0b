"""``hil monitor`` attaches to a running rig from another process and draws ``hil up``'s table.

GIVEN a rig stand-in on a real Zenoh hub publishing run, status, truth and solutions
WHEN ``hil monitor --rig R --once`` runs as its own process, connected only through the env
THEN it prints every service's row, the rig's identity and each estimator's current error; and
a rig that is not there gives exit 1 and one line saying so.
"""

from __future__ import annotations

import os
import subprocess
import sys
import threading
import time
from pathlib import Path

from hil.bus.keys import Keys
from hil.bus.pubsub import Publisher, Stats
from hil.bus.session import BusConfig, open_session
from hil.messages import NavSolution, RunInfo, ServiceStatus, Truth, counts, rates
from hil.runtime.supervisor import LiveView, SolutionSampler
from tests.conftest import REPO, free_port, hil_cmd

RIG = "monrig"


def _fake_rig(endpoint: str, stop: threading.Event) -> None:
    s = open_session(BusConfig(mode="router", listen=(endpoint,), connect=()))
    k = Keys(RIG)
    run = Publisher(s, k.run(), RunInfo)
    status = {n: Publisher(s, k.status(n), ServiceStatus) for n in ("world", "fusion")}
    truth = Publisher(s, k.truth(), Truth)
    nav = Publisher(s, k.nav("ekf15"), NavSolution)
    t = 0
    try:
        while not stop.wait(0.05):
            t += 50_000_000
            run.put(
                RunInfo(
                    seq=run.next_seq(),
                    stamp_ns=t,
                    rig=RIG,
                    start_epoch_ns=0,
                    speed=1.0,
                    scenario="fake",
                    scenario_sha256="x",
                    seed=0,
                    duration_s=60,
                    origin_lat_deg=0,
                    origin_lon_deg=0,
                    origin_alt_m=0,
                )
            )
            for name, p in status.items():
                p.put(
                    ServiceStatus(
                        seq=p.next_seq(),
                        stamp_ns=t,
                        service=name,
                        state="running",
                        pid=1,
                        uptime_s=t * 1e-9,
                        rates_hz=rates({"in.x": 400.0, "out.y": 50.0}),
                        counters=counts({"rejected.late": 3}),
                        last_error="late input" if name == "fusion" else "",
                    )
                )
            truth.put(
                Truth(
                    seq=truth.next_seq(),
                    stamp_ns=t,
                    lat_deg=0,
                    lon_deg=0,
                    alt_m=0,
                    pos_ned_m=[0.0, 0.0, 0.0],
                    vel_ned_mps=[0.0, 0.0, 0.0],
                    q_nb=[1.0, 0.0, 0.0, 0.0],
                    f_b_mps2=[0.0, 0.0, 0.0],
                    w_ib_b_radps=[0.0, 0.0, 0.0],
                )
            )
            nav.put(
                NavSolution(
                    seq=nav.next_seq(),
                    stamp_ns=t,
                    estimator="ekf15",
                    pos_ned_m=[3.0, 4.0, 0.0],
                    vel_ned_mps=[0.0, 0.0, 0.0],
                    q_nb=[1.0, 0.0, 0.0, 0.0],
                    lat_deg=0,
                    lon_deg=0,
                    alt_m=0,
                )
            )
    finally:
        s.close()


def _env(endpoint: str, mode: str = "client") -> dict[str, str]:
    listen = "" if mode == "client" else "tcp/127.0.0.1:0"
    return dict(os.environ, HIL_ZENOH_MODE=mode, HIL_ZENOH_CONNECT=endpoint, HIL_ZENOH_LISTEN=listen)


def test_monitor_attaches_and_draws_the_table(tmp_path: Path) -> None:
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    stop = threading.Event()
    th = threading.Thread(target=_fake_rig, args=(endpoint, stop), daemon=True)
    th.start()
    try:
        r = subprocess.run(
            hil_cmd("monitor", "--rig", RIG, "--once", "--interval", "1.5", "--duration", "40"),
            cwd=REPO,
            env=_env(endpoint),
            capture_output=True,
            text=True,
            timeout=60,
        )
    finally:
        stop.set()
        th.join(timeout=10)
    assert r.returncode == 0, r.stderr
    out = r.stdout
    assert f"hil monitor {RIG}" in out and "scenario fake" in out
    rows = {ln.split()[0]: ln for ln in out.splitlines() if ln.startswith("  ") and ln.split()}
    assert "running" in rows["fusion"] and "late input" in rows["fusion"]
    assert rows["fusion"].split()[2:5] == ["400", "50", "3"]
    assert "(no status)" in rows["recorder"]  # a service that never reported
    assert "ekf15 5.0" in out  # |(3, 4)| m against truth


def test_monitor_without_a_rig_says_so() -> None:
    # a peer that finds nobody opens anyway and listens (a client would fail to open: exit 2)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    r = subprocess.run(
        hil_cmd("monitor", "--rig", "nobody", "--duration", "2"),
        cwd=REPO,
        env=_env(endpoint, mode="peer"),
        capture_output=True,
        text=True,
        timeout=60,
    )
    assert r.returncode == 1
    assert "no status from rig 'nobody'" in r.stdout


def test_liveview_marks_stale_and_dead_services() -> None:
    v = LiveView()
    st = ServiceStatus(seq=0, stamp_ns=0, service="fusion", state="running", pid=1, uptime_s=1.0)
    v.on_status(st, "")
    seen = v.status_seen["fusion"]
    remote = v.table(1.0, now=seen + 10.0)
    assert "stale 10s" in remote
    local = v.table(1.0, {"fusion": False}, now=seen)
    assert "DEAD" in next(ln for ln in local.splitlines() if "fusion" in ln)
    assert "running" in next(
        ln for ln in v.table(1.0, {"fusion": True}, now=seen).splitlines() if "fusion" in ln
    )


def test_monitor_once_without_a_rig_answers_within_its_wait() -> None:
    """``--once`` is a one-shot question: with no rig it waited for ever (``--duration`` bounds it;
    without one, ``ONCE_WAIT_S``, shortened here)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    code = (
        "import sys; from hil import cli; cli.ONCE_WAIT_S = 1.5; "
        "raise SystemExit(cli.main(['monitor', '--rig', 'nobody', '--once', '--interval', '0.2']))"
    )
    r = subprocess.run(
        [sys.executable, "-c", code],
        cwd=REPO,
        env=_env(endpoint, mode="peer"),
        capture_output=True,
        text=True,
        timeout=120,  # before: it never returned
    )
    assert r.returncode == 1, r.stdout + r.stderr
    assert "no status from rig 'nobody'" in r.stdout


def _truth(seq: int, t: int) -> Truth:
    zero = [0.0, 0.0, 0.0]
    return Truth(
        seq=seq,
        stamp_ns=t,
        lat_deg=0,
        lon_deg=0,
        alt_m=0,
        pos_ned_m=zero,
        vel_ned_mps=zero,
        q_nb=[1.0, 0.0, 0.0, 0.0],
        f_b_mps2=zero,
        w_ib_b_radps=zero,
    )


def _solution(seq: int, t: int, name: str, north: float, east: float) -> NavSolution:
    return NavSolution(
        seq=seq,
        stamp_ns=t,
        estimator=name,
        pos_ned_m=[north, east, 0.0],
        vel_ned_mps=[0.0, 0.0, 0.0],
        q_nb=[1.0, 0.0, 0.0, 0.0],
        lat_deg=0,
        lon_deg=0,
        alt_m=0,
    )


def test_the_table_takes_each_estimators_newest_solution_from_a_ring() -> None:
    """``hil up``'s and ``hil monitor``'s error line: the solutions and truth wait in Zenoh's
    rings and each draw decodes only the last truth batches and each estimator's newest solution
    the truth reaches, not every one of the ~360 a second a 400 Hz rig publishes (each a Python
    wake-up)."""
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = open_session(BusConfig(mode="router", listen=(endpoint,), connect=()))
    viewer = None
    sampler = None
    try:
        viewer = open_session(BusConfig(mode="client", connect=(endpoint,), listen=()))
        k = Keys(RIG)
        view = LiveView()
        sampler = SolutionSampler(viewer, k, view, Stats())
        truth = Publisher(hub, k.truth(), Truth)
        navs = {n: Publisher(hub, k.nav(n), NavSolution) for n in ("ekf15", "ins")}
        t = 0

        def publish(n: int, north: float, east: float, truth_too: bool = True) -> None:
            nonlocal t
            for _ in range(n):
                t += 20_000_000
                if truth_too:
                    truth.put(_truth(truth.next_seq(), t))
                for name, p in navs.items():
                    p.put(_solution(p.next_seq(), t, name, north, east if name == "ekf15" else 0.0))

        deadline = time.monotonic() + 60
        while not view.nav_seen and time.monotonic() < deadline:  # until the routes are up
            publish(1, 300.0, 400.0)
            time.sleep(0.05)
            sampler.drain()
        assert view.nav_seen, "no solution reached the sampler within 60 s"
        before = sampler.decoded
        publish(200, 300.0, 400.0)  # 600 messages the table never needs
        publish(1, 3.0, 4.0)  # the last the truth reaches: ekf15 5 m off truth, ins 3 m
        # newer solutions than any truth (the world publishes its truth ten rows at a time):
        # nothing to compare them with, so the error is the one before them
        t += 20_000_000  # (one 20 ms on would still be within reach of the last truth)
        publish(3, 300.0, 400.0, truth_too=False)
        drains = 0
        line = ""
        while time.monotonic() < deadline:
            sampler.drain()
            drains += 1
            line = next((ln for ln in view.table(1.0).splitlines() if "error vs truth" in ln), "")
            if "ekf15 5.0" in line and "ins 3.0" in line:
                break
            time.sleep(0.05)
        assert "ekf15 5.0" in line and "ins 3.0" in line, line
        # each drain decoded at most NAV_KEEP solutions of each estimator and TRUTH_KEEP truths
        keep = 2 * SolutionSampler.NAV_KEEP + SolutionSampler.TRUTH_KEEP
        assert sampler.decoded - before <= drains * keep < 600
    finally:
        if sampler is not None:
            sampler.undeclare()
        if viewer is not None:
            viewer.close()
        hub.close()

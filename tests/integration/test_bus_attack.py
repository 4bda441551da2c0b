"""Attacks on the live rig (issue 18): a stranger's flood, spoof and forgeries, and a spoofed receiver.

GIVEN ``hil up`` (every service its own OS process on a real Zenoh session) whose GNSS receiver is
spoofed 500 m north claiming σ 0.5 m for 5 s (the emulator's ``gnss_spoof``), and on the same bus
``tools/bus_attack.py`` -- a plain zenoh-python process that is not the rig's -- which floods
``synced/gnss`` and ``sensor/gnss`` with 4,000 valid fixes a second each for 2 s (the issue's
rate), then spoofs ``synced/gnss`` the same way and forges duplicates, seq 10⁹ and stamps 10⁶ s
ahead
WHEN the run ends
THEN the fused output never lost a stamp, the stranger's messages reached no estimator (refused
and counted) but were recorded marked and apart (missing=0, replay-ready, a sane duration), the
integrity gate kept every spoofed fix of the receiver from every estimator and raised the alarm,
no estimator moved towards the spoof, and ``hil rerun --verify`` reproduces the fusion bit for
bit. One run of 14 rig seconds for all of it.
"""

from __future__ import annotations

import json
import os
import subprocess
import sys
from collections.abc import Iterator
from typing import Any

import numpy as np
import pytest

from hil.bus.inbox import AIDING_CAP, PACER_CAP
from hil.fusion.core import parse_journal_id
from hil.messages import NavSolution
from hil.record.mcapio import Session, read_session
from tests.conftest import REPO, hil_cmd, spoof_event_toml

pytestmark = pytest.mark.slow

RIG = "atk"
DURATION_S = 14
FLOOD = {"start": 3.0, "seconds": 2.0, "n": 8000}
SPOOF = {"start": 7.0, "seconds": 5.0, "seq_base": 5_000_000}
FLOOD_SEQ_BASE = 1_000_000  # bus_attack's default
FORGE_START = 7.0
RECEIVER_SPOOF = (7.0, 12.0)
SCENARIO = (REPO / "hil/scenarios/straight_level.toml").read_text() + spoof_event_toml(*RECEIVER_SPOOF)


def _attack(endpoint: str, start: float, *args: str) -> subprocess.Popen[str]:
    cmd = [sys.executable, str(REPO / "tools/bus_attack.py"), "--connect", endpoint, "--rig", RIG]
    cmd += ["--start-after", str(start), "--wait", "120", *args]
    return subprocess.Popen(cmd, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True, cwd=REPO)


@pytest.fixture(scope="module")
def attacked(tmp_path_factory: pytest.TempPathFactory) -> Iterator[dict[str, Any]]:
    from hil.bus.session import BusConfig, open_session
    from tests.conftest import free_port

    tmp = tmp_path_factory.mktemp("attack")
    out, scenario = tmp / "attack.mcap", tmp / "spoofed.toml"
    scenario.write_text(SCENARIO)
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    hub = open_session(BusConfig(mode="router", listen=(endpoint,), connect=()))
    env = dict(os.environ, HIL_ZENOH_MODE="client", HIL_ZENOH_CONNECT=endpoint, HIL_ZENOH_LISTEN="")
    procs: list[subprocess.Popen[str]] = []
    try:
        up = subprocess.Popen(
            hil_cmd(
                "up",
                "--scenario",
                str(scenario),
                "--duration",
                str(DURATION_S),
                "--record",
                str(out),
                "--quiet",
                "--rig",
                RIG,
            ),
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
            text=True,
            cwd=REPO,
            env=env,
        )
        procs.append(up)
        flood_args = ["flood", "--n", str(FLOOD["n"]), "--seconds", str(FLOOD["seconds"])]
        spoof_args = ["--seq-base", str(SPOOF["seq_base"]), "spoof", "--seconds", str(SPOOF["seconds"])]
        attackers = {
            "flood": _attack(endpoint, FLOOD["start"], *flood_args),
            "spoof": _attack(endpoint, SPOOF["start"], *spoof_args),
            "forge": _attack(endpoint, FORGE_START, "forge", "--seconds", "3"),
        }
        procs += attackers.values()
        sent = {}
        for name, p in attackers.items():
            stdout, stderr = p.communicate(timeout=240)
            assert p.returncode == 0, f"{name}: {stderr}"
            sent[name] = json.loads(stdout.strip().splitlines()[-1])
        console, _ = up.communicate(timeout=240)
        yield {"path": out, "up": up, "console": console, "sent": sent, "session": read_session(out)}
    finally:
        for p in procs:
            if p.poll() is None:
                p.kill()
                p.communicate()
        hub.close()


def _mine(s: Session, topic: str) -> list[Any]:
    return [r.decode() for r in s.by_topic(f"hil/{RIG}/{topic}") if not r.foreign]


def _rig_s(sent: dict[str, Any], key: str = "first_rig_ns") -> float:
    return float(sent[key]) / 1e9


def test_the_run_ends_cleanly_with_the_strangers_recorded_apart(attacked: dict[str, Any]) -> None:
    s: Session = attacked["session"]
    assert attacked["up"].returncode == 0, attacked["console"]
    assert s.meta("completeness", "missing") == 0 and s.meta("completeness", "replay_ready") is True
    foreign = [r for r in s.records if r.foreign]
    assert foreign, "the strangers' messages were not recorded"
    assert {r.topic.split("/", 2)[2] for r in foreign} <= {"synced/gnss", "sensor/gnss", "truth"}
    # forged seq 10⁹ and stamps 10⁶ s ahead: no billion missing, no 10⁶ s duration
    info = subprocess.run(hil_cmd("info", str(attacked["path"])), capture_output=True, text=True, cwd=REPO)
    assert info.returncode == 0, info.stderr
    duration = next(line for line in info.stdout.splitlines() if line.startswith("duration:"))
    assert float(duration.split()[1]) < 3 * DURATION_S, duration
    assert "foreign:" in info.stdout and "missing=0" in info.stdout


def test_the_fused_output_kept_every_stamp_and_no_strangers_fix_reached_it(attacked: dict[str, Any]) -> None:
    s: Session = attacked["session"]
    recs = [r for r in s.by_topic(f"hil/{RIG}/nav/ekf15") if not r.foreign]
    stamps = np.array([r.decode().stamp_ns for r in recs]) / 1e9
    assert stamps[-1] > DURATION_S - 2
    fusion, timesync, recorder = (_mine(s, f"status/{n}") for n in ("fusion", "timesync", "recorder"))
    assert max(m.counter_map().get("rejected.foreign.synced.gnss", 0) for m in fusion) > 0
    assert max(m.counter_map().get("rejected.foreign.sensor.gnss", 0) for m in timesync) > 0
    assert max(m.counter_map().get("inbox.peak", 0) for m in fusion) <= PACER_CAP + 8 * AIDING_CAP
    assert not any(m.counter_map().get("inbox.dropped.synced.imu", 0) for m in fusion)  # never starved
    assert max(m.counter_map().get("dropped_rig", 0) for m in recorder) == 0
    strangers = {SPOOF["seq_base"] + i for i in range(attacked["sent"]["spoof"]["sent"]["synced/gnss"])}
    strangers |= {FLOOD_SEQ_BASE + i for i in range(FLOOD["n"])} | {10**9, 10**9 + 1}
    for j in _mine(s, "fusion/journal"):
        for e in [*j.dropped, *j.gated]:
            assert int(parse_journal_id(e.split(">")[0])[1].split(":")[1]) not in strangers, e
    # the figures, not asserted (wall time on a shared machine): latency before and after the flood
    # receive time on the rig clock: log_time and publish_time are both epoch + rig time
    log = stamps + np.array([r.log_time_ns - r.publish_time_ns for r in recs]) / 1e9
    flood = attacked["sent"]["flood"]
    lat = log - stamps
    for name, (a, b) in {
        "before": (1.0, _rig_s(flood)),
        "flood": (_rig_s(flood), _rig_s(flood, "last_rig_ns")),
        "1 s after": (_rig_s(flood, "last_rig_ns"), _rig_s(flood, "last_rig_ns") + 1.0),
        "1-2 s after": (_rig_s(flood, "last_rig_ns") + 1.0, _rig_s(flood, "last_rig_ns") + 2.0),
    }.items():
        m = (log >= a) & (log < b)
        print(
            f"ekf15 {name}: {m.sum()} outputs, latency median {np.median(lat[m]) if m.any() else float('nan'):.3f} s"
        )
    print("fusion rss_kib", [m.counter_map().get("rss_kib") for m in fusion])
    print("ekf15 largest stamp gap (s)", float(np.diff(stamps).max()))  # IMU lost by a starved rig


def test_the_gate_kept_the_spoofed_receiver_from_every_estimator(attacked: dict[str, Any]) -> None:
    s: Session = attacked["session"]
    gated = [e for j in _mine(s, "fusion/journal") for e in j.gated]
    assert len({e.split(">")[0] for e in gated}) >= 0.8 * 10 * (RECEIVER_SPOOF[1] - RECEIVER_SPOOF[0])
    # the alarm stands 3 s into the spoof (raised by it -- or before, by a rig so starved of CPU
    # that its INS and its receiver disagreed: the gate cannot tell, nor should it)
    events = [e for e in _mine(s, "event/fusion") if e.kind.startswith("gnss_integrity")]
    before = [e.kind for e in events if e.stamp_ns <= (RECEIVER_SPOOF[0] + 3.0) * 1e9]
    assert before[-1:] == ["gnss_integrity_alarm"], events
    # no estimator moved towards the spoof: its north error from then on is nowhere near 500 m
    truth = _mine(s, "truth")
    t_truth = np.array([m.stamp_ns for m in truth])
    north = np.array([m.pos_ned_m[0] for m in truth])
    worst: dict[str, float] = {}
    for r in s.by_topic_prefix(f"hil/{RIG}/nav/"):
        m = r.decode()
        if not r.foreign and isinstance(m, NavSolution) and RECEIVER_SPOOF[0] * 1e9 <= m.stamp_ns:
            err = abs(m.pos_ned_m[0] - float(np.interp(m.stamp_ns, t_truth, north)))
            worst[m.estimator] = max(worst.get(m.estimator, 0.0), err)
    print("north error from the spoof's start, max m:", {k: round(v, 1) for k, v in sorted(worst.items())})
    assert {"ekf15", "cf3", "compvs", "kfvel", "comp1", "comp3f"} <= set(worst)
    assert max(worst.values()) < 100.0, worst


def test_rerun_verify_reproduces_the_attacked_fusion(attacked: dict[str, Any]) -> None:
    proc = subprocess.run(
        hil_cmd("rerun", str(attacked["path"]), "--core", "fusion", "--verify"),
        capture_output=True,
        text=True,
        timeout=240,
        cwd=REPO,
    )
    assert proc.returncode == 0 and "VERIFY OK" in proc.stdout, proc.stdout + proc.stderr

"""Injected loss and late arrivals: a session whose fusion lost inputs and dropped late ones is
still reproduced bit for bit -- by ``hil rerun --verify`` and by a lockstep replay into a fresh
fusion process.

The session is built from the golden recording's inputs the way the live rig would have seen
them: every 97th IMU sample never arrives (lost upstream: neither fusion nor recorder has it),
a few IMU samples arrive 600 ms late (behind the fusion's 0.5 s horizon: dropped and journaled),
a few 300 ms late (behind newer ones but ahead of the horizon: the estimators take them, the
output predictor, which has integrated past them, does not; journaled ``unpredicted``), a few
GNSS fixes arrive 100 ms late (inside the horizon's lag: fused at their time of validity).
The fusion core is pushed in that arrival order with the live service's journaling.
"""

from __future__ import annotations

import json
import signal
from collections.abc import Iterator
from pathlib import Path

import pytest

from hil.bus.keys import Keys
from hil.fusion.core import FusionCore
from hil.messages import FusionJournal, FusionSettings, GnssFix, ImuSample, RunInfo, encode
from hil.record.mcapio import SessionWriter, read_session
from hil.record.rerun import fusion_config_from, rerun
from hil.runtime.scenario_io import scenario_for_run
from tests.replay.helpers import GOLDEN, Hub

pytestmark = pytest.mark.slow

RIG = "lossy"


def build_lossy_session(path: Path) -> tuple[int, int]:
    """Write the perturbed session; return (inputs journaled as dropped, outputs)."""
    src = read_session(GOLDEN)
    cfg = fusion_config_from(src)
    run = next(r.decode() for r in src.records if r.topic.endswith("/run"))
    assert isinstance(run, RunInfo)
    inputs = [r.decode() for r in src.records if "/synced/" in r.topic]
    arrivals: list[tuple[int, int, ImuSample | GnssFix]] = []
    late_imu = behind_imu = late_gnss = 0
    for i, m in enumerate(inputs):
        assert isinstance(m, ImuSample | GnssFix)
        t = m.stamp_ns
        if isinstance(m, ImuSample) and m.seq % 97 == 50:
            continue  # lost upstream
        if isinstance(m, ImuSample) and m.seq % 331 == 100:
            t += 600_000_000
            late_imu += 1
        if isinstance(m, ImuSample) and m.seq % 331 == 200:
            t += 300_000_000
            behind_imu += 1
        if isinstance(m, GnssFix) and m.seq % 7 == 3:
            t += 100_000_000
            late_gnss += 1
        arrivals.append((t, i, m))
    arrivals.sort(key=lambda a: (a[0], a[1]))
    assert late_imu >= 3 and behind_imu >= 3 and late_gnss >= 3
    k = Keys(RIG)
    core = FusionCore.for_scenario(scenario_for_run(run), cfg)
    w = SessionWriter(path)
    w.write(k.run(), RunInfo, encode(run), log_time_ns=0, publish_time_ns=0, seq=0)
    w.write(
        k.root + "/fusion/config",
        FusionSettings,
        encode(cfg.settings(0, 0)),
        log_time_ns=0,
        publish_time_ns=0,
        seq=0,
    )
    jseq = 0
    dropped_total = unpredicted_total = 0
    outputs = 0

    def journal(t: int) -> None:
        nonlocal jseq, dropped_total, unpredicted_total
        j = core.journal(jseq, t)
        dropped_total += len(j.dropped)
        unpredicted_total += len(j.unpredicted)
        w.write(k.journal(), FusionJournal, encode(j), log_time_ns=t, publish_time_ns=t, seq=jseq)
        jseq += 1

    def emit(sols: list, t: int) -> None:  # type: ignore[type-arg]
        nonlocal outputs
        for s in sols:
            w.write(
                k.nav(s.estimator), type(s), encode(s), log_time_ns=t, publish_time_ns=s.stamp_ns, seq=s.seq
            )
            outputs += 1

    for n, (t, _i, m) in enumerate(arrivals):
        w.write(k.synced(m.sensor), type(m), encode(m), log_time_ns=t, publish_time_ns=m.stamp_ns, seq=m.seq)
        emit(core.push(m), t)
        if n % 200 == 199:
            journal(t)
    t_end = arrivals[-1][0] + 1
    emit(core.flush(), t_end)
    journal(t_end)
    w.close()
    assert unpredicted_total >= 3
    return dropped_total, outputs


@pytest.fixture(scope="module")
def lossy(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, int, int]:
    path = tmp_path_factory.mktemp("lossy") / "lossy.mcap"
    dropped, outputs = build_lossy_session(path)
    return path, dropped, outputs


def test_rerun_verify_reproduces_a_session_with_loss_and_late_arrivals(lossy: tuple[Path, int, int]) -> None:
    path, dropped, outputs = lossy
    assert dropped >= 3 and outputs > 1000
    rc, lines = rerun(str(path), core="fusion", verify=True)
    assert rc == 0, lines
    assert f"({dropped} journaled as dropped)" in lines[0]


@pytest.fixture
def hub() -> Iterator[Hub]:
    h = Hub()
    try:
        yield h
    finally:
        h.close()


def test_lockstep_replay_of_a_session_with_loss_and_late_arrivals(
    lossy: tuple[Path, int, int], hub: Hub
) -> None:
    path, _dropped, _outputs = lossy
    s = read_session(path)
    cfg = fusion_config_from(s)
    recorded = {(r.topic.rsplit("/", 1)[1], r.sequence): r.payload for r in s.records if "/nav/" in r.topic}
    hub.collect("hil/replay2/nav/*")
    opts = {
        "estimators": list(cfg.estimators),
        "lag_s": cfg.lag_ns / 1e9,
        "output_every": cfg.output_every,
        "imu_bias_model": cfg.imu_bias_model,  # the golden file's tuning: made before the wander was told
    }
    fusion = hub.spawn("service", "fusion", "--rig", "replay2", "--options", json.dumps(opts))
    try:
        hub.wait_status("fusion", lambda st: st.state == "waiting_run")
        rp = hub.run(
            "replay",
            str(path),
            "--rig",
            "replay2",
            "--lockstep",
            "--afap",
            "--topics",
            "/run$",
            "--topics",
            "/synced/",
        )
        assert rp.returncode == 0, rp.stdout + rp.stderr
        assert "inputs the live fusion had dropped were not sent" in rp.stdout
    finally:
        fusion.send_signal(signal.SIGTERM)
        out, _ = fusion.communicate(timeout=60)
    assert fusion.returncode == 0, out[-2000:]
    got = {(k.rsplit("/", 1)[1], json.loads(p)["seq"]): p for k, p in hub.samples}
    assert set(got) == set(recorded)
    assert all(got[k] == recorded[k] for k in recorded)

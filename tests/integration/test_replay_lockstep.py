"""Replay through the live bus: a recording replayed under another rig into a fresh fusion
process reproduces every recorded fusion output bit for bit, at --rate 1 and at --afap."""

from __future__ import annotations

import json
import signal
from collections.abc import Iterator

import pytest

from hil.record.mcapio import read_session
from hil.record.rerun import fusion_config_from
from tests.replay.helpers import GOLDEN, Hub

pytestmark = pytest.mark.slow


@pytest.fixture
def hub() -> Iterator[Hub]:
    h = Hub()
    try:
        yield h
    finally:
        h.close()


@pytest.mark.parametrize("timing", [["--afap"], ["--rate", "1"]], ids=["afap", "rate1"])
def test_replay_into_a_fresh_fusion_reproduces_the_recorded_outputs(hub: Hub, timing: list[str]) -> None:
    # GIVEN a recording and a fresh fusion process on rig "replay1", configured as the recorded one
    s = read_session(GOLDEN)
    cfg = fusion_config_from(s)
    recorded = {(r.topic.rsplit("/", 1)[1], r.sequence): r.payload for r in s.records if "/nav/" in r.topic}
    assert len(recorded) > 300
    hub.collect("hil/replay1/nav/*")
    opts = {
        "estimators": list(cfg.estimators),
        "lag_s": cfg.lag_ns / 1e9,
        "output_every": cfg.output_every,
        "imu_bias_model": cfg.imu_bias_model,  # the golden file's tuning: made before the wander was told
    }
    fusion = hub.spawn("service", "fusion", "--rig", "replay1", "--options", json.dumps(opts))
    try:
        hub.wait_status("fusion", lambda st: st.state == "waiting_run")
        # WHEN the run announcement and the synchronised inputs are replayed under replay1, in lockstep
        rp = hub.run(
            "replay",
            str(GOLDEN),
            "--rig",
            "replay1",
            "--lockstep",
            "--topics",
            "/run$",
            "--topics",
            "/synced/",
            *timing,
        )
        assert rp.returncode == 0, rp.stdout + rp.stderr
        assert "replay:" in rp.stdout
    finally:
        fusion.send_signal(signal.SIGTERM)  # the fusion releases its buffered tail at stop
        out, _ = fusion.communicate(timeout=60)
    assert fusion.returncode == 0, out[-2000:]
    # THEN every recorded output came out again, byte for byte, and nothing else
    got = {(k.rsplit("/", 1)[1], json.loads(p)["seq"]): p for k, p in hub.samples}
    assert set(got) == set(recorded), (len(got), len(recorded), sorted(set(recorded) ^ set(got))[:5])
    diff = [k for k in recorded if got[k] != recorded[k]]
    assert not diff, (diff[:3], got[diff[0]], recorded[diff[0]])

"""hil bench rig's latency table leaves the start-up out (the IMU is held until time sync locks)
and counts only what was captured after it, per hop."""

from __future__ import annotations

from pathlib import Path

import numpy as np

from hil.bench.rig import hop_latencies_ms
from hil.record.mcapio import read_session

GOLDEN = Path(__file__).parents[1] / "replay" / "golden" / "straight_level_4s.mcap"


def test_latencies_after_the_start_up_count_only_what_was_captured_after_it() -> None:
    whole = hop_latencies_ms(GOLDEN, "golden")
    later = hop_latencies_ms(GOLDEN, "golden", skip_s=2.0)
    s = read_session(GOLDEN)
    capture = sorted(r.publish_time_ns for r in s.by_topic("hil/golden/capture/imu"))
    after = sum(1 for t in capture if t >= capture[0] + 2_000_000_000)
    raw = "raw IMU sample (sensor/imu)"
    assert len(whole[raw]) == len(capture)
    assert len(later[raw]) == after
    assert 0 < len(later["synced IMU sample"]) <= after
    nav = [k for k in whole if k.startswith("fused output nav/")]
    assert "fused output nav/ekf15" in nav
    for k in nav:
        assert 0 < len(later[k]) < len(whole[k])
        assert np.all(later[k] >= 0)

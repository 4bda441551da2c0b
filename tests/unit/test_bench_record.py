"""hil bench record's rerun row states a recording's length in rig seconds on either timeline
(it took the wall-clock stamps of recordings since the Foxglove merge for rig time: 1.77e9 s)."""

from __future__ import annotations

from pathlib import Path

import pytest

from hil.bench.record import bench_rerun

GOLDEN = Path(__file__).parents[1] / "replay" / "golden"


@pytest.mark.parametrize("name", ["straight_level_4s.mcap", "legacy_straight_level_4s.mcap"])
def test_the_rerun_row_spans_the_recordings_rig_seconds(name: str) -> None:
    r = bench_rerun(GOLDEN / name, None)
    assert r["duration_s"] == pytest.approx(4.0, abs=0.05)
    assert r["outputs"] == 1400
    assert r["verified"] is (
        name == "straight_level_4s.mcap"
    )  # the legacy file's outputs predate the predictor

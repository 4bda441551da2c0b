"""A recording read by the Foxglove app's own code: @mcap/core (Foxglove's MCAP reader, CRCs
checked) and protobufjs on the FileDescriptorSet each channel embeds, as Foxglove's mcap-support
decodes protobuf; JSON channels are JSON.parse'd as the app does (their schemas are checked
against Foxglove's parser port in tests/unit/test_schema_rules). ``tools/mcapjs`` holds the
pinned packages (``npm ci`` there; .ci/run does it); without node or them the test is skipped."""

from __future__ import annotations

import json
import shutil
import subprocess
from pathlib import Path
from typing import Any

import pytest
from mcap.reader import make_reader

from tests.conftest import REPO

MCAPJS = REPO / "tools" / "mcapjs"


def read_in_foxglove(path: Path) -> dict[str, Any]:
    """``node tools/mcapjs/read.mjs FILE --decode``: totals, log-time span and per-topic decode counts.

    Every message must decode (no errors, raw channels aside) and the per-topic counts must be the
    Python mcap reader's: a reader nobody here wrote sees the same file."""
    if not shutil.which("node") or not (MCAPJS / "node_modules" / "protobufjs").is_dir():
        pytest.skip("Foxglove's reader is not installed: cd tools/mcapjs && npm ci")
    js = subprocess.run(
        ["node", str(MCAPJS / "read.mjs"), str(path), "--decode"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    assert js.returncode == 0, js.stderr
    got: dict[str, Any] = json.loads(js.stdout)
    per_topic = got["per_topic"]
    bad = {t: e["first_error"] for t, e in per_topic.items() if e["errors"]}
    assert not bad, bad
    undecoded = {
        t
        for t, e in per_topic.items()
        if e["encoding"] in ("json", "protobuf") and e["decoded"] != e["count"]
    }
    assert not undecoded, undecoded
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None and summary.statistics is not None
    counts = {summary.channels[cid].topic: n for cid, n in summary.statistics.channel_message_counts.items()}
    assert {t: e["count"] for t, e in per_topic.items()} == {t: n for t, n in counts.items() if n}
    assert int(got["start_ns"]) == summary.statistics.message_start_time
    assert int(got["end_ns"]) == summary.statistics.message_end_time
    return got


def expected_wellknown(estimators: set[str]) -> dict[str, str]:
    """The /foxglove/ channels a recording with these estimators carries (topic -> Foxglove schema)."""
    want = {f"/foxglove/fix/nav/{e}": "foxglove.LocationFix" for e in estimators}
    want |= {f"/foxglove/tf/nav/{e}": "foxglove.FrameTransform" for e in estimators}
    want |= {
        "/foxglove/fix/truth": "foxglove.LocationFix",
        "/foxglove/fix/sensor/gnss": "foxglove.LocationFix",
    }
    want |= {
        "/foxglove/tf/truth": "foxglove.FrameTransform",
        "/foxglove/tf_static": "foxglove.FrameTransform",
    }
    return want | {"/foxglove/log": "foxglove.Log"}


def same_first_fix(js_fix: dict[str, Any], py_fix: Any) -> bool:
    """The first LocationFix as protobufjs read it is the one the Python protobuf decoder read."""
    return (
        js_fix["latitude"] == py_fix.latitude
        and js_fix["longitude"] == py_fix.longitude
        and js_fix["altitude"] == py_fix.altitude
        and int(js_fix["timestamp"]["seconds"]) == py_fix.timestamp.seconds
        and js_fix["timestamp"]["nanos"] == py_fix.timestamp.nanos
        and js_fix["frame_id"] == py_fix.frame_id
    )

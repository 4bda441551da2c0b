"""The Foxglove export of a real recording: every channel kept, LocationFix channels for the map
panel valid against the LocationFix schema, hil schemas simplified but still valid JSON Schema."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jsonschema
from mcap.reader import make_reader

from hil.record.foxglove import FIX_PREFIX, LOCATION_FIX, LOCATION_FIX_SCHEMA
from hil.record.mcapio import read_session
from tests.conftest import REPO
from tests.replay.helpers import GOLDEN


def test_export_adds_location_fix_channels_and_keeps_everything(tmp_path: Path) -> None:
    out = tmp_path / "fox.mcap"
    proc = subprocess.run(
        [sys.executable, "-m", "hil.record.foxglove", str(GOLDEN), str(out)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    src = read_session(GOLDEN)
    with open(out, "rb") as fh:
        reader = make_reader(fh)
        summary = reader.get_summary()
        assert summary is not None
        chans = {c.topic: summary.schemas[c.schema_id] for c in summary.channels.values()}
        fixes: dict[str, list[dict[str, object]]] = {}
        kept = 0
        for schema, channel, msg in reader.iter_messages():
            assert (
                schema is not None and schema.encoding == "jsonschema" and channel.message_encoding == "json"
            )
            if channel.topic.startswith(FIX_PREFIX):
                fixes.setdefault(channel.topic, []).append(json.loads(msg.data))
            else:
                kept += 1
    assert kept == len(src.records)
    # every estimator, the free INS, the GNSS receiver and truth are on the map
    estimators = {r.topic.rsplit("/", 1)[1] for r in src.records if "/nav/" in r.topic}
    assert set(fixes) == {FIX_PREFIX + n for n in {*estimators, "gnss", "truth"}}
    assert len(fixes[FIX_PREFIX + "truth"]) == len([r for r in src.records if r.topic.endswith("/truth")])
    for topic, rows in fixes.items():
        assert chans[topic].name == LOCATION_FIX
        for row in rows[:50]:
            jsonschema.validate(row, LOCATION_FIX_SCHEMA)
            assert 40 < row["latitude"] < 60  # type: ignore[operator]
    gnss = fixes[FIX_PREFIX + "gnss"][0]
    assert gnss["position_covariance_type"] == 2 and gnss["position_covariance"][0] > 0  # type: ignore[index]
    # the hil schemas are still valid JSON Schema, and the payloads still validate against them
    for topic, schema in chans.items():
        body = json.loads(schema.data)
        jsonschema.Draft202012Validator.check_schema(body)
        assert "anyOf" not in json.dumps(body), topic
    assert {m.name for m in summary.metadata_indexes} >= set(src.metadata)
    assert len(summary.attachment_indexes) == len(src.attachments)


def test_export_of_a_bad_file_fails_in_one_line_and_leaves_nothing(tmp_path: Path) -> None:
    bad = tmp_path / "bad.mcap"
    bad.write_bytes(b"nope" * 100)
    out = tmp_path / "out.mcap"
    proc = subprocess.run(
        [sys.executable, "-m", "hil.record.foxglove", str(bad), str(out)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=60,
    )
    assert proc.returncode == 2 and "Traceback" not in proc.stderr
    assert len(proc.stderr.strip().splitlines()) == 1
    assert not out.exists()

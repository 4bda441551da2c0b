"""The export brings a recording made before the Foxglove-first change up to today's form: current
payloads under schemas Foxglove decodes, wall-clock times, the well-known channels; a recording
of today's form comes out with the same messages."""

from __future__ import annotations

import json
import subprocess
import sys
from pathlib import Path

import jsonschema
import pytest
from mcap.reader import make_reader

from hil.messages import NavSolution, RunInfo, Truth, decode, encode
from hil.record.foxglove import export_foxglove
from hil.record.mcapio import SessionWriter, read_session
from hil.schemas_io import foxglove_schema_problems
from tests.conftest import REPO
from tests.foxglove_js import expected_wellknown, read_in_foxglove, same_first_fix
from tests.replay.helpers import LEGACY_GOLDEN
from tests.wellknown_reader import decode_wellknown


def _schemas(path: Path) -> dict[str, tuple[str, str, bytes]]:
    with open(path, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    return {
        c.topic: (
            summary.schemas[c.schema_id].name,
            summary.schemas[c.schema_id].encoding,
            summary.schemas[c.schema_id].data,
        )
        for c in summary.channels.values()
    }


def test_export_of_an_old_recording_decodes_in_foxglove_and_keeps_every_message(tmp_path: Path) -> None:
    out = tmp_path / "fox.mcap"
    proc = subprocess.run(
        [sys.executable, "-m", "hil.record.foxglove", str(LEGACY_GOLDEN), str(out)],
        capture_output=True,
        text=True,
        cwd=REPO,
        timeout=120,
    )
    assert proc.returncode == 0, proc.stderr
    src, got = read_session(LEGACY_GOLDEN), read_session(out)
    assert [(r.topic, r.sequence) for r in got.records] == [(r.topic, r.sequence) for r in src.records]
    assert [r.decode() for r in got.records] == [r.decode() for r in src.records]  # same values ...
    assert all(b'"pos_sigma_m":null' not in r.payload for r in got.records)  # ... in today's form
    validators: dict[str, jsonschema.Draft202012Validator] = {}
    for topic, (name, enc, data) in _schemas(out).items():
        if enc == "jsonschema":
            body = json.loads(data)
            assert foxglove_schema_problems(body, name) == [], topic
            validators[topic] = jsonschema.Draft202012Validator(body)
    for r in got.records[::50]:
        validators[r.topic].validate(json.loads(r.payload))
    decoded = decode_wellknown(out)
    estimators = {r.topic.rsplit("/", 1)[1] for r in src.records if r.schema == "hil.NavSolution"}
    assert {f"/foxglove/fix/nav/{e}" for e in estimators} | {"/foxglove/fix/truth"} <= set(decoded)
    assert {f"/foxglove/tf/nav/{e}" for e in estimators} | {"/foxglove/tf_static"} <= set(decoded)
    with open(out, "rb") as fh:
        summary = make_reader(fh).get_summary()
    assert summary is not None
    assert {m.name for m in summary.metadata_indexes} >= set(src.metadata)
    assert len(summary.attachment_indexes) == len(src.attachments)


def test_export_moves_rig_time_log_times_onto_the_wall_clock(tmp_path: Path) -> None:
    # GIVEN a recording of the old timeline: rig time in log_time, start epoch in the run message
    old = tmp_path / "old.mcap"
    start = 1_767_225_600 * 10**9
    run = RunInfo(
        seq=0, stamp_ns=0, rig="x", start_epoch_ns=start, speed=1.0, scenario="s", scenario_sha256="",
        seed=1, duration_s=1.0, origin_lat_deg=50.0, origin_lon_deg=30.0, origin_alt_m=0.0,
    )  # fmt: skip
    truth = Truth(
        seq=0, stamp_ns=500_000_000, lat_deg=50.0, lon_deg=30.0, alt_m=0.0, pos_ned_m=[0, 0, 0],
        vel_ned_mps=[0, 0, 0], q_nb=[1, 0, 0, 0], f_b_mps2=[0, 0, 0], w_ib_b_radps=[0, 0, 0],
    )  # fmt: skip
    nav_null = (
        b'{"seq":0,"stamp_ns":500000000,"estimator":"ins","pos_ned_m":[0,0,0],"vel_ned_mps":[0,0,0],'
        b'"q_nb":[1,0,0,0],"lat_deg":50,"lon_deg":30,"alt_m":0,"pos_sigma_m":null,"vel_sigma_mps":null}'
    )
    w = SessionWriter(old)
    w.write("hil/x/run", RunInfo, encode(run), log_time_ns=0, publish_time_ns=0, seq=0)
    w.write("hil/x/truth", Truth, encode(truth), log_time_ns=600_000_000, publish_time_ns=500_000_000, seq=0)
    w.write(
        "hil/x/nav/ins", NavSolution, nav_null, log_time_ns=700_000_000, publish_time_ns=500_000_000, seq=0
    )
    w.close()
    # WHEN exported
    derived = export_foxglove(old, tmp_path / "new.mcap")
    # THEN every time is start epoch + rig time, and the map has truth and the INS
    s = read_session(tmp_path / "new.mcap")
    assert [(r.log_time_ns - start, r.publish_time_ns - start) for r in s.records] == [
        (0, 0),
        (600_000_000, 500_000_000),
        (700_000_000, 500_000_000),
    ]
    assert b'"pos_sigma_m":[]' in s.records[2].payload
    assert derived["/foxglove/fix/truth"] == 1 and derived["/foxglove/fix/nav/ins"] == 1
    fix = decode_wellknown(tmp_path / "new.mcap")["/foxglove/fix/truth"][0]
    assert fix[0] == start + 600_000_000 and fix[1].timestamp.seconds == start // 10**9  # type: ignore[attr-defined]


def test_export_of_a_recording_of_today_s_form_keeps_its_messages(
    sim_recording: Path, tmp_path: Path
) -> None:
    out = tmp_path / "again.mcap"
    export_foxglove(sim_recording, out)
    a, b = read_session(sim_recording, derived=True), read_session(out, derived=True)
    key = [(r.topic, r.log_time_ns, r.publish_time_ns, r.sequence, r.payload) for r in a.records]
    assert [(r.topic, r.log_time_ns, r.publish_time_ns, r.sequence, r.payload) for r in b.records] == key


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


def test_foxglove_s_own_reader_decodes_every_message_of_a_sim_recording(sim_recording: Path) -> None:
    got = read_in_foxglove(sim_recording)
    per_topic = got["per_topic"]
    estimators = {t.rsplit("/", 1)[1] for t, e in per_topic.items() if e["schema"] == "hil.NavSolution"}
    assert len(estimators) >= 5, estimators
    want = expected_wellknown(estimators)
    assert {t: per_topic[t]["schema"] for t in want if t in per_topic} == want
    assert all(per_topic[t]["encoding"] == "protobuf" and per_topic[t]["decoded"] >= 1 for t in want)
    assert {e["encoding"] for t, e in per_topic.items() if t.startswith("hil/")} == {"json"}
    # the timeline Foxglove shows is the run's wall clock: it starts at the run's start epoch
    run = decode(RunInfo, read_session(sim_recording).by_topic("hil/simrec/run")[0].payload)
    assert int(got["start_ns"]) == run.start_epoch_ns
    py = decode_wellknown(sim_recording)
    assert same_first_fix(per_topic["/foxglove/fix/truth"]["first"], py["/foxglove/fix/truth"][0][1])
    assert per_topic["/foxglove/tf/truth"]["first"]["child_frame_id"] == "truth"


def test_a_message_foxglove_cannot_decode_fails_the_foxglove_reader_check(tmp_path: Path) -> None:
    from foxglove.messages import LocationFix
    from mcap.writer import Writer

    from hil.wellknown import SCHEMAS

    def write(path: Path, fix: bytes, nav: bytes) -> Path:
        with open(path, "wb") as fh:
            w = Writer(fh)
            w.start()
            s = SCHEMAS["foxglove.LocationFix"]
            pb = w.register_schema(name=s.name, encoding=s.encoding, data=s.data)
            js = w.register_schema(name="hil.X", encoding="jsonschema", data=b'{"type":"object"}')
            c1 = w.register_channel(topic="/foxglove/fix/truth", message_encoding="protobuf", schema_id=pb)
            c2 = w.register_channel(topic="hil/x/nav/a", message_encoding="json", schema_id=js)
            w.add_message(channel_id=c1, log_time=1, publish_time=1, data=fix)
            w.add_message(channel_id=c2, log_time=2, publish_time=2, data=nav)
            w.finish()
        return path

    lat = LocationFix(latitude=1.5).encode()  # field 1, a double: 0x09 and its 8 bytes
    good = read_in_foxglove(write(tmp_path / "good.mcap", lat, b'{"seq":1}'))
    assert good["per_topic"]["/foxglove/fix/truth"]["first"]["latitude"] == 1.5
    # a truncated protobuf field (tag of a double, 3 of its 8 bytes) and a JSON payload cut short
    for fix, nav, bad in ((lat[:4], b'{"seq":1}', "/foxglove/fix/truth"), (lat, b'{"seq":', "hil/x/nav/a")):
        with pytest.raises(AssertionError, match=bad):
            read_in_foxglove(write(tmp_path / "bad.mcap", fix, nav))

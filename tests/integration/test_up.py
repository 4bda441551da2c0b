"""The live rig for real: `hil up` starts every service as its own OS process over a real Zenoh
session and a real python-can bus; the recording is checked with the mcap reader."""

from __future__ import annotations

import json
import re
import subprocess
from pathlib import Path

import jsonschema
import numpy as np
import pytest

from hil.messages import TYPES_BY_NAME, RunInfo, ServiceStatus, Truth, decode
from hil.record.info import estimator_errors
from hil.record.mcapio import read_session, rig_time_ns, split_parts
from hil.schemas_io import SCHEMAS_DIR
from tests.conftest import REPO, hil_cmd
from tests.foxglove_js import expected_wellknown, read_in_foxglove, same_first_fix
from tests.wellknown_reader import decode_wellknown

pytestmark = pytest.mark.slow

ALL_SERVICES = {"world", "imu_emulator", "can_bridge", "gnss_emulator", "timesync", "fusion", "recorder"}
REQUIRED_TYPES = {
    "hil.RunInfo",
    "hil.Truth",
    "hil.ImuSample",
    "hil.GnssFix",
    "hil.CanFrame",
    "hil.TimeTag",
    "hil.ClockModel",
    "hil.NavSolution",
    "hil.ServiceStatus",
    "hil.CaptureTruth",
    "hil.FusionJournal",
    "hil.FusionSettings",
    "hil.EstimatorHealth",
}


@pytest.fixture(scope="module")
def up_recording(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, subprocess.CompletedProcess[str]]:
    out = tmp_path_factory.mktemp("up") / "up.mcap"
    proc = subprocess.run(
        hil_cmd(
            "up",
            "--duration",
            "10",
            "--record",
            str(out),
            "--quiet",
            "--rig",
            "itest",
            "--dut",
            str(REPO / "examples/dut/navbox.toml"),
            "--dut-emulator",
            "truth",  # the truth+noise stand-in; the unit itself: tests/integration/test_dut.py
        ),
        capture_output=True,
        text=True,
        timeout=240,
        cwd=REPO,
    )
    return out, proc


def test_up_exits_zero_and_prints_a_summary(
    up_recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    path, proc = up_recording
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    assert path.is_file()
    assert "hil/itest/sensor/imu" in proc.stdout  # the hil info summary at the end
    assert "CAN vcan0" in proc.stdout  # says which CAN transport in one line
    # the CPU table holds every service, the supervisor (its hub and view) and the sum of them,
    # each with its threads' wake-ups a second (the IMU emulator's with its CAN sender process's,
    # which sleeps before each IMU sample it is not late for: 400 a second here)
    cpu_row = re.compile(r"^\s+(\w+)\s+([0-9.]+) s\s+[0-9.]+ %\s+(\d+) wake-ups/s$")
    lines = proc.stdout.splitlines()
    rows = {m[1]: float(m[2]) for ln in lines if (m := cpu_row.match(ln))}
    wakes = {m[1]: int(m[3]) for ln in lines if (m := cpu_row.match(ln))}
    assert {"recorder", "fusion", "supervisor", "all"} <= rows.keys(), proc.stdout[-3000:]
    assert rows["supervisor"] > 0.0
    assert rows["all"] == pytest.approx(sum(v for k, v in rows.items() if k != "all"), abs=0.05)
    assert min(wakes.values()) > 0 and wakes["imu_emulator"] >= 100, proc.stdout[-3000:]
    assert wakes["all"] == pytest.approx(sum(v for k, v in wakes.items() if k != "all"), abs=len(wakes))


def test_recording_holds_every_contract_type_valid_against_schemas(
    up_recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    path, _ = up_recording
    s = read_session(path)
    assert not s.truncated
    # the checked-in files in schemas/, one compiled validator each (jsonschema.validate would
    # rebuild a validator per message: minutes for a 30k-message session)
    validators = {
        name: jsonschema.Draft202012Validator(json.loads((SCHEMAS_DIR / f"{name}.json").read_text()))
        for name in TYPES_BY_NAME
    }
    seen = set()
    for r in s.records:
        seen.add(r.schema)
        validators[r.schema].validate(json.loads(r.payload))
    assert seen >= REQUIRED_TYPES, REQUIRED_TYPES - seen


def test_recording_is_complete_no_gaps_and_imu_at_rate(
    up_recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    path, _ = up_recording
    s = read_session(path)
    comp = s.metadata["completeness"]
    assert json.loads(comp["missing"]) == 0, comp["topics"]
    assert json.loads(comp["replay_ready"]) is True
    # Zenoh's own sample-miss detection is on by default and saw every sample sequenced, none missed
    assert json.loads(comp["zenoh_miss_detection"]) is True
    assert json.loads(comp["zenoh_missed"]) == 0 and json.loads(comp["zenoh_unsequenced"]) == 0
    imu = s.by_topic("hil/itest/sensor/imu")
    assert len(imu) >= 0.99 * 400 * 10
    statuses = {decode(ServiceStatus, r.payload).service for r in s.by_topic_prefix("hil/itest/status/")}
    assert statuses >= ALL_SERVICES
    # every service's statuses are on the rig clock once the run is announced: the recorder's
    # went out stamped 0 all run (hil info then read them as ~13 Hz over their publish times)
    for svc in ALL_SERVICES:
        stamps = [decode(ServiceStatus, r.payload).stamp_ns for r in s.by_topic(f"hil/itest/status/{svc}")]
        assert max(stamps) > 5e9, (svc, stamps)
    # each synced IMU sample keeps its raw seq
    assert {r.sequence for r in s.by_topic("hil/itest/synced/imu")} == {r.sequence for r in imu}


def test_fused_solution_tracks_truth(up_recording: tuple[Path, subprocess.CompletedProcess[str]]) -> None:
    path, _ = up_recording
    errs = estimator_errors(read_session(path))
    assert "ins" in errs and "comp1" in errs
    # straight-and-level, tactical IMU, 10 s: the free INS has drifted little and the classic
    # compensation filter sits within a few GNSS sigmas of truth
    assert errs["ins"]["max_m"] < 50.0
    assert errs["comp1"]["rms_m"] < 60.0
    assert np.isfinite([e["rms_m"] for e in errs.values()]).all()


def test_rerun_verify_reproduces_the_live_fusion_bit_for_bit(
    up_recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    path, _ = up_recording
    # the live fusion ran its kernels compiled (loaded in the background while it started) by
    # the end; the rerun below, compiled too, matches it as a Python one would (tests/unit/test_jit)
    statuses = read_session(path).by_topic("hil/itest/status/fusion")
    assert decode(ServiceStatus, statuses[-1].payload).counter_map()["kernels.compiled"] == 1
    for core in ("fusion", "timesync"):
        proc = subprocess.run(
            hil_cmd("rerun", str(path), "--core", core, "--verify"),
            capture_output=True,
            text=True,
            timeout=240,
            cwd=REPO,
        )
        assert proc.returncode == 0, proc.stdout + proc.stderr
        assert "VERIFY OK" in proc.stdout


def test_estimator_health_arrives_as_real_numbers(
    up_recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    # GIVEN the live rig's recording (real processes, Zenoh, the recorder's decode of the wire)
    out, _proc = up_recording
    s = read_session(out)
    health = {
        r.topic.rsplit("/", 1)[1]: [r.decode() for r in s.by_topic(r.topic)]
        for r in s.records
        if "/health/" in r.topic
    }
    # THEN every default estimator reports its health once a rig second, as named real numbers
    assert {"comp1", "comp3f", "compvs", "cf3", "kfvel", "ekf15"} <= set(health)
    assert all(len(v) >= 8 for v in health.values())
    # kfvel's Kalman gain lies strictly between 0 and 1: an int() on the way would make it 0
    # (0 only before its first GNSS update: time sync holds the IMU until its tag filter locks)
    gains = [h.as_dict()["gain_vel_n"] for h in health["kfvel"]]
    first = next((i for i, g in enumerate(gains) if g != 0.0), len(gains))
    assert gains[:first] == [0.0] * first and len(gains) - first >= 5, gains
    assert all(0.0 < g < 1.0 for g in gains[first:]), gains
    # ekf15's NIS and bias norms are real numbers too, not truncated counts
    ekf = health["ekf15"][-1].as_dict()
    assert {"nis_pos", "nis_vel", "gyro_bias_norm_radps"} <= set(ekf)
    assert any(v != int(v) for v in ekf.values())


def test_device_under_test_is_decoded_and_scored_like_an_estimator(
    up_recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    """The emulated navigation box sends its own DBC frames on the IMU's bus; the bridge decodes
    them with the mapping into nav/dut_navbox, which the report scores against truth."""
    path, _ = up_recording
    s = read_session(path)
    dut = s.by_topic("hil/itest/nav/dut_navbox")
    assert len(dut) >= 0.9 * 10 * 10  # 10 Hz for 10 s
    errs = estimator_errors(s)
    # the unit's own error is a 1.5 m Gauss-Markov wander per horizontal axis
    assert errs["dut_navbox"]["rms_m"] < 6.0
    assert {"dut_emulator"} <= {
        decode(ServiceStatus, r.payload).service for r in s.by_topic_prefix("hil/itest/status/")
    }


def test_the_live_recording_is_on_the_wall_clock_and_carries_foxglove_s_types(
    up_recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    path, _ = up_recording
    s = read_session(path)
    run = decode(RunInfo, s.by_topic("hil/itest/run")[0].payload)
    start = run.start_epoch_ns
    assert s.meta("hil", "time_base") == "epoch"
    # the run's time zero is this run's wall clock (the file was finished after it)
    assert 0 < path.stat().st_mtime_ns - start < 600 * 10**9
    truth = [(r, decode(Truth, r.payload)) for r in s.by_topic("hil/itest/truth")]
    for r, m in truth:
        assert r.publish_time_ns == start + m.stamp_ns  # epoch + time of validity
        assert 0 <= rig_time_ns(r.log_time_ns, start) - m.stamp_ns < 5 * 10**9  # received after it
    # the recorder wrote Foxglove's well-known types beside the messages; each decodes
    decoded = decode_wellknown(path)
    estimators = {r.topic.rsplit("/", 1)[1] for r in s.records if r.schema == "hil.NavSolution"}
    assert {"ekf15", "ins", "dut_navbox"} <= estimators
    want = {f"/foxglove/{k}/nav/{e}" for e in estimators for k in ("fix", "tf")}
    want |= {"/foxglove/fix/truth", "/foxglove/tf/truth", "/foxglove/fix/sensor/gnss", "/foxglove/tf_static"}
    assert want <= set(decoded), want - set(decoded)
    stamps = {start + m.stamp_ns for _r, m in truth}
    fixes = decoded["/foxglove/fix/truth"]
    assert len(fixes) >= 0.9 * 10 * 10  # 10 Hz for 10 s
    assert all(f.timestamp.seconds * 10**9 + f.timestamp.nanos in stamps for _t, f in fixes)  # type: ignore[attr-defined]
    # every service's start shows in the log panel
    logs = [m for _t, m in decoded["/foxglove/log"]]
    assert len({m.name for m in logs if "state" in m.message}) >= 3  # type: ignore[attr-defined]


def test_foxglove_s_own_reader_decodes_every_message_of_the_live_recording(
    up_recording: tuple[Path, subprocess.CompletedProcess[str]],
) -> None:
    path, _ = up_recording
    got = read_in_foxglove(path)
    per_topic = got["per_topic"]
    estimators = {t.rsplit("/", 1)[1] for t, e in per_topic.items() if e["schema"] == "hil.NavSolution"}
    assert {"ekf15", "ins", "dut_navbox"} <= estimators
    want = expected_wellknown(estimators)
    assert {t: per_topic[t]["schema"] for t in want if t in per_topic} == want
    assert all(per_topic[t]["encoding"] == "protobuf" and per_topic[t]["decoded"] >= 1 for t in want)
    assert per_topic["/foxglove/fix/truth"]["decoded"] >= 0.9 * 10 * 10  # 10 Hz for 10 s
    # Foxglove's timeline is this run's wall clock (statuses of the start-up come before time zero)
    run = decode(RunInfo, read_session(path).by_topic("hil/itest/run")[0].payload)
    first, last = int(got["start_ns"]), int(got["end_ns"])
    assert run.start_epoch_ns - 300 * 10**9 < first < run.start_epoch_ns < last < path.stat().st_mtime_ns
    py = decode_wellknown(path)
    assert same_first_fix(per_topic["/foxglove/fix/truth"]["first"], py["/foxglove/fix/truth"][0][1])


def test_up_split_by_size_writes_parts_that_together_hold_the_session(tmp_path: Path) -> None:
    """``hil up --split-mb``: the recorder starts a new part at a flush once a part reaches the
    size; every part stands alone (run metadata, attachments, its completeness), and the parts
    end to end hold every message of every publisher once, in order -- so ``hil rerun`` of the
    first part, which follows the parts, reproduces the whole session bit for bit."""
    out = tmp_path / "split.mcap"
    proc = subprocess.run(
        hil_cmd(
            "up", "--duration", "6", "--record", str(out), "--quiet", "--rig", "splitup", "--split-mb", "0.3"
        ),
        capture_output=True,
        text=True,
        timeout=240,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    parts = [out, *split_parts(out)]
    assert len(parts) >= 2, proc.stdout[-2000:]
    assert "more part(s)" in proc.stdout
    seqs: dict[str, list[int]] = {}
    for n, part in enumerate(parts):
        s = read_session(part)
        assert not s.truncated and "hil" in s.metadata and "completeness" in s.metadata, part
        assert json.loads(s.metadata["completeness"]["part"]) == n
        assert any(name.startswith("scenario/") for name in s.attachments)
        for r in s.records:
            seqs.setdefault(r.topic, []).append(r.sequence)
    # no gap and no duplicate across the parts, per publisher; the last summary says so too
    for topic, got in seqs.items():
        assert got == list(range(got[0], got[0] + len(got))), topic
    assert len(seqs["hil/splitup/sensor/imu"]) >= 0.99 * 400 * 6
    last = read_session(parts[-1]).metadata["completeness"]
    assert json.loads(last["missing"]) == 0 and json.loads(last["replay_ready"]) is True
    rerun = subprocess.run(
        hil_cmd("rerun", str(out), "--verify"), capture_output=True, text=True, timeout=240, cwd=REPO
    )
    assert rerun.returncode == 0, rerun.stdout + rerun.stderr
    assert f"reran its {len(parts)} parts in order" in rerun.stdout and "VERIFY OK" in rerun.stdout


def test_batched_inputs_lose_nothing_and_rerun_bit_for_bit(tmp_path: Path) -> None:
    """``--input-batch-ms 10``: time sync and the fusion take inputs several per wake-up (their
    status counts them) and every input still reaches the fusion in its total order: the
    recording is complete and the fusion's rerun reproduces every output."""
    out = tmp_path / "batched.mcap"
    proc = subprocess.run(
        hil_cmd(
            "up",
            "--duration",
            "5",
            "--record",
            str(out),
            "--quiet",
            "--rig",
            "batched",
            "--input-batch-ms",
            "10",
        ),
        capture_output=True,
        text=True,
        timeout=240,
        cwd=REPO,
    )
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    s = read_session(out)
    assert json.loads(s.metadata["completeness"]["missing"]) == 0
    imu = s.by_topic("hil/batched/sensor/imu")
    assert {r.sequence for r in s.by_topic("hil/batched/synced/imu")} == {r.sequence for r in imu}
    assert len(s.by_topic("hil/batched/nav/ekf15")) > 0
    for service in ("timesync", "fusion"):
        last = decode(ServiceStatus, s.by_topic(f"hil/batched/status/{service}")[-1].payload)
        counters = last.counter_map()
        assert counters["in.batches"] > 0
        # 400 Hz of IMU samples into a 10 ms window: several inputs per wake-up, never one each
        assert counters["in.batched_inputs"] >= 2 * counters["in.batches"], counters
    # the IMU emulator (compute_batch_ms, default 20 ms) computes several ticks per wake-up and
    # publishes its capture truth in batches: one wake-up per tick and per output would be ~0.5;
    # every sample still left on the wire and every capture was published
    emu = decode(ServiceStatus, s.by_topic("hil/batched/status/imu_emulator")[-1].payload).counter_map()
    assert emu["paced.ticks"] >= 1.5 * emu["paced.wakeups"], emu
    assert {r.sequence for r in s.by_topic("hil/batched/capture/imu")} >= {r.sequence for r in imu}
    # the bridge's raw frames travel a sample's at a time (one batch, one arrival at the recorder)
    # and are recorded one message each, every seq present
    raw = s.by_topic("hil/batched/can/vcan0")
    seqs = sorted(r.sequence for r in raw)
    assert seqs == list(range(seqs[0], seqs[0] + len(seqs))) and len(raw) >= 4 * len(imu)
    assert len({r.log_time_ns for r in raw}) <= 0.5 * len(raw)
    rr = subprocess.run(
        hil_cmd("rerun", str(out), "--core", "fusion", "--verify"),
        capture_output=True,
        text=True,
        timeout=240,
        cwd=REPO,
    )
    assert rr.returncode == 0 and "VERIFY OK" in rr.stdout, rr.stdout + rr.stderr

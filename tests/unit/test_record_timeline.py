"""Wall-clock timelines: a recording's MCAP times are start epoch + rig time, its messages keep rig
time, and every reader takes recordings of both timelines (before: rig time in log_time)."""

from __future__ import annotations

from pathlib import Path

from hil.messages import RunInfo, Truth, decode
from hil.record.mcapio import EPOCH_FLOOR_NS, read_session, rig_time_ns
from hil.record.rerun import rerun
from tests.replay.helpers import LEGACY_GOLDEN

START_UTC_2026_NS = 1_767_225_600 * 10**9  # the default scenario start_utc, 2026-01-01T00:00:00Z


def test_sim_log_and_publish_times_are_the_start_epoch_plus_rig_time(sim_recording: Path) -> None:
    s = read_session(sim_recording)
    start = int(s.meta("hil", "start_epoch_ns"))
    assert start == START_UTC_2026_NS and s.meta("hil", "time_base") == "epoch"
    run = next(r for r in s.records if r.schema == "hil.RunInfo")
    assert decode(RunInfo, run.payload).start_epoch_ns == start and run.log_time_ns == start
    hil = [r for r in s.records if r.schema.startswith("hil.")]
    assert all(r.log_time_ns >= start for r in hil)
    for r in s.by_topic("hil/simrec/truth"):
        t = decode(Truth, r.payload)
        assert 0 <= t.stamp_ns < 4 * 10**9  # the message keeps rig (true) time ...
        assert r.publish_time_ns == start + t.stamp_ns == r.log_time_ns  # ... its record the epoch
        assert rig_time_ns(r.log_time_ns, start) == t.stamp_ns


def test_rig_time_of_a_recorded_time_reads_both_timelines() -> None:
    assert rig_time_ns(START_UTC_2026_NS + 5, START_UTC_2026_NS) == 5
    assert rig_time_ns(5, START_UTC_2026_NS) == 5  # a recording from before: already rig time
    assert rig_time_ns(5, 0) == 5
    s = read_session(LEGACY_GOLDEN)
    if s.meta("hil", "time_base") != "epoch":
        assert max(r.log_time_ns for r in s.records) < EPOCH_FLOOR_NS


def test_timesync_rerun_feeds_rig_time_on_both_timelines(sim_recording: Path) -> None:
    rc, lines = rerun(str(sim_recording), core="timesync", verify=True)
    assert rc == 0, lines
    assert "VERIFY OK" in lines[-1]
    # the legacy file (rig-time log times) reruns on the same clock: every measurement re-stamped.
    # Not verified bit for bit: its time sync ran before the start-up hold of issue 22.2.
    rc, lines = rerun(str(LEGACY_GOLDEN), core="timesync", verify=False)
    assert rc == 0, lines
    n = next(ln for ln in lines if ln.startswith("rerun timesync:"))
    raw, restamped = (
        n.split(" raw measurements")[0].split()[-1],
        n.split(" re-stamps recomputed")[0].split()[-1],
    )
    assert raw == restamped and int(raw) > 1000, n

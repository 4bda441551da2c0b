"""hil info / the summary hil sim and hil up print stream the recording: what they print equals
the whole-session functions' figures, and they never hold the messages (a 12000 s session read
whole took 18.9 GB at the end of hil sim)."""

from __future__ import annotations

import tracemalloc
from pathlib import Path

from hil.messages import CaptureTruth, encode
from hil.record.info import (
    Summary,
    channel_infos,
    describe,
    estimator_errors,
    foreign_summary,
    summarise,
)
from hil.record.mcapio import SessionWriter, iter_records, read_session

GOLDEN = Path(__file__).parents[1] / "replay" / "golden" / "straight_level_4s.mcap"


def test_one_pass_gives_the_whole_sessions_figures() -> None:
    session = read_session(GOLDEN)
    streamed = Summary()
    for kind, rec in iter_records(GOLDEN):
        if kind == "message":
            streamed.add(rec)
    whole = summarise(session.records)
    assert streamed.channel_infos() == whole.channel_infos() == channel_infos(session)
    assert streamed.estimator_errors() == estimator_errors(session)
    assert set(streamed.estimator_errors()) >= {"ekf15", "ins", "cf3"}
    assert streamed.foreign_summary() == foreign_summary(session)
    text = describe(str(GOLDEN))
    assert "hil/golden/sensor/imu" in text and "ekf15" in text


def _long_recording(path: Path, n: int) -> Path:
    """n capture-time messages on four topics: many chunks, as a long session is."""
    w = SessionWriter(path, spill_index=False)
    for i in range(n):
        msg = CaptureTruth(seq=i // 4, stamp_ns=i * 625_000, sensor="imu", true_stamp_ns=i * 625_000)
        t = 1_000_000_000 + i * 625_000
        w.write(
            f"hil/t/capture/imu{i % 4}",
            CaptureTruth,
            encode(msg),
            log_time_ns=t,
            publish_time_ns=t,
            seq=i // 4,
        )
    w.close()
    return path


def test_describe_holds_a_fraction_of_what_reading_the_session_whole_does(tmp_path: Path) -> None:
    path = _long_recording(tmp_path / "long.mcap", 100_000)
    describe(str(GOLDEN))  # imports and decoder caches are not the file's
    tracemalloc.start()
    try:
        text = describe(str(path))
        _, streamed_peak = tracemalloc.get_traced_memory()
        tracemalloc.reset_peak()
        whole = read_session(path, derived=True)
        _, whole_peak = tracemalloc.get_traced_memory()
    finally:
        tracemalloc.stop()
    assert len(whole.records) == 100_000 and "hil/t/capture/imu3" in text
    assert streamed_peak < whole_peak / 5, (streamed_peak, whole_peak)


def test_large_figures_keep_their_columns_apart(tmp_path: Path) -> None:
    """A free INS over hours drifts by 10⁶ m: its errors printed as ``863771.752275713.02...``
    ran together. Every row of both tables splits into its columns."""
    from hil.messages import NavSolution, Truth

    w = SessionWriter(tmp_path / "drift.mcap", spill_index=False)
    zero, q = [0.0, 0.0, 0.0], [1.0, 0.0, 0.0, 0.0]
    for i in range(20):
        t = 1_000_000_000 * (i + 1)
        truth = Truth(
            seq=i, stamp_ns=t, lat_deg=50.0, lon_deg=30.0, alt_m=0.0, pos_ned_m=zero,
            vel_ned_mps=zero, q_nb=q, f_b_mps2=zero, w_ib_b_radps=zero,
        )  # fmt: skip
        nav = NavSolution(
            seq=i, stamp_ns=t, estimator="ins", pos_ned_m=[1.0e6 * (i + 1), 2.5e6, 0.0],
            vel_ned_mps=zero, q_nb=q, lat_deg=50.0, lon_deg=30.0, alt_m=0.0,
        )  # fmt: skip
        for key, cls, msg in (
            ("hil/t/truth", Truth, truth),
            ("hil/t/a_very_long_topic_name_of_a_nav/ins", NavSolution, nav),
        ):
            w.write(key, cls, encode(msg), log_time_ns=t, publish_time_ns=t, seq=i)
    w.close()
    lines = describe(str(tmp_path / "drift.mcap")).splitlines()
    head = lines.index(next(x for x in lines if x.startswith("topic")))
    rows = lines[head + 1 : lines.index("", head)]
    assert len(rows) == 2 and all(len(r.split()) == 6 for r in rows), rows
    ins = next(x for x in lines if x.startswith("ins "))
    rms, p95, top, final = (float(v) for v in ins.split()[1:])
    assert top == final > 2.0e7 and rms > 1.0e7 and p95 > 1.0e7

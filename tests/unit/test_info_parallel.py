"""``hil info`` reads a large file in two halves at once: the figures are those of one pass."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import numpy as np
import pytest

from hil.messages import SEQ_GENERATION_SHIFT, CaptureTruth, EstimatorHealth, encode
from hil.record import info
from hil.record.completeness import SeqTracker
from hil.record.info import Summary, _scan, _scan_halves, _SeqRuns, describe, info_json, last_fusion_status
from hil.record.mcapio import DamagedRecordingError, SessionWriter, file_halves, iter_records, session_files
from hil.runners.sim_worker import worker_possible

GOLDEN = Path(__file__).parents[1] / "replay" / "golden" / "straight_level_4s.mcap"


def _stream(seed: int) -> list[int]:
    """A publisher's seqs as a bus may deliver them: runs, gaps, repeats, late ones, restarts,
    forged far-ahead ones and a generation that does not start near 0."""
    g = np.random.default_rng(seed)
    out, seq, gen = [], int(g.integers(0, 50)), 0
    for _ in range(400):
        what = g.random()
        if what < 0.55:
            n = int(g.integers(1, 40))
            out += [(gen << SEQ_GENERATION_SHIFT) + seq + k for k in range(n)]
            seq += n
        elif what < 0.7:
            seq += int(g.integers(1, 20))  # a gap
        elif what < 0.8 and out:
            out.append(out[-int(g.integers(1, min(len(out), 30) + 1))])  # a repeat or a late one
        elif what < 0.85:
            gen, seq = gen + 1, int(g.integers(0, 5))  # a restart
        elif what < 0.9:
            out.append((gen << SEQ_GENERATION_SHIFT) + seq + 10**6)  # forged, far ahead
        elif what < 0.93:
            out.append(((gen + 3) << SEQ_GENERATION_SHIFT) + 10**6)  # a "generation" not near 0
        else:
            out.append(max(0, seq - int(g.integers(1, 60))))  # an old one, maybe of generation 0
    return out


@pytest.mark.parametrize("seed", range(12))
def test_runs_counted_after_a_first_part_give_one_pass_figures(seed: int) -> None:
    seqs = _stream(seed)
    for cut in (0, len(seqs) // 3, len(seqs) // 2, len(seqs) - 1):
        one = SeqTracker()
        for s in seqs:
            one.see(s)
        split, runs = SeqTracker(), _SeqRuns()
        for s in seqs[:cut]:
            split.see(s)
        for s in seqs[cut:]:
            runs.see("t", s)
        for first, n in runs.topics.get("t", []):
            split.see_run(first, n)
        assert split.summary() == one.summary(), (seed, cut)
        assert split.count == len(seqs)


_MIXED_SEQS = [*range(0, 900), *range(950, 1800), *((1 << 32) + k for k in range(3, 700)), 40, 2000]


def _no_fallback(*args: object, **kwargs: object) -> None:
    raise AssertionError("the two halves fell back to one pass")


def _mixed(path: Path) -> Path:
    """A file of many small chunks: gaps, a restart, a foreign publisher, metadata at the end."""
    w = SessionWriter(path, chunk_size=4096, spill_index=False)
    for i, seq in enumerate(_MIXED_SEQS):
        t = 1_000_000_000 + i * 2_500_000
        data = encode(CaptureTruth(seq=seq, stamp_ns=t, sensor="imu", true_stamp_ns=t))
        senders = [("aa", "rig", seq), ("ff", "foreign", i)] if i % 11 == 0 else [("aa", "rig", seq)]
        for who, origin, n in senders:
            kw = {"log_time_ns": t, "publish_time_ns": t, "seq": n, "publisher": who, "origin": origin}
            w.write("hil/t/capture/imu", CaptureTruth, data, **kw)  # type: ignore[arg-type]
        if i == 2000:  # a topic that first appears in the second half
            health = EstimatorHealth(seq=0, stamp_ns=t, estimator="ekf15")
            w.write(
                "hil/t/health/ekf15", EstimatorHealth, encode(health), log_time_ns=t, publish_time_ns=t, seq=0
            )
    w.add_metadata("completeness", {"missing": "50", "replay_ready": "true"})
    w.close()
    return path


@pytest.mark.skipif(not worker_possible(), reason="needs fork and two CPUs")
@pytest.mark.parametrize("make", ["golden", "mixed"])
def test_two_halves_give_the_one_pass_text_and_json(
    tmp_path: Path, make: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    path = GOLDEN if make == "golden" else _mixed(tmp_path / "mixed.mcap")
    halves = file_halves(path)
    assert halves is not None and 0 < halves[1].start < path.stat().st_size
    for derived in (True, False):
        one, s1 = _scan(path, derived=derived, accuracy=True)
        with monkeypatch.context() as m:  # the halves themselves, not the one pass they fall back to
            m.setattr(info, "_scan", _no_fallback)
            two, s2 = _scan_halves(path, halves, derived=derived, accuracy=True)
        assert two.channel_infos() == one.channel_infos()
        assert two.foreign_summary() == one.foreign_summary()
        assert two.estimator_errors() == one.estimator_errors()
        assert {t: tr.summary() for t, tr in two.comp.topics.items()} == {
            t: tr.summary() for t, tr in one.comp.topics.items()
        }
        assert (s2.metadata, s2.attachments, s2.truncated) == (s1.metadata, s1.attachments, s1.truncated)
    if make == "mixed":
        (imu,) = [c for c in one.channel_infos() if c.topic.endswith("capture/imu")]
        assert (imu.missing, imu.restarts) == (
            50 + 200,
            1,
        )  # 900-949, then 1800-1999 (2000 after the restart)
        assert two.comp.topics[imu.topic].out_of_order == 1  # 40 of the first generation, late
        assert any(c.topic.endswith("health/ekf15") for c in two.channel_infos())


@pytest.mark.skipif(not worker_possible(), reason="needs fork and two CPUs")
@pytest.mark.parametrize("where", ["first half", "second half", "second half's start"])
def test_damage_in_either_half_is_the_one_pass_error(
    tmp_path: Path, where: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A finished file damaged anywhere is corrupt, not truncated: both readings raise the one
    line one pass raises (the file, the damaged record's byte), and neither falls back."""
    path = _mixed(tmp_path / "damaged.mcap")
    halves = file_halves(path)
    assert halves is not None
    data = bytearray(path.read_bytes())
    mid = halves[1].start
    at = {
        "first half": mid // 2,
        "second half": mid + (len(data) - mid) // 3,
        "second half's start": mid + 40,
    }[where]
    data[at : at + 64] = b"\xff" * 64
    path.write_bytes(bytes(data))
    with pytest.raises(DamagedRecordingError) as one:
        _scan(path, derived=True, accuracy=True)
    monkeypatch.setattr(info, "_scan", _no_fallback)
    with pytest.raises(DamagedRecordingError) as two:
        _scan_halves(path, halves, derived=True, accuracy=True)
    assert str(two.value) == str(one.value)
    assert f"{path} is damaged at byte " in str(one.value) and "hil recover" in str(one.value)
    offset = int(str(one.value).split(" at byte ")[1].split()[0])
    assert offset < at + 64 and (offset < mid) is (where == "first half")  # at the damage or after


@pytest.mark.skipif(not worker_possible(), reason="needs fork and two CPUs")
def test_a_flipped_bit_in_either_half_fails_its_chunk_crc(tmp_path: Path) -> None:
    """One bit of a chunk's compressed bytes: the chunk still decompresses or not, but never reads."""
    path = _mixed(tmp_path / "bit.mcap")
    halves = file_halves(path)
    assert halves is not None
    clean = path.read_bytes()
    for at in (halves[1].start // 2, halves[1].start + 200):
        data = bytearray(clean)
        data[at] ^= 1
        path.write_bytes(bytes(data))
        with pytest.raises(DamagedRecordingError, match="damaged at byte"):
            _scan_halves(path, halves, derived=True, accuracy=True)


def test_a_small_file_is_read_in_one_pass_and_says_the_same(tmp_path: Path) -> None:
    path = _mixed(tmp_path / "small.mcap")
    assert describe(str(path), parallel=True) == describe(str(path))
    assert info_json(str(path), parallel=True) == info_json(str(path))


def test_a_run_never_crosses_into_the_next_generation() -> None:
    """Consecutive numbers across 2**32 are two generations' seqs: two runs, counted as
    one pass counts them."""
    top = 1 << SEQ_GENERATION_SHIFT
    seqs = [*range(top - 5, top + 3)]
    one, split, runs = SeqTracker(), SeqTracker(), _SeqRuns()
    for s in seqs:
        one.see(s)
        runs.see("t", s)
    assert runs.topics["t"] == [[top - 5, 5], [top, 3]]
    for first, n in runs.topics["t"]:
        split.see_run(first, n)
    assert split.summary() == one.summary()


def test_a_chunk_at_once_gives_what_one_message_at_a_time_gives(tmp_path: Path) -> None:
    """``describe`` takes a chunk's records in one call (``stream_session(on_batch=)``): the
    rig's gaps, a restart and a foreign publisher's messages count as they do one by one."""
    path = _mixed(tmp_path / "mixed.mcap")
    batched, _ = _scan(path, derived=False, accuracy=True)
    one_by_one = Summary()
    for kind, rec in iter_records(path):
        if kind == "message":
            one_by_one.add(rec)
    assert batched.channel_infos() == one_by_one.channel_infos()
    assert batched.foreign_summary() == one_by_one.foreign_summary()
    imu = next(c for c in batched.channel_infos() if c.topic.endswith("capture/imu"))
    assert (imu.count, imu.missing, imu.restarts) == (len(_MIXED_SEQS), 250, 1)
    assert batched.foreign_summary()["messages"] == len(range(0, len(_MIXED_SEQS), 11))


@pytest.mark.parametrize(("late", "says"), [(3001, True), (5, False), (0, False)])
def test_a_fusion_that_refused_much_of_its_imu_input_is_said(tmp_path: Path, late: int, says: bool) -> None:
    """A clock step put the IMU samples 100 s ahead and the fusion refused the rest of the run
    as late (3001 of ~3200): every service stayed up, hil info and hil sim's summary said
    nothing. The fusion's last status counts it; a tenth or more of the IMU input is a line, and
    a failing for the exit code of hil up."""
    from hil.messages import Count

    path = tmp_path / "s.mcap"
    w = SessionWriter(path, spill_index=False)
    for i, n in enumerate((0, late)):
        _write_fusion_status(w, i, [Count("dropped_late.imu", n), Count("consumed", 215 * (i + 1) * 4)])
    w.close()
    failings: list[str] = []
    lines = [ln for ln in describe(str(path), verdicts=failings).splitlines() if ln.startswith("fusion:")]
    assert (
        (lines == [lines[0]] and f"refused {late} IMU samples as late" in lines[0]) if says else not lines
    ), lines
    # what hil up prints as FAILED (and exits 1 for): the same finding
    assert failings == (
        [f"the fusion refused {late} IMU samples as late" + lines[0].split("as late", 1)[1]] if says else []
    )


@pytest.mark.parametrize(("late", "says"), [(170, True), (19, False), (0, False)])
def test_a_fusion_that_refused_its_gnss_fixes_as_late_is_said(tmp_path: Path, late: int, says: bool) -> None:
    """--fusion-lag below the receiver's latency: 170 of 199 fixes refused, every estimator
    coasting, and hil info said nothing (QA). A tenth or more of the fixes handed to the fusion
    (inputs.gnss) is a line naming the source and a failing; an outage (fewer fixes) is not."""
    from hil.messages import Count, ServiceStatus

    path = tmp_path / "s.mcap"
    counters = [
        Count("dropped_late.gnss", late),
        Count("consumed", 8000 + 199 - late),
        Count("horizon_lag_ms", 1),
        Count("inputs.gnss", 199),
        Count("inputs.imu", 8000),
    ]
    st = ServiceStatus(
        seq=0, stamp_ns=0, service="fusion", state="running", pid=1, uptime_s=0, counters=counters
    )
    w = SessionWriter(path, spill_index=False)
    w.write("hil/bench/status/fusion", ServiceStatus, encode(st), log_time_ns=0, publish_time_ns=0, seq=0)
    w.close()
    failings: list[str] = []
    lines = [ln for ln in describe(str(path), verdicts=failings).splitlines() if ln.startswith("fusion:")]
    said = f"fusion:    refused {late} of its 199 GNSS fixes as late (dropped_late.gnss): they reached it more than its lag (1 ms"
    assert [ln.startswith(said) for ln in lines] == ([True] if says else [])
    assert failings == ["the fusion " + ln.removeprefix("fusion:    ") for ln in lines]


def _write_fusion_status(w: SessionWriter, i: int, counters: list[Any]) -> None:
    """The fusion's status number ``i`` (at ``i`` s) with ``counters``, written to ``w``."""
    from hil.messages import ServiceStatus

    st = ServiceStatus(
        seq=i, stamp_ns=i * 10**9, service="fusion", state="running", pid=1, uptime_s=i, counters=counters
    )
    t = i * 10**9
    w.write("hil/bench/status/fusion", ServiceStatus, encode(st), log_time_ns=t, publish_time_ns=t, seq=i)


def _fusion_part(path: Path, index: int, statuses: list[tuple[int, int]], first_s: int) -> None:
    """A file of a split session (``index`` 0: its first) holding the fusion's statuses, each
    ``(dropped_late.imu, consumed)``, once a second from ``first_s``: the counters count from the
    fusion's start, whichever file the recorder writes them to."""
    from hil.messages import Count
    from hil.record.mcapio import part_metadata, split_part_path

    w = SessionWriter(path, spill_index=False)
    if index:
        w.add_metadata(
            "part", {"index": index, **part_metadata(split_part_path(path.parent / "s.mcap", index - 1))}
        )
    for k, (late, consumed) in enumerate(statuses):
        _write_fusion_status(w, first_s + k, [Count("dropped_late.imu", late), Count("consumed", consumed)])
    w.close()


def _split_session(tmp_path: Path, parts: list[list[tuple[int, int]]]) -> list[Path]:
    from hil.record.mcapio import split_part_path

    first = tmp_path / "s.mcap"
    files = [split_part_path(first, k) for k in range(len(parts))]
    n = 0
    for k, (path, statuses) in enumerate(zip(files, parts, strict=True)):
        _fusion_part(path, k, statuses, n)
        n += len(statuses)
    assert session_files(first) == files
    return files


def test_a_split_sessions_verdict_is_its_last_fusion_status_wherever_it_is(tmp_path: Path) -> None:
    """hil up --split-s judged the exit code on the first part's fusion counters only (QA): a
    run that refused 1200 of its last part's IMU samples (14.6 % by the end) exited 0, and one
    that refused 800 early on (3.3 % of the whole run) exited 1. The counters count from the
    fusion's start: the session's last status is the run's, and the first file, which stands
    for the run (hil up describes it, its exit code from what that finds), says it."""
    late = _split_session(
        tmp_path,
        [
            [(0, 400 * i) for i in range(1, 11)],
            [(0, 4000 + 400 * i) for i in range(1, 11)],
            [(0, 8000), (1200, 6999)],
        ],
    )
    found = last_fusion_status(late)
    assert found is not None and found[1] == late[2]
    failings: list[str] = []
    lines = [ln for ln in describe(str(late[0]), verdicts=failings).splitlines() if ln.startswith("fusion:")]
    assert lines == [
        "fusion:    refused 1200 IMU samples as late (dropped_late.imu) and took 6999 inputs: its horizon ran "
        "ahead of their stamps, so its solutions thin out or stop; event/fusion says when "
        "(latency_over_bound) (the session's last fusion status, in s_0002.mcap)"
    ]
    where = " (the session's last fusion status, in s_0002.mcap)"
    assert failings == ["the fusion " + lines[0].removeprefix("fusion:    ").removesuffix(where)]
    # the last part itself: its own status, the same finding
    assert "fusion:    refused 1200 IMU samples as late" in describe(str(late[2]))
    # a middle part: its counters as they stood at its end (nothing refused by then)
    assert "fusion:" not in describe(str(late[1]))


def test_a_split_session_that_refused_early_and_recovered_is_no_failure(tmp_path: Path) -> None:
    """800 IMU samples refused in the first 10 s (16 % of the first part), 800 of 24599 (3.3 %)
    by the end: the first file's own status says refused, the session's does not."""
    parts = [[(800, 400 * i) for i in range(1, 11)]] + [
        [(800, 4000 + 4000 * k + 400 * i) for i in range(1, 11)] for k in range(4)
    ]
    parts.append([(800, 23799)])
    early = _split_session(tmp_path, parts)
    assert _scan(early[0], derived=False, accuracy=True)[0].fusion_refusals() != []  # its own
    failings: list[str] = []
    text = describe(str(early[0]), verdicts=failings)
    assert "fusion:" not in text and failings == []


def test_the_last_fusion_status_is_taken_from_the_last_file_that_has_one(tmp_path: Path) -> None:
    """A last part too short to hold a status (the recorder rotated just before the end): the one
    before it has the session's last."""
    files = _split_session(tmp_path, [[(0, 400), (0, 800)], [(500, 1200), (1500, 1300)], []])
    found = last_fusion_status(files)
    assert found is not None and found[1] == files[1]
    failings: list[str] = []
    describe(str(files[0]), verdicts=failings)
    assert [f.split(" and took")[0] for f in failings] == [
        "the fusion refused 1500 IMU samples as late (dropped_late.imu)"
    ]
    assert last_fusion_status(files[2:]) is None


@pytest.mark.skipif(not worker_possible(), reason="needs fork and two CPUs")
@pytest.mark.parametrize("where", [500, 3000])
def test_a_payload_that_does_not_decode_is_the_same_line_from_either_half(
    tmp_path: Path, where: int, monkeypatch: pytest.MonkeyPatch
) -> None:
    """A truth message cut in half, in the first or the second half of a file read in two: the
    forked reader's error is the one line one pass gives (file, topic, seq, log time)."""
    from hil.messages import Truth
    from hil.record.mcapio import PayloadError

    path = tmp_path / "bad.mcap"
    w = SessionWriter(path, chunk_size=4096, spill_index=False)
    for i in range(4000):
        t = 1_000_000_000 + i * 2_500_000
        data = encode(
            Truth(
                seq=i,
                stamp_ns=t,
                lat_deg=50.0,
                lon_deg=30.0,
                alt_m=10.0,
                pos_ned_m=[0.0, 0.0, 0.0],
                vel_ned_mps=[0.0, 0.0, 0.0],
                q_nb=[1.0, 0.0, 0.0, 0.0],
                f_b_mps2=[0.0, 0.0, -9.8],
                w_ib_b_radps=[0.0, 0.0, 0.0],
            )
        )
        w.write(
            "hil/t/truth",
            Truth,
            data[: len(data) // 2] if i == where else data,
            log_time_ns=t,
            publish_time_ns=t,
            seq=i,
        )
    w.close()
    halves = file_halves(path)
    assert halves is not None
    with pytest.raises(PayloadError) as one:
        _scan(path, derived=True, accuracy=True)
    monkeypatch.setattr(info, "_scan", _no_fallback)
    with pytest.raises(PayloadError) as two:
        _scan_halves(path, halves, derived=True, accuracy=True)
    assert str(two.value) == str(one.value) and f"hil/t/truth seq {where} " in str(one.value)

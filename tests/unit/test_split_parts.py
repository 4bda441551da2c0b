"""A split recording's parts are followed only where each one continues the file before it: a new
recording at the same path leaves an earlier, longer one's parts on disk (nothing is deleted), and
neither a reader nor ``hil rerun --verify`` takes them for its own.

Found 2026-12-06: ``hil sim --split-s 2`` for 6 s, then for 1.5 s at the same path, left
``run_0001..0003`` beside the new ``run.mcap``; ``hil rerun --verify`` reran all four files as one
session and failed with a misleading loss note.
"""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from hil.record.export import export
from hil.record.info import describe, info_json
from hil.record.mcapio import (
    RecordingError,
    SessionStream,
    SessionWriter,
    aside_path,
    keep_aside,
    made_by_sim,
    session_files,
    session_note,
    split_part_path,
    split_parts,
    stale_parts,
)
from hil.record.replay import ReplayStats, _messages, recorded_span_ns
from hil.record.rerun import rerun, rerun_fusion_file, rerun_fusion_records
from hil.report.data import load as load_report
from hil.runners.sim import SimOptions, run_sim
from tests.conftest import run_hil


def _verified(path: Path) -> int:
    """How many recorded outputs the rerun of ``path`` (and the parts it follows) verified."""
    result, _stream, _note = rerun_fusion_file(path, worker=False)
    assert result.difference is None and result.n_recorded == result.n_recomputed > 0, result.difference
    return result.n_recorded


def _sim(path: Path, duration_s: float) -> None:
    run_sim(SimOptions(duration_s=duration_s, record=path, split_s=1.5, fusion_worker=False))


def test_a_shorter_recording_at_the_same_path_does_not_take_the_longer_ones_parts(tmp_path: Path) -> None:
    rec = tmp_path / "run.mcap"
    _sim(rec, 4.0)
    old = split_parts(rec)
    assert [p.name for p in old] == ["run_0001.mcap", "run_0002.mcap"]
    before = {p: p.read_bytes() for p in old}
    n_long = _verified(rec)  # a session of three parts, as written

    # WHEN a 2 s run writes run.mcap and run_0001.mcap again (over the old ones)
    _sim(rec, 2.0)
    # THEN its own part is followed and the old run_0002 is not, though it is still there
    assert split_parts(rec) == [split_part_path(rec, 1)]
    assert split_part_path(rec, 2).read_bytes() == before[split_part_path(rec, 2)]
    assert split_part_path(rec, 1).read_bytes() != before[split_part_path(rec, 1)]
    whole = list(SessionStream(rec, follow_parts=True))
    assert max(r.log_time_ns for r in whole) - min(r.log_time_ns for r in whole) < 2.2e9
    assert _verified(rec) < n_long

    # WHEN a 1 s run fits in one file: nothing follows it
    _sim(rec, 1.0)
    assert split_parts(rec) == []
    _verified(rec)
    assert stale_parts(rec) == [split_part_path(rec, 1), split_part_path(rec, 2)]


def test_hil_sim_says_which_files_an_earlier_recording_left(tmp_path: Path) -> None:
    rec = tmp_path / "run.mcap"
    _sim(rec, 4.0)
    proc = run_hil("sim", "--duration", "1", "--record", str(rec), "--quiet", timeout=120)
    assert proc.returncode == 0, proc.stderr
    warn = [ln for ln in proc.stderr.splitlines() if "warning" in ln]
    assert len(warn) == 1 and "run_0001.mcap .. run_0002.mcap" in warn[0] and "remove them" in warn[0]
    proc = run_hil("rerun", str(rec), "--verify", timeout=120)
    assert proc.returncode == 0 and "VERIFY OK" in proc.stdout and "split" not in proc.stdout, proc.stdout


def _file(path: Path, part: dict[str, object] | None, filler: int = 0) -> None:
    w = SessionWriter(path)
    if part is not None:
        w.add_metadata("part", part)
    w.add_metadata("filler", {"x": "y" * filler})
    w.close()


def test_a_part_is_followed_on_the_size_it_names_or_on_its_name_alone(tmp_path: Path) -> None:
    rec = tmp_path / "s.mcap"
    _file(rec, None, filler=100)
    size = rec.stat().st_size
    first = split_part_path(rec, 1)
    _file(first, {"index": 1, "previous": rec.name, "previous_bytes": size})
    assert split_parts(rec) == [first]
    _file(first, {"index": 1, "previous": rec.name, "previous_bytes": size + 1})
    assert split_parts(rec) == []
    # a part from before the size was recorded: taken on its name, as it always was
    _file(first, {"index": 1, "previous": rec.name})
    _file(split_part_path(rec, 2), {"index": 2, "previous": first.name})
    assert split_parts(rec) == [first, split_part_path(rec, 2)]
    # an unreadable part is taken on its name too: the reading then says what is wrong with it
    first.write_bytes(b"not an mcap file")
    assert split_parts(rec)[:1] == [first]


@pytest.fixture(scope="module")
def split_and_whole(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, Path]:
    """The same 4 s sim recorded in three parts and in one file."""
    d = tmp_path_factory.mktemp("parts")
    split, whole = d / "split.mcap", d / "whole.mcap"
    _sim(split, 4.0)
    run_sim(SimOptions(duration_s=4.0, record=whole, fusion_worker=False))
    assert len(split_parts(split)) == 2 and split_parts(whole) == []
    return split, whole


def test_replay_reads_a_split_recording_as_the_session(split_and_whole: tuple[Path, Path]) -> None:
    split, whole = split_and_whole

    def sent(path: Path) -> list[tuple[str, int, bytes]]:
        stats = ReplayStats()
        return [(r.topic, r.log_time_ns, r.payload) for r in _messages(path, stats)]

    assert sent(split) == sent(whole)
    assert recorded_span_ns(split) == recorded_span_ns(whole) > 3.9e9
    assert session_files(split) == [split, *split_parts(split)]
    note = session_note(session_files(split), "replayed")
    assert note is not None and "replayed its 3 parts" in ReplayStats(session=note).summary()
    assert "split" not in ReplayStats().summary()


def test_report_and_export_read_a_split_recording_as_the_session(
    split_and_whole: tuple[Path, Path], tmp_path: Path
) -> None:
    split, whole = split_and_whole
    a, b = load_report(split), load_report(whole)
    assert a.messages == b.messages > 10_000
    assert a.truth is not None and b.truth is not None and a.truth.n == b.truth.n
    assert {k: v.n for k, v in a.nav.items()} == {k: v.n for k, v in b.nav.items()}
    assert any("3 parts" in n for n in a.notes) and not any("parts" in n for n in b.notes)
    tables_a, notes_a = export(split, tmp_path / "a")
    tables_b, notes_b = export(whole, tmp_path / "b")
    assert sorted(tables_a) == sorted(tables_b)
    for topic, (path, rows) in tables_a.items():  # the same tables, byte for byte
        assert rows == tables_b[topic][1] > 0 and path.read_bytes() == tables_b[topic][0].read_bytes(), topic
    assert notes_a[0].endswith("exported its 3 parts in order") and not notes_b


def test_a_rerun_of_a_later_part_names_the_first_file(split_and_whole: tuple[Path, Path]) -> None:
    split, _whole = split_and_whole
    for n, part in enumerate(split_parts(split), start=1):
        with pytest.raises(RecordingError) as err:
            rerun_fusion_file(part, worker=False)
        assert f"part {n} of a split recording" in str(err.value) and f"rerun {split}," in str(err.value)
        # as a campaign's rerun reads it: records through a generator, the file known by name only
        with pytest.raises(RecordingError) as err:
            rerun_fusion_records(iter(SessionStream(part)), window_ns=None, name=str(part))
        assert f"part {n} of a split recording" in str(err.value), str(err.value)


def test_hil_info_says_where_a_file_stands_in_a_split_recording(split_and_whole: tuple[Path, Path]) -> None:
    split, whole = split_and_whole
    first = describe(str(split))
    assert "parts:     the session continues in 2 more part(s): split_0001.mcap, split_0002.mcap" in first
    later = describe(str(split_part_path(split, 2)))
    assert "parts:     part 2 of a split recording, after split_0001.mcap" in later
    assert "parts:" not in describe(str(whole))
    assert json.loads(info_json(str(split)))["parts"] == ["split_0001.mcap", "split_0002.mcap"]
    assert json.loads(info_json(str(whole)))["parts"] == []


def test_keep_aside_moves_a_recording_and_its_parts_to_the_next_free_name(tmp_path: Path) -> None:
    rec = tmp_path / "s.mcap"
    _sim(rec, 4.0)
    files = [rec, *split_parts(rec)]
    before = [f.read_bytes() for f in files]
    # a part of something older, which does not continue this session: it stays
    _file(split_part_path(rec, 3), {"index": 3, "previous": "s_0002.mcap", "previous_bytes": 1})
    (tmp_path / "s.1.mcap").write_bytes(b"")  # a name taken: the next one is used
    assert aside_path(rec, 2) == tmp_path / "s.2.mcap"
    kept = keep_aside(rec)
    assert kept == tmp_path / "s.2.mcap" and not rec.exists()
    assert [f.read_bytes() for f in [kept, *split_parts(kept)]] == before  # one session there still
    assert split_part_path(rec, 3).exists() and not split_part_path(rec, 1).exists()
    rec.write_bytes(b"")
    assert keep_aside(rec) is None and rec.exists()  # an empty file is nothing to keep
    assert keep_aside(tmp_path / "none.mcap") is None


def test_hil_up_keeps_an_earlier_recording_and_its_logs_before_the_run(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    from hil.cli import _keep_earlier_recording

    rec = tmp_path / "s.mcap"
    _sim(rec, 4.0)
    files = [rec, *split_parts(rec)]
    before = [f.read_bytes() for f in files]
    _file(split_part_path(rec, 3), {"index": 3, "previous": "x", "previous_bytes": 1})
    (tmp_path / "s.logs").mkdir()
    (tmp_path / "s.logs" / "fusion.log").write_text("the earlier run's log\n")
    _keep_earlier_recording(rec)
    kept = tmp_path / "s.1.mcap"
    err = capsys.readouterr().err.splitlines()
    assert (
        err[0]
        == f"hil up: {rec} held an earlier recording: kept as {kept} with its 2 later file(s) (its logs as "
        "s.1.logs), not written over"
    )
    assert err[1].startswith("hil up: warning: s_0003.mcap beside") and len(err) == 2
    assert [f.read_bytes() for f in session_files(kept)] == before  # one session there still
    assert (tmp_path / "s.1.logs" / "fusion.log").read_text() == "the earlier run's log\n"
    assert not rec.exists() and not (tmp_path / "s.logs").exists()
    _keep_earlier_recording(rec)  # nothing there now: nothing said but the stale part
    assert capsys.readouterr().err.count("\n") == 1


def test_hil_sim_writes_over_a_sims_file_only(tmp_path: Path) -> None:
    """A sim, finished or cut off, is made again from its options; a live session, or anything
    else at the path, is kept (``made_by_sim``), by the sim runner itself."""
    said: list[str] = []

    def sim_at(path: Path) -> None:
        run_sim(SimOptions(duration_s=1.0, record=path, fusion_worker=False, on_warning=said.append))

    sim = tmp_path / "sim.mcap"
    sim_at(sim)
    cut = tmp_path / "cut.mcap"
    cut.write_bytes(sim.read_bytes()[: sim.stat().st_size // 2])
    assert made_by_sim(sim) and made_by_sim(cut)
    for path in (sim, cut):
        sim_at(path)
        assert not path.with_name(f"{path.stem}.1.mcap").exists() and not said, said
    live = tmp_path / "live.mcap"
    w = SessionWriter(live)
    w.add_metadata("hil", {"rig": "bench", "executor": "live"})
    w.close()
    other = tmp_path / "notes.txt"
    other.write_text("not a recording\n")
    for path in (live, other):
        before = path.read_bytes()
        assert not made_by_sim(path)
        sim_at(path)
        kept = path.with_name(f"{path.stem}.1{path.suffix}")
        assert kept.read_bytes() == before and made_by_sim(path), path
        assert (
            said.pop() == f"{path} held a recording that no sim makes again (a live session?): kept as {kept}"
        )


def _sim_rig(path: Path, rig: str) -> None:
    run_sim(SimOptions(duration_s=0.5, record=path, rig=rig, fusion_worker=False))


def test_a_restarted_recorders_file_is_followed_only_for_its_own_run_and_moves_with_it(
    tmp_path: Path,
) -> None:
    # GIVEN a recording, and at its restarted recorder's name (<stem>.part1.mcap) another run's file
    first = tmp_path / "s.mcap"
    _sim_rig(first, "one")
    part = tmp_path / "s.part1.mcap"
    _sim_rig(tmp_path / "other.mcap", "two")
    (tmp_path / "other.mcap").rename(part)
    # THEN it is not this session's: a part an earlier session left there is not read as this one's
    assert session_files(first) == [first]
    # WHEN the file there records the same run (rig and start epoch: a restarted recorder's)
    _sim_rig(tmp_path / "same.mcap", "one")
    (tmp_path / "same.mcap").rename(part)
    # THEN the session's readers go on into it, and say so
    assert session_files(first) == [first, part]
    note = session_note(session_files(first), "read")
    assert (
        note
        == "the session is in 2 files, continued by a restarted recorder in s.part1.mcap: read them in order"
    )
    assert "(a restarted recorder's): s.part1.mcap" in describe(str(first))
    assert "continuing the session begun in s.mcap" in describe(str(part))
    # ... a rerun of the part alone points to the first file (it has neither run nor configuration)
    rc, lines = rerun(str(part), verify=True)
    assert rc == 2 and lines == [
        f"hil rerun: {part} is a later file of the session that begins in {first}: rerun that file, "
        "which reads the whole session in order"
    ]
    # ... the first file cut short (its recorder killed) reads as cut, not as the session's end
    whole = first.read_bytes()
    first.write_bytes(whole[: len(whole) * 2 // 3])
    said = describe(str(first))
    assert "CUT SHORT: read up to the last complete chunk" in said and "continues in s.part1.mcap" in said
    assert "TRUNCATED" not in said and "session:   missing=0 replay_ready=true over all 2 files" in said
    first.write_bytes(whole)
    # ... and a new recording at the path moves it aside with the first file
    kept = keep_aside(first)
    assert kept == tmp_path / "s.1.mcap" and not part.exists()
    assert session_files(kept) == [kept, tmp_path / "s.1.part1.mcap"]

"""A split recording's parts are followed only where each one continues the file before it: a new
recording at the same path leaves an earlier, longer one's parts on disk (nothing is deleted), and
neither a reader nor ``hil rerun --verify`` takes them for its own.

Found 2026-12-06: ``hil sim --split-s 2`` for 6 s, then for 1.5 s at the same path, left
``run_0001..0003`` beside the new ``run.mcap``; ``hil rerun --verify`` reran all four files as one
session and failed with a misleading loss note.
"""

from __future__ import annotations

from pathlib import Path

from hil.record.mcapio import SessionStream, SessionWriter, split_part_path, split_parts, stale_parts
from hil.record.rerun import rerun_fusion_file
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

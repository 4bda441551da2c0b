"""What ``hil rerun`` and ``hil export`` say of a recording that lacks what they need because it was
recorded or cut that way, not because a message was lost.

Found by QA: a sim recorded with ``--record-exclude 'synced/**'`` reran as "1229 inputs were lost
between the fusion and the recorder" and "VERIFY FAILED: the recording holds no fusion outputs to
compare" (it held 1050), exit 1; a recording of ``nav/**`` and ``truth`` only, and a piece cut by
``hil filter``, were "not a rig session" while ``hil info`` showed their run; ``hil export --topics
nomatch`` said the file had no nav messages while listing them.
"""

from __future__ import annotations

from pathlib import Path

from hil.runners.sim import SimOptions, run_sim
from tests.conftest import run_hil


def _sim(path: Path, **kw: object) -> Path:
    run_sim(SimOptions(duration_s=2.0, record=path, fusion_worker=False, **kw))  # type: ignore[arg-type]
    return path


def _rerun(path: Path) -> tuple[int, str]:
    res = run_hil("rerun", str(path), "--core", "fusion", "--verify", timeout=120)
    return res.returncode, res.stdout + res.stderr


def test_a_recording_without_the_fusions_inputs_is_said_so(tmp_path: Path) -> None:
    rc, out = _rerun(_sim(tmp_path / "x.mcap", record_exclude=["synced/**"]))
    assert rc == 2, out
    assert "holds the fusion's outputs but none of its inputs (synced/*)" in out
    assert "--record-include/--record-exclude" in out and "VERIFY" not in out


def test_a_recording_whose_key_filter_left_out_the_run_is_said_so(tmp_path: Path) -> None:
    rc, out = _rerun(_sim(tmp_path / "n.mcap", record_include=["nav/**", "truth"]))
    assert rc == 2 and "a rig's recording without its run messages" in out, out
    assert "not a rig session" not in out


def test_a_filtered_piece_without_the_run_points_to_its_source(tmp_path: Path) -> None:
    src = _sim(tmp_path / "s.mcap")
    piece = tmp_path / "p.mcap"
    res = run_hil("filter", str(src), "-o", str(piece), "--start", "1", "--end", "2")
    assert res.returncode == 0, res.stderr
    rc, out = _rerun(piece)
    assert (
        rc == 2
        and "a piece cut by hil filter (s.mcap)" in out
        and "rerun the recording it was cut from" in out
    )


def test_export_of_topics_that_match_nothing_names_the_pattern_and_the_topics(tmp_path: Path) -> None:
    src = _sim(tmp_path / "e.mcap")
    res = run_hil("export", str(src), "-o", str(tmp_path / "t"), "--topics", "nomatch")
    assert res.returncode == 2, res.stderr
    assert "--topics 'nomatch' matches none of the exportable topics of" in res.stderr
    assert "nav/ekf15" in res.stderr and "no IMU, GNSS" not in res.stderr

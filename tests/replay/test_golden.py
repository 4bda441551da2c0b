"""The golden replay: a short committed recording and the outputs the fusion must compute from it.

Any numerical change of the fusion fails here. If the change is intended, regenerate with
``.venv/bin/python -m tests.replay.golden_update`` and commit the new golden files with it.
"""

from __future__ import annotations

import json

from hil.record.rerun import rerun
from tests.conftest import run_hil
from tests.replay.golden_update import EXPECTED, GOLDEN, digest
from tests.replay.helpers import LEGACY_GOLDEN

HOW_TO_UPDATE = "if intended: .venv/bin/python -m tests.replay.golden_update, and commit tests/replay/golden/"


def test_golden_files_are_present_and_small() -> None:
    assert GOLDEN.is_file() and EXPECTED.is_file()
    assert GOLDEN.stat().st_size < 2_000_000


def test_fusion_outputs_match_the_committed_expectation_field_by_field() -> None:
    expected = json.loads(EXPECTED.read_text())
    got = digest(GOLDEN)
    assert got["inputs_used"] == expected["inputs_used"], HOW_TO_UPDATE
    assert set(got["estimators"]) == set(expected["estimators"]), HOW_TO_UPDATE  # type: ignore[arg-type]
    for name, exp in expected["estimators"].items():
        mine = got["estimators"][name]  # type: ignore[index]
        for field in ("outputs", "last_seq", "last_pos_ned_m", "last_vel_ned_mps", "sha256"):
            assert mine[field] == exp[field], (
                f"estimator {name}: {field} changed: {exp[field]} -> {mine[field]}; {HOW_TO_UPDATE}"
            )


def test_cli_rerun_verify_reproduces_every_recorded_output_of_the_golden_recording() -> None:
    proc = run_hil("rerun", str(GOLDEN), "--verify", timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr + HOW_TO_UPDATE
    assert "VERIFY OK" in proc.stdout


def test_timesync_rerun_verify_reproduces_every_restamp_of_the_golden_recording() -> None:
    rc, lines = rerun(str(GOLDEN), core="timesync", verify=True)
    assert rc == 0, "\n".join([*lines, HOW_TO_UPDATE])
    assert "VERIFY OK" in lines[-1]


def test_a_recording_of_the_previous_form_reads_and_reruns_every_output() -> None:
    """The golden as recorded before the Foxglove-first change (null sigmas, maps, rig-time log
    times, no well-known channels) and before the rig-clock integration (issue 22.2): read and
    rerun by today's cores, every estimator recomputing every output it recorded.

    Not verified bit for bit: 22.2 changed the numbers on purpose (the IMU is held until time sync
    locks; estimators integrate the synced interval; ekf15 reports its attitude sigma), which is
    why the current golden was regenerated. A recording verifies against the code that made it."""
    expected = json.loads(EXPECTED.read_text())
    got = digest(LEGACY_GOLDEN)
    assert set(got["estimators"]) == set(expected["estimators"])
    for est, d in got["estimators"].items():
        assert d["outputs"] == expected["estimators"][est]["outputs"], est
    for core in ("fusion", "timesync"):
        rc, lines = rerun(str(LEGACY_GOLDEN), core=core, verify=False)
        assert rc == 0, lines
        assert any("recomputed" in ln for ln in lines), lines

"""The journal and the table: attempts, the latest one, torn lines, Parquet and its fallback."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest

from hil.campaign import results
from hil.campaign.results import Journal, JournalBusy, read_results, write_table


def _row(key: str, est: str, status: str, run: int = 0, **kw: Any) -> dict[str, Any]:
    return {"key": key, "run": run, "estimator": est, "status": status, "h_rms_m": 1.0, **kw}


def test_latest_attempt_and_done(tmp_path: Path) -> None:
    j = Journal(tmp_path)
    j.append([_row("k1", "", "failed", error="boom")])
    j.append([_row("k2", "a", "ok", 1), _row("k2", "b", "ok", 1)])
    j.append([_row("k1", "a", "ok"), _row("k1", "b", "ok")])  # k1 rerun: its "" row is gone
    j.append([_row("k3", "a", "ok", 2), _row("k3", "b", "lost", 2)])
    j.close()
    res = read_results(tmp_path)
    assert len(res.rows) == 7
    assert sorted(res.latest()) == [
        ("k1", "a"),
        ("k1", "b"),
        ("k2", "a"),
        ("k2", "b"),
        ("k3", "a"),
        ("k3", "b"),
    ]
    assert res.done_keys() == {"k1", "k2"}
    assert [(r["run"], r["estimator"]) for r in res.table()] == [
        (0, "a"),
        (0, "b"),
        (1, "a"),
        (1, "b"),
        (2, "a"),
        (2, "b"),
    ]


def test_a_torn_line_is_skipped_and_counted(tmp_path: Path) -> None:
    j = Journal(tmp_path)
    j.append([_row("k1", "a", "ok")])
    j.close()
    with (tmp_path / results.JOURNAL).open("ab") as fh:
        fh.write(b'{"key": "k2", "run": 1, "estim')  # killed mid-write
    j = Journal(tmp_path)  # the next campaign starts on a fresh line
    j.append([_row("k3", "a", "ok", 2)])
    j.close()
    res = read_results(tmp_path)
    assert res.torn_lines == 1
    assert res.done_keys() == {"k1", "k3"}


def test_one_writer_per_directory(tmp_path: Path) -> None:
    j = Journal(tmp_path)
    try:
        with pytest.raises(JournalBusy, match="another campaign is writing"):
            Journal(tmp_path)
    finally:
        j.close()


def test_parquet_table_and_jsonl_fallback(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    rows = [
        _row("k1", "a", "ok", series_h_err_m=[1.0, None, 2.0], campaign="c"),
        _row("k2", "a", "failed", 1),
    ]
    path = write_table(tmp_path, rows)
    assert path == tmp_path / results.TABLE
    back = read_results(tmp_path).rows  # no journal here: the table is read
    assert [(r["key"], r["status"], r["series_h_err_m"]) for r in back] == [
        ("k1", "ok", [1.0, None, 2.0]),
        ("k2", "failed", None),
    ]
    assert set(back[0]) == set(results.COLUMNS)
    monkeypatch.setattr(results, "have_pyarrow", lambda: False)
    assert write_table(tmp_path / "x", rows) is None

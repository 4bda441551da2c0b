"""A campaign's results on disk: an append-only journal and the table derived from it.

``DIR/results.jsonl`` is the journal: every attempt of every run, one JSON object per row (a
run and an estimator), appended and flushed to disk as each run comes back -- a campaign killed
at any moment keeps every result it had received, and a line torn by the kill is skipped on
reading (and counted). It is what a resumed campaign reads to skip the runs already done.

``DIR/results.parquet`` is the table: the latest attempt of each (run, estimator), rewritten
(atomically) while the campaign runs and at its end. Without pyarrow the table is not written
and every reader takes the journal instead.
"""

from __future__ import annotations

import fcntl
import math
import os
from collections.abc import Iterable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import msgspec

from hil.campaign.execute import FINAL

JOURNAL = "results.jsonl"
TABLE = "results.parquet"
SPEC = "campaign.toml"
KEYS = "campaign.keys"  # the current spec's run keys, one a line, in run order

# the table's columns and their types (Parquet schema); rows may carry more, which are dropped
COLUMNS: dict[str, str] = {
    "campaign": "string",
    "run": "int64",
    "key": "string",
    "kind": "string",
    "replicate": "int64",
    "scenario": "string",
    "seed": "int64",
    "duration_s": "float64",
    "config": "string",
    "faults": "string",
    "recording": "string",
    "estimator": "string",
    "status": "string",
    "error": "string",
    "note": "string",
    "verify": "string",
    "n": "int64",
    "h_rms_m": "float64",
    "h_p95_m": "float64",
    "h_max_m": "float64",
    "h_final_m": "float64",
    "conv_s": "float64",
    "nees_mean": "float64",
    "nees_pos_mean": "float64",
    "nees_vel_mean": "float64",
    "nees_in_band": "float64",
    "series_dt_s": "float64",
    "series_h_err_m": "list<float64>",
    "series_h_sigma_m": "list<float64>",
    "series_nees": "list<float64>",
    "wall_s": "float64",
    "cpu_s": "float64",
    "worker": "string",
    "code": "string",
    "finished_utc": "string",
}

_ENC = msgspec.json.Encoder()


def have_pyarrow() -> bool:
    try:
        import pyarrow  # noqa: F401  (only whether it imports)
    except ImportError:
        return False
    return True


@dataclass
class Results:
    """What a results directory holds: every attempt in order, and how many lines were torn."""

    rows: list[dict[str, Any]] = field(default_factory=list)
    torn_lines: int = 0
    source: str = ""

    def latest(self) -> dict[tuple[str, str], dict[str, Any]]:
        """The last attempt of each (run key, estimator). A run's rows are appended in one write,
        so an attempt is a run of consecutive lines with one key; a later attempt replaces all
        rows of the earlier one (it may have other estimators: a failed run has one "")."""
        last: dict[str, list[dict[str, Any]]] = {}
        prev = None
        for r in self.rows:
            if r["key"] != prev:
                last[r["key"]] = []
                prev = r["key"]
            last[r["key"]].append(r)
        return {(k, r["estimator"]): r for k, rows in last.items() for r in rows}

    def table(self, keys: set[str] | None = None) -> list[dict[str, Any]]:
        """The latest rows (of the runs in ``keys`` if given), sorted by run index and estimator."""
        rows = self.latest().values()
        if keys is not None:
            rows = [r for r in rows if r["key"] in keys]
        return sorted(rows, key=lambda r: (r["run"], r["estimator"]))

    def done_keys(self) -> set[str]:
        """Runs with a final result (ok or mismatch) in every row of their latest attempt."""
        state: dict[str, bool] = {}
        for (key, _est), r in self.latest().items():
            state[key] = state.get(key, True) and r["status"] in FINAL
        return {k for k, done in state.items() if done}


def _clean(row: dict[str, Any]) -> dict[str, Any]:
    return {k: (None if isinstance(v, float) and not math.isfinite(v) else v) for k, v in row.items()}


def write_keys(out_dir: Path, keys: list[str]) -> None:
    """What the directory's campaign consists of now (the table and the report keep to it)."""
    tmp = out_dir / (KEYS + ".tmp")
    tmp.write_text("".join(k + "\n" for k in keys), encoding="utf-8")
    os.replace(tmp, out_dir / KEYS)


def current_keys(out_dir: str | Path) -> list[str] | None:
    """The current spec's run keys in order, None for a directory without them."""
    p = Path(out_dir) / KEYS
    return p.read_text(encoding="utf-8").split() if p.is_file() else None


def read_results(out_dir: str | Path) -> Results:
    """The journal if there is one, else the table; empty if neither exists."""
    d = Path(out_dir)
    j = d / JOURNAL
    if j.is_file():
        res = Results(source=str(j))
        with j.open("rb") as fh:
            for line in fh:
                if not line.strip():
                    continue
                try:
                    res.rows.append(msgspec.json.decode(line))
                except msgspec.DecodeError:
                    res.torn_lines += 1
        return res
    t = d / TABLE
    if t.is_file() and have_pyarrow():
        import pyarrow.parquet as pq

        return Results(rows=pq.read_table(t).to_pylist(), source=str(t))
    return Results()


class JournalBusy(RuntimeError):
    """Another campaign holds the directory's journal."""


class Journal:
    """Appends rows to ``DIR/results.jsonl``, each run's rows in one write, flushed and synced.

    The file is locked (``flock``) while open: two campaigns writing one directory would
    interleave their attempts."""

    def __init__(self, out_dir: Path) -> None:
        out_dir.mkdir(parents=True, exist_ok=True)
        self.path = out_dir / JOURNAL
        self._fh = self.path.open("ab")
        try:
            fcntl.flock(self._fh.fileno(), fcntl.LOCK_EX | fcntl.LOCK_NB)
        except OSError:
            self._fh.close()
            raise JournalBusy(f"{self.path}: another campaign is writing this directory") from None
        if self._fh.tell() > 0:  # a line torn by a kill must not glue onto the next one
            with self.path.open("rb") as fh:
                fh.seek(-1, os.SEEK_END)
                if fh.read(1) != b"\n":
                    self._fh.write(b"\n")

    def append(self, rows: Iterable[dict[str, Any]]) -> None:
        self._fh.write(b"".join(_ENC.encode(_clean(r)) + b"\n" for r in rows))
        self._fh.flush()
        os.fsync(self._fh.fileno())

    def close(self) -> None:
        self._fh.close()


def write_table(out_dir: Path, rows: list[dict[str, Any]]) -> Path | None:
    """``DIR/results.parquet`` from the latest rows (None without pyarrow); atomic replace."""
    if not have_pyarrow():
        return None
    import pyarrow as pa
    import pyarrow.parquet as pq

    types = {
        "string": pa.string(),
        "int64": pa.int64(),
        "float64": pa.float64(),
        "list<float64>": pa.list_(pa.float64()),
    }
    schema = pa.schema([(k, types[v]) for k, v in COLUMNS.items()])
    cols = {k: [r.get(k) for r in rows] for k in COLUMNS}
    table = pa.Table.from_pydict(cols, schema=schema)
    path = out_dir / TABLE
    tmp = path.with_suffix(".parquet.tmp")
    pq.write_table(table, tmp)
    os.replace(tmp, path)
    return path

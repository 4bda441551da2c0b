"""``hil export FILE --format csv|parquet``: IMU, GNSS, truth and nav as tables for pandas, R, Excel.

One table per topic (``sensor/imu`` -> ``sensor_imu.csv``, ``nav/ekf15`` -> ``nav_ekf15.parquet``),
one row per message, in file order. Columns: ``log_time_ns`` and ``publish_time_ns`` (the MCAP
record's times, ``docs/recording.md`` says which clock), then the message's fields with vectors
spread over named columns: NED vectors (``pos_*``, ``vel_*``, their sigmas) as ``_n/_e/_d``,
quaternions ``q_nb`` as ``_w/_x/_y/_z`` (scalar first, as the message has it), body-frame
vectors as ``_x/_y/_z``. A solution without a covariance (``pos_sigma_m`` absent: ``[]``, or
``null`` in a recording made before) leaves its sigma cells empty (CSV) or null (Parquet). Times
stay integer nanoseconds; ``log_time_ns``/``publish_time_ns`` are on the wall clock (start epoch +
rig time) in recordings made now, rig time in those made before; the message fields are rig time.

Parquet is written with pyarrow (``ParquetWriter``, zstd, in row groups of ``BATCH`` rows, so an
hour-long recording is converted in bounded memory): the columnar format Dask, Spark, DuckDB and
pandas read without a parser, with the integer and float types kept.
"""

from __future__ import annotations

import csv
import re
from collections.abc import Iterator
from pathlib import Path
from typing import IO, Any

import msgspec

from hil.messages import TYPES_BY_NAME, GnssFix, ImuSample, NavSolution, Truth, decode, schema_name
from hil.record.mcapio import RecordingError, session_files, session_note
from hil.record.scan import Scan, describe_loss
from hil.record.tools import iter_tagged

EXPORTED = {schema_name(t): t for t in (ImuSample, GnssFix, Truth, NavSolution)}
FORMATS = ("csv", "parquet")
BATCH = 65536

_NED = ("n", "e", "d")
_XYZ = ("x", "y", "z")
_WXYZ = ("w", "x", "y", "z")


def _axes(field: str, length: int) -> tuple[str, ...]:
    if length == 4:
        return _WXYZ
    if field.startswith(("pos_", "vel_")):
        return _NED
    return _XYZ if length == 3 else tuple(str(i) for i in range(length))


def _columns(cls: type[msgspec.Struct]) -> list[tuple[str, str, int | None, str]]:
    """(column, field, index or None, kind) for a type; kind: int, float, str, bool."""
    info = msgspec.inspect.type_info(cls)
    out: list[tuple[str, str, int | None, str]] = []
    for f in info.fields:  # type: ignore[attr-defined]
        t = f.type
        if isinstance(t, msgspec.inspect.UnionType):
            t = next(x for x in t.types if not isinstance(x, msgspec.inspect.NoneType))
        if isinstance(t, msgspec.inspect.ListType):
            n = t.max_length or 0
            out += [(f"{f.name}_{a}", f.name, i, "float") for i, a in enumerate(_axes(f.name, n))]
        elif isinstance(t, msgspec.inspect.IntType):
            out.append((f.name, f.name, None, "int"))
        elif isinstance(t, msgspec.inspect.FloatType):
            out.append((f.name, f.name, None, "float"))
        elif isinstance(t, msgspec.inspect.BoolType):
            out.append((f.name, f.name, None, "bool"))
        else:
            out.append((f.name, f.name, None, "str"))
    return out


def _row(msg: Any, cols: list[tuple[str, str, int | None, str]]) -> list[Any]:
    row = []
    for _c, name, i, _k in cols:
        v = getattr(msg, name)
        if i is None:
            row.append(v)
        else:  # an absent vector is [] (and was None in recordings made before)
            row.append(v[i] if v is not None and i < len(v) else None)
    return row


def table_name(topic: str) -> str:
    """``hil/<rig>/nav/ekf15`` -> ``nav_ekf15``."""
    parts = topic.split("/")
    rest = parts[2:] if len(parts) > 2 and parts[0] == "hil" else parts
    return re.sub(r"[^A-Za-z0-9_.-]", "_", "_".join(rest)) or "topic"


class _Table:
    def __init__(self, path: Path, cls: type[msgspec.Struct], fmt: str) -> None:
        self.path = path
        self.cls = cls
        self.cols = _columns(cls)
        self.names = ["log_time_ns", "publish_time_ns", *(c[0] for c in self.cols)]
        self.rows: list[list[Any]] = []
        self.count = 0
        self.fmt = fmt
        self._fh: IO[str] | None = None
        self._csv: Any = None
        self._pq: Any = None
        if fmt == "csv":
            self._fh = open(path, "w", newline="")  # noqa: SIM115 - closed in close()
            self._csv = csv.writer(self._fh)
            self._csv.writerow(self.names)

    def add(self, log_ns: int, pub_ns: int, msg: Any) -> None:
        row = [log_ns, pub_ns, *_row(msg, self.cols)]
        self.count += 1
        if self._csv is not None:
            self._csv.writerow(["" if v is None else v for v in row])
            return
        self.rows.append(row)
        if len(self.rows) >= BATCH:
            self._flush_parquet()

    def _schema(self) -> Any:
        import pyarrow as pa

        kinds = {"int": pa.int64(), "float": pa.float64(), "bool": pa.bool_(), "str": pa.string()}
        fields = [pa.field("log_time_ns", pa.int64()), pa.field("publish_time_ns", pa.int64())]
        fields += [pa.field(c[0], kinds[c[3]]) for c in self.cols]
        return pa.schema(fields, metadata={"hil.type": schema_name(self.cls)})  # type: ignore[arg-type]

    def _flush_parquet(self) -> None:
        import pyarrow as pa
        import pyarrow.parquet as pq

        schema = self._schema()
        if self._pq is None:
            self._pq = pq.ParquetWriter(self.path, schema, compression="zstd")
        columns = list(zip(*self.rows, strict=True)) if self.rows else [() for _ in self.names]
        self._pq.write_table(
            pa.Table.from_arrays(
                [pa.array(c, t) for c, t in zip(columns, schema.types, strict=True)], schema=schema
            )
        )
        self.rows = []

    def close(self) -> None:
        if self._fh is not None:
            self._fh.close()
        elif self.fmt == "parquet":
            if self.rows or self._pq is None:
                self._flush_parquet()
            self._pq.close()


def _check_pyarrow() -> None:
    try:
        import pyarrow.parquet  # noqa: F401
    except ImportError as err:
        raise RecordingError(
            f"--format parquet needs pyarrow ({err}); pip install pyarrow, or use --format csv"
        ) from err


def export(
    src: str | Path, out_dir: str | Path, fmt: str = "csv", topics: list[str] | None = None
) -> tuple[dict[str, tuple[Path, int]], list[str]]:
    """Write one table per exported topic under ``out_dir``; returns topic -> (path, rows), notes.

    ``topics``: regular expressions; only matching topics are exported (default: every topic of
    an exported type). A recording with none of them is an error (one line).
    """
    if fmt not in FORMATS:
        raise RecordingError(f"--format {fmt!r}: use csv or parquet")
    if fmt == "parquet":
        _check_pyarrow()
    try:
        pats = [re.compile(t) for t in topics or []]
    except re.error as err:  # as filter/cat/replay: one line, exit 2
        raise RecordingError(f"--topics: bad pattern {err.pattern!r}: {err}") from err
    out = Path(out_dir)
    # a split recording: its parts end to end (each part has its channels; tables go by topic)
    scans = [Scan(f) for f in session_files(src)]
    tables: dict[str, _Table] = {}
    unmatched: set[str] = set()  # exportable topics --topics left out
    decoders: dict[str, type[Any]] = {}
    bad: dict[str, tuple[int, int, int]] = {}  # topic -> (count, first MCAP sequence, its log time)
    try:
        for t in _wanted((t for scan in scans for t in iter_tagged(scan)), pats, unmatched):
            topic = t.channel.topic
            tab = tables.get(topic)
            if tab is None:
                cls = EXPORTED[t.schema.name]  # type: ignore[union-attr]
                try:
                    out.mkdir(parents=True, exist_ok=True)
                    tab = tables[topic] = _Table(out / f"{table_name(topic)}.{fmt}", cls, fmt)
                except OSError as err:
                    raise RecordingError(f"cannot write under {out}: {err.strerror}") from err
                decoders[topic] = cls
            try:
                msg = decode(decoders[topic], t.message.data)  # a recording's previous forms too
            except (msgspec.DecodeError, msgspec.ValidationError):
                # the recorder validated it: a damaged or foreign message is skipped, and said
                n, seq, log = bad.get(topic, (0, t.message.sequence, t.message.log_time))
                bad[topic] = (n + 1, seq, log)
                continue
            tab.add(t.message.log_time, t.message.publish_time, msg)
    finally:
        for tab in tables.values():
            tab.close()
    if not tables and unmatched:
        names = ", ".join(sorted(unmatched)[:8]) + (f" (+{len(unmatched) - 8})" if len(unmatched) > 8 else "")
        raise RecordingError(
            f"--topics {' '.join(repr(t) for t in topics or [])} matches none of the exportable topics of "
            f"{src}: {names}"
        )
    if not tables:
        have = ", ".join(sorted({t for scan in scans for t in scan.report.per_topic})) or "no messages"
        raise RecordingError(f"{src}: no IMU, GNSS, truth or nav messages to export (it has {have})")
    named = len(scans) > 1  # which file of the session a loss is in
    notes = [
        f"note: {scan.path.name}: {ln}" if named else f"note: {ln}"
        for scan in scans
        for ln in describe_loss(scan.report)
    ]
    for topic, (n, seq, log) in sorted(bad.items()):
        rows = tables[topic].count
        notes.append(
            f"note: {topic}: {n} payload(s) could not be decoded and are not in the table ({rows} rows), "
            f"the first at seq {seq}, log_time_ns {log} (`hil cat --topics` shows them)"
        )
    many = session_note([scan.path for scan in scans], "exported")
    if many:
        notes.insert(0, f"note: {many}")
    return {k: (v.path, v.count) for k, v in tables.items()}, notes


def _wanted(tagged: Iterator[Any], pats: list[re.Pattern[str]], unmatched: set[str]) -> Iterator[Any]:
    """The exported messages of topics ``pats`` select; ``unmatched`` collects the exportable
    topics they left out (what to say when they select none)."""
    for t in tagged:
        if t.schema is None or t.schema.name not in EXPORTED or TYPES_BY_NAME.get(t.schema.name) is None:
            continue
        if pats and not any(p.search(t.channel.topic) for p in pats):
            unmatched.add(t.channel.topic)
            continue
        yield t

"""What one task does on a worker: run it, reduce it to statistics rows, delete the recording.

A run never raises: an exception becomes rows with ``status = "failed"`` and the error text, so a
broken run comes back as a result like any other (the driver adds ``lost`` for a run whose
worker died more often than the scheduler allows). Each row also says where and with which code
it ran (``worker``, ``code``: a hash of the ``hil`` package's sources and built-in data, so a
cluster whose workers run another version shows it).
"""

from __future__ import annotations

import functools
import hashlib
import os
import socket
import tempfile
import time
from collections.abc import Iterator
from dataclasses import replace
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

import hil
from hil.campaign.metrics import Collected, empty_stats, estimator_stats, gnss_bound, scenario_windows
from hil.campaign.runs import SIM, RunSpec
from hil.fusion.core import FusionConfig
from hil.messages import RunInfo, encode
from hil.nav.scenario import parse_scenario, scenario_for_run
from hil.record.mcapio import Record, SessionStream
from hil.record.rerun import RERUN_WINDOW_S, OutOfWindow, RerunResult, config_of_record, rerun_fusion_records
from hil.runners.sim import SimOptions, run_sim

OK, FAILED, LOST, MISMATCH = "ok", "failed", "lost", "mismatch"
FINAL = frozenset({OK, MISMATCH})  # a result; FAILED and LOST are rerun by the next invocation


@functools.cache
def code_fingerprint() -> str:
    """sha256 (12 hex) of every ``.py`` and ``.toml`` file of the installed ``hil`` package."""
    root = Path(hil.__file__).resolve().parent
    h = hashlib.sha256()
    for p in sorted(q for q in root.rglob("*") if q.suffix in (".py", ".toml") and q.is_file()):
        h.update(p.relative_to(root).as_posix().encode() + b"\0" + p.read_bytes() + b"\0")
    return h.hexdigest()[:12]


def base_row(run: RunSpec, estimator: str, status: str, error: str = "") -> dict[str, Any]:
    """The identity columns of one row (one run, one estimator)."""
    return {
        "campaign": run.campaign,
        "run": run.index,
        "key": run.key,
        "kind": run.kind,
        "replicate": run.replicate,
        "scenario": run.scenario,
        "seed": run.seed,
        "duration_s": run.duration_s,
        "config": run.config,
        "faults": run.faults,
        "recording": run.recording,
        "estimator": estimator,
        "status": status,
        "error": error,
        "note": "",
        "verify": "",
    }


def failed_rows(run: RunSpec, status: str, error: str) -> list[dict[str, Any]]:
    """A run that gave no statistics: one row per estimator it was to run (or one with "")."""
    return [base_row(run, e, status, error) | empty_stats() for e in (run.estimators or ("",))]


def execute_run(run: RunSpec, keep: Path | None = None) -> list[dict[str, Any]]:
    """The task: one run's rows; never raises (see the module docstring). ``keep``: where to
    keep a sim run's MCAP (``hil campaign repro``), whatever the run's ``keep_dir``."""
    t0, c0 = time.perf_counter(), time.process_time()
    try:
        rows = _sim_rows(run, keep) if run.kind == SIM else _rerun_rows(run)
    except Exception as err:  # the run's failure is its result
        rows = failed_rows(run, FAILED, f"{type(err).__name__}: {err}".strip())
    where = f"{socket.gethostname()}:{os.getpid()}"
    done = datetime.now(UTC).isoformat(timespec="seconds")
    for row in rows:
        row.update(
            wall_s=round(time.perf_counter() - t0, 3),
            cpu_s=round(time.process_time() - c0, 3),  # this process's CPU: the run's cost, load aside
            worker=where,
            code=code_fingerprint(),
            finished_utc=done,
        )
    return rows


def kept_recording(run: RunSpec) -> Path:
    """Where ``keep_recordings`` puts a run's MCAP: ``KEEP/<campaign>/run-<index>-<key>.mcap``."""
    return Path(run.keep_dir) / run.campaign / f"run-{run.index:06d}-{run.key[:8]}.mcap"


# What a run's statistics read (``sim_statistics``): a recording that is deleted after them
# keeps only these; a kept one (``keep_dir``, ``hil campaign repro --record``) keeps everything.
STATISTICS_KEYS = ("run", "truth", "nav/**")


def sim_recording(run: RunSpec, record: Path, tmp: Path, *, everything: bool = True) -> list[str]:
    """``hil sim`` of the run into ``record``; returns its warnings. ``everything=False``
    records only ``STATISTICS_KEYS``: the cores run the same (the recorder's filter drops
    writes, nothing else), and a 60 s uav_survey run cost 15 % less CPU and wrote 12002
    messages, not 181624, for the statistics to read back."""
    scenario = tmp / f"{run.scenario}.toml"
    scenario.write_text(run.scenario_toml, encoding="utf-8")
    warnings: list[str] = []
    run_sim(
        SimOptions(
            scenario=str(scenario),
            duration_s=run.duration_s,
            record=record,
            estimators=list(run.estimators),
            lag_s=run.lag_s,
            output_every=run.output_every,
            on_warning=warnings.append,
            record_include=[] if everything else list(STATISTICS_KEYS),
        )
    )
    return warnings


def _sim_rows(run: RunSpec, keep: Path | None = None) -> list[dict[str, Any]]:
    """``hil sim`` of the run, its statistics; the MCAP kept at ``keep``, under ``keep_dir`` or
    deleted."""
    if keep is None and run.keep_dir:
        keep = kept_recording(run)
    with tempfile.TemporaryDirectory(prefix="hil-campaign-") as tmp:
        record = keep or Path(tmp) / "run.mcap"
        record.parent.mkdir(parents=True, exist_ok=True)
        warnings = sim_recording(run, record, Path(tmp), everything=keep is not None)
        rows = sim_statistics(run, record, warnings)
    if keep is not None:
        for row in rows:
            row["recording"] = str(record)
    return rows


def sim_statistics(run: RunSpec, record: Path, warnings: list[str]) -> list[dict[str, Any]]:
    """The rows of a sim run from its recording (read once, streamed)."""
    c = Collected(frozenset(run.estimators))
    for r in SessionStream(record):
        c.record(r)
    sc = parse_scenario(run.scenario_toml, run.scenario)
    windows, cap = scenario_windows(sc), gnss_bound(sc)
    rows = []
    for name in run.estimators:
        row = base_row(run, name, OK) | estimator_stats(
            c, name, settle_s=run.settle_s, windows=windows, cap_m=cap
        )
        row["note"] = "; ".join(warnings)
        if row["n"] == 0:
            row.update(status=FAILED, error=f"{name} published no solution inside the truth's span")
        rows.append(row)
    return rows


class _RerunTap:
    """The recording's records on their way to the rerun: truth and the run kept aside, the
    fusion's configuration replaced when the run asks for another one."""

    def __init__(self, run: RunSpec, collected: Collected) -> None:
        self.run = run
        self.c = collected
        self.info: RunInfo | None = None

    def records(self, stream: SessionStream) -> Iterator[Record]:
        override = bool(self.run.estimators)
        for r in stream:
            t = r.topic
            if t.endswith("/truth"):
                self.c.record(r)
                continue
            if self.info is None and t.endswith("/run"):
                m = r.decode()
                if isinstance(m, RunInfo):
                    self.info = m
            elif override and "/nav/" in t:
                continue  # another configuration's outputs: nothing to compare them with
            elif override and (cfg := config_of_record(r)) is not None:
                yield self._config(r, cfg)
                continue
            yield r

    def _config(self, r: Record, cfg: FusionConfig) -> Record:
        run = self.run
        new = replace(cfg, estimators=run.estimators, output_every=run.output_every or cfg.output_every)
        root = r.topic.split("/")[:2]  # hil/<rig>
        payload = encode(new.settings(0, r.publish_time_ns))
        return Record(
            "/".join([*root, "fusion", "config"]),
            "hil.FusionSettings",
            payload,
            r.log_time_ns,
            r.publish_time_ns,
            0,
        )


def _rerun_once(
    run: RunSpec, window_s: float | None
) -> tuple[RerunResult, Collected, _RerunTap, SessionStream]:
    c = Collected(frozenset(run.estimators) if run.estimators else None)
    tap = _RerunTap(run, c)
    stream = SessionStream(run.recording, follow_parts=True)
    window_ns = None if window_s is None else round(window_s * 1e9)
    res = rerun_fusion_records(
        tap.records(stream), window_ns=window_ns, keep_outputs=True, name=run.recording
    )
    for s in res.recomputed:
        c.solution(s)
    return res, c, tap, stream


def _rerun_rows(run: RunSpec) -> list[dict[str, Any]]:
    """The recording's inputs through today's fusion core (its own or the run's configuration);
    statistics of the recomputed outputs; with ``verify``, bit-identical or the first difference."""
    note = ""
    try:
        res, c, tap, stream = _rerun_once(run, RERUN_WINDOW_S)
    except OutOfWindow as why:
        res, c, tap, stream = _rerun_once(run, None)
        note = f"{why}: reran with the whole file in memory"
    if stream.truncated:
        note = "; ".join(x for x in (note, "the file is truncated: rerun up to its last complete chunk") if x)
    info = tap.info
    sc = scenario_for_run(info) if info is not None and info.scenario_toml else None
    windows = scenario_windows(sc) if sc is not None else []
    cap = gnss_bound(sc) if sc is not None else None
    named = replace(
        run,
        scenario=info.scenario if info else "",
        seed=info.seed if info else -1,
        duration_s=info.duration_s if info else None,
    )
    diff = res.first_difference() if run.verify else None
    rows = []
    for name in run.estimators or tuple(sorted(c.nav)):
        row = base_row(named, name, MISMATCH if diff else OK, diff or "")
        row |= estimator_stats(c, name, settle_s=run.settle_s, windows=windows, cap_m=cap)
        row["note"] = note
        row["verify"] = ("mismatch" if diff else "ok") if run.verify else ""
        rows.append(row)
    if not rows:
        rows = failed_rows(
            named, MISMATCH if diff else FAILED, diff or "the rerun produced no estimator output"
        )
    return rows

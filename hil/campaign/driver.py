"""The campaign on Dask: runs are tasks, rows come back, the journal takes them as they come.

Without ``scheduler`` a ``LocalCluster`` of worker *processes* (one thread each: a run is pure
Python, the GIL would serialise threads) is started, one per core unless ``workers`` says, and
torn down at the end whatever happens. With ``scheduler`` (``tcp://host:8786``) the campaign
runs on that existing cluster; its workers must run the same ``hil`` (checked by
:func:`hil.campaign.execute.code_fingerprint` before any task is sent).

Honesty: a run is submitted unless the journal already holds a final result for its key; every
submitted run comes back as rows -- its statistics, ``failed`` with the exception the run
raised, or ``lost`` with what Dask said (a worker that died with it more often than the
scheduler allows: ``distributed.scheduler.allowed-failures``, 3) -- and is journaled at once. A
worker killed mid-run costs only the runs it held: the scheduler gives them to another worker,
and what was already journaled stays. The next invocation reruns ``failed`` and ``lost`` runs.
"""

from __future__ import annotations

import contextlib
import logging
import os
import re
import signal
import threading
import time
from collections.abc import Callable, Iterator
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from hil.campaign.execute import FAILED, LOST, MISMATCH, OK, code_fingerprint, execute_run, failed_rows
from hil.campaign.results import (
    SPEC,
    Journal,
    JournalBusy,
    current_keys,
    read_results,
    write_keys,
    write_table,
)
from hil.campaign.runs import RunSpec, derive_runs
from hil.campaign.spec import CampaignSpec
from hil.progress import Progress

_ADDRESS = re.compile(r"^(tcp|tls)://[^\s/:]+:\d{1,5}$")


class CampaignError(RuntimeError):
    """A campaign that cannot start (scheduler, workers, directory); one line for the user."""


@dataclass
class DriverOptions:
    out_dir: Path
    scheduler: str | None = None  # tcp://host:port of an existing cluster; None: a local one
    workers: int | None = None  # local cluster size; None: one per core
    connect_timeout_s: float = 10.0
    progress: bool | None = None  # None: when stderr is a terminal
    table_every_s: float = 60.0  # how often results.parquet is rewritten while running
    on_rows: Callable[[RunSpec, list[dict[str, Any]]], None] | None = None  # after each journaling


@dataclass
class Outcome:
    """What one invocation did; ``failures`` are (run, status, error) of runs without a result."""

    total: int
    skipped: int
    counts: dict[str, int] = field(default_factory=dict)
    failures: list[tuple[RunSpec, str, str]] = field(default_factory=list)
    wall_s: float = 0.0
    cluster: str = ""
    table: Path | None = None
    torn_lines: int = 0

    @property
    def ran(self) -> int:
        return sum(self.counts.values())


def local_workers(requested: int | None) -> int:
    return max(1, requested if requested else (os.cpu_count() or 1))


@contextlib.contextmanager
def _workers_ignore_sigint() -> Iterator[None]:
    """SIGINT ignored while the local workers are spawned, so they inherit it ignored (Python
    then installs no KeyboardInterrupt handler in them): Ctrl-C in a terminal reaches the whole
    process group, and a worker taking it printed its own traceback after the driver's clean
    stop line. The driver alone takes Ctrl-C and closes the cluster, which stops the workers."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return
    previous = signal.signal(signal.SIGINT, signal.SIG_IGN)
    try:
        yield
    finally:
        signal.signal(signal.SIGINT, previous)


def connect(opts: DriverOptions) -> tuple[Any, Any, str]:
    """(client, local cluster or None, description); a one-line CampaignError if it cannot."""
    from dask.distributed import Client, LocalCluster

    if opts.scheduler is None:
        n = local_workers(opts.workers)
        with _workers_ignore_sigint():
            cluster = LocalCluster(
                n_workers=n,
                threads_per_worker=1,
                processes=True,
                dashboard_address=":0",  # a free port: never "8787 is already in use"
                silence_logs=logging.ERROR,
            )
        try:
            client = Client(cluster, set_as_default=False)
        except BaseException:
            cluster.close()
            raise
        return client, cluster, f"local Dask cluster, {n} worker process(es)"
    addr = opts.scheduler
    if not _ADDRESS.match(addr):
        raise CampaignError(f"--scheduler {addr}: expected tcp://HOST:PORT (e.g. tcp://10.0.0.5:8786)")
    try:
        client = Client(addr, timeout=opts.connect_timeout_s, set_as_default=False)
    except (OSError, TimeoutError, ValueError) as err:
        raise CampaignError(f"--scheduler {addr}: cannot reach a Dask scheduler there ({err})") from None
    try:
        client.wait_for_workers(1, timeout=opts.connect_timeout_s)
    except (TimeoutError, OSError):
        client.close()
        raise CampaignError(
            f"--scheduler {addr}: the scheduler has no worker after {opts.connect_timeout_s:g} s "
            "(start one: dask worker " + addr + ")"
        ) from None
    n = len(client.scheduler_info().get("workers", {}))
    return client, None, f"Dask scheduler {addr}, {n} worker(s)"


def check_workers(client: Any) -> None:
    """Every worker runs this client's ``hil`` (same sources): else the runs are not the spec's."""
    mine = code_fingerprint()
    try:
        theirs: dict[str, str] = client.run(code_fingerprint)
    except Exception as err:
        raise CampaignError(
            f"the workers cannot run hil's campaign code ({type(err).__name__}: {err})"
        ) from None
    other = {w: fp for w, fp in theirs.items() if fp != mine}
    if other:
        w, fp = next(iter(sorted(other.items())))
        raise CampaignError(
            f"{len(other)} worker(s) run other hil code than this client (e.g. {w}: {fp}, here: {mine}); "
            "install the same version on every worker"
        )


def _status(rows: list[dict[str, Any]]) -> tuple[str, str]:
    """A run's status from its rows: the worst one, and its error."""
    for s in (LOST, FAILED, MISMATCH):
        for r in rows:
            if r["status"] == s:
                return s, r.get("error", "")
    return OK, ""


def _submit(client: Any, todo: list[RunSpec]) -> list[Any]:
    keys = [f"hil-run-{r.index}-{r.key[:12]}" for r in todo]
    return client.map(execute_run, todo, key=keys, pure=False)


def _collect(
    client: Any, futures: list[Any], todo: list[RunSpec], journal: Journal, out: Outcome, opts: DriverOptions
) -> None:
    """Each run's rows into the journal as it completes, whatever it completed with."""
    from dask.distributed import as_completed
    from distributed.scheduler import KilledWorker

    by_key = {f.key: r for f, r in zip(futures, todo, strict=True)}
    keys = set(current_keys(opts.out_dir) or ())
    # without a terminal (nohup, a log file): a line a minute, so a run of hours shows its ETA
    log_every = 60.0 if opts.progress is None else None
    bar = Progress("campaign", total=len(todo), unit="runs", enabled=opts.progress, log_every_s=log_every)
    next_table = time.monotonic() + opts.table_every_s
    try:
        for fut in as_completed(futures, loop=client.loop):
            run = by_key[fut.key]
            try:
                rows = fut.result()
            except KilledWorker as err:
                rows = failed_rows(run, LOST, f"KilledWorker: {err}")
            except Exception as err:  # cancelled, the scheduler gone, a task that would not unpickle
                rows = failed_rows(run, LOST, f"{type(err).__name__}: {err}")
            fut.release()
            journal.append(rows)
            status, error = _status(rows)
            out.counts[status] = out.counts.get(status, 0) + 1
            if status != OK:
                out.failures.append((run, status, error))
            bad = len(out.failures)
            bar.update(out.ran, stage=f"{bad} failed" if bad else "")
            if opts.on_rows is not None:
                opts.on_rows(run, rows)
            if time.monotonic() >= next_table:
                write_table(opts.out_dir, read_results(opts.out_dir).table(keys))
                next_table = time.monotonic() + opts.table_every_s
    finally:
        bar.close()


def run_campaign(spec: CampaignSpec, opts: DriverOptions) -> Outcome:
    """Derive the runs (refusing a bad spec before anything starts), skip those already done,
    run the rest on Dask, journal every result, write the table."""
    t0 = time.monotonic()
    runs = derive_runs(spec)
    out_dir = opts.out_dir
    prior = read_results(out_dir)
    done = prior.done_keys()
    todo = [r for r in runs if r.key not in done]
    out = Outcome(total=len(runs), skipped=len(runs) - len(todo), torn_lines=prior.torn_lines)
    out_dir.mkdir(parents=True, exist_ok=True)
    try:
        journal = Journal(out_dir)
    except JournalBusy as err:
        raise CampaignError(str(err)) from None
    try:
        (out_dir / SPEC).write_text(spec.to_toml(), encoding="utf-8")
        write_keys(out_dir, [r.key for r in runs])
        if todo:
            client, cluster, out.cluster = connect(opts)
            try:
                check_workers(client)
                _collect(client, _submit(client, todo), todo, journal, out, opts)
            finally:
                client.close()
                if cluster is not None:
                    cluster.close()
    finally:
        journal.close()
        out.table = write_table(out_dir, read_results(out_dir).table({r.key for r in runs}))
        out.wall_s = time.monotonic() - t0
    return out

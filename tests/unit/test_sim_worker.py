"""``hil sim`` with the fusion in a worker process writes the one-process file byte for byte, and a
worker that fails or dies is a clear error, never a hang or an orphan process."""

from __future__ import annotations

import os
import signal
from pathlib import Path

import pytest

from hil.messages import Event
from hil.nodes.base import Node, Out
from hil.runners.sim import SimOptions, run_sim, sim_run_info
from hil.runners.sim_worker import RemoteNode, WorkerError, drive

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="the worker is forked")


def test_worker_writes_the_one_process_file(tmp_path: Path) -> None:
    files = {}
    for worker in (False, True):
        rec = tmp_path / f"w{int(worker)}.mcap"
        opts = SimOptions(scenario="uav_survey", duration_s=4.0, record=rec, fusion_worker=worker)
        res = run_sim(opts)
        assert res.messages > 10_000
        files[worker] = rec.read_bytes()
    assert files[True] == files[False]


def test_worker_outputs_encoded_there_keep_parts_and_filters(tmp_path: Path) -> None:
    """The worker's outputs come back as bytes with their Foxglove messages: split parts (each
    registering its channels anew) and a record filter (leaving some of the worker's keys and
    what derives from them out) give the one-process files."""
    from hil.record.info import describe

    parts: dict[bool, list[bytes]] = {}
    for worker in (False, True):
        rec = tmp_path / f"p{int(worker)}" / "s.mcap"
        opts = SimOptions(
            scenario="uav_survey",
            duration_s=4.0,
            record=rec,
            split_s=1.5,
            record_exclude=["nav/comp1", "health/**"],
            fusion_worker=worker,
        )
        run_sim(opts)
        parts[worker] = [p.read_bytes() for p in sorted(rec.parent.glob("*.mcap"))]
    assert len(parts[False]) == 3
    assert parts[True] == parts[False]
    summary = describe(str(max((tmp_path / "p1").glob("*.mcap"), key=lambda p: p.stat().st_size)))
    assert "/nav/ekf15" in summary and "/foxglove/fix/nav/ekf15" in summary
    assert "/nav/comp1" not in summary and "/foxglove/fix/nav/comp1" not in summary


def test_only_the_types_that_derive_foxglove_messages_are_offered(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    from hil import wellknown
    from hil.runners import sim

    files = []
    for every in (False, True):  # the filter (hil.wellknown.derives), then every message offered
        if every:
            monkeypatch.setattr(sim, "derives", lambda _cls: True)
            monkeypatch.setattr(wellknown, "derives", lambda _cls: True)
        rec = tmp_path / f"d{len(files)}.mcap"
        run_sim(
            SimOptions(
                scenario="car_drive", duration_s=3.0, record=rec, fusion_worker=False, gnss_protocol=["nmea"]
            )
        )
        files.append(rec.read_bytes())
    assert files[0] == files[1]


class _Ticker(Node):
    """Ticks every 10 ms and says so; raises at ``fail_at_ns``."""

    name = "ticker"
    inputs_move_timers = False

    def __init__(self, run, fail_at_ns: int | None = None) -> None:  # type: ignore[no-untyped-def]
        super().__init__(run)
        self.t = 0
        self.fail_at_ns = fail_at_ns

    def next_tick_ns(self) -> int | None:
        return self.t

    def tick(self, now_ns: int) -> list[Out]:
        if self.fail_at_ns is not None and now_ns >= self.fail_at_ns:
            raise ValueError(f"boom at {now_ns}")
        self.t = now_ns + 10_000_000
        self.inc("ticks")
        return [self.event("tick", "", now_ns)]

    def on_message(self, key: str, msg: object, now_ns: int) -> list[Out]:
        self.inc("inputs")
        return [self.event("input", key, now_ns)]


def _run_info():  # type: ignore[no-untyped-def]
    return sim_run_info(SimOptions(duration_s=2.0))


def test_remote_node_gives_what_the_node_gives_here() -> None:
    ev = Event(seq=0, stamp_ns=0, kind="x", source="y", detail="")
    inputs = [(5_000_000, "event/a", ev), (20_000_000, "event/b", ev)]
    local: list[tuple[list[Out], int]] = []
    here = _Ticker(_run_info())
    busy_here = drive(here, inputs, 30_000_000, lambda outs, t: local.append((outs, t)) if outs else None)
    remote = RemoteNode(_Ticker(_run_info()))
    try:
        remote.window(inputs, 30_000_000)
        published, busy = remote.result()
    finally:
        remote.close()
    assert published == local
    assert [t for _outs, t in published] == [0, 5_000_000, 10_000_000, 20_000_000, 20_000_000]
    assert busy is busy_here is True
    assert remote.counters() == here.counters() == {"ticks": 3, "inputs": 2}


def test_a_failing_worker_is_an_error_with_its_traceback() -> None:
    remote = RemoteNode(_Ticker(_run_info(), fail_at_ns=10_000_000))
    try:
        remote.window([], 30_000_000)
        with pytest.raises(WorkerError, match="boom at 10000000"):
            remote.result()
    finally:
        remote.close()
    with pytest.raises(ChildProcessError):
        os.waitpid(remote.pid, os.WNOHANG)  # reaped


def test_a_killed_worker_is_an_error() -> None:
    remote = RemoteNode(_Ticker(_run_info()))
    try:
        os.kill(remote.pid, signal.SIGKILL)
        os.waitpid(remote.pid, 0)
        with pytest.raises(WorkerError, match="died"):
            remote.window([], 30_000_000)
            remote.result()
    finally:
        remote.close()


class _Chatty(_Ticker):
    """Publishes far more per window than a socket buffer holds."""

    def tick(self, now_ns: int) -> list[Out]:
        self.t = now_ns + 1_000_000
        return [self.event("tick", "x" * 2000, now_ns)] * 10


def test_close_does_not_wait_on_a_worker_blocked_writing() -> None:
    import threading

    remote = RemoteNode(_Chatty(_run_info()))
    remote.window([], 1_000_000_000)  # ~10 MB of reply nobody reads
    remote.window([], 2_000_000_000)
    closer = threading.Thread(target=remote.close)
    closer.start()
    closer.join(timeout=30.0)
    hung = closer.is_alive()
    if hung:  # unblock it before failing: a test never hangs
        os.kill(remote.pid, signal.SIGKILL)
        closer.join()
    assert not hung
    with pytest.raises(ChildProcessError):
        os.waitpid(remote.pid, os.WNOHANG)  # reaped

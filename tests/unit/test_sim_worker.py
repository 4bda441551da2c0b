"""``hil sim`` with the fusion in a worker process writes the one-process file byte for byte, and a
worker that fails or dies is a clear error, never a hang or an orphan process."""

from __future__ import annotations

import contextlib
import gc
import os
import signal
import threading
import time
from pathlib import Path

import can
import pytest

from hil.messages import Event
from hil.nodes.base import Node, Out
from hil.runners.sim import Scheduler, SimOptions, run_sim, sim_run_info
from hil.runners.sim_worker import (
    AHEAD_WINDOWS,
    REPLY_RING_BYTES,
    REQUEST_RING_BYTES,
    ForkedCall,
    ForkedChild,
    RemoteTail,
    WorkerError,
    _Link,
    portable,
    worker_possible,
)

pytestmark = pytest.mark.skipif(not hasattr(os, "fork"), reason="the worker is forked")


@pytest.mark.parametrize(
    ("scenario", "estimators", "gnss", "tail"),
    [
        # a consumer IMU's defaults (feedback, ekf15's calibration states): the fusion alone
        ("uav_survey", [], [], ["fusion"]),
        # a tactical IMU's six estimators: everything after the CAN bridge (the line's reader too)
        ("straight_level", [], ["nmea"], ["gnss_emulator", "gnss_bridge", "timesync", "fusion"]),
        # the free INS alone: from the CAN bridge on
        ("static", ["ins"], [], ["can_bridge", "gnss_emulator", "timesync", "fusion"]),
    ],
)
def test_worker_writes_the_one_process_file(
    tmp_path: Path,
    monkeypatch: pytest.MonkeyPatch,
    scenario: str,
    estimators: list[str],
    gnss: list[str],
    tail: list[str],
) -> None:
    from hil.runners import sim

    tails: list[list[str]] = []

    class Counted(RemoteTail):  # the real worker, its nodes noted
        def __init__(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
            super().__init__(*args, **kwargs)
            tails.append(self.names)

    monkeypatch.setattr(sim, "RemoteTail", Counted)
    files = {}
    for worker in (False, True):
        rec = tmp_path / f"w{int(worker)}.mcap"
        opts = SimOptions(
            scenario=scenario,
            duration_s=4.0,
            record=rec,
            estimators=estimators,
            gnss_protocol=gnss,
            fusion_worker=worker,
        )
        res = run_sim(opts)
        assert res.messages > 10_000
        files[worker] = rec.read_bytes()
    assert tails == [tail]
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


def _no_write(events: object) -> None:
    raise AssertionError("a tail's scheduler writes nothing")


def _tail(node: Node) -> RemoteTail:
    nodes = [node]
    return RemoteTail(nodes, 0, lambda: Scheduler(nodes, _no_write, None))  # type: ignore[arg-type]


class _Echo(_Ticker):
    """Says what each input was, a CAN frame field by field."""

    def on_message(self, key: str, msg: object, now_ns: int) -> list[Out]:
        if isinstance(msg, can.Message):
            f = msg
            detail = (
                f"{f.timestamp!r} {f.arbitration_id:x} {f.is_extended_id} {f.is_remote_frame} "
                f"{f.is_error_frame} {f.channel} {f.dlc} {bytes(f.data).hex()} {type(f.data).__name__} "
                f"{f.is_fd} {f.is_rx} {f.bitrate_switch} {f.error_state_indicator}"
            )
        else:
            detail = f"{key} {msg!r}"
        return [self.event("input", detail, now_ns)]


def test_remote_tail_gives_what_the_scheduler_gives_here() -> None:
    """A window's inputs (a CAN frame among them, shipped as its fields) through the scheduler
    here and in a worker: the same messages, stamps and order, and the same counters."""
    ev = Event(seq=0, stamp_ns=0, kind="x", source="y", detail="")
    fd = can.Message(
        0.0051, 0x1ABCDE, True, False, False, "vcan0", 12, bytearray(range(12)), True, True, True, True
    )
    classic = can.Message(timestamp=0.0052, arbitration_id=0x181, data=b"\x01\x02", is_extended_id=False)
    inputs = [
        (5_000_000, -1, 1, "event/a", ev),
        (5_100_000, -1, 2, "@can/vcan0", fd),
        (5_200_000, -1, 3, "@can/vcan0", classic),
        (20_000_000, -1, 4, "event/b", ev),
    ]
    here_node = _Echo(_run_info())
    here = Scheduler([here_node], _no_write, None)  # type: ignore[arg-type]
    local, busy_here = here.run_tail(0, [list(inputs)], 30_000_000, None)
    remote = _tail(_Echo(_run_info()))
    try:
        shipped = [portable(e) for e in inputs]
        # a frame crosses as its fields (python-can's type is bound by the first tail)
        assert [type(e[-1]) is tuple for e in shipped] == [False, True, True, False]
        remote.window([shipped], 30_000_000)
        events, busy = remote.result()
    finally:
        remote.close()
    assert events == local
    assert [e[0] for e in events] == [0, 5_000_000, 5_100_000, 5_200_000, 10_000_000, 20_000_000, 20_000_000]
    frame_line = events[2][4].detail
    assert (
        frame_line
        == "0.0051 1abcde True False False vcan0 12 000102030405060708090a0b bytearray True True True True"
    )
    assert busy is busy_here is True
    assert remote.snapshot() == [("ticker", here_node.counters(), "")]
    assert here_node.counters() == {"ticks": 3}


def test_a_failing_worker_is_an_error_with_its_traceback() -> None:
    remote = _tail(_Ticker(_run_info(), fail_at_ns=10_000_000))
    try:
        remote.window([[]], 30_000_000)
        with pytest.raises(WorkerError, match="boom at 10000000"):
            remote.result()
    finally:
        remote.close()
    with pytest.raises(ChildProcessError):
        os.waitpid(remote.pid, os.WNOHANG)  # reaped


def test_a_killed_worker_is_an_error() -> None:
    remote = _tail(_Ticker(_run_info()))
    try:
        os.kill(remote.pid, signal.SIGKILL)
        os.waitpid(remote.pid, 0)
        with pytest.raises(WorkerError, match="died"):
            remote.window([[]], 30_000_000)
            remote.result()
    finally:
        remote.close()


def _denied() -> None:
    """A worker's setup that fails, as loading the kernels from an unreadable directory did."""
    raise PermissionError(13, "Permission denied", "/kernels/hil_kernels_x.so")


def _windows_past_the_ring(remote: RemoteTail, first_ns: int) -> None:
    """Windows sent ahead, as ``hil sim`` sends them, three request rings' worth in all: a worker
    that has left can never take them, so the sender waits on it and sees it gone."""
    payload = b"x" * (2 << 20)
    for k in range(3 * REQUEST_RING_BYTES // len(payload)):
        t = first_ns + k * 10_000_000
        remote.window([[(t, -1, 1, "event/a", payload)]], t + 10_000_000)


def test_a_worker_whose_setup_fails_says_why_in_one_line() -> None:
    """A setup that raises in the child (the kernels' loading) is the caller's ``WorkerError``,
    one line naming the cause and where it was raised. It was the child's silent exit: "Broken
    pipe" or "Connection reset by peer", and nothing of why."""
    from hil.runners.sim_worker import RemoteNode

    remote = RemoteNode(_Ticker(_run_info()), setup=_denied)
    try:
        remote.call(_counters)
        with pytest.raises(WorkerError) as err:
            remote.called()
    finally:
        remote.close()
    said = str(err.value)
    assert "\n" not in said
    assert said.startswith(
        "hil: the ticker worker could not start: PermissionError: [Errno 13] Permission denied"
    )
    assert "/kernels/hil_kernels_x.so" in said and "test_sim_worker.py:" in said and "in _denied" in said
    with pytest.raises(ChildProcessError):
        os.waitpid(remote.pid, os.WNOHANG)  # reaped


def test_a_tail_whose_setup_fails_says_why_to_a_sim_sending_windows_ahead() -> None:
    """``hil sim`` sends its worker windows ahead before it reads a reply: the child that could
    not start stays until closed, taking them in, so the sim reads its reason (it had left: the
    sim's next send found its socket closed, "Broken pipe")."""
    nodes: list[Node] = [_Ticker(_run_info())]
    remote = RemoteTail(nodes, 0, lambda: Scheduler(nodes, _no_write, None), setup=_denied)  # type: ignore[arg-type]
    try:
        _windows_past_the_ring(remote, 0)
        with pytest.raises(WorkerError, match=r"^hil: the ticker worker could not start: PermissionError"):
            remote.result()
    finally:
        _closes_and_reaps(remote)


def test_a_tail_that_fails_midway_says_why_to_a_sim_sending_windows_ahead() -> None:
    """The same for a window that raises: its traceback, not a closed socket, even with the
    windows after it sent before its reply is read."""
    remote = _tail(_Ticker(_run_info(), fail_at_ns=10_000_000))
    try:
        remote.window([[]], 30_000_000)
        _windows_past_the_ring(remote, 30_000_000)
        with pytest.raises(WorkerError, match="boom at 10000000"):
            remote.result()
    finally:
        _closes_and_reaps(remote)


@pytest.mark.skipif(not worker_possible(), reason="hil sim forks its worker with two CPUs")
def test_hil_sim_whose_worker_cannot_start_says_why(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    from hil.runtime import jit

    monkeypatch.setattr(jit, "enable_for_run", _denied)  # the worker's setup (forked: it has this)
    with pytest.raises(WorkerError) as err:
        run_sim(
            SimOptions(scenario="uav_survey", duration_s=4.0, record=tmp_path / "s.mcap", fusion_worker=True)
        )
    assert str(err.value).startswith("hil: the fusion worker could not start: PermissionError: [Errno 13]")


def _counters(node: Node) -> object:
    return node.counters()


class _Chatty(_Ticker):
    """Publishes far more per window than the reply ring holds (20 MB)."""

    def tick(self, now_ns: int) -> list[Out]:
        self.t = now_ns + 1_000_000
        return [self.event("tick", "x" * 2000, now_ns)] * 10


def _closes_and_reaps(remote: RemoteTail) -> None:
    """``remote.close()`` returns (within a minute, however slow the machine) and reaps the child."""
    closer = threading.Thread(target=remote.close)
    closer.start()
    closer.join(timeout=60.0)
    hung = closer.is_alive()
    if hung:  # unblock it before failing: a test never hangs
        os.kill(remote.pid, signal.SIGKILL)
        closer.join()
    assert not hung
    with pytest.raises(ChildProcessError):
        os.waitpid(remote.pid, os.WNOHANG)  # reaped


def test_close_does_not_wait_on_a_worker_blocked_writing() -> None:
    remote = _tail(_Chatty(_run_info()))
    try:
        remote.window([[]], 1_000_000_000)  # ~10 MB of reply nobody reads
        remote.window([[]], 2_000_000_000)
    finally:
        _closes_and_reaps(remote)


def _echo_big(reply: bytes) -> ForkedChild:
    """A child that answers each request ``(n, payload)`` with ``("ok", n, reply)``."""

    def serve(link: _Link) -> None:
        receive, say = link.receive, link.say
        with contextlib.suppress(EOFError):  # the caller gone: the end
            while True:
                n, payload = receive()
                say(("ok", n, len(payload), reply))

    return ForkedChild(serve)


@pytest.mark.parametrize(
    ("request_mb", "reply_mb"),
    [(3, 5), (REQUEST_RING_BYTES * 5 // 4 >> 20, REPLY_RING_BYTES * 3 // 2 >> 20)],
    ids=["larger than the socket", "larger than the rings"],
)
def test_requests_and_replies_pass_each_other(request_mb: int, reply_mb: int) -> None:
    """The sim sends window k + 1 before it takes the reply to k. With both larger than the
    socket's buffers (``hil sim --estimators ins --imu-rate 1000``) each side used to block
    writing to the other for ever; messages larger than a ring go through it in parts, each side
    taking in the other's while it waits for room."""
    big_req, big_reply = os.urandom(request_mb << 20), os.urandom(reply_mb << 20)
    child = _echo_big(big_reply)
    watchdog = threading.Timer(120.0, child.close)  # a deadlock fails the test, never hangs it
    watchdog.start()
    try:
        for n in range(3):  # three windows out before any reply is taken
            child._send((n, big_req))
        replies = [child._reply() for _ in range(3)]
    finally:
        watchdog.cancel()
        child.close()
    assert [r[1:3] for r in replies] == [(n, len(big_req)) for n in range(3)]
    assert all(r[3] == big_reply for r in replies)


def test_the_caller_sends_on_without_waiting_for_a_worker_that_reads_nothing_yet() -> None:
    """``hil sim`` goes on with its next windows while its worker loads its kernels: 6 MB of
    requests leave with the child reading none (the socket alone held ~200 KB: the child is let
    go only after the last send returns, so a send that waits is a deadlock, which the watchdog
    turns into a failure)."""
    gate_r, gate_w = os.pipe()
    reply = os.urandom(1 << 20)

    def serve(link: _Link) -> None:
        os.close(gate_w)
        os.read(gate_r, 1)
        receive, say = link.receive, link.say
        with contextlib.suppress(EOFError):
            while True:
                n, payload = receive()
                say(("ok", n, len(payload), reply))

    child = ForkedChild(serve, REQUEST_RING_BYTES, REPLY_RING_BYTES)  # hil sim's rings
    os.close(gate_r)
    big_req = os.urandom(3 << 20)
    watchdog = threading.Timer(120.0, child.close)
    watchdog.start()
    try:
        assert not child._end.ready()  # nothing said yet
        for n in range(2):
            child._send((n, big_req))
        os.write(gate_w, b"g")
        replies = [child._reply() for _ in range(2)]
    finally:
        watchdog.cancel()
        os.close(gate_w)
        child.close()
    assert [r[1:3] for r in replies] == [(0, len(big_req)), (1, len(big_req))]
    assert all(r[3] == reply for r in replies)


def test_the_worker_goes_on_while_the_caller_reads_none_of_its_replies() -> None:
    """A worker ahead of a sim still busy with its own window: three 4 MB replies, none read yet,
    and the child has gone on through all three (it tells so down a pipe; through the socket
    alone it waited in the first, and the watchdog turned that into a failure)."""
    done_r, done_w = os.pipe()
    reply = os.urandom(4 << 20)

    def serve(link: _Link) -> None:
        os.close(done_r)
        receive, say = link.receive, link.say
        with contextlib.suppress(EOFError):
            for n in range(3):
                receive()
                say(("ok", n, reply))
            os.write(done_w, b"d")
            receive()

    child = ForkedChild(serve, REQUEST_RING_BYTES, REPLY_RING_BYTES)  # hil sim's rings
    os.close(done_w)
    watchdog = threading.Timer(120.0, child.close)
    watchdog.start()
    try:
        for n in range(3):
            child._send((n,))
        assert os.read(done_r, 1) == b"d"  # b"" (the child gone) if the watchdog fired
        assert child._end.ready()
        replies = [child._reply() for _ in range(3)]
    finally:
        watchdog.cancel()
        os.close(done_r)
        child.close()
    assert [r[1] for r in replies] == [0, 1, 2]
    assert all(r[2] == reply for r in replies)
    assert child._end.largest > 4 << 20


def test_a_worker_that_dies_halfway_through_a_reply_is_a_worker_error() -> None:
    """Half a pickle, then the worker's end closes: the reader says it died, never waits on."""
    import pickle

    def serve(link: _Link) -> None:
        link.receive()
        reply = pickle.dumps(("ok", os.urandom(3 << 20)), protocol=pickle.HIGHEST_PROTOCOL)
        link.write(reply[: len(reply) // 2])
        link._tell()  # that half announced, then gone

    child = ForkedChild(serve)
    watchdog = threading.Timer(120.0, child.close)  # a reader that waits on fails, never hangs
    watchdog.start()
    try:
        child._send((0, b"go"))
        with pytest.raises(WorkerError, match="died"):
            child._reply()
    finally:
        watchdog.cancel()
        child.close()


def test_a_garbled_control_record_is_a_worker_error() -> None:
    def serve(link: _Link) -> None:
        link.receive()
        link._send_ctrl(b"X", 0)
        link.receive()

    child = ForkedChild(serve)
    try:
        child._send((0,))
        with pytest.raises(WorkerError, match="unknown kind"):
            child._reply()
    finally:
        child.close()


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the worker through /proc")
def test_hil_sim_runs_windows_ahead_of_a_worker_still_starting(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The worker's start (numba and the kernels: ~0.45 s) no longer holds the sim up: the worker
    is let start only once the sim has sent it four windows (the sim waited for the first
    answer after two before: a deadlock, which the watchdog turns into a failure), and the file
    is the one-process file."""
    from hil.runners import sim
    from hil.runtime import jit

    gate_r, gate_w = os.pipe()
    real_setup = jit.enable_for_run
    calls: list[str] = []

    def setup() -> str:  # in the worker
        os.close(gate_w)
        os.read(gate_r, 1)
        return real_setup()

    class Gated(RemoteTail):
        def window(self, *args, **kwargs) -> None:  # type: ignore[no-untyped-def]
            super().window(*args, **kwargs)
            calls.append("window")
            if calls.count("window") == 4:
                os.write(gate_w, b"g")

        def result(self):  # type: ignore[no-untyped-def]
            calls.append("result")
            return super().result()

    me = os.getpid()

    def unstick() -> None:
        for pid in _children(me):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)

    monkeypatch.setattr(jit, "enable_for_run", setup)
    monkeypatch.setattr(sim, "RemoteTail", Gated)
    files = {}
    try:
        for worker in (False, True):
            rec = tmp_path / f"a{int(worker)}.mcap"
            watchdog = threading.Timer(120.0, unstick)
            watchdog.start()
            try:
                run_sim(SimOptions(scenario="uav_survey", duration_s=8.0, record=rec, fusion_worker=worker))
            finally:
                watchdog.cancel()
            files[worker] = rec.read_bytes()
    finally:
        os.close(gate_r)
        os.close(gate_w)
    assert calls[:4] == ["window"] * 4
    assert calls.count("result") >= 8
    assert files[True] == files[False]


def test_the_sim_runs_less_far_ahead_of_a_worker_whose_replies_are_large() -> None:
    """As many windows ahead as the reply ring holds while the sim works (a 2 kHz IMU's ~4 MB
    replies: 4), so the worker never waits for room."""
    remote = _tail(_Echo(_run_info()))
    try:
        assert remote.ahead() == AHEAD_WINDOWS  # no reply yet: a worker still starting
        remote._end.largest = 4 << 20
        assert remote.ahead() == REPLY_RING_BYTES // (4 << 20) < AHEAD_WINDOWS
        remote._end.largest = 64 << 20
        assert remote.ahead() == 1
    finally:
        remote.close()


def test_a_request_after_close_is_a_worker_error() -> None:
    child = _echo_big(b"")
    child.close()
    with pytest.raises(WorkerError, match="died"):
        child._send((0, b"late"))
    with pytest.raises(WorkerError, match="died"):
        child._reply()


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the worker through /proc")
def test_hil_sim_at_1_khz_with_its_can_bridge_in_the_worker_ends_with_the_one_process_file(
    tmp_path: Path,
) -> None:
    """The free INS alone at 1 kHz: the CAN bridge's frames out and the synced samples back are
    each more than a socket buffer holds per window (this hung for good before)."""
    files = {}
    me = os.getpid()

    def unstick() -> None:  # a hang becomes the worker's death, a WorkerError: never a hung test
        for pid in _children(me):
            with contextlib.suppress(ProcessLookupError):
                os.kill(pid, signal.SIGKILL)

    for worker in (False, True):
        rec = tmp_path / f"k{int(worker)}.mcap"
        opts = SimOptions(
            scenario="static",
            duration_s=3.0,
            record=rec,
            estimators=["ins"],
            imu_rate_hz=1000,
            fusion_worker=worker,
        )
        watchdog = threading.Timer(300.0, unstick)
        watchdog.start()
        try:
            res = run_sim(opts)
        finally:
            watchdog.cancel()
        assert res.messages > 3 * 1000 * 7
        files[worker] = rec.read_bytes()
    assert files[True] == files[False]


class _Collector(_Ticker):
    """Collects garbage in every tick, as a busy worker's allocations do sooner or later."""

    def tick(self, now_ns: int) -> list[Out]:
        gc.collect()
        return super().tick(now_ns)


class _DiesIfFinalizedInAFork:
    """Garbage whose finalizer, run in a forked child, ends that child (as a Zenoh session's
    blocks it for ever there: its runtime's threads are not in the fork)."""

    def __init__(self) -> None:
        self.pid = os.getpid()
        self.cycle = self

    def __del__(self) -> None:
        if os.getpid() != self.pid:
            os._exit(3)


def test_the_worker_never_finalizes_garbage_it_inherited() -> None:
    _DiesIfFinalizedInAFork()  # a cycle: garbage, not collected yet when the worker forks
    gc_was = gc.isenabled()
    gc.disable()  # nothing collects it here before the fork
    try:
        remote = _tail(_Collector(_run_info()))
    finally:
        if gc_was:
            gc.enable()
    try:
        remote.window([[]], 30_000_000)
        events, _ = remote.result()  # WorkerError "died" if the child ran the finalizer
    finally:
        remote.close()
    assert [e[4].kind for e in events] == ["tick"] * 3


class _Stuck(_Ticker):
    """Never answers, and never reads its socket again."""

    def tick(self, now_ns: int) -> list[Out]:
        signal.signal(signal.SIGTERM, signal.SIG_IGN)
        threading.Event().wait()
        return []


def test_close_kills_a_worker_that_does_not_leave() -> None:
    remote = _tail(_Stuck(_run_info()))
    remote.close_grace_s = 0.2
    try:
        remote.window([[]], 30_000_000)
    finally:
        _closes_and_reaps(remote)


def _children(pid: int) -> list[int]:
    try:
        return [int(c) for c in Path(f"/proc/{pid}/task/{pid}/children").read_text().split()]
    except OSError:
        return []


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="finds the worker through /proc")
@pytest.mark.skipif(not worker_possible(), reason="hil sim forks its worker with two CPUs")
def test_hil_sim_whose_worker_is_killed_says_so_in_one_line_and_keeps_the_file(tmp_path: Path) -> None:
    """The worker killed mid-run (as the OOM killer would): ``hil sim`` stops with exit code 1
    and one line naming the worker and the file, no traceback; what was flushed stays readable."""
    import subprocess
    import sys
    import time

    from hil.record.mcapio import read_session

    rec = tmp_path / "k.mcap"
    cmd = [sys.executable, "-m", "hil.cli", "sim", "--scenario", "static", "--duration", "3000"]
    cmd += ["--estimators", "ins", "--record", str(rec), "--quiet"]
    repo = Path(__file__).resolve().parents[2]
    p = subprocess.Popen(cmd, cwd=repo, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    try:
        deadline = time.monotonic() + 120.0
        while time.monotonic() < deadline and p.poll() is None:  # a few windows written
            if rec.exists() and rec.stat().st_size > 2_000_000 and _children(p.pid):
                break
            time.sleep(0.05)
        workers = _children(p.pid)
        assert p.poll() is None and len(workers) == 1, "the sim ended or never forked its worker"
        os.kill(workers[0], signal.SIGKILL)
        _out, err = p.communicate(timeout=120)
    finally:
        if p.poll() is None:
            p.kill()
            p.communicate()
    assert p.returncode == 1, err
    assert "Traceback" not in err
    lines = [line for line in err.splitlines() if line.strip()]
    assert len(lines) == 1, err
    assert lines[0].startswith("hil: the can_bridge+gnss_emulator+timesync+fusion worker process died")
    assert f"{rec} holds what was written until then" in lines[0]
    s = read_session(rec)
    assert s.truncated and len(s.records) > 10_000


def _big_reply(n: int) -> bytes:
    return bytes(range(256)) * (n // 256)


@pytest.mark.skipif(not worker_possible(1), reason="needs fork")
def test_a_forked_call_stays_until_its_reply_is_read() -> None:
    """``ForkedCall``'s child waits for the caller's close. A child that left once it had said
    its reply took with it the socket the caller acknowledges what it reads on: a caller busy
    elsewhere meanwhile (``hil info`` reading its own half) then saw a worker that died, and
    read the file again in one pass. The pause only gives such a child time to leave: with the
    child waiting, the result comes whatever the pause."""
    want = _big_reply(600 << 10)  # within the reply ring: said whole before the caller reads
    call = ForkedCall("test reader", _big_reply, 600 << 10)
    try:
        time.sleep(0.5)
        assert call.result() == want
    finally:
        call.close()

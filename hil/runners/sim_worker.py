"""The tail of ``hil sim``'s pipeline in a second process, one window behind; ``hil rerun``'s cores.

Why: nothing in the sim consumes the tail's outputs but the recording (the nodes form a
pipeline). So while the worker runs the fusion -- and, when the fusion is light, the CAN bridge,
GNSS emulator and time sync before it (``hil.runners.sim.tail_split``) -- over window *k*, the
sim's own process runs the world and the IMU emulator over window *k + 1*; window *k* is written
once the worker's outputs for it are back. The worker runs the very node objects the
one-process sim would (forked after ``start``, so their state is those objects'), with the same
inputs in the same order through the same scheduler (``RemoteTail``), so the outputs, their
order and the file are byte for byte those of one process; only the wall time differs.

``fork`` and shared memory: no ``multiprocessing.Process`` (a campaign runs sims inside daemonic
workers, which may not start one). The child never returns into the caller's code: it leaves
with ``os._exit``, whatever happens, and reports an exception as its text. The two ends speak
pickle: both are this process's own code and objects (rings of shared memory and a socketpair
made before the fork), never a file or the wire, which is why tests/docker/test_compose_static.py
allows it here and nowhere else. Each way the pickles stream through a ring of shared memory
(``_Link``) many windows deep: the sim runs ahead of a worker still loading its kernels, and a
worker whose replies the sim has not read yet goes on with its next window (through the socket
alone, ~200 KB, each waited on the other; both larger than it, at an IMU of 1 kHz and up, two
blocking writers waited for ever).
"""

from __future__ import annotations

import contextlib
import gc
import mmap
import operator
import os
import pickle
import signal
import socket
import struct
import threading
import time
import traceback
from collections.abc import Callable, Sequence
from typing import Any, Protocol

from hil.messages import decode, encode
from hil.nodes.base import CAN_RX, Node, Out
from hil.runtime.errors import WorkerError

__all__ = [
    "WORKER_MIN_ESTIMATORS",
    "EncodedInput",
    "ForkedChild",
    "RemoteNode",
    "RemoteTail",
    "Replayed",
    "TailScheduler",
    "drive",
    "portable",
    "replay_split",
    "worker_pays",
    "worker_possible",
]

# a worker for a fusion of at least this many estimators (``hil sim``, ``hil rerun``): with one or
# two the pickling to and from the worker cost more than the second core gave (static, kfvel:
# +10 % CPU)
WORKER_MIN_ESTIMATORS = 3

# one recomputed solution as ``hil rerun`` matches it: estimator, seq, encoded bytes, time of
# validity, and the solution itself when the caller keeps the outputs (else None)
Replayed = tuple[str, int, bytes, int, Any]

# one input of ``hil rerun`` as a worker is sent it: the payload as recorded, its message type,
# publisher and whether the live predictor took it. The bytes, not the decoded message: pickling a
# message struct and rebuilding it in the worker cost 2.3 + 2.4 µs (8 µs of the worker's CPU in a
# rerun: 0.99 of its 9.06 s on 300 s of straight_level), a decode there ~1.9
EncodedInput = tuple[bytes, type, str, bool]

# each direction's ring of shared memory: what one side has said and the other not read yet.
# ``hil sim``'s worker: the replies' 16 windows of uav_survey at 400 Hz, 4 at 2 kHz (a request is
# a sixth of its reply or less). Its pages are touched as it fills, once (~0.8 ms a MB in each
# process: with rings this size a time-sync rerun of uav_survey 120 s took 5 % longer): at most
# this much more resident memory, shared by both. A caller with one request at a time (``hil rerun``) needs no
# depth: its messages go through small rings in parts, as through a socket.
REPLY_RING_BYTES = 16 << 20
REQUEST_RING_BYTES = 8 << 20
SMALL_RING_BYTES = 1 << 20
# windows ``hil sim`` may run ahead of its worker: its start (numba and the kernels loaded there,
# ~0.45 s) is ~15 windows of the sim's own work at 400 Hz, which it held up before (uav_survey
# 120 s: 0.41 s, 9 % of the sim's wall time)
AHEAD_WINDOWS = 16

# a control record on the socket: kind, a position (bytes a side has put into, or taken out of, a
# ring since the start)
_CTRL = struct.Struct("<cQ")
_DATA, _TAKEN = b"D", b"T"
# a long message is announced in parts this large, so the reader unpickles it as it comes
_TELL_EVERY = 256 << 10


class _Link:
    """One end of a ``ForkedChild``'s channel: pickles streamed through two rings of shared memory,
    one each way, made before the fork; the socket pair carries only small control records --
    "the ring holds your bytes up to here" (``D``, at a message's end and every
    ``_TELL_EVERY`` bytes of a long one, which the reader unpickles as it comes) and "I have
    taken yours up to here" (``T``).

    Why not the socket alone: its buffers hold ~200 KB, less than a window's outputs, so a worker
    whose reply the sim was not reading yet waited, and a sim ahead of a worker still loading its
    kernels waited to send. The rings hold many windows both ways, so neither side waits for the
    other while it computes. A side that waits (for bytes to read, or for room in its ring) takes
    in everything the other has said meanwhile, copying it out of the ring and saying so: two
    sides waiting on each other always free each other's rings, so they never wait for ever. A
    message larger than a ring goes through it in parts. The end of either side is the end of
    the socket: the other's wait raises ``died(why)``."""

    def __init__(
        self, sock: socket.socket, out: mmap.mmap, into: mmap.mmap, died: Callable[[object], Exception]
    ) -> None:
        self._sock = sock
        self._died = died
        self._out, self._out_size = out, len(out)
        self._written = 0  # bytes put into the outgoing ring
        self._said = 0  # of them, told to the other side
        self._peer_took = 0  # of them, taken by the other side
        self._in, self.in_size = into, len(into)
        self._took = 0  # bytes taken out of the incoming ring
        self._inbox = bytearray()  # taken out of the ring, not read yet
        self._consumed = 0  # bytes read
        self._ctrl = bytearray()  # control bytes received, not parsed yet
        self.largest = 0  # bytes of the largest message received so far

    # -- writing: the pickler's file ----------------------------------------------------------
    def write(self, data: bytes | bytearray | memoryview) -> None:
        view = memoryview(data).cast("B")
        size = self._out_size
        while view:
            room = size - (self._written - self._peer_took)
            if not room:
                self._tell()  # what it holds so far, so the other side can take it
                self._take_in()
                continue
            pos = self._written % size
            n = min(len(view), room, size - pos)
            self._out[pos : pos + n] = view[:n]
            self._written += n
            view = view[n:]
        if self._written - self._said >= _TELL_EVERY:  # the other side can begin to read
            self._tell()

    def say(self, obj: Any) -> None:
        """``obj`` pickled to the other side (streamed through the ring as the pickler makes it)."""
        pickle.dump(obj, self, protocol=pickle.HIGHEST_PROTOCOL)
        self._tell()

    def _tell(self) -> None:
        """The other side told where the ring holds its bytes up to (once per new bytes)."""
        if self._said < self._written:
            self._said = self._written
            self._send_ctrl(_DATA, self._written)

    def _send_ctrl(self, kind: bytes, position: int) -> None:
        try:
            self._sock.sendall(_CTRL.pack(kind, position))
        except (OSError, ValueError) as err:  # ValueError: its socket already closed here
            raise self._died(err) from err

    # -- reading: the unpickler's file ----------------------------------------------------------
    def receive(self) -> Any:
        """The next message the other side says, unpickled as it comes (waiting for it)."""
        before = self._consumed
        obj = pickle.load(self)
        self.largest = max(self.largest, self._consumed - before)
        return obj

    def ready(self) -> bool:
        """Whether the other side has said something not read yet (without waiting)."""
        if not self._inbox:
            self._take_in(wait=False)
        return bool(self._inbox)

    def read(self, n: int) -> bytes:  # the unpickler always asks for a size
        while len(self._inbox) < n:
            self._take_in()
        return self._pop(n)

    def readinto(self, b: Any) -> int:
        out = memoryview(b).cast("B")
        n = len(out)
        while len(self._inbox) < n:
            self._take_in()
        with memoryview(self._inbox) as view:
            out[:] = view[:n]
        del self._inbox[:n]
        self._consumed += n
        return n

    def readline(self) -> bytes:
        while (i := self._inbox.find(b"\n")) < 0:
            self._take_in()
        return self._pop(i + 1)

    def _pop(self, n: int) -> bytes:
        with memoryview(self._inbox) as view:
            out = bytes(view[:n])
        del self._inbox[:n]
        self._consumed += n
        return out

    def _take_in(self, wait: bool = True) -> None:
        """Wait for control records (``wait``: else take what is there); act on every one that came
        (the data they announce copied out of the ring, and said so)."""
        try:
            got = self._sock.recv(1 << 16, 0 if wait else socket.MSG_DONTWAIT)
        except BlockingIOError:
            return
        except OSError as err:
            raise self._died(err) from err
        if not got:
            raise self._died("its end of the socket closed")
        ctrl = self._ctrl
        ctrl += got
        n = len(ctrl) - len(ctrl) % _CTRL.size
        took = self._took
        for kind, position in _CTRL.iter_unpack(memoryview(ctrl)[:n]):
            if kind == _TAKEN:
                self._peer_took = position
            elif kind == _DATA:
                self._copy_out(position)
            else:
                raise self._died(f"a control record of unknown kind {kind!r}")
        del ctrl[:n]
        if self._took > took:
            self._send_ctrl(_TAKEN, self._took)

    def _copy_out(self, position: int) -> None:
        size = self.in_size
        if position - self._took > size or position < self._took:
            raise self._died(f"a ring position out of range ({position}, took {self._took})")
        with memoryview(self._in) as into:
            while self._took < position:
                pos = self._took % size
                n = min(position - self._took, size - pos)
                self._inbox += into[pos : pos + n]
                self._took += n

    def drain(self) -> None:
        """Take in, and drop unread, all the other side says until its end: a child that has
        stopped serving (its failure said) stays until its caller closes, so that a caller still
        sending (``hil sim`` runs windows ahead) reads why instead of failing on a closed socket
        ("Broken pipe")."""
        with contextlib.suppress(EOFError):
            while True:
                self._take_in()
                self._inbox.clear()

    def close(self) -> None:
        """Shut down (a side waiting sees its end) and close."""
        with contextlib.suppress(OSError):
            self._sock.shutdown(socket.SHUT_RDWR)
        with contextlib.suppress(OSError):
            self._sock.close()


# one input as ``drive`` reads it: rig time first, key and message last (the scheduler's events
# carry producer and publication order between)
Event = Sequence[Any]


def drive(node: Node, now: Sequence[Event], t_end_ns: int, publish: Callable[[list[Out], int], None]) -> bool:
    """One window of one node: its ticks before ``t_end_ns`` and its inputs ``now`` (sorted), in
    rig-time order, a tick before an input at the same time; ``publish(outs, t)`` after each.
    True if the node still wants a tick."""
    j, n = 0, len(now)
    t_tick = node.next_tick_ns()
    moves = node.inputs_move_timers
    while True:
        if t_tick is not None and t_tick < t_end_ns and (j == n or t_tick <= now[j][0]):
            publish(node.tick(t_tick), t_tick)
            t_tick = node.next_tick_ns()
        elif j < n:
            e = now[j]
            j += 1
            publish(node.on_message(e[-2], e[-1], e[0]), e[0])
            if moves:
                t_tick = node.next_tick_ns()
        else:
            return t_tick is not None


def worker_possible(cpus: int = 2) -> bool:
    """More processes are worth it: ``fork`` exists, this process may run on ``cpus`` CPUs, and
    it is the main thread that asks (a sim embedded in a thread pool -- a campaign's Dask worker
    -- stays in one process: forking beside other threads can inherit their locks held)."""
    if not hasattr(os, "fork") or threading.current_thread() is not threading.main_thread():
        return False
    try:
        return len(os.sched_getaffinity(0)) >= cpus
    except (AttributeError, OSError):
        return (os.cpu_count() or 1) >= cpus


def worker_pays(node: Node) -> bool:
    """The fusion ``node`` in a worker, by default (``hil rerun``; ``hil sim`` always uses a
    second process when it can, ``hil.runners.sim.tail_split`` says for which nodes): it runs at
    least ``WORKER_MIN_ESTIMATORS`` estimators and a second process is possible."""
    estimators = getattr(getattr(node, "config", None), "estimators", ())
    return len(estimators) >= WORKER_MIN_ESTIMATORS and worker_possible()


class ForkedChild:
    """A forked child serving ``serve(link)`` on its end of a ``_Link`` (``RemoteNode``,
    ``RemoteTail``): requests out, replies in, either side's failure a ``WorkerError`` naming
    it, and the child stopped and reaped by :meth:`close`. The child never returns into the
    caller's code: it leaves with ``os._exit``, whatever happens. What it raises is said to the
    caller before it leaves, and the child then stays until the caller closes (:meth:`_Link.drain`):
    a failing ``setup`` as one line naming the cause (``("setup", why)``), anything else out of
    ``serve`` with its traceback (``("error", text)``), each a ``WorkerError`` at the caller's next
    reply -- never only a closed socket ("Broken pipe") that says nothing of why.

    The child freezes the heap it inherits before anything else (``gc.freeze``): garbage the
    caller had not collected yet is never finalized there. A finalizer run in a fork can block
    for ever -- a Zenoh session's waits on a runtime whose threads the fork does not have (seen:
    ``hil sim`` in a test process that had opened sessions before, its worker parked in Zenoh's
    runtime under a collection)."""

    name = "worker"
    close_grace_s = 5.0  # after its socket ends, how long the child has to leave before SIGKILL

    def __init__(
        self,
        serve: Callable[[_Link], None],
        request_ring: int = SMALL_RING_BYTES,
        reply_ring: int = SMALL_RING_BYTES,
        setup: Callable[[], object] | None = None,
    ) -> None:
        """``request_ring``, ``reply_ring``: bytes each way that one side may have said and the
        other not read yet, without either waiting. ``setup``: called first in the child."""
        parent, child = socket.socketpair()
        requests, replies = mmap.mmap(-1, request_ring), mmap.mmap(-1, reply_ring)
        pid = os.fork()
        if pid == 0:
            code = 1
            link = None
            starting = True
            try:
                gc.freeze()
                # Ctrl-C reaches the whole process group: the caller decides how the run ends
                # (``hil sim`` finishes its file first) and this child goes when its socket ends
                signal.signal(signal.SIGINT, signal.SIG_IGN)
                signal.signal(signal.SIGTERM, signal.SIG_IGN)
                parent.close()
                link = _Link(child, replies, requests, lambda why: EOFError(why))
                if setup is not None:
                    setup()
                starting = False
                serve(link)
                code = 0
            except BaseException as err:  # said to the caller, which raises it: it leaves below
                if link is not None:
                    _say_failure(link, err, starting)
            finally:
                os._exit(code)
        child.close()
        self.pid = pid
        self._end = _Link(parent, requests, replies, self._died)

    def _died(self, why: object) -> WorkerError:
        return WorkerError(f"hil: the {self.name} worker process died ({why})")

    def _send(self, req: tuple[Any, ...]) -> None:
        """``req`` to the child (pickled: this process's own objects, to its own fork), streamed
        out as the pickler makes it."""
        self._end.say(req)

    def _reply(self) -> tuple[Any, ...]:
        """What the child answered next; an error it reported, or its end, raised here."""
        try:
            reply: tuple[Any, ...] = self._end.receive()
        except (EOFError, pickle.UnpicklingError) as err:  # a message that is not one
            raise self._died(err) from err
        if reply[0] == "error":
            raise WorkerError(f"hil: the {self.name} worker failed:\n{reply[1]}")
        if reply[0] == "setup":  # it never started serving: one line, the cause
            raise WorkerError(f"hil: the {self.name} worker could not start: {reply[1]}")
        if reply[0] == "raise":  # the worker has stopped
            raise reply[1]
        return reply

    def close(self) -> None:
        """Stop the worker and reap it (also after a failure on either side). A shutdown, not a
        message: a child blocked writing a large reply while this side is not reading would
        never see one; it sees its socket end, and leaves. One still there ``close_grace_s``
        later (stuck, or deep in a window nobody will read) is killed: closing never hangs."""
        self._end.close()
        deadline = time.monotonic() + self.close_grace_s
        with contextlib.suppress(ChildProcessError):
            while os.waitpid(self.pid, os.WNOHANG)[0] == 0:
                if time.monotonic() >= deadline:
                    with contextlib.suppress(ProcessLookupError):
                        os.kill(self.pid, signal.SIGKILL)
                    os.waitpid(self.pid, 0)
                    return
                time.sleep(0.005)


def _say_failure(link: _Link, err: BaseException, starting: bool) -> None:
    """In a child: what it raised said to the caller -- while ``starting`` (its ``setup``) in one
    line, the exception and where it was raised, else with its traceback -- and then everything
    the caller sends taken in and dropped until it closes (``_Link.drain``). Nothing, if the
    caller is gone already."""
    if starting:
        where = traceback.extract_tb(err.__traceback__)[-1:]
        at = f" ({_short(where[0].filename)}:{where[0].lineno} in {where[0].name})" if where else ""
        said = " ".join(ln.strip() for ln in traceback.format_exception_only(err) if ln.strip())
        reply: tuple[Any, ...] = ("setup", said + at)
    else:
        reply = ("error", "".join(traceback.format_exception(err)))
    with contextlib.suppress(Exception):  # EOFError: the caller is gone
        link.say(reply)
    link.drain()


def _short(filename: str) -> str:
    """A source file of this checkout from its root (``hil/runtime/prebuilt.py``), others as they are."""
    root = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
    return os.path.relpath(filename, root) if filename.startswith(root + os.sep) else filename


class ForkedCall(ForkedChild):
    """``fn(*args)`` in a forked child, started at once, beside the caller's own work;
    ``result`` waits for what it returned (``fn`` failing there is a ``WorkerError`` here).
    :meth:`close` ends it, done or not: nothing it does is kept unless asked for."""

    close_grace_s = 0.2

    def __init__(self, name: str, fn: Callable[..., Any], *args: Any) -> None:
        self.name = name

        def serve(link: _Link) -> None:
            try:
                reply: tuple[Any, ...] = ("ok", fn(*args))
            except Exception:
                reply = ("error", traceback.format_exc())
            link.say(reply)
            # stay until the caller closes: it tells this end how far it has read, and a child
            # gone before that is, to the caller, one that died mid-reply
            with contextlib.suppress(EOFError):
                link.receive()

        super().__init__(serve)

    def result(self) -> Any:
        return self._reply()[1]


class RemoteNode(ForkedChild):
    """A node run in a forked child (``hil rerun``): ``replay`` or ``call`` sends a batch of
    work, ``replayed`` or ``called`` waits for its answer; between the two the caller is free
    to work on the next batch."""

    def __init__(self, node: Node, setup: Callable[[], object] | None = None) -> None:
        """``setup``: called first in the child (the fusion's compiled kernels loaded there)."""
        self.name = node.name

        def serve(link: _Link) -> None:  # the worker
            _serve(node, link)

        super().__init__(serve, setup=setup)

    def replay(
        self,
        inputs: list[EncodedInput],
        keep: bool,
        only: frozenset[str] | None = None,
        relay: dict[str, bool | None] | None = None,
        verdicts: bool = False,
    ) -> None:
        """``hil rerun``: these inputs (``EncodedInput``: decoded there) through the node's
        ``replay`` in this order; ``replayed`` takes their solutions (``only``: those of these
        estimators). ``relay`` and ``verdicts``: the GNSS gate's verdicts taken from, or kept
        for, the other core of a split rerun (:func:`replay_split`)."""
        self._send(("replay", inputs, keep, only, relay, verdicts))

    def call(self, fn: Callable[..., Any], *args: Any) -> None:
        """``fn(node, *args)`` in the worker; ``called`` takes what it returned. ``fn`` is a
        module-level function (pickled by name): ``hil rerun --core timesync``'s node side."""
        self._send(("call", fn, args))

    def called(self) -> Any:
        """What the oldest ``call`` sent returned."""
        return self._reply()[1]

    def replayed(self) -> list[list[Replayed]]:
        """The solutions of the oldest ``replay`` sent, one list per input, encoded there."""
        return self.replayed_split()[0]

    def replayed_split(self) -> tuple[list[list[Replayed]], dict[str, bool | None] | None]:
        """``replayed``, and the gate's verdicts kept meanwhile (asked for with ``verdicts``)."""
        _ok, out, verdicts = self._reply()
        return out, verdicts


class LocalNode:
    """The second core of a split ``hil rerun`` in this process, with :class:`RemoteNode`'s
    interface: on two CPUs a second worker would share them with this one, which reads and
    compares at a fraction of a CPU. ``replay`` runs the batch at once (inputs decoded): the
    caller sends its worker the next one first, so both run meanwhile."""

    def __init__(self, node: Node) -> None:
        self.name = node.name
        self.node = node
        self._done: list[tuple[list[list[Replayed]], dict[str, bool | None] | None]] = []

    def replay(
        self,
        inputs: list[tuple[Any, str, bool]],
        keep: bool,
        only: frozenset[str] | None = None,
        relay: dict[str, bool | None] | None = None,
        verdicts: bool = False,
    ) -> None:
        self._done.append(replay_split(self.node, inputs, keep, only, relay, verdicts))

    def replayed(self) -> list[list[Replayed]]:
        return self.replayed_split()[0]

    def replayed_split(self) -> tuple[list[list[Replayed]], dict[str, bool | None] | None]:
        return self._done.pop(0)

    def close(self) -> None:
        self._done.clear()


# a python-can frame as shipped to a tail (``portable``): pickling can.Message itself costs
# ~2.6 µs a side, four frames an IMU sample; these fields, rebuilt there, a tenth of that
_FRAME_FIELDS = (
    "timestamp",
    "arbitration_id",
    "is_extended_id",
    "is_remote_frame",
    "is_error_frame",
    "channel",
    "dlc",
    "data",
    "is_fd",
    "is_rx",
    "bitrate_switch",
    "error_state_indicator",
)
_frame_fields = operator.attrgetter(*_FRAME_FIELDS)


class _NoFrame:
    """No event is one of these: ``portable`` before a tail imported python-can."""


# python-can's frame type, bound by the first ``RemoteTail`` (before it forks): ``hil rerun``
# imports this module without python-can (44 ms of its start-up)
_Frame: type = _NoFrame


def portable(event: Sequence[Any]) -> tuple[Any, ...]:
    """An inbox event as it crosses to a tail: a CAN frame as its fields, anything else as is."""
    msg = event[-1]
    if type(msg) is _Frame:
        return (*event[:-1], _frame_fields(msg))
    return tuple(event)


def _rebuilt(event: tuple[Any, ...]) -> tuple[Any, ...]:
    f = event[-1]
    if type(f) is tuple and event[3].startswith(CAN_RX):  # a frame's fields (``portable``)
        return (*event[:-1], _Frame(*f))  # its data a bytearray of its own, as sent
    return event


class TailScheduler(Protocol):
    """What a tail's worker runs (``hil.runners.sim.Scheduler``, made in the child)."""

    nodes: list[Node]

    def run_tail(
        self, split: int, boxes: list[list[Any]], t_end_ns: int, finish_ns: int | None
    ) -> tuple[list[tuple[int, int, int, str, Any]], bool]: ...


class RemoteTail(ForkedChild):
    """The nodes of a pipeline from ``split`` on, run in a forked child by a scheduler of their own.

    ``window`` sends the inputs this process's nodes published to them before ``t_end_ns``;
    ``result`` waits for what they published in that window, ready for the file;
    between the two the caller works on its next window. Nothing flows back upstream (the sim
    checks its nodes form a pipeline), so the child's outputs only join the file."""

    def __init__(
        self,
        nodes: list[Node],
        split: int,
        make_scheduler: Callable[[], TailScheduler],
        setup: Callable[[], object] | None = None,
        prepare: Callable[[tuple[int, int, int, str, Any]], tuple[Any, ...]] | None = None,
    ) -> None:
        """``make_scheduler()``: the child's scheduler over the same (forked) ``nodes``.
        ``setup``: called first in the child (the fusion's compiled kernels loaded there, so
        that this process never imports numba). ``prepare(event)``: what each output event
        ``(t, producer, order, key, message)`` is sent back as (the sim: with its bytes for the
        file, made there); default the event itself."""
        global _Frame
        import can

        _Frame = can.Message
        self.split = split
        self.names = [n.name for n in nodes[split:]]
        self.name = "+".join(self.names)
        self._snapshot = [(n.name, n.counters(), n.last_error) for n in nodes[split:]]

        def serve(link: _Link) -> None:  # the worker
            _serve_tail(make_scheduler(), split, link, prepare)

        super().__init__(serve, REQUEST_RING_BYTES, REPLY_RING_BYTES, setup)

    def window(self, boxes: list[list[tuple[Any, ...]]], t_end_ns: int) -> None:
        """Each tail node's inputs from upstream (``portable`` events), before ``t_end_ns``."""
        self._send((boxes, t_end_ns, None))

    def finish_request(self, boxes: list[list[tuple[Any, ...]]], t_end_ns: int, t_ns: int) -> None:
        """As ``window``, then each tail node told ``finish(t_ns)`` in pipeline order."""
        self._send((boxes, t_end_ns, t_ns))

    def result(self) -> tuple[list[tuple[Any, ...]], bool]:
        """The oldest window's outputs (each as ``prepare`` made it; the caller sorts them into
        file order with its own), and whether a tail node still wants a tick or has input in
        flight."""
        _ok, events, busy, self._snapshot = self._reply()
        return events, busy

    def ready(self) -> bool:
        """Whether the oldest window's outputs are back (without waiting)."""
        return self._end.ready()

    def ahead(self) -> int:
        """How many windows the caller may have sent and not taken back: ``AHEAD_WINDOWS``, or
        fewer once its replies are large (as many as its ring holds while the caller works)."""
        largest, ring = self._end.largest, self._end.in_size
        return AHEAD_WINDOWS if not largest else max(1, min(AHEAD_WINDOWS, ring // largest))

    def snapshot(self) -> list[tuple[str, Any, str]]:
        """Each tail node's name, counters and last error after the last window taken."""
        return list(self._snapshot)


def _serve_tail(
    sched: TailScheduler,
    split: int,
    link: _Link,
    prepare: Callable[[tuple[int, int, int, str, Any]], tuple[Any, ...]] | None,
) -> None:
    receive, say = link.receive, link.say
    tail = sched.nodes[split:]
    while True:
        try:
            boxes, t_end, finish_ns = receive()
        except EOFError:
            return
        try:
            boxes = [[_rebuilt(e) for e in box] for box in boxes]
            out, busy = sched.run_tail(split, boxes, t_end, finish_ns)
            events = out if prepare is None else [prepare(e) for e in out]
            snap = [(n.name, n.counters(), n.last_error) for n in tail]
            reply: tuple[Any, ...] = ("ok", events, busy, snap)
        except Exception:
            reply = ("error", traceback.format_exc())
        say(reply)
        if reply[0] == "error":
            link.drain()  # a caller sending windows ahead reads this, not a closed socket
            return


def _serve(node: Node, link: _Link) -> None:
    receive, say = link.receive, link.say
    while True:
        try:
            req = receive()
        except EOFError:
            return
        try:
            if req[0] == "call":
                try:
                    reply: tuple[Any, ...] = ("ok", req[1](node, *req[2]))
                except ValueError as err:  # bad input (a malformed payload): raised as the caller's
                    reply = ("raise", err)
            else:  # replay
                inputs = [(decode(cls, payload), source, p) for payload, cls, source, p in req[1]]
                reply = ("ok", *replay_split(node, inputs, *req[2:]))
        except Exception:
            reply = ("error", traceback.format_exc())
        say(reply)
        if reply[0] in ("error", "raise"):
            link.drain()
            return


def replay_split(
    node: Any,
    inputs: list[tuple[Any, str, bool]],
    keep: bool,
    only: frozenset[str] | None = None,
    relay: dict[str, bool | None] | None = None,
    verdicts: bool = False,
) -> tuple[list[list[Replayed]], dict[str, bool | None] | None]:
    """:func:`replay_encoded` as one core of a split ``hil rerun`` (``split_estimators``): the
    core that runs the GNSS gate's reference keeps its verdicts on these inputs' fixes
    (``verdicts``) and hands them back; the core without it takes them (``relay``, every batch's
    kept until its fix comes: both cores release a fix at the same input, so in the same batch)."""
    core = node.core
    if relay is not None:
        if core.gate_relay is None:
            core.gate_relay = {}
        core.gate_relay.update(relay)
    core.gate_verdicts = {} if verdicts else None
    out = replay_encoded(node, inputs, keep, only)
    kept, core.gate_verdicts = core.gate_verdicts, None
    return out, kept


def replay_encoded(
    node: Any, inputs: list[tuple[Any, str, bool]], keep: bool, only: frozenset[str] | None = None
) -> list[list[Replayed]]:
    """Inputs through ``node.replay`` (the fusion's, ``hil rerun``) in order: each one's
    solutions encoded, as the rerun compares them -- in the worker, or inline without one.
    ``only``: the solutions of these estimators (a worker's share of a split rerun)."""
    return [
        [
            (s.estimator, s.seq, encode(s), s.stamp_ns, s if keep else None)
            for s in node.replay(*item)
            if only is None or s.estimator in only
        ]
        for item in inputs
    ]

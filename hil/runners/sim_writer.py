"""``hil sim``'s recording written by a second process, a window behind.

Why: appending ~3300 messages a rig second to the open MCAP chunk, compressing each closed chunk
with zstd and writing it is ~15 % of ``hil sim``'s own process, the pipeline's slower one on
straight_level. Here that process makes every ``SessionWriter`` call as before, but each is
kept as an operation and a window's operations go to a forked child in one message at the window's
flush; the child makes the same calls on a real :class:`SessionWriter` in the same order, so the
file is byte for byte the one-process file (``tests/unit/test_sim_writer.py``). The messages are
already encoded here (their bytes go over), so the child never decodes.

A failure in the child (a full disk) comes back as the same :class:`RecordingError` at the next
flush or at ``close``; a child that died says so. What it flushed before stays in the file, as
with :class:`SessionWriter`. The fork, the socket pair and what goes over it are
:mod:`hil.runners.sim_worker`'s (``ForkedChild``, ``child_ends``): this process's own objects to
its own fork, never a file or the wire.
"""

from __future__ import annotations

import select
import socket
import traceback
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.messages import Message
from hil.record.mcapio import RecordingError, SessionWriter
from hil.runners.sim_worker import ForkedChild, child_ends
from hil.runtime import heap

__all__ = ["RemoteWriter"]


class RemoteWriter(ForkedChild):
    """:class:`SessionWriter`'s interface for ``hil sim``, the calls made in a forked child."""

    def __init__(self, path: str | Path) -> None:
        self.path = Path(path)
        self.closed = False
        self._ops: list[tuple[Any, ...]] = []
        self._tokens = 0
        super().__init__(lambda sock: _serve(sock, self.path))
        try:
            self._reply()  # the file is open (or the child's RecordingError is raised here)
        except BaseException:
            self._reap()
            raise

    def bind(
        self, topic: str, cls: type[Message], publisher: str | None = None, origin: str = ""
    ) -> Callable[[bytes, int, int, int], None]:
        """As :meth:`SessionWriter.bind`; a message is kept as ``(channel, payload, log time,
        publish time, seq)``, the channel a number the child maps to its own ``put``."""
        token = self._tokens
        self._tokens += 1
        ops = self._ops
        ops.append(("bind", token, topic, cls, publisher, origin))
        append = ops.append

        def put(payload: bytes, log_time_ns: int, publish_time_ns: int, seq: int) -> None:
            append((token, payload, log_time_ns, publish_time_ns, seq))

        return put

    def write_wellknown(self, d: Any, *, log_time_ns: int) -> None:
        self._ops.append(("write_wellknown", d, log_time_ns))

    def add_metadata(self, name: str, data: dict[str, Any]) -> None:
        self._ops.append(("add_metadata", name, data))

    def add_attachment(
        self, name: str, data: bytes, media_type: str = "text/plain", log_time_ns: int = 0
    ) -> None:
        self._ops.append(("add_attachment", name, data, media_type, log_time_ns))

    def flush(self) -> None:
        """The window's operations to the child, then its chunk closed there; a failure the
        child reported since the last flush is raised here."""
        self._ops.append(("flush",))
        self._send()
        readable, _, _ = select.select([self._sock], [], [], 0)
        if readable:  # the child speaks only to fail, or to answer tell/close
            self._reply()

    def tell(self) -> int:
        """Bytes the child has handed to the OS, after every operation so far."""
        self._ops.append(("tell",))
        self._send()
        return int(self._reply()[1])

    def close(self) -> None:
        if self.closed:
            return
        self.closed = True
        try:
            self._ops.append(("close",))
            self._send()
            self._reply()
        finally:
            self._reap()

    def abandon(self) -> None:
        """Stop the child and keep what it flushed; never raises."""
        self.closed = True
        self._reap()

    def _send(self) -> None:
        ops = self._ops
        try:
            self._put(ops)
        except OSError as err:
            if select.select([self._sock], [], [], 0)[0]:
                self._reply()  # the child said why it stopped: that is the error
            raise RecordingError(f"the writer process for {self.path} died ({err})") from err
        finally:
            ops.clear()  # in place: the bound puts append to this list

    def _reply(self) -> tuple[Any, ...]:
        try:
            reply: tuple[Any, ...] = self._get()
        except (EOFError, OSError) as err:
            raise RecordingError(f"the writer process for {self.path} died ({err or 'no reply'})") from err
        if reply[0] == "raise":
            raise reply[1]
        if reply[0] == "error":
            raise RecordingError(f"the writer process for {self.path} failed:\n{reply[1]}")
        return reply


def _serve(sock: socket.socket, path: Path) -> None:
    receive, say = child_ends(sock)
    try:
        w = SessionWriter(path)
    except RecordingError as err:
        say(("raise", err))
        return
    if heap.command_process:
        heap.offline_collector()
    say(("ok",))
    puts: dict[int, Callable[[bytes, int, int, int], None]] = {}
    try:
        while True:
            try:
                ops = receive()
            except EOFError:  # the caller is gone without closing: keep what was flushed
                w.abandon()
                return
            for op in ops:
                head = op[0]
                if type(head) is int:
                    puts[head](op[1], op[2], op[3], op[4])
                elif head == "bind":
                    puts[op[1]] = w.bind(*op[2:])
                elif head == "flush":
                    w.flush()
                elif head == "write_wellknown":
                    w.write_wellknown(op[1], log_time_ns=op[2])
                elif head == "add_metadata":
                    w.add_metadata(op[1], op[2])
                elif head == "add_attachment":
                    w.add_attachment(op[1], op[2], op[3], op[4])
                elif head == "tell":
                    say(("ok", w.tell()))
                elif head == "close":
                    w.close()
                    say(("ok",))
                    return
    except RecordingError as err:
        w.abandon()
        say(("raise", err))
    except OSError as err:  # a full disk, a file gone: as SessionWriter's caller would see it
        w.abandon()
        say(("raise", RecordingError(f"cannot write {path}: {err.strerror or err}")))
    except Exception:
        w.abandon()
        say(("error", traceback.format_exc()))

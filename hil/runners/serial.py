"""Serial lines for the live runner: a receiver's UART as a device, gpsd or the rig reads it.

``LineWriter`` is the emulator's side. The same bytes go to every line it was given:

- a **pseudo-terminal** per path in ``links``: the pty's slave end, symlinked at the path, is
  what a device under test, gpsd or the rig's ``gnss_bridge`` opens like a UART (gpsd's own test
  tool, gpsfake, feeds receivers' logs the same way). Raw mode, the baud rate set on it (a pty
  does not clock bytes, so the writer paces them);
- a **TCP server** (``tcp_listen``, loopback unless told otherwise) for containers and hosts
  without a shared ``/dev``: every connected client gets the stream;
- a **real serial device** (``device``, e.g. a USB-serial adapter's ``/dev/ttyUSB0``) opened at
  the baud rate, whose UART clocks the bytes itself.

Bytes are written at the UART's pace: each burst from its first byte's time, a chunk a
millisecond, so a reader sees them arrive as off a real line. A pty nobody reads fills (about
4 KiB) and then drops what does not fit, counted as ``line.unread_bytes`` -- a UART with nothing
connected sends into the void; it never blocks the emulator.

``LineReader`` is the bridge's side: it opens a path (retrying until the writer has made it) or
connects to a TCP server (retrying), and returns what each read got with its receive time.
"""

from __future__ import annotations

import contextlib
import errno
import fcntl
import os
import queue
import select
import socket
import struct
import termios
import threading
import time
import tty
from collections.abc import Callable
from pathlib import Path
from typing import Any

from hil.wire.line import byte_time_ns

_BAUDS = {
    9600: termios.B9600,
    19200: termios.B19200,
    38400: termios.B38400,
    57600: termios.B57600,
    115200: termios.B115200,
    230400: termios.B230400,
    460800: termios.B460800,
    921600: termios.B921600,
}
CHUNK_S = 0.001  # the writer hands the line a millisecond of bytes at a time
UNREAD_WAIT_S = 1.0  # at close, how long a pty's reader gets to take the bytes still unread


class LineError(OSError):
    """A line that cannot be made or opened; the message says which path and why."""


def tcp_endpoint(where: str) -> tuple[str, int]:
    """``--gnss-tcp [HOST]:PORT`` as (host, port), the host 127.0.0.1 when left out."""
    host, sep, port = where.rpartition(":")
    if not sep or not port.isdigit() or not 1 <= int(port) <= 65535:
        raise LineError(f"--gnss-tcp {where}: expected HOST:PORT with PORT 1-65535 (e.g. 127.0.0.1:5020)")
    return host.strip("[]") or "127.0.0.1", int(port)


def tcp_server(where: str) -> socket.socket:
    """The line's TCP listener on ``where`` (``hil up`` opens one to try it before anything starts)."""
    try:
        return socket.create_server(tcp_endpoint(where), reuse_port=False)
    except (OSError, UnicodeError) as err:
        if isinstance(err, LineError):
            raise
        raise LineError(
            f"--gnss-tcp {where}: cannot listen there: {getattr(err, 'strerror', None) or err}"
        ) from None


def _raw(fd: int, baud: int) -> None:
    """Raw 8N1 at ``baud`` (where termios knows the rate): no echo, no line editing, no CR/LF
    translation -- a UART, not a terminal."""
    tty.setraw(fd)
    speed = _BAUDS.get(baud)
    if speed is not None:
        attrs = termios.tcgetattr(fd)
        attrs[4] = attrs[5] = speed
        termios.tcsetattr(fd, termios.TCSANOW, attrs)


def _link(path: str, target: str) -> None:
    """Symlink ``path`` -> ``target``; an existing symlink is replaced, anything else refused."""
    p = Path(path)
    if p.is_symlink():
        p.unlink()
    elif p.exists():
        raise LineError(
            f"--gnss-serial {path}: exists and is not a link this rig made; remove it or pick another path"
        )
    try:
        p.parent.mkdir(parents=True, exist_ok=True)
        os.symlink(target, p)
    except OSError as err:
        raise LineError(f"--gnss-serial {path}: cannot link it to {target}: {err.strerror}") from None


class LineWriter:
    """The emulator's line(s): ptys linked at ``links``, a TCP server, a device; paced writes."""

    def __init__(
        self,
        baud: int,
        links: list[str],
        *,
        tcp_listen: str | None = None,
        device: str | None = None,
        on_error: Callable[[str, str], None] | None = None,
    ) -> None:
        self.baud = baud
        self.on_error = on_error or (lambda _c, _m: None)
        self.counts = {"line.written_bytes": 0, "line.unread_bytes": 0, "line.tcp_clients": 0}
        self._masters: list[tuple[int, int, str]] = []  # (master fd, slave fd, link)
        self._clients: list[socket.socket] = []
        self._server: socket.socket | None = None
        self._device: Any = None
        self._queue: queue.SimpleQueue[tuple[float, bytes] | None] = queue.SimpleQueue()
        self._stop = threading.Event()
        try:
            for path in links:
                self._open_pty(path)
            if tcp_listen:
                self._listen(tcp_listen)
            if device:
                self._open_device(device)
        except BaseException:
            self.close()
            raise
        self._thread = threading.Thread(target=self._write_loop, name="line-writer", daemon=True)
        self._thread.start()

    def _open_pty(self, path: str) -> None:
        master, slave = os.openpty()
        _raw(slave, self.baud)
        os.set_blocking(master, False)
        self._masters.append((master, slave, path))
        _link(path, os.ttyname(slave))

    def _listen(self, where: str) -> None:
        srv = tcp_server(where)
        srv.setblocking(False)
        self._server = srv

    def _open_device(self, path: str) -> None:
        try:
            import serial  # lazy: pyserial is needed only for a real device

            self._device = serial.Serial(path, self.baud, timeout=0, write_timeout=0)
        except Exception as err:
            raise LineError(f"--gnss-device {path}: cannot open it at {self.baud} baud: {err}") from None

    def write(self, data: bytes, start_wall_s: float) -> None:
        """Put ``data`` on the line(s) from ``start_wall_s`` (time.time() seconds) at the baud rate:
        its first bit then, its last byte readable ``len(data)`` byte times later."""
        self._queue.put((start_wall_s, data))

    def _write_loop(self) -> None:
        per_chunk = max(1, int(self.baud / 10 * CHUNK_S))
        dt_s = byte_time_ns(self.baud) * 1e-9
        while True:
            item = self._queue.get()
            if item is None:
                return
            start, data = item
            for i in range(0, len(data), per_chunk):
                # a byte is there for the reader once its stop bit is: each chunk is handed over
                # when its last byte would have come in, not when its first began
                due = start + min(i + per_chunk, len(data)) * dt_s
                wait = due - time.time()
                if wait > 0 and self._stop.wait(wait):
                    return
                self._put(data[i : i + per_chunk])

    def _put(self, chunk: bytes) -> None:
        self.counts["line.written_bytes"] += len(chunk)
        for master, _slave, path in self._masters:
            try:
                n = os.write(master, chunk)
            except OSError as err:
                if err.errno not in (errno.EAGAIN, errno.EIO):
                    self.on_error("errors.line.write", f"{path}: {err.strerror}")
                n = 0
            self.counts["line.unread_bytes"] += len(chunk) - n
        self._accept()
        for c in list(self._clients):
            try:
                c.sendall(chunk)
            except OSError:
                self._clients.remove(c)
                with contextlib.suppress(OSError):
                    c.close()
        if self._device is not None:
            try:
                self._device.write(chunk)
            except Exception as err:  # a pulled adapter: say so, keep the rest of the rig going
                self.on_error("errors.line.device", f"{err}")

    def _accept(self) -> None:
        if self._server is None:
            return
        try:
            while True:
                c, _addr = self._server.accept()
                c.setsockopt(socket.IPPROTO_TCP, socket.TCP_NODELAY, 1)
                self._clients.append(c)
                self.counts["line.tcp_clients"] += 1
        except (BlockingIOError, OSError):
            return

    def _let_readers_drain(self, wait_s: float) -> None:
        """Closing a pty's master discards what its reader has not read yet (the reader gets EIO):
        give a reader that is still there a moment to take the tail, which it does in
        milliseconds; a line nobody reads is closed after ``wait_s``."""
        deadline = time.monotonic() + wait_s
        for _master, slave, _path in self._masters:
            while time.monotonic() < deadline:
                try:
                    unread = struct.unpack("i", fcntl.ioctl(slave, termios.FIONREAD, b"\0\0\0\0"))[0]
                except OSError:
                    break
                if unread == 0:
                    break
                time.sleep(0.01)

    def close(self, drain_s: float = 2.0) -> None:
        """Write what is queued (at its pace, for at most ``drain_s``), then close every line."""
        self._queue.put(None)
        thread = getattr(self, "_thread", None)
        if thread is not None:
            thread.join(timeout=drain_s)
        self._stop.set()
        if thread is not None:
            thread.join(timeout=1.0)
        self._let_readers_drain(UNREAD_WAIT_S)
        for master, slave, path in self._masters:
            for fd in (master, slave):
                with contextlib.suppress(OSError):
                    os.close(fd)
            with contextlib.suppress(OSError):
                if Path(path).is_symlink():
                    os.unlink(path)
        for c in self._clients:
            with contextlib.suppress(OSError):
                c.close()
        if self._server is not None:
            self._server.close()
        if self._device is not None:
            with contextlib.suppress(Exception):
                self._device.close()


class LineReader:
    """The bridge's side of a line: a path (pty link or device) or a TCP server, read as it comes."""

    def __init__(self, baud: int, *, path: str | None = None, tcp: str | None = None) -> None:
        if not (path or tcp):
            raise LineError("gnss_bridge: give it the line to read (serial_path or tcp_connect)")
        self.baud = baud
        self.path = path
        self.tcp = tcp
        self._fd: int | None = None
        self._sock: socket.socket | None = None
        self.opens = 0

    @property
    def where(self) -> str:
        return self.path or f"tcp {self.tcp}"

    def _open(self) -> bool:
        try:
            if self.path:
                fd = os.open(self.path, os.O_RDONLY | os.O_NOCTTY | os.O_NONBLOCK)
                with contextlib.suppress(termios.error):
                    _raw(fd, self.baud)
                self._fd = fd
            else:
                self._sock = socket.create_connection(tcp_endpoint(str(self.tcp)), timeout=1.0)
                self._sock.setblocking(False)
        except OSError:
            return False
        self.opens += 1
        return True

    def read(self, timeout_s: float) -> tuple[bytes, int] | None:
        """What arrived within ``timeout_s``, with its receive time (``time.time_ns``); None if
        nothing did. Not yet open (the writer has not made the line): tries again, quietly."""
        if self._fd is None and self._sock is None and not self._open():
            time.sleep(min(timeout_s, 0.05))
            return None
        handle: Any = self._fd if self._fd is not None else self._sock
        ready, _, _ = select.select([handle], [], [], timeout_s)
        if not ready:
            return None
        t = time.time_ns()
        try:
            data = os.read(self._fd, 65536) if self._fd is not None else self._sock.recv(65536)  # type: ignore[union-attr]
        except (BlockingIOError, InterruptedError):
            return None
        except OSError:
            data = b""
        if not data:  # the other end went away (emulator restarted): open again
            self.close()
            return None
        return data, t

    def close(self) -> None:
        if self._fd is not None:
            with contextlib.suppress(OSError):
                os.close(self._fd)
            self._fd = None
        if self._sock is not None:
            with contextlib.suppress(OSError):
                self._sock.close()
            self._sock = None

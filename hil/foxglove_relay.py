"""Both names of Foxglove's WebSocket protocol on one port.

The protocol (foxglove/ws-protocol, ``docs/spec.md``) was first negotiated as the subprotocol
``foxglove.websocket.v1``; the SDK's server negotiates it as ``foxglove.sdk.v1`` and answers a
client that offers only the first name with HTTP 400 (``foxglove-sdk`` 0.30.3, ``handshake.rs``:
"Missing expected sec-websocket-protocol header"). Today's Foxglove app offers both; Foxglove
Studio before the SDK, Lichtblick's older releases, ws-protocol's own client library and its
examples offer only the first, and could not open ``hil up --foxglove``. The ops and frames are
the same under both names, so hil's port is this relay's: it reads a connection's HTTP upgrade
request, offers the SDK's server (on a loopback port of its own) the name it knows where the
client offered only the old one, names back the one the client offered in the answer, and from
then on copies bytes both ways untouched. A slow client holds its own copy loop and, through
TCP, the SDK's sender, whose queue per client is bounded (it drops, as without the relay).

``offered_names``/``upstream_request``/``client_response`` are the pure part; ``Relay`` the
sockets and threads.
"""

from __future__ import annotations

import contextlib
import selectors
import socket
import threading
import time
from dataclasses import dataclass, field

SDK_NAME = "foxglove.sdk.v1"
FIRST_NAME = "foxglove.websocket.v1"
_HEADER = b"sec-websocket-protocol"
MAX_HEAD = 16 * 1024  # an HTTP upgrade request is a few hundred bytes; past this it is not one
HANDSHAKE_TIMEOUT_S = 10.0  # a client that connects and says nothing is let go
MAX_CLIENTS = 32  # connections at a time (each holds two threads); more are answered 503
RECV_BYTES = 256 * 1024
# the server-to-client direction waits this long after a wake-up to send what came meanwhile in
# one go: a live view's 4 ms. With a client subscribed to every channel of a 400 Hz rig (~3500
# messages a second), `hil foxglove` used 11.9 % of a core through the relay against 10.8 % with
# the client straight on the SDK's port, and 14.3 % against 12.6 % without gathering and with it
# (two processes side by side on one rig each time, 20 s, 2026-12-07)
GATHER_S = 0.004
GATHER_MAX_BYTES = 4 * 1024 * 1024


def _header_lines(head: bytes) -> list[bytes]:
    """The request or status line, then the header lines (``head`` ends with its blank line)."""
    return head.removesuffix(b"\r\n\r\n").split(b"\r\n")


def _is_protocol(line: bytes) -> bool:
    name, sep, _value = line.partition(b":")
    return bool(sep) and name.strip().lower() == _HEADER


def offered_names(head: bytes) -> list[str]:
    """The subprotocols an HTTP head names, in its order (every such header)."""
    names: list[str] = []
    for line in _header_lines(head)[1:]:
        if _is_protocol(line):
            value = line.partition(b":")[2]
            names += [v.strip().decode("latin-1") for v in value.split(b",") if v.strip()]
    return names


def _with_protocol(head: bytes, names: list[str]) -> bytes:
    """``head`` with its subprotocol headers replaced by one naming ``names``."""
    first, *headers = _header_lines(head)
    kept = [ln for ln in headers if not _is_protocol(ln)]
    line = b"Sec-WebSocket-Protocol: " + ", ".join(names).encode("latin-1")
    return b"\r\n".join([first, *kept, line]) + b"\r\n\r\n"


def upstream_request(head: bytes) -> tuple[bytes, bool]:
    """The request as the SDK's server takes it, and whether its answer must name the first name
    back: a client offering ``foxglove.websocket.v1`` and not ``foxglove.sdk.v1`` is offered as
    the second; anything else passes unchanged (the server refuses what it refuses)."""
    names = offered_names(head)
    if SDK_NAME in names or FIRST_NAME not in names:
        return head, False
    return _with_protocol(head, [SDK_NAME if n == FIRST_NAME else n for n in names]), True


def client_response(head: bytes) -> bytes:
    """The SDK's answer to a client that offered only the first name: that name chosen."""
    if offered_names(head) != [SDK_NAME]:
        return head  # a refusal (no protocol chosen): as it is
    return _with_protocol(head, [FIRST_NAME])


def _read_head(sock: socket.socket) -> tuple[bytes, bytes] | None:
    """An HTTP head (through its blank line) and what came after it; None if the peer closed,
    went silent or sent more than ``MAX_HEAD`` without one."""
    buf = b""
    while b"\r\n\r\n" not in buf:
        if len(buf) > MAX_HEAD:
            return None
        try:
            chunk = sock.recv(4096)
        except OSError:  # the handshake's timeout too
            return None
        if not chunk:
            return None
        buf += chunk
    at = buf.index(b"\r\n\r\n") + 4
    return buf[:at], buf[at:]


def _gathered(src: socket.socket, first: bytes) -> tuple[bytes, bool]:
    """``first`` and what else ``src`` holds now (up to ``GATHER_MAX_BYTES``), and whether ``src``
    is still open."""
    parts, size = [first], len(first)
    while size < GATHER_MAX_BYTES:
        try:
            more = src.recv(RECV_BYTES, socket.MSG_DONTWAIT)
        except (BlockingIOError, InterruptedError):
            break
        if not more:
            return b"".join(parts), False
        parts.append(more)
        size += len(more)
    return b"".join(parts), True


def _shutdown(s: socket.socket) -> None:
    """Both directions ended (a peer already gone is not an error): wakes a thread in recv."""
    with contextlib.suppress(OSError):
        s.shutdown(socket.SHUT_RDWR)


def _close(*socks: socket.socket) -> None:
    for s in socks:
        _shutdown(s)
        s.close()


@dataclass
class Relay:
    """Listens on ``host:port`` (0: any free port, then ``port`` says which) and relays each
    connection to the Foxglove server on ``upstream`` (loopback), the handshake's names mapped
    (``upstream_request``). ``close()`` stops listening and ends every connection.

    Without ``upstream`` it only holds the port (connections wait in the backlog) until
    ``start(upstream)``: the caller binds hil's port before the server takes a free one of its
    own, which could otherwise be the very port asked for."""

    host: str
    port: int
    upstream: tuple[str, int] | None = None
    counters: dict[str, int] = field(default_factory=dict)

    def __post_init__(self) -> None:
        info = socket.getaddrinfo(self.host, self.port, type=socket.SOCK_STREAM, flags=socket.AI_PASSIVE)[0]
        self._listener = socket.socket(info[0], socket.SOCK_STREAM)
        try:
            self._listener.setsockopt(socket.SOL_SOCKET, socket.SO_REUSEADDR, 1)
            self._listener.bind(info[4])
            self._listener.listen(16)
        except OSError:
            self._listener.close()
            raise
        self.port = int(self._listener.getsockname()[1])
        self._lock = threading.Lock()
        self._open: set[socket.socket] = set()  # every connection's sockets, from its accept
        self._threads: list[threading.Thread] = []
        self._stopping = threading.Event()
        self._acceptor = threading.Thread(target=self._accept, name="foxglove-relay", daemon=True)
        if self.upstream is not None:
            self._acceptor.start()

    def start(self, upstream: tuple[str, int]) -> None:
        """Relay to ``upstream`` from now on (a relay made without one)."""
        self.upstream = upstream
        self._acceptor.start()

    def _count(self, name: str) -> None:
        with self._lock:
            self.counters[name] = self.counters.get(name, 0) + 1

    def _accept(self) -> None:
        with selectors.DefaultSelector() as sel:
            sel.register(self._listener, selectors.EVENT_READ)
            while not self._stopping.is_set():
                if not sel.select(timeout=0.2):
                    continue
                try:
                    client, _addr = self._listener.accept()
                except OSError:
                    continue
                with self._lock:
                    self._threads = [t for t in self._threads if t.is_alive()]
                    full = len(self._threads) >= MAX_CLIENTS
                    if not full:
                        self._open.add(client)
                if full:
                    self._count("refused.too_many_clients")
                    with contextlib.suppress(OSError):
                        client.sendall(b"HTTP/1.1 503 Service Unavailable\r\nContent-Length: 0\r\n\r\n")
                    _close(client)
                    continue
                t = threading.Thread(
                    target=self._serve, args=(client,), name="foxglove-relay-conn", daemon=True
                )
                with self._lock:
                    self._threads.append(t)
                t.start()

    def _serve(self, client: socket.socket) -> None:
        """One connection: the handshake with the names mapped, then bytes both ways."""
        upstream: socket.socket | None = None
        try:
            client.settimeout(HANDSHAKE_TIMEOUT_S)
            got = _read_head(client)
            if got is None:
                self._count("refused.no_handshake")
                return
            head, rest = got
            request, rename = upstream_request(head)
            assert self.upstream is not None  # the acceptor runs only once it is known
            upstream = socket.create_connection(self.upstream, timeout=HANDSHAKE_TIMEOUT_S)
            with self._lock:
                self._open.add(upstream)
                if self._stopping.is_set():
                    return
            upstream.sendall(request + rest)
            answer = _read_head(upstream)
            if answer is None:
                self._count("errors.upstream")
                return
            head, rest = answer
            client.sendall((client_response(head) if rename else head) + rest)
            if not head.startswith(b"HTTP/1.1 101"):  # the server refused it (and said why)
                self._count("refused.by_server")
                return
            self._count("clients.first_name" if rename else "clients")
            client.settimeout(None)
            upstream.settimeout(None)
            back = threading.Thread(target=self._copy, args=(upstream, client, GATHER_S), daemon=True)
            back.start()
            self._copy(client, upstream)
            back.join()
        except OSError:
            self._count("errors.connection")
        finally:
            socks = [client] if upstream is None else [client, upstream]
            with self._lock:
                self._open.difference_update(socks)
            _close(*socks)

    @staticmethod
    def _copy(src: socket.socket, dst: socket.socket, gather_s: float = 0.0) -> None:
        """Bytes from ``src`` to ``dst`` until either side ends. ``gather_s``: after a wake-up,
        wait that long and take everything that came meanwhile, so a stream of small messages
        costs a wake-up and a send per gathering instead of per message (``GATHER_S``)."""
        try:
            more = True
            while more and (chunk := src.recv(RECV_BYTES)):
                if gather_s:
                    time.sleep(gather_s)
                    chunk, more = _gathered(src, chunk)  # more: False once src ended meanwhile
                dst.sendall(chunk)
        except OSError:
            pass
        _shutdown(src)  # either side gone: both directions end
        _shutdown(dst)

    def close(self) -> None:
        self._stopping.set()
        if self._acceptor.is_alive():
            self._acceptor.join(timeout=5)
        self._listener.close()
        with self._lock:
            for s in self._open:
                _shutdown(s)
            threads = list(self._threads)
        for t in threads:
            t.join(timeout=5)

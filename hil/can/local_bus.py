"""A python-can interface for the rig's own CAN on one machine without SocketCAN (``hillocal``).

Why: where the kernel has no ``vcan0`` the rig's processes still need a shared CAN bus. Over
Zenoh (``hilzenoh``) every IMU sample's frames are one message through the rig's hub: measured,
an isolated Zenoh message costs ~270 µs of CPU at its two ends and the hub routes it too, which
is most of what one IMU stream costs the live rig (docs/benchmarks.md, ``bus-paced-400``). A CAN
bus is local to a machine anyway -- the emulator, the bridge and a DUT emulator sit on it -- so
``hil up`` gives its processes this one: Unix sockets in a directory only the user can enter
(the rig's runtime directory, 0700), kernel to kernel, no hub, no Zenoh.

    bus = can.Bus(interface="hillocal", channel="vcan0", directory="/run/user/1000/hil/r-123.can")

How it works:

- every bus that receives listens on ``<directory>/<channel>/<id>.sock`` (``SOCK_SEQPACKET``:
  message boundaries, a connection per sender, the kernel's socket buffer per connection rather
  than a datagram socket's queue of ten);
- a sender connects to every listener of the channel but its own and writes each frame (or one
  IMU sample's burst) to each as one packet, without blocking: a listener whose buffer is full
  loses that packet (counted in the sender's ``tx_overflow``), as a CAN controller whose receive
  FIFO overflows does -- a stalled reader never holds the sender, or the IMU's pacing, back;
- senders notice listeners coming and going from the directory's modification time (one
  ``stat`` per send); a listener that went away is dropped at the first failed write;
- a received frame's timestamp is its sender's wire time when it says so (``send_stamped``,
  ``send_burst_stamped``: the kernel stamps a ``vcan`` frame in the sender's ``send`` too), else
  its arrival, as the kernel stamped the packet (``SO_TIMESTAMPNS``); a stated time after the
  arrival is replaced by it and counted (``rx_stamp_skew``); ``send`` states the time it sends;
- a receiving bus reads its sockets in ``recv`` (no thread): what waits in the kernel is read in
  one call, each packet with its kernel stamp; a bus that stops reading lets its senders' packets
  wait in its socket buffers (1 MiB per sender), then lose them (their ``tx_overflow``), as a
  CAN controller's full receive FIFO does;
- own frames are not received back (unless ``receive_own_messages``); a bus opened with
  ``fd=False`` refuses FD frames and does not see them; ``receive=False`` only sends.

Packet format (little-endian): ``u8 version (1) | u8 n | i64 wire time (epoch ns) × n`` then
the frames' records as ``hilzenoh`` packs them (:func:`hil.can.frame_bus.pack_frame`); ``n`` is
0 (arrival stamps) or the number of records. Anything else -- a packet another process of the
user wrote into the directory -- is counted in ``rx_malformed`` and dropped whole.

Who may join: the user's own processes (the directory is 0700; ``hil up`` makes it inside the
rig's runtime directory, hands it to its children as ``HIL_CAN_DIR`` and removes it at exit).
A tool joins with ``--bus-kwargs rig=<rig>`` (the running ``hil up`` of that rig on this
machine) or ``directory=<dir>`` (``python -m can.logger -i hillocal``), or ``HIL_CAN_DIR``;
``hil up`` prints the directory at start, and ``hil replay --can`` finds it by the rig.
"""

from __future__ import annotations

import contextlib
import hashlib
import os
import selectors
import shutil
import socket
import struct
import tempfile
import threading
import time
from collections.abc import Mapping, Sequence
from pathlib import Path
from typing import Any

import can

from hil.can.frame_bus import FrameQueueBus, unpack_frames

DIR_ENV = "HIL_CAN_DIR"  # set by hil up for its children (hil.can.bus.LOCAL_DIR_ENV)
_HEAD = struct.Struct("<BB")
VERSION = 1
MAX_PACKET = 1 + 1 + 8 * 255 + 255 * (14 + 64)  # what one burst can be; reads take this much
SOCKET_BUFFER_BYTES = 1 << 20  # per connection: ~10 000 classic frames, seconds of a stalled reader
_MAX_PATH = 107  # sun_path
_NAME_LEN = len("0123456789abcdef.sock")
_SEND_FLAGS = socket.MSG_DONTWAIT | socket.MSG_NOSIGNAL  # never wait; a closed peer is an error, not a signal
SO_TIMESTAMPNS = getattr(socket, "SO_TIMESTAMPNS", 35)  # Linux's value; Python names it from 3.13 on
_TIMESPEC = struct.Struct("@qq")  # struct timespec: the kernel's stamp of a packet (realtime clock)
_ANC_SIZE = socket.CMSG_SPACE(_TIMESPEC.size)


def packet(records: Sequence[bytes], stamps_epoch_ns: Sequence[int] | None) -> bytes:
    """One packet: the header, the stamps (or none), the records (module docstring)."""
    n = 0 if stamps_epoch_ns is None else len(stamps_epoch_ns)
    head = _HEAD.pack(VERSION, n)
    if n:
        head += struct.pack(f"<{n}q", *stamps_epoch_ns)  # type: ignore[misc]
    return head + b"".join(records)


def parse_packet(data: bytes) -> tuple[list[int] | None, list[tuple[int, can.Message]]]:
    """``(stamps or None, frames)``; ``ValueError`` on anything that is not one of our packets."""
    if len(data) < _HEAD.size:
        raise ValueError(f"packet of {len(data)} B, short of its {_HEAD.size} B header")
    version, n = _HEAD.unpack_from(data)
    if version != VERSION:
        raise ValueError(f"packet version {version}, not {VERSION}")
    at = _HEAD.size + 8 * n
    if len(data) < at:
        raise ValueError(f"packet of {len(data)} B announces {n} stamps")
    stamps = list(struct.unpack_from(f"<{n}q", data, _HEAD.size)) if n else None
    frames = unpack_frames(data[at:])
    if stamps is not None and len(stamps) != len(frames):
        raise ValueError(f"{len(stamps)} stamps for {len(frames)} frames")
    return stamps, frames


def running_rig_dir(rig: str, env: Mapping[str, str] | None = None) -> Path | None:
    """The CAN directory of the running ``hil up`` of this rig on this machine (found as a
    viewer finds the rig: its endpoint file, whose process is alive), or None: how a process
    started by hand (``hil replay --can``, a python-can tool) finds the rig's bus."""
    from hil.bus.endpoint import find_rig

    found, _why = find_rig(rig, env)
    if found is None or not found.can_dir.is_dir():
        return None
    return found.can_dir


def channel_dir(directory: str | os.PathLike[str], channel: str) -> Path:
    """Where a channel's listeners are: ``<directory>/<channel>`` (a plain name only), or the
    same under the directory's short alias (:func:`short_alias`) where a socket's path there
    would be longer than a Unix socket's may be."""
    if not channel or "/" in channel or channel in (".", ".."):
        raise ValueError(f"CAN channel {channel!r} is not a plain name")
    d = Path(directory) / channel
    if len(os.fsencode(d)) + 1 + _NAME_LEN <= _MAX_PATH:
        return d
    return short_alias(directory) / channel


def short_alias(directory: str | os.PathLike[str]) -> Path:
    """``<tmp>/hilcan-<uid>/<digest of the directory's path>``: every process of the rig derives
    the same one (a long ``HIL_RUNTIME_DIR``, a test's temporary directory), private as the
    directory itself; :func:`remove_can_dir` removes both."""
    root = Path(tempfile.gettempdir()) / f"hilcan-{os.getuid()}"
    digest = hashlib.sha256(os.fsencode(Path(directory).absolute())).hexdigest()[:16]
    return root / digest


def remove_can_dir(directory: str | os.PathLike[str]) -> None:
    """A rig's CAN directory and its short alias, whatever is in them (``hil up`` at exit)."""
    shutil.rmtree(directory, ignore_errors=True)
    shutil.rmtree(short_alias(directory), ignore_errors=True)


def _private(path: Path, create: bool) -> None:
    """``path`` as a directory only this user can enter (made so with ``create``), or
    ``CanInitializationError`` (:func:`hil.bus.endpoint.private_dir`'s rule)."""
    from hil.bus.endpoint import private_dir
    from hil.bus.session import BusConfigError

    try:
        private_dir(path, create=create)
    except BusConfigError as err:
        raise can.CanInitializationError(f"hillocal: {err}") from None
    if not path.is_dir():
        raise can.CanInitializationError(f"hillocal: {path} is not a directory (is the rig running?)")


class LocalCanBus(FrameQueueBus):
    """python-can bus over Unix sockets in a private directory. Keyword arguments beyond
    python-can's own:

    - ``directory``: the rig's CAN directory (default ``$HIL_CAN_DIR``, else the running rig
      named by ``rig``: :func:`running_rig_dir`);
    - ``fd``: accept and send CAN FD frames (default False);
    - ``receive``: listen (default True); False: send only;
    - ``receive_own_messages``: also deliver this bus's own frames (default False);
    - ``rx_queue_size``: frames held for ``recv`` before new ones are dropped and counted in
      ``rx_overflow`` (default 100 000).
    """

    NAME = "hillocal"

    def __init__(
        self,
        channel: Any = "vcan0",
        can_filters: Any = None,
        *,
        directory: str | os.PathLike[str] | None = None,
        rig: str | None = None,
        fd: bool = False,
        receive: bool = True,
        receive_own_messages: bool = False,
        rx_queue_size: int = 100_000,
        **kwargs: Any,
    ) -> None:
        self.channel = str(channel or "vcan0")
        where: str | os.PathLike[str] = directory or os.environ.get(DIR_ENV, "")
        if not where and rig:
            where = running_rig_dir(str(rig)) or ""
            if not where:
                raise can.CanInitializationError(
                    f"hillocal: no rig {rig!r} running on this machine (hil up --rig {rig})"
                )
        if not where:
            raise can.CanInitializationError(
                f"hillocal: no directory (the directory or rig keyword, or {DIR_ENV}; hil up prints its own)"
            )
        try:
            self.dir = channel_dir(where, self.channel)
        except ValueError as err:
            raise can.CanInitializationError(f"hillocal: {err}") from None
        base = Path(where)
        _private(base, create=False)
        if receive and len(os.fsencode(self.dir)) + 1 + _NAME_LEN > _MAX_PATH:  # a long channel name
            raise can.CanInitializationError(
                f"hillocal: a socket in {self.dir} would be longer than a Unix socket path may be "
                f"({_MAX_PATH} B): use a shorter channel name"
            )
        if self.dir.parent != base:  # the short alias (a long directory path)
            _private(self.dir.parent.parent, create=True)
            _private(self.dir.parent, create=True)
        _private(self.dir, create=True)
        self._init_frames(fd, receive_own_messages, rx_queue_size, str(self.dir))
        self.tx_overflow = 0  # packets a listener had no room for (lost for that listener)
        self.tx_peers_lost = 0
        self._peers: dict[str, socket.socket] = {}
        self._dir_mtime = -1
        self._tx_lock = threading.Lock()
        self.path: Path | None = None
        self._listener: socket.socket | None = None
        self._sel: selectors.BaseSelector | None = None
        self._conns: list[socket.socket] = []
        self._rx_lock = threading.Lock()  # one reader of the sockets at a time; shutdown waits for it
        self._wake_r, self._wake_w = socket.socketpair()
        if receive:
            self.path = self.dir / f"{self._sender:016x}.sock"
            lst = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            try:
                lst.bind(str(self.path))
                lst.listen(64)
            except OSError as err:
                lst.close()
                raise can.CanInitializationError(f"hillocal: cannot listen on {self.path}: {err}") from err
            lst.setblocking(False)
            self._listener = lst
            self._sel = selectors.DefaultSelector()
            self._sel.register(lst, selectors.EVENT_READ, "accept")
            self._sel.register(self._wake_r, selectors.EVENT_READ, "wake")
        super().__init__(channel=self.channel, can_filters=can_filters, **kwargs)

    # -- receiving: in the caller's recv, no thread of its own ----------------------------------
    # The kernel stamps each packet as it is sent (SO_TIMESTAMPNS), so a frame read late still
    # has its arrival time, and the caller reads a read window's packets in one wake-up: a
    # thread woken per packet to stamp it cost the bridge a wake-up and a hand-over per sample.
    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        if self._sel is None:  # a sender only: its own frames looped back, if asked for
            return super()._recv_internal(timeout)
        if self._rx.empty():
            deadline = None if timeout is None else time.monotonic() + max(0.0, timeout)
            wait: float | None = 0.0 if timeout is not None and timeout <= 0 else timeout
            while True:
                self._read_ready(wait)
                if not self._rx.empty() or self._closed.is_set():
                    break
                if deadline is not None:
                    wait = deadline - time.monotonic()
                    if wait <= 0:
                        break
        return super()._recv_internal(0)

    def _read_ready(self, wait: float | None) -> None:
        """Accept new senders and read every packet already queued in the kernel (waiting up to
        ``wait`` s for the first): what one wake-up of the reader finds."""
        with self._rx_lock:
            if self._closed.is_set() or self._sel is None:
                return
            for key, _ in self._sel.select(wait):
                what = key.data
                if what == "wake":
                    return
                if what == "accept":
                    self._accept()
                    continue
                self._drain(key.fileobj)  # type: ignore[arg-type]

    def _accept(self) -> None:
        assert self._listener is not None and self._sel is not None
        while True:
            try:
                conn, _addr = self._listener.accept()
            except OSError:  # none left (BlockingIOError), or the listener closed
                return
            conn.setblocking(False)
            with contextlib.suppress(OSError):
                conn.setsockopt(socket.SOL_SOCKET, socket.SO_RCVBUF, SOCKET_BUFFER_BYTES)
            with contextlib.suppress(OSError):
                conn.setsockopt(socket.SOL_SOCKET, SO_TIMESTAMPNS, 1)
            self._sel.register(conn, selectors.EVENT_READ, "conn")
            self._conns.append(conn)

    def _drain(self, conn: socket.socket) -> None:
        while True:
            try:
                data, anc, _flags, _addr = conn.recvmsg(MAX_PACKET, _ANC_SIZE)
            except BlockingIOError:
                return
            except OSError:
                data, anc = b"", []
            if not data:  # the sender closed (or went away)
                assert self._sel is not None
                self._sel.unregister(conn)
                self._conns.remove(conn)
                conn.close()
                return
            arrival = None
            for level, kind, raw in anc:
                if level == socket.SOL_SOCKET and kind == SO_TIMESTAMPNS and len(raw) >= _TIMESPEC.size:
                    sec, nsec = _TIMESPEC.unpack_from(raw)
                    arrival = sec + nsec * 1e-9
            self._on_packet(data, time.time() if arrival is None else arrival)

    def _on_packet(self, data: bytes, arrival: float) -> None:
        try:
            stamps, frames = parse_packet(data)
        except Exception:
            self.rx_malformed += 1
            return
        for i, (sender, msg) in enumerate(frames):
            self._deliver(sender, msg, self._stamp(None if stamps is None else stamps[i], arrival))

    # -- sending ------------------------------------------------------------------------------------
    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        # stamped as it leaves, as the kernel stamps a vcan frame in send: the receiver's kernel
        # stamp misses the packets a new connection carries before the receiver accepts it
        self._send([self._packed(msg)], [time.time_ns()])

    def send_stamped(self, msg: can.Message, stamp_epoch_ns: int, timeout: float | None = None) -> None:
        """``send``, telling receivers the frame was on the wire at ``stamp_epoch_ns``."""
        self._send([self._packed(msg)], [int(stamp_epoch_ns)])

    def send_burst_stamped(
        self, msgs: Sequence[can.Message], stamps_epoch_ns: Sequence[int], timeout: float | None = None
    ) -> None:
        """Frames that leave back to back (one sample's) as one packet, each with its wire time."""
        if len(msgs) != len(stamps_epoch_ns):
            raise can.CanOperationError(
                f"hillocal: a burst of {len(msgs)} frames with {len(stamps_epoch_ns)} stamps"
            )
        if not msgs:
            return
        if len(msgs) > 255:
            raise can.CanOperationError(f"hillocal: a burst of {len(msgs)} frames (at most 255)")
        self._send([self._packed(m) for m in msgs], [int(s) for s in stamps_epoch_ns])

    def _send(self, records: list[bytes], stamps: list[int] | None) -> None:
        data = packet(records, stamps)
        with self._tx_lock:
            self._refresh_peers()
            for path, sock in list(self._peers.items()):
                try:
                    sock.send(data, _SEND_FLAGS)
                except BlockingIOError:
                    self.tx_overflow += 1
                except OSError:  # the listener went away
                    self._drop_peer(path)
        self.tx_frames += len(records)
        if self.receive_own_messages and self._listener is not None:
            self._on_packet(data, time.time())  # its own frames, as a SocketCAN socket loops them back

    def _refresh_peers(self) -> None:
        """Connect to listeners that appeared, forget those that went (the directory changed)."""
        try:
            mtime = os.stat(self.dir).st_mtime_ns
        except OSError:
            return
        if mtime == self._dir_mtime:
            return
        self._dir_mtime = mtime
        try:
            names = {str(p) for p in self.dir.glob("*.sock")}
        except OSError:
            return
        own = str(self.path) if self.path is not None else None
        for path in list(self._peers):
            if path not in names:
                self._drop_peer(path, lost=False)
        for path in names - self._peers.keys():
            if path == own:
                continue
            sock = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
            sock.setblocking(False)  # never wait here: this is the IMU's pacing thread
            try:
                sock.setsockopt(socket.SOL_SOCKET, socket.SO_SNDBUF, SOCKET_BUFFER_BYTES)
                sock.connect(path)
            except BlockingIOError:  # its backlog is full (a stopped process): try again next send
                sock.close()
                self._dir_mtime = -1
                continue
            except OSError:  # a socket file left by a process that is gone
                sock.close()
                continue
            self._peers[path] = sock

    def _drop_peer(self, path: str, lost: bool = True) -> None:
        """Forget a listener; one whose connection failed (``lost``) is looked for again at the
        next send, and reconnected if its socket still answers (a gone process's does not)."""
        sock = self._peers.pop(path, None)
        if sock is not None:
            sock.close()
            self.tx_peers_lost += int(lost)
            if lost:
                self._dir_mtime = -1

    def counters(self) -> dict[str, int]:
        """For the owning service's status: what the transport refused or lost (a malformed
        packet is a rejected input; a full listener lost a packet; a listener went away)."""
        return {
            "rejected.can.transport_malformed": self.rx_malformed,
            "can.rx_overflow": self.rx_overflow,
            "can.rx_fd_ignored": self.rx_fd_ignored,
            "can.rx_stamp_skew": self.rx_stamp_skew,
            "can.tx_overflow": self.tx_overflow,
            "can.tx_peers_lost": self.tx_peers_lost,
        }

    @property
    def peers(self) -> int:
        """Listeners this bus sends to (after its last send)."""
        return len(self._peers)

    def shutdown(self) -> None:
        if self._closed.is_set():
            return
        self._closed.set()
        with contextlib.suppress(OSError):
            self._wake_w.send(b"x")  # a reader waiting in recv returns
        locked = self._rx_lock.acquire(timeout=2.0)
        try:
            if self._sel is not None:
                self._sel.close()
            for conn in self._conns:
                conn.close()
            self._conns.clear()
        finally:
            if locked:
                self._rx_lock.release()
        if self._listener is not None:
            self._listener.close()
        if self.path is not None:
            with contextlib.suppress(OSError):
                self.path.unlink()
        with self._tx_lock:
            for path in list(self._peers):
                self._drop_peer(path, lost=False)
        self._wake_r.close()
        self._wake_w.close()
        super().shutdown()

    @staticmethod
    def _detect_available_configs() -> list[Any]:
        where = os.environ.get(DIR_ENV)
        return [{"interface": "hillocal", "channel": "vcan0", "directory": where}] if where else []

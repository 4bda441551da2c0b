"""hillocal (the rig's CAN on Unix sockets) between real processes: delivery, stamps, what it
refuses, what a stalled or vanished reader does to the sender."""

from __future__ import annotations

import itertools
import os
import socket
import subprocess
import sys
import textwrap
import time
from collections.abc import Iterator
from pathlib import Path

import can
import pytest

from hil.can.bus import LOCAL_DIR_ENV, open_can_bus, resolve_interface
from hil.can.frame_bus import pack_frame
from hil.can.local_bus import LocalCanBus, packet, parse_packet, remove_can_dir
from tests.conftest import exchange_with_child


@pytest.fixture
def can_dir(tmp_path: Path) -> Iterator[Path]:
    d = tmp_path / "can"
    d.mkdir(mode=0o700)
    yield d
    remove_can_dir(d)  # and its short alias, where this test's long path needed one


@pytest.fixture
def listener_and_raw(can_dir: Path) -> Iterator[tuple[LocalCanBus, socket.socket]]:
    """A listening bus and a plain socket connected to it: another tool's packets, as written."""
    bus = LocalCanBus(channel="vcan0", directory=can_dir)
    raw = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    try:
        assert bus.path is not None
        raw.connect(str(bus.path))
        yield bus, raw
    finally:
        raw.close()
        bus.shutdown()


CHILD = textwrap.dedent(
    """
    import sys, time, can
    n, where = int(sys.argv[1]), sys.argv[2]
    bus = can.Bus(interface="hillocal", channel="vcan0", directory=where, fd=True)
    assert bus.recv(timeout=20).arbitration_id == 0x7FF        # the parent's "go"
    for i in range(n):
        bus.send(can.Message(arbitration_id=0x100 + i % 4, is_extended_id=False, data=i.to_bytes(8, "little")))
        if i % 250 == 249:  # wait for the parent's "got 250" (a stalled reader loses frames by design)
            while (m := bus.recv(timeout=20)) is not None and m.arbitration_id != 0x7FD:
                pass
    assert bus.tx_overflow == 0
    bus.send(can.Message(arbitration_id=0x110, is_extended_id=False, is_fd=True, bitrate_switch=True,
                         data=bytes(range(32))))
    t = time.time_ns()
    bus.send_burst_stamped([can.Message(arbitration_id=0x120 + k, is_extended_id=False, data=bytes([k]))
                            for k in range(4)], [t - 4000 + 1000 * k for k in range(4)])
    ack = bus.recv(timeout=20)                                  # wait until the parent has it all
    while ack is not None and ack.arbitration_id == 0x7FF:
        ack = bus.recv(timeout=20)
    print("ack", ack is not None and ack.arbitration_id == 0x7FE, t, flush=True)
    bus.shutdown()
    """
)


def test_frames_between_two_processes_in_order_with_the_senders_wire_time(can_dir: Path) -> None:
    n = 3000
    bus = LocalCanBus(channel="vcan0", directory=can_dir, fd=True)
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(n), str(can_dir)],
        stdout=subprocess.PIPE,
        stderr=subprocess.PIPE,
        text=True,
    )
    t0 = time.time()
    got, out, err = exchange_with_child(bus, child, n + 5, 30.0, credit_every=250, credits=n)
    assert child.returncode == 0, err
    assert "ack True" in out
    assert [int.from_bytes(m.data, "little") for m in got[:n]] == list(range(n))
    assert all(m.arbitration_id not in (0x7FF, 0x7FE) for m in got)  # own frames not echoed
    fd = got[n]
    assert fd.is_fd and fd.bitrate_switch and bytes(fd.data) == bytes(range(32))
    burst = got[n + 1 : n + 5]
    t_burst = int(out.split()[-1])
    assert [m.arbitration_id for m in burst] == [0x120, 0x121, 0x122, 0x123]
    # each frame of the burst carries its own wire time (epoch ns -> s), not its arrival
    assert [round(m.timestamp * 1e9) for m in burst] == pytest.approx(
        [t_burst - 4000 + 1000 * k for k in range(4)], abs=1000
    )
    stamps = [m.timestamp for m in got[:n]]
    assert t0 - 1 < stamps[0] <= stamps[-1] <= time.time()
    assert all(b >= a for a, b in itertools.pairwise(stamps))
    assert not any(
        p.name.endswith(".sock") for p in (can_dir / "vcan0").iterdir()
    )  # both removed their socket


def test_classic_bus_refuses_fd_frames_and_does_not_see_them(can_dir: Path) -> None:
    classic = LocalCanBus(channel="vcan0", directory=can_dir)
    fd = LocalCanBus(channel="vcan0", directory=can_dir, fd=True, receive=False)
    try:
        with pytest.raises(can.CanOperationError, match="FD frame"):
            classic.send(can.Message(arbitration_id=1, is_fd=True, data=bytes(12)))
        with pytest.raises(can.CanOperationError, match="classic"):
            classic.send(can.Message(arbitration_id=1, data=bytes(12)))
        fd.send(can.Message(arbitration_id=2, is_fd=True, data=bytes(12)))
        fd.send(can.Message(arbitration_id=3, data=b"\x01"))
        got = classic.recv(timeout=10)
        assert got is not None and got.arbitration_id == 3 and got.is_rx
        assert classic.rx_fd_ignored == 1
    finally:
        classic.shutdown()
        fd.shutdown()
    own = LocalCanBus(channel="vcan0", directory=can_dir, receive_own_messages=True)
    try:  # as a SocketCAN socket with CAN_RAW_RECV_OWN_MSGS: its own frames back, not as received
        stated_ns = time.time_ns() - 10**6
        own.send_stamped(can.Message(arbitration_id=4, is_extended_id=False, data=b"me"), stated_ns)
        got = own.recv(timeout=10)
        assert got is not None and bytes(got.data) == b"me" and not got.is_rx
        assert got.timestamp == pytest.approx(stated_ns * 1e-9, abs=1e-6)  # the stated wire time
    finally:
        own.shutdown()


def test_malformed_packets_are_counted_and_dropped_whole(
    listener_and_raw: tuple[LocalCanBus, socket.socket],
) -> None:
    bus, raw = listener_and_raw
    good = pack_frame(7, can.Message(arbitration_id=5, is_extended_id=False, data=b"ok"))
    bad = [
        b"",
        b"\x01",
        b"\x02\x00" + good,  # another version
        b"\x01\x02" + b"\x00" * 8 + good,  # two stamps, one frame
        b"\x01\x00" + good[:-1],  # a truncated record
        os.urandom(300),
    ]
    for p in bad:
        if p:
            raw.send(p)
    raw.send(packet([good], None))  # then a good one: the bus is still reading
    msg = bus.recv(timeout=10)
    assert msg is not None and bytes(msg.data) == b"ok"
    assert bus.rx_malformed == len([p for p in bad if p])
    with pytest.raises(ValueError):
        parse_packet(b"\x01\x01" + b"\x00" * 4)


def test_a_packet_read_late_keeps_the_time_the_kernel_stamped_it(
    can_dir: Path, listener_and_raw: tuple[LocalCanBus, socket.socket]
) -> None:
    """The bus reads its sockets in recv, not in a thread of its own: a frame without a stated
    wire time (another tool's packet) is stamped with its arrival as the kernel stamped it, not
    with when recv got round to it."""
    bus, raw = listener_and_raw
    first = pack_frame(7, can.Message(arbitration_id=5, is_extended_id=False, data=b"1"))
    raw.send(packet([first], None))
    assert bus.recv(timeout=10) is not None  # the connection accepted: the kernel stamps from now
    t_sent = time.time()
    raw.send(packet([pack_frame(7, can.Message(arbitration_id=6, is_extended_id=False, data=b"2"))], None))
    time.sleep(0.3)  # read well after it arrived
    t_read = time.time()
    msg = bus.recv(timeout=10)
    assert msg is not None and msg.arbitration_id == 6
    assert t_sent <= msg.timestamp < t_read, (t_sent, msg.timestamp, t_read)
    # and a plain send states its own time, which the receiver keeps
    other = LocalCanBus(channel="vcan0", directory=can_dir, receive=False)
    try:
        t0 = time.time()
        other.send(can.Message(arbitration_id=8, is_extended_id=False, data=b"3"))
        time.sleep(0.3)
        t1 = time.time()
        msg = bus.recv(timeout=10)
        assert msg is not None and msg.arbitration_id == 8 and t0 <= msg.timestamp < t1
    finally:
        other.shutdown()


def test_a_stalled_reader_never_holds_the_sender_and_a_vanished_one_is_dropped(can_dir: Path) -> None:
    sender = LocalCanBus(channel="vcan0", directory=can_dir, receive=False)
    # a listener that accepts nothing and reads nothing (a process stopped in a debugger)
    stalled = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    stalled.bind(str(can_dir / "vcan0" / "stalled.sock"))
    stalled.listen(1)
    live: LocalCanBus | None = None
    try:
        frame = can.Message(arbitration_id=9, is_extended_id=False, data=bytes(8))
        for _ in range(20_000):  # far past any socket buffer: a blocking send would hang here
            sender.send(frame)
        assert sender.tx_overflow > 0  # lost for the stalled listener, counted
        assert sender.peers == 1
        live = LocalCanBus(channel="vcan0", directory=can_dir)  # joins: the sender finds it
        for i in range(100):
            sender.send(can.Message(arbitration_id=10, is_extended_id=False, data=bytes([i])))
            got = live.recv(timeout=10)
            assert got is not None and bytes(got.data) == bytes([i])
        assert sender.peers == 2
        stalled.close()  # its socket file stays: the next write fails, the peer is dropped
        sender.send(frame)
        sender.send(frame)
        assert sender.tx_peers_lost == 1 and sender.peers == 1
    finally:
        stalled.close()
        if live is not None:
            live.shutdown()
        sender.shutdown()


def test_the_directory_must_be_private_and_exist(tmp_path: Path) -> None:
    with pytest.raises(can.CanInitializationError, match="not a directory"):
        LocalCanBus(channel="vcan0", directory=tmp_path / "missing")
    open_dir = tmp_path / "open"
    open_dir.mkdir(mode=0o755)
    open_dir.chmod(0o755)
    with pytest.raises(can.CanInitializationError, match="not a private directory"):
        LocalCanBus(channel="vcan0", directory=open_dir)
    with pytest.raises(can.CanInitializationError, match="not a plain name"):
        LocalCanBus(channel="../x", directory=tmp_path)
    long_dir = tmp_path / ("d" * 90)  # its sockets go under a short alias: same for every process
    long_dir.mkdir(mode=0o700)
    a = LocalCanBus(channel="vcan0", directory=long_dir)
    b = LocalCanBus(channel="vcan0", directory=long_dir, receive=False)
    try:
        assert a.path is not None and not str(a.path).startswith(str(long_dir))
        b.send(can.Message(arbitration_id=0x33, is_extended_id=False, data=b"x"))
        got = a.recv(timeout=10)
        assert got is not None and got.arbitration_id == 0x33
    finally:
        a.shutdown()
        b.shutdown()
        remove_can_dir(long_dir)
    with pytest.raises(can.CanInitializationError, match="longer than a Unix socket path"):
        LocalCanBus(channel="c" * 100, directory=tmp_path)


def test_auto_resolution_takes_the_rigs_local_bus_where_it_has_one(
    can_dir: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    assert resolve_interface("vcan-does-not-exist", None, {}) == "hilzenoh"
    assert resolve_interface("vcan-does-not-exist", None, {LOCAL_DIR_ENV: str(can_dir)}) == "hillocal"
    assert resolve_interface("lo", None, {LOCAL_DIR_ENV: str(can_dir)}) == "socketcan"  # the kernel's first
    monkeypatch.setenv(LOCAL_DIR_ENV, str(can_dir))
    bus, desc = open_can_bus("vcan-x", None, receive=False)
    bus.shutdown()
    assert desc.startswith("hillocal (auto) channel vcan-x in ")


def test_a_process_started_by_hand_finds_the_running_rigs_bus_by_its_name(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    """``hil replay --can`` or a python-can tool beside a running ``hil up --rig R``: found as a
    viewer finds the rig (its endpoint file, whose process is alive); a dead run's is passed over."""
    from hil.bus.endpoint import RigAccess

    runtime = tmp_path / "rt"
    runtime.mkdir(mode=0o700)
    monkeypatch.setenv("HIL_RUNTIME_DIR", str(runtime))
    monkeypatch.delenv(LOCAL_DIR_ENV, raising=False)
    dead = subprocess.Popen([sys.executable, "-c", "pass"])
    dead.wait()
    gone = RigAccess("r1", "tcp/127.0.0.1:1", dead.pid, authenticated=False, directory=runtime)
    gone.write()
    gone.can_dir.mkdir(mode=0o700)
    assert resolve_interface("vcan-x", None, rig="r1") == "hilzenoh"  # only a dead run's
    access = RigAccess("r1", "tcp/127.0.0.1:1", os.getpid(), authenticated=False, directory=runtime)
    access.write()
    assert resolve_interface("vcan-x", None, rig="r1") == "hilzenoh"  # running, but no CAN directory
    live_dir = access.can_dir
    live_dir.mkdir(mode=0o700)
    assert resolve_interface("vcan-x", None, rig="r1") == "hillocal"
    assert resolve_interface("vcan-x", None, rig="r2") == "hilzenoh"
    listener = LocalCanBus(channel="vcan-x", directory=live_dir)
    try:
        bus, desc = open_can_bus("vcan-x", None, rig="r1", receive=False)
        try:
            assert desc.startswith("hillocal (auto) channel vcan-x")
            bus.send(can.Message(arbitration_id=0x42, is_extended_id=False, data=b"hi"))
            got = listener.recv(timeout=10)
            assert got is not None and bytes(got.data) == b"hi"
        finally:
            bus.shutdown()
    finally:
        listener.shutdown()
        remove_can_dir(live_dir)
    with pytest.raises(can.CanInitializationError, match="no rig 'r2' running"):
        LocalCanBus(channel="vcan-x", rig="r2")


def test_hil_up_gives_its_children_a_can_directory_unless_it_joins_a_router_or_is_told_otherwise(
    monkeypatch: pytest.MonkeyPatch,
) -> None:
    from hil.runtime.supervisor import Supervisor, UpOptions

    for var in ("HIL_ZENOH_CONNECT", "HIL_ZENOH_MODE", LOCAL_DIR_ENV):
        monkeypatch.delenv(var, raising=False)
    for iface, local in ((None, True), ("auto", True), ("hillocal", True), ("hilzenoh", False)):
        sup = Supervisor(UpOptions(live=False, rig="cd", channel="vcan-none", interface=iface))
        assert (sup.can_dir is not None) == local, iface
        env = sup._child_env()
        assert (env.get(LOCAL_DIR_ENV) == str(sup.can_dir)) if local else (LOCAL_DIR_ENV not in env)
        if local:
            assert sup.can_dir is not None and sup.can_dir.name == f"cd-{os.getpid()}.can"
    # a kernel interface of that name (lo stands in for vcan0): SocketCAN, no directory
    assert Supervisor(UpOptions(live=False, rig="cd", channel="lo")).can_dir is None
    # joining a router: the rig may span hosts, so its CAN goes over Zenoh
    monkeypatch.setenv("HIL_ZENOH_CONNECT", "tcp/127.0.0.1:1")
    assert Supervisor(UpOptions(live=False, rig="cd", channel="vcan-none")).can_dir is None


def test_a_listener_that_dropped_the_connection_is_reconnected_at_the_next_send(can_dir: Path) -> None:
    sender = LocalCanBus(channel="vcan0", directory=can_dir, receive=False)
    listener = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
    listener.bind(str(can_dir / "vcan0" / "flaky.sock"))
    listener.listen(4)
    listener.settimeout(10)
    frame = can.Message(arbitration_id=0x55, is_extended_id=False, data=b"\x01")
    try:
        sender.send(frame)  # connects, and the packet waits in the new connection
        first, _ = listener.accept()
        first.close()  # the listener drops this sender (as a reader that restarted would)
        deadline = time.monotonic() + 10
        while sender.tx_peers_lost == 0 and time.monotonic() < deadline:
            sender.send(frame)  # fails once the close is seen: dropped, looked for again
        assert sender.tx_peers_lost == 1
        sender.send(frame)  # the socket still answers: connected again
        second, _ = listener.accept()
        second.settimeout(10)
        data = second.recv(4096)
        _stamps, frames = parse_packet(data)
        assert [m.arbitration_id for _s, m in frames] == [0x55] and sender.peers == 1
        second.close()
    finally:
        listener.close()
        sender.shutdown()


def test_hil_up_removes_the_can_directories_of_killed_runs_only(tmp_path: Path) -> None:
    """A run killed before it removed its directory leaves ``<rig>-<pid>.can``: the next ``hil up``
    removes those whose process is gone, never a running rig's."""
    from hil.runtime.supervisor import _remove_stale_can_dirs

    gone = subprocess.Popen([sys.executable, "-c", "pass"])
    gone.wait()
    dead = tmp_path / f"old-rig-{gone.pid}.can"
    live = tmp_path / f"bench-{os.getpid()}.can"
    other = tmp_path / "notes.can"  # not a run's name: left alone
    for d in (dead, live, other):
        (d / "vcan0").mkdir(parents=True)
    _remove_stale_can_dirs(tmp_path)
    assert not dead.exists() and live.is_dir() and other.is_dir()

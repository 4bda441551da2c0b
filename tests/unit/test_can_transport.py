"""hilzenoh between two real processes over a loopback Zenoh hub; the CAN node's failure policy."""

from __future__ import annotations

import errno
import itertools
import subprocess
import sys
import textwrap
import time
from typing import Any

import can
import pytest

from hil.bus.session import BusConfig, open_session
from hil.can.bus import open_can_bus, resolve_interface
from hil.can.busload import frame_bits, sample_load
from hil.can.codec import ImuCanCodec
from hil.can.frame_bus import pack_frame, unpack_frame, unpack_frames
from hil.can.node import CanTransmitter, ImuCanNode
from tests.conftest import exchange_with_child

CHILD = textwrap.dedent(
    """
    import sys, can
    n = int(sys.argv[1])
    bus = can.Bus(interface="hilzenoh", channel="vcan0", rig=sys.argv[2], fd=True)
    assert bus.recv(timeout=20).arbitration_id == 0x7FF        # the parent's "go"
    for i in range(n):
        data = i.to_bytes(8, "little")
        bus.send(can.Message(arbitration_id=0x100 + i % 4, is_extended_id=False, data=data))
    bus.send(can.Message(arbitration_id=0x110, is_extended_id=False, is_fd=True, bitrate_switch=True,
                         data=bytes(range(32))))
    ack = bus.recv(timeout=20)                                  # wait until the parent has it all
    while ack is not None and ack.arbitration_id == 0x7FF:      # skip repeated "go"s
        ack = bus.recv(timeout=20)
    print("ack", ack is not None and ack.arbitration_id == 0x7FE, flush=True)
    bus.shutdown()
    """
)


def test_zenoh_can_bus_between_two_processes(zenoh_hub: str) -> None:
    n = 2000
    rig = "t-canbus"
    child = subprocess.Popen(
        [sys.executable, "-c", CHILD, str(n), rig], stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    bus = can.Bus(interface="hilzenoh", channel="vcan0", rig=rig, fd=True)
    t0 = time.time()
    got, out, err = exchange_with_child(bus, child, n + 1, 20.0)
    assert child.returncode == 0, err
    assert "ack True" in out
    # every frame, in order, none of our own "go"/"ack" echoed back
    assert [int.from_bytes(m.data, "little") for m in got[:n]] == list(range(n))
    assert all(m.arbitration_id not in (0x7FF, 0x7FE) for m in got)
    fd = got[n]
    assert fd.is_fd and fd.bitrate_switch and bytes(fd.data) == bytes(range(32)) and not fd.is_extended_id
    # receive stamps: epoch seconds taken on arrival, non-decreasing
    stamps = [m.timestamp for m in got]
    assert t0 - 1 < stamps[0] <= stamps[-1] <= time.time()
    assert all(b >= a for a, b in itertools.pairwise(stamps))


def test_classic_bus_refuses_fd_and_filters_apply(zenoh_hub: str) -> None:
    rig = "t-canbus2"
    a = can.Bus(interface="hilzenoh", channel="can1", rig=rig, fd=True)
    b = can.Bus(
        interface="hilzenoh",
        channel="can1",
        rig=rig,
        fd=False,
        can_filters=[{"can_id": 0x100, "can_mask": 0x7FF, "extended": False}],
    )
    try:
        with pytest.raises(can.CanOperationError, match="fd=False"):
            b.send(can.Message(arbitration_id=1, is_fd=True, data=bytes(12)))
        with pytest.raises(can.CanOperationError, match="classic"):
            b.send(can.Message(arbitration_id=1, data=bytes(9), check=False))
        time.sleep(0.3)
        a.send(can.Message(arbitration_id=0x110, is_extended_id=False, is_fd=True, data=bytes(32)))
        a.send(can.Message(arbitration_id=0x101, is_extended_id=False, data=b"\x01"))
        a.send(can.Message(arbitration_id=0x100, is_extended_id=False, data=b"\x02"))
        msg = b.recv(timeout=3)
        assert msg is not None and msg.arbitration_id == 0x100
        assert b.rx_fd_ignored == 1  # type: ignore[attr-defined]
    finally:
        a.shutdown()
        b.shutdown()
    with pytest.raises(can.CanOperationError):
        a.send(can.Message(arbitration_id=1, data=b""))


def test_malformed_payload_is_counted_not_raised(zenoh_hub: str) -> None:
    bus = can.Bus(interface="hilzenoh", channel="vcan9", rig="t-canbus3")
    stray = open_session(BusConfig.from_env())  # a stray publisher writing garbage on the key
    try:
        time.sleep(0.3)
        stray.put("hilcan/t-canbus3/vcan9", b"\x01\x02")
        deadline = time.time() + 3
        while bus.rx_malformed == 0 and time.time() < deadline:  # type: ignore[attr-defined]
            assert bus.recv(timeout=0.1) is None
        assert bus.rx_malformed == 1  # type: ignore[attr-defined]
    finally:
        stray.close()
        bus.shutdown()


def test_frame_payload_round_trip() -> None:
    m = can.Message(
        arbitration_id=0x1ABCDEF0, is_extended_id=True, is_fd=True, error_state_indicator=True, data=b"x" * 48
    )
    sender, back = unpack_frame(pack_frame(42, m))
    assert sender == 42 and back.equals(m, timestamp_delta=None)
    with pytest.raises(ValueError):
        unpack_frame(b"\x00" * 5)
    with pytest.raises(ValueError):
        unpack_frame(pack_frame(1, m)[:-1])


def _sample_frames(k: int) -> list[can.Message]:
    return [
        can.Message(arbitration_id=0x181 + j, is_extended_id=False, data=bytes([k & 0xFF, j] * 4))
        for j in range(4)
    ]


def test_burst_payload_round_trip_and_malformed_bursts_refused() -> None:
    frames = _sample_frames(7)
    payload = b"".join(pack_frame(9, m) for m in frames)
    back = unpack_frames(payload)
    assert [s for s, _m in back] == [9] * 4
    assert all(b.equals(m, timestamp_delta=None) for (_s, b), m in zip(back, frames, strict=True))
    with pytest.raises(ValueError, match="carries 4 frames"):
        unpack_frame(payload)  # one frame was asked for
    for cut in (1, 14, len(payload) - 1):  # a truncated record anywhere: the whole payload is refused
        with pytest.raises(ValueError):
            unpack_frames(payload[:-cut])


def test_a_burst_is_one_zenoh_message_and_each_frame_keeps_its_wire_stamp(zenoh_hub: str) -> None:
    rig = "t-canburst"
    tx = can.Bus(interface="hilzenoh", channel="vcan0", rig=rig, receive=False)
    rx = can.Bus(interface="hilzenoh", channel="vcan0", rig=rig)
    stray = open_session(BusConfig.from_env())
    try:
        # until the subscription is matched, probe with single frames
        deadline = time.time() + 10
        while rx.recv(timeout=0.1) is None and time.time() < deadline:
            tx.send(can.Message(arbitration_id=0x7FF, is_extended_id=False, data=b"probe"))
        while rx.recv(timeout=0.3) is not None:
            pass
        samples0 = rx.rx_samples  # type: ignore[attr-defined]
        now_ns = time.time_ns()
        n = 50
        for k in range(n):
            stamps = [now_ns - 10_000_000 + k * 100_000 + j * 135_000 for j in range(4)]
            tx.send_burst_stamped(_sample_frames(k), stamps)  # type: ignore[attr-defined]
        got: list[can.Message] = []
        deadline = time.time() + 20
        while len(got) < 4 * n and time.time() < deadline:
            m = rx.recv(timeout=0.2)
            if m is not None:
                got.append(m)
        assert len(got) == 4 * n
        assert [(m.arbitration_id, m.data[0]) for m in got] == [
            (0x181 + j, k) for k in range(n) for j in range(4)
        ]
        want = [(now_ns - 10_000_000 + k * 100_000 + j * 135_000) * 1e-9 for k in range(n) for j in range(4)]
        assert [m.timestamp for m in got] == pytest.approx(want, abs=1e-6)
        assert rx.rx_samples - samples0 == n  # type: ignore[attr-defined]  # one Zenoh message per burst
        assert tx.tx_frames >= 4 * n  # type: ignore[attr-defined]
        # a stamp in the future is the receiver's arrival, counted as clock skew
        tx.send_burst_stamped(_sample_frames(1), [time.time_ns() + 10**10] * 4)  # type: ignore[attr-defined]
        late = [rx.recv(timeout=5) for _ in range(4)]
        assert all(m is not None and m.timestamp <= time.time() for m in late)
        assert rx.rx_stamp_skew == 4  # type: ignore[attr-defined]
        # a burst with one record cut short: counted once, none of its frames delivered
        bad = b"".join(pack_frame(5, m) for m in _sample_frames(2))[:-3]
        stray.put(f"hilcan/{rig}/vcan0", bad)
        deadline = time.time() + 5
        while rx.rx_malformed == 0 and time.time() < deadline:  # type: ignore[attr-defined]
            assert rx.recv(timeout=0.1) is None
        assert rx.rx_malformed == 1  # type: ignore[attr-defined]
        with pytest.raises(can.CanOperationError, match="3 stamps"):
            tx.send_burst_stamped(_sample_frames(0), [now_ns] * 3)  # type: ignore[attr-defined]
    finally:
        stray.close()
        tx.shutdown()
        rx.shutdown()


def test_transmitter_sends_a_burst_in_one_write_and_drops_it_whole_on_failure() -> None:
    class BurstBus(_FlakyBus):
        def __init__(self, fail: int) -> None:
            super().__init__(fail)
            self.writes: list[list[tuple[int, int]]] = []

        def send_burst_stamped(self, msgs: Any, stamps: Any, timeout: float | None = None) -> None:
            if self.fail:
                self.fail -= 1
                raise can.CanOperationError("Transmit buffer full", error_code=errno.ENOBUFS)
            self.writes.append([(m.arbitration_id, s) for m, s in zip(msgs, stamps, strict=True)])

    sleeps: list[float] = []
    bus = BurstBus(fail=1)
    tx = CanTransmitter(bus, None, sleep=sleeps.append)
    frames = _sample_frames(3)
    assert tx.send_burst(frames, [10, 20, 30, 40]) is True
    assert bus.writes == [[(0x181, 10), (0x182, 20), (0x183, 30), (0x184, 40)]] and sleeps == [0.0005]
    c = tx.counters()
    assert c["tx_frames"] == 4 and c["tx_retries"] == 1 and c["tx_buffer_full"] == 1
    dead = BurstBus(fail=-1)
    tx = CanTransmitter(dead, None, sleep=sleeps.append)
    assert tx.send_burst(frames, [1, 2, 3, 4]) is False
    c = tx.counters()
    assert c["tx_dropped_frames"] == 4 and c["tx_frames"] == 0 and c["tx_retries"] == 3
    # a bus without bursts (SocketCAN) gets the frames one by one
    plain = _FlakyBus(fail=0)
    tx = CanTransmitter(plain, None)
    assert tx.send_burst(frames, [1, 2, 3, 4]) is True and len(plain.sent) == 4
    for b in (bus, dead, plain):
        b.shutdown()


def test_auto_interface_resolution() -> None:
    assert resolve_interface("lo", None) == "socketcan"  # any existing netdev counts as present
    assert resolve_interface("vcan-does-not-exist", "auto") == "hilzenoh"
    assert resolve_interface("x", "virtual") == "virtual"
    bus, desc = open_can_bus("vnode", "virtual")
    bus.shutdown()
    assert desc.startswith("virtual channel vnode")


class _FlakyBus(can.BusABC):
    """Raises ENOBUFS for the first ``fail`` sends (or always with fail < 0)."""

    def __init__(self, fail: int) -> None:
        self.fail = fail
        self.sent: list[can.Message] = []
        super().__init__(channel="flaky")

    def send(self, msg: can.Message, timeout: float | None = None) -> None:
        if self.fail != 0:
            self.fail -= 1 if self.fail > 0 else 0
            raise can.CanOperationError("Transmit buffer full", error_code=errno.ENOBUFS)
        self.sent.append(msg)

    def _recv_internal(self, timeout: float | None) -> tuple[can.Message | None, bool]:
        return None, False


def test_node_backs_off_on_full_buffer_then_counts_drops() -> None:
    sleeps: list[float] = []
    bus = _FlakyBus(fail=2)
    node = ImuCanNode(bus, ImuCanCodec.from_dbc(), None, sleep=sleeps.append)
    assert node.send_sample(0, [0.0] * 3, [0.0] * 3) is True
    c = node.counters()
    assert c["tx_buffer_full"] == 2 and c["tx_retries"] == 2 and c["tx_frames"] == 5
    assert sleeps == [0.0005, 0.001]
    dead = _FlakyBus(fail=-1)
    node = ImuCanNode(dead, ImuCanCodec.from_dbc(), None, sleep=sleeps.append)
    assert node.send_sample(0, [0.0] * 3, [0.0] * 3) is False
    assert node.send_sync(5) is False
    c = node.counters()
    assert c["tx_dropped_frames"] == 6 and c["tx_dropped_samples"] == 1 and c["tx_frames"] == 0
    assert node.send_sample(0, [float("nan")] * 3, [0.0] * 3) is False
    assert node.counters()["tx_encode_errors"] == 1
    bus.shutdown()
    dead.shutdown()


def test_node_bus_load_matches_frame_arithmetic() -> None:
    t = [0.0]
    bus = _FlakyBus(fail=0)
    node = ImuCanNode(bus, ImuCanCodec.from_dbc(fd=False), None, now=lambda: t[0])
    for i in range(400):  # one second at 400 Hz
        t[0] = i / 400
        node.send_sample(i * 2_500_000, [0.0] * 3, [0.0] * 3)
    status_frames = sum(1 for m in bus.sent if m.arbitration_id == 0x180)
    expect = (400 * 4 + status_frames) * frame_bits(8).seconds()
    assert node.bus_load() == pytest.approx(expect, rel=0.02)
    assert 0.2 < node.bus_load() < 0.25
    assert sample_load([(32, True)], 400) < 0.05  # FD: one frame per sample, data phase at 5 Mbit/s
    bus.shutdown()

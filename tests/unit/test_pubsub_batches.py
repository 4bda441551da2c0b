"""Every hil subscriber takes a batch (``Publisher.put_many``) message by message: the typed
``Subscriber``, the ``DispatchSubscriber`` and the services' ``RawSubscriber``; a batch that is
not one is counted, never raised."""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Any

import pytest
import zenoh

from hil.bus.pubsub import DispatchSubscriber, RawSubscriber, Stats, Subscriber
from hil.bus.session import BusConfig, open_session
from hil.messages import MAX_BATCH, CanFrame, encode, encode_batch

KEY = "hil/t/can/vcan0"


@dataclass
class _Payload:
    raw: bytes

    def to_bytes(self) -> bytes:
        return self.raw


@dataclass
class _Sample:
    """What the subscribers read of a zenoh.Sample."""

    key_expr: str
    payload: _Payload
    source_info: Any = None


def _frame(seq: int) -> CanFrame:
    return CanFrame(seq=seq, stamp_ns=seq, channel="vcan0", arbitration_id=0x181, data_hex="00" * 8)


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    s = open_session(BusConfig(mode="peer", listen=(), connect=()))
    try:
        yield s
    finally:
        s.close()


def _feed(sub: Any, payloads: list[bytes]) -> None:
    for raw in payloads:
        sub._on_sample(_Sample(KEY, _Payload(raw)))


PAYLOADS = [
    encode(_frame(0)),
    encode_batch([_frame(1), _frame(2), _frame(3)]),
    b"[" + encode(_frame(4)),  # a cut batch: refused whole
    encode_batch([_frame(5), _frame(6)]).replace(b'"seq":6', b'"seq":-1'),  # one bad element
    encode_batch([_frame(i) for i in range(MAX_BATCH + 1)]),  # too many: refused whole
]


def test_typed_and_dispatch_subscribers_take_batches_message_by_message(session: zenoh.Session) -> None:
    for make in (
        lambda st, got: Subscriber(session, KEY, CanFrame, lambda m, _k: got.append(m.seq), st),
        lambda st, got: DispatchSubscriber(
            session, KEY, {"can": (CanFrame, lambda m, _k: got.append(m.seq))}, st
        ),
    ):
        stats, got = Stats(), []
        sub = make(stats, got)
        try:
            _feed(sub, PAYLOADS)
        finally:
            sub.undeclare()
        assert got == [0, 1, 2, 3, 5]
        assert stats.counters["rejected.can.vcan0.invalid"] == 3, stats.counters


def test_raw_subscriber_hands_each_message_of_a_batch_to_the_inbox(session: zenoh.Session) -> None:
    stats, got = Stats(), []
    sub = RawSubscriber(session, KEY, {"can": CanFrame}, lambda k, raw, src, cls: got.append(raw), stats)
    try:
        _feed(sub, PAYLOADS[:3])
    finally:
        sub.undeclare()
    assert got == [encode(_frame(i)) for i in range(4)]  # the bytes each was encoded as
    assert stats.counters["rejected.can.vcan0.invalid"] == 1

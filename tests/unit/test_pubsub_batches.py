"""Every hil subscriber takes a batch (``Publisher.put_many``) message by message: the typed
``Subscriber``, the ``DispatchSubscriber`` and the services' ``RawSubscriber``, each on a real
Zenoh session fed by a real publisher; a batch that is not one is counted, never raised."""

from __future__ import annotations

import time
from collections.abc import Callable, Iterator
from typing import Any

import pytest
import zenoh

from hil.bus.pubsub import DispatchSubscriber, Publisher, RawSubscriber, Stats, Subscriber
from hil.bus.session import BusConfig, open_session
from hil.messages import MAX_BATCH, CanFrame, encode, encode_batch

KEY = "hil/t/can/vcan0"


def _frame(seq: int) -> CanFrame:
    return CanFrame(seq=seq, stamp_ns=seq, channel="vcan0", arbitration_id=0x181, data_hex="00" * 8)


# what goes on the key, in order: a message, a batch, a cut batch (refused whole), a batch with
# one invalid element (refused alone), a batch of one too many (refused whole), a last message
BAD = [
    b"[" + encode(_frame(4)),
    encode_batch([_frame(5), _frame(6)]).replace(b'"seq":6', b'"seq":-1'),
    encode_batch([_frame(i) for i in range(MAX_BATCH + 1)]),
]


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    s = open_session(BusConfig(mode="peer", listen=(), connect=()))
    try:
        yield s
    finally:
        s.close()


def _send_and_wait(session: zenoh.Session, got: list[Any], last: Any) -> None:
    pub = Publisher(session, KEY, CanFrame)
    raw = session.declare_publisher(KEY)
    try:
        pub.put(_frame(0))
        pub.put_many([_frame(1), _frame(2), _frame(3)])
        for payload in BAD:
            raw.put(payload)
        pub.put(_frame(7))
        deadline = time.monotonic() + 20
        while last not in got and time.monotonic() < deadline:
            time.sleep(0.02)
    finally:
        raw.undeclare()
        pub.undeclare()


@pytest.mark.parametrize("kind", ["typed", "dispatch"])
def test_typed_and_dispatch_subscribers_take_batches_message_by_message(
    session: zenoh.Session, kind: str
) -> None:
    stats, got = Stats(), []
    on: Callable[[CanFrame, str], None] = lambda m, _k: got.append(m.seq)  # noqa: E731
    sub: Any = (
        Subscriber(session, KEY, CanFrame, on, stats)
        if kind == "typed"
        else DispatchSubscriber(session, KEY, {"can": (CanFrame, on)}, stats)
    )
    try:
        _send_and_wait(session, got, 7)
    finally:
        sub.undeclare()
    assert got == [0, 1, 2, 3, 5, 7]
    assert stats.counters["rejected.can.vcan0.invalid"] == 3, stats.counters


def test_raw_subscriber_hands_each_message_of_a_batch_to_the_inbox(session: zenoh.Session) -> None:
    stats, got = Stats(), []
    sub = RawSubscriber(session, KEY, {"can": CanFrame}, lambda k, raw, src, cls: got.append(raw), stats)
    try:
        _send_and_wait(session, got, encode(_frame(7)))
    finally:
        sub.undeclare()
    # the bytes each was encoded as; the bad element is the consumer's to refuse (it decodes)
    want = [encode(_frame(i)) for i in range(4)]
    assert got[:4] == want and got[-1] == encode(_frame(7)) and len(got) == 7
    assert stats.counters["rejected.can.vcan0.invalid"] == 2, stats.counters

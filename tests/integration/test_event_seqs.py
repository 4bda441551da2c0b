"""One seq counter per key: a live service's own events (its line, CAN transport, pacing) and its
node's (``fault_start``, ...) share ``event/<name>``; two counters gave both seq 0 whenever a
fault was applied (``hil info``: dups 1)."""

from __future__ import annotations

import threading
import time
from collections.abc import Iterator

import pytest
import zenoh

from hil.bus.session import BusConfig, open_session
from hil.messages import Event, FaultCommand, decode, split_batch
from hil.messages import params as fault_params
from hil.runners.sim import SimOptions, sim_run_info
from hil.runtime.service import ServiceContext
from services.gnss_emulator import SERVICE
from tests.conftest import free_port

RIG = "seqtest"


@pytest.fixture
def session() -> Iterator[zenoh.Session]:
    s = open_session(BusConfig(mode="peer", listen=(f"tcp/127.0.0.1:{free_port()}",), connect=()))
    try:
        yield s
    finally:
        s.close()


def test_the_services_events_and_its_nodes_share_one_seq_counter(session: zenoh.Session) -> None:
    got: list[Event] = []
    lock = threading.Lock()

    def on_event(sample: zenoh.Sample) -> None:
        with lock:
            got.extend(decode(Event, p) for p in split_batch(sample.payload.to_bytes()))

    sub = session.declare_subscriber(f"hil/{RIG}/event/gnss_emulator", on_event)
    try:
        svc = SERVICE(ServiceContext(name="gnss_emulator", rig=RIG, session=session, options={}))
        svc.emit_event("line", "before the node")  # as _open_line / _open_can do in setup
        run = sim_run_info(SimOptions(scenario="straight_level", duration_s=3.0))
        node = svc.make_node(run)
        with svc.lock:
            svc.node = node
        svc.emit_event("pacing", "{}")  # as the live runner does once its node exists
        cmd = FaultCommand(seq=1, stamp_ns=0, kind="gnss_outage", params=fault_params({}), duration_s=1.0)
        node.on_message("control/fault", cmd, 0)
        svc._publish(node.tick(1), "tick")  # the node's fault_start, on the same key
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline:
            with lock:
                if len(got) >= 3:
                    break
            time.sleep(0.05)
    finally:
        sub.undeclare()
    with lock:
        kinds = [e.kind for e in got]
        seqs = [e.seq for e in got]
    assert sorted(kinds) == ["fault_start", "line", "pacing"], kinds
    assert sorted(seqs) == [0, 1, 2], list(zip(kinds, seqs, strict=True))

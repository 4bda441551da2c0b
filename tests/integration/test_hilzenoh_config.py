"""The ``hilzenoh`` python-can interface takes its rig from python-can's own configuration and
says so when it listens on a rig with no traffic (a real Zenoh hub, real ``can.Bus`` calls)."""

from __future__ import annotations

import logging
import time

import can
import pytest


def test_the_rig_comes_from_python_can_config_then_hil_rig(
    zenoh_hub: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    monkeypatch.setenv("HIL_RIG", "fromenv")
    monkeypatch.setenv("CAN_CONFIG", '{"rig": "fromcfg"}')  # python-can's own config, as ~/.canrc would
    with can.Bus(interface="hilzenoh", channel="vcan9", no_traffic_warn_s=0) as bus:
        assert bus.key == "hilcan/fromcfg/vcan9"
    monkeypatch.delenv("CAN_CONFIG")
    with can.Bus(interface="hilzenoh", channel="vcan9", no_traffic_warn_s=0) as bus:
        assert bus.key == "hilcan/fromenv/vcan9"
    with can.Bus(interface="hilzenoh", channel="vcan9", rig="kw", no_traffic_warn_s=0) as bus:
        assert bus.key == "hilcan/kw/vcan9"


def test_a_bus_on_a_silent_rig_warns_and_a_busy_one_does_not(
    zenoh_hub: str, caplog: pytest.LogCaptureFixture
) -> None:
    caplog.set_level(logging.WARNING, logger="can.hilzenoh")
    with (
        can.Bus(interface="hilzenoh", channel="vcan9", rig="nosuchrig", no_traffic_warn_s=0.3) as silent,
        can.Bus(interface="hilzenoh", channel="vcan9", rig="busy", no_traffic_warn_s=5) as busy,
        can.Bus(interface="hilzenoh", channel="vcan9", rig="busy", no_traffic_warn_s=0) as peer,
    ):
        # a new subscription reaches the peer within moments (longer under load): send until heard
        got = None
        deadline = time.monotonic() + 30
        while got is None and time.monotonic() < deadline:
            peer.send(can.Message(arbitration_id=1, data=b"\x01"))
            got = busy.recv(timeout=0.2)
        assert got is not None and got.arbitration_id == 1
        deadline = time.monotonic() + 30
        while time.monotonic() < deadline and not [
            r for r in caplog.records if "nosuchrig" in r.getMessage()
        ]:
            time.sleep(0.1)
        assert busy._watch is not None
        busy._watch.join(timeout=30)  # the busy bus's watch has looked, and kept quiet
        assert not busy._watch.is_alive()
    warned = [r.getMessage() for r in caplog.records if r.name == "can.hilzenoh"]
    assert any("hilcan/nosuchrig/vcan9" in m and "rig keyword" in m for m in warned), warned
    assert not any("hilcan/busy/" in m for m in warned), warned
    assert silent.rig == "nosuchrig"

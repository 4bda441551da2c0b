"""``hil.foxglove_relay``: Foxglove's WebSocket protocol under both its subprotocol names on one port.

foxglove-sdk's server answers a client offering only ``foxglove.websocket.v1`` (Foxglove Studio
before the SDK, older Lichtblick, ws-protocol's client) with HTTP 400; through the relay such a
client is served, told the name it offered, and every other handshake passes as it was. Real
sockets on loopback and the SDK's own server; the pre-SDK client itself (ws-protocol's
FoxgloveClient, in node) is in tests/integration/test_foxglove_live.py.
"""

from __future__ import annotations

import asyncio
import json
import socket
from collections.abc import Iterator
from typing import Any

import foxglove
import pytest
import websockets
from websockets.sync.client import connect

from hil import foxglove_relay
from hil.foxglove_relay import (
    FIRST_NAME,
    SDK_NAME,
    Relay,
    client_response,
    offered_names,
    upstream_request,
)

REQUEST = (
    b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
    b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\nSec-WebSocket-Version: 13\r\n"
    b"%s\r\nUser-Agent: test\r\n\r\n"
)


def _request(protocol_lines: bytes) -> bytes:
    return REQUEST % protocol_lines


def test_the_names_offered_are_read_from_every_protocol_header_in_any_case() -> None:
    head = _request(b"sec-websocket-protocol: a, foxglove.websocket.v1\r\nSEC-WEBSOCKET-PROTOCOL:b")
    assert offered_names(head) == ["a", FIRST_NAME, "b"]
    assert offered_names(_request(b"X-Other: 1")) == []


def test_a_client_offering_only_the_first_name_is_offered_as_the_sdks_and_answered_in_its_own() -> None:
    head = _request(b"Sec-WebSocket-Protocol: foxglove.websocket.v1")
    up, rename = upstream_request(head)
    assert rename and offered_names(up) == [SDK_NAME]
    # the rest of the request as it was, the head still ending with its blank line
    assert up.startswith(b"GET / HTTP/1.1\r\nHost: 127.0.0.1:8765\r\n") and up.endswith(b"\r\n\r\n")
    assert b"Sec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n" in up and b"User-Agent: test" in up
    answer = (
        b"HTTP/1.1 101 Switching Protocols\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n"
        b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\nSec-WebSocket-Protocol: foxglove.sdk.v1\r\n\r\n"
    )
    back = client_response(answer)
    assert offered_names(back) == [FIRST_NAME]
    assert back.startswith(b"HTTP/1.1 101 Switching Protocols\r\n") and back.endswith(b"\r\n\r\n")
    assert b"Sec-WebSocket-Accept: s3pPLMBiTxaQ9kYGzzhZRbK+xOo=\r\n" in back


@pytest.mark.parametrize(
    "lines",
    [
        b"Sec-WebSocket-Protocol: foxglove.sdk.v1",
        b"Sec-WebSocket-Protocol: foxglove.sdk.v1, foxglove.websocket.v1",
        b"Sec-WebSocket-Protocol: other",
        b"X-None: 1",
    ],
)
def test_every_other_handshake_passes_as_it_was(lines: bytes) -> None:
    head = _request(lines)
    assert upstream_request(head) == (head, False)


def test_a_refusal_is_passed_back_as_it_is() -> None:
    refusal = b"HTTP/1.1 400 Bad Request\r\ncontent-length: 46\r\n\r\n"
    assert client_response(refusal) == refusal


@pytest.fixture
def relay() -> Iterator[Relay]:
    server = foxglove.start_server(name="relay test", host="127.0.0.1", port=0)
    relay = None
    try:
        relay = Relay("127.0.0.1", 0, ("127.0.0.1", int(server.port)))
        yield relay
    finally:
        if relay is not None:
            relay.close()
        server.stop()


async def _server_info(url: str, names: list[str] | None) -> tuple[str | None, dict[str, Any]]:
    async with websockets.connect(url, subprotocols=names, open_timeout=30) as ws:  # type: ignore[arg-type]
        info = json.loads(await asyncio.wait_for(ws.recv(), 30))
        return ws.subprotocol, info


@pytest.mark.parametrize(
    ("offered", "chosen"),
    [
        ([FIRST_NAME], FIRST_NAME),
        ([SDK_NAME], SDK_NAME),
        ([SDK_NAME, FIRST_NAME], SDK_NAME),
        ([FIRST_NAME, SDK_NAME], SDK_NAME),
    ],
)
def test_the_sdks_server_serves_both_names_through_the_relay(
    relay: Relay, offered: list[str], chosen: str
) -> None:
    got, info = asyncio.run(_server_info(f"ws://127.0.0.1:{relay.port}", offered))
    assert got == chosen
    assert info["op"] == "serverInfo" and info["name"] == "relay test"
    key = "clients.first_name" if chosen == FIRST_NAME and SDK_NAME not in offered else "clients"
    assert relay.counters == {key: 1}


@pytest.mark.parametrize("offered", [["other"], None])
def test_what_the_sdk_refuses_is_refused_with_its_answer(relay: Relay, offered: list[str] | None) -> None:
    with pytest.raises(websockets.InvalidStatus) as err:
        asyncio.run(_server_info(f"ws://127.0.0.1:{relay.port}", offered))
    assert err.value.response.status_code == 400
    assert relay.counters == {"refused.by_server": 1}


def test_closing_the_relay_ends_its_connections(relay: Relay) -> None:
    async def held() -> str:
        async with websockets.connect(f"ws://127.0.0.1:{relay.port}", subprotocols=[FIRST_NAME]) as ws:  # type: ignore[list-item]
            await asyncio.wait_for(ws.recv(), 30)  # serverInfo
            await asyncio.get_running_loop().run_in_executor(None, relay.close)
            try:
                while True:
                    await asyncio.wait_for(ws.recv(), 30)
            except websockets.ConnectionClosed:
                return "closed"

    assert asyncio.run(held()) == "closed"
    with pytest.raises(OSError), socket.create_connection(("127.0.0.1", relay.port), timeout=5):
        pass  # nobody listens any more


def test_a_silent_client_is_let_go(relay: Relay, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(foxglove_relay, "HANDSHAKE_TIMEOUT_S", 0.5)
    with socket.create_connection(("127.0.0.1", relay.port), timeout=30) as silent:
        assert silent.recv(100) == b""  # closed without a word once its handshake timed out
    assert relay.counters == {"refused.no_handshake": 1}


def test_more_clients_than_allowed_are_answered_503(relay: Relay, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(foxglove_relay, "MAX_CLIENTS", 1)
    # the one place held by a served client for as long as it is connected
    with connect(f"ws://127.0.0.1:{relay.port}", subprotocols=[FIRST_NAME], open_timeout=30) as held:  # type: ignore[list-item]
        assert json.loads(held.recv(timeout=30))["op"] == "serverInfo"
        with socket.create_connection(("127.0.0.1", relay.port), timeout=30) as second:
            assert second.recv(100).startswith(b"HTTP/1.1 503")
    assert relay.counters == {"clients.first_name": 1, "refused.too_many_clients": 1}


def test_what_came_meanwhile_goes_in_one_send_and_an_end_is_told() -> None:
    a, b = socket.socketpair()
    with a, b:
        for part in (b"one", b"two", b"three"):
            a.sendall(part)
        first = b.recv(3)
        assert foxglove_relay._gathered(b, first) == (b"onetwothree", True)
        assert foxglove_relay._gathered(b, b"x") == (b"x", True)  # nothing more: not an end
        a.sendall(b"last")
        a.shutdown(socket.SHUT_WR)
        assert foxglove_relay._gathered(b, b"") == (b"last", False)

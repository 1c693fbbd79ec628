"""Issue 28: which WebSocket subprotocols the Foxglove server (foxglove-sdk) accepts.

foxglove-sdk 0.30 speaks only the SDK's protocol (``foxglove.sdk.v1``, ``foxglove.sdk.v1.1``) and
answers a client that offers only the older ``foxglove.websocket.v1`` (Foxglove Studio before the
SDK, Lichtblick before its Dec 2025 release, ``@foxglove/ws-protocol`` clients, ...) with
``HTTP 400 Bad Request`` / ``Missing expected sec-websocket-protocol header``; the SDK has no option
to accept it too.  docs/graph.md says which clients connect.  This pins the behaviour, so an SDK
update that changes it shows here (and the doc can be updated)."""

from __future__ import annotations

import base64
import os
import socket

import pytest

foxglove = pytest.importorskip("foxglove")


@pytest.fixture()
def server():
    srv = foxglove.start_server(name="rotortwin", host="127.0.0.1", port=0)  # as foxglove_node starts it
    try:
        yield srv
    finally:
        srv.stop()


def _handshake(port: int, protocols: str | None) -> str:
    """The server's HTTP answer to a WebSocket upgrade offering ``protocols``."""
    key = base64.b64encode(os.urandom(16)).decode()
    head = (f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nUpgrade: websocket\r\nConnection: Upgrade\r\n"
            f"Sec-WebSocket-Key: {key}\r\nSec-WebSocket-Version: 13\r\n")
    if protocols is not None:
        head += f"Sec-WebSocket-Protocol: {protocols}\r\n"
    with socket.create_connection(("127.0.0.1", port), timeout=5) as s:
        s.sendall((head + "\r\n").encode())
        data = b""
        while b"\r\n\r\n" not in data:
            chunk = s.recv(4096)
            if not chunk:
                break
            data += chunk
        s.settimeout(0.5)
        try:
            data += s.recv(4096)  # the 400's body, if any
        except OSError:
            pass
    return data.decode("latin-1")


@pytest.mark.parametrize("offered, chosen", [
    ("foxglove.sdk.v1", "foxglove.sdk.v1"),
    ("foxglove.sdk.v1.1", "foxglove.sdk.v1.1"),
    ("foxglove.sdk.v1, foxglove.websocket.v1", "foxglove.sdk.v1"),   # what tests/foxglove_ws.py offers
])
def test_sdk_subprotocols_connect(server, offered, chosen):
    reply = _handshake(server.port, offered)
    assert reply.startswith("HTTP/1.1 101"), reply
    assert f"sec-websocket-protocol: {chosen}" in reply.lower(), reply


@pytest.mark.parametrize("offered", ["foxglove.websocket.v1", None])
def test_legacy_ws_protocol_only_is_refused(server, offered):
    """What an old client sees: HTTP 400 with this exact body."""
    reply = _handshake(server.port, offered)
    assert reply.startswith("HTTP/1.1 400 Bad Request"), reply
    assert reply.endswith("Missing expected sec-websocket-protocol header"), reply


def test_websockets_client_with_legacy_protocol_gets_400(server):
    ws = pytest.importorskip("websockets.sync.client")
    from websockets.exceptions import InvalidStatus

    with pytest.raises(InvalidStatus) as err:
        ws.connect(f"ws://127.0.0.1:{server.port}", subprotocols=["foxglove.websocket.v1"], open_timeout=5)
    assert err.value.response.status_code == 400
    with ws.connect(f"ws://127.0.0.1:{server.port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5) as c:
        assert c.subprotocol == "foxglove.sdk.v1"
        assert '"op":"serverInfo"' in c.recv(timeout=5)

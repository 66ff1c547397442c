"""The TCP bridge with a peer written here with plain ``socket`` (no rap_bridges code),
speaking the frame format docs/bridges.md documents."""

from __future__ import annotations

import json
import socket
import struct
from typing import Any, cast

import anyio
import pytest
from rap_bridges import Bridge, BridgeSpec
from rap_bridges.tcp import TcpLink
from rap_sdk import MemoryFabric

from libs.rap_bridges.tests.contract import KEY, FabricSide, Reading, fast_backoff, until

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))


def frame(payload: bytes, headers: dict[str, str] | None = None) -> bytes:
    h = json.dumps(headers).encode() if headers else b""
    return struct.pack(">IH", 2 + len(h) + len(payload), len(h)) + h + payload


def recv_exactly(conn: socket.socket, n: int) -> bytes:
    data = b""
    while len(data) < n:
        chunk = conn.recv(n - len(data))
        if not chunk:
            raise ConnectionError("closed")
        data += chunk
    return data


def read_frame(conn: socket.socket) -> tuple[dict[str, Any], bytes]:
    (length,) = struct.unpack(">I", recv_exactly(conn, 4))
    body = recv_exactly(conn, length)
    (hlen,) = struct.unpack(">H", body[:2])
    headers = json.loads(body[2 : 2 + hlen]) if hlen else {}
    return headers, body[2 + hlen :]


def socket_server(listener: socket.socket, n: int) -> list[tuple[dict[str, Any], bytes]]:
    """Accept one bridge, take ``n`` frames and acknowledge each numbered one."""
    conn, _ = listener.accept()
    got = []
    with conn:
        conn.settimeout(10)
        while len(got) < n:
            headers, payload = read_frame(conn)
            got.append((headers, payload))
            if "rap-seq" in headers:
                conn.sendall(frame(b"", {"rap-ack": headers["rap-seq"]}))
    return got


async def test_a_plain_socket_server_gets_an_out_bridges_frames() -> None:
    listener = socket.create_server(("127.0.0.1", 0))
    listener.settimeout(10)
    port = listener.getsockname()[1]
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        spec = BridgeSpec(protocol="tcp", url=f"tcp://127.0.0.1:{port}", format="json", qos=1)
        b = Bridge("tcp-out", spec, fabric, KEY, direction="out", message=Reading)
        b.backoff = fast_backoff()
        await tg.start(b.run)
        side = FabricSide(fabric)
        for n in range(3):
            await side.publish(n, cycle=CYCLE if n == 0 else None)
        with listener, anyio.fail_after(15):
            got = await anyio.to_thread.run_sync(socket_server, listener, 3)
        await until(lambda: b.stats.sent >= 3)
        tg.cancel_scope.cancel()
    assert [json.loads(p)["n"] for _, p in got] == [0, 1, 2]
    assert got[0][0]["rap-cycle"] == CYCLE.hex()
    assert [h["rap-seq"] for h, _ in got] == ["0", "1", "2"]


def socket_client(port: int) -> list[str]:
    """Send a good frame, an oversize one (the bridge closes the connection), then,
    connected again, a numbered good frame and wait for its acknowledgement."""
    events = []
    with socket.create_connection(("127.0.0.1", port), timeout=10) as c:
        c.sendall(frame(b'{"n": 1}', {"rap-cycle": CYCLE.hex()}))
        c.sendall(struct.pack(">IH", 50_000_000, 0))
        try:
            closed = c.recv(1) == b""
        except ConnectionError:
            closed = True
        events.append("closed" if closed else "open")
    with socket.create_connection(("127.0.0.1", port), timeout=10) as c:
        c.sendall(frame(b'{"n": 2}', {"rap-seq": "0", "rap-sender": "plain"}))
        headers, payload = read_frame(c)
        events.append(f"ack {headers.get('rap-ack')} {payload!r}")
    return events


async def test_a_plain_socket_client_feeds_a_serving_in_bridge() -> None:
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        side = FabricSide(fabric)
        await tg.start(side.record)
        spec = BridgeSpec(
            protocol="tcp", url="tcp://127.0.0.1:0", serve=True, format="json", max_frame=4096
        )
        b = Bridge("tcp-in", spec, fabric, KEY, direction="in", message=Reading)
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        port = cast(TcpLink, b.link).port
        with anyio.fail_after(15):
            events = await anyio.to_thread.run_sync(socket_client, port)
        await side.wait_for(2)
        tg.cancel_scope.cancel()
    assert events == ["closed", "ack 0 b''"]
    assert side.readings() == [1, 2]
    assert side.got[0].cycle == CYCLE
    assert b.stats.rejected == 1
    assert "over the limit" in next(iter(b.stats.rejections.by_reason))

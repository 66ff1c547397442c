"""The WebSocket bridge with peers written here with the ``websockets`` library directly
(not the bridge's link), speaking the message format docs/bridges/websocket.md
documents: a plain server, a plain client sending a browser's text JSON, two clients of
a serving bridge, and TLS with client certificates."""

from __future__ import annotations

import json
import ssl
from pathlib import Path
from typing import cast

import anyio
import pytest
from blockbuster import blockbuster_ctx
from msgspec.msgpack import decode
from rap_bridges import Bridge, BridgeSpec
from rap_bridges.websocket import WebSocketLink
from rap_schemas import Envelope, keys
from rap_sdk import InboxPolicy, MemoryFabric, Overflow
from websockets.asyncio.client import connect
from websockets.asyncio.server import ServerConnection, serve
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus

from libs.rap_bridges.tests.contract import (
    KEY,
    SYSTEM,
    FabricSide,
    Reading,
    fast_backoff,
    until,
)
from libs.rap_bridges.tests.outside_websocket import pack, unpack
from libs.rap_sdk.tests.certs_support import make_certs

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))
BACK = keys.data(SYSTEM, "reading_back")


def serving(port: int = 0, *, tls: bool = False, **kw: object) -> BridgeSpec:
    return BridgeSpec(
        protocol="websocket",
        url=f"{'wss' if tls else 'ws'}://127.0.0.1:{port}",
        address="/robot",
        serve=True,
        format="json",
        **kw,  # type: ignore[arg-type]
    )


async def test_a_plain_websockets_server_gets_an_out_bridges_messages() -> None:
    got: list[tuple[dict[str, str], bytes]] = []
    paths: list[str] = []
    three = anyio.Event()

    async def handler(ws: ServerConnection) -> None:
        assert ws.request is not None
        paths.append(ws.request.path)
        async for message in ws:
            assert isinstance(message, bytes)  # the bridge sends binary messages only
            headers, payload = unpack(message)
            got.append((headers, payload))
            await ws.send(pack(b"", {"rap-ack": headers["rap-seq"]}))
            if len(got) == 3:
                three.set()

    async with serve(handler, "127.0.0.1", 0) as server:
        port = server.sockets[0].getsockname()[1]
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            spec = BridgeSpec(
                protocol="websocket",
                url=f"ws://127.0.0.1:{port}",
                address="/robot/scan",
                format="json",
                qos=1,
            )
            b = Bridge("ws-out", spec, fabric, KEY, direction="out", message=Reading)
            b.backoff = fast_backoff()
            await tg.start(b.run)
            side = FabricSide(fabric)
            for n in range(3):
                await side.publish(n, cycle=CYCLE if n == 0 else None)
            with anyio.fail_after(10):
                await three.wait()
            await until(lambda: b.stats.sent == 3)  # each acknowledged
            tg.cancel_scope.cancel()
    assert paths == ["/robot/scan"]
    assert [json.loads(p)["n"] for _, p in got] == [0, 1, 2]
    assert got[0][0]["rap-cycle"] == CYCLE.hex()
    assert got[0][0]["rap-type"] == "test.Reading/1"
    assert [h["rap-seq"] for h, _ in got] == ["0", "1", "2"]
    assert len({h["rap-sender"] for h, _ in got}) == 1


async def test_a_plain_client_feeds_a_serving_in_bridge_text_json_and_binary() -> None:
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        side = FabricSide(fabric)
        await tg.start(side.record)
        b = Bridge("ws-in", serving(max_frame=4096), fabric, KEY, direction="in", message=Reading)
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        port = cast(WebSocketLink, b.link).port
        with pytest.raises(InvalidStatus) as refused:  # another path: HTTP 404
            await connect(f"ws://127.0.0.1:{port}/elsewhere", proxy=None)
        assert refused.value.response.status_code == 404
        async with connect(f"ws://127.0.0.1:{port}/robot", proxy=None) as ws:
            await ws.send('{"n": 1, "note": "from a browser"}')  # text: bare JSON
            await ws.send(b"\x00")  # binary, too short for its header length
            await ws.send("not json")  # text, not a Reading
            await ws.send(pack(b'{"n": 2}', {"rap-seq": "0", "rap-sender": "plain"}))
            ack = await ws.recv()
            await ws.send(pack(b'{"n": 2}', {"rap-seq": "0", "rap-sender": "plain"}))
            again = await ws.recv()  # a resend: acknowledged, passed over
            await ws.send(pack(b'{"n": 3}', {"rap-cycle": CYCLE.hex()}))
            await side.wait_for(3)
            await ws.send(b"\x00\x00" + b"x" * 80_000)  # over max_frame + 64 KiB
            with pytest.raises(ConnectionClosed) as closed:
                await ws.recv()
        await until(lambda: b.stats.rejected == 3)
        tg.cancel_scope.cancel()
    assert unpack(cast(bytes, ack)) == ({"rap-ack": "0"}, b"")
    assert unpack(cast(bytes, again)) == ({"rap-ack": "0"}, b"")
    assert side.readings() == [1, 2, 3]
    assert side.got[2].cycle == CYCLE
    assert side.got[0].source == "ws-in"
    assert closed.value.rcvd is not None
    assert closed.value.rcvd.code == 1009
    reasons = " | ".join(b.stats.rejections.by_reason)
    assert "cannot hold its header length" in reasons
    assert "over the limit" in reasons
    assert "test.Reading/N JSON" in reasons


async def test_a_serving_out_bridge_sends_every_message_to_each_client() -> None:
    async def client(port: int, got: list[int], done: anyio.Event) -> None:
        async with connect(f"ws://127.0.0.1:{port}/robot", proxy=None) as ws:
            while len(got) < 3:
                headers, payload = unpack(cast(bytes, await ws.recv()))
                got.append(json.loads(payload)["n"])
                await ws.send(pack(b"", {"rap-ack": headers["rap-seq"]}))
            done.set()

    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        b = Bridge("ws-serve", serving(qos=1), fabric, KEY, direction="out", message=Reading)
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        link = cast(WebSocketLink, b.link)
        side = FabricSide(fabric)
        await side.publish(0)  # no client yet: the bridge waits for one
        firsts: list[int] = []
        seconds: list[int] = []
        done1, done2 = anyio.Event(), anyio.Event()
        tg.start_soon(client, link.port, firsts, done1)
        await until(lambda: firsts == [0])
        tg.start_soon(client, link.port, seconds, done2)
        await until(lambda: link.clients == 2)
        await side.publish(1)
        await side.publish(2)
        await side.publish(3)
        with anyio.fail_after(10):
            await done1.wait()
            await done2.wait()
        await until(lambda: b.stats.sent == 4)
        tg.cancel_scope.cancel()
    assert firsts == [0, 1, 2]
    assert seconds == [1, 2, 3]  # it came after message 0


def client_context(certs: Path, *, with_cert: bool) -> ssl.SSLContext:
    context = ssl.create_default_context(cafile=str(certs / "ca.pem"))
    if with_cert:
        context.load_cert_chain(str(certs / "robot.pem"), str(certs / "robot.key"))
    return context


async def send_once(uri: str, context: ssl.SSLContext) -> None:
    async with connect(uri, ssl=context, proxy=None) as ws:
        await ws.send('{"n": 0}')
        await ws.recv()


async def test_wss_admits_only_clients_with_a_certificate_of_its_ca(tmp_path: Path) -> None:
    certs = make_certs(
        tmp_path / "certs",
        {"bridge": "", "robot": ""},
        system="ws",
        hosts={"bridge": ["127.0.0.1"]},
    )
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        side = FabricSide(fabric)
        await tg.start(side.record)
        spec = serving(
            tls=True,
            ca=str(certs / "ca.pem"),
            cert=str(certs / "bridge.pem"),
            key=str(certs / "bridge.key"),
        )
        b = Bridge("wss-in", spec, fabric, KEY, direction="in", message=Reading)
        await tg.start(b.run)
        with anyio.fail_after(10):
            await b.wait_connected()
        uri = f"wss://127.0.0.1:{cast(WebSocketLink, b.link).port}/robot"
        with pytest.raises((OSError, InvalidHandshake)):  # TLS refused, so no WebSocket
            await send_once(uri, client_context(certs, with_cert=False))
        async with connect(uri, ssl=client_context(certs, with_cert=True), proxy=None) as ws:
            await ws.send('{"n": 1}')
            await side.wait_for(1)
        tg.cancel_scope.cancel()
    assert side.readings() == [1]


async def test_a_wss_out_bridge_checks_the_servers_certificate(tmp_path: Path) -> None:
    certs = make_certs(
        tmp_path / "certs",
        {"server": "", "robot": ""},
        system="ws",
        hosts={"server": ["127.0.0.1"]},
    )
    other = make_certs(tmp_path / "other", {}, system="other")
    server_tls = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
    server_tls.load_cert_chain(str(certs / "server.pem"), str(certs / "server.key"))
    got: list[bytes] = []
    arrived = anyio.Event()

    async def handler(ws: ServerConnection) -> None:
        async for message in ws:
            got.append(unpack(cast(bytes, message))[1])
            arrived.set()

    async with serve(handler, "127.0.0.1", 0, ssl=server_tls) as server:
        port = server.sockets[0].getsockname()[1]
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:

            def spec(ca: Path) -> BridgeSpec:
                return BridgeSpec(
                    protocol="websocket",
                    url=f"wss://127.0.0.1:{port}",
                    format="json",
                    qos=0,
                    ca=str(ca),
                )

            wrong = Bridge(
                "wss-wrong", spec(other / "ca.pem"), fabric, KEY, direction="out", message=Reading
            )
            wrong.backoff = fast_backoff()
            right = Bridge(
                "wss-out", spec(certs / "ca.pem"), fabric, KEY, direction="out", message=Reading
            )
            await tg.start(wrong.run)
            await tg.start(right.run)
            with anyio.fail_after(10):
                await right.wait_connected()
            await until(lambda: wrong.stats.connect_failures >= 2)
            assert not wrong.connected
            await FabricSide(fabric).publish(5)
            with anyio.fail_after(10):
                await arrived.wait()
            tg.cancel_scope.cancel()
    assert [json.loads(p)["n"] for p in got] == [5]


async def test_websocket_bridges_make_no_blocking_call(tmp_path: Path) -> None:
    """blockbuster turns a blocking call on the event loop into an error: a wss:// out
    bridge feeding a serving wss:// in bridge, at QoS 1, makes none."""
    certs = make_certs(
        tmp_path / "certs", {"bridge": "", "robot": ""}, hosts={"bridge": ["127.0.0.1"]}
    )
    tls = {"ca": str(certs / "ca.pem")}
    policy = InboxPolicy(capacity=1000, overflow=Overflow.FIFO, block=False)
    with blockbuster_ctx():
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            back = fabric.subscribe(BACK, policy)
            server = serving(
                tls=True, cert=str(certs / "bridge.pem"), key=str(certs / "bridge.key"), **tls
            )
            into = Bridge("nb-in", server, fabric, BACK, direction="in", message=Reading)
            await tg.start(into.run)
            with anyio.fail_after(10):
                await into.wait_connected()
            client = BridgeSpec(
                protocol="websocket",
                url=f"wss://127.0.0.1:{cast(WebSocketLink, into.link).port}",
                address="/robot",
                format="json",
                cert=str(certs / "robot.pem"),
                key=str(certs / "robot.key"),
                **tls,  # type: ignore[arg-type]
            )
            out = Bridge("nb-out", client, fabric, KEY, direction="out", message=Reading)
            await tg.start(out.run)
            side = FabricSide(fabric)
            for n in range(50):
                await side.publish(n)
            with anyio.fail_after(20):
                got = [decode((await back.get()).payload, type=Envelope) for _ in range(50)]
            await until(lambda: out.stats.sent == 50)
            tg.cancel_scope.cancel()
    assert [decode(e.body, type=Reading).n for e in got] == list(range(50))
    assert {e.source for e in got} == {"nb-in"}

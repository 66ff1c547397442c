"""Bridges over a real Zenoh fabric on loopback: TCP frames come in through a bridge on
one session and leave through a bridge on another, as TCP frames again."""

from __future__ import annotations

import anyio
import pytest
from anyio.abc import SocketStream
from anyio.streams.buffered import BufferedByteReceiveStream
from rap_bridges import Bridge, BridgeSpec
from rap_bridges.tcp import TcpLink, encode_frame, read_frame
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.fabric import free_port

from libs.rap_bridges.tests.contract import (
    KEY,
    FabricSide,
    Reading,
    fast_backoff,
    json_frame,
    until,
)

pytestmark = [pytest.mark.anyio, pytest.mark.zenoh]

CYCLE = bytes(range(16))


async def test_frames_cross_two_zenoh_sessions_between_two_bridges() -> None:
    """A peer sends TCP frames to bridge A (in, serving) on session 1; bridge B (out,
    client) on session 2 sends them on to a second TCP peer; cycle rides along."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    out_port = free_port()
    got: list[tuple[dict[str, str], bytes]] = []
    async with (
        ZenohFabric(ZenohConfig(listen=[ep])) as one,
        ZenohFabric(ZenohConfig(connect=[ep])) as two,
        anyio.create_task_group() as tg,
    ):
        listener = await anyio.create_tcp_listener(local_host="127.0.0.1", local_port=out_port)

        async def handle(stream: SocketStream) -> None:
            reader = BufferedByteReceiveStream(stream)
            async with stream:
                while len(got) < 3:
                    headers, payload = await read_frame(reader, 1 << 20)
                    got.append((headers, payload))
                    await stream.send(encode_frame(b"", {"rap-ack": headers["rap-seq"]}))

        async def receive_side() -> None:
            async with listener:
                await listener.serve(handle)

        tg.start_soon(receive_side)
        b_out = Bridge(
            "to-peer",
            BridgeSpec(protocol="tcp", url=f"tcp://127.0.0.1:{out_port}", format="json"),
            two,
            KEY,
            direction="out",
            message=Reading,
            backoff=fast_backoff(),
        )
        await tg.start(b_out.run)
        b_in = Bridge(
            "from-peer",
            BridgeSpec(protocol="tcp", url="tcp://127.0.0.1:0", serve=True, format="json"),
            one,
            KEY,
            direction="in",
            message=Reading,
        )
        await tg.start(b_in.run)
        side = FabricSide(two)
        await tg.start(side.record)
        with anyio.fail_after(10):
            await b_in.wait_connected()
            await b_out.wait_connected()
            await one.wait_matched(KEY)
        port = b_in.link.port if isinstance(b_in.link, TcpLink) else 0
        async with await anyio.connect_tcp("127.0.0.1", port) as peer:
            frames = [json_frame(0, **{"rap-cycle": CYCLE.hex()}), json_frame(1), json_frame(2)]
            await peer.send(b"".join(encode_frame(f.payload, dict(f.headers)) for f in frames))
            await side.wait_for(3)
            await until(lambda: len(got) >= 3)
        tg.cancel_scope.cancel()
    assert side.readings() == [0, 1, 2]
    assert side.got[0].source == "from-peer"
    assert [p for _, p in got] == [f.payload for f in frames]
    assert got[0][0]["rap-cycle"] == CYCLE.hex()
    assert got[0][0]["rap-source"] == "from-peer"
    assert (b_in.stats.published, b_out.stats.sent) == (3, 3)

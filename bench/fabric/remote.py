"""Client side of the two-process measurements (the peer runs bench.fabric.peer)."""

from __future__ import annotations

import asyncio
import os
import struct
import sys
import time
from typing import Any

import anyio
import zenoh
from rap_schemas import keys
from rap_sdk import Context, InboxPolicy, Node, Overflow, ZenohConfig, ZenohFabric, run_nodes
from rap_sdk.testing import free_port

from ..procs import spawn
from .common import RAW_BLAST, RAW_PING, RAW_PONG, SYSTEM, Blob, raw_session

PEER_TIMEOUT = 60.0


def peer(transport: str, role: str, addr: str, n: int = 0) -> Any:
    """bench.fabric.peer in its own process, on the same kind of event loop as this one."""
    uv = type(asyncio.get_running_loop()).__module__.startswith("uvloop")
    return spawn(
        [sys.executable, "-m", "bench.fabric.peer", transport, role, addr, str(n)],
        env={**os.environ, "BENCH_UVLOOP": "1" if uv else "0"},
    )


# -- rap_sdk -----------------------------------------------------------------------------


async def sdk_latency(size: int, iters: int, warm: int, *, direct: bool = True) -> list[int]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    client = Node("client")
    waiter: dict[str, asyncio.Future[int]] = {}

    @client.on_data("pong", policy=InboxPolicy(capacity=16, overflow=Overflow.FIFO))
    async def pong(ctx: Context, blob: Blob) -> None:
        waiter["f"].set_result(time.perf_counter_ns())

    samples: list[int] = []
    loop = asyncio.get_running_loop()
    async with ZenohFabric(ZenohConfig(listen=[ep], direct_callbacks=direct)) as fabric:
        async with run_nodes([client], fabric=fabric, system=SYSTEM) as group:
            transport = "sdk" if direct else "sdk-indirect"
            async with peer(transport, "echo", ep):
                await fabric.wait_matched(keys.data(SYSTEM, "ping"), timeout=PEER_TIMEOUT)
                rt, key, blob = group["client"], keys.data(SYSTEM, "ping"), Blob(data=b"x" * size)
                for i in range(warm + iters):
                    waiter["f"] = fut = loop.create_future()
                    t0 = time.perf_counter_ns()
                    await rt.send(key, blob)
                    t1 = await fut
                    if i >= warm:
                        samples.append(t1 - t0)
    return samples


async def fabric_latency(size: int, iters: int, warm: int) -> list[int]:
    """The fabric alone on both sides (no envelope, no node runtime): splits the SDK's
    cost between transport plumbing and the node layer."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    samples: list[int] = []
    async with ZenohFabric(ZenohConfig(listen=[ep])) as fabric:
        sub = fabric.subscribe(keys.data(SYSTEM, "pong"), InboxPolicy(capacity=16))
        ping = keys.data(SYSTEM, "ping")
        async with peer("fabric", "echo", ep):
            await fabric.wait_matched(ping, timeout=PEER_TIMEOUT)
            payload = b"x" * size
            for i in range(warm + iters):
                t0 = time.perf_counter_ns()
                await fabric.publish(ping, payload)
                await sub.get()
                t1 = time.perf_counter_ns()
                if i >= warm:
                    samples.append(t1 - t0)
    return samples


async def sdk_throughput(size: int, n: int) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    async with ZenohFabric(ZenohConfig(listen=[ep])) as fabric:
        async with run_nodes([Node("blaster")], fabric=fabric, system=SYSTEM) as group:
            async with peer("sdk", "sink", ep, n) as p:
                key = keys.data(SYSTEM, "blast")
                await fabric.wait_matched(key, timeout=PEER_TIMEOUT)
                rt, blob = group["blaster"], Blob(data=b"x" * size)
                for _ in range(n):
                    await rt.send(key, blob)
                return await p.result()


# -- raw zenoh-python into asyncio ---------------------------------------------------------


async def _matched(pub: zenoh.Publisher) -> None:
    loop = asyncio.get_running_loop()
    ready = asyncio.Event()

    def on_status(status: zenoh.MatchingStatus) -> None:
        if status.matching:
            loop.call_soon_threadsafe(ready.set)

    listener = pub.declare_matching_listener(zenoh.handlers.Callback(on_status, indirect=False))
    try:
        if not pub.matching_status.matching:
            with anyio.fail_after(PEER_TIMEOUT):
                await ready.wait()
    finally:
        listener.undeclare()


async def zenoh_latency(
    size: int,
    iters: int,
    warm: int,
    *,
    via_queue: bool = True,
) -> list[int]:
    """Raw zenoh-python ping-pong; ``via_queue``: samples reach coroutine code through an
    asyncio.Queue on both sides, else they are handled in the loop callback (the floor)."""
    ep = f"tcp/127.0.0.1:{free_port()}"
    loop = asyncio.get_running_loop()
    session = await anyio.to_thread.run_sync(raw_session, [ep], [])
    waiter: dict[str, asyncio.Future[int]] = {}
    queue: asyncio.Queue[bytes] = asyncio.Queue()

    def arrived(_: bytes) -> None:
        waiter["f"].set_result(time.perf_counter_ns())

    deliver = queue.put_nowait if via_queue else arrived
    session.declare_subscriber(
        RAW_PONG,
        zenoh.handlers.Callback(
            lambda s: loop.call_soon_threadsafe(deliver, s.payload.to_bytes()), indirect=False
        ),
    )
    pub = session.declare_publisher(RAW_PING, congestion_control=zenoh.CongestionControl.BLOCK)
    samples: list[int] = []
    try:
        async with peer("zenoh" if via_queue else "zenoh-callback", "echo", ep):
            await _matched(pub)
            payload = b"x" * size
            for i in range(warm + iters):
                t0 = time.perf_counter_ns()
                pub.put(payload)
                if via_queue:
                    await queue.get()
                    t1 = time.perf_counter_ns()
                else:
                    waiter["f"] = fut = loop.create_future()
                    t1 = await fut
                if i >= warm:
                    samples.append(t1 - t0)
    finally:
        await anyio.to_thread.run_sync(session.close)
    return samples


async def zenoh_throughput(size: int, n: int) -> dict[str, Any]:
    ep = f"tcp/127.0.0.1:{free_port()}"
    session = await anyio.to_thread.run_sync(raw_session, [ep], [])
    pub = session.declare_publisher(RAW_BLAST, congestion_control=zenoh.CongestionControl.BLOCK)
    try:
        async with peer("zenoh", "sink", ep, n) as p:
            await _matched(pub)
            payload = b"x" * size
            for _ in range(n):
                pub.put(payload)
            return await p.result()
    finally:
        await anyio.to_thread.run_sync(session.close)


# -- asyncio TCP ---------------------------------------------------------------------------

_HDR = struct.Struct("!I")


async def _tcp_server() -> tuple[asyncio.Server, asyncio.Future[Any]]:
    conn: asyncio.Future[Any] = asyncio.get_running_loop().create_future()

    async def on_conn(r: asyncio.StreamReader, w: asyncio.StreamWriter) -> None:
        conn.set_result((r, w))

    server = await asyncio.start_server(on_conn, "127.0.0.1", 0)
    return server, conn


async def tcp_latency(size: int, iters: int, warm: int) -> list[int]:
    server, conn = await _tcp_server()
    port = server.sockets[0].getsockname()[1]
    samples: list[int] = []
    async with server, peer("tcp", "echo", f"127.0.0.1:{port}"):
        reader, writer = await conn
        frame = _HDR.pack(size) + b"x" * size
        for i in range(warm + iters):
            t0 = time.perf_counter_ns()
            writer.write(frame)
            await reader.readexactly(4 + size)
            t1 = time.perf_counter_ns()
            if i >= warm:
                samples.append(t1 - t0)
        writer.close()
    return samples


async def tcp_throughput(size: int, n: int) -> dict[str, Any]:
    server, conn = await _tcp_server()
    port = server.sockets[0].getsockname()[1]
    async with server, peer("tcp", "sink", f"127.0.0.1:{port}", n) as p:
        _, writer = await conn
        frame = _HDR.pack(size) + b"x" * size
        for _ in range(n):
            writer.write(frame)
            await writer.drain()
        result = await p.result()
        writer.close()
        return result

"""The remote side of bench/fabric: ``python -m bench.fabric.peer TRANSPORT ROLE ADDR N``.

TRANSPORT: sdk | sdk-indirect | zenoh | zenoh-callback | tcp; ROLE: echo (send back what arrives) or
sink (count N arrivals, print the receive time of the first and last as JSON).
Prints READY when it can receive.
"""

from __future__ import annotations

import asyncio
import json
import os
import struct
import sys
import time

import anyio
import zenoh
from rap_schemas import keys
from rap_sdk import Context, InboxPolicy, Node, Overflow, ZenohFabric, run_nodes

from .common import RAW_BLAST, RAW_PING, RAW_PONG, SYSTEM, Blob, raw_session, sdk_config


def ready() -> None:
    print("READY", flush=True)


def done(first: int, last: int, n: int) -> None:
    print(json.dumps({"first_ns": first, "last_ns": last, "n": n}), flush=True)


async def sdk(role: str, addr: str, n: int, direct: bool) -> None:
    node = Node("peer")
    finished = anyio.Event()
    seen = {"n": 0, "first": 0}
    if role == "echo":

        @node.on_data("ping", policy=InboxPolicy(capacity=16, overflow=Overflow.FIFO))
        async def echo(ctx: Context, blob: Blob) -> None:
            await ctx.publish("pong", blob)
    else:

        @node.on_data("blast", policy=InboxPolicy(capacity=n + 16, block=False))
        async def sink(ctx: Context, blob: Blob) -> None:
            seen["n"] += 1
            if seen["n"] == 1:
                seen["first"] = time.perf_counter_ns()
            if seen["n"] == n:
                done(seen["first"], time.perf_counter_ns(), n)
                finished.set()

    async with ZenohFabric(sdk_config(addr, direct=direct)) as fabric:
        async with run_nodes([node], fabric=fabric, system=SYSTEM):
            if role == "echo":  # the client listens for pongs before we say READY
                await fabric.wait_matched(keys.data(SYSTEM, "pong"), timeout=30)
            ready()
            await finished.wait()


async def raw(role: str, addr: str, n: int, via_queue: bool) -> None:
    """Raw zenoh-python. ``via_queue``: each sample goes through an asyncio.Queue to a
    consumer coroutine (data landing in coroutine code, as in the SDK); otherwise it is
    handled in the loop callback itself, never entering a coroutine (the floor)."""
    loop = asyncio.get_running_loop()
    finished = asyncio.Event()
    session = raw_session([], [addr])
    pub = session.declare_publisher(RAW_PONG, congestion_control=zenoh.CongestionControl.BLOCK)
    count = {"n": 0, "first": 0}

    def echo(payload: bytes) -> None:
        pub.put(payload)

    def sink(payload: bytes) -> None:
        count["n"] += 1
        if count["n"] == 1:
            count["first"] = time.perf_counter_ns()
        if count["n"] == n:
            done(count["first"], time.perf_counter_ns(), n)
            finished.set()

    handler = echo if role == "echo" else sink
    key = RAW_PING if role == "echo" else RAW_BLAST
    queue: asyncio.Queue[bytes] = asyncio.Queue()

    async def consume() -> None:
        while True:
            handler(await queue.get())

    deliver = queue.put_nowait if via_queue else handler
    session.declare_subscriber(
        key,
        zenoh.handlers.Callback(
            lambda s: loop.call_soon_threadsafe(deliver, s.payload.to_bytes()), indirect=False
        ),
    )
    consumer = asyncio.ensure_future(consume()) if via_queue else None
    ready()
    await finished.wait()
    if consumer is not None:
        consumer.cancel()
    session.close()


async def fabric_only(addr: str) -> None:
    """The fabric alone: subscription inbox in, publish out; no envelope, no node."""
    async with ZenohFabric(sdk_config(addr)) as fabric:
        sub = fabric.subscribe(keys.data(SYSTEM, "ping"), InboxPolicy(capacity=16))
        pong = keys.data(SYSTEM, "pong")
        await fabric.wait_matched(pong, timeout=30)
        ready()
        while True:
            sample = await sub.get()
            await fabric.publish(pong, sample.payload)


async def tcp(role: str, addr: str, n: int) -> None:
    host, port = addr.rsplit(":", 1)
    reader, writer = await asyncio.open_connection(host, int(port))
    ready()
    hdr = struct.Struct("!I")
    count, first = 0, 0
    while True:
        try:
            (size,) = hdr.unpack(await reader.readexactly(4))
            data = await reader.readexactly(size)
        except asyncio.IncompleteReadError:
            break
        if role == "echo":
            writer.write(hdr.pack(size) + data)
        else:
            count += 1
            if count == 1:
                first = time.perf_counter_ns()
            if count == n:
                done(first, time.perf_counter_ns(), n)
                break
    writer.close()


def main() -> None:
    transport, role, addr, n = sys.argv[1], sys.argv[2], sys.argv[3], int(sys.argv[4])
    if transport in ("sdk", "sdk-indirect"):
        coro = sdk(role, addr, n, direct=transport == "sdk")
    elif transport == "fabric":
        coro = fabric_only(addr)
    elif transport in ("zenoh", "zenoh-callback"):
        coro = raw(role, addr, n, via_queue=transport == "zenoh")
    else:
        coro = tcp(role, addr, n)
    if os.environ.get("BENCH_UVLOOP") == "1":
        import uvloop

        uvloop.run(coro)
    else:
        asyncio.run(coro)


if __name__ == "__main__":
    main()

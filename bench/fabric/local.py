"""In-process measurements: stage-to-stage delivery and the thread-to-loop hand-off."""

from __future__ import annotations

import asyncio
import threading
import time
from typing import Any

import anyio
import zenoh
from rap_schemas import keys
from rap_sdk import Context, MemoryFabric, Node, ZenohConfig, ZenohFabric, run_nodes
from rap_sdk.fabric import Fabric
from rap_sdk.fabric.handoff import LoopHandoff
from rap_sdk.testing import free_port

from .common import SYSTEM, raw_session


async def stage_hop(
    kind: str, iters: int, warm: int, *, trace: bool = True, trace_listener: bool = False
) -> list[int]:
    """Latency from a node's emit to the next stage's handler start, one at a time.
    ``trace_listener``: another Zenoh session subscribes to the trace records (as a
    trust checker would), so they are really built and sent."""
    waiter: dict[str, asyncio.Future[int]] = {}
    b = Node("b", stage="analyse")

    @b.on_event("hop")
    async def hop(ctx: Context) -> None:
        waiter["f"].set_result(time.perf_counter_ns())

    loop = asyncio.get_running_loop()
    port = free_port()
    fabric: Fabric = (
        MemoryFabric()
        if kind == "memory"
        else ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{port}"]))
    )
    samples: list[int] = []
    async with (
        fabric,
        run_nodes(
            [Node("a", stage="monitor"), b], fabric=fabric, system=SYSTEM, trace=trace
        ) as group,
    ):
        listener = None
        if trace_listener:
            listener = await anyio.to_thread.run_sync(raw_session, [], [f"tcp/127.0.0.1:{port}"])
            listener.declare_subscriber(
                keys.pattern(SYSTEM, keys.Kind.TRACE),
                zenoh.handlers.Callback(lambda s: None, indirect=False),
            )
            await fabric.wait_matched(keys.trace(SYSTEM, "b"), timeout=10)
        rt, key = group["a"], keys.event(SYSTEM, "hop")
        for i in range(warm + iters):
            waiter["f"] = fut = loop.create_future()
            t0 = time.perf_counter_ns()
            await rt.send(key, None)
            t1 = await fut
            if i >= warm:
                samples.append(t1 - t0)
        if listener is not None:
            await anyio.to_thread.run_sync(listener.close)
    return samples


async def queue_hop(iters: int, warm: int) -> list[int]:
    """The floor: a bare asyncio.Queue between two tasks."""
    q: asyncio.Queue[int] = asyncio.Queue(maxsize=256)
    loop = asyncio.get_running_loop()
    waiter: dict[str, asyncio.Future[int]] = {}

    async def consumer() -> None:
        while True:
            await q.get()
            waiter["f"].set_result(time.perf_counter_ns())

    task = asyncio.ensure_future(consumer())
    samples: list[int] = []
    try:
        for i in range(warm + iters):
            waiter["f"] = fut = loop.create_future()
            t0 = time.perf_counter_ns()
            await q.put(t0)
            t1 = await fut
            if i >= warm:
                samples.append(t1 - t0)
    finally:
        task.cancel()
    return samples


async def handoff(scheme: str, iters: int, burst: int) -> dict[str, Any]:
    """Transport-thread -> loop: latency of single items, and burst throughput."""
    loop = asyncio.get_running_loop()
    lat: list[int] = []
    got = threading.Event()
    bulk_done = asyncio.Event()
    count = {"n": 0}
    ho = LoopHandoff(loop)

    def deliver_one(ts: int) -> None:
        lat.append(time.perf_counter_ns() - ts)
        got.set()

    def deliver_bulk(_: int) -> None:
        count["n"] += 1
        if count["n"] == burst:
            bulk_done.set()

    def push(fn: Any, item: int) -> None:
        if scheme == "batched":
            ho.push(fn, item)
        else:
            loop.call_soon_threadsafe(fn, item)

    def producer_latency() -> None:
        for _ in range(iters):
            got.clear()
            push(deliver_one, time.perf_counter_ns())
            got.wait(5)

    def producer_burst() -> None:
        for i in range(burst):
            push(deliver_bulk, i)

    await asyncio.to_thread(producer_latency)
    t0 = time.perf_counter_ns()
    th = threading.Thread(target=producer_burst)
    th.start()
    await bulk_done.wait()
    elapsed = time.perf_counter_ns() - t0
    th.join()
    return {"latency_ns": lat, "burst_items_per_s": round(burst / elapsed * 1e9)}

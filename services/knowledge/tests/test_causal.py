"""Causal reads: a handler reading a key named in its trigger's ctx never sees an older
version than the event promised, even when the write reaches it after the event."""

from __future__ import annotations

import math
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from typing import Any

import anyio
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_schemas import LaserScan, StageTrace, keys
from rap_sdk import Context, KnowledgeError, MemoryBus, MemoryFabric, Node, run_nodes
from rap_sdk.envelope import Sealer
from rap_sdk.testing import DelayedKnowledgeWrites

pytestmark = pytest.mark.anyio


def scan(stamp: int) -> LaserScan:
    return LaserScan(
        stamp=stamp,
        frame_id="base_link",
        angle_min=-math.pi,
        angle_increment=0.1,
        range_min=0.1,
        range_max=12.0,
        ranges=[1.0],
    )


def loop_nodes(seen: list[Any]) -> tuple[Node, Node]:
    monitor, analyse = Node("monitor", stage="monitor"), Node("analyse", stage="analyse")

    @monitor.on_data("scan")
    async def on_scan(ctx: Context, s: LaserScan) -> None:
        await ctx.kb.write("laser_scan", s.stamp)  # no round trip
        await ctx.emit("new-data")  # carries {"laser_scan": version} in ctx

    @analyse.on_event("new-data")
    async def detect(ctx: Context) -> None:
        try:
            seen.append(await ctx.kb.read("laser_scan", int))
        except KnowledgeError as exc:
            seen.append(exc)

    return monitor, analyse


@asynccontextmanager
async def two_nodes(
    delay: float,
    drop: bool = False,
    service: bool = True,
) -> AsyncIterator[tuple[list[Any], Any, Any]]:
    seen: list[Any] = []
    monitor, analyse = loop_nodes(seen)
    bus = MemoryBus()
    async with AsyncExitStack() as stack:
        tg = await stack.enter_async_context(anyio.create_task_group())
        if service:
            kf = await stack.enter_async_context(MemoryFabric(bus=bus))
            await stack.enter_async_context(open_service(KnowledgeConfig(system="t"), fabric=kf))
        wf = await stack.enter_async_context(MemoryFabric(bus=bus))
        rf = await stack.enter_async_context(MemoryFabric(bus=bus))
        slow = DelayedKnowledgeWrites(wf, tg, delay, drop)
        writer = await stack.enter_async_context(run_nodes(slow, [monitor], system="t"))
        reader = await stack.enter_async_context(run_nodes(rf, [analyse], system="t"))
        yield seen, writer["monitor"], reader["analyse"]
        tg.cancel_scope.cancel()


async def feed(rt: Any, stamps: range, seen: list[Any]) -> None:
    sealer = Sealer("robot")
    for i in stamps:
        payload, _ = sealer.seal_message(keys.data("t", "scan"), scan(i))
        await rt.fabric.publish(keys.data("t", "scan"), payload)
        with anyio.fail_after(5):
            while len(seen) < i:
                await anyio.wait_all_tasks_blocked()


@pytest.mark.parametrize("service", [True, False], ids=["with-service", "stream-only"])
async def test_a_read_never_sees_an_older_version_than_promised(service: bool) -> None:
    async with two_nodes(delay=0.02, service=service) as (seen, _, reader):
        await feed(reader, range(1, 11), seen)
        assert seen == list(range(1, 11))
        assert reader.knowledge.waits >= 5  # the writes really were late: reads waited


async def test_a_promised_version_that_never_comes_fails_clearly() -> None:
    async with two_nodes(delay=0.0, drop=True) as (seen, _, reader):
        reader.knowledge.timeout = 0.2
        await feed(reader, range(1, 2), seen)
        (err,) = seen
        assert isinstance(err, KnowledgeError)
        assert "read of 'laser_scan' needs version >=" in str(err)
        assert "the newest known is 0" in str(err)


async def test_ctx_carries_writes_and_reads_are_traced() -> None:
    async with two_nodes(delay=0.0) as (seen, _, reader):
        traces = reader.fabric.subscribe(keys.pattern("t", keys.Kind.TRACE))
        events = reader.fabric.subscribe(keys.event("t", "new-data"))
        await feed(reader, range(1, 2), seen)
        import msgspec
        from rap_schemas import Envelope, KnowledgeAccess

        env = msgspec.msgpack.decode((await events.get()).payload, type=Envelope)
        assert list(env.ctx) == ["laser_scan"]
        access = []
        with anyio.fail_after(5):
            while len(access) < 2:
                e = msgspec.msgpack.decode((await traces.get()).payload, type=Envelope)
                if e.type == KnowledgeAccess.TYPE:
                    access.append(msgspec.msgpack.decode(e.body, type=KnowledgeAccess))
                else:
                    assert e.type == StageTrace.TYPE
        assert {(a.node, a.op) for a in access} == {("monitor", "write"), ("analyse", "read")}
        assert {a.version for a in access} == {env.ctx["laser_scan"]}

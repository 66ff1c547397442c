"""Causal reads: a handler reading a key named in its trigger's ctx never sees an older
version than the event promised, even when the write reaches it after the event."""

from __future__ import annotations

import math
import time
from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from typing import Any

import anyio
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_schemas import LaserScan, StageTrace, keys, pack_ranges
from rap_schemas.knowledge import EPOCH_MS
from rap_sdk import (
    Context,
    KnowledgeClient,
    KnowledgeError,
    MemoryBus,
    MemoryFabric,
    Node,
    run_nodes,
)
from rap_sdk.envelope import Sealer
from rap_sdk.knowledge import writer_tag
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
        ranges=pack_ranges([1.0]),
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
        slow = DelayedKnowledgeWrites(fabric=wf, tg=tg, delay=delay, drop=drop)
        writer = await stack.enter_async_context(run_nodes([monitor], fabric=slow, system="t"))
        reader = await stack.enter_async_context(run_nodes([analyse], fabric=rf, system="t"))
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
        from rap_schemas import Envelope

        env = msgspec.msgpack.decode((await events.get()).payload, type=Envelope)
        assert list(env.ctx) == ["laser_scan"]
        access = []
        with anyio.fail_after(5):
            while len(access) < 2:
                e = msgspec.msgpack.decode((await traces.get()).payload, type=Envelope)
                assert e.type == StageTrace.TYPE
                rec = msgspec.msgpack.decode(e.body, type=StageTrace)
                access += [(rec.node, a) for a in rec.access]
        assert {(node, a.op) for node, a in access} == {("monitor", "write"), ("analyse", "read")}
        assert {a.version for _, a in access} == {env.ctx["laser_scan"]}


# -- promises that never come: the damage is bounded -------------------------------------


def forged_version(tag_of: str, ahead_ms: int = 10_000) -> int:
    """A plausible version of writer ``tag_of``, a little ahead of now (within the drift
    the service and replicas accept), that nobody ever writes."""
    return ((time.time_ns() // 1_000_000 - EPOCH_MS + ahead_ms) << 20) | writer_tag(tag_of)


@asynccontextmanager
async def promised(timeout: float) -> AsyncIterator[tuple[list[Any], list[str], Any, Any]]:
    """monitor -> analyse (with a second, unrelated route), the service, on one bus."""
    seen: list[Any] = []
    other: list[str] = []
    monitor, analyse = loop_nodes(seen)

    @analyse.on_event("other")
    async def unrelated(ctx: Context) -> None:
        other.append("handled")

    bus = MemoryBus()
    async with AsyncExitStack() as stack:
        kf = await stack.enter_async_context(MemoryFabric(bus=bus))
        await stack.enter_async_context(open_service(KnowledgeConfig(system="t"), fabric=kf))
        fabric = await stack.enter_async_context(MemoryFabric(bus=bus))
        group = await stack.enter_async_context(
            run_nodes([monitor, analyse], fabric=fabric, system="t")
        )
        group["analyse"].knowledge.timeout = timeout
        await feed(group["analyse"], range(1, 2), seen)  # analyse replicates laser_scan now
        yield seen, other, group["analyse"], Sealer("forger")


async def test_a_promise_from_a_writer_that_is_not_alive_is_not_waited_for() -> None:
    async with promised(timeout=30.0) as (seen, _, rt, forger):
        payload, _ = forger.seal_message(
            keys.event("t", "new-data"), None, ctx={"laser_scan": forged_version("nobody")}
        )
        with anyio.fail_after(5):  # far below the 30 s read timeout
            await rt.fabric.publish(keys.event("t", "new-data"), payload)
            while len(seen) < 2:
                await anyio.wait_all_tasks_blocked()
        assert isinstance(seen[1], KnowledgeError)
        assert "its writer is not alive" in str(seen[1])


async def test_forged_promises_cost_one_deadline_and_hold_no_other_route() -> None:
    """Ten events promising a version of an alive writer that never comes delayed a real
    event by ten read deadlines (20 s); now the deadline counts from arrival, so the
    ten queued behind each other cost one, and the node's other routes run meanwhile."""
    timeout = 1.0
    async with promised(timeout=timeout) as (seen, other, rt, forger):
        key = keys.event("t", "new-data")
        for _ in range(10):
            payload, _ = forger.seal_message(
                key, None, ctx={"laser_scan": forged_version("monitor")}
            )
            await rt.fabric.publish(key, payload)
        payload, _ = forger.seal_message(keys.event("t", "other"), None)
        await rt.fabric.publish(keys.event("t", "other"), payload)
        with anyio.fail_after(timeout / 2):  # while the first forged event still waits
            while not other:
                await anyio.wait_all_tasks_blocked()
        assert len(seen) == 1  # the forged events are still waiting
        sealer = Sealer("robot")
        scan_key = keys.data("t", "scan")
        payload, _ = sealer.seal_message(scan_key, scan(2))
        with anyio.fail_after(3 * timeout):
            await rt.fabric.publish(scan_key, payload)
            while 2 not in seen:
                await anyio.wait_all_tasks_blocked()
        errors = [s for s in seen if isinstance(s, KnowledgeError)]
        assert len(errors) == 10
        assert seen[-1] == 2


async def test_a_new_replica_gets_a_version_written_before_it_subscribed_at_once() -> None:
    """The first read of a key waits for a version written before its replica
    subscribed (the stream will not bring it again) while the service has not stored
    it yet: the client asks the service again until it has, instead of waiting out
    its whole timeout."""
    bus = MemoryBus()
    async with (
        MemoryFabric(bus=bus) as kf,
        open_service(KnowledgeConfig(system="t"), fabric=kf) as svc,
        MemoryFabric(bus=bus) as wf,
        MemoryFabric(bus=bus) as rf,
        KnowledgeClient(fabric=wf, system="t", writer="w") as writer,
        KnowledgeClient(fabric=rf, system="t", writer="r", timeout=5.0) as reader,
    ):
        stored = anyio.Event()
        release = anyio.Event()
        apply = svc.store.apply

        async def late_apply(rec, **kw):  # type: ignore[no-untyped-def]
            await release.wait()  # the service is slow to store the record
            out = await apply(rec, **kw)
            stored.set()
            return out

        svc.store.apply = late_apply  # type: ignore[method-assign]
        wf.declare_token(keys.alive("t", "w"))  # a node alive: its versions are waited for
        version = await writer.write("laser_scan", 7)
        with anyio.fail_after(5):
            while not reader.writer_alive(version):  # noqa: ASYNC110
                await anyio.sleep(0.01)

        async def store_later() -> None:
            await anyio.sleep(0.1)
            release.set()

        async with anyio.create_task_group() as tg:
            tg.start_soon(store_later)
            t0 = anyio.current_time()
            value = await reader.read("laser_scan", min_version=version)
            waited = anyio.current_time() - t0
        assert stored.is_set()
        assert value == 7
        assert waited < 1.0  # not the client's 5 s timeout

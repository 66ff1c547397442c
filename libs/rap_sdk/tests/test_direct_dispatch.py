"""Direct dispatch: a local sample for an idle node is handled in the publisher's task,
keeping what the inbox guarantees: one handler at a time per node, order per route,
bounded depth and inboxes, and the route's overflow policy when the node is busy.
Runs on both fabrics (the path is the fabric's local delivery)."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

import anyio
import pytest
from rap_schemas import Empty, SimTime, keys
from rap_sdk import (
    Context,
    InboxPolicy,
    MemoryFabric,
    Node,
    Overflow,
    ZenohConfig,
    ZenohFabric,
    run_nodes,
)
from rap_sdk import runtime as rt_mod

pytestmark = pytest.mark.anyio
SYSTEM = "d"
KINDS = ["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)]


@asynccontextmanager
async def fabric_of(kind: str) -> AsyncIterator[Any]:
    if kind == "memory":
        async with MemoryFabric() as f:
            yield f
    else:
        async with ZenohFabric(ZenohConfig(listen=[])) as f:
            yield f


def tick(t: int) -> SimTime:
    return SimTime(t=t)


@pytest.mark.parametrize("kind", KINDS)
async def test_an_idle_node_handles_a_local_sample_in_the_senders_task(kind: str) -> None:
    node = Node("n")
    tasks: list[object] = []

    @node.on_data("t")
    async def on_t(ctx: Context, m: SimTime) -> None:
        tasks.append(anyio.get_current_task().id)

    async with fabric_of(kind) as fabric, run_nodes([node], fabric=fabric, system=SYSTEM) as g:
        await g["n"].send(keys.data(SYSTEM, "t"), tick(1))
        assert tasks == [anyio.get_current_task().id]  # done before send returned
        assert g["n"].stats.handled == 1


@pytest.mark.parametrize("kind", KINDS)
async def test_a_busy_node_gets_samples_through_its_inbox_in_order(kind: str) -> None:
    node = Node("n")
    seen: list[int] = []
    running = 0
    most = 0
    release = anyio.Event()

    @node.on_data("t", policy=InboxPolicy(capacity=16, overflow=Overflow.FIFO))
    async def on_t(ctx: Context, m: SimTime) -> None:
        nonlocal running, most
        running += 1
        most = max(most, running)
        if m.t == 0:
            await release.wait()  # busy: what comes now must queue
        seen.append(m.t)
        running -= 1

    async with fabric_of(kind) as fabric, run_nodes([node], fabric=fabric, system=SYSTEM) as g:
        sender = g["n"]
        async with anyio.create_task_group() as tg:
            tg.start_soon(sender.send, keys.data(SYSTEM, "t"), tick(0))
            await anyio.wait_all_tasks_blocked()
            for i in range(1, 6):
                await sender.send(keys.data(SYSTEM, "t"), tick(i))
            assert seen == []  # all queued behind the busy handler
            release.set()
        with anyio.fail_after(5):
            while len(seen) < 6:  # noqa: ASYNC110 (the consumer's progress)
                await anyio.sleep(0.01)
    assert seen == [0, 1, 2, 3, 4, 5]
    assert most == 1  # one handler at a time


@pytest.mark.parametrize("kind", KINDS)
async def test_the_overflow_policy_holds_while_the_node_is_busy(kind: str) -> None:
    node = Node("n")
    seen: list[int] = []
    release = anyio.Event()

    @node.on_data("t", policy=InboxPolicy(capacity=2, overflow=Overflow.LATEST))
    async def on_t(ctx: Context, m: SimTime) -> None:
        if m.t == 0:
            await release.wait()
        seen.append(m.t)

    async with fabric_of(kind) as fabric, run_nodes([node], fabric=fabric, system=SYSTEM) as g:
        sender = g["n"]
        async with anyio.create_task_group() as tg:
            tg.start_soon(sender.send, keys.data(SYSTEM, "t"), tick(0))
            await anyio.wait_all_tasks_blocked()
            for i in range(1, 6):
                await sender.send(keys.data(SYSTEM, "t"), tick(i))
            release.set()
        with anyio.fail_after(5):
            while len(seen) < 3:  # noqa: ASYNC110
                await anyio.sleep(0.01)
        # 1..5 came while the handler was busy: the inbox (newest 2) dropped 1, 2 and 3
        assert [s.stats.dropped for s in g["n"]._subs] == [3]
    assert seen == [0, 4, 5]


async def test_nesting_is_bounded(monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.setattr(rt_mod, "MAX_DIRECT_DEPTH", 3)
    depths: list[int] = []

    def stage(i: int) -> Node:
        node = Node(f"s{i}")

        @node.on_event(f"e{i}")
        async def step(ctx: Context) -> None:
            depths.append(rt_mod._depth[0])
            if i < 5:
                await ctx.emit(f"e{i + 1}")

        return node

    nodes = [stage(i) for i in range(6)]
    async with MemoryFabric() as fabric, run_nodes(nodes, fabric=fabric, system=SYSTEM) as g:
        await g["s0"].send(keys.event(SYSTEM, "e0"), Empty())
        with anyio.fail_after(5):
            while len(depths) < 6:  # noqa: ASYNC110
                await anyio.sleep(0.01)
    assert max(depths) <= 3
    assert depths[:3] == [1, 2, 3]  # then the inbox takes over, nesting starts again


async def test_a_sample_promising_a_version_not_here_yet_goes_through_the_inbox() -> None:
    node = Node("n")
    handled_in: list[object] = []

    @node.on_event("go")
    async def go(ctx: Context) -> None:
        handled_in.append(anyio.get_current_task().id)

    async with MemoryFabric() as fabric, run_nodes([node], fabric=fabric, system=SYSTEM) as g:
        rt = g["n"]
        await rt.knowledge.read("k", default=None)  # replicated here, at version 0
        own = rt.knowledge.clock.next()  # a version of this node's own writer: awaited
        await rt.send(keys.event(SYSTEM, "go"), Empty(), ctx={"k": own})
        assert handled_in == []  # not handled in the sender's task: it would wait there


@pytest.mark.parametrize("kind", KINDS)
async def test_subscribers_of_one_sample_may_wait_for_each_other(kind: str) -> None:
    """At most one subscriber runs in the sender's task, after the others have the
    sample in their inboxes: one that waits for another does not hold it up."""
    started = {"a": anyio.Event(), "b": anyio.Event()}
    done: list[str] = []

    def waiter(me: str, other: str) -> Node:
        node = Node(me)

        @node.on_data("t")
        async def on_t(ctx: Context, m: SimTime) -> None:
            started[me].set()
            with anyio.fail_after(5):
                await started[other].wait()
            done.append(me)

        return node

    nodes = [waiter("a", "b"), waiter("b", "a"), Node("sender")]
    async with fabric_of(kind) as fabric, run_nodes(nodes, fabric=fabric, system=SYSTEM) as g:
        await g["sender"].send(keys.data(SYSTEM, "t"), tick(1))
        with anyio.fail_after(5):
            while len(done) < 2:  # noqa: ASYNC110
                await anyio.sleep(0.01)
    assert sorted(done) == ["a", "b"]


async def test_only_the_last_send_of_a_handler_is_handled_in_its_task() -> None:
    tasks: dict[str, object] = {}
    sender, first, last = Node("s"), Node("first"), Node("last")

    @sender.on_event("go")
    async def go(ctx: Context) -> None:
        await ctx.emit("one")
        await ctx.emit("two")

    @first.on_event("one")
    async def one(ctx: Context) -> None:
        tasks["one"] = anyio.get_current_task().id

    @last.on_event("two")
    async def two(ctx: Context) -> None:
        tasks["two"] = anyio.get_current_task().id

    async with (
        MemoryFabric() as fabric,
        run_nodes([sender, first, last], fabric=fabric, system=SYSTEM) as g,
    ):
        await g["s"].send(keys.event(SYSTEM, "go"), Empty())
        with anyio.fail_after(5):
            while len(tasks) < 2:  # noqa: ASYNC110
                await anyio.sleep(0.01)
    here = anyio.get_current_task().id
    assert tasks["two"] == here  # go, then two, ran in this task
    assert tasks["one"] != here  # one went through first's inbox

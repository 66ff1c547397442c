"""What an operator needs to hear about: inbox drops, a node name used twice, nodes that
go away and come back, a process alone on its system or without a knowledge service."""

from __future__ import annotations

import logging

import anyio
import anyio.lowlevel
import pytest
from rap_schemas import Message, keys
from rap_sdk import (
    Context,
    HandlerError,
    InboxPolicy,
    LifecycleError,
    MemoryBus,
    MemoryFabric,
    Node,
    Overflow,
    Sealer,
    ZenohConfig,
    ZenohFabric,
    run_nodes,
)
from rap_sdk.fabric import free_port
from rap_sdk.peers import PeerWatch
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio


class Battery(Message, frozen=True):
    TYPE = "app.Battery/1"

    level: float


async def test_inbox_drops_are_counted_and_logged(caplog: pytest.LogCaptureFixture) -> None:
    node = Node("slow")
    gate = anyio.Event()
    handled = 0

    @node.on_event("tick", policy=InboxPolicy(capacity=2, overflow=Overflow.LATEST))
    async def tick(ctx: Context) -> None:
        nonlocal handled
        await gate.wait()
        handled += 1

    async with Harness(system="t") as h:
        group = await h.start(node)
        for _ in range(20):
            await h.emit("tick")
        gate.set()
        await h.emit("tick")
        stats = group["slow"].stats
        with anyio.fail_after(5):
            while handled + stats.dropped < 21:
                await anyio.wait_all_tasks_blocked()
        assert stats.dropped >= 15  # a capacity of 2 kept the newest: every sample counted
    assert "dropped samples on rap/t/event/tick" in caplog.text
    assert "raise the capacity" in caplog.text


async def test_a_second_node_with_the_same_name_refuses_to_start() -> None:
    bus = MemoryBus()
    first, second = Node("monitor"), Node("monitor")
    async with MemoryFabric(bus=bus) as a, MemoryFabric(bus=bus) as b:
        async with run_nodes([first], fabric=a, system="t"):
            with pytest.raises(LifecycleError, match="'monitor' is already running"):
                async with run_nodes([second], fabric=b, system="t"):
                    pass
        async with run_nodes([second], fabric=b, system="t"):  # once the first is gone, it may
            pass


@pytest.mark.zenoh
async def test_a_second_node_with_the_same_name_refuses_to_start_over_zenoh() -> None:
    first, second = Node("monitor"), Node("monitor")
    endpoint = f"tcp/127.0.0.1:{free_port()}"
    async with (
        ZenohFabric(ZenohConfig(listen=[endpoint])) as a,
        run_nodes([first], fabric=a, system="t"),
        ZenohFabric(ZenohConfig(connect=[endpoint])) as b,  # another process, linked
    ):
        with pytest.raises(LifecycleError, match="already running"):
            async with run_nodes([second], fabric=b, system="t"):
                pass


async def test_nodes_that_go_and_come_back_are_logged(caplog: pytest.LogCaptureFixture) -> None:
    caplog.set_level(logging.WARNING)
    bus = MemoryBus()
    async with MemoryFabric(bus=bus) as mine, MemoryFabric(bus=bus) as other:
        watch = PeerWatch(fabric=mine, system="t", mine={"me"}, alone_after=60)
        async with anyio.create_task_group() as tg:
            await tg.start(watch.run)
            tok = other.declare_token(keys.alive("t", "analysis"))
            await anyio.wait_all_tasks_blocked()
            assert watch.stats.alive == {"analysis"}
            tok.undeclare()
            await anyio.wait_all_tasks_blocked()
            tok = other.declare_token(keys.alive("t", "analysis"))
            await anyio.wait_all_tasks_blocked()
            tg.cancel_scope.cancel()
    assert (watch.stats.lost, watch.stats.back) == (1, 1)
    assert "node analysis lost its liveliness" in caplog.text
    assert "node analysis is alive again" in caplog.text


@pytest.mark.parametrize(
    ("others", "expect_knowledge", "warning"),
    [
        ([], False, "no other node has been alive"),
        (["planner"], True, "no knowledge service has been alive"),
        (["planner", "knowledge"], True, None),
    ],
)
async def test_a_process_alone_or_without_knowledge_is_warned(
    others: list[str], expect_knowledge: bool, warning: str | None
) -> None:
    bus = MemoryBus()
    async with MemoryFabric(bus=bus) as mine, MemoryFabric(bus=bus) as other:
        for name in others:
            other.declare_token(keys.alive("lonely", name))
        watch = PeerWatch(
            fabric=mine, system="lonely", expect_knowledge=expect_knowledge, alone_after=0.05
        )
        async with anyio.create_task_group() as tg:
            await tg.start(watch.run)
            await anyio.sleep(0.2)  # past alone_after: the check has run
            tg.cancel_scope.cancel()
    if warning is None:
        assert watch.stats.warnings == []
    else:
        (said,) = watch.stats.warnings
        assert warning in said
        assert "'lonely'" in said


async def test_a_sample_over_the_routes_size_limit_is_rejected_before_decoding() -> None:
    node = Node("n")
    got: list[int] = []

    @node.on_event("e", type=Battery, max_bytes=1000)
    async def e(ctx: Context) -> None:
        got.append(1)

    async with Harness(system="t") as h:
        await h.start(node)
        payload, _ = h.sealer.seal(keys.event("t", "e"), Battery.TYPE, b"\xc4\xff" + b"x" * 255)
        await h.emit("e", Battery(level=0.5))
        await h.publish_raw(keys.event("t", "e"), payload + b"\x00" * 2000)
        await h.wait_for(lambda r: len(h.rejections("n")) == 1)
        assert "over the route's limit of 1000" in h.rejections("n")[0].reason
        assert got == [1]


def test_a_node_handles_a_key_once() -> None:
    node = Node("n")

    @node.on_event("e")
    async def first(ctx: Context) -> None: ...

    with pytest.raises(HandlerError, match="second handler of that key"):

        @node.on_event("e")
        async def second(ctx: Context) -> None: ...


async def test_local_nodes_sending_in_a_cycle_do_not_deadlock() -> None:
    """What make fuzz found in the one-process loop: the planner held its lock waiting for
    room in legitimate's full inbox, legitimate waited for room in the planner's full
    plan-rejected inbox, whose consumer waited for that lock. Local sends now give up on
    a full inbox after a deadline (counted), so the cycle breaks. The steps below build
    exactly that state."""
    tiny = InboxPolicy(capacity=1, overflow=Overflow.FIFO)
    planner, judge = Node("planner"), Node("judge")
    hold = anyio.Event()
    planned: list[int] = []
    replanned: list[int] = []

    @planner.on_event("anomaly", policy=tiny)
    async def plan(ctx: Context) -> None:
        await hold.wait()  # holds the planner's one-handler-at-a-time lock
        await ctx.emit("new-plan")
        planned.append(1)

    @planner.on_event("rejected", policy=tiny)
    async def replan(ctx: Context) -> None:
        replanned.append(1)

    @judge.on_event("new-plan", policy=tiny)
    async def decide(ctx: Context) -> None:
        await ctx.emit("rejected")

    bus = MemoryBus()
    sealer = Sealer("feeder")

    async def feed(fabric: MemoryFabric, event: str) -> None:
        key = keys.event("t", event)
        payload, _ = sealer.seal_message(key, None)
        await fabric.publish(key, payload)  # from another process: never waits
        await anyio.wait_all_tasks_blocked()

    async with MemoryFabric(bus=bus) as feeder, MemoryFabric(bus=bus) as nodes:
        async with run_nodes([planner, judge], fabric=nodes, system="t") as group:
            await feed(feeder, "anomaly")  # the planner takes it and holds its lock
            for _ in range(4):  # the judge answers until its emit waits on a full inbox,
                await feed(feeder, "new-plan")  # and one more new-plan fills its own
            hold.set()  # the planner now emits into the judge's full inbox
            with anyio.fail_after(10):  # before: never
                while not planned or len(replanned) < 2:
                    await anyio.wait_all_tasks_blocked()
            assert group["planner"].stats.send_timeouts + group["judge"].stats.send_timeouts

"""Periodic handlers (``@node.every``): they tick while the node runs, one call at a time
and never next to another handler of the node, overruns skip and count the missed
ticks, a failing call does not stop the timer, and the timer stops with the node."""

from __future__ import annotations

import itertools
import logging
import math
import time
from typing import Any

import anyio
import pytest
from prometheus_client.core import Metric
from rap_schemas import Empty, StageTrace, keys
from rap_sdk import (
    ConfigError,
    Context,
    HandlerError,
    MemoryFabric,
    Node,
    NodeRuntime,
    Sealer,
    run_nodes,
)
from rap_sdk.metrics import RuntimeCollector
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio

PERIOD = 0.01


class Calls:
    """Counts a handler's calls; ``await calls.reach(n)`` waits until there were ``n``."""

    def __init__(self) -> None:
        self.n = 0
        self.running = False
        self._changed = anyio.Event()

    def started(self) -> None:
        self.n += 1
        self.running = True
        self._wake()

    def ended(self) -> None:
        self.running = False
        self._wake()

    def hit(self) -> None:
        self.started()
        self.ended()

    def _wake(self) -> None:
        self._changed.set()
        self._changed = anyio.Event()

    async def until(self, pred: Any, timeout: float = 5.0) -> None:
        with anyio.fail_after(timeout):
            while not pred():
                await self._changed.wait()

    async def reach(self, n: int) -> None:
        await self.until(lambda: self.n >= n)


@pytest.mark.parametrize("isolate", [False, True], ids=["shared", "isolated"])
async def test_ticks_emit_as_roots_of_their_own_cycles(isolate: bool) -> None:
    node = Node("poller", stage="monitor")

    @node.every(PERIOD)
    async def poll(ctx: Context) -> None:
        await ctx.kb.write("polled", ctx.envelope.seq)
        await ctx.emit("polled")

    async with Harness(system="t", isolate=isolate) as h:
        group = await h.start(node)
        first = await h.expect_event("polled")
        second = await h.expect_event("polled", after=h.records.index(first) + 1)
        for rec in (first, second):
            env = rec.envelope
            assert env is not None
            assert env.cycle is not None
            assert env.cycle == env.cause  # the tick is the root of its cycle
        assert first.envelope is not None
        assert second.envelope is not None
        first_cycle = first.envelope.cycle
        assert first_cycle != second.envelope.cycle  # one cycle per tick
        # the call's record went out before what it emitted
        assert any(t.cycle == first_cycle for t in h.traces("poller"))
        calls = [t for t in h.traces("poller") if t.cycle == first_cycle]
        assert [(t.phase, t.ok, t.handler) for t in calls] == [("call", True, poll.__qualname__)]
        assert calls[0].trigger == first_cycle
        assert calls[0].trigger_key == "every:poller/poll"
        assert calls[0].sent == [keys.event("t", "polled")]
        assert [a.key for a in calls[0].access] == ["polled"]
        stats = group["poller"].stats
        assert stats.ticks >= 2
        assert stats.received == 0  # ticks are no samples
        assert not h.rejections()


async def test_no_overlap_and_overruns_skip_and_count_missed_ticks(
    caplog: pytest.LogCaptureFixture,
) -> None:
    node = Node("slow")
    running = 0
    most = 0
    starts: list[float] = []
    calls = Calls()

    async def busy() -> None:
        nonlocal running, most
        running += 1
        most = max(most, running)
        try:
            await anyio.sleep(5 * PERIOD)  # gives the loop away: others could run now
        finally:
            running -= 1

    @node.every(PERIOD)
    async def tick(ctx: Context) -> None:
        starts.append(anyio.current_time())
        await busy()
        calls.hit()

    @node.on_event("poke")
    async def poke(ctx: Context) -> None:
        await busy()

    caplog.set_level(logging.WARNING, logger="rap_sdk.runtime")
    async with MemoryFabric() as fabric, run_nodes([node], fabric=fabric, system="t") as group:
        rt = group["slow"]
        sealer = Sealer("src")
        for _ in range(3):  # events compete with the ticks for the node's turn
            payload, _ = sealer.seal_message(keys.event("t", "poke"), None)
            await fabric.publish(keys.event("t", "poke"), payload)
        await calls.reach(5)
    stats = rt.stats
    assert most == 1  # never two calls of the node at once
    assert stats.handled == stats.ticks + 3
    # each call takes 5 periods: at least the 4 ticks that fell in it are skipped
    assert stats.ticks_skipped >= 3 * stats.ticks
    gaps = [b - a for a, b in itertools.pairwise(starts)]
    assert min(gaps) >= 4 * PERIOD  # the next call waits for the next tick after
    overran = [r for r in caplog.records if "overran its period" in r.getMessage()]
    assert overran
    assert "node slow: periodic handler" in overran[0].getMessage()
    assert len(overran) < stats.ticks  # rate limited: not one line per overrun


async def test_a_failing_call_is_counted_and_the_timer_goes_on(
    caplog: pytest.LogCaptureFixture,
) -> None:
    node = Node("flaky")
    calls = Calls()
    handled = Calls()

    @node.every(PERIOD)
    async def tick(ctx: Context) -> None:
        calls.hit()
        raise RuntimeError(f"bug {calls.n}")

    @node.on_event("go")
    async def go(ctx: Context) -> None:
        handled.hit()

    caplog.set_level(logging.ERROR, logger="rap_sdk.runtime")
    async with Harness(system="t") as h:
        group = await h.start(node)
        rt = group["flaky"]
        await calls.reach(3)
        await h.emit("go")  # the node still handles its input
        await handled.reach(1)
        await h.wait_for(lambda r: r.kind is keys.Kind.TRACE and not r.decode(StageTrace).ok)
    assert rt.stats.failed >= 3
    assert rt.stats.failed == rt.stats.ticks
    assert rt.stats.handled == 1
    failed = [t for t in h.traces("flaky") if not t.ok]
    assert failed[0].error == "RuntimeError: bug 1"
    logged = [r for r in caplog.records if "handler" in r.getMessage() and r.exc_info]
    assert logged
    assert "every:flaky/tick" in logged[0].getMessage()


async def test_the_timer_stops_with_the_node_and_a_running_call_ends() -> None:
    node = Node("ticker")
    calls = Calls()
    finished = 0

    @node.every(PERIOD)
    async def tick(ctx: Context) -> None:
        nonlocal finished
        calls.started()
        await anyio.sleep(2 * PERIOD)
        finished += 1
        calls.ended()

    async with MemoryFabric() as fabric:
        async with run_nodes([node], fabric=fabric, system="t", grace=5.0) as group:
            await calls.reach(2)
            await calls.until(lambda: calls.running)  # leave while a call runs
            t0 = time.monotonic()
        assert time.monotonic() - t0 < 2.0  # the timers ended at once, not at the grace
        assert finished == calls.n  # the running call was let finish, not cancelled
        assert group["ticker"]._state == "stopped"
        await anyio.sleep(10 * PERIOD)  # time for ticks that must not come
        assert calls.n == finished


async def test_a_paused_node_does_not_tick() -> None:
    node = Node("p")
    calls = Calls()

    @node.every(PERIOD)
    async def tick(ctx: Context) -> None:
        calls.hit()

    async with MemoryFabric() as fabric, run_nodes([node], fabric=fabric, system="t") as group:
        rt = group["p"]
        await calls.reach(1)
        await rt.pause()
        seen = calls.n
        await anyio.sleep(5 * PERIOD)  # ticks would come now
        assert calls.n == seen
        rt.resume()
        await calls.reach(seen + 1)
        assert rt.stats.ticks_skipped >= 3  # the ticks of the pause


async def test_ticks_are_counted_in_the_metrics() -> None:
    node = Node("m")
    calls = Calls()

    @node.every(PERIOD)
    async def tick(ctx: Context) -> None:
        calls.hit()

    async with MemoryFabric() as fabric, run_nodes([node], fabric=fabric, system="t") as group:
        rt = group["m"]
        await calls.reach(2)
        families: list[Metric] = list(RuntimeCollector([rt], system="t").collect())
    ticks = next(f for f in families if f.name == "rap_ticks")
    skipped = next(f for f in families if f.name == "rap_ticks_skipped")
    assert ticks.samples[0].value >= 2
    assert ticks.samples[0].labels["component"] == "m"
    assert skipped.samples[0].value == rt.stats.ticks_skipped


@pytest.mark.parametrize("period", [0, -1.0, math.inf, math.nan, True, "1"])
def test_the_period_must_be_positive_and_finite(period: Any) -> None:
    node = Node("clocky")
    with pytest.raises(HandlerError, match=r"node 'clocky', every\(.*\): the period must be"):
        node.every(period)


def test_periodic_declarations_are_checked() -> None:
    node = Node("n")

    with pytest.raises(HandlerError, match="'async def'"):

        @node.every(1.0)  # type: ignore[type-var]
        def not_async(ctx: Context) -> None: ...

    with pytest.raises(HandlerError, match=r"must take \(ctx\) only"):

        @node.every(1.0)
        async def takes_a_message(ctx: Context, msg: Empty) -> None: ...

    @node.every(1.0)
    async def tick(ctx: Context) -> None: ...

    with pytest.raises(HandlerError, match="second periodic handler named 'tick'"):
        node.every(2.0, name="tick")(tick)

    with pytest.raises(HandlerError, match="not a valid periodic handler name"):
        node.every(2.0, name="a/b")(tick)

    node.every(2.0, name="tick2")(tick)
    assert [(p.name, p.period) for p in node.periodic] == [("tick", 1.0), ("tick2", 2.0)]
    assert node.routes == []  # nothing to subscribe to
    assert "periodic=2" in repr(node)


def test_a_swap_keeps_the_periodic_handlers() -> None:
    def make(*names: str) -> Node:
        node = Node("n")
        for name in names:

            @node.every(1.0, name=name)
            async def tick(ctx: Context) -> None: ...

        return node

    rt = NodeRuntime(make("a"), fabric=MemoryFabric(), system="t")
    rt.match_routes(make("a"))  # same handlers: fits
    with pytest.raises(ConfigError, match="it has no periodic handler 'a'"):
        rt.match_routes(make())
    with pytest.raises(ConfigError, match="periodic handler 'b', which the running one does not"):
        rt.match_routes(make("a", "b"))

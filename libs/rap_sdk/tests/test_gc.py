"""Garbage collection off the critical path: collected while idle, forced past a bound,
automatic collection back afterwards."""

from __future__ import annotations

import gc
import time
import weakref
from collections.abc import Iterator

import anyio
import anyio.lowlevel
import pytest
from rap_sdk import Context, MemoryFabric, Node, run_nodes
from rap_sdk.gc import IdleCollector

pytestmark = pytest.mark.anyio


@pytest.fixture(autouse=True)
def _thawed() -> Iterator[None]:
    """A collector freezes the heap and turns collection off: undone after each test,
    whatever it asserted."""
    yield
    gc.unfreeze()
    gc.enable()


class _Cyclic:
    def __init__(self) -> None:
        self.me = self


def garbage(n: int) -> weakref.ref[_Cyclic]:
    """``n`` objects in reference cycles (only the collector frees them)."""
    last = _Cyclic()
    for _ in range(n - 1):
        _Cyclic()
    return weakref.ref(last)


async def test_collects_when_idle_and_gives_collection_back() -> None:
    assert gc.isenabled()
    collector = IdleCollector(lambda: False, period=0.005, young=100)
    async with anyio.create_task_group() as tg:
        await tg.start(collector.run)
        assert not gc.isenabled()
        ref = garbage(500)
        with anyio.fail_after(5):
            while ref() is not None:  # noqa: ASYNC110 (the collector's progress)
                await anyio.sleep(0.005)
        assert collector.stats.idle >= 1
        collector.stop()
    assert gc.isenabled()


async def test_a_busy_loop_is_collected_once_the_bound_is_passed() -> None:
    collector = IdleCollector(lambda: True, period=0.005, young=100, force=2000)
    async with anyio.create_task_group() as tg:
        await tg.start(collector.run)
        ref = garbage(500)
        await anyio.sleep(0.05)
        assert ref() is not None  # busy, under the bound: left for later
        ref = garbage(5000)
        with anyio.fail_after(5):
            while ref() is not None:  # noqa: ASYNC110
                await anyio.sleep(0.005)
        assert collector.stats.forced >= 1
        assert collector.stats.idle == 0
        collector.stop()


async def test_run_nodes_with_idle_collection_stops_at_once() -> None:
    node = Node("n")
    seen: list[int] = []

    @node.on_event("go")
    async def go(ctx: Context) -> None:
        seen.append(1)

    async with MemoryFabric() as fabric:
        t0 = time.monotonic()
        async with run_nodes([node], fabric=fabric, system="s", gc_idle=True) as group:
            assert not gc.isenabled()
            assert group.collector is not None
            await group["n"].send("rap/s/event/go", None)
        assert time.monotonic() - t0 < 2.0  # not the 5 s grace
    assert seen == [1]
    assert gc.isenabled()


async def test_a_poke_looks_once_the_loop_turns_without_waiting_for_the_period() -> None:
    collector = IdleCollector(lambda: False, period=3600, young=100)
    async with anyio.create_task_group() as tg:
        await tg.start(collector.run)
        ref = garbage(500)
        await anyio.sleep(0.05)
        assert ref() is not None  # nothing looks: the period is an hour
        collector.poke()
        collector.poke()  # one look per turn of the loop
        await anyio.lowlevel.checkpoint()
        await anyio.lowlevel.checkpoint()
        assert ref() is None
        assert collector.stats.idle == 1
        collector.stop()


async def test_run_nodes_looks_after_each_handler_call() -> None:
    """With ``gc_idle`` the garbage of a handler is collected when the call has ended
    and the nodes are idle, long before the collector's period."""
    node = Node("n")
    refs: list[weakref.ref[_Cyclic]] = []

    @node.on_event("go")
    async def go(ctx: Context) -> None:
        refs.append(garbage(2000))

    async with (
        MemoryFabric() as fabric,
        run_nodes([node], fabric=fabric, system="s", gc_idle=True) as group,
    ):
        assert group.collector is not None
        assert group.collector.period >= 1.0
        await group["n"].send("rap/s/event/go", None)
        with anyio.fail_after(0.5):  # well inside the period
            while not refs or refs[0]() is not None:  # noqa: ASYNC110
                await anyio.sleep(0.005)
        assert group.collector.stats.idle >= 1

"""What a handler sends leaves when it returns, after its one trace record; a handler
that waits, or flushes, is recorded as a start and an end around its sends."""

from __future__ import annotations

import anyio
import pytest
from rap_schemas import Empty, StageTrace, keys
from rap_sdk import Context, Node
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio


def order(h: Harness) -> list[str]:
    """Trace records (by phase) and events, in the order the harness received them."""
    out = []
    for r in h.records:
        if r.kind is keys.Kind.TRACE:
            out.append(r.decode(StageTrace).phase)
        elif r.kind is keys.Kind.EVENT:
            out.append(r.name)
    return out


async def test_one_record_per_call_before_what_the_call_sent() -> None:
    node = Node("n", stage="monitor")

    @node.on_event("go")
    async def go(ctx: Context) -> None:
        await ctx.emit("first")
        await ctx.emit("second")

    async with Harness(system="t") as h:
        await h.start(node)
        await h.emit("go")
        await h.expect_event("second")
        assert order(h) == ["go", "call", "first", "second"]
        (rec,) = h.traces("n")
        assert rec.sent == [keys.event("t", "first"), keys.event("t", "second")]


async def test_a_handler_that_waits_is_recorded_as_start_then_end() -> None:
    node = Node("n", stage="monitor")
    release = anyio.Event()

    @node.on_event("go")
    async def go(ctx: Context) -> None:
        await ctx.emit("done")
        await release.wait()  # gives the loop a turn: a checker must see it started

    async with Harness(system="t") as h:
        await h.start(node)
        await h.emit("go")
        await h.wait_for(lambda r: any(t.phase == "start" for t in h.traces("n")))
        assert not h.of(keys.Kind.EVENT, "done")  # not sent before the handler returns
        release.set()
        await h.expect_event("done")
        assert order(h) == ["go", "start", "end", "done"]
        start, end = h.traces("n")
        assert start.started
        assert not start.ended
        assert end.ended
        assert end.sent == [keys.event("t", "done")]


async def test_flush_sends_at_once_after_a_start_record() -> None:
    node = Node("n", stage="execute")

    @node.on_event("go", type=Empty)
    async def go(ctx: Context) -> None:
        await ctx.emit("step")
        await ctx.flush()
        await ctx.emit("last")

    async with Harness(system="t") as h:
        await h.start(node)
        await h.emit("go")
        await h.expect_event("last")
        assert order(h) == ["go", "start", "step", "end", "last"]


async def test_what_a_failing_handler_sent_still_goes_out_after_its_record() -> None:
    node = Node("n", stage="plan")

    @node.on_event("go")
    async def go(ctx: Context) -> None:
        await ctx.emit("partial")
        raise RuntimeError("bug")

    async with Harness(system="t") as h:
        await h.start(node)
        await h.emit("go")
        await h.expect_event("partial")
        assert order(h) == ["go", "call", "partial"]
        (rec,) = h.traces("n")
        assert not rec.ok
        assert rec.error == "RuntimeError: bug"

"""blockbuster turns a blocking call made on the event loop into an error."""

from __future__ import annotations

from collections.abc import Iterator

import pytest
from blockbuster import BlockBuster, blockbuster_ctx
from rap_schemas import keys
from rap_sdk import Context, Node
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio


@pytest.fixture
def blockbuster() -> Iterator[BlockBuster]:
    with blockbuster_ctx() as bb:
        yield bb


@pytest.mark.parametrize("fabric", ["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)])
async def test_a_loop_cycle_makes_no_blocking_call(
    blockbuster: BlockBuster,
    fabric: str,
) -> None:
    a, b = Node("a", stage="monitor"), Node("b", stage="analyse")

    @a.on_event("go")
    async def go(ctx: Context) -> None:
        await ctx.emit("next")

    @b.on_event("next")
    async def nxt(ctx: Context) -> None:
        await ctx.emit("done")

    async with Harness(system="bb", fabric=fabric, isolate=fabric == "zenoh") as h:  # type: ignore[arg-type]
        await h.start(a, b)
        for _ in range(20):
            n = len(h.records)
            await h.emit("go")
            await h.expect(keys.Kind.EVENT, "done", after=n)


async def test_the_guard_is_live(blockbuster: BlockBuster) -> None:
    """The same guard catches a blocking call in a handler (so the test above can fail)."""
    import time

    n = Node("sleepy")

    @n.on_event("go")
    async def go(ctx: Context) -> None:
        time.sleep(0.001)  # noqa: ASYNC251 - the blocking call under test

    async with Harness(system="bb") as h:
        await h.start(n)
        await h.emit("go")
        await h.wait_for(lambda r: any(t.ended for t in h.traces()))
        (end,) = [t for t in h.traces() if t.ended]
        assert not end.ok
        assert "BlockingError" in end.error

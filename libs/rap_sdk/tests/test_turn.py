"""The node's turn (one handler at a time): taken at once when free, handed over in
order, and never lost to a waiter that was cancelled."""

from __future__ import annotations

import asyncio
from collections.abc import Awaitable, Callable

import pytest
from rap_sdk.runtime import Turn

pytestmark = pytest.mark.anyio


async def test_waiters_get_the_turn_in_order_and_a_direct_taker_cannot_overtake() -> None:
    turn = Turn()
    order: list[int] = []

    async def take(i: int) -> None:
        async with turn:
            order.append(i)
            await asyncio.sleep(0)

    turn.held = True  # as direct dispatch takes it
    tasks = [asyncio.create_task(take(i)) for i in range(3)]
    await asyncio.sleep(0)
    turn.release()  # handed to the first waiter: it stays held
    assert turn.held
    await asyncio.gather(*tasks)
    assert order == [0, 1, 2]
    assert not turn.held


def _held() -> tuple[Turn, list[str], Callable[[str], Awaitable[None]]]:
    """A turn held (as direct dispatch holds it), and waiters that note their name."""
    turn = Turn()
    turn.held = True
    got: list[str] = []

    async def take(name: str) -> None:
        async with turn:
            got.append(name)

    return turn, got, take


async def test_a_cancelled_waiter_is_skipped() -> None:
    turn, got, take = _held()
    first = asyncio.create_task(take("cancelled"))
    second = asyncio.create_task(take("second"))
    await asyncio.sleep(0)
    first.cancel()
    await asyncio.sleep(0)
    turn.release()
    await second
    assert got == ["second"]
    assert first.cancelled()
    assert not turn.held


async def test_a_waiter_cancelled_after_it_was_handed_the_turn_passes_it_on() -> None:
    turn, got, take = _held()
    first = asyncio.create_task(take("first"))
    second = asyncio.create_task(take("second"))
    await asyncio.sleep(0)
    turn.release()  # handed to first ...
    first.cancel()  # ... which is cancelled before it runs
    await asyncio.gather(first, second, return_exceptions=True)
    assert got == ["second"]
    assert not turn.held

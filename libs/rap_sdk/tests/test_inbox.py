from __future__ import annotations

import asyncio

import anyio
import pytest
from rap_sdk import BackpressureTimeout, InboxPolicy, Overflow
from rap_sdk.inbox import Inbox

pytestmark = pytest.mark.anyio


def test_a_string_overflow_becomes_the_policy_it_names() -> None:
    assert InboxPolicy(overflow="fifo").overflow is Overflow.FIFO  # type: ignore[arg-type]
    assert InboxPolicy(overflow="latest").overflow is Overflow.LATEST  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="overflow must be one of"):
        InboxPolicy(overflow="newest")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="capacity must be >= 1"):
        InboxPolicy(capacity=0)
    fifo: Inbox[int] = Inbox(InboxPolicy(capacity=1, overflow="fifo", block=False))  # type: ignore[arg-type]
    assert fifo.offer(1)
    assert not fifo.offer(2)  # FIFO drops the new item, not the old one
    assert fifo.get_nowait() == 1


async def test_a_cancelled_waiting_put_hands_its_wake_up_on() -> None:
    inbox: Inbox[int] = Inbox(InboxPolicy(capacity=1))
    await inbox.put(0)
    a = asyncio.ensure_future(inbox.put(1))
    b = asyncio.ensure_future(inbox.put(2))
    await anyio.wait_all_tasks_blocked()
    assert inbox.get_nowait() == 0  # room for one: wakes putter A ...
    a.cancel()  # ... which is cancelled before it runs
    with anyio.fail_after(2):
        await asyncio.wait([a])
        assert a.cancelled()
        assert await b  # B got the room A gave up
    assert inbox.get_nowait() == 2


async def test_the_put_deadline_is_total_not_per_wake_up() -> None:
    inbox: Inbox[int] = Inbox(InboxPolicy(capacity=1))
    await inbox.put(0)
    with pytest.raises(BackpressureTimeout), anyio.fail_after(2):
        await inbox.put(1, timeout=0.05)


async def test_latest_drops_the_oldest_and_counts() -> None:
    inbox: Inbox[int] = Inbox(InboxPolicy(capacity=2, overflow=Overflow.LATEST))
    for i in range(5):
        assert inbox.offer(i)
    assert [inbox.get_nowait(), inbox.get_nowait()] == [3, 4]
    assert (inbox.stats.accepted, inbox.stats.dropped, inbox.stats.high_water) == (5, 3, 2)


def test_a_byte_budget_bounds_what_is_queued() -> None:
    fifo = Inbox(InboxPolicy(capacity=100, max_bytes=10), size=len)
    assert fifo.offer(b"12345")
    assert fifo.offer(b"12345")
    assert not fifo.offer(b"1")  # 11 bytes would be over 10: dropped
    assert fifo.stats.dropped == 1
    assert fifo.get_nowait() == b"12345"
    assert fifo.offer(b"1")  # room again
    latest = Inbox(InboxPolicy(capacity=100, overflow=Overflow.LATEST, max_bytes=10), size=len)
    for chunk in (b"aaaa", b"bbbb", b"cccc"):
        latest.offer(chunk)
    assert [latest.get_nowait(), latest.get_nowait()] == [b"bbbb", b"cccc"]  # newest kept
    assert latest.stats.dropped == 1
    big = Inbox(InboxPolicy(capacity=100, max_bytes=10), size=len)
    assert big.offer(b"x" * 50)  # alone, an item larger than the budget still passes
    assert not big.offer(b"y")

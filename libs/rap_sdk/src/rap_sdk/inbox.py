"""Bounded inboxes with an explicit overflow policy.

``latest``: when full, the oldest item is dropped for the new one (sensor data: the
newest reading is what matters). ``fifo``: when full, a local publisher waits for room
(``block=True``, backpressure) or the new item is dropped (``block=False``). Items that
arrive from another process on a transport thread never wait: into a full FIFO inbox they
are dropped and counted (a transport thread must never block), so size FIFO inboxes for
the bursts you expect from remote senders.
"""

from __future__ import annotations

import asyncio
import enum
from collections import deque
from collections.abc import Callable
from dataclasses import dataclass
from typing import Generic, TypeVar

import msgspec

from .errors import BackpressureTimeout, LifecycleError

__all__ = ["Inbox", "InboxPolicy", "InboxStats", "Overflow"]

T = TypeVar("T")


class Overflow(enum.StrEnum):
    LATEST = "latest"
    FIFO = "fifo"


class InboxPolicy(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    capacity: int = 64
    overflow: Overflow = Overflow.FIFO
    block: bool = True
    """FIFO only: local publishers wait for room instead of dropping."""
    max_bytes: int | None = None
    """Bytes the queued samples may hold together (None: bounded by count only); past it
    the inbox is full, as past ``capacity``. A count alone does not bound memory when
    samples may be large."""

    def __post_init__(self) -> None:
        if self.capacity < 1:
            raise ValueError(f"inbox capacity must be >= 1, got {self.capacity}")
        if self.max_bytes is not None and self.max_bytes < 1:
            raise ValueError(f"inbox max_bytes must be >= 1 or None, got {self.max_bytes}")
        # a plain string (InboxPolicy(overflow="fifo")) becomes the enum, or is refused
        try:
            msgspec.structs.force_setattr(self, "overflow", Overflow(self.overflow))
        except ValueError:
            raise ValueError(
                f"inbox overflow must be one of {[o.value for o in Overflow]}, "
                f"got {self.overflow!r}"
            ) from None


@dataclass(slots=True)
class InboxStats:
    accepted: int = 0
    dropped: int = 0
    high_water: int = 0


class Inbox(Generic[T]):
    """A single-consumer bounded queue living on one event loop."""

    __slots__ = ("_bytes", "_closed", "_getter", "_items", "_putters", "_size", "policy", "stats")

    def __init__(self, policy: InboxPolicy, size: Callable[[T], int] | None = None) -> None:
        """``size(item)``: an item's bytes, for ``policy.max_bytes``."""
        self.policy = policy
        self.stats = InboxStats()
        self._items: deque[T] = deque()
        self._getter: asyncio.Future[None] | None = None
        self._putters: deque[asyncio.Future[None]] = deque()
        self._closed = False
        self._size = size if policy.max_bytes is not None else None
        self._bytes = 0

    def _full(self, n: int) -> bool:
        """No room for one more item of ``n`` bytes."""
        if len(self._items) >= self.policy.capacity:
            return True
        limit = self.policy.max_bytes
        return limit is not None and self._bytes + n > limit and bool(self._items)

    def _pop(self) -> T:
        item = self._items.popleft()
        if self._size is not None:
            self._bytes -= self._size(item)
        return item

    def __len__(self) -> int:
        return len(self._items)

    @property
    def closed(self) -> bool:
        return self._closed

    def offer(self, item: T) -> bool:
        """Add without waiting. Returns False when the item was dropped."""
        if self._closed:
            return False
        n = self._size(item) if self._size is not None else 0
        if self._full(n):
            if self.policy.overflow is Overflow.FIFO:
                self.stats.dropped += 1
                return False
            while self._full(n):  # latest: the oldest make room for the newest
                self._pop()
                self.stats.dropped += 1
        self._items.append(item)
        self._bytes += n
        self._accepted(len(self._items))
        return True

    def put_nowait(self, item: T) -> bool:
        """Add without waiting when the policy allows it now. False only when the item
        must wait for room (FIFO with ``block``, full): then ``await put(item)``."""
        if self._closed:
            return True  # dropped, as offer() drops it: nobody will take it
        policy = self.policy
        size = self._size
        n = size(item) if size is not None else 0
        items = self._items
        limit = policy.max_bytes
        if len(items) >= policy.capacity or (
            limit is not None and self._bytes + n > limit and items
        ):
            if policy.block and policy.overflow is Overflow.FIFO:
                return False
            self.offer(item)
            return True
        items.append(item)  # the usual case, offer() inlined
        self._bytes += n
        st = self.stats
        st.accepted += 1
        if len(items) > st.high_water:
            st.high_water = len(items)
        g = self._getter
        if g is not None and not g.done():
            g.set_result(None)
        return True

    async def put(self, item: T, *, timeout: float | None = None) -> bool:
        """Add, waiting for room when the policy is FIFO with ``block``.

        Raises :class:`BackpressureTimeout` when room does not come within ``timeout``.
        """
        policy = self.policy
        if not (policy.overflow is Overflow.FIFO and policy.block):
            return self.offer(item)
        loop = asyncio.get_running_loop()
        deadline = None if timeout is None else loop.time() + timeout
        n = self._size(item) if self._size is not None else 0
        while self._full(n) and not self._closed:
            fut = loop.create_future()
            self._putters.append(fut)
            left = None if deadline is None else max(0.0, deadline - loop.time())
            try:
                await asyncio.wait_for(fut, left)
            except TimeoutError:
                raise BackpressureTimeout(
                    f"inbox full ({policy.capacity} items) for {timeout} s; the consumer "
                    "is too slow: raise its capacity or speed up its handler"
                ) from None
            except BaseException:
                # woken but cancelled before taking the room: hand the wake-up on
                if fut.done() and not fut.cancelled():
                    self._wake_putter()
                raise
            finally:
                if fut in self._putters:
                    self._putters.remove(fut)
        if self._closed:
            return False
        self._items.append(item)
        self._bytes += n
        self._accepted(len(self._items))
        return True

    def _accepted(self, n: int) -> None:
        st = self.stats
        st.accepted += 1
        if n > st.high_water:
            st.high_water = n
        g = self._getter
        if g is not None and not g.done():
            g.set_result(None)

    def get_nowait(self) -> T | None:
        if not self._items:
            return None
        item = self._pop()
        self._wake_putter()
        return item

    async def get(self) -> T:
        """The next item; raises :class:`LifecycleError` once closed and drained."""
        while not self._items:
            if self._closed:
                raise LifecycleError("inbox closed")
            if self._getter is not None and not self._getter.done():
                raise LifecycleError("inbox has one consumer; a second get() is a bug")
            self._getter = asyncio.get_running_loop().create_future()
            try:
                await self._getter
            finally:
                self._getter = None
        item = self._items.popleft()
        if self._size is not None:
            self._bytes -= self._size(item)
        if self._putters:
            self._wake_putter()
        return item

    def _wake_putter(self) -> None:
        while self._putters:
            fut = self._putters.popleft()
            if not fut.done():
                fut.set_result(None)
                return

    def close(self) -> None:
        """Stop accepting; the consumer drains what is queued, then ``get`` raises."""
        self._closed = True
        if self._getter is not None and not self._getter.done():
            self._getter.set_result(None)
        while self._putters:
            fut = self._putters.popleft()
            if not fut.done():
                fut.set_result(None)

"""Garbage collection off the critical path.

CPython's collector runs when allocations pass a threshold, which is in the middle of
whatever handler allocated last: a pause of a fraction of a millisecond lands on a loop
cycle now and then (the p99). :class:`IdleCollector` moves it out of the way: after
start-up it collects once and freezes what survived (modules, nodes, configs are never
scanned again), turns automatic collection off, and collects the young generation when
the nodes are idle: no handler running and no sample queued. It looks when a handler
call ends (:meth:`IdleCollector.poke`, once the event loop has run what was ready), and
every ``period`` s for what allocates outside handlers: an idle process is not woken
up to look. If the loop is never idle, it collects anyway once ``force`` objects are
waiting (checked at every look), so memory stays bounded under any load: by ``force``
objects while handlers run, and by what the process allocates outside handlers in
one ``period``. Automatic collection comes back when the last collector of the process
stops.

    async with run_nodes(nodes, fabric=fabric, system="tb4", gc_idle=True): ...
"""

from __future__ import annotations

import asyncio
import gc
import time
from collections.abc import Callable
from dataclasses import dataclass

import anyio
from anyio.abc import TaskStatus

__all__ = ["GcStats", "IdleCollector"]

_active = 0
"""Collectors running in this process (automatic collection is off while any is)."""


@dataclass(slots=True)
class GcStats:
    idle: int = 0
    """Collections made while the nodes were idle."""
    forced: int = 0
    """Collections made while busy, because ``force`` objects were waiting."""
    full: int = 0
    """Collections of the oldest generation (idle only)."""
    max_pause_ns: int = 0


class IdleCollector:
    def __init__(
        self,
        busy: Callable[[], bool],
        *,
        period: float = 1.0,
        young: int = 700,
        force: int = 50_000,
    ) -> None:
        """``busy()``: whether a handler is running or a sample is queued. At each
        look (after :meth:`poke`, and every ``period`` s), with more than ``young`` new
        objects, the young generation is collected if not busy (or, past ``force``,
        anyway); the older ones when their turn comes and the nodes are idle."""
        self.busy = busy
        self.period = period
        self.young = young
        self.force = force
        self.stats = GcStats()
        self._scope: anyio.CancelScope | None = None
        self._stopped = False
        self._loop: asyncio.AbstractEventLoop | None = None
        self._poked = False

    def poke(self) -> None:
        """A handler call ended: look once the event loop has run what is ready (the
        rest of the cycle in this process), at most one look per turn of the loop."""
        if not self._poked and self._loop is not None:
            self._poked = True
            self._loop.call_soon(self._look)

    def _look(self) -> None:
        self._poked = False
        if not self._stopped:
            self.step()

    def stop(self) -> None:
        """End :meth:`run` (automatic collection comes back if it was the last)."""
        self._stopped = True
        if self._scope is not None:
            self._scope.cancel()

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        global _active
        gc.collect()
        gc.freeze()
        _active += 1
        gc.disable()
        self._loop = asyncio.get_running_loop()
        task_status.started()
        try:
            with anyio.CancelScope() as self._scope:
                if self._stopped:
                    self._scope.cancel()
                while True:
                    await anyio.sleep(self.period)
                    self.step()
        finally:
            _active -= 1
            if not _active:
                gc.enable()

    def step(self) -> None:
        """One look: collect what is due (see the class)."""
        young, older, oldest = gc.get_count()
        if young < self.young:
            return
        idle = not self.busy()
        if not idle and young < self.force:
            return
        t0 = time.perf_counter_ns()
        if idle and oldest >= 10:
            gc.collect(2)
            self.stats.full += 1
        elif idle and older >= 10:
            gc.collect(1)
        else:
            gc.collect(0)
        pause = time.perf_counter_ns() - t0
        if idle:
            self.stats.idle += 1
        else:
            self.stats.forced += 1
        if pause > self.stats.max_pause_ns:
            self.stats.max_pause_ns = pause

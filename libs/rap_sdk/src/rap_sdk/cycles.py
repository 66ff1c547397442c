"""Knowing when a loop cycle is over, from the trace records alone.

A cycle starts with a root message (a scan, say). Every handler that runs in the cycle
publishes a ``call`` (or ``end``) record naming its trigger's key and listing the keys it sent on;
each of those keys is handled once per subscribed route of the loop's nodes. So a cycle
is over when, for every key, as many handler calls triggered on it have ended as its
messages promised (per key, so that records arriving out of order between nodes can
never balance early). A lockstep simulator waits for that before it steps on, which
makes the loop's timing deterministic without a single sleep:

    topo = Topology.of(nodes, system="demo")
    tracker = CycleTracker(topo)
    tg.start_soon(partial(tracker.follow, fabric=fabric))        # subscribes to rap/demo/trace/**
    env = await rt.send(scan_key, scan)
    tracker.expect(env.uid, scan_key)
    await tracker.wait(env.uid, timeout=2.0)     # False: the loop lost the cycle

Only the records of the topology's nodes count. A message lost on the way (an inbox
overflow) leaves its cycle open: ``wait`` returns False at its deadline and the tracker
counts it in ``timeouts``.
"""

from __future__ import annotations

import logging
from collections import OrderedDict
from collections.abc import Iterable, Mapping
from dataclasses import dataclass, field

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import StageTrace, keys

from .envelope import typed_decoder
from .fabric import Fabric
from .inbox import InboxPolicy, Overflow
from .node import Node

__all__ = ["CycleTracker", "Topology"]

log = logging.getLogger(__name__)

_decode_trace = typed_decoder(None)
_trace_body = msgspec.msgpack.Decoder(StageTrace).decode


@dataclass(frozen=True)
class Topology:
    """Which node handles which key: ``subscribers[key]`` routes in ``nodes``."""

    system: str
    subscribers: Mapping[str, int]
    nodes: frozenset[str]

    @classmethod
    def of(cls, nodes: Iterable[Node], *, system: str) -> Topology:
        subs: dict[str, int] = {}
        names: set[str] = set()
        for node in nodes:
            names.add(node.name)
            for route in node.routes:
                if not route.traced:  # no end record balances it (trust verdict routes)
                    continue
                key = route.key(system)
                subs[key] = subs.get(key, 0) + 1
        return cls(system, subs, frozenset(names))


@dataclass(slots=True)
class _Cycle:
    balance: dict[str, int] = field(default_factory=dict)
    """Per key: handler calls its messages promised minus calls that ended."""
    unbalanced: int = 0
    rooted: bool = False
    ended: int = 0
    expected: int = 0
    done: anyio.Event = field(default_factory=anyio.Event)

    def add(self, key: str, n: int) -> None:
        old = self.balance.get(key, 0)
        new = self.balance[key] = old + n
        self.unbalanced += (new != 0) - (old != 0)

    def check(self) -> None:
        if self.rooted and not self.unbalanced:
            self.done.set()


class CycleTracker:
    def __init__(self, topology: Topology, *, memory: int = 4096) -> None:
        self.topology = topology
        self.memory = memory
        self.completed = 0
        self.timeouts = 0
        self._cycles: OrderedDict[bytes, _Cycle] = OrderedDict()

    def _get(self, cycle: bytes) -> _Cycle:
        st = self._cycles.get(cycle)
        if st is None:
            st = self._cycles[cycle] = _Cycle()
            if len(self._cycles) > self.memory:
                self._cycles.popitem(last=False)
        return st

    def expect(self, cycle: bytes, key: str) -> None:
        """Cycle ``cycle`` started with a message on ``key``."""
        st = self._get(cycle)
        st.rooted = True
        n = self.topology.subscribers.get(key, 0)
        st.expected += n
        st.add(key, n)
        st.check()

    def observe(self, rec: StageTrace) -> None:
        """Account for one trace record."""
        if rec.phase == "start" or rec.node not in self.topology.nodes:
            return
        st = self._get(rec.cycle)
        st.ended += 1
        st.add(rec.trigger_key, -1)
        subs = self.topology.subscribers
        for key in rec.sent:
            n = subs.get(key, 0)
            if n:
                st.expected += n
                st.add(key, n)
        st.check()

    def pending(self, cycle: bytes) -> tuple[int, int]:
        """(ended, expected) handler calls of ``cycle`` so far."""
        st = self._cycles.get(cycle)
        return (st.ended, st.expected) if st else (0, 0)

    async def wait(self, cycle: bytes, timeout: float) -> bool:
        """Wait until ``cycle`` is over (True), or ``timeout`` s (False, counted)."""
        st = self._get(cycle)
        with anyio.move_on_after(timeout):
            await st.done.wait()
        self._cycles.pop(cycle, None)
        if st.done.is_set():
            self.completed += 1
            return True
        self.timeouts += 1
        log.warning(
            "cycle %s not over after %.3g s: %d of %d handler calls ended",
            cycle.hex(),
            timeout,
            st.ended,
            st.expected,
        )
        return False

    async def follow(
        self, *, fabric: Fabric, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED
    ) -> None:
        """Feed the tracker from the system's trace records until cancelled."""
        policy = InboxPolicy(capacity=4096, overflow=Overflow.FIFO)
        key = keys.pattern(self.topology.system, keys.Kind.TRACE)
        with fabric.subscribe(key, policy) as sub:
            task_status.started()
            async for sample in sub:
                try:
                    env = _decode_trace(sample.payload)
                    if env.type != StageTrace.TYPE:
                        continue  # another record (a KnowledgeAccess from elsewhere)
                    self.observe(_trace_body(env.body))
                except (msgspec.ValidationError, msgspec.DecodeError) as exc:
                    log.warning("tracker: bad trace record on %s: %s", sample.key, exc)

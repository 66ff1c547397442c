"""Running nodes on a fabric: inboxes, typed dispatch, tracing, rejections, shutdown.

Each route of a node gets its own subscription with its own bounded inbox and a consumer
task; a node's handlers run one at a time (a node's state needs no locks). What a
handler emits or publishes leaves when it returns, in order (``ctx.flush()`` sends it
earlier). For every handler call, when someone subscribes to the node's trace key, the
runtime publishes one :class:`~rap_schemas.StageTrace` record (start, end, knowledge
reads and writes, what it sent) before what the call sent, carrying the ``cycle``
(except for handlers of trust-checker outputs, which run outside the MAPLE-K cycle). A
sample that cannot be accepted is counted, logged (rate limited) and published as a
:class:`~rap_schemas.Rejection` on ``rap/<system>/log/<node>``; it never stops the node.

A node's periodic handlers (``@node.every(period)``) each get a timer task that calls
them on the event loop's monotonic clock (anyio's: the SDK's :class:`Clock` only stamps
wall time), taking the node's turn like any handler; each call is the root of a cycle.
"""

from __future__ import annotations

import asyncio
import logging
import math
import os
import signal
import time
from bisect import bisect_left
from collections import deque
from collections.abc import AsyncIterator, Awaitable, Callable, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass
from functools import partial
from time import perf_counter
from typing import Any

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import Access, Empty, Message, Rejection, StageTrace, keys

from .envelope import (
    Clock,
    Opener,
    OutgoingEnvelope,
    Sealer,
    SenderStats,
    SystemClock,
    TypedEnvelope,
    new_uid,
)
from .errors import BackpressureTimeout, ConfigError, LifecycleError, RapError, RejectedSample
from .fabric import Fabric, Outgoing, Sample, Subscription
from .gc import IdleCollector
from .knowledge import _MISSING, KnowledgeClient
from .latency import BUCKETS as LATENCY_BUCKETS
from .latency import RECENT, Latency
from .node import Node, Periodic, Route
from .rejections import Rejections, Throttle

__all__ = [
    "Context",
    "NodeGroup",
    "NodeRuntime",
    "NodeStats",
    "await_alive",
    "refuse_running",
    "run_nodes",
    "serve",
]

log = logging.getLogger(__name__)

RECORD_TIMEOUT = 1.0
"""Seconds a trace or rejection record may wait for room in a local inbox."""
MAX_DIRECT_DEPTH = 16
"""How many handlers may run nested in one task by direct dispatch (a chain of local
stages each handling what the one before sent); deeper, samples go through inboxes."""
_depth = [0]
LATENCY_MASK = RECENT - 1
NODE_ENV = "RAP_COMPUTE_NODE"
"""The environment variable naming the compute node a process runs on."""
SEND_TIMEOUT = 1.0
"""Seconds a handler's emit or publish may wait for room in a local node's full FIFO
inbox before that node is skipped (counted and logged): local nodes that send to each
other in a cycle (plan -> legitimate -> plan-rejected -> plan) would otherwise wait for
each other for ever once their inboxes are full."""


class Turn:
    """A node's turn to run a handler (one at a time): a lock that a caller may take at
    once when it is free (direct dispatch: ``held = True``, no await), and that
    consumer tasks wait for in order. Released, it is handed to the first waiter that
    still waits, so a direct call never overtakes a consumer that was waiting."""

    __slots__ = ("_waiters", "held")

    def __init__(self) -> None:
        self.held = False
        self._waiters: deque[asyncio.Future[None]] = deque()

    def locked(self) -> bool:
        return self.held

    async def __aenter__(self) -> None:
        if not self.held:
            self.held = True
            return
        waiter: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        self._waiters.append(waiter)
        try:
            await waiter
        except BaseException:
            if waiter.done() and not waiter.cancelled():
                self.release()  # handed the turn, then cancelled: pass it on
            elif waiter in self._waiters:
                self._waiters.remove(waiter)
            raise

    async def __aexit__(self, *exc: object) -> None:
        self.release()

    def release(self) -> None:
        waiters = self._waiters
        while waiters:
            waiter = waiters.popleft()
            if not waiter.done():
                waiter.set_result(None)  # handed over: it stays held
                return
        self.held = False


@dataclass(slots=True)
class NodeStats:
    received: int = 0
    handled: int = 0
    failed: int = 0
    rejected: int = 0
    sent: int = 0
    dropped: int = 0
    """Samples the node's inboxes dropped because they were full (logged, rate-limited)."""
    send_timeouts: int = 0
    """Sends of this node that a local node's inbox could not take within
    ``SEND_TIMEOUT`` (that node did not get them; logged, rate-limited)."""
    records_lost: int = 0
    """Trace or rejection records that could not be published."""
    kb_reads: int = 0
    """Knowledge reads of its handlers."""
    kb_writes: int = 0
    """Knowledge writes and deletes of its handlers."""
    ticks: int = 0
    """Calls of its periodic handlers (``@node.every``; also in ``handled`` or
    ``failed``)."""
    ticks_skipped: int = 0
    """Ticks of its periodic handlers that were not run because the call before (or
    the wait for the node's turn) overran them (logged, rate-limited)."""


class Context:
    """What a handler gets: the triggering envelope and ways to act in its cycle."""

    __slots__ = (
        "_kb",
        "_out",
        "_route",
        "_rt",
        "_split",
        "_starting",
        "access",
        "cycle",
        "deadline",
        "envelope",
        "key",
        "message",
        "sent",
        "started",
        "written",
    )

    def __init__(
        self,
        rt: NodeRuntime,
        key: str,
        envelope: TypedEnvelope[Any],
        message: Any,
        deadline: float = 0.0,
    ) -> None:
        self._rt = rt
        self.deadline = deadline
        """Monotonic time until which a read waits for a version the trigger promised:
        the knowledge client's timeout counted from the trigger's arrival (0: none)."""
        self.key = key
        self.envelope = envelope
        self.message = message
        self.cycle: bytes = envelope.cycle or envelope.uid
        self.written: dict[str, int] | None = None
        """Knowledge versions this handler wrote: carried in what it emits."""
        self.sent: list[str] | None = None
        """Keys this handler emitted or published on, in order (for the trace record)."""
        self._kb: ContextKnowledge | None = None
        self._out: list[tuple[str, Outgoing]] | None = None
        """What the handler sent and has not left yet (it leaves when the handler
        returns, or at ``flush()``)."""
        self._route: Route | Periodic | None = None
        self._split = False
        """A ``start`` record went out (the handler waited, or flushed): the call ends
        with an ``end`` record."""
        self._starting: asyncio.Task[None] | None = None
        self.access: list[Access] | None = None
        """The handler's knowledge accesses, when the call is traced (else None)."""
        self.started = 0
        """When the handler started, UTC ns (when traced)."""

    @property
    def kb(self) -> ContextKnowledge:
        """Knowledge, causally: reads wait for the versions the trigger promised."""
        if self._kb is None:
            self._kb = ContextKnowledge(self)
        return self._kb

    @property
    def node(self) -> Node:
        return self._rt.node

    @property
    def system(self) -> str:
        return self._rt.system

    @property
    def config(self) -> Any:
        return self._rt.node.config

    @property
    def clock(self) -> Clock:
        """The runtime's clock (wall time, ns): stamp plans, judge freshness."""
        return self._rt.clock

    async def emit(self, name: str, message: Message | None = None) -> OutgoingEnvelope:
        """Emit event ``name`` in this cycle, caused by the triggering envelope. It is
        sealed now (with the knowledge versions written so far) and leaves when the
        handler returns (or at :meth:`flush`)."""
        rt = self._rt
        key = rt.event_keys.get(name) or rt.build_key(keys.event, name, rt.event_keys)
        return self._queue(key, message)

    async def publish(self, topic: str, message: Message) -> OutgoingEnvelope:
        """Publish on data topic ``topic`` in this cycle; it leaves as :meth:`emit`'s
        messages do."""
        rt = self._rt
        key = rt.data_keys.get(topic) or rt.build_key(keys.data, topic, rt.data_keys)
        return self._queue(key, message)

    def _queue(self, key: str, message: Message | None) -> OutgoingEnvelope:
        if self.sent is None:
            self.sent = [key]
        else:
            self.sent.append(key)
        env = self.envelope
        inherited, written = env.ctx, self.written
        ctx: dict[str, int] | None
        if written:
            ctx = {**inherited, **written} if inherited else dict(written)
        else:
            ctx = inherited or None
        out = self._rt.sealer.seal_out(key, message, cycle=self.cycle, cause=env.uid, ctx=ctx)
        if self._out is None:
            self._out = [(key, out)]
        else:
            self._out.append((key, out))
        return out.obj  # type: ignore[no-any-return]

    async def flush(self) -> None:
        """Send now what this handler emitted or published so far, instead of when it
        returns: for a handler that streams commands, or waits for an answer to what it
        sent. A traced call is then recorded as a ``start`` record (before these
        sends) and an ``end`` record (when it returns)."""
        await self._rt._flush(self)


class ContextKnowledge:
    """``ctx.kb``: the node's knowledge client, seen from one handler call.

    A read of a key named in the triggering envelope's ``ctx`` returns at least that
    version (it waits, at most until the client's timeout has passed since the trigger
    arrived, then asks the service, else raises ``KnowledgeError`` naming key and
    versions; a version whose writer is not alive is not waited for). Writes are
    remembered and carried, with what the trigger carried, in the ``ctx`` of what this
    handler emits. Each read and write is listed in
    the call's trace record when someone subscribes to the node's trace key."""

    __slots__ = ("_ctx",)

    def __init__(self, ctx: Context) -> None:
        self._ctx = ctx

    @property
    def client(self) -> KnowledgeClient:
        return self._ctx._rt.knowledge

    async def read(
        self,
        key: str,
        type: Any = None,
        *,
        default: Any = _MISSING,
        timeout: float | None = None,
    ) -> Any:
        ctx = self._ctx
        rt = ctx._rt
        rt.stats.kb_reads += 1
        client = rt._knowledge or self.client
        min_version = ctx.envelope.ctx.get(key, 0)
        value = client.value_here(key, type, min_version)  # most reads: no await
        if value is _MISSING:
            kw = {} if default is _MISSING else {"default": default}
            if timeout is None and ctx.deadline:
                timeout = max(0.0, ctx.deadline - time.monotonic())
            value = await client.read(key, type, min_version=min_version, timeout=timeout, **kw)
        if ctx.access is not None:
            ctx.access.append(
                Access("read", key, client.known_version(key), ctx._rt.clock.time_ns())
            )
        return value

    def _after_trigger(self) -> None:
        """A write in this handler happens after every write its trigger carries: the
        clock moves past them, so the new version orders after theirs (else a writer
        whose clock lags would lose to the very write that caused its own)."""
        versions = self._ctx.envelope.ctx
        if versions:
            self.client.clock.observe(max(versions.values()))

    async def write(
        self, key: str, value: Any, *, durable: bool = False, expect: int | None = None
    ) -> int:
        ctx = self._ctx
        rt = ctx._rt
        rt.stats.kb_writes += 1
        client = rt._knowledge or self.client
        versions = ctx.envelope.ctx
        if versions:  # see _after_trigger
            client.clock.observe(max(versions.values()))
        version = await client.write(key, value, durable=durable, expect=expect)
        if ctx.written is None:
            ctx.written = {}
        ctx.written[key] = version
        if ctx.access is not None:
            ctx.access.append(Access("write", key, version, ctx._rt.clock.time_ns()))
        return version

    async def delete(self, key: str, *, durable: bool = False, expect: int | None = None) -> int:
        ctx = self._ctx
        ctx._rt.stats.kb_writes += 1
        self._after_trigger()
        version = await self.client.delete(key, durable=durable, expect=expect)
        if ctx.written is None:
            ctx.written = {}
        ctx.written[key] = version
        if ctx.access is not None:
            ctx.access.append(Access("delete", key, version, ctx._rt.clock.time_ns()))
        return version


class NodeRuntime:
    """One node running on one fabric."""

    def __init__(
        self,
        node: Node,
        *,
        fabric: Fabric,
        system: str,
        clock: Clock | None = None,
        trace: bool = True,
        check_name: bool = True,
    ) -> None:
        """``check_name``: refuse to run when a node of this name is alive already
        (:func:`run_nodes` checks the whole group once instead)."""
        keys.system_pattern(system)  # validates the system name
        self._check_name = check_name
        self.node = node
        self.fabric = fabric
        self.system = system
        self.trace = trace
        self.clock: Clock = clock or SystemClock()
        self.sealer = Sealer(node.name, self.clock)
        self.opener = Opener(self.clock)
        self.stats = NodeStats()
        # one handler at a time: the consumer tasks of the routes and direct dispatch
        # (in a publisher's task) take the lock (asyncio's: no loop turn uncontended)
        self._lock = Turn()
        self._subs: list[Subscription] = []
        self.rejections = Rejections(node.name, log, clock=self.clock.time_ns)
        self._drop_log = Throttle()
        self._trace_key = keys.trace(system, node.name)
        self.after_call: Callable[[], None] | None = None
        """Called when a handler call has ended (the idle collector's ``poke``)."""
        self._tracing = (-1, False)
        """The fabric's epoch when last looked at, and whether the trace key had
        subscribers then."""
        self._log_key = keys.log(system, node.name)
        self._stopping: anyio.Event | None = None
        self._stop_requested = False
        self._knowledge: KnowledgeClient | None = None
        self._loop: asyncio.AbstractEventLoop | None = None
        """The loop ``run`` runs on (handle() may also be called without it, in tests)."""
        self._calling = 0
        self._inflight: set[Route] = set()
        """Routes whose consumer holds a sample it has taken from the inbox."""
        self.event_keys: dict[str, str] = {}
        self.data_keys: dict[str, str] = {}
        self._state = "new"
        self.latency = Latency()
        """Seconds its handler calls took (rap status, metrics)."""
        self.last_cycle = b""
        """The cycle of its last handler call."""
        self._last_end = 0.0
        """``perf_counter()`` when its last handler call ended (0: none yet)."""
        self.last_failed = False
        """Whether its last handler call raised."""
        self.compute_node = os.environ.get(NODE_ENV, "")
        """The compute node it runs on (in status replies): the runner's, else
        ``RAP_COMPUTE_NODE`` (rap up sets it for every process of a node)."""
        self.resume_state = False
        """At start, restore the node's latest snapshot from knowledge (when it has a
        restore hook and there is one): a restarted process resumes its state."""
        self.admin = True
        """Serve the admin verbs (rap_sdk.admin) while running."""
        self.started_at = 0
        self.restarts = 0
        self.swaps = 0
        self._routes: list[Route] = []
        """The route each consumer serves, by subscription (a swap replaces them)."""
        self._paused = False
        self._token: Any = None
        self._swapped: dict[int, tuple[Route, Route]] = {}
        """id of a route replaced by a swap -> (that route, its replacement): a consumer
        that took a sample before the swap hands it to the new implementation."""
        self.admin_lock = anyio.Lock()
        """Held by each admin verb: one at a time on a node."""

    def build_key(
        self,
        build: Callable[[str, str], str],
        name: str,
        cache: dict[str, str],
    ) -> str:
        """Build (and validate) a key once; handlers then reuse it from ``cache``."""
        key = build(self.system, name)
        if len(cache) < 4096:
            cache[name] = key
        return key

    @property
    def busy(self) -> bool:
        """A handler is running or a sample is queued."""
        return bool(self._calling) or any(len(sub.inbox) for sub in self._subs)  # type: ignore[attr-defined]

    @property
    def inbox_depth(self) -> int:
        """Samples queued in its inboxes now, all routes together (metrics)."""
        n = 0
        for sub in self._subs:
            n += len(sub.inbox)  # type: ignore[attr-defined]
        return n

    @property
    def sender_stats(self) -> SenderStats:
        return self.opener.stats

    def route_key(self, route: Route) -> str:
        return route.key(self.system)

    # -- sending -----------------------------------------------------------------------

    async def send(
        self,
        key: str,
        message: Message | None,
        *,
        cycle: bytes | None = None,
        cause: bytes | None = None,
        ctx: dict[str, int] | None = None,
    ) -> OutgoingEnvelope:
        """Seal and publish ``message`` on ``key`` (a full key from rap_schemas.keys). A
        local node whose FIFO inbox stays full for ``SEND_TIMEOUT`` s does not get it
        (counted in ``stats.send_timeouts``, logged); everyone else does."""
        out = self.sealer.seal_out(key, message, cycle=cycle, cause=cause, ctx=ctx)
        await self._send_out(key, out)
        return out.obj  # type: ignore[no-any-return]

    async def _send_out(self, key: str, out: Outgoing) -> None:
        try:
            await self.fabric.publish(key, out, timeout=SEND_TIMEOUT)
        except BackpressureTimeout:
            self._send_timed_out(key)
        self.stats.sent += 1

    def _send_timed_out(self, key: str) -> None:
        self.stats.send_timeouts += 1
        if self._drop_log.hit(f"send {key}"):
            log.warning(
                "node %s: a local node's inbox on %s stayed full for %g s: it did not get "
                "this sample (%d such sends in all); that node is slower than its input",
                self.node.name,
                key,
                SEND_TIMEOUT,
                self.stats.send_timeouts,
            )

    async def _flush(self, ctx: Context) -> None:
        """Send what ``ctx``'s handler queued; a traced call gets its ``start`` record
        first (once)."""
        if ctx.access is not None and ctx._route is not None:
            if not ctx._split:
                ctx._split = True
                access, ctx.access = ctx.access, []
                await self._trace(ctx._route, "start", ctx, ctx.started, access=access)
            elif ctx._starting is not None:
                await ctx._starting
        await self._send_queued(ctx)

    def _waited(self, ctx: Context) -> None:
        """The handler of a traced call gave the event loop a turn (it waits for
        something): its ``start`` record goes out now, so that a checker sees it
        started while it waits (two executions overlapping, a stage stuck)."""
        if ctx._split or ctx._route is None or ctx.access is None:
            return
        ctx._split = True
        access, ctx.access = ctx.access, []
        ctx._starting = asyncio.get_running_loop().create_task(
            self._trace(ctx._route, "start", ctx, ctx.started, access=access)
        )

    async def _send_queued(self, ctx: Context) -> None:
        out, ctx._out = ctx._out, None
        if not out:
            return
        for key, o in out[:-1]:
            o.direct = False  # only the last send may be handled in this task: a
            await self._send_out(key, o)  # handler that waits then holds up nothing
        key, o = out[-1]
        try:  # as _send_out, one frame fewer under every local handler it runs
            await self.fabric.publish(key, o, timeout=SEND_TIMEOUT)
        except BackpressureTimeout:
            self._send_timed_out(key)
        self.stats.sent += 1

    async def _trace(
        self,
        route: Route | Periodic,
        phase: str,
        ctx: Context,
        ts: int,
        duration: int = 0,
        error: str = "",
        access: list[Access] | None = None,
    ) -> None:
        env = ctx.envelope
        rec = StageTrace(
            node=self.node.name,
            stage=self.node.stage,
            handler=route.handler_name,
            phase=phase,  # type: ignore[arg-type]
            trigger=env.uid,
            trigger_key=ctx.key,
            cycle=ctx.cycle,
            ts=ts,
            duration_ns=duration,
            ok=not error,
            error=error,
            sent=(ctx.sent or []) if phase != "start" else [],
            access=access or [],
        )
        key = self._trace_key
        out = self.sealer.seal_out(key, rec, cycle=ctx.cycle, cause=env.uid)
        try:  # as _publish_record, one frame fewer
            await self.fabric.publish(key, out, timeout=RECORD_TIMEOUT)
        except RapError as exc:
            self._record_lost(key, exc)

    @property
    def knowledge(self) -> KnowledgeClient:
        if self._knowledge is None:
            raise LifecycleError(
                f"node {self.node.name!r} is not running: knowledge is "
                "available inside handlers of a running node"
            )
        return self._knowledge

    async def _publish_record(self, key: str, payload: bytes | Outgoing) -> None:
        """Publish a trace or rejection record. A record that cannot go out (fabric
        closing or failing, a subscriber's inbox full past the deadline) is counted in
        ``stats.records_lost`` and logged; it never stops the node nor hangs shutdown."""
        try:
            await self.fabric.publish(key, payload, timeout=RECORD_TIMEOUT)
        except RapError as exc:
            self._record_lost(key, exc)

    def _record_lost(self, key: str, exc: RapError) -> None:
        self.stats.records_lost += 1
        if self.stats.records_lost == 1 or self.stats.records_lost % 1000 == 0:
            log.warning(
                "node %s: %d record(s) on %s could not be published: %s",
                self.node.name,
                self.stats.records_lost,
                key,
                exc,
            )

    # -- receiving ---------------------------------------------------------------------

    async def _reject(self, key: str, reason: str, source: str = "", type_: str = "") -> None:
        self.stats.rejected += 1
        rec = self.rejections.reject(key, reason, source=source, type=type_)
        if rec is not None:
            payload, _ = self.sealer.seal_message(self._log_key, rec)
            await self._publish_record(self._log_key, payload)

    async def _publish_rejection(self, rec: Rejection) -> None:
        payload, _ = self.sealer.seal_message(self._log_key, rec)
        await self._publish_record(self._log_key, payload)

    async def _flush_rejections(self) -> None:
        for rec in self.rejections.flush():
            payload, _ = self.sealer.seal_message(self._log_key, rec)
            await self._publish_record(self._log_key, payload)

    def direct(self, route: Route, sub: Subscription, sample: Sample) -> Awaitable[None] | None:
        """The handling of a local ``sample`` to run at once in the publisher's task,
        when that keeps every guarantee of the inbox: the node runs no handler and its
        consumers hold no sample, nothing is queued on the route (order), the route is
        open, the message is a local object of the route's type that passes its check,
        and the knowledge versions it promises are here (no wait); nesting is bounded
        (``MAX_DIRECT_DEPTH``). None: the sample goes through the inbox."""
        inbox = sub.inbox  # type: ignore[attr-defined]
        if (
            self._calling
            or self._inflight
            or inbox._items
            or inbox._closed
            or _depth[0] >= MAX_DIRECT_DEPTH
            or self._lock.held
        ):
            return None
        env = sample.obj
        accepts = route.accepts
        if env is None or accepts is None or not accepts(env.body):
            return None
        if route.check is not None and route.check(env.body) is not None:
            return None  # the inbox path words the rejection
        kb = self._knowledge
        if kb is None or (env.ctx and not kb.has_versions(env.ctx)):
            return None
        # taken at once (no await between here and the call): nothing else may start on
        # this node until the call returns
        self._lock.held = True
        self._calling += 1
        _depth[0] += 1
        inbox.stats.accepted += 1
        self.stats.received += 1
        return self._call(route, Context(self, sample.key, env, env.body, 0.0), True)

    async def handle(self, route: Route, sample: Sample) -> None:
        """Open, check, decode and dispatch one sample to ``route``'s handler."""
        self.stats.received += 1
        try:
            env = sample.obj
            accepts = route.accepts
            if env is None or accepts is None or not accepts(env.body):
                # bytes from elsewhere (or a local object of another type: decoded from
                # its bytes, and rejected with the reason if it does not fit)
                if sample.size > route.max_bytes:
                    raise RejectedSample(
                        f"sample of {sample.size} bytes is over the route's limit of "
                        f"{route.max_bytes} (max_bytes= on the handler's decorator)"
                    )
                env = self.opener.open_typed(
                    sample.key, sample.payload, route.decode, route.msg_type.TYPE, sample.prepared
                )
                if env is None:
                    return  # duplicate, counted by the opener
            if route.check is not None:
                reason = route.check(env.body)
                if reason is not None:
                    raise RejectedSample(reason, source=env.source, type=env.type)
        except RejectedSample as exc:
            await self._reject(sample.key, exc.reason, exc.source, exc.type)
            return
        deadline = 0.0
        kb = self._knowledge
        if env.ctx and kb is not None:
            # wait for promised versions here, outside the node's lock: a version that is
            # late (or forged, and never comes) holds this route only, and only until the
            # client's timeout has passed since the sample arrived, however many such
            # samples are queued behind each other
            deadline = (sample.arrived or time.monotonic()) + kb.timeout
            await kb.await_versions(env.ctx, deadline)
        ctx = Context(self, sample.key, env, env.body, deadline)
        async with self._lock:
            if self._swapped:  # by identity: a Route's own hash walks its fields
                swapped = self._swapped.get(id(route))
                if swapped is not None:
                    route = swapped[1]
            await self._call(route, ctx)

    async def _call(self, route: Route | Periodic, ctx: Context, direct: bool = False) -> None:
        """Run ``route``'s handler on ``ctx``, trace it, send what it sent. ``direct``:
        :meth:`direct` took the node's turn for this call; it is given back at the end."""
        try:
            clock = self.clock
            # records nobody subscribes to are not built (decided once per call, from
            # what the fabric said while its subscriptions stay as they were)
            traced = False
            if self.trace and route.traced:
                fabric = self.fabric
                epoch, traced = self._tracing
                if epoch != fabric.epoch:
                    epoch = fabric.epoch
                    traced = fabric.has_subscribers(self._trace_key)
                    self._tracing = (epoch, traced)
            start = 0
            waited = None
            if traced:
                start = ctx.started = clock.time_ns()
                ctx.access = []
                ctx._route = route
                # runs only if the handler gives the loop a turn before it returns
                loop = self._loop or asyncio.get_running_loop()
                waited = loop.call_soon(self._waited, ctx)
            error = ""
            self._calling += 1
            t0 = perf_counter()
            try:
                if route.takes_message:
                    await route.fn(ctx, ctx.message)
                else:
                    await route.fn(ctx)
            except Exception as exc:  # a handler bug must not stop the node
                error = f"{type(exc).__name__}: {exc}"
                self._failed(route, ctx)
                self.last_failed = True
            else:
                self.stats.handled += 1
                self.last_failed = False
            finally:
                self._calling -= 1
                t1 = perf_counter()
                dt = t1 - t0
                lat = self.latency  # Latency.observe, inline
                lat.counts[bisect_left(LATENCY_BUCKETS, dt)] += 1
                lat.sum += dt
                lat.recent[lat.n & LATENCY_MASK] = dt
                lat.n += 1
                self.last_cycle = ctx.cycle
                self._last_end = t1
                if waited is not None:
                    waited.cancel()  # also when the call was cancelled
            if traced:
                end = clock.time_ns()
                if ctx._starting is not None:
                    await ctx._starting
                phase = "end" if ctx._split else "call"
                await self._trace(
                    route, phase, ctx, end if ctx._split else start, end - start, error, ctx.access
                )
            out = ctx._out
            if out:  # what it sent before it failed goes out too, as it was sent
                if len(out) == 1:  # as _send_queued, one frame fewer under what it runs
                    ctx._out = None
                    key, o = out[0]
                    try:
                        await self.fabric.publish(key, o, timeout=SEND_TIMEOUT)
                    except BackpressureTimeout:
                        self._send_timed_out(key)
                    self.stats.sent += 1
                else:
                    await self._send_queued(ctx)
        finally:
            if direct:
                _depth[0] -= 1
                self._calling -= 1
                turn = self._lock
                if turn._waiters:
                    turn.release()
                else:
                    turn.held = False
            if self.after_call is not None:
                self.after_call()

    def _failed(self, route: Route | Periodic, ctx: Context) -> None:
        """Count a handler's failure and log its traceback (at once, then at most one a
        second per handler with a count: a poisoned input can make every call fail)."""
        self.stats.failed += 1
        count = self._drop_log.hit(f"failed {route.handler_name}")
        if count:
            log.exception(
                "node %s: handler %s failed on %s (%d failure(s) since the last report, %d in all)",
                self.node.name,
                route.handler_name,
                ctx.key,
                count,
                self.stats.failed,
            )

    # -- lifecycle ---------------------------------------------------------------------

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Declare the node's subscriptions and liveliness token, report ready, and
        consume until :meth:`stop`; what was queued before ``stop`` is still handled."""
        if self._state != "new":
            raise LifecycleError(
                f"node {self.node.name!r} runtime is {self._state}; a runtime runs once"
            )
        self._state = "running"
        self._loop = asyncio.get_running_loop()
        self._stopping = anyio.Event()
        if self._stop_requested:
            self._stopping.set()
        self._token = admin = None
        alive_key = keys.alive(self.system, self.node.name)
        if self._check_name:
            try:
                await refuse_running(fabric=self.fabric, system=self.system, names=[self.node.name])
            except LifecycleError:
                self._state = "stopped"
                raise
        try:
            async with (
                KnowledgeClient(
                    fabric=self.fabric, system=self.system, writer=self.node.name
                ) as kb,
                anyio.create_task_group() as tg,
            ):
                self._knowledge = kb
                kb.on_rejection = self._publish_rejection
                if self.resume_state:
                    from .admin import resume_from_knowledge

                    await resume_from_knowledge(self, kb)
                for i, route in enumerate(self.node.routes):
                    sub = self.fabric.subscribe(
                        self.route_key(route), route.policy, prepare=route.decode
                    )
                    if hasattr(sub, "direct") and route.accepts is not None:
                        sub.direct = partial(self.direct, route, sub)
                    self._subs.append(sub)
                    self._routes.append(route)
                    tg.start_soon(self._consume, i, sub)
                if self.admin:
                    from .admin import serve_admin

                    admin = serve_admin(self)
                # the token comes after the subscriptions: declarations on a link keep
                # their order, so a peer that sees the token can already reach the node
                token = self._token = self.fabric.declare_token(alive_key)
                self.started_at = time.time_ns()
                for periodic in self.node.periodic:
                    tg.start_soon(self._every, periodic.name)
                task_status.started()
                await self._stopping.wait()
                for sub in self._subs:  # stop() may have come before they existed
                    sub.close()
                # consumers now drain what their closed inboxes still hold, then end
        finally:
            with anyio.CancelScope(shield=True):
                await self._flush_rejections()
            if admin is not None:
                admin.undeclare()
            token = self._token
            if token is not None:
                token.undeclare()
            for sub in self._subs:
                sub.close()
            self._state = "stopped"

    async def _consume(self, i: int, sub: Subscription) -> None:
        get, handle = sub.inbox.get, self.handle  # type: ignore[attr-defined]
        inflight = self._inflight
        routes = self._routes  # a swap replaces routes[i] in place
        stats = sub.stats
        counted = 0
        while True:
            try:
                sample = await get()
            except LifecycleError:  # closed and drained
                self._dropped(routes[i], stats.dropped - counted)
                return
            route = routes[i]
            if stats.dropped != counted:
                self._dropped(route, stats.dropped - counted)
                counted = stats.dropped
            inflight.add(route)
            try:
                await handle(route, sample)
            finally:
                inflight.discard(route)

    async def _every(self, name: str) -> None:
        """The timer of periodic handler ``name``: a call one period after the start,
        then one on every tick of that grid, until the node stops. A call waits for the
        node's turn; the ticks whose time passed before the call (with that wait) ended
        are skipped and counted. The handler is looked up at each tick (a swap may have
        replaced it, and its period)."""
        stopping = self._stopping
        if stopping is None:
            return
        now = anyio.current_time
        found = self._periodic(name)
        if found is None:
            return
        due = now() + found.period
        seq = 0
        while True:
            with anyio.CancelScope(deadline=due):
                await stopping.wait()
            if stopping.is_set():
                return
            periodic = self._periodic(name)
            if periodic is None:
                return
            async with self._lock:
                if self._stop_requested:
                    return
                self.stats.ticks += 1
                await self._call(periodic, self._tick_context(periodic, seq))
            seq += 1
            due += periodic.period
            late = now() - due
            if late > 0:
                missed = math.ceil(late / periodic.period)
                due += missed * periodic.period
                self._skipped(periodic, missed)

    def _periodic(self, name: str) -> Periodic | None:
        return next((p for p in self.node.periodic if p.name == name), None)

    def _tick_context(self, periodic: Periodic, seq: int) -> Context:
        """A tick's context: a synthetic trigger (uid, time, an empty body) that no
        fabric carried; what the handler sends starts a cycle of its own."""
        ts = self.clock.time_ns()
        body = Empty()
        env: TypedEnvelope[Any] = TypedEnvelope(
            uid=new_uid.at(ts), ts=ts, source=self.node.name, seq=seq, type=Empty.TYPE, body=body
        )
        return Context(self, periodic.trigger(self.node.name), env, body)

    def _skipped(self, periodic: Periodic, n: int) -> None:
        """Ticks a periodic handler missed: counted, and said (at most once a second)."""
        self.stats.ticks_skipped += n
        count = self._drop_log.hit(f"every {periodic.name}")
        if count:
            log.warning(
                "node %s: periodic handler %s (every %g s) overran its period %d time(s) "
                "since the last report (%d tick(s) skipped in all): the call, or its wait "
                "for the node's turn, took longer than the period; make it faster or give "
                "it a longer period",
                self.node.name,
                periodic.handler_name,
                periodic.period,
                count,
                self.stats.ticks_skipped,
            )

    def _dropped(self, route: Route, n: int) -> None:
        """Samples an inbox dropped: counted, and said (at most once a second a route)."""
        if n <= 0:
            return
        self.stats.dropped += n
        key = self.route_key(route)
        count = self._drop_log.hit(key)
        if count:
            p = route.policy
            log.warning(
                "node %s dropped samples on %s (%d in all): its inbox (%s, capacity %d) was "
                "full, the handler %s is slower than they arrive; raise the capacity "
                "(policy=InboxPolicy(...)) or make the handler faster",
                self.node.name,
                key,
                self.stats.dropped,
                p.overflow.value,
                p.capacity,
                route.handler_name,
            )

    # -- administration (rap_sdk.admin serves these as verbs) ------------------------------

    @property
    def last_call(self) -> int:
        """When its last handler call ended, UTC ns (0: none yet)."""
        if not self._last_end:
            return 0
        return time.time_ns() - int((perf_counter() - self._last_end) * 1e9)

    @property
    def paused(self) -> bool:
        return self._paused

    @asynccontextmanager
    async def exclusive(self) -> AsyncIterator[None]:
        """A block in which no handler of the node runs (the running one has returned;
        what arrives meanwhile waits in the inboxes). A paused node's handlers do not
        run already."""
        if self._paused:
            yield
            return
        await self._lock.__aenter__()
        try:
            yield
        finally:
            self._lock.release()

    async def pause(self) -> bool:
        """Let the running handler finish, then run none until :meth:`resume`: input
        waits in the inboxes under their policies (``rap_schemas.admin.PAUSE_POLICY``).
        False when it was paused already."""
        if self._paused:
            return False
        await self._lock.__aenter__()
        if self._stop_requested:
            self._lock.release()
            raise LifecycleError(f"node {self.node.name!r} is stopping; it cannot pause")
        self._paused = True
        return True

    def resume(self) -> bool:
        """Handle what waited, in order, and what comes. False when it was not paused."""
        if not self._paused:
            return False
        self._paused = False
        self._lock.release()
        return True

    def match_routes(self, new: Node) -> list[Route]:
        """``new``'s routes in the order of the running ones; :class:`ConfigError` when
        ``new`` does not handle exactly the same inputs with the same message types, or
        is of another stage."""
        if new.stage != self.node.stage:
            raise ConfigError(
                f"the new implementation is of stage {new.stage.value if new.stage else None!r}"
                f", the component runs {self.node.stage.value if self.node.stage else None!r}: "
                "a swap keeps the stage"
            )
        theirs = {(r.kind, r.name): r for r in new.routes}
        ours = {(r.kind, r.name): r for r in self._routes}
        problems = [f"it does not handle {k}/{n}" for k, n in ours if (k, n) not in theirs]
        problems += [
            f"it handles {k}/{n}, which the running one does not"
            for k, n in theirs
            if (k, n) not in ours
        ]
        ticking = {p.name for p in self.node.periodic}
        new_ticking = {p.name for p in new.periodic}
        problems += [f"it has no periodic handler {n!r}" for n in sorted(ticking - new_ticking)]
        problems += [
            f"it has a periodic handler {n!r}, which the running one does not"
            for n in sorted(new_ticking - ticking)
        ]
        for key, r in ours.items():
            t = theirs.get(key)
            if t is not None and t.msg_type.TYPE != r.msg_type.TYPE:
                problems.append(f"{key[0]}/{key[1]} takes {t.msg_type.TYPE}, not {r.msg_type.TYPE}")
        if problems:
            raise ConfigError(
                "the new implementation does not fit the running component: "
                + "; ".join(problems)
                + " (a swap keeps the inputs; change the model and restart to change them)"
            )
        return [theirs[(r.kind, r.name)] for r in self._routes]

    def _install(self, new: Node, state: bytes) -> None:
        """Put ``new`` in the old node's place (the caller holds :meth:`exclusive`):
        its config carried over, ``state`` restored into it, its routes taking the
        running ones' inboxes. Raises :class:`ConfigError` with nothing changed."""
        old = self.node
        routes = self.match_routes(new)
        if old.config is not None and new.config is not None:
            carried = {
                k: v
                for k, v in msgspec.to_builtins(old.config).items()
                if k in type(new.config).__struct_fields__
            }
            new.configure(carried)
        new.restore(state)
        if new.name != old.name:
            log.info(
                "node %s: the new implementation's Node is named %r; it runs as %s",
                old.name,
                new.name,
                old.name,
            )
            new.name = old.name
        for i, (sub, route) in enumerate(zip(self._subs, routes, strict=True)):
            prev = self._routes[i]
            for k, (old_route, replacement) in list(self._swapped.items()):
                if replacement is prev:
                    self._swapped[k] = (old_route, route)
            self._swapped[id(prev)] = (prev, route)
            self._routes[i] = route
            if hasattr(sub, "direct"):  # never left pointing at the old route
                sub.direct = partial(self.direct, route, sub) if route.accepts else None
        self.node = new

    async def swap(self, new: Node) -> None:
        """Replace the node's implementation in the running process: no handler runs
        while its state is taken and restored into ``new``; what arrives meanwhile
        waits in the inboxes and is handled by ``new`` (nothing lost, nothing twice)."""
        if new is self.node:
            raise ConfigError("the component runs that implementation already")
        self.match_routes(new)  # refused before anything waits
        async with self.exclusive():
            self._install(new, self.node.snapshot())
            self.swaps += 1

    async def restart(self, fresh: Node | None, state: bytes | None) -> None:
        """Restart the component in this process: its liveliness token goes down, it
        is replaced by ``fresh`` (None: the same Node object), ``state`` (None: the
        state it had) is restored, and its token comes back. Input waits meanwhile."""
        async with self.exclusive():
            if self._token is not None:
                self._token.undeclare()
                self._token = None
            try:
                current = self.node.snapshot() if state is None else state
                if fresh is not None and fresh is not self.node:
                    self._install(fresh, current)
                elif state is not None:
                    self.node.restore(state)
            finally:
                self._token = self.fabric.declare_token(keys.alive(self.system, self.node.name))
            self.restarts += 1
            self.last_failed = False

    def stop(self) -> None:
        """Stop taking new samples; queued ones are still handled, then ``run`` returns."""
        self._stop_requested = True
        if self._paused:  # what waited is handled, as for a running node
            self._paused = False
            self._lock.release()
        for sub in self._subs:
            sub.close()
        if self._stopping is not None:
            self._stopping.set()


async def refuse_running(*, fabric: Fabric, system: str, names: Sequence[str]) -> None:
    """Raise :class:`LifecycleError` when a node of one of ``names`` is already alive in
    ``system`` (a second one would handle every sample again)."""
    up = {
        keys.parse(k).name for k in await fabric.alive(keys.pattern(system, keys.Kind.ALIVE, "*"))
    }
    taken = [n for n in names if n in up]
    if taken:
        raise LifecycleError(
            f"node {taken[0]!r} is already running in system {system!r} (its liveliness "
            "token is up): a second one would handle every sample again; stop the other, "
            "or give this one another name or system"
        )


class NodeGroup:
    """Several node runtimes sharing one task group."""

    def __init__(self, runtimes: Sequence[NodeRuntime]) -> None:
        self.runtimes = list(runtimes)
        self.collector: IdleCollector | None = None
        """The garbage collector of ``run_nodes(gc_idle=True)``."""

    def __getitem__(self, name: str) -> NodeRuntime:
        for rt in self.runtimes:
            if rt.node.name == name:
                return rt
        raise KeyError(f"no node {name!r}; running: {[r.node.name for r in self.runtimes]}")

    def stop(self) -> None:
        for rt in self.runtimes:
            rt.stop()
        if self.collector is not None:
            self.collector.stop()


@asynccontextmanager
async def run_nodes(
    nodes: Sequence[Node],
    *,
    fabric: Fabric,
    system: str,
    clock: Clock | None = None,
    trace: bool = True,
    grace: float = 5.0,
    gc_idle: bool = False,
    compute_node: str = "",
    resume_state: bool = False,
) -> AsyncIterator[NodeGroup]:
    """Run ``nodes`` on ``fabric`` until the block exits; every node is subscribed when
    the block starts. On exit, nodes stop taking input, handle what is queued (within
    ``grace`` s), then are cancelled. ``gc_idle``: collect garbage only while the nodes
    are idle (:class:`rap_sdk.gc.IdleCollector`; for a process that runs a loop).
    ``compute_node``: named in the nodes' status replies. ``resume_state``: each node
    with a restore hook resumes from its latest snapshot in knowledge, if one is kept."""
    names = [n.name for n in nodes]
    if len(set(names)) != len(names):
        raise LifecycleError(f"node names must be unique within a group: {names}")
    group = NodeGroup(
        [
            NodeRuntime(n, fabric=fabric, system=system, clock=clock, trace=trace, check_name=False)
            for n in nodes
        ]
    )
    for rt in group.runtimes:
        rt.compute_node = compute_node or rt.compute_node
        rt.resume_state = resume_state
    # before the task group, so that the error comes plain
    await refuse_running(fabric=fabric, system=system, names=names)
    async with anyio.create_task_group() as tg:
        for rt in group.runtimes:
            await tg.start(rt.run)
        if gc_idle:
            group.collector = IdleCollector(lambda: any(rt.busy for rt in group.runtimes))
            await tg.start(group.collector.run)
            for rt in group.runtimes:
                rt.after_call = group.collector.poke
        try:
            yield group
        finally:
            group.stop()
            tg.cancel_scope.deadline = anyio.current_time() + grace


async def await_alive(names: set[str], *, fabric: Fabric, system: str, timeout: float) -> None:
    """Wait until a liveliness token is up for each node in ``names`` (a node declares
    its token after its subscriptions: once seen, the node is reachable). Raises
    ``TimeoutError`` naming the nodes still missing after ``timeout`` s."""
    missing = set(names)
    with fabric.watch_liveliness(keys.pattern(system, keys.Kind.ALIVE)) as watch:
        try:
            with anyio.fail_after(timeout):
                while missing:
                    change = await watch.get()
                    if change.alive:
                        missing.discard(keys.parse(change.key).name)
        except TimeoutError:
            raise TimeoutError(f"nodes {sorted(missing)} not alive within {timeout} s") from None


async def serve(nodes: Sequence[Node], *, fabric: Fabric, system: str, grace: float = 5.0) -> None:
    """Run ``nodes`` until SIGTERM or SIGINT, then stop gracefully."""
    with anyio.open_signal_receiver(signal.SIGTERM, signal.SIGINT) as signals:
        async with run_nodes(nodes, fabric=fabric, system=system, grace=grace):
            async for signum in signals:
                log.info(
                    "received %s; stopping %d node(s)", signal.Signals(signum).name, len(nodes)
                )
                break

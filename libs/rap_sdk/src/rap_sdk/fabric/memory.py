"""MemoryFabric: an in-process, deterministic fabric for tests.

Several MemoryFabrics on one :class:`MemoryBus` behave like several processes on one
network: a sample published on one reaches its own subscribers directly (with
backpressure) and the others' as remote samples (never waiting), once each. Delivery is
immediate and in order, within the publishing call, so tests need no sleeps.
"""

from __future__ import annotations

import itertools
from time import monotonic
from types import TracebackType

import anyio

from ..errors import FabricError, LifecycleError, QueryError
from ..inbox import InboxPolicy
from ..keyexpr import intersects, validate
from ._local import (
    DEFAULT_POLICY,
    InboxStream,
    Lifecycle,
    LocalSubscription,
    Router,
    answer,
    liveliness_stream,
)
from ._types import (
    LivelinessChange,
    Outgoing,
    Prepare,
    QueryHandler,
    QueryRequest,
    Reply,
    Sample,
)

__all__ = ["MemoryBus", "MemoryFabric"]

_ids = itertools.count(1)


class MemoryBus:
    """The shared medium of several MemoryFabrics."""

    def __init__(self) -> None:
        self.members: list[MemoryFabric] = []
        self.tokens: dict[str, int] = {}
        self.watches: list[tuple[str, InboxStream[LivelinessChange]]] = []
        self.queryables: list[_MemQueryable] = []
        self._changed: anyio.Event | None = None
        self.epoch = 0
        """Counts changes of members and subscriptions (cached matches are redone)."""

    def bump(self) -> None:
        """A member or a subscription changed: every member's ``epoch`` moves."""
        self.epoch += 1
        for m in self.members:
            m.epoch = self.epoch

    async def wait_changed(self) -> None:
        """Wait for the next subscription or queryable on the bus."""
        if self._changed is None:
            self._changed = anyio.Event()
        await self._changed.wait()

    def notify(self) -> None:
        if self._changed is not None:
            self._changed.set()
            self._changed = None

    def token_changed(self, key: str, delta: int) -> None:
        before = self.tokens.get(key, 0)
        after = before + delta
        if after:
            self.tokens[key] = after
        else:
            self.tokens.pop(key, None)
        if (before == 0) != (after == 0):
            for expr, stream in self.watches:
                if intersects(expr, key):
                    stream.inbox.offer(LivelinessChange(key, after > 0))


class _MemToken:
    def __init__(self, fabric: MemoryFabric, key: str) -> None:
        self.key = key
        self._fabric: MemoryFabric | None = fabric

    def undeclare(self) -> None:
        if self._fabric is not None:
            self._fabric._tokens.remove(self)
            self._fabric.bus.token_changed(self.key, -1)
            self._fabric = None


class _MemQueryable:
    def __init__(self, fabric: MemoryFabric, key_expr: str, handler: QueryHandler) -> None:
        self.key_expr = key_expr
        self.handler = handler
        self._fabric: MemoryFabric | None = fabric

    def undeclare(self) -> None:
        if self._fabric is not None:
            self._fabric.bus.queryables.remove(self)
            self._fabric._queryables.remove(self)
            self._fabric = None


class MemoryFabric:
    def __init__(
        self,
        *,
        bus: MemoryBus | None = None,
        query_handler_timeout: float = 5.0,
    ) -> None:
        self.bus = bus if bus is not None else MemoryBus()
        self._id = f"mem-{next(_ids)}"
        self._router = Router()
        self._life = Lifecycle("MemoryFabric")
        self._tokens: list[_MemToken] = []
        self._queryables: list[_MemQueryable] = []
        self._watches: list[InboxStream[LivelinessChange]] = []
        self._handler_timeout = query_handler_timeout
        self._published: set[str] = set()
        """Keys already validated by publish()."""
        self._epoch = -1
        self.epoch = -1
        """The bus's epoch (see :meth:`Fabric.epoch`), kept here by the bus."""
        self._others: list[MemoryFabric] = []
        self._has: dict[str, bool] = {}
        self._has_remote: dict[str, bool] = {}

    def _refresh(self) -> None:
        """Redo what is cached from the bus (its members or a subscription changed)."""
        self._epoch = self.bus.epoch
        self._others = [m for m in self.bus.members if m is not self]
        self._has.clear()
        self._has_remote.clear()

    @property
    def id(self) -> str:
        return self._id

    async def __aenter__(self) -> MemoryFabric:
        await self._life.open()
        self.bus.members.append(self)
        self.bus.bump()
        return self

    async def __aexit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        if not self._life.is_open:
            return
        for tok in list(self._tokens):
            tok.undeclare()
        for q in list(self._queryables):
            q.undeclare()
        self._router.close_all()
        for w in list(self._watches):
            w.close()
        self.bus.members.remove(self)
        self.bus.bump()
        await self._life.close(et, ev, tb)

    async def publish(
        self,
        key: str,
        payload: bytes | Outgoing,
        *,
        timeout: float | None = None,
        local: bool = True,
    ) -> None:
        if not self._life.is_open:
            self._life.check_open()
        if key not in self._published:
            validate(key)
            if "*" in key:
                raise FabricError(
                    f"cannot publish on a wildcard expression {key!r}; use a "
                    "concrete key built by rap_schemas.keys"
                )
            if len(self._published) < 4096:
                self._published.add(key)
        # other "processes" first (they get bytes, as over a network): a local
        # subscriber may handle the sample in this task at once, and what it sends must
        # not reach them before the sample itself
        if self._epoch != self.bus.epoch:
            self._refresh()
        for member in self._others:
            for sub in member._router.matching(key):
                data = payload.data if isinstance(payload, Outgoing) else payload
                sub.inbox.offer(sub.sample(key, data, True))
        router = self._router
        subs = (router.cached(key) or router.matching(key)) if local else ()
        if subs:
            late = await router.deliver(subs, key, payload, timeout)
            if late is not None:
                raise late

    def has_subscribers(self, key: str, *, remote_only: bool = False) -> bool:
        if not self._life.is_open:
            self._life.check_open()
        if self._epoch != self.bus.epoch:
            self._refresh()
        cache = self._has_remote if remote_only else self._has
        hit = cache.get(key)
        if hit is None:
            hit = any(m._router.matching(key) for m in self._others) or (
                not remote_only and bool(self._router.matching(key))
            )
            if len(cache) < 4096:
                cache[key] = hit
        return hit

    def local_subscribers(self, key: str) -> tuple[LocalSubscription, ...]:
        if not self._life.is_open:
            self._life.check_open()
        return self._router.matching(key)

    def subscribe(
        self,
        key_expr: str,
        policy: InboxPolicy | None = None,
        *,
        prepare: Prepare | None = None,
        group: object = None,
    ) -> LocalSubscription:
        self._life.check_open()
        validate(key_expr)

        def closed(s: InboxStream[Sample]) -> None:
            assert isinstance(s, LocalSubscription)
            self._router.remove(s)
            self.bus.bump()

        sub = LocalSubscription(key_expr, policy or DEFAULT_POLICY, closed, prepare, group)
        self._router.add(sub)
        self.bus.bump()
        self.bus.notify()
        return sub

    def serve(self, key_expr: str, handler: QueryHandler) -> _MemQueryable:
        self._life.check_open()
        validate(key_expr)
        q = _MemQueryable(self, key_expr, handler)
        self.bus.queryables.append(q)
        self._queryables.append(q)
        self.bus.notify()
        return q

    async def wait_matched(
        self, key: str, *, queryable: bool = False, timeout: float = 5.0
    ) -> None:
        """Wait until another fabric on the bus has a subscriber (or queryable) matching
        ``key``."""
        self._life.check_open()
        validate(key)

        def matched() -> bool:
            if queryable:
                return any(
                    intersects(q.key_expr, key)
                    for q in self.bus.queryables
                    if q._fabric is not self
                )
            return any(m._router.matching(key) for m in self.bus.members if m is not self)

        try:
            with anyio.fail_after(timeout):
                while not matched():
                    await self.bus.wait_changed()
        except TimeoutError:
            what = "queryable" if queryable else "subscriber"
            raise FabricError(
                f"no other fabric on the bus has a {what} matching {key!r} after {timeout} s"
            ) from None

    async def query(
        self,
        selector: str,
        payload: bytes = b"",
        *,
        timeout: float = 2.0,
        partial: bool = False,
        attachment: bytes = b"",
    ) -> list[Reply]:
        self._life.check_open()
        key, _, params = selector.partition("?")
        validate(key)
        targets = [q for q in self.bus.queryables if intersects(q.key_expr, key)]
        replies: list[Reply] = []
        try:
            with anyio.fail_after(timeout):
                for q in targets:
                    replies += await answer(
                        q.handler,
                        QueryRequest(key, params, payload, monotonic(), attachment),
                        self._handler_timeout,
                    )
        except TimeoutError:
            if partial:  # what came in time (a wildcard query: the quick answerers)
                return list(replies)
            raise QueryError(
                f"query {selector!r} got no complete answer within {timeout} s"
            ) from None
        return replies

    def declare_token(self, key: str) -> _MemToken:
        self._life.check_open()
        validate(key)
        if "*" in key:
            raise LifecycleError(f"a liveliness token needs a concrete key, got {key!r}")
        tok = _MemToken(self, key)
        self._tokens.append(tok)
        self.bus.token_changed(key, +1)
        return tok

    async def alive(self, key_expr: str, *, timeout: float = 2.0) -> list[str]:
        self._life.check_open()
        validate(key_expr)
        return sorted(k for k in self.bus.tokens if intersects(key_expr, k))

    def watch_liveliness(
        self,
        key_expr: str,
        *,
        capacity: int = 256,
    ) -> InboxStream[LivelinessChange]:
        self._life.check_open()
        validate(key_expr)

        def closed(stream: InboxStream[LivelinessChange]) -> None:
            self.bus.watches[:] = [(e, s) for e, s in self.bus.watches if s is not stream]
            if stream in self._watches:
                self._watches.remove(stream)

        stream = liveliness_stream(capacity, closed)
        for key in sorted(self.bus.tokens):
            if intersects(key_expr, key):
                stream.inbox.offer(LivelinessChange(key, True))
        self.bus.watches.append((key_expr, stream))
        self._watches.append(stream)
        return stream

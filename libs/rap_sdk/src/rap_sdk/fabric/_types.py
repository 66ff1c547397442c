"""The Fabric protocol and the values that cross it."""

from __future__ import annotations

from collections.abc import AsyncIterator, Awaitable, Callable, Iterable, Sequence
from dataclasses import dataclass
from types import TracebackType
from typing import Any, Protocol, Self, runtime_checkable

from ..inbox import InboxPolicy, InboxStats

__all__ = [
    "Fabric",
    "FabricStats",
    "LivelinessChange",
    "LivelinessWatch",
    "Outgoing",
    "Prepare",
    "QueryHandler",
    "QueryRequest",
    "Queryable",
    "Reply",
    "Sample",
    "Subscription",
    "Token",
]


class Outgoing:
    """A message on its way out: the sender's envelope object and its encoding, made at
    most once, when first needed (a subscriber in another process, or a local one that
    reads the bytes). Local subscribers may receive the object itself: it is shared,
    so it must never be modified (RAP's messages are frozen Structs)."""

    __slots__ = ("_data", "_encode", "direct", "group", "obj")

    def __init__(self, obj: Any, encode: Callable[[Any], bytes], group: object = None) -> None:
        self.obj = obj
        self._encode = encode
        self._data: bytes | None = None
        self.group = group
        """Local subscriptions made with this ``group`` do not get the sample: their
        owners were handed it directly by the publisher (knowledge replicas)."""
        self.direct = True
        """Whether a local subscriber may handle it in the publisher's task (direct
        dispatch); a node's runtime allows it only for the last of a handler's sends."""

    @property
    def encoded(self) -> bool:
        """Whether the bytes have been made."""
        return self._data is not None

    @property
    def data(self) -> bytes:
        data = self._data
        if data is None:
            data = self._data = self._encode(self.obj)
        return data


class Sample:
    """One sample as a subscriber sees it."""

    __slots__ = ("_out", "_payload", "arrived", "key", "obj", "prepared", "remote")

    def __init__(
        self,
        key: str,
        payload: bytes | Outgoing,
        remote: bool = False,
        prepared: Any = None,
        arrived: float = 0.0,
    ) -> None:
        self.key = key
        if type(payload) is Outgoing:
            self._out: Outgoing | None = payload
            self._payload: bytes | None = None
            self.obj: Any = payload.obj
            """For a sample published in this process: the sender's envelope object
            (shared: never modify it); None for a sample that came as bytes."""
        else:
            self._out = None
            self._payload = payload  # type: ignore[assignment]
            self.obj = None
        self.remote = remote
        """True when the sample came from another session (process)."""
        self.prepared = prepared
        """What the subscription's ``prepare`` function made of the payload, when it
        has run (on the transport thread, while the loop wakes up) and succeeded; else
        None."""
        self.arrived = arrived
        """``time.monotonic()`` when the sample reached this process (0: unknown).
        Deadlines of the handling (a causal read's wait) count from here, not from when
        a queued sample's turn comes."""

    @property
    def payload(self) -> bytes:
        """The encoded envelope (for a local sample made now if nobody needed it yet,
        once for every subscriber)."""
        data = self._payload
        if data is None:
            assert self._out is not None
            data = self._payload = self._out.data
        return data

    @property
    def size(self) -> int:
        """The payload's length when it is bytes already; 0 for a local object not
        encoded (it takes no buffer of its own: the sender holds it)."""
        data = self._payload
        return len(data) if data is not None else 0

    def __repr__(self) -> str:
        return f"Sample(key={self.key!r}, remote={self.remote}, size={self.size})"


@dataclass(frozen=True, slots=True)
class QueryRequest:
    key: str
    """The key expression of the query (may hold wildcards)."""
    parameters: str
    payload: bytes
    arrived: float = 0.0
    """``time.monotonic()`` when the query reached this process (0: unknown)."""
    attachment: bytes = b""
    """What the querier attached beside the payload (b"": nothing), e.g. a signature
    (``rap_sdk.identity``)."""


@dataclass(frozen=True, slots=True)
class Reply:
    key: str
    payload: bytes
    ok: bool = True
    """False for an error reply; ``payload`` then holds the UTF-8 reason."""


@dataclass(slots=True)
class FabricStats:
    """What happened to the fabric's links to other processes (ZenohFabric)."""

    links_up: int = 0
    links_down: int = 0
    reconnects: int = 0
    """Links that came up to a peer this fabric had been linked to before."""


@dataclass(frozen=True, slots=True)
class LivelinessChange:
    key: str
    alive: bool


QueryHandler = Callable[[QueryRequest], Awaitable[Iterable[Reply]]]
Prepare = Callable[[bytes], Any]


class Subscription(Protocol):
    key_expr: str
    group: object
    """The ``group`` it was made with (see :meth:`Fabric.subscribe`)."""

    @property
    def stats(self) -> InboxStats: ...
    def __aiter__(self) -> AsyncIterator[Sample]: ...
    async def get(self) -> Sample: ...
    def get_nowait(self) -> Sample | None: ...
    def close(self) -> None: ...
    def __enter__(self) -> Self: ...
    def __exit__(self, *exc: object) -> None: ...


class LivelinessWatch(Protocol):
    def __aiter__(self) -> AsyncIterator[LivelinessChange]: ...
    async def get(self) -> LivelinessChange: ...
    def close(self) -> None: ...
    def __enter__(self) -> Self: ...
    def __exit__(self, *exc: object) -> None: ...


class Token(Protocol):
    key: str

    def undeclare(self) -> None: ...


class Queryable(Protocol):
    key_expr: str

    def undeclare(self) -> None: ...


@runtime_checkable
class Fabric(Protocol):
    """What RAP needs from a data fabric. Two implementations pass one contract suite:
    :class:`~rap_sdk.fabric.ZenohFabric` and :class:`~rap_sdk.fabric.MemoryFabric`.

    Open it with ``async with``; every method but ``publish``/``query`` is synchronous
    and cheap. Samples published here reach subscribers of this fabric directly (no
    network path) and subscribers elsewhere once.
    """

    @property
    def id(self) -> str: ...

    async def __aenter__(self) -> Self: ...

    async def __aexit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None: ...

    async def publish(
        self,
        key: str,
        payload: bytes | Outgoing,
        *,
        timeout: float | None = None,
        local: bool = True,
    ) -> None:
        """Deliver ``payload`` on ``key``. Local FIFO inboxes with ``block`` make this
        wait for room (at most ``timeout`` s). ``local=False``: other processes only.
        An :class:`Outgoing` reaches local subscribers as the object itself
        (``Sample.obj``) and is encoded once, only if a remote subscriber or a local
        reader of ``Sample.payload`` needs the bytes."""

    def subscribe(
        self,
        key_expr: str,
        policy: InboxPolicy | None = None,
        *,
        prepare: Prepare | None = None,
        group: object = None,
    ) -> Subscription:
        """Subscribe with a bounded inbox. ``prepare(payload)`` (a pure function such as
        a msgspec decoder) is applied to each sample before the consumer sees it and
        the result put in ``Sample.prepared``; for samples from other processes it runs
        on the transport thread after the hand-off, overlapping the loop's wake-up. A
        consumer must accept ``prepared is None`` (not run yet, or it raised) and do the
        work itself. ``group``: local publishes of an :class:`Outgoing` of the same
        group skip this subscription (its owner got them from the publisher directly)."""

    def has_subscribers(self, key: str, *, remote_only: bool = False) -> bool:
        """Whether a subscriber here or elsewhere (``remote_only``: elsewhere) matches
        ``key`` now (publishers may skip building samples nobody would receive)."""

    @property
    def epoch(self) -> int:
        """A number that changes whenever the subscribers matching some key may have
        changed, here or elsewhere: what a caller concluded from
        :meth:`has_subscribers` or :meth:`local_subscribers` holds while it is the
        same."""

    def local_subscribers(self, key: str) -> Sequence[Subscription]:
        """This session's own subscriptions that match ``key`` now. A caller that
        caches what it concludes from them keys the cache on :attr:`epoch`."""

    def serve(self, key_expr: str, handler: QueryHandler) -> Queryable: ...

    async def wait_matched(
        self, key: str, *, queryable: bool = False, timeout: float = 5.0
    ) -> None:
        """Wait until another session has a subscriber (or queryable) matching ``key``."""

    async def query(
        self,
        selector: str,
        payload: bytes = b"",
        *,
        timeout: float = 2.0,
        partial: bool = False,
        attachment: bytes = b"",
    ) -> list[Reply]:
        """The replies to ``selector``. :class:`QueryError` when they are not all in
        within ``timeout`` s, unless ``partial``: then the replies that came in time.
        ``attachment`` reaches the queryables as ``QueryRequest.attachment``."""

    def declare_token(self, key: str) -> Token: ...

    def watch_liveliness(self, key_expr: str, *, capacity: int = 256) -> LivelinessWatch: ...

    async def alive(self, key_expr: str, *, timeout: float = 2.0) -> list[str]:
        """The keys of the liveliness tokens matching ``key_expr`` that are up now (here
        and elsewhere), sorted."""

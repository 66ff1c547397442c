"""ZenohFabric: the fabric over one Zenoh session.

One session per process (peer mode by default, multicast scouting off, explicit
``listen``/``connect`` endpoints). Samples published here reach this process's
subscribers through the in-process router and never the network; Zenoh carries them to
other sessions only (publishers declared with ``allowed_destination=REMOTE``,
subscribers with ``allowed_origin=REMOTE``), so each subscriber gets each sample once.

Zenoh callbacks run on Zenoh threads: they copy the payload and hand it to the loop
through :class:`~rap_sdk.fabric.handoff.LoopHandoff`; they never block and never call
Zenoh. Replies to queries are sent from the loop.

Zenoh's own calls (``put``, ``reply``) run on the loop thread and return at once, except
with ``congestion_control="block"`` while the link's send queue is full: then ``put``
waits for room, stalling the loop as backpressure (nothing is lost). Choose ``"drop"``
for streams where losing a sample is better than waiting.
"""

from __future__ import annotations

import asyncio
import contextlib
import itertools
import json
import logging
import os
import socket
from collections.abc import Callable, Iterator, Mapping
from time import monotonic
from types import TracebackType
from typing import Any, Literal

import anyio
import msgspec
import zenoh
from rap_schemas.limits import MAX_MESSAGE_BYTES, MESSAGE_HEADROOM

from ..errors import FabricError, LifecycleError, QueryError
from ..inbox import Inbox, InboxPolicy, Overflow
from ..keyexpr import validate
from ..rejections import Throttle
from ._local import (
    DEFAULT_POLICY,
    InboxStream,
    Lifecycle,
    LocalSubscription,
    Router,
    answer,
    liveliness_stream,
    prepared,
)
from ._types import (
    FabricStats,
    LivelinessChange,
    Outgoing,
    Prepare,
    QueryHandler,
    QueryRequest,
    Reply,
    Sample,
)
from .handoff import LoopHandoff

__all__ = ["CONFIG_ENV", "ZenohConfig", "ZenohFabric", "node_overlay"]

RUNTIME_ENV = "ZENOH_RUNTIME"
CONFIG_ENV = "RAP_ZENOH_CONFIG"
"""A Zenoh config file (JSON with whole-line ``//`` comments) laid over every session this
process opens: ``mode``, ``listen`` and ``connect`` replace the session's own, other
top-level keys are merged into :attr:`ZenohConfig.extra`. ``rap up`` and the generated
compose files point it at the compute node's client config, so that every process of a
node reaches the others through the node's Zenoh router."""

log = logging.getLogger(__name__)


LEAN_RUNTIME = (
    "(rx: (worker_threads: 1), tx: (worker_threads: 1), net: (handover: rx), "
    "acc: (handover: rx), app: (handover: rx))"
)
"""Zenoh's tasks on two worker threads: one writes the links, the other does the rest (see
``ZenohConfig.runtime``)."""


class ZenohConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    mode: Literal["peer", "client", "router"] = "peer"
    listen: list[str] = msgspec.field(default_factory=lambda: ["tcp/127.0.0.1:0"])
    """Endpoints to listen on. The default listens on loopback only, on a free port."""
    connect: list[str] = []
    multicast_scouting: bool = False
    congestion_control: Literal["block", "drop"] = "block"
    """``block``: a full network send queue makes ``publish`` wait for room, on the loop
    thread (nothing is lost); ``drop``: the sample is dropped (high-rate sensor data)."""
    direct_callbacks: bool = True
    """Run transport callbacks on Zenoh's own thread (they only copy and hand off);
    ``False`` adds Zenoh's extra Python thread hop (measured in bench/fabric)."""
    lease_ms: int = 3000
    """A link to another session that stays silent this long is closed (and reported:
    ``fabric.stats.links_down``, lost liveliness), then re-established when it can be.
    Zenoh's own default, 10 s, let a 5 s partition pass without a trace."""
    query_handler_timeout: float = 5.0
    query_workers: int = 4
    """Tasks answering the queries of one queryable concurrently."""
    query_backlog: int = 1024
    """Queries waiting for a worker before new ones get an 'overloaded' error reply."""
    max_sample_bytes: int = MAX_MESSAGE_BYTES
    """The largest sample, query or reply payload this session's links must take: Zenoh
    drops a message over this plus ``MESSAGE_HEADROOM`` (its
    ``transport.link.rx.max_message_size``) before reassembling it, silently, and the
    link stays up. A message that Zenoh's shared memory carries (between sessions of one
    machine, up to its 16 MiB pool; off in the configs ``rap up`` and ``rap generate``
    write) escapes the limit; a ``transport`` in :attr:`extra` replaces it."""
    extra: dict[str, Any] = {}
    """Further Zenoh configuration, merged at top level (e.g. ``transport``)."""
    runtime: str | None = LEAN_RUNTIME
    """Zenoh's thread pools in this process, in the syntax of Zenoh's ``ZENOH_RUNTIME``
    setting. The default gives Zenoh two worker threads: one writes the links, the other
    reads them and runs everything else. A sample then wakes one thread at each end
    instead of several, which on a small machine cuts the CPU a message costs and the
    latency of a cross-process hop (``make bench-loop``). Writing keeps a thread of its
    own: the thread that reads a link may wait for room in a send queue (congestion
    control ``block``), and were it also the one thread that empties the queue, it would
    wait for itself until Zenoh closes the link 5 s later (seen in ``make faults``).
    ``None`` keeps Zenoh's own pools. It applies to the whole process and is read when
    the process's first session opens: a ``ZENOH_RUNTIME`` environment variable, or an
    earlier session, wins. Processes started from this one inherit it."""

    def use_runtime(self) -> None:
        """Give this process's Zenoh the thread pools of :attr:`runtime`, unless the
        environment names its own; it takes effect if no session has opened yet."""
        if self.runtime is not None and RUNTIME_ENV not in os.environ:
            os.environ[RUNTIME_ENV] = self.runtime

    def to_json5(self) -> str:
        conf: dict[str, Any] = {
            "mode": self.mode,
            "listen": {"endpoints": list(self.listen)},
            "connect": {"endpoints": list(self.connect)},
            "scouting": {"multicast": {"enabled": self.multicast_scouting}},
            "transport": {
                "link": {
                    "tx": {"lease": self.lease_ms, "keep_alive": 4},
                    "rx": {"max_message_size": self.max_sample_bytes + MESSAGE_HEADROOM},
                }
            },
        }
        for key, value in self.extra.items():
            if key in ("listen", "connect") and isinstance(value, dict):
                conf[key] = {**conf[key], **value}
            else:
                conf[key] = value
        return json.dumps(conf)


def node_overlay(
    config: ZenohConfig,
    text: str,
    *,
    source: str = CONFIG_ENV,
    env: Mapping[str, str] | None = None,
) -> ZenohConfig:
    """``config`` with the Zenoh config ``text`` (a JSON object) laid over it: ``mode``,
    ``listen.endpoints`` and ``connect.endpoints`` replace the session's; a client never
    listens; any other key is merged into ``extra``. Raises :class:`FabricError`.

    A ``transport.link.tls`` section without a certificate of its own (``rap up`` and
    the compose files write one for every process of a node with ``fabric.tls``) gets
    this process's identity from ``env`` (default: the environment): ``RAP_CERTS`` the
    folder ``rap certs`` wrote, ``RAP_AS`` the identity (``<CERTS>/<AS>.pem``, ``.key``,
    and the CA ``ca.pem``)."""
    body = "\n".join(line for line in text.splitlines() if not line.lstrip().startswith("//"))
    try:
        doc = json.loads(body)
    except ValueError as exc:
        raise FabricError(
            f"{source}: not a JSON Zenoh config (JSON with whole-line // comments): {exc}"
        ) from None
    if not isinstance(doc, dict):
        raise FabricError(f"{source}: a Zenoh config is a JSON object, got {type(doc).__name__}")
    changes: dict[str, Any] = {}
    extra = dict(config.extra)
    for key, value in doc.items():
        if key == "mode":
            if value not in ("peer", "client", "router"):
                raise FabricError(f"{source}: mode {value!r} is not peer, client or router")
            changes["mode"] = value
        elif key in ("listen", "connect"):
            endpoints = value.get("endpoints") if isinstance(value, dict) else None
            if not isinstance(endpoints, list) or not all(isinstance(e, str) for e in endpoints):
                raise FabricError(f"{source}: {key}.endpoints must be a list of endpoints")
            changes[key] = endpoints
            rest = {k: v for k, v in value.items() if k != "endpoints"}
            if rest:
                extra[key] = rest
        else:
            extra[key] = value
    mode = changes.get("mode", config.mode)
    if mode == "client":
        changes["listen"] = []
    _identity(extra, source, os.environ if env is None else env)
    return msgspec.structs.replace(config, **changes, extra=extra)


CERTS_ENV = "RAP_CERTS"
"""The folder of this process's certificates (``rap certs``): ``ca.pem``, ``<AS>.pem``."""
AS_ENV = "RAP_AS"
"""This process's identity: the common name of its certificate."""


def _identity(extra: dict[str, Any], source: str, env: Mapping[str, str]) -> None:
    """Fill the certificate of a TLS section that names none from ``env`` (in place)."""
    transport = extra.get("transport")
    link = transport.get("link") if isinstance(transport, dict) else None
    tls = link.get("tls") if isinstance(link, dict) else None
    if not isinstance(link, dict) or not isinstance(tls, dict) or "connect_certificate" in tls:
        return
    folder, name = env.get(CERTS_ENV, ""), env.get(AS_ENV, "")
    if not folder or not name:
        raise FabricError(
            f"{source}: the router link is TLS and this process has no identity - set "
            f"{AS_ENV}=<identity> and {CERTS_ENV}=<folder rap certs wrote> (rap up and the "
            "compose files set them)"
        )
    base = os.path.join(folder, name)
    files = {
        "root_ca_certificate": tls.get("root_ca_certificate") or os.path.join(folder, "ca.pem"),
        "connect_certificate": f"{base}.pem",
        "connect_private_key": f"{base}.key",
    }
    link["tls"] = {**tls, **files}


def tls_files(config: ZenohConfig) -> list[str]:
    """The certificate and key files a session of ``config`` presents (none without TLS)."""
    transport = config.extra.get("transport")
    link = transport.get("link") if isinstance(transport, dict) else None
    tls = link.get("tls") if isinstance(link, dict) else None
    if not isinstance(tls, dict):
        return []
    names = ("root_ca_certificate", "connect_certificate", "connect_private_key")
    return [str(tls[n]) for n in names if isinstance(tls.get(n), str)]


def _matching(entity: Any) -> bool:
    """A publisher's or querier's matching status. (The stubs type ``matching_status``
    as bool; at run time it is a MatchingStatus whose ``matching`` says it.)"""
    return bool(entity.matching_status.matching)


@contextlib.contextmanager
def _zenoh_errors(what: str) -> Iterator[None]:
    try:
        yield
    except zenoh.ZError as exc:
        raise FabricError(f"{what} failed: {exc}") from None


MAX_PUBLISHERS = 1024


class _Pub:
    """A declared publisher and whether a remote subscriber matches it. A matching
    listener keeps ``matching`` current with a plain store on Zenoh's thread, so reading
    it costs an attribute lookup instead of a query into Zenoh. An evicted cell is only
    dropped: a late callback writes into it harmlessly."""

    __slots__ = ("listener", "matching", "pub", "waiters")

    def __init__(self, pub: zenoh.Publisher) -> None:
        self.pub = pub
        self.listener: Any = None
        self.matching = False
        self.waiters: list[anyio.Event] = []

    def wake(self) -> None:
        for event in self.waiters:
            event.set()

    def undeclare(self) -> None:
        for entity in (self.listener, self.pub):
            if entity is not None:
                with contextlib.suppress(zenoh.ZError):
                    entity.undeclare()


class _Handle:
    """A token or queryable: undeclares its Zenoh entity once."""

    def __init__(self, key: str, entity: Any, owner: set[_Handle]) -> None:
        self.key = self.key_expr = key
        self._entity = entity
        self._owner = owner
        self.on_undeclare: Callable[[], None] | None = None
        owner.add(self)

    def undeclare(self) -> None:
        if self._entity is not None:
            entity, self._entity = self._entity, None
            self._owner.discard(self)
            if self.on_undeclare is not None:
                self.on_undeclare()
            try:
                entity.undeclare()
            except zenoh.ZError as exc:
                log.debug("undeclare of %r failed: %s", self.key, exc)


class ZenohFabric:
    def __init__(self, config: ZenohConfig | None = None) -> None:
        self.config = config or ZenohConfig()
        self._life = Lifecycle("ZenohFabric")
        self._router = Router()
        self._ticks = itertools.count(1)
        self.epoch = 0
        """Changes whenever a subscription here or a publisher's match elsewhere changes
        (set from Zenoh's thread too: each change takes a value never used before)."""
        self._session: zenoh.Session | None = None
        self._blind = False
        self._handoff: LoopHandoff | None = None
        self._pubs: dict[str, _Pub] = {}
        self._selectors: set[str] = set()
        """Query selectors already validated."""
        self._handles: set[_Handle] = set()
        self._watches: list[InboxStream[LivelinessChange]] = []
        self._id = ""
        self.stats = FabricStats()
        self.endpoints: list[str] = []
        """The endpoints this fabric listens on once open (a port 0 made concrete)."""
        self._linked: set[str] = set()
        """Peers (zenoh ids) linked now."""
        self._ever: set[str] = set()
        self._link_log = Throttle()
        self._first_link: anyio.Event | None = None
        self._transports: Any = None
        cc = zenoh.CongestionControl
        self._cc = cc.BLOCK if self.config.congestion_control == "block" else cc.DROP

    # -- lifecycle ---------------------------------------------------------------------

    @property
    def id(self) -> str:
        return self._id

    @property
    def reach(self) -> str:
        """How others reach this session, for logs: ``listening on ...``, or for a
        client ``a Zenoh client of <router>``."""
        if self.endpoints:
            return f"listening on {', '.join(self.endpoints)}"
        if self.config.mode == "client":
            return f"a Zenoh client of {', '.join(self.config.connect) or '(no router)'}"
        return f"connecting to {', '.join(self.config.connect) or '(nothing)'}"

    @property
    def session(self) -> zenoh.Session:
        self._life.check_open()
        assert self._session is not None
        return self._session

    @property
    def _push(self) -> Any:
        assert self._handoff is not None
        return self._handoff.push

    async def __aenter__(self) -> ZenohFabric:
        overlay = os.environ.get(CONFIG_ENV)
        if overlay:
            try:
                text = await anyio.Path(overlay).read_text()
            except OSError as exc:
                raise FabricError(
                    f"{CONFIG_ENV}={overlay}: cannot read it ({exc.strerror or exc}); point "
                    "it at a Zenoh config file, or unset it"
                ) from None
            self.config = node_overlay(self.config, text, source=overlay)
            for f in tls_files(self.config):
                if not await anyio.Path(f).is_file():
                    raise FabricError(
                        f"{overlay}: {f} is not there - make the certificates with rap "
                        f"certs MODEL, or fix {CERTS_ENV} and {AS_ENV}"
                    )
        # A client learns of matching subscribers only after its router answers the
        # publisher's declaration: until then every put goes to the router, which routes
        # it (waiting for the answer would lose the first samples on each new key).
        self._blind = self.config.mode == "client"
        self.endpoints = [_concrete(e) for e in self.config.listen]
        config = msgspec.structs.replace(self.config, listen=self.endpoints)
        try:
            zconf = zenoh.Config.from_json5(config.to_json5())
        except zenoh.ZError as exc:
            raise FabricError(f"invalid Zenoh configuration: {exc}") from None
        self.config.use_runtime()  # read once, at the process's first open
        try:
            session = await anyio.to_thread.run_sync(zenoh.open, zconf)
        except zenoh.ZError as exc:
            raise FabricError(
                f"cannot open a Zenoh session (listen={self.config.listen}, "
                f"connect={self.config.connect}): {exc}"
            ) from None
        except BaseException as exc:  # Zenoh panics on a runtime setting it cannot parse
            if type(exc).__name__ != "PanicException":
                raise
            raise FabricError(
                f"Zenoh could not start its threads with {RUNTIME_ENV}="
                f"{os.environ.get(RUNTIME_ENV)!r} (ZenohConfig.runtime or the environment "
                f"variable): {exc}; fix or unset it"
            ) from None
        try:
            await self._life.open()
        except BaseException:
            with anyio.CancelScope(shield=True):
                await anyio.to_thread.run_sync(session.close)
            raise
        self._session = session
        self._id = str(session.info.zid())
        self._handoff = LoopHandoff(asyncio.get_running_loop())
        push = self._handoff.push
        put = zenoh.SampleKind.PUT

        def on_transport(event: Any) -> None:
            push(self._link_changed, (str(event.transport.zid), event.kind == put))

        self._transports = session.info.declare_transport_events_listener(
            self._callback(on_transport), history=True
        )
        return self

    def _link_changed(self, change: tuple[str, bool]) -> None:
        """A link to another Zenoh session came up or went down: counted and logged
        (rate-limited per peer), so that a partition leaves a trace in every process."""
        zid, up = change
        st = self.stats
        if up:
            if zid in self._linked:
                return
            self._linked.add(zid)
            st.links_up += 1
            if self._first_link is not None:
                self._first_link.set()
            again = zid in self._ever
            self._ever.add(zid)
            if again:
                st.reconnects += 1
                if self._link_log.hit(zid):
                    log.info("fabric: link to peer %s is back (reconnected)", zid[:8])
            return
        if zid not in self._linked:
            return
        self._linked.discard(zid)
        st.links_down += 1
        if self._link_log.hit(zid):
            log.info(  # a peer stopping does this too: PeerWatch says which node is gone
                "fabric: link to peer %s lost (%d peer(s) still linked); Zenoh keeps "
                "trying to reconnect",
                zid[:8],
                len(self._linked),
            )

    async def __aexit__(
        self, et: type[BaseException] | None, ev: BaseException | None, tb: TracebackType | None
    ) -> None:
        if not self._life.is_open:
            return
        if self._transports is not None:
            with contextlib.suppress(zenoh.ZError):
                self._transports.undeclare()
            self._transports = None
        for h in list(self._handles):
            h.undeclare()
        self._router.close_all()
        for w in list(self._watches):
            w.close()
        for cell in self._pubs.values():
            cell.undeclare()
        self._pubs.clear()
        try:
            await self._life.close(et, ev, tb)
        finally:
            session, self._session = self._session, None
            if session is not None:
                with anyio.CancelScope(shield=True):
                    await anyio.to_thread.run_sync(session.close)

    def _callback(self, fn: Any, drop: Any = None) -> zenoh.handlers.Callback[Any]:
        return zenoh.handlers.Callback(fn, drop, indirect=not self.config.direct_callbacks)

    # -- pub/sub -----------------------------------------------------------------------

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
        cell = self._pubs.get(key) or self._declare_publisher(key)  # validates the key
        # The matching flag flips on Zenoh's thread when a remote subscriber's
        # declaration reaches this session, i.e. when Zenoh's own routing would start
        # sending it samples: skipping the put before then loses nothing Zenoh delivers.
        # Other processes first: a local subscriber may handle the sample in this task
        # at once, and what it sends must not reach them before the sample itself.
        if cell.matching or self._blind:
            try:
                cell.pub.put(payload.data if type(payload) is Outgoing else payload)
            except zenoh.ZError as exc:
                raise FabricError(f"publish on {key!r} failed: {exc}") from None
        router = self._router
        subs = (router.cached(key) or router.matching(key)) if local else ()
        if subs:
            late = await router.deliver(subs, key, payload, timeout)
            if late is not None:
                raise late

    def _declare_publisher(self, key: str) -> _Pub:
        validate(key)
        if "*" in key:
            raise FabricError(
                f"cannot publish on a wildcard expression {key!r}; use a "
                "concrete key built by rap_schemas.keys"
            )
        if len(self._pubs) >= MAX_PUBLISHERS:
            # evict the least recently declared publisher that nobody waits on
            old = next((k for k, c in self._pubs.items() if not c.waiters), None)
            if old is not None:
                self._pubs.pop(old).undeclare()
        with _zenoh_errors(f"declaring a publisher on {key!r}"):
            cell = _Pub(
                self.session.declare_publisher(
                    key, congestion_control=self._cc, allowed_destination=zenoh.Locality.REMOTE
                )
            )
            push = self._push

            def on_status(status: zenoh.MatchingStatus) -> None:
                cell.matching = status.matching  # set before waking: a woken waiter sees it
                self.epoch = next(self._ticks)
                if status.matching and cell.waiters:
                    push(_Pub.wake, cell)

            cell.listener = cell.pub.declare_matching_listener(self._callback(on_status))
            if _matching(cell.pub):
                cell.matching = True
        self._pubs[key] = cell
        self.epoch = next(self._ticks)
        return cell

    def has_subscribers(self, key: str, *, remote_only: bool = False) -> bool:
        if not self._life.is_open:
            self._life.check_open()
        if not remote_only and self._router.matching(key):
            return True
        return (self._pubs.get(key) or self._declare_publisher(key)).matching

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
            self.epoch = next(self._ticks)
            if s.remote_handle is not None:
                with contextlib.suppress(zenoh.ZError):
                    s.remote_handle.undeclare()  # type: ignore[attr-defined]

        sub = LocalSubscription(key_expr, policy or DEFAULT_POLICY, closed, prepare, group)
        deliver = sub.inbox.offer
        push = self._push

        def on_sample(s: zenoh.Sample) -> None:
            payload = s.payload.to_bytes()
            sample = Sample(str(s.key_expr), payload, True, arrived=monotonic())
            if prepare is not None:
                # before the hand-off: decoding after it would hold the interpreter lock
                # while the loop thread wakes, which then sleeps again waiting for it
                sample.prepared = prepared(prepare, payload)
            push(deliver, sample)

        with _zenoh_errors(f"subscribing to {key_expr!r}"):
            sub.remote_handle = self.session.declare_subscriber(
                key_expr, self._callback(on_sample), allowed_origin=zenoh.Locality.REMOTE
            )
        self._router.add(sub)
        self.epoch = next(self._ticks)
        return sub

    async def wait_matched(
        self, key: str, *, queryable: bool = False, timeout: float = 5.0
    ) -> None:
        """Wait until another session has a subscriber (or, with ``queryable``, a
        queryable) matching ``key``: the way to know a remote peer is ready, no sleep."""
        self._life.check_open()
        validate(key)
        what = "queryable" if queryable else "subscriber"
        fail = FabricError(
            f"no remote {what} matched {key!r} within {timeout} s; is the peer running "
            "and connected (check listen/connect)?"
        )
        if queryable:
            await self._wait_queryable(key, timeout, fail)
            return
        # subscribers: the same flag that publish() consults, so a publish made right
        # after this returns is sent
        cell = self._pubs.get(key) or self._declare_publisher(key)
        mine = anyio.Event()
        cell.waiters.append(mine)
        try:
            with anyio.fail_after(timeout):
                while not cell.matching:
                    await mine.wait()
                    if not cell.matching:  # flipped back: wait for the next change
                        cell.waiters.remove(mine)
                        mine = anyio.Event()
                        cell.waiters.append(mine)
        except TimeoutError:
            raise fail from None
        finally:
            if mine in cell.waiters:
                cell.waiters.remove(mine)

    async def _wait_queryable(self, key: str, timeout: float, fail: FabricError) -> None:
        ready = anyio.Event()
        push = self._push
        with _zenoh_errors(f"declaring a querier on {key!r}"):
            querier = self.session.declare_querier(key)

        def on_status(status: zenoh.MatchingStatus) -> None:
            if status.matching:
                push(lambda _: ready.set(), None)

        listener = querier.declare_matching_listener(self._callback(on_status))
        try:
            if not _matching(querier):
                with anyio.fail_after(timeout):
                    await ready.wait()
        except TimeoutError:
            raise fail from None
        finally:
            listener.undeclare()
            querier.undeclare()

    # -- query/reply -------------------------------------------------------------------

    def serve(self, key_expr: str, handler: QueryHandler) -> _Handle:
        """Answer queries on ``key_expr`` with ``handler`` (async, under the configured
        deadline). Queries are handed from Zenoh's thread into a bounded inbox served by
        ``query_workers`` long-lived tasks (no task per query); when the inbox is full a
        query gets an error reply saying so."""
        self._life.check_open()
        validate(key_expr)
        tg = self._life.task_group
        push = self._push
        timeout = self.config.query_handler_timeout
        inbox: Inbox[tuple[zenoh.Query, float]] = Inbox(
            InboxPolicy(capacity=self.config.query_backlog, overflow=Overflow.FIFO, block=False)
        )

        async def worker() -> None:
            while True:
                try:
                    query, arrived = await inbox.get()
                except LifecycleError:
                    return
                payload = query.payload.to_bytes() if query.payload is not None else b""
                attached = query.attachment
                request = QueryRequest(
                    str(query.key_expr),
                    str(query.parameters),
                    payload,
                    arrived,
                    attached.to_bytes() if attached is not None else b"",
                )
                try:
                    for r in await answer(handler, request, timeout):
                        if r.ok:
                            query.reply(r.key, r.payload)
                        else:
                            query.reply_err(r.payload)
                except zenoh.ZError as exc:
                    log.warning("reply to %r failed: %s", request.key, exc)
                finally:
                    query.drop()

        def accept(item: tuple[zenoh.Query, float]) -> None:
            query = item[0]
            if not self._life.is_open or not inbox.offer(item):
                with contextlib.suppress(zenoh.ZError):
                    query.reply_err(
                        f"queryable {key_expr!r} is overloaded or closing "
                        f"({self.config.query_backlog} queries waiting); retry later".encode()
                    )
                query.drop()

        def on_query(query: zenoh.Query) -> None:
            push(accept, (query, monotonic()))

        for _ in range(self.config.query_workers):
            tg.start_soon(worker)
        with _zenoh_errors(f"serving {key_expr!r}"):
            q = self.session.declare_queryable(key_expr, self._callback(on_query))
        handle = _Handle(key_expr, q, self._handles)
        handle.on_undeclare = inbox.close
        return handle

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
        if selector not in self._selectors:
            validate(selector.partition("?")[0])
            if len(self._selectors) < 4096:
                self._selectors.add(selector)
        loop = asyncio.get_running_loop()
        done: asyncio.Future[None] = loop.create_future()
        replies: list[Reply] = []
        push = self._push

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                replies.append(Reply(str(reply.ok.key_expr), reply.ok.payload.to_bytes()))
            elif reply.err is not None:
                replies.append(Reply(selector, reply.err.payload.to_bytes(), ok=False))

        def finish(_: object) -> None:
            if not done.done():
                done.set_result(None)

        def on_drop() -> None:
            push(finish, None)

        # No Zenoh-side timeout: arming Zenoh's query timer costs ~50 us per query
        # (bench/knowledge). Our deadline below bounds the wait; a query left behind by
        # it is finalised by Zenoh's own default query timeout.
        try:
            if partial:  # replies as they come (Zenoh's default holds them to the end)
                self.session.get(
                    selector,
                    self._callback(on_reply, on_drop),
                    payload=payload or None,
                    attachment=attachment or None,
                    consolidation=zenoh.ConsolidationMode.NONE,
                )
            else:
                self.session.get(
                    selector,
                    self._callback(on_reply, on_drop),
                    payload=payload or None,
                    attachment=attachment or None,
                )
        except zenoh.ZError as exc:
            raise FabricError(f"query {selector!r} failed: {exc}") from None
        try:
            async with asyncio.timeout(timeout):  # cheaper than an anyio scope, measured
                await done
        except TimeoutError:
            if partial:  # what came in time (a wildcard query: the quick answerers)
                return list(replies)
            raise QueryError(
                f"query {selector!r} got no complete answer within {timeout} s"
            ) from None
        return list(replies)

    # -- liveliness --------------------------------------------------------------------

    def declare_token(self, key: str) -> _Handle:
        self._life.check_open()
        validate(key)
        if "*" in key:
            raise LifecycleError(f"a liveliness token needs a concrete key, got {key!r}")
        with _zenoh_errors(f"declaring a liveliness token on {key!r}"):
            tok = self.session.liveliness().declare_token(key)
        return _Handle(key, tok, self._handles)

    async def alive(self, key_expr: str, *, timeout: float = 2.0) -> list[str]:
        self._life.check_open()
        validate(key_expr)
        if self.config.connect and not self._linked and self._first_link is None:
            # a session that has just opened may not be linked yet: it would hear nobody
            # (waited for once: an endpoint that does not answer costs this only once)
            self._first_link = anyio.Event()
            with anyio.move_on_after(timeout):
                await self._first_link.wait()
        done: asyncio.Future[None] = asyncio.get_running_loop().create_future()
        found: set[str] = set()
        push = self._push

        def on_reply(reply: zenoh.Reply) -> None:
            if reply.ok is not None:
                found.add(str(reply.ok.key_expr))

        def finish(_: object) -> None:
            if not done.done():
                done.set_result(None)

        with _zenoh_errors(f"asking which tokens match {key_expr!r}"):
            self.session.liveliness().get(
                key_expr, self._callback(on_reply, lambda: push(finish, None)), timeout=timeout
            )
        try:
            async with asyncio.timeout(timeout + 1.0):
                await done
        except TimeoutError:
            raise QueryError(
                f"liveliness query {key_expr!r} got no complete answer within {timeout} s"
            ) from None
        return sorted(found)

    def watch_liveliness(
        self,
        key_expr: str,
        *,
        capacity: int = 256,
    ) -> InboxStream[LivelinessChange]:
        self._life.check_open()
        validate(key_expr)
        handle: list[Any] = []

        def closed(s: InboxStream[LivelinessChange]) -> None:
            if s in self._watches:
                self._watches.remove(s)
            for h in handle:
                with contextlib.suppress(zenoh.ZError):
                    h.undeclare()

        stream = liveliness_stream(capacity, closed)
        deliver = stream.inbox.offer
        push = self._push
        put_kind = zenoh.SampleKind.PUT

        def on_change(s: zenoh.Sample) -> None:
            push(deliver, LivelinessChange(str(s.key_expr), s.kind == put_kind))

        with _zenoh_errors(f"watching liveliness of {key_expr!r}"):
            handle.append(
                self.session.liveliness().declare_subscriber(
                    key_expr, self._callback(on_change), history=True
                )
            )
        self._watches.append(stream)
        return stream


def _concrete(endpoint: str) -> str:
    """``tcp/<host>:0`` (any free port) with a free port chosen now, so that the
    fabric knows, and can log, where it really listens."""
    proto, sep, rest = endpoint.partition("/")
    host, colon, port = rest.rpartition(":")
    if not sep or not colon or port != "0" or proto not in ("tcp", "udp", "quic", "tls"):
        return endpoint
    return f"{proto}/{host}:{free_port(host.strip('[]') or '127.0.0.1')}"


def free_port(host: str = "127.0.0.1") -> int:
    """A free TCP port on ``host`` (loopback by default), for a listen endpoint
    (``tcp/127.0.0.1:<port>``)."""
    family = socket.AF_INET6 if ":" in host else socket.AF_INET
    with socket.socket(family) as sock:
        sock.bind((host, 0))
        port: int = sock.getsockname()[1]
        return port

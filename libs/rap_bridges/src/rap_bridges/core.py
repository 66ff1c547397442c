"""The protocol-independent part of every bridge (docs/bridges.md).

A :class:`Bridge` runs one port's pump between the fabric and a :class:`Link` (one
protocol's connection):

- ``out`` (fabric -> outside): a fabric subscription whose bounded inbox *is* the
  buffer (the spec's ``buffer`` and ``overflow``); each sample is opened with the
  fabric's own rules (strict envelope, declared type, duplicates), encoded per format,
  its cycle and cause put in headers, and sent; a message is kept until the link
  confirmed it, and sent again after a reconnect.
- ``in`` (outside -> fabric): frames go into a bounded inbox with the same policies;
  each is decoded and validated against the port's message type, sealed into an
  envelope (``source`` = the bridge's name; cycle and cause from the headers) and
  published on the fabric key. What does not validate is rejected with its reason,
  counted, logged (rate-limited), and the next frame is taken.

The link is reconnected with :class:`Backoff` (exponential, with jitter). Everything
is counted in :class:`BridgeStats` (exported by :class:`rap_bridges.metrics.BridgeCollector`).
"""

from __future__ import annotations

import importlib
import logging
import random
from collections.abc import Awaitable, Callable, Mapping
from dataclasses import dataclass, field
from typing import Any, Final, Literal, Protocol

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import Message
from rap_schemas.limits import DecodeRejected, SafeDecoder
from rap_sdk.envelope import Clock, Opener, Sealer, TypedEnvelope, typed_decoder
from rap_sdk.errors import FabricError, LifecycleError, RejectedSample
from rap_sdk.fabric import Fabric, Outgoing, Sample, Subscription
from rap_sdk.inbox import Inbox, InboxPolicy, InboxStats, Overflow
from rap_sdk.keyexpr import validate
from rap_sdk.rejections import Rejections, Throttle

from .spec import BridgeSpec

__all__ = [
    "HEADER_CAUSE",
    "HEADER_CYCLE",
    "HEADER_SOURCE",
    "HEADER_TYPE",
    "STABLE_S",
    "TRANSPORT_ERRORS",
    "Backoff",
    "Bridge",
    "BridgeStats",
    "Deliver",
    "Direction",
    "Frame",
    "FrameRefused",
    "Link",
    "LinkContext",
    "LinkDown",
    "buffer_policy",
    "make_link",
    "register_link",
]

log = logging.getLogger(__name__)

Direction = Literal["in", "out"]
"""``out``: fabric -> outside; ``in``: outside -> fabric."""

HEADER_CYCLE: Final = "rap-cycle"
"""The envelope's ``cycle`` (32 hex digits)."""
HEADER_CAUSE: Final = "rap-cause"
"""The envelope's ``cause`` (32 hex digits)."""
HEADER_TYPE: Final = "rap-type"
"""The message's wire type (``rap.LaserScan/1``)."""
HEADER_SOURCE: Final = "rap-source"
"""The envelope's sender (outgoing only; incoming messages are sealed by the bridge)."""
TRANSPORT_ERRORS: Final = (
    OSError,
    anyio.BrokenResourceError,
    anyio.ClosedResourceError,
    anyio.EndOfStream,
    anyio.IncompleteRead,
)
"""Errors of a connection that a link let through unworded: the connection is taken as
lost (and made again), as with :class:`LinkDown`."""
STABLE_S: Final = 1.0
"""A connection that held this long resets the backoff; one lost sooner (a server that
accepts and drops at once) keeps the pauses growing."""


@dataclass(frozen=True, slots=True)
class Frame:
    """One message as a link carries it: payload bytes and string headers (MQTT v5 user
    properties, the header map of a TCP frame)."""

    payload: bytes
    headers: Mapping[str, str] = field(default_factory=dict)


class FrameRefused(Exception):
    """Raised by :meth:`Link.send` for a frame the other side can never take (over its
    size limit, a header it cannot carry, a value its type cannot hold): the bridge
    counts it as rejected with ``reason``, not as sent, and takes the next one."""

    def __init__(self, reason: str) -> None:
        super().__init__(reason)
        self.reason = reason


class LinkDown(Exception):
    """The link cannot carry messages now (connection refused, lost, closed). ``fix``:
    what the operator can do, when known."""

    def __init__(self, reason: str, fix: str = "") -> None:
        super().__init__(reason)
        self.reason = reason
        self.fix = fix

    def __str__(self) -> str:
        return f"{self.reason} - {self.fix}" if self.fix else self.reason


Deliver = Callable[[Frame], Awaitable[None]]
"""What a link calls for each frame it received; when it returns, the frame is the
bridge's (a link that acknowledges frames does so then)."""


class Link(Protocol):
    """One protocol's connection, as a bridge drives it. A link is used by one bridge:
    ``open`` and ``run`` alternate with ``send`` calls of one task at a time."""

    @property
    def where(self) -> str:
        """The URL and address, for logs (never credentials)."""

    async def open(self) -> None:
        """Connect (or, for a server, listen and wait for a first client); drop what is
        left of an earlier connection first. :class:`LinkDown` when it cannot."""

    async def run(self, deliver: Deliver) -> None:
        """Receive until the connection is lost (:class:`LinkDown`), handing each frame
        to ``deliver``. An outgoing-only link still runs it: it is how a lost connection
        is noticed while nothing is sent."""

    async def send(self, frame: Frame) -> None:
        """Send one frame; return once the other side has it as the QoS asks (QoS >= 1:
        confirmed). :class:`LinkDown` when the connection is lost: the bridge sends the
        frame again after a reconnect; :class:`FrameRefused` for a frame that can never
        be sent."""

    async def close(self) -> None:
        """Disconnect for good (the bridge stops)."""


@dataclass(frozen=True, slots=True)
class LinkContext:
    """What a link gets from its bridge."""

    name: str
    """The bridge's name (MQTT client id, logs)."""
    direction: Direction
    reject: Callable[[str], None]
    """Count and log one frame refused by the link itself (oversize, bad headers)."""
    message: type[Message] | None = None
    """The port's message type (None: any): DDS's format cdr maps it to a ROS 2 message."""


LinkFactory = Callable[[BridgeSpec, LinkContext], Link]
_FACTORIES: dict[str, LinkFactory] = {}


def register_link(protocol: str, factory: LinkFactory) -> None:
    """Make ``protocol`` a bridge protocol (a new transport's module calls it)."""
    _FACTORIES[protocol] = factory


_BUILT_IN: Final[dict[str, tuple[str, str]]] = {
    "mqtt": ("mqtt", "MqttLink"),
    "tcp": ("tcp", "TcpLink"),
    "redis": ("redis", "RedisLink"),
    "redis-stream": ("redis", "RedisStreamLink"),
    "amqp": ("amqp", "AmqpLink"),
    "websocket": ("websocket", "WebSocketLink"),
    "nats": ("nats", "NatsLink"),
    "dds": ("dds", "DdsLink"),
    "kafka": ("kafka", "KafkaLink"),
}
"""protocol -> (module of rap_bridges, link class): imported when first used, so that a
process that bridges MQTT only never imports aio-pika or nats."""


def make_link(spec: BridgeSpec, ctx: LinkContext) -> Link:
    """The link ``spec.protocol`` names (the built-in ones are imported on first use)."""
    if spec.protocol not in _FACTORIES and spec.protocol in _BUILT_IN:
        module, cls = _BUILT_IN[spec.protocol]
        factory = getattr(importlib.import_module(f"rap_bridges.{module}"), cls)
        register_link(spec.protocol, factory)
    try:
        factory = _FACTORIES[spec.protocol]
    except KeyError:
        raise ValueError(
            f"no bridge for protocol {spec.protocol!r}; known: {sorted(_FACTORIES)}"
        ) from None
    return factory(spec, ctx)


class Backoff:
    """Pauses between connection attempts: ``initial`` s, times ``multiplier`` after
    each failure up to ``max`` s, each spread by +/- ``jitter`` (a fraction) so that many
    bridges that lost one server do not come back in step. :meth:`reset` after a
    success (a bridge: after a connection that held :data:`STABLE_S`)."""

    __slots__ = ("_next", "_rng", "initial", "jitter", "max", "multiplier")

    def __init__(
        self,
        initial: float = 0.1,
        max: float = 10.0,
        multiplier: float = 2.0,
        jitter: float = 0.2,
        *,
        rng: random.Random | None = None,
    ) -> None:
        if not 0 < initial <= max:
            raise ValueError(f"backoff needs 0 < initial <= max, got {initial} and {max}")
        if multiplier < 1:
            raise ValueError(f"backoff multiplier must be >= 1, got {multiplier}")
        if not 0 <= jitter < 1:
            raise ValueError(f"backoff jitter is a fraction in [0, 1), got {jitter}")
        self.initial = initial
        self.max = max
        self.multiplier = multiplier
        self.jitter = jitter
        self._rng = rng or random.Random()
        self._next = initial

    def next(self) -> float:
        """The pause before the next attempt (and the one after grows)."""
        base = self._next
        self._next = min(self.max, base * self.multiplier)
        return base * (1 + self._rng.uniform(-self.jitter, self.jitter))

    def reset(self) -> None:
        self._next = self.initial


def buffer_policy(spec: BridgeSpec) -> InboxPolicy:
    """The bounded inbox of a spec's ``buffer`` and ``overflow``."""
    if spec.overflow == "drop-oldest":
        return InboxPolicy(capacity=spec.buffer, overflow=Overflow.LATEST, block=False)
    return InboxPolicy(capacity=spec.buffer, overflow=Overflow.FIFO, block=spec.overflow == "block")


@dataclass(slots=True)
class BridgeStats:
    """What a bridge counts (read by :class:`rap_bridges.metrics.BridgeCollector`)."""

    rejections: Rejections
    """Messages refused, by kind of reason (``by_reason``) and in all (``total``)."""
    sent: int = 0
    """Messages the link confirmed sending (out)."""
    received: int = 0
    """Frames the link received (in), before any check."""
    published: int = 0
    """Messages published on the fabric (in)."""
    duplicates: int = 0
    """Envelopes seen twice (a resend after a reconnect) and passed over."""
    connects: int = 0
    """Connections made (the first one and every reconnect)."""
    reconnects: int = 0
    """Connections made after one was lost or refused."""
    disconnects: int = 0
    """Connections lost."""
    connect_failures: int = 0
    """Attempts to connect that failed."""
    fabric_failures: int = 0
    """Messages (in) the fabric refused to take; each is logged."""
    connected: bool = False
    buffer: InboxStats | None = None
    """The buffer's counters (accepted, dropped by the overflow policy, high water)."""
    buffered: Callable[[], int] = lambda: 0
    """How many messages wait in the buffer now."""

    @property
    def rejected(self) -> int:
        return self.rejections.total

    @property
    def dropped(self) -> int:
        """Messages the overflow policy dropped from a full buffer."""
        return self.buffer.dropped if self.buffer is not None else 0


def _wildcard(topic: str) -> bool:
    return "+" in topic or "#" in topic


def _hex_uid(headers: Mapping[str, str], name: str) -> bytes | None:
    text = headers.get(name)
    if text is None or text == "":
        return None
    try:
        value = bytes.fromhex(text)
    except ValueError:
        value = b""
    if len(value) != 16:
        raise RejectedSample(f"header {name} must be 32 hex digits (a uid), got {text[:40]!r}")
    return value


class _Codec:
    """One port's message format at the boundary, both ways."""

    def __init__(self, spec: BridgeSpec, message: type[Message] | None) -> None:
        self.format = spec.format
        self.message = message
        self.expected = message.TYPE if message is not None else None
        self.max_bytes = spec.max_frame
        self.decode_env: Callable[[bytes], TypedEnvelope[Any]] = typed_decoder(message)
        if spec.format != "envelope":
            if message is None:
                raise ValueError(
                    f"format {spec.format} needs the port's message type (only envelope "
                    "carries its own type)"
                )
            protocol = "json" if spec.format == "json" else "msgpack"
            what = f"{message.TYPE} {'JSON' if protocol == 'json' else 'msgpack body'}"
            self.decode_body: Callable[[bytes], Any] = SafeDecoder(
                message, protocol=protocol, max_bytes=spec.max_frame, what=what
            ).decode
        self._json = msgspec.json.Encoder().encode
        self._msgpack = msgspec.msgpack.Encoder().encode

    def outgoing(self, opener: Opener, key: str, payload: bytes) -> Frame | None:
        """The frame of one fabric sample (None: a duplicate); :class:`RejectedSample`."""
        env = opener.open_typed(key, payload, self.decode_env, self.expected)
        if env is None:
            return None
        headers = {HEADER_TYPE: env.type, HEADER_SOURCE: env.source}
        if env.cycle is not None:
            headers[HEADER_CYCLE] = env.cycle.hex()
        if env.cause is not None:
            headers[HEADER_CAUSE] = env.cause.hex()
        if self.format == "envelope":
            return Frame(payload, headers)
        body = env.body
        if self.format == "json":
            return Frame(self._json(body), headers)
        return Frame(self._msgpack(body), headers)

    def incoming(
        self, opener: Opener, sealer: Sealer, key: str, frame: Frame
    ) -> bytes | Outgoing | None:
        """What to publish for one frame (None: a duplicate); :class:`RejectedSample`."""
        payload, headers = frame.payload, frame.headers
        if len(payload) > self.max_bytes:
            raise RejectedSample(
                f"message of {len(payload)} bytes is over the limit of {self.max_bytes} "
                "(the spec's max_frame)"
            )
        cycle = _hex_uid(headers, HEADER_CYCLE)
        cause = _hex_uid(headers, HEADER_CAUSE)
        if self.format == "envelope":
            env = opener.open_typed(key, payload, self.decode_env, self.expected)
            if env is None:
                return None
            cycle = env.cycle if env.cycle is not None else cycle
            cause = env.cause if env.cause is not None else cause
            if self.message is None:
                data, _ = sealer.seal(key, env.type, bytes(env.body), cycle=cycle, cause=cause)
                return data
            return sealer.seal_out(key, env.body, cycle=cycle, cause=cause)
        said = headers.get(HEADER_TYPE)
        if said and said != self.expected:
            raise RejectedSample(f"expected type {self.expected}, got {said!r}", type=said)
        try:
            body = self.decode_body(payload)
        except DecodeRejected as exc:
            raise RejectedSample(f"invalid {exc.reason}", type=self.expected or "") from None
        return sealer.seal_out(key, body, cycle=cycle, cause=cause)


class Bridge:
    """One port's pump between ``fabric`` (on ``key``) and the outside ``spec`` names.

    ``direction``: ``out`` (fabric -> outside) or ``in`` (outside -> fabric);
    ``message``: the port's message type (None: any, for format ``envelope`` only).
    Run it in a task group (``await tg.start(bridge.run)``: when it has started, the
    ``out`` buffer takes samples) and cancel the group to stop it.
    """

    def __init__(
        self,
        name: str,
        spec: BridgeSpec,
        fabric: Fabric,
        key: str,
        *,
        direction: Direction,
        message: type[Message] | None = None,
        backoff: Backoff | None = None,
        link: Link | None = None,
        clock: Clock | None = None,
    ) -> None:
        if direction not in ("in", "out"):
            raise ValueError(f"direction must be 'in' or 'out', got {direction!r}")
        if direction == "out" and spec.protocol == "mqtt" and _wildcard(spec.address):
            raise ValueError(
                f"an out bridge publishes on one topic: {spec.address!r} has a wildcard"
            )
        validate(key)  # KeyExprError (a ValueError) with the fix
        if direction == "in" and "*" in key:
            raise ValueError(
                f"an in bridge publishes on one key: {key!r} has a wildcard - use a concrete "
                "key built by rap_schemas.keys"
            )
        self.name = name
        self.spec = spec
        self.fabric = fabric
        self.key = key
        self.direction: Direction = direction
        self.backoff = backoff or Backoff()
        self._codec = _Codec(spec, message)
        self.stats = BridgeStats(Rejections(f"bridge {name}", log))
        ctx = LinkContext(name=name, direction=direction, reject=self._link_reject, message=message)
        self.link: Link = link if link is not None else make_link(spec, ctx)
        self._opener = Opener(clock)
        self._sealer = Sealer(name, clock)
        self._pending: Frame | None = None
        self._inbox: Inbox[Frame] | None = None
        self._sub: Subscription | None = None
        self._changed: anyio.Event | None = None  # made on the event loop, when needed
        self._throttle = Throttle()
        self._dropped_logged = 0
        self._scope: anyio.CancelScope | None = None

    # -- state --------------------------------------------------------------------------

    @property
    def connected(self) -> bool:
        return self.stats.connected

    async def wait_connected(self, connected: bool = True) -> None:
        """Wait until the link is up (``connected=False``: down)."""
        while self.stats.connected is not connected:
            await self._change().wait()

    async def wait_connects(self, n: int) -> None:
        """Wait until the link has been made ``n`` times in all, and is up."""
        while self.stats.connects < n or not self.stats.connected:
            await self._change().wait()

    def _change(self) -> anyio.Event:
        if self._changed is None:
            self._changed = anyio.Event()
        return self._changed

    def _notify(self) -> None:
        changed, self._changed = self._changed, None
        if changed is not None:
            changed.set()

    def _link_reject(self, reason: str) -> None:
        self.stats.rejections.reject(self.link.where, reason)

    # -- running ------------------------------------------------------------------------

    def _stop(self) -> None:
        if self._scope is not None:
            self._scope.cancel()

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        policy = buffer_policy(self.spec)
        try:
            async with anyio.create_task_group() as tg:
                self._scope = tg.cancel_scope
                if self.direction == "out":
                    sub = self._sub = self.fabric.subscribe(self.key, policy)
                    self.stats.buffer = sub.stats
                    queue: Inbox[Sample] | None = getattr(sub, "inbox", None)
                    if queue is not None:
                        self.stats.buffered = queue.__len__
                else:
                    inbox = self._inbox = Inbox(policy)
                    self.stats.buffer = inbox.stats
                    self.stats.buffered = inbox.__len__
                    tg.start_soon(self._publish_in, inbox)
                tg.start_soon(self._watch_drops)
                tg.start_soon(self._connect_loop)
                task_status.started()
        finally:
            with anyio.CancelScope(shield=True):
                if self._sub is not None:
                    self._sub.close()
                if self._inbox is not None:
                    self._inbox.close()
                try:
                    await self.link.close()
                except LinkDown as exc:
                    log.debug("bridge %s: closing %s: %s", self.name, self.link.where, exc)
                if self.stats.connected:
                    self.stats.connected = False
                    self._notify()
                for rec in self.stats.rejections.flush():
                    log.debug("bridge %s: %s", self.name, rec.reason)

    async def _connect_loop(self) -> None:
        ever = False
        failing = False
        while True:
            try:
                await self.link.open()
            except (LinkDown, *TRANSPORT_ERRORS) as exc:
                self.stats.connect_failures += 1
                pause = self.backoff.next()
                n = self._throttle.hit("connect")
                if n:
                    log.warning(
                        "bridge %s: cannot connect to %s (%d attempt(s)): %s; retrying in "
                        "%.2f s, buffering up to %d message(s) (overflow %s)",
                        self.name,
                        self.link.where,
                        n,
                        exc,
                        pause,
                        self.spec.buffer,
                        self.spec.overflow,
                    )
                failing = True
                await anyio.sleep(pause)
                continue
            st = self.stats
            st.connects += 1
            if ever or failing:
                st.reconnects += 1
            st.connected = True
            self._notify()
            log.info(
                "bridge %s: connected to %s (%s, %d message(s) buffered)",
                self.name,
                self.link.where,
                "reconnect" if ever or failing else "first connection",
                st.buffered(),
            )
            ever, failing = True, False
            began = anyio.current_time()
            reason = await self._session()
            if anyio.current_time() - began >= STABLE_S:
                self.backoff.reset()  # a connection that held: start again from the shortest
            st.disconnects += 1
            st.connected = False
            self._notify()
            pause = self.backoff.next()
            log.warning(
                "bridge %s: lost %s: %s; reconnecting in %.2f s, buffering up to %d "
                "message(s) meanwhile (overflow %s)",
                self.name,
                self.link.where,
                reason,
                pause,
                self.spec.buffer,
                self.spec.overflow,
            )
            await anyio.sleep(pause)

    async def _session(self) -> str:
        """Run one connection until it is lost; the reason."""
        down: list[str] = []
        async with anyio.create_task_group() as tg:

            async def receive() -> None:
                try:
                    await self.link.run(self._deliver)
                    down.append("the connection was closed")
                except LinkDown as exc:
                    down.append(str(exc))
                except TRANSPORT_ERRORS as exc:  # one a link did not word itself
                    down.append(f"{type(exc).__name__}: {exc}")
                tg.cancel_scope.cancel()

            tg.start_soon(receive)
            if self.direction == "out":
                try:
                    await self._send_loop()
                except LinkDown as exc:
                    down.append(str(exc))
                except TRANSPORT_ERRORS as exc:
                    down.append(f"{type(exc).__name__}: {exc}")
                tg.cancel_scope.cancel()
        return down[0] if down else "the connection was closed"

    async def _send_loop(self) -> None:
        sub = self._sub
        assert sub is not None
        codec, opener, send, st = self._codec, self._opener, self.link.send, self.stats
        while True:
            if self._pending is None:
                try:
                    sample: Sample = await sub.get()
                except LifecycleError:  # the fabric closed: nothing more will come
                    log.info("bridge %s: the fabric closed %s; stopping", self.name, self.key)
                    self._stop()
                    await anyio.sleep_forever()
                try:
                    frame = codec.outgoing(opener, sample.key, sample.payload)
                except RejectedSample as exc:
                    st.rejections.reject(sample.key, exc.reason, source=exc.source, type=exc.type)
                    continue
                if frame is None:
                    st.duplicates += 1
                    continue
                self._pending = frame
            try:
                await send(self._pending)
            except FrameRefused as exc:
                st.rejections.reject(self.link.where, exc.reason)
            else:
                st.sent += 1
            self._pending = None

    async def _deliver(self, frame: Frame) -> None:
        inbox = self._inbox
        if inbox is None:  # an out bridge takes nothing in
            self._link_reject("an out bridge takes no messages from outside")
            return
        self.stats.received += 1
        if not inbox.put_nowait(frame):
            await inbox.put(frame)  # overflow block: the link waits (backpressure)

    async def _publish_in(self, inbox: Inbox[Frame]) -> None:
        codec, st = self._codec, self.stats
        while True:
            try:
                frame = await inbox.get()
            except LifecycleError:
                return
            try:
                out = codec.incoming(self._opener, self._sealer, self.key, frame)
            except RejectedSample as exc:
                st.rejections.reject(self.link.where, exc.reason, source=exc.source, type=exc.type)
                continue
            if out is None:
                st.duplicates += 1
                continue
            try:
                await self.fabric.publish(self.key, out)
            except (FabricError, LifecycleError) as exc:
                st.fabric_failures += 1
                if self._throttle.hit("fabric"):
                    log.error(
                        "bridge %s: the fabric refused a message for %s: %s (%d so far)",
                        self.name,
                        self.key,
                        exc,
                        st.fabric_failures,
                    )
                continue
            st.published += 1

    async def _watch_drops(self, every: float = 1.0) -> None:
        """Log what the overflow policy dropped (once a second at most)."""
        while True:
            await anyio.sleep(every)
            self.log_drops()

    def log_drops(self) -> None:
        dropped = self.stats.dropped
        if dropped > self._dropped_logged:
            log.warning(
                "bridge %s: dropped %d message(s) for %s (buffer of %d full, overflow %s; "
                "%d in all) - raise buffer, or see why the link is down or slow",
                self.name,
                dropped - self._dropped_logged,
                self.link.where,
                self.spec.buffer,
                self.spec.overflow,
                dropped,
            )
            self._dropped_logged = dropped

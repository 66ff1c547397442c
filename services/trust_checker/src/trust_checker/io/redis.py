"""The checker on Redis pub/sub (redis.asyncio), the way it runs on MQTT (:mod:`.mqtt`).

Inputs: each input stream is read from the channel of its own name, or the channel that
``RedisConfig.channels`` maps it to (``{"x": {"channel": "robot/x"}}``); a channel with
``*``, ``?`` or ``[`` is a glob-style pattern, subscribed with ``PSUBSCRIBE``. Payloads
in any of the forms of :mod:`trust_checker.io.codec`, refused by the same rules as on
MQTT. The subscriptions follow the running spec's inputs across hot swaps. A message on
a channel that several subscriptions match comes once per subscription (Redis's rule),
each setting the streams of its own subscription.

Outputs: each output that ticks is published on its channel (same rule) as
``{"value": <plain JSON>}`` (⊥: ``{"value": null, "deferred": true}``), or tagged
(``{"Int": 42}``, ⊥: ``"Unknown"``) with ``tagged``; NoVal is never published. The
outputs of one tick go in one round trip (a pipeline).

Verdicts (a session with ``explain=True``): each ``rap.TrustVerdict`` as JSON on
``verdict_channel`` (default ``trust/verdicts``; "" for none), and, with
``verdict_stream``, also added to that Redis stream (``XADD <stream> MAXLEN ~ <n> *
verdict <json>``), where a reader that was not subscribed at the time finds them.

Hot swap, only on a checker with identities (``RAP_CERTS``, ``--certs``): a spec update
signed by an operator (:func:`trust_checker.io.auth.signed_update`, over the spec
channel's name) on ``spec_channel`` (default ``trust/spec``) replaces the running spec
between two ticks, as on MQTT; every other update is refused (``"problems": ["swap
refused: ..."]`` on ``status_channel``), counted, logged and audited (``via`` ``redis``).
A checker without identities does not subscribe to the spec channel at all: anyone who
may publish on a Redis server could otherwise replace what the checker judges by.
:func:`redis_swap` sends a signed update and waits for the checker's status.

The connection: ``redis://`` or ``rediss://`` (TLS), a user name (an ACL user) and a
password (from an environment variable or a file, never from the config or the command
line), TLS with the server's CA and a client certificate and key, as
:class:`~trust_checker.config.RedisConfig` says; the password and the certificates are
read again, in a worker thread, at each connection.

Bad input (a payload the codec refuses, a spec update that is not one) is rejected:
counted by reason in ``stats.rejections`` (a :class:`rap_sdk.rejections.Rejections`),
logged rate-limited, and the next message is taken.

The connection is re-established after a loss (pauses doubling from 0.1 s up to
``reconnect_max``; each reconnection counted in ``stats.reconnects`` and logged); the
runner and its history live on in the session meanwhile. Outputs of ticks that happen
while disconnected are dropped and counted, and what was published on the input
channels meanwhile is lost (pub/sub keeps nothing). A checker that reads slower than its
inputs come is cut off by the server once its pending messages pass the server's
``client-output-buffer-limit pubsub`` (32 MiB by default), and reconnects.
"""

from __future__ import annotations

import logging
import ssl
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field
from functools import partial
from typing import Any, Final

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import TrustSpecStatus, TrustVerdict
from rap_schemas.limits import MAX_SAMPLE_BYTES, DecodeRejected, SafeDecoder
from rap_sdk.admin import Gate, audit
from rap_sdk.errors import ConfigError, QueryError
from rap_sdk.identity import AuthError, Caller, Signer
from rap_sdk.rejections import Rejections, Throttle
from redis.asyncio import ConnectionPool, Redis
from redis.asyncio.client import PubSub
from redis.asyncio.connection import Connection
from redis.asyncio.retry import Retry
from redis.backoff import NoBackoff
from redis.exceptions import AuthenticationError, NoPermissionError, RedisError

from ..config import RedisConfig
from .auth import SWAP_VERB, SignedSpecUpdate, outcome, signed_update, spec_summary, update_body
from .codec import CodecError, decode_payload, encode_value
from .credentials import read_credentials
from .ports import OutputLike
from .session import Session, SwapRequest
from .ticks import Arrival

__all__ = [
    "MAX_SPEC_BYTES",
    "RedisCredentials",
    "RedisTransport",
    "RedisTransportStats",
    "redis_credentials",
    "redis_swap",
]

log = logging.getLogger(__name__)

MAX_SPEC_BYTES: Final = MAX_SAMPLE_BYTES
"""Largest spec update taken on the spec channel (bytes of JSON)."""

_GLOB: Final = frozenset("*?[")
_BARRIER: Final = b"trust-checker-subscribed"
_decode_update: Callable[[bytes], SignedSpecUpdate] = SafeDecoder(
    SignedSpecUpdate, protocol="json", max_bytes=MAX_SPEC_BYTES, what="spec update"
).decode
_decode_status: Callable[[bytes], TrustSpecStatus] = SafeDecoder(
    TrustSpecStatus, protocol="json", max_bytes=MAX_SAMPLE_BYTES, what="spec status"
).decode
_encode = msgspec.json.Encoder().encode


@dataclass(frozen=True, slots=True)
class RedisCredentials:
    """What one connection presents: the password and the TLS context (None: none)."""

    password: str | None = field(default=None, repr=False)
    tls: ssl.SSLContext | None = None


def redis_credentials(
    config: RedisConfig, env: Mapping[str, str] | None = None
) -> RedisCredentials:
    """The password and TLS context ``config`` names, read now (files: call it in a worker
    thread from an event loop); :class:`rap_sdk.ConfigError` saying what is missing."""
    return RedisCredentials(*read_credentials("Redis", "--redis", config, env))


class _TlsConnection(Connection):
    """A TCP connection over TLS with a context made beforehand, in a worker thread
    (redis-py's own ``SSLConnection`` reads the certificate files in the event loop)."""

    def __init__(self, *, tls_context: ssl.SSLContext, **kwargs: Any) -> None:
        self._tls_context = tls_context
        super().__init__(**kwargs)

    def _connection_arguments(self) -> Mapping[str, Any]:
        return {**super()._connection_arguments(), "ssl": self._tls_context}


def _pool(config: RedisConfig, creds: RedisCredentials) -> ConnectionPool:
    """The connections of one session with the server: no retries of their own (the
    transport reconnects, counting it), each command bounded by ``config.timeout``."""
    host, port, db = config.address
    kwargs: dict[str, Any] = {
        "host": host,
        "port": port,
        "db": db,
        "username": config.username or None,
        "password": creds.password,
        "socket_timeout": config.timeout,
        "socket_connect_timeout": config.timeout,
        "client_name": _client_name(config.client_name) or None,
        "retry": Retry(NoBackoff(), 0),
    }
    if creds.tls is not None:
        return ConnectionPool(connection_class=_TlsConnection, tls_context=creds.tls, **kwargs)
    return ConnectionPool(**kwargs)


def _client_name(name: str) -> str:
    """A name ``CLIENT SETNAME`` takes (no spaces or control characters)."""
    return "".join(c if c.isascii() and c.isprintable() and c != " " else "_" for c in name)


def _clip(text: str, n: int = 200) -> str:
    return text if len(text) <= n else text[: n - 3] + "..."


def _hint(exc: BaseException) -> str:
    """A fix for a refused connection, when the error says what it is."""
    if isinstance(exc, AuthenticationError):
        return " - check the user name and the password (--redis-user, --redis-password-*)"
    if isinstance(exc, NoPermissionError):
        return " - the server's ACL does not let this user do that: check its channels (&...)"
    text = str(exc).lower()
    if "certificate" in text or "ssl" in text or "tls" in text:
        return " - check --redis-ca, --redis-cert and --redis-key, and the server's name"
    return ""


@dataclass(slots=True)
class RedisTransportStats:
    rejections: Rejections
    """Payloads refused (input values the codec cannot read, spec updates that are not
    one or not signed by an operator), counted by reason (``rejections.by_reason``,
    ``rejections.total``)."""
    connects: int = 0
    """Connections made (the first, then one per reconnection)."""
    reconnects: int = 0
    """Connections made again after one was lost or refused."""
    published: int = 0
    """Messages published (outputs, verdicts, statuses)."""
    streamed: int = 0
    """Verdicts added to ``verdict_stream``."""
    dropped: int = 0
    """Outputs, verdicts or statuses that could not be published or added (no
    connection, a server error)."""


class RedisTransport:
    """Feeds ``session`` from Redis pub/sub and publishes its results there (it adds
    itself to the session's sinks). Run :meth:`run` in a task group, next to
    ``session.run``."""

    def __init__(self, session: Session, config: RedisConfig, *, gate: Gate | None = None) -> None:
        self.session = session
        self.config = config
        self.gate = gate if gate is not None else Gate()
        """Who may swap the spec (default: ``RAP_CERTS``'s CA when it is set)."""
        self.swaps = bool(config.spec_channel) and self.gate.checks
        """Whether spec updates are read (only with identities, see the module doc)."""
        self.stats = RedisTransportStats(Rejections(f"{session.node} (redis)", log))
        self._throttle = Throttle()
        self._client: Redis | None = None
        self._pubsub: PubSub | None = None
        self._lock = anyio.Lock()
        """Held while the subscriptions change, and while a connection is torn down."""
        self._spec = config.spec_channel.encode()
        self._channels: dict[bytes, list[str]] = {}
        """Input channel -> the input streams it sets."""
        self._patterns: dict[bytes, list[str]] = {}
        """Input channel pattern -> the input streams it sets."""
        self._subscribed: tuple[set[bytes], set[bytes]] = (set(), set())
        """Channels and patterns subscribed on the current connection."""
        self.connected = anyio.Event()
        session.sinks.append(self)

    # -- routing ---------------------------------------------------------------------

    def _input_routes(
        self, inputs: Sequence[str]
    ) -> tuple[dict[bytes, list[str]], dict[bytes, list[str]]]:
        channels: dict[bytes, list[str]] = {}
        patterns: dict[bytes, list[str]] = {}
        for stream in inputs:
            name = self.config.channel_of(stream)
            routes = patterns if _GLOB.intersection(name) else channels
            routes.setdefault(name.encode(), []).append(stream)
        return channels, patterns

    async def _sync_subscriptions(self, pubsub: PubSub) -> None:
        """Subscribe to the running spec's input channels and patterns (and the spec
        channel); drop those no input needs any more. Sends the commands only: their
        answers come with the messages."""
        self._channels, self._patterns = self._input_routes(self.session.runner.inputs)
        channels, patterns = self._subscribed
        want_channels = set(self._channels)
        if self.swaps:
            want_channels.add(self._spec)
        want_patterns = set(self._patterns)
        if new := sorted(want_channels - channels):
            await pubsub.subscribe(*new)
        if new := sorted(want_patterns - patterns):
            await pubsub.psubscribe(*new)
        if gone := sorted(channels - want_channels):
            await pubsub.unsubscribe(*gone)
        if gone := sorted(patterns - want_patterns):
            await pubsub.punsubscribe(*gone)
        self._subscribed = (want_channels, want_patterns)
        log.debug("redis inputs: %s, patterns %s", self._channels, self._patterns)

    async def _settle(self, pubsub: PubSub) -> None:
        """Wait until the server has taken the subscriptions sent (the answer to a PING
        comes after theirs); messages that come meanwhile are taken."""
        await pubsub.ping(_BARRIER)
        with anyio.fail_after(self.config.timeout):
            while True:
                message = await pubsub.get_message(ignore_subscribe_messages=True, timeout=None)
                if message is None:
                    continue
                if message.get("type") == "pong":
                    if message.get("data") == _BARRIER:
                        return
                    continue
                await self._on_message(message)

    # -- the connection --------------------------------------------------------------

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Connect, subscribe, then take messages until cancelled; reconnect after a
        loss. ``task_status.started()`` once the first subscriptions are in place."""
        started = False
        pause = 0.1
        cfg = self.config
        host, port, db = cfg.address
        where = f"{host}:{port}/{db}"
        if cfg.spec_channel and not self.swaps:
            log.info(
                "redis: hot swap over Redis is off: this checker has no identities "
                "(--certs); swap over the fabric or MQTT, or give --certs"
            )
        while True:
            try:
                creds = await anyio.to_thread.run_sync(redis_credentials, cfg)
            except ConfigError as exc:
                if not started:
                    raise
                log.error("redis: %s; retrying in %.1f s", exc, pause)
                await anyio.sleep(pause)  # pacing: a file to be fixed, no event to wait on
                pause = min(pause * 2, cfg.reconnect_max)
                continue
            pool = _pool(cfg, creds)
            client = Redis(connection_pool=pool)
            pubsub = client.pubsub(ignore_subscribe_messages=True)
            try:
                self._client = client
                self._pubsub = pubsub  # a swap from now on changes its subscriptions
                async with self._lock:
                    self._subscribed = (set(), set())
                    await self._sync_subscriptions(pubsub)
                await self._settle(pubsub)
                self.stats.connects += 1
                pause = 0.1
                if started:
                    self.stats.reconnects += 1
                    log.warning(
                        "redis: reconnected to %s (reconnection %d)", where, self.stats.reconnects
                    )
                else:
                    log.info(
                        "redis: connected to %s%s%s",
                        where,
                        " over TLS" if creds.tls is not None else "",
                        f" as {cfg.username}" if cfg.username else "",
                    )
                self.connected.set()
                if not started:
                    started = True
                    task_status.started()
                while True:
                    message = await pubsub.get_message(ignore_subscribe_messages=True, timeout=None)
                    if message is not None:
                        await self._on_message(message)
            except (RedisError, OSError) as exc:  # TimeoutError is an OSError
                log.warning(
                    "redis: connection to %s lost or refused (%s: %s%s); retrying in %.1f s",
                    where,
                    type(exc).__name__,
                    str(exc) or "no answer in time",
                    _hint(exc),
                    pause,
                )
            finally:
                self._client = None
                self._pubsub = None
                self.connected = anyio.Event()
                with anyio.CancelScope(shield=True):
                    async with self._lock:
                        await _close(pubsub, client, pool)
            # pacing reconnection attempts (not waiting for an event: there is none)
            await anyio.sleep(pause)
            pause = min(pause * 2, cfg.reconnect_max)

    async def _on_message(self, message: Mapping[str, Any]) -> None:
        kind = message.get("type")
        data = message.get("data")
        channel = message.get("channel")
        if kind not in ("message", "pmessage") or type(data) is not bytes:
            return
        if type(channel) is not bytes:
            return
        name = _clip(channel.decode("utf-8", "replace"))
        if kind == "message":
            if self.swaps and channel == self._spec:
                await self._on_spec(name, data)
                return
            streams = self._channels.get(channel)
        else:
            streams = self._patterns.get(message.get("pattern") or b"")
        if not streams:
            return  # a channel no input of the running spec reads (any more)
        try:
            value = decode_payload(data)
        except CodecError as exc:
            self.stats.rejections.reject(name, exc.reason)
            return
        await self.session.submit(
            Arrival(dict.fromkeys(streams, value), self.session.clock.time_ns(), name)
        )

    async def _on_spec(self, channel: str, payload: bytes) -> None:
        node = self.session.node
        try:
            update = _decode_update(payload)
        except DecodeRejected as exc:
            reason = (
                f"spec update on {channel!r} refused: {exc.reason} - send "
                '{"spec": "<spec text>", "auth": {...}} as JSON, signed by an operator'
            )
            self.stats.rejections.reject(channel, reason)
            audit(
                verb=SWAP_VERB,
                component=node,
                result="error",
                caller=None,
                checked=self.gate.checks,
                key=channel,
                via="redis",
                request=f"{len(payload)} bytes",
                reason=reason,
            )
            await self._refuse(reason)
            return
        path = update.path if update.path != "<swap>" else f"<redis:{channel}>"
        what = spec_summary(update.spec, path)
        try:
            caller = await self.gate.check(
                channel,
                SWAP_VERB,
                update_body(update.spec, update.path),
                update.auth,
                scope=f"{node}:redis",
                what=f"swap the spec of {node}",
            )
        except AuthError as exc:
            self.stats.rejections.reject(channel, f"swap refused: {exc.kind} ({exc.reason})")
            audit(
                verb=SWAP_VERB,
                component=node,
                result="refused",
                caller=exc.caller,
                checked=True,
                key=channel,
                via="redis",
                request=what,
                reason=exc.reason,
                kind=exc.kind,
                throttle=self.gate.refusals,
            )
            await self._refuse(f"swap refused: {exc.reason}")
            return
        if caller is None:  # identities were configured, then could not be loaded: never
            self.stats.rejections.reject(channel, "swap refused: identities not loaded")
            await self._refuse("swap refused: this checker cannot check who signed it")
            return
        done = partial(self._audit, caller, channel, what)
        origin = f"{channel} from {caller}"
        await self.session.submit(SwapRequest(update.spec, path, origin, on_done=done))

    def _audit(self, caller: Caller, channel: str, what: str, st: TrustSpecStatus) -> None:
        result, reason = outcome(st)
        audit(
            verb=SWAP_VERB,
            component=self.session.node,
            result=result,
            caller=caller,
            checked=True,
            key=channel,
            via="redis",
            request=what,
            reason=reason,
        )

    async def _refuse(self, reason: str) -> None:
        """Answer a spec update that was not taken on the status channel."""
        runner = self.session.runner
        await self.status(
            TrustSpecStatus(
                ok=False,
                node=self.session.node,
                ts=self.session.clock.time_ns(),
                tick=runner.tick,
                problems=[reason],
                inputs=list(runner.inputs),
                outputs=list(runner.outputs),
            )
        )

    # -- the sink --------------------------------------------------------------------

    async def _send(self, messages: Sequence[tuple[str, bytes]], stream: bytes = b"") -> None:
        """Publish ``(channel, payload)`` messages in one round trip; with ``stream``,
        also add each payload to that Redis stream."""
        client = self._client
        n = sum(bool(channel) for channel, _ in messages) + (len(messages) if stream else 0)
        if not n:
            return
        if client is None:
            self.stats.dropped += n
            return
        try:
            async with client.pipeline(transaction=False) as pipe:
                for channel, payload in messages:
                    if channel:
                        pipe.publish(channel, payload)
                    if stream:
                        pipe.xadd(
                            stream,
                            {"verdict": payload},
                            maxlen=self.config.stream_maxlen,
                            approximate=True,
                        )
                results = await pipe.execute(raise_on_error=False)
        except (RedisError, OSError) as exc:
            self.stats.dropped += n
            self._warn("publish", "%d message(s) not published: %s%s", n, exc, _hint(exc))
            return
        for result in results:
            if isinstance(result, Exception):
                self.stats.dropped += 1
                self._warn("refused", "a message was refused by the server: %s", result)
            elif isinstance(result, int):
                self.stats.published += 1
            else:
                self.stats.streamed += 1

    def _warn(self, kind: str, msg: str, *args: object) -> None:
        n = self._throttle.hit(kind)
        if n:
            log.warning("redis: %s (%d like it since the last report)", msg % args, n)

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        tagged = self.config.tagged
        channel_of = self.config.channel_of
        await self._send(
            [(channel_of(o.stream), encode_value(o.value, tagged=tagged)) for o in outs]
        )

    async def verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        channel = self.config.verdict_channel
        stream = self.config.verdict_stream.encode()
        if channel or stream:
            await self._send([(channel, _encode(v)) for v in verdicts], stream)

    async def status(self, status: TrustSpecStatus) -> None:
        """Follow a new spec's inputs (the subscriptions are sent before the status, so
        that a sender told ``ok`` finds them in place), then say how the update went."""
        pubsub = self._pubsub
        if status.ok and pubsub is not None:
            try:
                async with self._lock:
                    if pubsub is self._pubsub:
                        await self._sync_subscriptions(pubsub)
            except (RedisError, OSError) as exc:  # the reconnect subscribes from scratch
                log.warning("redis: could not follow the new spec's inputs yet: %s", exc)
        # (a connection made later subscribes to the running spec's inputs)
        if self.config.status_channel:
            await self._send([(self.config.status_channel, _encode(status))])


async def _close(pubsub: PubSub, client: Redis, pool: ConnectionPool) -> None:
    """Close a session with the server, whatever state it is in."""
    for close in (pubsub.aclose, client.aclose, pool.aclose):
        try:
            await close()
        except (RedisError, OSError) as exc:
            log.debug("redis: closing: %s", exc)


async def redis_swap(
    config: RedisConfig,
    spec: str,
    *,
    node: str,
    signer: Signer | None = None,
    path: str = "<swap>",
    timeout: float = 10.0,
) -> TrustSpecStatus:
    """Ask the checker ``node`` reading ``config.spec_channel`` to run ``spec``, signed by
    ``signer`` when given (a checker takes only an operator's); its status (``ok``, or
    why not). Raises :class:`rap_sdk.QueryError` when no checker answers within
    ``timeout`` s or the server cannot be reached; :class:`rap_sdk.ConfigError` for
    credentials that cannot be read."""
    creds = await anyio.to_thread.run_sync(redis_credentials, config)
    channel = config.spec_channel
    if signer is not None:
        payload = signed_update(signer, channel, spec, path)
    else:
        payload = update_body(spec, path)
    host, port, db = config.address
    where = f"{host}:{port}/{db}"
    pool = _pool(config, creds)
    client = Redis(connection_pool=pool)
    pubsub = client.pubsub(ignore_subscribe_messages=True)
    try:
        await pubsub.subscribe(config.status_channel)
        await pubsub.ping(_BARRIER)
        with anyio.fail_after(timeout):
            while True:  # the subscription is in place once the PING is answered
                message = await pubsub.get_message(ignore_subscribe_messages=True, timeout=None)
                if message is not None and message.get("data") == _BARRIER:
                    break
            if not await client.publish(channel, payload):
                raise QueryError(
                    f"redis {where}: no one reads {channel!r} - is the checker --node {node} "
                    "running there with identities (--certs)? without them it takes no "
                    "swap over Redis"
                )
            while True:
                message = await pubsub.get_message(ignore_subscribe_messages=True, timeout=None)
                data = message.get("data") if message is not None else None
                if message is None or message.get("type") != "message" or type(data) is not bytes:
                    continue
                try:
                    status = _decode_status(data)
                except DecodeRejected:
                    continue
                if status.node == node:
                    return status
    except TimeoutError:
        raise QueryError(
            f"redis {where}: no status from --node {node} on {config.status_channel!r} "
            f"within {timeout:g} s - is the checker running there?"
        ) from None
    except (RedisError, OSError) as exc:
        raise QueryError(f"redis {where}: {exc}{_hint(exc)}") from None
    finally:
        with anyio.CancelScope(shield=True):
            await _close(pubsub, client, pool)

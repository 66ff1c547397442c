"""RPIO nodes as stages of a RAP loop (docs/migrating-from-rpio.md).

An RPIO 0.4.3 node (PyPI ``robosapiensio``, client library ``rpio.clientLibraries.rpclpy``)
keeps its knowledge in Redis keys (``write_knowledge``: SET of a string, JSON by
convention; ``read_knowledge``: GET, parsed as JSON when it is JSON) and exchanges
*events* (``publish_event``: a JSON object to which rpclpy adds ``uid`` and
``timestamp``) and *messages* (``publish_message``: any string) on Redis pub/sub
channels, or MQTT topics, named after the event or message. It runs unmodified, in its
own environment; an :class:`RpioStage` is the RAP node that stands in the loop for it.

One call of :meth:`Request.call`, from the RAP handler of the stage's trigger:

1. writes the knowledge the RPIO stage reads into its Redis, in RPIO's encoding (the
   handler has read it from RAP's knowledge, typed, and encoded it),
2. fires the RPIO stage's trigger: an event (a JSON object with ``uid``, ``timestamp``,
   the request's number under :attr:`RpioConfig.correlate` and ``rap_cycle``) or a
   message,
3. waits, up to :attr:`RpioConfig.timeout` seconds, for the stage's answer (one of the
   events or messages named) that belongs to this request,
4. reads the keys the stage wrote from Redis and decodes them, through the handler's
   decoders, into RAP's typed messages; the handler then writes them into RAP's
   knowledge and emits the RAP event, in the trigger's cycle (the envelope's ``cycle``
   and ``cause`` are the trigger's, and the knowledge versions it wrote travel with it).

What is guaranteed:

- One request at a time per stage: the next trigger's knowledge is written only after
  the answer to the last one came (or its time ran out), so the RPIO stage reads the
  knowledge of the cycle it answers, although RPIO's knowledge keeps one value per key.
- An answer belongs to the request whose number it carries (the field
  :attr:`RpioConfig.correlate` of the answering event or message, and of each taken
  knowledge value that is a JSON object): answers and values carrying another number
  are stale, counted, and passed over (an answer that carries no number is taken as
  the answer: RPIO itself orders nothing).
- RAP's cycle survives the round trip: RPIO's events carry no cause, so the RAP event
  is emitted in the cycle of the trigger it answers; the RPIO event the adapter fires
  has the trigger's uid as its ``uid`` and its cycle as ``rap_cycle``.
- Typed decoding at the boundary: an answer or a knowledge value that is not valid
  JSON, is too large (:attr:`RpioConfig.max_bytes`), is not an rpclpy event (an object
  with ``uid`` and ``timestamp`` strings), or that a decoder refuses, is rejected with
  the reason, counted (:attr:`RpioStats.rejections`) and logged (rate-limited); no input
  stops the node. Pickled knowledge (rpclpy's ``write_knowledge_as_object``) is refused:
  it is never unpickled.
- A missing RPIO stage is noticed at once on Redis (PUBLISH reached no subscriber:
  :attr:`RpioStats.absent`); an unanswered request after ``timeout``
  (:attr:`RpioStats.unanswered`). A lost Redis or broker is connected again, with
  backoff, by a later call (:attr:`RpioStats.unreachable`): a call waits out the
  backoff's pause when it ends within the call's ``timeout``, else it fails at once. A
  call that failed returns a false :class:`Reply` whose ``reason`` says why: the
  handler emits nothing (a Legitimate stage rejects the plan).

Not guaranteed: RPIO's events and messages are at most once (Redis pub/sub, MQTT QoS 0
as rpclpy publishes); an RPIO stage that answers some triggers with nothing makes the
RAP stage wait ``timeout`` each time; the RPIO stage's own effects beyond the keys and
answers named (other keys it writes, messages it publishes elsewhere) are not seen.
rpclpy 0.4.3 connects with neither password nor TLS, so neither does this adapter: keep
that Redis (and broker) on loopback or a private network.
"""

from __future__ import annotations

import json
import logging
import math
import uuid
from collections.abc import Callable, Collection, Mapping
from dataclasses import dataclass, field
from datetime import UTC, datetime
from functools import partial
from typing import Annotated, Any, Final, Protocol
from urllib.parse import urlsplit

import aiomqtt
import anyio
import msgspec
from rap_schemas.limits import MAX_SAMPLE_BYTES
from rap_sdk import Context, Node
from rap_sdk.rejections import Rejections, Throttle
from redis.asyncio import Redis
from redis.asyncio.retry import Retry
from redis.backoff import NoBackoff
from redis.exceptions import RedisError

from .core import Backoff

__all__ = [
    "CORRELATE",
    "Reply",
    "Request",
    "RpioConfig",
    "RpioStage",
    "RpioStats",
    "dumps",
    "loads",
]

log = logging.getLogger(__name__)

CORRELATE: Final = "seq"
"""The default field that carries a request's number through the RPIO stage (the RPIO
lidar-occlusion chain carries its scan's ``seq`` through knowledge and events)."""
Positive = Annotated[float, msgspec.Meta(gt=0, le=3600)]
PositiveInt = Annotated[int, msgspec.Meta(gt=0)]


class RpioConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    """Where the RPIO stage's Redis (and broker) are, and how long it may take. The
    config of an :class:`RpioStage`'s node: the model's ``config:`` of the component."""

    url: str = "redis://127.0.0.1:6379"
    """The Redis of the RPIO nodes (their ``Knowledge_Config``): ``redis://HOST:PORT``,
    optionally ``/DB`` (default 0)."""
    events: str = "redis"
    """Where events and messages travel: ``redis`` (pub/sub on ``url``'s server, RPIO's
    ``protocol: redis``) or ``mqtt://HOST:PORT`` (an MQTT broker, ``protocol: mqtt``)."""
    timeout: Positive = 1.0
    """Seconds to wait for the RPIO stage's answer to one request."""
    correlate: str = CORRELATE
    """The JSON field that carries the request's number (empty: none; answers are then
    taken in the order they come)."""
    max_bytes: PositiveInt = MAX_SAMPLE_BYTES
    """The largest answer or knowledge value taken (bytes)."""

    def __post_init__(self) -> None:
        _redis_address(self.url)
        if self.events != "redis":
            _mqtt_address(self.events)

    @property
    def host(self) -> str:
        return _redis_address(self.url)[0]

    @property
    def port(self) -> int:
        return _redis_address(self.url)[1]

    @property
    def db(self) -> int:
        return _redis_address(self.url)[2]


def _redis_address(url: str) -> tuple[str, int, int]:
    example = "redis://127.0.0.1:6379 (or redis://127.0.0.1:6379/0)"
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"url {url!r}: {exc} - write e.g. {example}") from None
    if parts.scheme != "redis":
        hint = (
            " (rpclpy 0.4.3 connects without TLS, so RPIO's Redis cannot require it)"
            if parts.scheme == "rediss"
            else ""
        )
        raise ValueError(f"url {url!r} is not a redis:// URL{hint} - write e.g. {example}")
    if not parts.hostname:
        raise ValueError(f"url {url!r} has no host - write e.g. {example}")
    if parts.username or parts.password or parts.query or parts.fragment:
        raise ValueError(
            f"url {url!r}: only host, port and database number are taken (rpclpy 0.4.3 "
            f"logs in with no password) - write e.g. {example}"
        )
    db = parts.path.strip("/") or "0"
    if not db.isdigit():
        raise ValueError(f"url {url!r}: the database {db!r} is not a number - write e.g. {example}")
    return parts.hostname, port if port is not None else 6379, int(db)


def _mqtt_address(url: str) -> tuple[str, int]:
    example = "mqtt://127.0.0.1:1883, or redis for Redis pub/sub"
    try:
        parts = urlsplit(url)
        port = parts.port
    except ValueError as exc:
        raise ValueError(f"events {url!r}: {exc} - write e.g. {example}") from None
    if parts.scheme != "mqtt" or not parts.hostname:
        raise ValueError(
            f"events {url!r} is neither redis nor mqtt://HOST:PORT - write e.g. {example}"
        )
    if parts.username or parts.password or parts.path not in ("", "/") or parts.query:
        raise ValueError(
            f"events {url!r}: only host and port are taken (rpclpy 0.4.3 connects to its "
            f"broker with no credentials) - write e.g. {example}"
        )
    return parts.hostname, port if port is not None else 1883


@dataclass(slots=True)
class RpioStats:
    """What an :class:`RpioStage` counts."""

    rejections: Rejections
    """Answers and knowledge values refused, by kind of reason and in all."""
    calls: int = 0
    """Requests made."""
    answered: int = 0
    """Requests whose answer came and decoded."""
    unanswered: int = 0
    """Requests with no answer within the timeout."""
    absent: int = 0
    """Requests whose trigger reached no RPIO node (Redis: nobody subscribes to it)."""
    stale: int = 0
    """Answers that belonged to no request in hand (late, or another's), passed over."""
    unreachable: int = 0
    """Requests that failed because Redis or the broker could not be reached."""
    connects: int = 0
    """Connections made to the RPIO side (the first one and every reconnect)."""


@dataclass(frozen=True, slots=True)
class Reply:
    """The RPIO stage's answer to one request: truthy when it came and decoded."""

    name: str = ""
    """The event or message that answered."""
    answer: Any = None
    """The answer decoded: the event's JSON object, or what ``decode`` made of it."""
    values: Mapping[str, Any] = field(default_factory=dict)
    """The knowledge values taken, as their decoders made them, by key."""
    reason: str | None = None
    """Why there is no answer (None: there is one)."""

    def __bool__(self) -> bool:
        return self.reason is None


def dumps(value: Any) -> bytes:
    """``value`` in RPIO's encoding: JSON as Python's ``json.dumps`` writes it (the
    encoding rpclpy nodes read back with ``json.loads``: ``Infinity`` and ``NaN`` for
    the non-finite numbers); a ``str`` or ``bytes`` value is written as it is."""
    if isinstance(value, bytes):
        return value
    if isinstance(value, str):
        return value.encode()
    return json.dumps(value, allow_nan=True, separators=(",", ":")).encode()


def loads(raw: bytes, *, max_bytes: int = MAX_SAMPLE_BYTES, what: str = "value") -> Any:
    """Parse one RPIO value as rpclpy's ``read_knowledge`` does (JSON when it is JSON,
    else the text), within ``max_bytes``; ``ValueError`` with the reason otherwise."""
    if len(raw) > max_bytes:
        raise ValueError(f"{what} of {len(raw)} bytes is over the limit of {max_bytes} (max_bytes)")
    if raw[:2] == b"\x80\x04" or raw[:2] == b"\x80\x05":
        raise ValueError(
            f"{what} is a pickled object (rpclpy's write_knowledge_as_object), which is never "
            "unpickled here: write it as JSON"
        )
    try:
        text = raw.decode()
    except UnicodeDecodeError:
        raise ValueError(f"{what} is not UTF-8 text") from None
    try:
        return json.loads(text)
    except RecursionError:
        raise ValueError(f"{what} nests too deeply") from None
    except ValueError:
        return text  # rpclpy hands such a value over as the string


def _event_object(raw: bytes, *, max_bytes: int, what: str) -> dict[str, Any]:
    value = loads(raw, max_bytes=max_bytes, what=what)
    if not isinstance(value, dict):
        raise ValueError(f"{what} is not a JSON object (an rpclpy event is one): {raw[:60]!r}")
    for name in ("uid", "timestamp"):  # what rpclpy's publish_event adds to every event
        if not isinstance(value.get(name), str):
            raise ValueError(
                f"{what} is not an rpclpy event: its {name!r} is "
                f"{'missing' if name not in value else type(value[name]).__name__}, not a string"
            )
    return value


class _Transport(Protocol):
    """Where events and messages travel (Redis pub/sub or MQTT)."""

    async def subscribe(self, names: Collection[str]) -> None: ...

    async def publish(self, name: str, payload: bytes) -> int | None:
        """Publish; the number of subscribers that got it when the transport says."""

    async def receive(self, timeout: float) -> tuple[str, bytes] | None: ...

    async def close(self) -> None: ...


class _RedisEvents:
    def __init__(self, client: Any) -> None:
        self.client = client
        self.pubsub: Any = None

    async def subscribe(self, names: Collection[str]) -> None:
        if self.pubsub is None:
            self.pubsub = self.client.pubsub(ignore_subscribe_messages=True)
        await self.pubsub.subscribe(*names)

    async def publish(self, name: str, payload: bytes) -> int | None:
        return int(await self.client.publish(name, payload))

    async def receive(self, timeout: float) -> tuple[str, bytes] | None:
        if self.pubsub is None:
            await anyio.sleep(timeout)
            return None
        msg = await self.pubsub.get_message(ignore_subscribe_messages=True, timeout=timeout)
        if msg is None or msg.get("type") != "message":
            return None
        channel = msg["channel"]
        name = channel.decode(errors="replace") if isinstance(channel, bytes) else str(channel)
        data = msg["data"]
        return name, data if isinstance(data, bytes) else str(data).encode()

    async def close(self) -> None:
        if self.pubsub is not None:
            pubsub, self.pubsub = self.pubsub, None
            await pubsub.aclose()


class _MqttEvents:
    def __init__(self, client: Any) -> None:
        self.client = client

    async def subscribe(self, names: Collection[str]) -> None:
        for name in names:
            await self.client.subscribe(name, qos=0)

    async def publish(self, name: str, payload: bytes) -> int | None:
        await self.client.publish(name, payload, qos=0)
        return None  # MQTT does not say who got it

    async def receive(self, timeout: float) -> tuple[str, bytes] | None:
        if timeout <= 0:
            if not len(self.client.messages):
                return None
            timeout = 1.0  # one is queued: taken at once (a wait cut at once takes none)
        with anyio.move_on_after(timeout):
            msg = await anext(self.client.messages)
            payload = msg.payload
            data = payload if isinstance(payload, bytes) else str(payload or "").encode()
            return str(msg.topic), data
        return None

    async def close(self) -> None:
        await self.client.__aexit__(None, None, None)


_LOST: Final = (OSError, TimeoutError, RedisError, aiomqtt.MqttError)
"""Errors of a connection to the RPIO side that failed or was lost."""


class RpioStage:
    """The RAP node standing for one RPIO stage: ``node`` is what the model's component
    names (``module: package.module:attribute``); its config is an :class:`RpioConfig`
    (the component's ``config:``). Handlers declared on ``node`` call
    ``stage.request(ctx).call(...)``; see the module's documentation."""

    def __init__(
        self,
        name: str,
        *,
        stage: str,
        config: RpioConfig | None = None,
        backoff: Backoff | None = None,
    ) -> None:
        self.node = Node(name, stage=stage, config=config or RpioConfig())
        self.stats = RpioStats(Rejections(f"rpio stage {name}", log))
        self.backoff = backoff or Backoff(initial=0.2, max=5.0)
        self._seq = 0
        self._lock: anyio.Lock | None = None
        self._redis: Any = None
        self._events: _Transport | None = None
        self._subscribed: set[str] = set()
        self._connected_to: RpioConfig | None = None
        self._retry_at = 0.0
        self._down = ""
        self._throttle = Throttle()

    @property
    def name(self) -> str:
        return self.node.name

    @property
    def config(self) -> RpioConfig:
        cfg = self.node.config
        assert isinstance(cfg, RpioConfig)
        return cfg

    def request(self, ctx: Context) -> Request:
        """A new request in ``ctx``'s cycle; its number is ``request.seq``."""
        self._seq += 1
        return Request(self, ctx, self._seq)

    # -- the connection --------------------------------------------------------------

    async def _connect(self, cfg: RpioConfig) -> None:
        await self.close()
        # built in a worker thread: redis-py's constructor reads its package's metadata
        client = await anyio.to_thread.run_sync(
            partial(
                Redis,
                host=cfg.host,
                port=cfg.port,
                db=cfg.db,
                socket_timeout=max(cfg.timeout, 1.0) + 1.0,
                socket_connect_timeout=2.0,
                retry=Retry(NoBackoff(), 0),  # retries are this stage's, with its backoff
                client_name=f"rap-rpio-{self.name}",
            )
        )
        try:
            await client.ping()
        except BaseException:
            await client.aclose()
            raise
        events: _Transport
        if cfg.events == "redis":
            events = _RedisEvents(client)
        else:
            host, port = _mqtt_address(cfg.events)
            mqtt = aiomqtt.Client(
                host, port, identifier=f"rap-rpio-{self.name}-{uuid.uuid4().hex[:8]}", timeout=5.0
            )
            try:
                await mqtt.__aenter__()
            except BaseException:
                await client.aclose()
                raise
            events = _MqttEvents(mqtt)
        self._redis, self._events = client, events
        self._connected_to = cfg
        self.stats.connects += 1
        self.backoff.reset()

    async def aclose(self) -> None:
        """Drop the connections (the next call makes them again): when the node stops
        (``async with contextlib.aclosing(stage)``), or they go with the process."""
        await self.close()

    async def close(self) -> None:
        """Drop the connections (the next call makes them again)."""
        redis, events = self._redis, self._events
        self._redis = self._events = None
        self._subscribed = set()
        self._connected_to = None
        with anyio.CancelScope(shield=True):
            for closing in (events.close if events else None, redis.aclose if redis else None):
                if closing is None:
                    continue
                try:
                    await closing()
                except (*_LOST, RuntimeError) as exc:
                    log.debug("rpio stage %s: closing: %s", self.name, exc)

    async def _ready(self, answers: Collection[str]) -> str | None:
        """Connected (and subscribed to ``answers``); else why not."""
        cfg = self.config
        if self._redis is not None and self._connected_to == cfg:
            missing = set(answers) - self._subscribed
            if missing:
                assert self._events is not None
                await self._events.subscribe(sorted(missing))
                self._subscribed |= missing
            return None
        now = anyio.current_time()
        pause = self._retry_at - now
        if pause > cfg.timeout:  # this request cannot wait that long: it fails now
            return f"{self._down}; connecting again in {pause:.1f} s"
        if pause > 0:
            await anyio.sleep(pause)  # the backoff's pause ends within this request's time
            now = anyio.current_time()
        try:
            await self._connect(cfg)
        except _LOST as exc:
            where = cfg.url if cfg.events == "redis" else f"{cfg.url} and {cfg.events}"
            self._down = f"cannot reach the RPIO side at {where}: {exc}"
            self._retry_at = now + self.backoff.next()
            return self._down + " - is it running, and is the address in the stage's config right?"
        log.info("rpio stage %s: connected to %s (events: %s)", self.name, cfg.url, cfg.events)
        return await self._ready(answers)

    async def _lost(self, exc: BaseException) -> str:
        self.stats.unreachable += 1
        self._down = f"lost the RPIO side at {self.config.url}: {type(exc).__name__}: {exc}"
        self._retry_at = anyio.current_time() + self.backoff.next()
        await self.close()
        return self._down

    def _lock_(self) -> anyio.Lock:
        if self._lock is None:
            self._lock = anyio.Lock()
        return self._lock

    def _reject(self, where: str, reason: str) -> None:
        self.stats.rejections.reject(where, reason)

    def _warn(self, reason: str) -> None:
        n = self._throttle.hit(reason[:60])
        if n:
            log.warning(
                "rpio stage %s: no answer (%d time(s) since the last report): %s",
                self.name,
                n,
                reason,
            )


class Request:
    """One request to the RPIO stage, in the cycle of the RAP handler call ``ctx``."""

    def __init__(self, stage: RpioStage, ctx: Context, seq: int) -> None:
        self.stage = stage
        self.ctx = ctx
        self.seq = seq
        """The request's number: put it in the knowledge written (where the RPIO stage
        carries it on), it comes back in the answer."""

    def event(self, data: Mapping[str, Any] | None = None) -> dict[str, Any]:
        """The JSON object of an RPIO event fired for this request: ``data``, the
        request's number, and what rpclpy adds (``uid``: the RAP trigger's uid;
        ``timestamp``), with ``rap_cycle``."""
        out = dict(data or {})
        corr = self.stage.config.correlate
        if corr:
            out[corr] = self.seq
        env = self.ctx.envelope
        out["uid"] = env.uid.hex()
        out["timestamp"] = datetime.now(UTC).isoformat()
        out["rap_cycle"] = self.ctx.cycle.hex()
        return out

    async def call(
        self,
        *,
        write: Mapping[str, Any] | None = None,
        event: str | None = None,
        data: Mapping[str, Any] | None = None,
        message: str | None = None,
        payload: Any = None,
        answer: str | Collection[str] = (),
        answer_message: str | Collection[str] = (),
        decode: Callable[[Any], Any] | None = None,
        take: Mapping[str, Callable[[Any], Any]] | None = None,
    ) -> Reply:
        """Write ``write`` (RPIO key -> value, see :func:`dumps`) into the RPIO Redis,
        fire ``event`` (with ``data``) or ``message`` (with ``payload``), wait for one of
        the events ``answer`` or messages ``answer_message`` names, decode it with
        ``decode`` (default: the JSON as it is; a decoder raises ``ValueError`` to
        refuse), then read and decode the keys ``take`` names (key -> decoder). A false
        :class:`Reply` says why when a step failed (counted in the stage's stats)."""
        if (event is None) == (message is None):
            raise ValueError("fire either an event or a message")
        events = _names(answer)
        messages = _names(answer_message)
        if not events and not messages:
            raise ValueError("name the events (answer=) or messages (answer_message=) that answer")
        if events & messages:
            raise ValueError(f"{sorted(events & messages)} named as both event and message")
        st = self.stage
        async with st._lock_():
            st.stats.calls += 1
            try:
                reply = await self._call(
                    write or {}, event, data, message, payload, events, messages, decode, take or {}
                )
            except _LOST as exc:
                reply = Reply(reason=await st._lost(exc))
            except anyio.get_cancelled_exc_class():
                await st.close()  # a half-read answer must not be taken for the next one's
                raise
            if reply:
                st.stats.answered += 1
            else:
                st._warn(reply.reason or "")
            return reply

    async def _call(
        self,
        write: Mapping[str, Any],
        event: str | None,
        data: Mapping[str, Any] | None,
        message: str | None,
        payload: Any,
        events: set[str],
        messages: set[str],
        decode: Callable[[Any], Any] | None,
        take: Mapping[str, Callable[[Any], Any]],
    ) -> Reply:
        st = self.stage
        cfg = st.config
        names = events | messages
        down = await st._ready(names)
        if down is not None:
            st.stats.unreachable += 1
            return Reply(reason=down)
        transport, redis = st._events, st._redis
        assert transport is not None
        assert redis is not None
        # what came after an earlier request's time ran out is nobody's now
        while (late := await transport.receive(0)) is not None:
            st.stats.stale += 1
            log.debug("rpio stage %s: passed over a late %s", st.name, late[0])
        if write:
            await redis.mset({k: dumps(v) for k, v in write.items()})
        fired = event if event is not None else message
        assert fired is not None
        body = dumps(self.event(data)) if event is not None else dumps(payload)
        if await transport.publish(fired, body) == 0:
            st.stats.absent += 1
            return Reply(
                reason=f"no RPIO node subscribes to {fired!r} at {cfg.url} (is the RPIO stage "
                "running, on this Redis and database?)"
            )
        deadline = anyio.current_time() + cfg.timeout
        while True:
            left = deadline - anyio.current_time()
            if left <= 0:
                st.stats.unanswered += 1
                return Reply(
                    reason=f"no {' or '.join(sorted(names))} from the RPIO stage within "
                    f"{cfg.timeout:g} s of {fired!r}"
                )
            got = await transport.receive(left)
            if got is None or got[0] not in names:
                continue
            name, raw = got
            kind = "event" if name in events else "message"
            where = f"{cfg.url} {kind} {name}"
            try:
                if kind == "event":
                    value = _event_object(raw, max_bytes=cfg.max_bytes, what=f"event {name!r}")
                else:
                    value = loads(raw, max_bytes=cfg.max_bytes, what=f"message {name!r}")
            except ValueError as exc:
                st._reject(where, str(exc))
                continue  # not an answer at all: the real one may still come
            if not self._ours(value):
                st.stats.stale += 1
                continue
            try:
                answer = decode(value) if decode is not None else value
            except (ValueError, TypeError, LookupError) as exc:
                reason = f"{kind} {name!r}: {_reason(exc)}"
                st._reject(where, reason)
                return Reply(name=name, reason=f"refused the RPIO stage's {reason}")
            break
        values: dict[str, Any] = {}
        if take:
            keys = list(take)
            raws = await redis.mget(keys)
            for key, raw_value in zip(keys, raws, strict=True):
                where = f"{cfg.url} knowledge {key}"
                if raw_value is None:
                    reason = f"knowledge {key!r} is not in the RPIO Redis after {name!r}"
                    st._reject(where, reason)
                    return Reply(name=name, answer=answer, reason=reason)
                try:
                    parsed = loads(raw_value, max_bytes=cfg.max_bytes, what=f"knowledge {key!r}")
                    if not self._ours(parsed):
                        raise ValueError(
                            f"it is of request {parsed.get(cfg.correlate)!r}, not of {self.seq} "
                            "(written by another, or not yet when the stage answered)"
                        )
                    values[key] = take[key](parsed)
                except (ValueError, TypeError, LookupError) as exc:
                    reason = f"knowledge {key!r}: {_reason(exc)}"
                    st._reject(where, reason)
                    return Reply(name=name, answer=answer, reason=f"refused {reason}")
        return Reply(name=name, answer=answer, values=values)

    def _ours(self, value: Any) -> bool:
        """Whether ``value`` belongs to this request (or says nothing of it)."""
        corr = self.stage.config.correlate
        if not corr or not isinstance(value, dict) or corr not in value:
            return True
        number = value[corr]
        return (
            isinstance(number, int | float)
            and not isinstance(number, bool)
            and math.isfinite(number)
            and number == self.seq
        )


def _names(names: str | Collection[str]) -> set[str]:
    return {names} if isinstance(names, str) else set(names)


def _reason(exc: BaseException) -> str:
    text = str(exc) or type(exc).__name__
    if isinstance(exc, LookupError):
        return f"missing {text}"
    return text[:500]

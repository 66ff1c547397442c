"""The Redis links: pub/sub (protocol ``redis``) and streams (``redis-stream``)
(docs/bridges/redis.md).

Each link is one connection of redis-py's asyncio client (RESP2), which retries nothing
itself: a lost connection is the bridge's to make again, with its backoff. A connection
that carries nothing is checked with PING every :data:`PING_S` s, so that a bridge
notices a lost Redis within about a second even while it has nothing to send.

Pub/sub (``redis``):

- ``out``: each message is published with PUBLISH on the channel ``address``; it counts
  as sent once Redis answered (with the number of subscribers that got it). While Redis
  is away messages wait in the bridge's buffer and are published once it is back; a
  message whose answer a lost connection cut off is published again (at least once, to
  Redis). Redis keeps nothing: a subscriber that is not connected when a message is
  published never gets it. QoS 0 and 1 are alike.
- ``in``: the link subscribes to ``address`` (SUBSCRIBE; PSUBSCRIBE when it is a glob
  pattern, with ``*``, ``?`` or ``[``). At most once: what is published while the bridge
  is reconnecting is lost, by Redis itself. So an ``in`` bridge takes ``qos: 0`` only;
  QoS 1 is refused with a pointer to ``redis-stream``.
- Pub/sub messages have no headers. Format ``envelope``: the envelope's bytes, which carry
  type, sender, cycle and cause themselves. Formats ``json`` and ``raw``: a message
  leaves *wrapped*, as a map of exactly two entries in the format's own encoding (a JSON
  object, a msgpack map): ``headers`` (the ``rap-*`` headers, string to string) and
  ``payload`` (the message itself, as an object, not as a string)::

      {"headers": {"rap-type": "rap.Battery/1", "rap-source": "bms", "rap-cycle": "..."},
       "payload": {"voltage": 24.1}}

  An incoming message may be wrapped so, or plain (the message alone, as
  ``redis-cli PUBLISH robot.cmd '{"speed": 0.5}'`` sends it). A map whose keys are
  exactly ``headers`` and ``payload`` is taken as wrapped, anything else as plain.

Streams (``redis-stream``):

- ``out``: each message is added with XADD to the stream ``address`` as an entry with
  the field ``payload`` (the message in the spec's format) and one field per header
  (``rap-type``, ``rap-source``, ``rap-cycle``, ``rap-cause``); with ``maxlen``, trimmed
  to about that many entries (``MAXLEN ~``). It counts as sent once Redis answered with
  the entry's id; one whose answer was cut off is added again after the reconnect (at
  least once). A Redis that persists (``appendonly yes``) keeps what it acknowledged
  across a restart.
- ``in``: the link reads with XREADGROUP as consumer ``<bridge name>`` of the consumer
  group ``group`` (default ``rap-bridge-<bridge name>``), created with MKSTREAM when
  missing, at the stream's end (``$``: entries added before the group existed are not
  read). An entry is acknowledged (XACK) once the bridge has it in its buffer; after a
  reconnect the entries given to this consumer and not acknowledged are read again
  first (at least once). An entry is read as its ``payload`` field (required) and its
  other fields as headers (UTF-8). An entry the link cannot take (no ``payload``,
  fields that are not UTF-8, deleted before it was read) is rejected, counted and
  acknowledged: it would fail again.

Both: ``username`` with ``password_env`` or ``password_file`` (Redis ACL users; with a
bare ``requirepass`` the user is ``default``), read at each connection; TLS with
``rediss://`` and ``ca``/``cert``/``key``.
"""

from __future__ import annotations

import logging
import re
import ssl
from collections.abc import Callable, Mapping
from typing import Any, Final

import anyio
import msgspec
from rap_schemas.limits import DECODE_ERRORS, decode_failure
from redis.asyncio.connection import Connection
from redis.exceptions import AuthenticationError, NoPermissionError, RedisError, ResponseError

from .core import Deliver, Frame, LinkContext, LinkDown
from .credentials import link_credentials
from .spec import BridgeSpec

__all__ = [
    "BATCH",
    "BLOCK_MS",
    "HEADER_ROOM",
    "PING_S",
    "BadMessage",
    "RedisLink",
    "RedisStreamLink",
    "Wrapped",
    "is_pattern",
    "unwrap",
    "wrap",
]

log = logging.getLogger(__name__)

TIMEOUT_S: Final = 10.0
"""How long a connection or an answer may take before the link counts as lost."""
PING_S: Final = 1.0
"""A connection that carried nothing this long is checked with PING."""
BLOCK_MS: Final = 1000
"""How long one XREADGROUP waits for new entries before it asks again."""
BATCH: Final = 100
"""Stream entries read at a time."""
HEADER_ROOM: Final = 64 * 1024
"""What a wrapped pub/sub message may hold beside its payload (``max_frame``)."""
PAYLOAD: Final = "payload"
"""The stream entry's field, and the wrapped message's entry, that holds the message."""
PATTERN_CHARS: Final = frozenset("*?[")


class Wrapped(msgspec.Struct, frozen=True):
    """A pub/sub message with its headers (formats ``json`` and ``raw``)."""

    headers: dict[str, str]
    payload: msgspec.Raw
    """The message, as it is in the format (a JSON value, msgpack bytes)."""


class BadMessage(Exception):
    """A message the link cannot take (the reason)."""


_WRAP: Final[dict[str, Callable[[Any], bytes]]] = {
    "json": msgspec.json.Encoder().encode,
    "raw": msgspec.msgpack.Encoder().encode,
}
_TOP: Final[dict[str, Callable[[bytes], dict[str, msgspec.Raw]]]] = {
    "json": msgspec.json.Decoder(dict[str, msgspec.Raw]).decode,
    "raw": msgspec.msgpack.Decoder(dict[str, msgspec.Raw]).decode,
}
_HEADERS: Final[dict[str, Callable[[msgspec.Raw], dict[str, str]]]] = {
    "json": msgspec.json.Decoder(dict[str, str]).decode,
    "raw": msgspec.msgpack.Decoder(dict[str, str]).decode,
}
_MARK: Final = {"json": b'"headers"', "raw": b"\xa7headers"}
"""What a wrapped message holds for sure (the key ``headers``), in each encoding."""
_WRAPPED_KEYS: Final = frozenset({"headers", PAYLOAD})


def is_pattern(channel: str) -> bool:
    """Whether a channel name is a glob pattern (subscribed with PSUBSCRIBE)."""
    return not PATTERN_CHARS.isdisjoint(channel)


def wrap(frame: Frame, fmt: str) -> bytes:
    """A pub/sub message's bytes: the envelope as it is, else :class:`Wrapped`."""
    if fmt == "envelope":
        return frame.payload
    return _WRAP[fmt](Wrapped(dict(frame.headers), msgspec.Raw(frame.payload)))


def unwrap(data: bytes, fmt: str) -> Frame:
    """The frame of a pub/sub message, wrapped or plain; :class:`BadMessage` for a
    wrapped one whose headers are not a map of strings."""
    if fmt == "envelope" or _MARK[fmt] not in data:
        return Frame(data)
    try:
        parts = _TOP[fmt](data)
    except DECODE_ERRORS:
        return Frame(data)  # not a map: plain, and the bridge's decoder says what is wrong
    if parts.keys() != _WRAPPED_KEYS:
        return Frame(data)
    try:
        headers = _HEADERS[fmt](parts["headers"])
    except DECODE_ERRORS as exc:
        raise BadMessage(
            f"a wrapped message's headers must map strings to strings: {decode_failure(exc)}"
        ) from None
    return Frame(bytes(parts[PAYLOAD]), headers)


def _fix(exc: BaseException, spec: BridgeSpec) -> str:
    text = str(exc).lower()
    if isinstance(exc, AuthenticationError) or "wrongpass" in text or "noauth" in text:
        return (
            "check username and password_env / password_file (with a bare requirepass "
            "the user is default)"
        )
    if isinstance(exc, NoPermissionError) or "noperm" in text:
        return (
            f"give user {spec.username or 'default'} the command and "
            f"{'channel' if spec.protocol == 'redis' else 'key'} {spec.address!r} in "
            "Redis's ACL"
        )
    if "wrongtype" in text:
        return f"key {spec.address!r} holds something else than a stream - use another address"
    if "certificate" in text or "ssl" in text or "tls" in text:
        return "check ca, cert and key, and that Redis's certificate names its host"
    if "connect" in text or "timeout" in text or "closed" in text or "refused" in text:
        return f"is redis-server running and reachable at {spec.host}:{spec.port}?"
    return ""


def _new_connection(spec: BridgeSpec) -> Connection:
    """A connection (not yet made) as ``spec`` says, its password and TLS files read now:
    call it in a worker thread (redis-py also reads its own package's metadata here)."""
    password, tls = link_credentials(spec, "Redis")
    options: dict[str, Any] = {
        "host": spec.host,
        "port": spec.port,
        "username": spec.username,
        "password": password,
        "socket_timeout": TIMEOUT_S,
        "socket_connect_timeout": TIMEOUT_S,
        "protocol": 2,
    }
    return Connection(**options) if tls is None else _TlsConnection(tls, **options)


def _client_name(bridge: str) -> str:
    """The connection's name in Redis's CLIENT LIST (no spaces allowed)."""
    return "rap-bridge-" + re.sub(r"[^\w.:-]", "_", bridge)


class _TlsConnection(Connection):
    """A TLS connection with a context made beforehand (in a worker thread: redis-py's
    own would load the certificate files on the event loop)."""

    def __init__(self, context: ssl.SSLContext, **kwargs: Any) -> None:
        self._tls = context
        super().__init__(**kwargs)

    def _connection_arguments(self) -> Mapping[str, Any]:
        return {**super()._connection_arguments(), "ssl": self._tls}


class _RedisLink:
    """One Redis connection for one bridge: connect, ask, watch, drop."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        self.spec = spec
        self.ctx = ctx
        self._conn: Connection | None = None
        self._lock: anyio.Lock | None = None

    @property
    def where(self) -> str:
        return self.spec.where

    async def _connect(self) -> None:
        await self._drop()
        spec = self.spec
        conn = await anyio.to_thread.run_sync(_new_connection, spec)
        try:
            await conn.connect()  # type: ignore[no-untyped-call]
            await conn.send_command("CLIENT", "SETNAME", _client_name(self.ctx.name))
            await conn.send_command("PING")  # (also: is the password right?)
            try:
                await conn.read_response()
            except ResponseError:
                pass  # a user without +client|setname: the name is a courtesy
            await conn.read_response()
        except (RedisError, OSError) as exc:
            await _disconnect(conn)
            raise LinkDown(f"cannot connect: {exc}", _fix(exc, spec)) from None
        except anyio.get_cancelled_exc_class():  # the bridge stops while it connects
            await _disconnect(conn)
            raise
        self._conn = conn
        self._lock = anyio.Lock()

    async def _call(self, *args: Any, allow: str = "") -> Any:
        """Send one command and return its answer; :class:`LinkDown` when the connection
        is lost or Redis refuses the command (an error starting with ``allow`` is
        returned instead)."""
        conn, lock = self._conn, self._lock
        if conn is None or lock is None or not conn.is_connected:
            raise LinkDown("not connected")
        async with lock:
            try:
                await conn.send_command(*args)
                return await conn.read_response()
            except ResponseError as exc:
                if allow and str(exc).startswith(allow):
                    return exc
                raise LinkDown(f"Redis refused {args[0]}: {exc}", _fix(exc, self.spec)) from None
            except (RedisError, OSError) as exc:
                raise LinkDown(f"connection lost: {exc}", _fix(exc, self.spec)) from None

    async def _watch(self) -> None:
        """An ``out`` link's run: PING now and then, so that a lost connection is noticed
        while nothing is sent."""
        while True:
            await anyio.sleep(PING_S)
            await self._call("PING")

    async def close(self) -> None:
        await self._drop()

    async def _drop(self) -> None:
        conn, self._conn = self._conn, None
        if conn is not None:
            await _disconnect(conn)


async def _disconnect(conn: Connection) -> None:
    with anyio.move_on_after(TIMEOUT_S, shield=True):
        try:
            await conn.disconnect()
        except (RedisError, OSError):
            pass  # already gone: nothing to say goodbye to


class RedisLink(_RedisLink):
    """Redis pub/sub for one bridge (see the module's documentation)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        super().__init__(spec, ctx)
        self.pattern = is_pattern(spec.address)
        if ctx.direction == "in" and spec.qos > 0:
            raise ValueError(
                f"Redis pub/sub delivers at most once, so an in bridge on {spec.address!r} "
                f"cannot be qos {spec.qos} (at least once): messages published while it "
                "reconnects are lost by Redis - write qos: 0, or use protocol: redis-stream "
                "for at least once"
            )
        if ctx.direction == "out" and self.pattern:
            raise ValueError(
                f"an out bridge publishes on one channel: {spec.address!r} is a pattern "
                "(it has *, ? or [) - name the channel"
            )
        self._unheard = False

    async def open(self) -> None:
        await self._connect()
        if self.ctx.direction == "in":
            command = "PSUBSCRIBE" if self.pattern else "SUBSCRIBE"
            try:
                await self._call(command, self.spec.address)
            except LinkDown:
                await self._drop()
                raise

    async def run(self, deliver: Deliver) -> None:
        if self.ctx.direction == "out":
            await self._watch()
        conn = self._conn
        if conn is None:
            raise LinkDown("not connected")
        pinged = False
        while True:
            try:
                item = await conn.read_response(timeout=TIMEOUT_S if pinged else PING_S)
                if item is None:  # nothing for a while: is the connection still there?
                    if pinged:
                        raise LinkDown(
                            f"Redis did not answer a PING within {TIMEOUT_S:g} s",
                            f"is redis-server running and reachable at {self.spec.host}:"
                            f"{self.spec.port}?",
                        )
                    await conn.send_command("PING")
                    pinged = True
                    continue
            except (RedisError, OSError) as exc:
                raise LinkDown(f"connection lost: {exc}", _fix(exc, self.spec)) from None
            pinged = False
            if not isinstance(item, list) or not item:
                continue
            kind = item[0]
            if kind == b"message" and len(item) == 3:
                data = item[2]
            elif kind == b"pmessage" and len(item) == 4:
                data = item[3]
            else:
                continue  # a PING's answer, a subscription's confirmation
            frame = self._frame(data)
            if frame is not None:
                await deliver(frame)

    def _frame(self, data: object) -> Frame | None:
        if not isinstance(data, bytes):
            self.ctx.reject(f"a pub/sub message of type {type(data).__name__}, not bytes")
            return None
        limit = self.spec.max_frame + HEADER_ROOM
        if len(data) > limit:
            self.ctx.reject(
                f"message of {len(data)} bytes is over the limit of {limit} (max_frame "
                f"{self.spec.max_frame} + {HEADER_ROOM} for headers)"
            )
            return None
        try:
            return unwrap(data, self.spec.format)
        except BadMessage as exc:
            self.ctx.reject(str(exc))
            return None

    async def send(self, frame: Frame) -> None:
        receivers = await self._call("PUBLISH", self.spec.address, wrap(frame, self.spec.format))
        if receivers == 0 and not self._unheard:
            log.info(
                "%s: no subscriber listens; Redis drops what is published while none does",
                self.where,
            )
        self._unheard = receivers == 0


class RedisStreamLink(_RedisLink):
    """A Redis stream for one bridge (see the module's documentation)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        super().__init__(spec, ctx)
        if ctx.direction == "in" and spec.maxlen is not None:
            raise ValueError(
                "maxlen trims the stream an out bridge adds to; an in bridge only reads - "
                "remove maxlen (trim with the bridge that adds, or XTRIM)"
            )
        if ctx.direction == "out" and spec.group is not None:
            raise ValueError(
                "group names the consumer group an in bridge reads with; an out bridge "
                "only adds entries - remove group"
            )
        self.group = spec.group or f"rap-bridge-{ctx.name}"
        self.consumer = ctx.name

    async def open(self) -> None:
        await self._connect()
        if self.ctx.direction == "in":
            try:
                await self._call(
                    "XGROUP",
                    "CREATE",
                    self.spec.address,
                    self.group,
                    "$",
                    "MKSTREAM",
                    allow="BUSYGROUP",  # it exists: go on where it is
                )
            except LinkDown:
                await self._drop()
                raise

    async def run(self, deliver: Deliver) -> None:
        if self.ctx.direction == "out":
            await self._watch()
        key, group = self.spec.address, self.group
        head = ["XREADGROUP", "GROUP", group, self.consumer, "COUNT", BATCH]
        after: str | None = "0"  # first what this consumer was given and did not acknowledge
        while True:
            if after is not None:
                entries = _entries(await self._call(*head, "STREAMS", key, after))
                if not entries:
                    after = None
                    continue
            else:
                reply = await self._call(*head, "BLOCK", BLOCK_MS, "STREAMS", key, ">")
                entries = _entries(reply)
            for entry_id, fields in entries:
                frame = self._frame(entry_id, fields)
                if frame is not None:
                    await deliver(frame)
                await self._call("XACK", key, group, entry_id)
                if after is not None:
                    after = entry_id.decode()

    def _frame(self, entry_id: bytes, fields: object) -> Frame | None:
        what = f"entry {entry_id.decode(errors='replace')}"
        if not isinstance(fields, list):
            self.ctx.reject(f"{what} was deleted (the stream trimmed) before it was read")
            return None
        if len(fields) % 2 or not all(isinstance(f, bytes) for f in fields):
            self.ctx.reject(f"{what}: its fields are not name/value pairs")
            return None
        payload: bytes | None = None
        headers: dict[str, str] = {}
        for name, value in zip(fields[::2], fields[1::2], strict=True):
            if name == b"payload":
                payload = value
                continue
            try:
                headers[name.decode()] = value.decode()
            except UnicodeDecodeError:
                self.ctx.reject(f"{what}: field {name[:40]!r} is not UTF-8 text")
                return None
        if payload is None:
            self.ctx.reject(
                f"{what} has no field {PAYLOAD!r} - write the message in it "
                f"(XADD {self.spec.address} * {PAYLOAD} <message>)"
            )
            return None
        return Frame(payload, headers)

    async def send(self, frame: Frame) -> None:
        args: list[Any] = ["XADD", self.spec.address]
        if self.spec.maxlen is not None:
            args += ["MAXLEN", "~", self.spec.maxlen]
        args += ["*", PAYLOAD, frame.payload]
        for name, value in frame.headers.items():
            if name != PAYLOAD:
                args += [name, value]
        await self._call(*args)


def _entries(reply: object) -> list[tuple[bytes, object]]:
    """The entries of an XREADGROUP answer (one stream): (id, fields or None)."""
    if not isinstance(reply, list):
        return []  # nil: nothing came within the block time
    found: list[tuple[bytes, object]] = []
    for stream in reply:
        if isinstance(stream, list) and len(stream) == 2 and isinstance(stream[1], list):
            found.extend(
                (entry[0], entry[1])
                for entry in stream[1]
                if isinstance(entry, list) and len(entry) == 2 and isinstance(entry[0], bytes)
            )
    return found

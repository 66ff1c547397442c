"""The AMQP 0-9-1 link (aio-pika; RabbitMQ and other AMQP 0-9-1 brokers).

- ``out``: each message is published to ``exchange`` ("": the default exchange) with
  ``address`` as its routing key; on the default exchange ``address`` is a queue, which
  the link declares (durable) when it connects, so that messages wait there for their
  consumers. Cycle, cause, wire type and sender go in the message's AMQP headers
  (``rap-cycle``, ``rap-cause``: 32 hex digits; ``rap-type``, ``rap-source``); the
  content type is ``application/json`` (format ``json``) or ``application/msgpack``.
  At QoS >= 1 the channel is in publisher-confirm mode, messages are persistent
  (delivery mode 2) and mandatory, and a message counts as sent once the broker
  confirmed it (``basic.ack``); one whose confirmation was cut off by a lost connection
  is published again after the reconnect (at least once). A message the broker refuses
  (``basic.nack``: a full queue that rejects publishes, say) is kept and published
  again after a reconnect. A message no queue takes is returned by the broker: on the
  default exchange the queue is gone, and the link reconnects (which declares it
  again); on a named exchange no queue is bound for the routing key, and the message is
  rejected (counted, logged) and dropped. At QoS 0 messages are transient and
  unconfirmed.
- ``in``: the link consumes the queue ``address``, declared durable when it is missing
  (a queue that exists is used as it is: a quorum queue, say); with ``exchange`` the
  queue is bound to it with ``address`` as the routing key. At most ``buffer`` (up to
  65535) messages are in flight unacknowledged (the consumer's prefetch). At QoS >= 1 a
  message is acknowledged once the bridge has taken it (``deliver`` returned): one that
  was not when the connection was lost is delivered again by the broker (at least
  once). At QoS 0 it is acknowledged as it is taken from the link's queue (at most once).
  Header values that are not strings are passed on as their text (the bridge's checks
  reject a malformed ``rap-cycle``); the payload is the message body.
- A lost connection or channel (the broker stopped, a channel error, the consumer
  cancelled by the broker because the queue was deleted) ends :meth:`AmqpLink.run` with
  :class:`LinkDown`: the connection is a plain one (not aio-pika's robust connection),
  the bridge reconnects and counts. Heartbeats (:data:`HEARTBEAT_S`) find a broker that
  went away silently within about half a minute.
- Credentials: ``username`` with ``password_env`` or ``password_file`` (read at each
  connection, never from the spec; no username: RabbitMQ's ``guest``, which it accepts
  on loopback only); TLS with ``amqps://`` and ``ca``/``cert``/``key``. The virtual host
  is ``/``.
"""

from __future__ import annotations

import math
import ssl
from dataclasses import dataclass
from typing import Any, Final

import aio_pika
import aiormq
import anyio
from aio_pika.abc import (
    AbstractChannel,
    AbstractConnection,
    AbstractExchange,
    AbstractIncomingMessage,
    AbstractQueue,
    DeliveryMode,
)
from anyio.streams.memory import MemoryObjectReceiveStream, MemoryObjectSendStream

from .core import Deliver, Frame, FrameRefused, LinkContext, LinkDown
from .credentials import link_credentials
from .spec import BridgeSpec

__all__ = [
    "HEARTBEAT_S",
    "MAX_PREFETCH",
    "NAME_MAX",
    "TIMEOUT_S",
    "AmqpLink",
    "amqp_credentials",
    "check_names",
]

TIMEOUT_S: Final = 10.0
"""How long a connection, declaration or confirmation may take before the link counts
as lost."""
HEARTBEAT_S: Final = 10
"""The heartbeat asked of the broker (s): a connection silent for about three of them
(aiormq's grace, half a minute) is lost."""
MAX_PREFETCH: Final = 65535
"""The largest prefetch AMQP can say (a short): an ``in`` link's is ``min(buffer, this)``."""

_ERRORS: Final = (
    aiormq.exceptions.AMQPError,
    RuntimeError,  # a closed connection or channel (ChannelInvalidStateError is one)
    OSError,  # ConnectionError, ssl.SSLError
    TimeoutError,
)
"""What aio-pika raises when the broker, the network or a channel fails (aio-pika's own
list of connection errors has RuntimeError too)."""
NAME_MAX: Final = 255
"""The longest queue, exchange or routing key AMQP can carry (bytes of UTF-8)."""

_PERMISSIONS: Final = "rabbitmqctl set_permissions -p / {user} '.*' '.*' '.*'"


def amqp_credentials(spec: BridgeSpec) -> tuple[str | None, ssl.SSLContext | None]:
    """The password and TLS context ``spec`` names, read now (it reads files: call it in
    a worker thread); :class:`LinkDown` saying what to fix otherwise."""
    return link_credentials(spec, "AMQP")


def _vhost_refused(exc: BaseException) -> bool:
    """The broker closed the connection in answer to Connection.Open: the user may not
    use the virtual host (aiormq reports it as an unexpected frame, without the text)."""
    text = str(exc)
    return isinstance(exc, aiormq.exceptions.ConnectionNotAllowed) or (
        isinstance(exc, aiormq.exceptions.InvalidFrameError)
        and "Connection.OpenOk" in text
        and "Connection.Close" in text
    )


def _describe(exc: BaseException) -> str:
    """An aio-pika error in words (its reply code and text, when the broker sent them)."""
    if _vhost_refused(exc) and isinstance(exc, aiormq.exceptions.InvalidFrameError):
        return "the broker refused access to virtual host / (it closed the connection)"
    if isinstance(exc, aiormq.exceptions.AMQPError) and not isinstance(
        exc, aiormq.exceptions.DeliveryError
    ):
        text = " ".join(str(a) for a in exc.args if a not in (None, ""))
    else:
        text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


def _fix(exc: BaseException, spec: BridgeSpec) -> str:
    user = spec.username or "guest"
    exceptions = aiormq.exceptions
    text = _describe(exc).lower()
    if isinstance(exc, exceptions.ChannelAccessRefused):
        return (
            "the user may not configure, write or read this queue or exchange: "
            + _PERMISSIONS.format(user=user)
        )
    if _vhost_refused(exc):
        return f"give the user access to the virtual host: {_PERMISSIONS.format(user=user)}"
    if isinstance(exc, exceptions.ConnectionClosed) and exc.args and exc.args[0] == 320:
        return "the broker was stopped, or an operator closed the connection; reconnecting"
    if (
        isinstance(exc, (exceptions.AuthenticationError, exceptions.ProbableAuthenticationError))
        or "access_refused" in text
        or "login" in text
    ):
        return (
            "check username and password_env / password_file (rabbitmqctl "
            f"authenticate_user {user} <password> tells whether the broker takes them)"
        )
    if isinstance(exc, ssl.SSLError) or "certificate" in text or "ssl" in text:
        return "check ca, cert and key, and that the broker's certificate names its host"
    if isinstance(exc, (OSError, TimeoutError)):
        return f"is the broker running and reachable at {spec.host}:{spec.port}?"
    return ""


def _text(value: object) -> str:
    """A header value as text (AMQP headers are typed; RAP's are strings)."""
    if isinstance(value, str):
        return value
    if isinstance(value, (bytes, bytearray)):
        return bytes(value).decode("utf-8", errors="replace")
    return str(value)


@dataclass(slots=True)
class _Session:
    """One connection and what was set up on it."""

    connection: AbstractConnection
    lost: anyio.Event
    reason: str = ""
    fix: str = ""
    channel: AbstractChannel | None = None
    exchange: AbstractExchange | None = None
    incoming: MemoryObjectReceiveStream[AbstractIncomingMessage] | None = None
    feed: MemoryObjectSendStream[AbstractIncomingMessage] | None = None

    def down(self, reason: str, fix: str = "") -> None:
        if not self.lost.is_set():
            self.reason, self.fix = reason, fix
            self.lost.set()


def check_names(spec: BridgeSpec, direction: str) -> None:
    """ValueError when ``address`` or ``exchange`` cannot be an AMQP name here, saying
    what to write instead."""
    for what, name in (("address", spec.address), ("exchange", spec.exchange)):
        if len(name.encode()) > NAME_MAX:
            raise ValueError(
                f"an amqp {what} is at most {NAME_MAX} bytes, {name[:40]!r}... has "
                f"{len(name.encode())} - write a shorter one"
            )
    is_queue = direction == "in" or not spec.exchange
    if is_queue and spec.address.startswith("amq."):
        raise ValueError(
            f"queue names starting with 'amq.' are the broker's: {spec.address!r} - choose "
            "another address"
        )


class AmqpLink:
    """An AMQP 0-9-1 connection for one bridge (see the module's documentation)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        check_names(spec, ctx.direction)
        self.spec = spec
        self.ctx = ctx
        self._session: _Session | None = None
        self._content_type = "application/json" if spec.format == "json" else "application/msgpack"
        self._delivery_mode = DeliveryMode.PERSISTENT if spec.qos else DeliveryMode.NOT_PERSISTENT

    @property
    def where(self) -> str:
        if self.spec.exchange:
            return f"{self.spec.where} (exchange {self.spec.exchange})"
        return self.spec.where

    # -- connecting -------------------------------------------------------------------------

    async def open(self) -> None:
        await self._drop()
        spec = self.spec
        password, tls = await anyio.to_thread.run_sync(amqp_credentials, spec)
        try:
            with anyio.fail_after(TIMEOUT_S):
                connection = await aio_pika.connect(
                    host=spec.host,
                    port=spec.port,
                    login=spec.username or "guest",
                    password=(password or "") if spec.username else "guest",
                    ssl=spec.tls,
                    ssl_context=tls,
                    timeout=TIMEOUT_S,
                    client_properties={"connection_name": f"rap-bridge-{self.ctx.name}"},
                    heartbeat=HEARTBEAT_S,
                )
        except _ERRORS as exc:
            raise LinkDown(f"cannot connect: {_describe(exc)}", _fix(exc, spec)) from None
        session = self._session = _Session(connection, anyio.Event())

        def closed(_sender: object, exc: BaseException | None = None) -> None:
            why = _describe(exc) if exc is not None else "closed"
            session.down(f"the connection was lost: {why}", _fix(exc, spec) if exc else "")

        connection.close_callbacks.add(closed)
        try:
            with anyio.fail_after(TIMEOUT_S):
                if self.ctx.direction == "out":
                    await self._set_up_out(session)
                else:
                    await self._set_up_in(session)
        except LinkDown:
            await self._drop()
            raise
        except _ERRORS as exc:
            await self._drop()
            raise LinkDown(
                f"cannot set up {self.where}: {_describe(exc)}", _fix(exc, spec)
            ) from None

    async def _channel(self, session: _Session) -> AbstractChannel:
        """A new channel (publisher confirms for an ``out`` link at QoS >= 1)."""
        confirms = self.ctx.direction == "out" and self.spec.qos > 0
        channel = session.connection.channel(publisher_confirms=confirms)
        await channel.initialize(timeout=TIMEOUT_S)
        return channel

    def _watch(self, session: _Session, channel: AbstractChannel) -> None:
        """Count the link as lost when ``channel`` closes."""
        spec = self.spec

        def closed(_sender: object, exc: BaseException | None = None) -> None:
            why = _describe(exc) if exc is not None else "closed"
            session.down(f"the channel was closed: {why}", _fix(exc, spec) if exc else "")

        channel.close_callbacks.add(closed)
        session.channel = channel

    async def _check_exchange(self, session: _Session) -> AbstractChannel:
        """A channel, once ``exchange`` is known to exist."""
        name = self.spec.exchange
        channel = await self._channel(session)
        try:
            await channel.declare_exchange(name, passive=True, timeout=TIMEOUT_S)
        except aiormq.exceptions.ChannelNotFoundEntity:
            raise LinkDown(
                f"exchange {name!r} does not exist",
                f"declare it (rabbitmqadmin declare exchange name={name} type=topic "
                "durable=true) or correct exchange in the spec",
            ) from None
        return channel

    async def _queue(
        self, session: _Session, channel: AbstractChannel
    ) -> tuple[AbstractChannel, AbstractQueue]:
        """The queue ``address`` as it is, or declared durable when it is missing, and
        the channel to use it on."""
        try:
            return channel, await channel.declare_queue(
                self.spec.address, passive=True, timeout=TIMEOUT_S
            )
        except aiormq.exceptions.ChannelNotFoundEntity:
            pass  # the broker closed that channel
        channel = await self._channel(session)
        return channel, await channel.declare_queue(
            self.spec.address, durable=True, timeout=TIMEOUT_S
        )

    async def _set_up_out(self, session: _Session) -> None:
        if self.spec.exchange:
            channel = await self._check_exchange(session)
            session.exchange = await channel.get_exchange(self.spec.exchange, ensure=False)
        else:
            channel, _ = await self._queue(session, await self._channel(session))
            session.exchange = channel.default_exchange
        self._watch(session, channel)

    async def _set_up_in(self, session: _Session) -> None:
        spec = self.spec
        first = await (self._check_exchange(session) if spec.exchange else self._channel(session))
        channel, queue = await self._queue(session, first)
        self._watch(session, channel)
        await channel.set_qos(prefetch_count=min(spec.buffer, MAX_PREFETCH), timeout=TIMEOUT_S)
        if spec.exchange:
            await queue.bind(spec.exchange, routing_key=spec.address, timeout=TIMEOUT_S)
        feed, incoming = anyio.create_memory_object_stream[AbstractIncomingMessage](math.inf)
        session.feed, session.incoming = feed, incoming

        async def take(message: AbstractIncomingMessage) -> None:
            # no await before the message is queued: deliveries keep their order
            try:
                feed.send_nowait(message)
            except (anyio.ClosedResourceError, anyio.BrokenResourceError):
                pass  # the link let this connection go: the broker delivers it again

        def cancelled(_frame: Any) -> None:
            session.down(
                f"the broker cancelled the consumer of queue {spec.address!r} (deleted?)",
                "it is declared again on reconnecting",
            )

        underlay = await channel.get_underlay_channel()
        underlay.on_consumer_cancel_callbacks.add(cancelled)
        await queue.consume(take, no_ack=False, timeout=TIMEOUT_S)

    # -- running ------------------------------------------------------------------------

    async def run(self, deliver: Deliver) -> None:
        session = self._session
        if session is None:
            raise LinkDown("not connected")
        incoming = session.incoming
        async with anyio.create_task_group() as tg:
            if incoming is not None:
                tg.start_soon(self._consume, session, incoming, deliver)
            await session.lost.wait()
            tg.cancel_scope.cancel()
        raise LinkDown(session.reason, session.fix)

    async def _consume(
        self,
        session: _Session,
        incoming: MemoryObjectReceiveStream[AbstractIncomingMessage],
        deliver: Deliver,
    ) -> None:
        early = self.spec.qos == 0  # at most once: acknowledged before it is handed over
        async for message in incoming:
            headers = {str(k): _text(v) for k, v in (message.headers or {}).items()}
            try:
                if early:
                    await message.ack()
                await deliver(Frame(message.body, headers))
                if not early:
                    await message.ack()
            except _ERRORS as exc:
                session.down(f"cannot acknowledge a message: {_describe(exc)}")
                return

    async def send(self, frame: Frame) -> None:
        session = self._session
        exchange = session.exchange if session is not None else None
        if session is None or exchange is None:
            raise LinkDown("not connected")
        if session.lost.is_set():
            raise LinkDown(session.reason, session.fix)
        spec = self.spec
        message = aio_pika.Message(
            frame.payload,
            headers=dict(frame.headers),
            content_type=self._content_type,
            delivery_mode=self._delivery_mode,
        )
        try:
            result = await exchange.publish(
                message, spec.address, mandatory=spec.qos > 0, timeout=TIMEOUT_S
            )
        except aiormq.exceptions.DeliveryError as exc:  # basic.nack
            raise LinkDown(
                f"the broker refused a message ({exc})",
                f"a queue that rejects publishes when full? make room in {spec.address!r} "
                "or raise its max-length; see the broker's log",
            ) from None
        except TimeoutError:
            raise LinkDown(
                f"the broker did not confirm a message within {TIMEOUT_S:g} s",
                "is it blocking publishers (a memory or disk alarm: rabbitmq-diagnostics alarms)?",
            ) from None
        except _ERRORS as exc:
            raise LinkDown(f"publication failed: {_describe(exc)}", _fix(exc, spec)) from None
        if isinstance(result, aiormq.abc.DeliveredMessage):  # basic.return: unroutable
            if not spec.exchange:
                raise LinkDown(
                    f"queue {spec.address!r} is gone (the broker returned a message)",
                    "it is declared again on reconnecting",
                )
            raise FrameRefused(
                f"no queue is bound to exchange {spec.exchange!r} for routing key "
                f"{spec.address!r}: the message was dropped - bind a queue to it"
            )

    async def close(self) -> None:
        await self._drop()

    async def _drop(self) -> None:
        session, self._session = self._session, None
        if session is None:
            return
        session.down("the link was closed")
        if session.feed is not None:
            session.feed.close()
        if session.incoming is not None:
            session.incoming.close()  # unacknowledged: the broker delivers them again
        with anyio.CancelScope(shield=True), anyio.move_on_after(TIMEOUT_S):
            try:
                await session.connection.close()
            except _ERRORS:
                pass  # already gone: nothing to say goodbye to

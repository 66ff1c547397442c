"""The NATS link (nats-py; docs/bridges/nats.md).

- QoS 0, core NATS: ``out`` publishes each message on the subject ``address`` with
  cycle, cause, wire type and sender as NATS headers (``rap-cycle``, ``rap-cause``: 32
  hex digits; ``rap-type``, ``rap-source``); a message counts as sent once it is handed
  to the connection (at most once: one the connection loses is lost). ``in``
  subscribes to ``address`` (wildcards ``*`` and ``>`` allowed) and reads those headers;
  what is published while the bridge is away is not kept for it.
- QoS >= 1, JetStream: the stream ``stream`` holds the subject; with no ``stream`` in
  the spec, the stream the server already has for the subject, else
  ``rap-<subject, every character but letters, digits, - and _ made _>``. A stream that
  is missing is created, with file storage and the subject ``address``.

  ``out``: ``js.publish``: a message counts as sent once the server acknowledged that
  the stream stored it; one whose acknowledgement a lost connection cut off is
  published again after the reconnect, with the same ``Nats-Msg-Id`` (this link's id
  and a number), so that the stream stores it once (within its duplicate window, two
  minutes by default).

  ``in``: a durable pull consumer named ``group`` (None: ``rap-bridge-<bridge name>``)
  with explicit acknowledgement, filtered on ``address``. A message is acknowledged once
  the bridge has taken it (it is in the buffer, then on the fabric); one not yet
  acknowledged when the connection (or the server) goes is delivered again after the
  reconnect (at least once). A consumer made now starts with the messages published
  from now on (deliver policy ``new``); it is kept by the server, with its position,
  across restarts of the server and of the bridge.
- Reconnecting is the bridge's (backoff, counting): nats-py's own reconnect is off, and
  a lost connection ends ``run`` with :class:`LinkDown`.
- Credentials: ``username`` with ``password_env`` or ``password_file`` (read at each
  connection, in a worker thread, never from the spec); TLS with ``tls://`` and
  ``ca``/``cert``/``key``.
"""

from __future__ import annotations

import logging
import os
import re
import ssl
from typing import Any, Final

import anyio
import nats.errors
import nats.js.errors
from nats.aio.client import Client
from nats.aio.msg import Msg
from nats.aio.subscription import Subscription
from nats.js import JetStreamContext
from nats.js.api import AckPolicy, ConsumerConfig, DeliverPolicy, Header, StorageType

from .core import Deliver, Frame, FrameRefused, LinkContext, LinkDown
from .credentials import link_credentials
from .spec import BridgeSpec

__all__ = ["NatsLink", "derived_name"]

log = logging.getLogger(__name__)

TIMEOUT_S: Final = 10.0
"""How long a connection, a JetStream request or an acknowledgement may take before the
link counts as lost."""
FETCH_S: Final = 5.0
"""How long one pull of an ``in`` consumer waits for messages before it asks again."""
BATCH: Final = 100
"""Messages asked for at once by an ``in`` consumer."""
CLOSE_S: Final = 2.0
"""How long closing a connection may take (it flushes what is still buffered)."""
PING_S: Final = 10
"""Seconds between the client's pings; two unanswered ones end the connection."""

_NOT_NAME = re.compile(r"[^A-Za-z0-9_-]")


def derived_name(prefix: str, text: str) -> str:
    """A JetStream stream or consumer name made of ``text`` (no ``.``, ``*``, ``>``,
    spaces or slashes in it)."""
    return prefix + _NOT_NAME.sub("_", text)


def _wildcard(subject: str) -> bool:
    return any(token in ("*", ">") for token in subject.split("."))


def _why(exc: BaseException) -> str:
    text = getattr(exc, "strerror", None) or str(exc)
    return text if text and text != "None" else type(exc).__name__


def _fix(exc: BaseException, spec: BridgeSpec) -> str:
    text = f"{type(exc).__name__} {exc}".lower()
    if isinstance(exc, nats.errors.AuthorizationError) or "authori" in text:
        return "check username and password_env / password_file"
    if isinstance(exc, nats.errors.SecureConnRequiredError) or (
        isinstance(exc, ssl.SSLError) and not spec.tls
    ):
        return f"the server asks for TLS: write tls://{spec.host}:{spec.port} (and ca)"
    if "certificate" in text or "ssl" in text or "tls" in text:
        return "check ca, cert and key, and that the server's certificate names its host"
    if isinstance(exc, OSError | TimeoutError | nats.errors.NoServersError):
        return f"is nats-server running and reachable at {spec.host}:{spec.port}?"
    return ""


def _jetstream_fix(exc: BaseException) -> str:
    if isinstance(exc, nats.errors.NoRespondersError | nats.js.errors.ServiceUnavailableError):
        return "the server has no JetStream: start nats-server with -js, or use qos: 0"
    return ""


class NatsLink:
    """A NATS connection for one bridge (see the module's documentation)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        subject = spec.address
        if any(c.isspace() for c in subject) or "" in subject.split("."):
            raise ValueError(
                f"NATS subject {subject!r} is malformed: write tokens separated by dots, "
                "without spaces, e.g. address: robot.scan"
            )
        if ctx.direction == "out" and _wildcard(subject):
            raise ValueError(
                f"an out bridge publishes on one subject: {subject!r} has a wildcard (* or >)"
            )
        self.spec = spec
        self.ctx = ctx
        self.jetstream = spec.qos > 0
        self.durable = spec.group or derived_name("rap-bridge-", ctx.name)
        """The ``in`` consumer's name (JetStream)."""
        self.stream: str | None = spec.stream
        """The JetStream stream (known once connected)."""
        self.sender = os.urandom(8).hex()
        """This link's id in ``Nats-Msg-Id``."""
        self._seq = -1
        self._last: tuple[Frame, str] | None = None
        self._nc: Client | None = None
        self._js: JetStreamContext | None = None
        self._sub: Subscription | None = None
        self._pull: JetStreamContext.PullSubscription | None = None
        self._lost: anyio.Event | None = None
        self._error: BaseException | None = None

    @property
    def where(self) -> str:
        return self.spec.where

    @property
    def _url(self) -> str:
        spec = self.spec
        host = f"[{spec.host}]" if ":" in spec.host else spec.host
        return f"{'tls' if spec.tls else 'nats'}://{host}:{spec.port}"

    # -- connecting --------------------------------------------------------------------

    async def open(self) -> None:
        await self._drop()
        spec = self.spec
        password, tls = await anyio.to_thread.run_sync(link_credentials, spec, "NATS")
        lost = anyio.Event()
        self._error = None

        async def on_lost() -> None:
            lost.set()

        async def on_error(exc: Exception) -> None:
            if isinstance(exc, nats.errors.SlowConsumerError):  # one call per message
                self.ctx.reject(  # counted, and logged at most once a second
                    "the NATS client dropped a message: the bridge is a slow consumer "
                    "(its pending limit is full) - raise buffer, or see why the fabric is slow"
                )
                return
            self._error = exc
            log.debug("bridge %s: %s: %s", self.ctx.name, self.where, exc)

        options: dict[str, Any] = {}
        if tls is not None:
            options["tls"] = tls
        if spec.username:
            options["user"] = spec.username
            options["password"] = password or ""
        nc = Client()
        try:
            with anyio.fail_after(TIMEOUT_S + 1):
                await nc.connect(
                    servers=[self._url],
                    name=f"rap-bridge-{self.ctx.name}",
                    allow_reconnect=False,
                    max_reconnect_attempts=0,
                    connect_timeout=int(TIMEOUT_S),
                    ping_interval=PING_S,
                    max_outstanding_pings=2,
                    error_cb=on_error,
                    disconnected_cb=on_lost,
                    closed_cb=on_lost,
                    **options,
                )
        except (OSError, TimeoutError, nats.errors.Error) as exc:
            # bounded: after a failed TLS handshake nats-py's close waits for a transport
            # that never reports itself closed (the socket is closed already)
            with anyio.CancelScope(shield=True), anyio.move_on_after(0.25):
                await nc.close()
            raise LinkDown(f"cannot connect: {_why(exc)}", _fix(exc, spec)) from None
        except anyio.get_cancelled_exc_class():  # the bridge stops while it connects
            with anyio.CancelScope(shield=True), anyio.move_on_after(0.25):
                await nc.close()
            raise
        self._nc, self._lost = nc, lost
        try:
            if self.jetstream:
                await self._open_jetstream(nc)
            elif self.ctx.direction == "in":
                self._sub = await nc.subscribe(spec.address)
        except LinkDown:
            await self._drop()
            raise
        except (OSError, TimeoutError, nats.errors.Error) as exc:
            await self._drop()
            fix = _jetstream_fix(exc)
            raise LinkDown(
                f"cannot {'set up JetStream for' if self.jetstream else 'subscribe to'} "
                f"{spec.address!r}: {'no JetStream answered' if fix else _why(exc)}",
                fix or "check the subject and the server's permissions",
            ) from None

    async def _open_jetstream(self, nc: Client) -> None:
        js = self._js = nc.jetstream(timeout=TIMEOUT_S)
        subject = self.spec.address
        stream = self.spec.stream
        if stream is None:
            try:
                stream = await js.find_stream_name_by_subject(subject)
            except nats.js.errors.NotFoundError:
                stream = derived_name("rap-", subject)
                await self._create_stream(js, stream)
        else:
            try:
                await js.stream_info(stream)
            except nats.js.errors.NotFoundError:
                await self._create_stream(js, stream)
        self.stream = stream
        if self.ctx.direction == "in":
            config = ConsumerConfig(
                durable_name=self.durable,
                ack_policy=AckPolicy.EXPLICIT,
                deliver_policy=DeliverPolicy.NEW,
                filter_subject=subject,
            )
            try:
                self._pull = await js.pull_subscribe(
                    subject, durable=self.durable, stream=stream, config=config
                )
            except nats.js.errors.APIError as exc:
                raise LinkDown(
                    f"cannot make the consumer {self.durable} on stream {stream}: {exc}",
                    "check that the stream holds the subject (address) and group names no "
                    "consumer of another subject",
                ) from None

    async def _create_stream(self, js: JetStreamContext, stream: str) -> None:
        subject = self.spec.address
        try:
            await js.add_stream(name=stream, subjects=[subject], storage=StorageType.FILE)
        except nats.js.errors.APIError as exc:
            if isinstance(exc, nats.js.errors.ServiceUnavailableError):
                raise
            raise LinkDown(
                f"cannot create the JetStream stream {stream} for {subject!r}: {exc}",
                "does another stream hold an overlapping subject? name the stream with "
                "stream: <name>",
            ) from None
        log.info(
            "bridge %s: created the JetStream stream %s (file storage) for %s",
            self.ctx.name,
            stream,
            subject,
        )

    # -- receiving ---------------------------------------------------------------------

    def _lost_reason(self) -> str:
        nc = self._nc
        error = self._error or (nc.last_error if nc is not None else None)
        return f"connection lost: {_why(error)}" if error is not None else "connection lost"

    async def run(self, deliver: Deliver) -> None:
        nc, lost = self._nc, self._lost
        if nc is None or lost is None:
            raise LinkDown("not connected")
        try:
            if self._pull is not None:
                await self._pull_loop(self._pull, deliver)
            elif self._sub is not None:
                async for msg in self._sub.messages:
                    await deliver(Frame(msg.data, dict(msg.headers or {})))
            else:
                await lost.wait()
        except (OSError, nats.errors.Error) as exc:
            if isinstance(exc, nats.errors.ConnectionClosedError):
                raise LinkDown(self._lost_reason(), _fix(self._error or exc, self.spec)) from None
            raise LinkDown(f"connection lost: {_why(exc)}", _jetstream_fix(exc)) from None
        raise LinkDown(self._lost_reason(), _fix(self._error, self.spec) if self._error else "")

    async def _pull_loop(self, pull: JetStreamContext.PullSubscription, deliver: Deliver) -> None:
        nc = self._nc
        while nc is not None and not nc.is_closed:
            try:
                msgs: list[Msg] = await pull.fetch(BATCH, timeout=FETCH_S)
            except nats.errors.TimeoutError:
                continue  # nothing new: ask again
            for msg in msgs:
                await deliver(Frame(msg.data, dict(msg.headers or {})))
                await msg.ack()

    # -- sending -----------------------------------------------------------------------

    def _msg_id(self, frame: Frame) -> str:
        last = self._last
        if last is not None and last[0] is frame:
            return last[1]  # the same frame again (after a reconnect): the same id
        self._seq += 1
        msg_id = f"{self.sender}-{self._seq}"
        self._last = (frame, msg_id)
        return msg_id

    async def send(self, frame: Frame) -> None:
        nc = self._nc
        if nc is None:
            raise LinkDown("not connected")
        if len(frame.payload) > nc.max_payload:
            raise FrameRefused(
                f"message of {len(frame.payload)} bytes is over the server's max_payload "
                f"({nc.max_payload}); not sent"
            )
        headers = dict(frame.headers)
        try:
            if self._js is not None:
                headers[Header.MSG_ID.value] = self._msg_id(frame)
                await self._js.publish(
                    self.spec.address,
                    frame.payload,
                    timeout=TIMEOUT_S,
                    stream=self.stream,
                    headers=headers,
                )
            else:
                await nc.publish(self.spec.address, frame.payload, headers=headers or None)
        except nats.errors.BadHeaderError as exc:
            raise FrameRefused(f"a header NATS cannot carry: {exc}; not sent") from None
        except nats.errors.TimeoutError:
            raise LinkDown(
                f"the server did not acknowledge within {TIMEOUT_S:g} s",
                "is nats-server (JetStream) healthy?",
            ) from None
        except nats.js.errors.NoStreamResponseError:
            raise LinkDown(
                f"no JetStream stream took the message on {self.spec.address!r}",
                "was the stream deleted? it is made again at the next connection",
            ) from None
        except (OSError, nats.errors.Error) as exc:
            if nc.is_closed:
                raise LinkDown(self._lost_reason()) from None
            raise LinkDown(f"publication failed: {_why(exc)}", _jetstream_fix(exc)) from None

    # -- closing -----------------------------------------------------------------------

    async def close(self) -> None:
        await self._drop()

    async def _drop(self) -> None:
        nc, self._nc = self._nc, None
        self._js = self._sub = self._pull = None
        if nc is None:
            return
        with anyio.CancelScope(shield=True), anyio.move_on_after(CLOSE_S):
            try:
                await nc.close()
            except (OSError, nats.errors.Error) as exc:
                log.debug("bridge %s: closing %s: %s", self.ctx.name, self.where, exc)

"""The WebSocket link (websockets, asyncio API; docs/bridges/websocket.md).

Messages:

- a **binary** message is one frame: every integer big-endian ::

      hlen    u16   the length of the header map
      headers       hlen bytes: a JSON object of string -> string, UTF-8 (hlen 0: none)
      payload       the message, in the spec's format

  (the TCP frame without its u32 length: a WebSocket message is delimited already).
  Every message the link sends is binary.
- a **text** message is taken as a bare payload without headers (its UTF-8 bytes), so
  that a browser or ``websocat`` can send JSON (format ``json``). It is never numbered
  and never acknowledged.

Headers RAP uses: ``rap-cycle``, ``rap-cause`` (32 hex digits), ``rap-type``,
``rap-source``; and at QoS >= 1, as over TCP, ``rap-seq`` (a decimal number, growing
per sender) with ``rap-sender`` (the sender's id). A binary message that carries
``rap-seq`` is acknowledged once the receiver has taken it (or rejected it for good)
with a binary message of empty payload whose only header is ``rap-ack`` (the same
number). A sender at QoS >= 1 sends one message at a time and waits for its
acknowledgement (10 s); after a reconnect it sends the unacknowledged message again
with the same number, and the receiver passes over a number it has taken already from
that sender: nothing is lost across a restart of the other side, and nothing reaches
the fabric twice.

A binary message whose header part is malformed, or whose payload is over
``max_frame``, is rejected and counted, and the next message is read. A message over
``max_frame`` + 64 KiB is refused by websockets itself, which closes the connection
(code 1009); it is counted as a rejection and the connection is made again (a client
of a serving bridge is dropped). A text message that is not UTF-8 closes the
connection the same way (code 1007).

Client mode (``ws://host:port``, ``address`` the path, default ``/``) reconnects through
the bridge. Server mode (``serve: true``) listens on the URL's address (with
``address`` set, only on that path: other paths get HTTP 404), takes any number of
clients, sends each outgoing message to every client (waiting for a first client while
there is none; a client that takes nothing for 10 s is dropped) and takes messages from
all.

TLS: ``wss://``. A client verifies the server with ``ca`` (None: the system's CAs) and
shows ``cert``/``key`` when given; a serving bridge needs ``cert``/``key`` (its own
certificate) and, with ``ca``, admits only clients whose certificate ``ca`` signed.
"""

from __future__ import annotations

import logging
import ssl
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, Final

import anyio
import msgspec
from rap_schemas.limits import DECODE_ERRORS
from websockets.asyncio.client import connect
from websockets.asyncio.connection import Connection
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed, InvalidHandshake, InvalidStatus, InvalidURI
from websockets.frames import CloseCode
from websockets.http11 import Request, Response

from .core import Deliver, Frame, FrameRefused, LinkContext, LinkDown
from .sequencing import HEADER_ACK, Acks, Sequencer, to_every_peer
from .spec import BridgeSpec
from .tcp import HEADER_ROOM

__all__ = [
    "BadMessage",
    "WebSocketLink",
    "decode_message",
    "encode_message",
    "websocket_tls",
]

log = logging.getLogger(__name__)

TIMEOUT_S: Final = 10.0
"""How long a handshake or an acknowledgement may take before the link counts as lost."""
CLOSE_TIMEOUT_S: Final = 2.0
"""How long a closing handshake may take."""

_HLEN = struct.Struct(">H")
_encode_headers = msgspec.json.Encoder().encode
_decode_headers: Callable[[bytes], dict[str, str]] = msgspec.json.Decoder(dict[str, str]).decode


def encode_message(payload: bytes, headers: dict[str, str] | None = None) -> bytes:
    """One binary message's bytes (the format above)."""
    h = _encode_headers(headers) if headers else b""
    if len(h) > 0xFFFF:
        raise ValueError(f"message headers of {len(h)} bytes: at most 65535")
    return _HLEN.pack(len(h)) + h + payload


class BadMessage(Exception):
    """A message that cannot be taken (its header part, its size)."""


def decode_message(data: bytes | str, max_payload: int) -> tuple[dict[str, str], bytes]:
    """The headers and payload of one message (text: no headers); :class:`BadMessage`."""
    headers: dict[str, str] = {}
    if isinstance(data, str):
        payload = data.encode("utf-8")
    else:
        if len(data) < 2:
            raise BadMessage(
                f"binary message of {len(data)} byte(s) cannot hold its header length "
                "(2 bytes; send JSON as a text message instead)"
            )
        (hlen,) = _HLEN.unpack_from(data)
        if 2 + hlen > len(data):
            raise BadMessage(
                f"binary message says {hlen} bytes of headers but holds {len(data) - 2}"
            )
        if hlen:
            try:
                headers = _decode_headers(data[2 : 2 + hlen])
            except DECODE_ERRORS as exc:
                raise BadMessage(f"message headers are not a JSON map of strings: {exc}") from None
        payload = bytes(data[2 + hlen :])
    if len(payload) > max_payload:
        raise BadMessage(f"payload of {len(payload)} bytes is over max_frame {max_payload}")
    return headers, payload


def websocket_tls(spec: BridgeSpec) -> ssl.SSLContext:
    """The TLS context of a ``wss://`` spec, read now (it reads files: call it in a worker
    thread); :class:`LinkDown` saying what to fix otherwise."""
    try:
        if spec.serve:
            context = ssl.create_default_context(ssl.Purpose.CLIENT_AUTH)
            context.load_cert_chain(str(spec.cert), spec.key)
            if spec.ca:
                context.load_verify_locations(spec.ca)
                context.verify_mode = ssl.CERT_REQUIRED
        else:
            context = ssl.create_default_context(cafile=spec.ca or None)
            if spec.cert:
                context.load_cert_chain(spec.cert, spec.key)
    except OSError as exc:  # ssl.SSLError is one
        what = spec.cert if spec.serve else spec.ca or spec.cert or "the CAs"
        raise LinkDown(
            f"WebSocket TLS: cannot load {what} ({getattr(exc, 'strerror', None) or exc})",
            "check ca, cert and key: PEM files, the key unencrypted",
        ) from None
    return context


def _peer_name(conn: Connection) -> str:
    try:
        addr = conn.remote_address
    except (AttributeError, OSError):
        return "a client"
    return f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr or "a client")


@dataclass(eq=False)
class _Peer:
    conn: Connection
    name: str
    lock: anyio.Lock = field(default_factory=anyio.Lock)
    acks: Acks = field(default_factory=Acks)

    async def write(self, data: bytes) -> None:
        try:
            async with self.lock:
                with anyio.move_on_after(TIMEOUT_S) as slow:
                    await self.conn.send(data)
        except ConnectionClosed as exc:
            raise LinkDown(f"connection to {self.name} lost: {exc}") from None
        if slow.cancelled_caught:
            raise LinkDown(
                f"{self.name} took nothing for {TIMEOUT_S:g} s",
                "is the peer reading its messages?",
            )

    def leave(self) -> None:
        self.acks.leave()


class WebSocketLink:
    """WebSocket messages, as a client that reconnects or as a server (see the module)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        if spec.serve and spec.tls and not spec.cert:
            raise ValueError(
                "a serving wss:// bridge needs its certificate: give cert and key (and ca "
                "to admit only clients with a certificate it signed)"
            )
        self.spec = spec
        self.ctx = ctx
        self.path = spec.address or "/"
        self.sequencer = Sequencer(numbered=spec.qos > 0)
        """Numbers what it sends, and remembers what it took (``rap-seq``)."""
        self.port: int = spec.port
        """The port: for a server on port 0, the one it got."""
        self._peer: _Peer | None = None
        self._peers: set[_Peer] = set()
        self._changed: anyio.Event | None = None  # made on the event loop
        self._server: Server | None = None

    @property
    def sender(self) -> str:
        """This link's id in ``rap-sender``."""
        return self.sequencer.sender

    @property
    def duplicates(self) -> int:
        """Frames received again (a resend after a reconnect) and passed over."""
        return self.sequencer.duplicates

    @property
    def where(self) -> str:
        scheme = "wss" if self.spec.tls else "ws"
        host = self.spec.host
        host = f"[{host}]" if ":" in host else host
        url = f"{scheme}://{host}:{self.port}{self.path}"
        return url + (" (serving)" if self.spec.serve else "")

    @property
    def clients(self) -> int:
        """Clients connected now (server mode)."""
        return len(self._peers)

    @property
    def _limit(self) -> int:
        return self.spec.max_frame + HEADER_ROOM

    def _notify(self) -> None:
        changed, self._changed = self._changed, None
        if changed is not None:
            changed.set()

    async def _wait_change(self) -> None:
        if self._changed is None:
            self._changed = anyio.Event()
        await self._changed.wait()

    # -- connecting --------------------------------------------------------------------

    async def open(self) -> None:
        spec = self.spec
        if spec.serve and self._server is not None:
            return  # listening already (the clients come and go by themselves)
        tls = await anyio.to_thread.run_sync(websocket_tls, spec) if spec.tls else None
        extra: dict[str, Any] = {"ssl": tls} if tls is not None else {}
        if spec.serve:
            try:
                server = await serve(
                    self._handler,
                    spec.host,
                    spec.port,
                    process_request=self._check_path if spec.address else None,
                    open_timeout=TIMEOUT_S,
                    close_timeout=CLOSE_TIMEOUT_S,
                    max_size=self._limit,
                    **extra,
                )
            except OSError as exc:
                raise LinkDown(
                    f"cannot listen on {spec.host}:{spec.port}: {exc.strerror or exc}",
                    "is another process on that port? give another url",
                ) from None
            self._server = server
            self.port = server.sockets[0].getsockname()[1]
            log.info("bridge %s: listening on %s", self.ctx.name, self.where)
            return
        await self._drop()
        uri = self.where
        try:
            conn = await connect(
                uri,
                open_timeout=TIMEOUT_S,
                close_timeout=CLOSE_TIMEOUT_S,
                max_size=self._limit,
                proxy=None,
                **extra,
            )
        except InvalidStatus as exc:
            status = exc.response.status_code
            raise LinkDown(
                f"the server answered the WebSocket handshake with HTTP {status}",
                f"is {self.path} the server's WebSocket path? (address: /path)"
                if status == 404
                else "check the server's logs and access rules",
            ) from None
        except (OSError, TimeoutError, InvalidHandshake, InvalidURI) as exc:
            why = getattr(exc, "strerror", None) or str(exc) or type(exc).__name__
            text = why.lower()
            if "certificate" in text or "ssl" in text or "tls" in text:
                fix = "check ca, cert and key, and that the server's certificate names its host"
            else:
                fix = f"is a WebSocket server listening at {spec.host}:{spec.port}?"
            raise LinkDown(f"cannot connect: {why}", fix) from None
        self._peer = _Peer(conn, f"{spec.host}:{spec.port}")

    async def run(self, deliver: Deliver) -> None:
        if self.spec.serve:
            if self._server is None:
                raise LinkDown("not listening")
            reading: set[_Peer] = set()
            async with anyio.create_task_group() as tg:
                while True:
                    for client in list(self._peers):
                        if client not in reading:
                            reading.add(client)
                            tg.start_soon(self._client, client, deliver, reading)
                    await self._wait_change()
        peer = self._peer
        if peer is None:
            raise LinkDown("not connected")
        try:
            await self._serve_peer(peer, deliver)
        finally:
            peer.leave()

    async def close(self) -> None:
        await self._drop()
        server, self._server = self._server, None
        if server is not None:
            with anyio.CancelScope(shield=True), anyio.move_on_after(TIMEOUT_S):
                server.close()
                await server.wait_closed()
        self._peers.clear()

    async def _drop(self) -> None:
        peer, self._peer = self._peer, None
        if peer is not None:
            peer.leave()
            with anyio.CancelScope(shield=True), anyio.move_on_after(CLOSE_TIMEOUT_S + 1):
                await peer.conn.close()

    def _check_path(self, conn: ServerConnection, request: Request) -> Response | None:
        if request.path.split("?", 1)[0] == self.path:
            return None
        return conn.respond(404, f"no WebSocket here: this bridge serves {self.path}\n")

    async def _handler(self, conn: ServerConnection) -> None:
        """websockets' handler of one client: the connection lives while it waits; the
        bridge's ``run`` reads it."""
        peer = _Peer(conn, _peer_name(conn))
        self._peers.add(peer)
        self._notify()
        log.info("bridge %s: client %s connected to %s", self.ctx.name, peer.name, self.where)
        try:
            await conn.wait_closed()
        finally:
            self._peers.discard(peer)
            peer.leave()
            self._notify()

    async def _client(self, peer: _Peer, deliver: Deliver, reading: set[_Peer]) -> None:
        try:
            await self._serve_peer(peer, deliver)
        except LinkDown as exc:
            log.info("bridge %s: client %s left: %s", self.ctx.name, peer.name, exc)
            self._peers.discard(peer)
            peer.leave()
            # closed here too (an acknowledgement it did not read in time): its handler
            # waits for the close, and the client learns it is dropped
            with anyio.CancelScope(shield=True), anyio.move_on_after(CLOSE_TIMEOUT_S + 1):
                await peer.conn.close()
        finally:
            reading.discard(peer)

    # -- receiving ---------------------------------------------------------------------

    async def _serve_peer(self, peer: _Peer, deliver: Deliver) -> None:
        limit = self.spec.max_frame
        conn = peer.conn
        while True:
            try:
                data = await conn.recv()
            except ConnectionClosed as exc:
                code = exc.sent.code if exc.sent is not None else None
                if code == CloseCode.MESSAGE_TOO_BIG:
                    self.ctx.reject(
                        f"message over the limit of {self._limit} bytes (max_frame {limit} + "
                        f"{HEADER_ROOM} for headers); connection closed (code 1009)"
                    )
                elif code == CloseCode.INVALID_DATA:
                    self.ctx.reject("text message is not UTF-8; connection closed (code 1007)")
                raise LinkDown(f"connection to {peer.name} closed: {exc}") from None
            try:
                headers, payload = decode_message(data, limit)
            except BadMessage as exc:
                self.ctx.reject(str(exc))
                continue
            ack = await self.sequencer.incoming(
                headers, payload, deliver, self.ctx.reject, peer.acks.ack
            )
            if ack is not None:
                await peer.write(encode_message(b"", {HEADER_ACK: ack}))

    # -- sending -----------------------------------------------------------------------

    def _numbered(self, frame: Frame) -> tuple[bytes, int]:
        if len(frame.payload) > self.spec.max_frame:  # a receiver of this spec refuses it
            raise FrameRefused(
                f"message of {len(frame.payload)} bytes is over max_frame "
                f"({self.spec.max_frame}); not sent"
            )
        headers, seq = self.sequencer.outgoing(frame)
        try:
            return encode_message(frame.payload, headers), seq
        except ValueError as exc:  # headers over 64 KiB
            raise FrameRefused(f"{exc}; not sent") from None

    async def send(self, frame: Frame) -> None:
        data, seq = self._numbered(frame)
        if not self.spec.serve:
            peer = self._peer
            if peer is None:
                raise LinkDown("not connected")
            await self._send_to(peer, data, seq)
            return
        # a server: every client gets it; wait for one while there is none

        async def drop(peer: _Peer, exc: LinkDown) -> None:
            log.info("bridge %s: client %s dropped: %s", self.ctx.name, peer.name, exc)
            self._peers.discard(peer)
            peer.leave()
            with anyio.CancelScope(shield=True), anyio.move_on_after(CLOSE_TIMEOUT_S + 1):
                await peer.conn.close()

        await to_every_peer(
            self._peers, lambda p: self._send_to(p, data, seq), drop, self._wait_change
        )

    async def _send_to(self, peer: _Peer, data: bytes, seq: int) -> None:
        await peer.write(data)
        if seq >= 0:
            await peer.acks.wait(seq, peer.name, TIMEOUT_S)

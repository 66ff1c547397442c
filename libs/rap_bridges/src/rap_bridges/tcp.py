"""The TCP link: length-prefixed frames over one connection (docs/bridges.md, "TCP").

A frame, every integer big-endian::

    length  u32   2 + hlen + len(payload): the bytes that follow
    hlen    u16   the length of the header map
    headers       hlen bytes: a JSON object of string -> string, UTF-8 (hlen 0: none)
    payload       the message, in the spec's format

Headers RAP uses: ``rap-cycle``, ``rap-cause`` (32 hex digits), ``rap-type``,
``rap-source``; and for QoS >= 1 ``rap-seq`` (a decimal number, growing per sender)
with ``rap-sender`` (the sender's id). A frame that carries ``rap-seq`` is acknowledged
once the receiver has taken it (or rejected it for good) with a frame of empty payload
whose only header is ``rap-ack`` (the same number). A sender at QoS >= 1 sends one frame
at a time and waits for its acknowledgement; after a reconnect it sends the
unacknowledged frame again with the same number, and the receiver passes over a number
it has taken already from that sender (at least once on the wire, once on the fabric).

A frame longer than ``max_frame`` + 64 KiB (the spec's payload limit and room for the
headers) is rejected and counted, and the connection is closed: it is the only way to
find the next frame. A frame whose headers are not a JSON map of strings, or whose
payload is over ``max_frame``, is rejected and the next frame is read.

Client mode (``tcp://host:port``) reconnects; server mode (``serve: true``) listens on
the URL's address, takes any number of clients, sends each outgoing frame to every
client (waiting for a first client while there is none) and takes frames from all.
"""

from __future__ import annotations

import logging
import struct
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Final

import anyio
import msgspec
from anyio.abc import SocketAttribute, SocketStream
from anyio.streams.buffered import BufferedByteReceiveStream
from anyio.streams.stapled import MultiListener
from rap_schemas.limits import DECODE_ERRORS

from .core import Deliver, Frame, FrameRefused, LinkContext, LinkDown
from .sequencing import HEADER_ACK, HEADER_SENDER, HEADER_SEQ, Acks, Sequencer, to_every_peer
from .spec import BridgeSpec

__all__ = [
    "HEADER_ACK",
    "HEADER_ROOM",
    "HEADER_SENDER",
    "HEADER_SEQ",
    "BadFrame",
    "FrameTooLong",
    "TcpLink",
    "encode_frame",
    "read_frame",
]

log = logging.getLogger(__name__)

HEADER_ROOM: Final = 2 + 0xFFFF
"""What a frame may hold beside its payload: the header map's length and the map."""
TIMEOUT_S: Final = 10.0
"""How long a connection or an acknowledgement may take before the link counts as lost."""

_HEAD = struct.Struct(">IH")
_LENGTH = struct.Struct(">I")
_HLEN = struct.Struct(">H")
_encode_headers = msgspec.json.Encoder().encode
_decode_headers: Callable[[bytes], dict[str, str]] = msgspec.json.Decoder(dict[str, str]).decode


def encode_frame(payload: bytes, headers: dict[str, str] | None = None) -> bytes:
    """One frame's bytes (the format above)."""
    h = _encode_headers(headers) if headers else b""
    if len(h) > 0xFFFF:
        raise ValueError(f"frame headers of {len(h)} bytes: at most 65535")
    return _HEAD.pack(2 + len(h) + len(payload), len(h)) + h + payload


class FrameTooLong(Exception):
    """A frame over the limit (or whose lengths contradict each other): nothing more
    can be read on its connection."""


class BadFrame(Exception):
    """A frame that was read whole but cannot be taken (headers, payload size)."""


async def read_frame(
    reader: BufferedByteReceiveStream, max_payload: int
) -> tuple[dict[str, str], bytes]:
    """The next frame's headers and payload. :class:`FrameTooLong` (nothing more can be
    read on this connection), :class:`BadFrame` (this frame only), anyio's end-of-stream
    errors."""
    (length,) = _LENGTH.unpack(await reader.receive_exactly(4))
    if length > max_payload + HEADER_ROOM:
        raise FrameTooLong(
            f"frame of {length} bytes is over the limit of {max_payload + HEADER_ROOM} "
            f"(max_frame {max_payload} + {HEADER_ROOM} for headers)"
        )
    if length < 2:
        raise FrameTooLong(f"frame of {length} bytes cannot hold its header length (2 bytes)")
    body = await reader.receive_exactly(length)
    (hlen,) = _HLEN.unpack_from(body)
    if 2 + hlen > length:
        raise FrameTooLong(f"frame says {hlen} bytes of headers but holds {length - 2}")
    headers: dict[str, str] = {}
    if hlen:
        try:
            headers = _decode_headers(body[2 : 2 + hlen])
        except DECODE_ERRORS as exc:
            raise BadFrame(f"frame headers are not a JSON map of strings: {exc}") from None
    payload = body[2 + hlen :]
    if len(payload) > max_payload:
        raise BadFrame(f"payload of {len(payload)} bytes is over max_frame {max_payload}")
    return headers, payload


@dataclass(eq=False)
class _Peer:
    stream: SocketStream
    name: str
    reader: BufferedByteReceiveStream = field(init=False)
    lock: anyio.Lock = field(default_factory=anyio.Lock)
    acks: Acks = field(default_factory=Acks)

    def __post_init__(self) -> None:
        self.reader = BufferedByteReceiveStream(self.stream)

    async def write(self, data: bytes) -> None:
        try:
            async with self.lock:
                await self.stream.send(data)
        except (anyio.BrokenResourceError, anyio.ClosedResourceError, OSError) as exc:
            raise LinkDown(f"connection to {self.name} lost: {exc or type(exc).__name__}") from None


def _peer_name(stream: SocketStream) -> str:
    try:
        addr = stream.extra(SocketAttribute.remote_address)
    except anyio.TypedAttributeLookupError:
        return "a client"
    return f"{addr[0]}:{addr[1]}" if isinstance(addr, tuple) else str(addr)


class TcpLink:
    """TCP frames, as a client that reconnects or as a server (see the module)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        self.spec = spec
        self.ctx = ctx
        self.sequencer = Sequencer(numbered=spec.qos > 0)
        """Numbers what it sends, and remembers what it took (``rap-seq``)."""
        self.port: int = spec.port
        """The port: for a server on port 0, the one it got."""
        self._peer: _Peer | None = None
        self._peers: set[_Peer] = set()
        self._joined: anyio.Event | None = None  # made on the event loop
        self._listener: MultiListener[SocketStream] | None = None

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
        host = self.spec.host
        return f"tcp://{host}:{self.port}" + (" (serving)" if self.spec.serve else "")

    # -- connecting --------------------------------------------------------------------

    async def open(self) -> None:
        spec = self.spec
        if spec.serve:
            if self._listener is None:
                try:
                    listener = await anyio.create_tcp_listener(
                        local_host=spec.host, local_port=spec.port, reuse_port=False
                    )
                except OSError as exc:
                    raise LinkDown(
                        f"cannot listen on {spec.host}:{spec.port}: {exc.strerror or exc}",
                        "is another process on that port? give another url",
                    ) from None
                self._listener = listener
                self.port = listener.listeners[0].extra(SocketAttribute.local_port)
                log.info("bridge %s: listening on %s", self.ctx.name, self.where)
            return
        await self._drop()
        try:
            with anyio.fail_after(TIMEOUT_S):
                stream = await anyio.connect_tcp(spec.host, spec.port)
        except (OSError, TimeoutError) as exc:
            why = getattr(exc, "strerror", None) or str(exc) or "timed out"
            raise LinkDown(
                f"cannot connect: {why}", f"is the peer listening at {spec.host}:{spec.port}?"
            ) from None
        self._peer = _Peer(stream, f"{spec.host}:{spec.port}")

    async def run(self, deliver: Deliver) -> None:
        listener = self._listener
        if listener is not None:
            try:
                await listener.serve(lambda stream: self._client(stream, deliver))
            except OSError as exc:
                self._listener = None
                with anyio.CancelScope(shield=True):
                    await listener.aclose()
                raise LinkDown(f"cannot accept clients: {exc.strerror or exc}") from None
            return
        peer = self._peer
        if peer is None:
            raise LinkDown("not connected")
        await self._serve_peer(peer, deliver)

    async def close(self) -> None:
        await self._drop()
        for peer in list(self._peers):
            await peer.stream.aclose()
        self._peers.clear()
        listener, self._listener = self._listener, None
        if listener is not None:
            await listener.aclose()

    async def _drop(self) -> None:
        peer, self._peer = self._peer, None
        if peer is not None:
            with anyio.CancelScope(shield=True):
                await peer.stream.aclose()

    async def _client(self, stream: SocketStream, deliver: Deliver) -> None:
        peer = _Peer(stream, _peer_name(stream))
        self._peers.add(peer)
        if self._joined is not None:
            self._joined.set()
        log.info("bridge %s: client %s connected to %s", self.ctx.name, peer.name, self.where)
        try:
            await self._serve_peer(peer, deliver)
        except LinkDown as exc:
            log.info("bridge %s: client %s left: %s", self.ctx.name, peer.name, exc)
        finally:
            self._peers.discard(peer)
            peer.acks.leave()  # a send waiting for its acknowledgement stops waiting
            with anyio.CancelScope(shield=True):
                await stream.aclose()

    # -- receiving ---------------------------------------------------------------------

    async def _serve_peer(self, peer: _Peer, deliver: Deliver) -> None:
        limit = self.spec.max_frame
        while True:
            try:
                headers, payload = await read_frame(peer.reader, limit)
            except FrameTooLong as exc:
                self.ctx.reject(str(exc))
                raise LinkDown(f"{exc}; connection closed to find the next frame") from None
            except BadFrame as exc:
                self.ctx.reject(str(exc))
                continue
            except (anyio.EndOfStream, anyio.IncompleteRead):
                raise LinkDown(f"{peer.name} closed the connection") from None
            except (anyio.BrokenResourceError, anyio.ClosedResourceError, OSError) as exc:
                raise LinkDown(f"connection to {peer.name} lost: {exc}") from None
            ack = await self.sequencer.incoming(
                headers, payload, deliver, self.ctx.reject, peer.acks.ack
            )
            if ack is not None:
                await peer.write(encode_frame(b"", {HEADER_ACK: ack}))

    # -- sending -----------------------------------------------------------------------

    def _numbered(self, frame: Frame) -> tuple[bytes, int]:
        if len(frame.payload) > self.spec.max_frame:  # a receiver of this spec refuses it
            raise FrameRefused(
                f"message of {len(frame.payload)} bytes is over max_frame "
                f"({self.spec.max_frame}); not sent"
            )
        headers, seq = self.sequencer.outgoing(frame)
        try:
            return encode_frame(frame.payload, headers), seq
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
            await peer.stream.aclose()

        await to_every_peer(self._peers, lambda p: self._send_to(p, data, seq), drop, self._joining)

    async def _joining(self) -> None:
        if self._joined is None or self._joined.is_set():
            self._joined = anyio.Event()
        await self._joined.wait()

    async def _send_to(self, peer: _Peer, data: bytes, seq: int) -> None:
        await peer.write(data)
        if seq >= 0:
            await peer.acks.wait(seq, peer.name, TIMEOUT_S)

"""The contract's WebSocket outside: a peer server of the test's own, written with the
``websockets`` library directly (not the bridge's link) on a free loopback port.

It reads binary messages in the documented format (``u16`` header length, a JSON header
map, the payload), acknowledges numbered ones (``rap-seq`` -> ``rap-ack``), passes over
a number it has taken already from a sender, records what it gets and sends frames to
the last connected bridge. :meth:`Outside.stop` closes the server and every connection;
:meth:`Outside.start` listens again on the same port.
"""

from __future__ import annotations

import json
import struct
from pathlib import Path
from typing import Any

import anyio
from anyio.abc import TaskGroup
from rap_bridges import BridgeSpec, Direction, Frame
from rap_sdk.fabric import free_port
from websockets.asyncio.server import Server, ServerConnection, serve
from websockets.exceptions import ConnectionClosed

from libs.rap_bridges.tests.contract import TIMEOUT, _Received

PATH = "/contract"


def require_server() -> None:
    """Nothing to install: the peer is the websockets library, a dependency."""


def pack(payload: bytes, headers: dict[str, str] | None = None) -> bytes:
    """A binary message as docs/bridges/websocket.md describes it (written here, not
    taken from the link)."""
    h = json.dumps(headers).encode() if headers else b""
    return struct.pack(">H", len(h)) + h + payload


def unpack(data: bytes) -> tuple[dict[str, str], bytes]:
    (hlen,) = struct.unpack(">H", data[:2])
    headers = json.loads(data[2 : 2 + hlen]) if hlen else {}
    return headers, data[2 + hlen :]


class Outside(_Received):
    protocol = "websocket"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        self.port = free_port()
        self._server: Server | None = None
        self.conns: list[ServerConnection] = []
        self._joined = anyio.Event()
        self.seen: dict[str, int] = {}
        self.paths: list[str] = []

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        kw.setdefault("format", "json")
        return BridgeSpec(
            protocol="websocket", url=f"ws://127.0.0.1:{self.port}", address=PATH, **kw
        )

    async def start(self) -> None:
        self._server = await serve(self._conn, "127.0.0.1", self.port)

    async def stop(self) -> None:
        server, self._server = self._server, None
        if server is not None:
            server.close()  # closes every connection (1001, going away)
            await server.wait_closed()
        self.conns.clear()
        self._joined = anyio.Event()

    async def _conn(self, ws: ServerConnection) -> None:
        assert ws.request is not None
        self.paths.append(ws.request.path)
        self.conns.append(ws)
        self._joined.set()
        try:
            async for message in ws:
                if isinstance(message, str):
                    continue
                headers, payload = unpack(message)
                seq = headers.pop("rap-seq", None)
                sender = headers.pop("rap-sender", "")
                if seq is not None:
                    if int(seq) > self.seen.get(sender, -1):
                        self.seen[sender] = int(seq)
                        self.add(Frame(payload, headers))
                    await ws.send(pack(b"", {"rap-ack": seq}))
                elif "rap-ack" not in headers:
                    self.add(Frame(payload, headers))
        except ConnectionClosed:
            pass
        finally:
            if ws in self.conns:
                self.conns.remove(ws)

    async def start_receiver(self) -> None:
        """Nothing to start: the server records what every connection brings."""

    async def send(self, frames: list[Frame]) -> None:
        with anyio.fail_after(TIMEOUT):
            while not self.conns:
                await self._joined.wait()
        ws = self.conns[-1]
        for f in frames:
            await ws.send(pack(f.payload, dict(f.headers)))

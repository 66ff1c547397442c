"""The contract's Redis streams outside: a redis-server of the test's own that persists
every write (``appendonly yes``, an fsync each), so that a restart keeps the streams,
their consumer groups and what they had acknowledged, as on a production server.

The client on the outside is redis-py used directly (not the bridge's link):

- the receiver of ``out`` bridges reads the stream with XREAD from the last entry id it
  has seen, again after every restart (so it misses nothing and takes nothing twice);
- the sender adds entries for ``in`` bridges with XADD: the field ``payload`` and one
  field per header.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import anyio
import redis.asyncio
import redis.exceptions
from anyio.abc import TaskGroup
from rap_bridges import BridgeSpec, Direction, Frame

from libs.rap_bridges.tests.contract import _Received
from libs.rap_bridges.tests.outside_redis import NO_RETRY, RedisServer

OUT_STREAM = "contract.out"
IN_STREAM = "contract.in"


def require_server() -> None:
    from libs.rap_bridges.tests.outside_redis import require_server as redis_server

    redis_server()


def entry_frame(fields: dict[bytes, bytes]) -> Frame:
    """The frame of a stream entry: its ``payload`` field and the others as headers."""
    headers = {k.decode(): v.decode() for k, v in fields.items() if k != b"payload"}
    return Frame(fields.get(b"payload", b""), headers)


class Outside(_Received):
    protocol = "redis-stream"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        self.server = RedisServer(directory, appendonly=True)
        self.port = self.server.port
        self._tg = tg
        self.ready = anyio.Event()
        """Set while the receiver is reading."""
        self.last = b"0"
        """The id of the last entry the receiver took."""

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        address = OUT_STREAM if direction == "out" else IN_STREAM
        kw.setdefault("format", "json")
        return BridgeSpec(
            protocol="redis-stream", url=f"redis://127.0.0.1:{self.port}", address=address, **kw
        )

    def client(self) -> redis.asyncio.Redis:
        return redis.asyncio.Redis(host="127.0.0.1", port=self.port, retry=NO_RETRY)

    async def start(self) -> None:
        await self.server.start()

    async def stop(self) -> None:
        await self.server.stop()

    async def receive_forever(self) -> None:
        while True:
            client = self.client()
            try:
                while True:
                    reply = await client.xread({OUT_STREAM: self.last}, count=500, block=1000)
                    self.ready.set()
                    for _stream, entries in reply:
                        for entry_id, fields in entries:
                            self.last = entry_id
                            self.add(entry_frame(fields))
            except (OSError, redis.exceptions.ConnectionError, redis.exceptions.TimeoutError):
                if self.ready.is_set():
                    self.ready = anyio.Event()
                await anyio.sleep(0.05)  # the server is down: try again
            finally:
                with anyio.CancelScope(shield=True):
                    await client.aclose()

    async def start_receiver(self) -> None:
        self._tg.start_soon(self.receive_forever)
        with anyio.fail_after(10):
            await self.ready.wait()

    async def send(self, frames: list[Frame]) -> None:
        client = self.client()
        try:
            async with client.pipeline(transaction=False) as pipe:
                for f in frames:
                    pipe.xadd(IN_STREAM, {"payload": f.payload, **f.headers})
                await pipe.execute()
        finally:
            await client.aclose()

"""The contract's Redis pub/sub outside, and :class:`RedisServer`, the redis-server every
Redis bridge test starts itself.

The client on the outside is redis-py used directly (not the bridge's link), and the
wrapped form of a pub/sub message (docs/bridges/redis.md) is written and read here with
the standard library's ``json``:

- the receiver of ``out`` bridges subscribes through the server's unix socket. Redis
  keeps nothing for a subscriber that is away, so after a restart the server's TCP port
  (the bridges') opens only once the receiver has subscribed again: what a bridge
  publishes from its buffer then reaches it, as it would reach a subscriber that
  outlived the server.
- the sender publishes to ``in`` bridges, wrapping a frame that has headers.
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Sequence
from pathlib import Path
from typing import Any

import anyio
import redis.asyncio
import redis.exceptions
from anyio.abc import TaskGroup
from rap_bridges import BridgeSpec, Direction, Frame
from rap_sdk.fabric import free_port
from rap_sdk.testing import require_binary, stop_process
from redis.asyncio.retry import Retry
from redis.backoff import NoBackoff

from libs.rap_bridges.tests.contract import _Received

OUT_CHANNEL = "contract.out"
IN_CHANNEL = "contract.in"
NO_RETRY = Retry(NoBackoff(), 0)
"""redis-py retries nothing by itself: the tests see every failure."""


def require_server() -> None:
    require_binary("redis-server", hint="apt-get install redis-server")


class RedisServer:
    """A redis-server of the test's own on a free loopback port, configured by a file in
    ``directory`` and answering on a unix socket there too; :meth:`stop` and
    :meth:`start` restart it on the same port (and files)."""

    def __init__(
        self,
        directory: Path,
        *,
        appendonly: bool = False,
        password: str | None = None,
        users: Sequence[str] = (),
        tls: tuple[Path, Path, Path] | None = None,
    ) -> None:
        """``appendonly``: persist every write (fsync each) so that a restart keeps the
        data; ``password``: ``requirepass``; ``users``: ACL lines (``"robot on >pw ~*
        &* +@all"``); ``tls``: the CA, certificate and key of a TLS-only port that asks
        clients for a certificate of that CA."""
        self.binary = require_binary("redis-server", hint="apt-get install redis-server")
        self.directory = directory
        self.port = free_port()
        self.socket = directory / "redis.sock"
        self.log = directory / "redis.log"
        self.tls = tls is not None
        lines = [
            "bind 127.0.0.1",
            f"unixsocket {self.socket}",
            "unixsocketperm 700",
            f"dir {directory}",
            f"logfile {self.log}",
            'save ""',
            f"appendonly {'yes' if appendonly else 'no'}",
            "appendfsync always",
        ]
        if tls is not None:
            ca, cert, key = tls
            lines += [f"tls-cert-file {cert}", f"tls-key-file {key}", f"tls-ca-cert-file {ca}"]
            lines.append("tls-auth-clients yes")
        if password is not None:
            lines.append(f"requirepass {password}")
        lines += [f"user {user}" for user in users]
        self.conf = directory / "redis.conf"
        self.conf.write_text("\n".join(lines) + "\n", encoding="utf-8")
        self._proc: Any = None

    def admin(self) -> redis.asyncio.Redis:
        """A redis-py client on the unix socket, as the default user, retrying nothing."""
        return redis.asyncio.Redis(unix_socket_path=str(self.socket), retry=NO_RETRY)

    async def start(self, *, hold: bool = False) -> None:
        """Start it; ``hold``: with its TCP port closed (the unix socket answers) until
        :meth:`open_port`."""
        port = ["--port", "0"] if hold or self.tls else ["--port", str(self.port)]
        if self.tls:
            port += ["--tls-port", "0" if hold else str(self.port)]
        self._proc = await anyio.open_process(
            [self.binary, str(self.conf), *port],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.DEVNULL,
        )
        with anyio.fail_after(10):
            while True:
                try:
                    stream = await anyio.connect_unix(self.socket)
                except OSError:
                    if self._proc.returncode is not None:
                        raise RuntimeError(
                            f"redis-server exited at start; see {self.log}"
                        ) from None
                    await anyio.sleep(0.02)  # it says nothing when ready: wait until it accepts
                    continue
                await stream.aclose()
                return

    async def open_port(self) -> None:
        """Open the TCP port of a server started with ``hold``."""
        await self.command("CONFIG", "SET", "tls-port" if self.tls else "port", str(self.port))

    async def command(self, *args: Any) -> Any:
        """One command on the unix socket, as the default user."""
        async with self.admin() as client:
            return await client.execute_command(*args)

    async def stop(self) -> None:
        proc, self._proc = self._proc, None
        if proc is not None:
            await stop_process(proc, grace=10)
            await proc.aclose()


def wrapped(frame: Frame) -> bytes:
    """A pub/sub message for an ``in`` bridge: wrapped when the frame has headers."""
    if not frame.headers:
        return frame.payload
    return b'{"headers": %s, "payload": %s}' % (
        json.dumps(dict(frame.headers)).encode(),
        frame.payload,
    )


def unwrapped(data: bytes) -> Frame:
    """The frame of a message an ``out`` bridge published (wrapped, with format json)."""
    value = json.loads(data)
    if isinstance(value, dict) and set(value) == {"headers", "payload"}:
        return Frame(json.dumps(value["payload"]).encode(), value["headers"])
    return Frame(data)


class Outside(_Received):
    protocol = "redis"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        self.server = RedisServer(directory)
        self.port = self.server.port
        self._tg = tg
        self.receiving = False
        self.ready = anyio.Event()
        """Set while the receiver is subscribed."""

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        address = OUT_CHANNEL if direction == "out" else IN_CHANNEL
        kw.setdefault("format", "json")
        if direction == "in":
            kw.setdefault("qos", 0)  # pub/sub takes at most once
        return BridgeSpec(
            protocol="redis", url=f"redis://127.0.0.1:{self.port}", address=address, **kw
        )

    async def start(self) -> None:
        if not self.receiving:
            await self.server.start()
            return
        await self.server.start(hold=True)
        with anyio.fail_after(10):
            await self.ready.wait()
        await self.server.open_port()

    async def stop(self) -> None:
        await self.server.stop()
        self.ready = anyio.Event()  # the receiver's subscription went with the server

    async def receive_forever(self) -> None:
        while True:
            client = self.server.admin()
            try:
                async with client.pubsub() as ps:
                    await ps.subscribe(OUT_CHANNEL)
                    async for m in ps.listen():
                        if m["type"] == "subscribe":
                            self.ready.set()
                        elif m["type"] == "message":
                            self.add(unwrapped(m["data"]))
            except (OSError, redis.exceptions.ConnectionError, redis.exceptions.TimeoutError):
                await anyio.sleep(0.05)  # the server is down: try again
            finally:
                with anyio.CancelScope(shield=True):
                    await client.aclose()

    async def start_receiver(self) -> None:
        self.receiving = True
        self._tg.start_soon(self.receive_forever)
        with anyio.fail_after(10):
            await self.ready.wait()

    async def send(self, frames: list[Frame]) -> None:
        client = redis.asyncio.Redis(host="127.0.0.1", port=self.port, retry=NO_RETRY)
        try:
            async with client.pipeline(transaction=False) as pipe:
                for f in frames:
                    pipe.publish(IN_CHANNEL, wrapped(f))
                await pipe.execute()
        finally:
            await client.aclose()

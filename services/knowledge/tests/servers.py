"""Servers a test starts itself, on a free loopback port, and can restart."""

from __future__ import annotations

import subprocess
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import anyio
from anyio.abc import Process
from anyio.streams.text import TextReceiveStream
from rap_sdk.testing import free_port, require_binary


class RedisServer:
    """A redis-server of our own (append-only file on, so a restart keeps the data)."""

    def __init__(self, directory: Path) -> None:
        self.binary = require_binary("redis-server", hint="apt-get install redis-server")
        self.directory = directory
        self.port = free_port()
        self._proc: Process | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    async def start(self) -> None:
        self._proc = await anyio.open_process(
            [
                self.binary,
                "--bind",
                "127.0.0.1",
                "--port",
                str(self.port),
                "--dir",
                str(self.directory),
                "--appendonly",
                "yes",
                "--appendfsync",
                "always",
                "--save",
                "",
                "--logfile",
                "",
            ],
            stdout=subprocess.PIPE,
            stderr=subprocess.STDOUT,
        )
        assert self._proc.stdout is not None
        seen = ""
        with anyio.fail_after(10):
            async for chunk in TextReceiveStream(self._proc.stdout):
                seen += chunk
                if "Ready to accept connections" in seen:
                    return
        raise RuntimeError(f"redis-server did not start:\n{seen}")

    async def stop(self) -> None:
        if self._proc is not None:
            proc, self._proc = self._proc, None
            proc.terminate()
            with anyio.fail_after(10):
                await proc.wait()
            await proc.aclose()

    async def restart(self) -> None:
        await self.stop()
        await self.start()


@asynccontextmanager
async def redis_server(directory: Path) -> AsyncIterator[RedisServer]:
    server = RedisServer(directory)
    await server.start()
    try:
        yield server
    finally:
        with anyio.CancelScope(shield=True):
            await server.stop()

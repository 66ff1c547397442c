"""Servers a test starts itself, on a free loopback port, and can restart (redis-server,
memcached)."""

from __future__ import annotations

import contextlib
import os
import pwd
import subprocess
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path

import anyio
from anyio.abc import Process
from anyio.streams.text import TextReceiveStream
from rap_sdk.testing import accepting, free_port, require_binary


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


class MemcachedServer:
    """A memcached of our own on a free loopback port (64 MiB; it keeps nothing across a
    restart, as memcached never does)."""

    def __init__(self, *, memory_mb: int = 64) -> None:
        self.binary = require_binary("memcached", hint="apt-get install memcached")
        self.port = free_port()
        self.memory_mb = memory_mb
        self._proc: Process | None = None

    @property
    def url(self) -> str:
        return f"memcached://127.0.0.1:{self.port}"

    async def start(self) -> None:
        # memcached refuses to run as root unless told which user to run as
        user = pwd.getpwuid(os.geteuid()).pw_name
        self._proc = await anyio.open_process(
            [
                self.binary,
                "--listen=127.0.0.1",
                f"--port={self.port}",
                "--udp-port=0",
                f"--memory-limit={self.memory_mb}",
                "--threads=1",
                f"--user={user}",
            ],
            stdout=subprocess.DEVNULL,
            stderr=subprocess.PIPE,
        )
        proc = self._proc  # it says nothing when ready: wait until it accepts
        try:
            await accepting(self.port, lambda: None if proc.returncode is None else "exited")
        except RuntimeError:
            err = b""
            if proc.stderr is not None:
                with contextlib.suppress(anyio.EndOfStream):
                    err = await proc.stderr.receive()
            raise RuntimeError(f"memcached did not start: {err.decode(errors='replace')}") from None

    async def stop(self) -> None:
        if self._proc is not None:
            proc, self._proc = self._proc, None
            proc.kill()
            with anyio.fail_after(10):
                await proc.wait()
            await proc.aclose()

    async def restart(self) -> None:
        """Kill it and start it again on the same port: every item is gone."""
        await self.stop()
        await self.start()


@asynccontextmanager
async def memcached_server() -> AsyncIterator[MemcachedServer]:
    server = MemcachedServer()
    await server.start()
    try:
        yield server
    finally:
        with anyio.CancelScope(shield=True):
            await server.stop()

"""Processes a benchmark starts: wait for a ready line, read lines, stop them."""

from __future__ import annotations

import json
import subprocess
from collections.abc import AsyncIterator, Mapping
from contextlib import asynccontextmanager
from typing import Any

import anyio
from anyio.abc import Process
from anyio.streams.text import TextReceiveStream

TIMEOUT = 60.0


class Proc:
    def __init__(self, proc: Process) -> None:
        self.proc = proc
        assert proc.stdout is not None
        self._text = TextReceiveStream(proc.stdout)
        self._buf = ""

    async def line(self) -> str:
        with anyio.fail_after(TIMEOUT):
            while "\n" not in self._buf:
                self._buf += await self._text.receive()
        line, self._buf = self._buf.split("\n", 1)
        return line

    async def result(self) -> dict[str, Any]:
        """The next line, as a JSON object (what a sink peer prints when done)."""
        data: dict[str, Any] = json.loads(await self.line())
        return data


@asynccontextmanager
async def spawn(
    args: list[str], *, ready: str = "READY", env: Mapping[str, str] | None = None
) -> AsyncIterator[Proc]:
    """Start ``args``; yield once a line of its output contains ``ready``; on exit
    terminate it (kill after 5 s)."""
    proc = await anyio.open_process(args, stdout=subprocess.PIPE, stderr=subprocess.STDOUT, env=env)
    p = Proc(proc)
    try:
        while ready not in await p.line():
            pass
        yield p
    finally:
        if proc.returncode is None:
            proc.terminate()
        with anyio.move_on_after(5):
            await proc.wait()
        if proc.returncode is None:
            proc.kill()
            await proc.wait()
        await proc.aclose()

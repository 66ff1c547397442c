"""The console: outputs as the reference checker's lines (``name[tick] = Int(7)``), and
verdicts as JSON lines (``rap.TrustVerdict``).

:class:`ConsoleSink` is the live modes' sink (stdout for outputs, stderr for verdicts
with ``explain``); :func:`console_lines` and :func:`verdict_lines` are the same text for
a trace file's ticks.
"""

from __future__ import annotations

import sys
from collections.abc import Sequence

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import TrustSpecStatus, TrustVerdict

from .io.ports import OutputLike
from .values import console

__all__ = ["ConsoleSink", "console_lines", "verdict_lines"]

_encode_json = msgspec.json.Encoder().encode


def console_lines(outs: Sequence[OutputLike]) -> str:
    """One tick's outputs as console lines, each ending in a newline."""
    return "".join(f"{o.stream}[{o.tick}] = {console(o.value)}\n" for o in outs)


def verdict_lines(verdicts: Sequence[TrustVerdict]) -> str:
    """``--explain``: one JSON line per verdict (the ``rap.TrustVerdict`` wire form)."""
    return "".join(_encode_json(v).decode() + "\n" for v in verdicts)


class ConsoleSink:
    """Console lines on stdout for every output (the reference checker's format), and
    with ``explain`` each verdict as a JSON line on stderr.

    A tick's lines are queued and :meth:`run` writes whatever has queued in one call on a
    worker thread, so neither a slow reader nor a write per tick holds up the session
    (and the sinks after this one); only ``MAX_PENDING`` unwritten chunks make a tick
    wait. What is queued when the checker stops is still written."""

    MAX_PENDING = 10_000

    def __init__(self, *, explain: bool = False) -> None:
        self.explain = explain
        self._send, self._receive = anyio.create_memory_object_stream[tuple[bool, str]](
            self.MAX_PENDING
        )

    async def outputs(self, outs: Sequence[OutputLike]) -> None:
        text = console_lines(outs)
        if text:
            await self._put((False, text))

    async def verdicts(self, verdicts: Sequence[TrustVerdict]) -> None:
        if self.explain and verdicts:
            await self._put((True, verdict_lines(verdicts)))

    async def _put(self, chunk: tuple[bool, str]) -> None:
        """Queue without yielding to the event loop while there is room (a tick's lines
        cost no task switch); wait only when ``MAX_PENDING`` chunks are unwritten."""
        try:
            self._send.send_nowait(chunk)
        except anyio.WouldBlock:
            await self._send.send(chunk)

    async def status(self, status: TrustSpecStatus) -> None:
        """Swap outcomes are logged by the session."""

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        task_status.started()
        try:
            async for first in self._receive:
                await anyio.to_thread.run_sync(_write_chunks, self._drain(first))
        finally:
            with anyio.CancelScope(shield=True):
                rest = self._drain(None)
                if rest:
                    await anyio.to_thread.run_sync(_write_chunks, rest)
            self._send.close()
            self._receive.close()

    def _drain(self, first: tuple[bool, str] | None) -> list[tuple[bool, str]]:
        chunks = [] if first is None else [first]
        while True:
            try:
                chunks.append(self._receive.receive_nowait())
            except (anyio.WouldBlock, anyio.EndOfStream, anyio.ClosedResourceError):
                return chunks


def _write_chunks(chunks: list[tuple[bool, str]]) -> None:
    """Write (and flush) what has queued: a worker thread's job, never the loop's."""
    out = "".join(text for err, text in chunks if not err)
    err = "".join(text for is_err, text in chunks if is_err)
    if out:
        sys.stdout.write(out)
        sys.stdout.flush()
    if err:
        sys.stderr.write(err)
        sys.stderr.flush()

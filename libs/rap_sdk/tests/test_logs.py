"""Structured logs: the JSON line, the rotating file that stays bounded, the fabric
handler over real Zenoh (delivery, a flood dropped and counted without blocking, no
recursion), and the Redis stream handler against a redis-server of the test's own
(bounded by MAXLEN ~, surviving the server going away and coming back)."""

from __future__ import annotations

import json
import logging
import subprocess
import sys
from collections.abc import AsyncIterator, Iterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import anyio
import anyio.lowlevel
import msgspec
import pytest
from anyio.abc import Process
from rap_schemas import LogRecord, keys
from rap_sdk import ZenohConfig, ZenohFabric
from rap_sdk.logs import (
    FabricLogHandler,
    JsonFileLog,
    JsonFormatter,
    LogContext,
    RedisStreamHandler,
    add_file_log,
    publish_logs,
    redis_stream,
)
from rap_sdk.testing import Harness, free_port, require_binary, stop_process

pytestmark = pytest.mark.anyio

S = "logs"
CTX = LogContext(
    system=S,
    compute_node="robot",
    process="runner",
    components={"app.nodes": "analysis"},
    names=frozenset({"planner"}),
)


@pytest.fixture
def logger(request: pytest.FixtureRequest) -> Iterator[logging.Logger]:
    """A logger of the test's own (not the root: other tests' lines stay out)."""
    lg = logging.getLogger(f"test_logs.{request.node.name}")
    lg.setLevel(logging.DEBUG)
    lg.propagate = False
    yield lg
    for h in list(lg.handlers):
        lg.removeHandler(h)


def _record(name: str, level: int, msg: str, *args: Any, **extra: Any) -> logging.LogRecord:
    rec = logging.LogRecord(name, level, __file__, 1, msg, args, None)
    rec.__dict__.update(extra)
    return rec


def test_a_line_is_one_json_object_with_the_context() -> None:
    fmt = JsonFormatter(CTX)
    line = fmt.format(_record("app.nodes.detect", logging.WARNING, "mask of %d beams", 12))
    assert "\n" not in line
    obj = json.loads(line)
    assert obj["level"] == "WARNING"
    assert obj["logger"] == "app.nodes.detect"
    assert obj["message"] == "mask of 12 beams"
    assert obj["system"] == S
    assert obj["compute_node"] == "robot"
    assert obj["process"] == "runner"
    assert obj["component"] == "analysis"  # the component's module
    assert isinstance(obj["ts"], int)
    assert obj["ts"] > 1_600_000_000 * 10**9
    # the same object as the wire message
    assert msgspec.json.decode(line, type=LogRecord).message == "mask of 12 beams"
    # a runtime line naming one of the process's components is about it
    rt = fmt.to_message(_record("rap_sdk.runtime", logging.ERROR, "node %s: failed", "planner"))
    assert rt.component == "planner"
    other = fmt.to_message(_record("rap_sdk.runtime", logging.ERROR, "node %s: x", "stranger"))
    assert other.component == ""
    given = fmt.to_message(_record("x", logging.INFO, "hi", component="executor"))
    assert given.component == "executor"


def test_exception_text_and_a_bad_format_do_not_raise() -> None:
    fmt = JsonFormatter(CTX)
    try:
        raise ValueError("boom")
    except ValueError:
        rec = logging.LogRecord("x", logging.ERROR, __file__, 1, "failed", (), sys.exc_info())
    msg = fmt.to_message(rec)
    assert "ValueError: boom" in msg.exc
    assert "Traceback" in msg.exc
    bad = fmt.to_message(_record("x", logging.INFO, "%d items", "not a number"))
    assert "cannot be formatted" in bad.message
    huge = fmt.to_message(_record("x", logging.INFO, "y" * 100_000))
    assert len(huge.message) < 17_000
    assert huge.message.endswith("characters cut]")


def test_the_file_rotates_and_stays_bounded(tmp_path: Path, logger: logging.Logger) -> None:
    path = tmp_path / "logs" / "runner.jsonl"
    handler = add_file_log(path, CTX, max_bytes=4000, backup_count=2, logger=logger)
    try:
        for i in range(1000):
            logger.info("line %d of the flood", i)
    finally:
        handler.close()
    assert handler not in logger.handlers
    files = sorted(tmp_path.joinpath("logs").iterdir())
    assert [f.name for f in files] == ["runner.jsonl", "runner.jsonl.1", "runner.jsonl.2"]
    lines = []
    for f in files:
        assert f.stat().st_size <= 4000
        lines += [json.loads(t) for t in f.read_text().splitlines()]
    assert handler.stats.queued + handler.stats.dropped == 1000
    assert 0 < len(lines) < 1000  # the oldest went with the rotation
    newest = json.loads(path.read_text().splitlines()[-1])
    assert newest["message"].startswith("line ")
    assert newest["process"] == "runner"
    assert handler.stats.dropped == 0  # 1000 lines fit the queue (4096)
    assert newest["message"] == "line 999 of the flood"


def test_a_stuck_file_writer_drops_and_counts(tmp_path: Path, logger: logging.Logger) -> None:
    """The thread that logs never waits for the disk: with the writer stuck, lines past
    the queue's bound are dropped and counted."""
    handler = JsonFileLog(tmp_path / "x.jsonl", context=CTX, capacity=4)
    logger.addHandler(handler)
    handler.file.acquire()  # the writer thread blocks on its next line
    try:
        for i in range(20):
            logger.info("line %d", i)
    finally:
        handler.file.release()
        handler.close()
    assert handler.stats.queued + handler.stats.dropped == 20
    assert handler.stats.dropped >= 20 - 4 - 1  # at most one taken by the stuck writer
    lines = (tmp_path / "x.jsonl").read_text().splitlines()
    assert len(lines) == handler.stats.queued
    assert json.loads(lines[0])["message"] == "line 0"


# -- the fabric ---------------------------------------------------------------------------


def _log_records(h: Harness) -> list[LogRecord]:
    return [
        r.decode(LogRecord)
        for r in h.of(keys.Kind.LOG)
        if r.envelope is not None and r.envelope.type == LogRecord.TYPE
    ]


@asynccontextmanager
async def _peer(h: Harness) -> AsyncIterator[ZenohFabric]:
    """A Zenoh session of its own, connected to the harness's over loopback."""
    async with ZenohFabric(ZenohConfig(connect=[h.endpoint])) as fabric:
        yield fabric


@pytest.mark.zenoh
async def test_the_fabric_handler_delivers_records_over_zenoh(logger: logging.Logger) -> None:
    async with Harness(system=S, fabric="zenoh") as h, _peer(h) as fabric:
        key = keys.log(S, "runner-robot")
        await fabric.wait_matched(key)
        async with publish_logs(fabric, CTX, node="runner-robot", logger=logger) as handlers:
            logger.info("ready: %s", "tcp/127.0.0.1:1")
            try:
                raise KeyError("k")
            except KeyError:
                logger.exception("node %s: handler failed", "planner")
            await h.wait_for(lambda r: len(_log_records(h)) == 2)
        (fh,) = handlers
    first, second = _log_records(h)
    assert first.message == "ready: tcp/127.0.0.1:1"
    assert first.level == "INFO"
    assert second.level == "ERROR"
    assert "KeyError: 'k'" in second.exc
    rec = next(r for r in h.of(keys.Kind.LOG) if r.envelope and r.envelope.type == LogRecord.TYPE)
    assert rec.key == key
    assert rec.envelope is not None
    assert rec.envelope.source == "runner-robot.log"  # not the node's rejections' sequence
    assert fh.stats.sent == 2
    assert fh.stats.dropped == fh.stats.lost == 0


class _Chatty:
    """A fabric whose publishing logs a line (as a failing link would): the handler must
    not publish that line in turn, for ever."""

    def __init__(self, fabric: ZenohFabric, logger: logging.Logger) -> None:
        self._fabric = fabric
        self._logger = logger

    def __getattr__(self, name: str) -> Any:
        return getattr(self._fabric, name)

    async def publish(self, key: str, payload: Any, **kw: Any) -> None:
        self._logger.warning("publishing on %s", key)
        await self._fabric.publish(key, payload, **kw)


@pytest.mark.zenoh
async def test_a_flood_is_dropped_and_counted_without_blocking(logger: logging.Logger) -> None:
    async with Harness(system=S, fabric="zenoh") as h, _peer(h) as fabric:
        handler = FabricLogHandler(fabric, system=S, node="flood", context=CTX, capacity=16)
        await fabric.wait_matched(keys.log(S, "flood"))
        logger.addHandler(handler)
        async with anyio.create_task_group() as tg:
            await tg.start(handler.run)
            # 5000 lines without giving the loop a turn: logging never waits for the
            # fabric, the queue keeps 16 and counts the rest
            for i in range(5000):
                logger.info("flood %d", i)
            assert handler.stats.queued == 16
            assert handler.stats.dropped == 5000 - 16
            await h.wait_for(lambda r: len(_log_records(h)) == 16)
            # the loop was free all along: the queue drains, a later line goes through
            logger.warning("after the flood")
            await h.wait_for(lambda r: len(_log_records(h)) == 17)
            tg.cancel_scope.cancel()
    got = _log_records(h)
    assert [r.message for r in got[:3]] == ["flood 0", "flood 1", "flood 2"]
    assert got[-1].message == "after the flood"


@pytest.mark.zenoh
async def test_a_line_logged_while_publishing_is_not_published(logger: logging.Logger) -> None:
    async with Harness(system=S, fabric="zenoh") as h, _peer(h) as fabric:
        chatty = _Chatty(fabric, logger)
        handler = FabricLogHandler(chatty, system=S, node="chatty", context=CTX)
        await fabric.wait_matched(keys.log(S, "chatty"))
        logger.addHandler(handler)
        async with anyio.create_task_group() as tg:
            await tg.start(handler.run)
            for i in range(3):
                logger.info("line %d", i)
            await h.wait_for(lambda r: len(_log_records(h)) == 3)
            await anyio.sleep(0.2)  # a recursion would go on publishing here
            tg.cancel_scope.cancel()
    assert [r.message for r in _log_records(h)] == ["line 0", "line 1", "line 2"]
    assert handler.stats.recursive == 3


# -- Redis ---------------------------------------------------------------------------------


class _Redis:
    """A redis-server of the test's own on a free loopback port (no persistence)."""

    def __init__(self, directory: Path) -> None:
        self.binary = require_binary("redis-server", hint="apt-get install redis-server")
        self.directory = directory
        self.port = free_port()
        self.proc: Process | None = None

    @property
    def url(self) -> str:
        return f"redis://127.0.0.1:{self.port}/0"

    async def start(self) -> None:
        argv = [self.binary, "--bind", "127.0.0.1", "--port", str(self.port)]
        argv += ["--dir", str(self.directory), "--save", "", "--appendonly", "no"]
        self.proc = await anyio.open_process(argv, stdout=subprocess.PIPE, stderr=subprocess.STDOUT)
        assert self.proc.stdout is not None
        seen = b""
        with anyio.fail_after(10):
            async for chunk in self.proc.stdout:
                seen += chunk
                if b"Ready to accept connections" in seen:
                    return

    async def kill(self) -> None:
        if self.proc is not None:
            self.proc.kill()
            await self.proc.wait()
            await self.proc.aclose()
            self.proc = None

    async def stop(self) -> None:
        if self.proc is not None:
            await stop_process(self.proc, grace=5)
            await self.proc.aclose()
            self.proc = None


@asynccontextmanager
async def _redis(tmp_path: Path) -> AsyncIterator[_Redis]:
    server = _Redis(tmp_path)
    await server.start()
    try:
        yield server
    finally:
        await server.stop()


async def _entries(url: str, stream: str) -> list[LogRecord]:
    import redis.asyncio

    client = redis.asyncio.from_url(url)
    try:
        rows = await client.xrange(stream)
    finally:
        await client.aclose()
    return [
        msgspec.json.decode(fields[b"record"], type=LogRecord)
        for _, fields in rows or []
        if fields is not None
    ]


async def _until(pred: Any, timeout: float = 10.0) -> None:
    with anyio.fail_after(timeout):
        while not await pred():  # noqa: ASYNC110 (counters, and a server's stream)
            await anyio.sleep(0.02)


@pytest.mark.redis
async def test_the_redis_stream_stays_bounded(tmp_path: Path, logger: logging.Logger) -> None:
    stream = f"{redis_stream(S)}:{free_port()}"
    async with _redis(tmp_path) as server:
        handler = RedisStreamHandler(server.url, stream=stream, maxlen=50, context=CTX)
        logger.addHandler(handler)
        async with anyio.create_task_group() as tg:
            await tg.start(handler.run)
            for i in range(1000):
                logger.info("entry %d", i)
                if i % 100 == 99:
                    await anyio.lowlevel.checkpoint()  # let the handler send (its queue holds 4096)

            async def all_sent() -> bool:
                return handler.stats.sent == 1000

            await _until(all_sent)
            tg.cancel_scope.cancel()
        await handler.aclose()
        got = await _entries(server.url, stream)
    # MAXLEN ~ 50 trims whole macro nodes (100 entries a node by default): about 50
    assert 50 <= len(got) <= 150
    assert got[-1].message == "entry 999"
    assert got[-1].process == "runner"


@pytest.mark.redis
async def test_the_redis_handler_survives_the_server_going_away(
    tmp_path: Path, logger: logging.Logger
) -> None:
    stream = redis_stream(S)
    server = _Redis(tmp_path)
    await server.start()
    try:
        handler = RedisStreamHandler(server.url, stream=stream, context=CTX, capacity=64)
        logger.addHandler(handler)
        async with anyio.create_task_group() as tg:
            await tg.start(handler.run)
            logger.info("before")

            async def sent(n: int) -> bool:
                return handler.stats.sent >= n

            await _until(lambda: sent(1))
            await server.kill()
            for i in range(200):  # while it is down: kept up to the queue's bound, counted
                logger.info("while down %d", i)
                await anyio.lowlevel.checkpoint()

            async def failing() -> bool:
                return handler.stats.failures >= 2

            await _until(failing)
            assert handler.stats.dropped > 0
            assert handler.stats.queued - handler.stats.sent <= 64 + 1
            await server.start()  # back on the same port
            logger.info("after")

            async def arrived() -> bool:
                got = await _entries(server.url, stream)
                return bool(got) and got[-1].message == "after"

            await _until(arrived, timeout=20)  # within the retry delay
            tg.cancel_scope.cancel()
        await handler.aclose()
        got = [r.message for r in await _entries(server.url, stream)]
    finally:
        await server.stop()
    # the server lost "before" with its memory; what waited in the queue came through
    assert "before" not in got
    assert got[-1] == "after"
    assert got[0].startswith("while down ")
    assert len(got) <= 64 + 1

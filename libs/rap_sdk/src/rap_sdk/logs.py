"""Structured logs: one JSON object per line, to a bounded file, the fabric and Redis.

    ctx = LogContext(system="demo", compute_node="robot", process="runner",
                     components={"lidar_occlusion.nodes": "analysis"})
    file = add_file_log(Path("runner.jsonl"), ctx)        # rotating, bounded, own thread
    async with publish_logs(fabric, ctx, node="runner-robot",
                            redis_url="redis://127.0.0.1:6379/0"):
        ...                                                # log as usual
    file.close()

Every line is a :class:`~rap_schemas.LogRecord` (``ts`` UTC ns, ``level``, ``logger``,
``message``, ``system``, ``compute_node``, ``process``, ``component`` when known,
``exc``) as JSON: the same object in the files, on the fabric (``rap/<system>/log/<node>``,
envelope type ``rap.LogRecord/1``, beside the ``rap.Rejection/1`` records of that key)
and in the Redis stream (field ``record``).

No handler here blocks the event loop or the thread that logs: a line is formatted where
it is logged and handed over through a bounded queue (the file's to a writer thread, the
fabric's and Redis's to a task on the loop); when the queue is full the line is dropped
and counted (``handler.stats.dropped``). A line logged while a handler publishes one (the
fabric logging about its own publishing, say) is not published again (counted in
``stats.recursive``), and this module's own warnings go to the other handlers only. A
Redis that is down or goes away is retried with a growing delay; the process goes on.
"""

from __future__ import annotations

import asyncio
import contextlib
import contextvars
import logging
import logging.handlers
import queue
import threading
from collections import deque
from collections.abc import AsyncIterator, Mapping, Sequence
from contextlib import asynccontextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Final

import anyio
import msgspec
from anyio.abc import TaskStatus
from rap_schemas import LogRecord, keys
from rap_schemas.logrecord import MAX_LOG_MESSAGE

from .envelope import Sealer
from .errors import RapError
from .fabric import Fabric
from .rejections import Throttle

__all__ = [
    "BACKUP_COUNT",
    "MAX_BYTES",
    "REDIS_MAXLEN",
    "FabricLogHandler",
    "JsonFileLog",
    "JsonFormatter",
    "LogContext",
    "LogStats",
    "RedisStreamHandler",
    "add_file_log",
    "check_redis_url",
    "open_file_log",
    "publish_logs",
    "redis_stream",
]

log = logging.getLogger(__name__)

MAX_BYTES: Final = 10 * 1024 * 1024
"""Bytes a JSON lines file grows to before it is rotated."""
BACKUP_COUNT: Final = 5
"""Rotated files kept (``x.jsonl.1`` ... ``x.jsonl.5``): a file log takes at most
``MAX_BYTES * (BACKUP_COUNT + 1)`` bytes."""
CAPACITY: Final = 4096
"""Lines a handler's queue holds; past it lines are dropped and counted."""
REDIS_MAXLEN: Final = 100_000
"""Entries a Redis log stream keeps (``XADD ... MAXLEN ~``: about that many)."""
BATCH: Final = 256
"""Lines sent to Redis in one round trip at most."""
RETRY_FIRST: Final = 0.5
RETRY_MAX: Final = 30.0
"""Seconds between attempts to reach a Redis that is down: doubling from the first to the
max."""

_publishing: contextvars.ContextVar[bool] = contextvars.ContextVar("rap_log_publishing")
_encode = msgspec.json.Encoder().encode
_LEVELS: Final = ("DEBUG", "INFO", "WARNING", "ERROR", "CRITICAL")


def redis_stream(system: str) -> str:
    """The Redis stream key of a system's logs (``rap:<system>:log``)."""
    keys.system_pattern(system)  # validates the name
    return f"rap:{system}:log"


@dataclass(frozen=True, slots=True)
class LogContext:
    """What a process says about itself in each line."""

    system: str = ""
    compute_node: str = ""
    process: str = ""
    components: Mapping[str, str] = field(default_factory=dict)
    """Logger name (or prefix: a package's modules) -> the component its lines are about
    (the module of a component's Node)."""
    names: frozenset[str] = frozenset()
    """The components this process runs: a line of RAP's own loggers (``rap_sdk...``)
    whose first argument is one of them (``node %s: ...``) is about that component."""


def _cut(text: str) -> str:
    if len(text) <= MAX_LOG_MESSAGE:
        return text
    return text[:MAX_LOG_MESSAGE] + f"... [{len(text) - MAX_LOG_MESSAGE} characters cut]"


class JsonFormatter(logging.Formatter):
    """Formats a ``logging`` record as one JSON object (a :class:`LogRecord`)."""

    def __init__(self, context: LogContext | None = None) -> None:
        super().__init__()
        self.context = context or LogContext()
        self._prefixes = sorted(self.context.components.items(), key=lambda kv: -len(kv[0]))

    def component(self, record: logging.LogRecord) -> str:
        given = record.__dict__.get("component")
        if isinstance(given, str):
            return given
        name = record.name
        for prefix, comp in self._prefixes:
            if name == prefix or name.startswith(prefix + "."):
                return comp
        args = record.args
        if (
            self.context.names
            and name.startswith("rap_sdk")
            and isinstance(args, tuple)
            and args
            and isinstance(args[0], str)
            and args[0] in self.context.names
        ):
            return args[0]
        return ""

    def to_message(self, record: logging.LogRecord) -> LogRecord:
        try:
            message = record.getMessage()
        except (TypeError, ValueError) as exc:  # a format string and arguments that differ
            message = f"{record.msg!r} % {record.args!r} (cannot be formatted: {exc})"
        exc_text = ""
        if record.exc_info:
            exc_text = self.formatException(record.exc_info)
        elif record.exc_text:
            exc_text = record.exc_text
        if record.stack_info:
            exc_text = f"{exc_text}\n{self.formatStack(record.stack_info)}".strip()
        ctx = self.context
        level = record.levelname if record.levelname in _LEVELS else f"LEVEL{record.levelno}"
        return LogRecord(
            ts=int(record.created * 1e9),
            level=level,
            logger=record.name,
            message=_cut(message),
            system=ctx.system,
            compute_node=ctx.compute_node,
            process=ctx.process,
            component=self.component(record),
            exc=_cut(exc_text),
        )

    def format(self, record: logging.LogRecord) -> str:
        return _encode(self.to_message(record)).decode()


@dataclass(slots=True)
class LogStats:
    queued: int = 0
    """Lines taken into the handler's queue (a file's: written once its writer thread
    has taken them)."""
    dropped: int = 0
    """Lines dropped because the queue was full."""
    sent: int = 0
    """Lines written or published."""
    lost: int = 0
    """Lines that could not be published (the fabric refused or timed out)."""
    unheard: int = 0
    """Lines not published because nobody subscribed (fabric)."""
    recursive: int = 0
    """Lines logged while a line was being published: not published."""
    failures: int = 0
    """Failed attempts to reach the sink (Redis down)."""


# -- the file --------------------------------------------------------------------------------


class _Passthrough(logging.Formatter):
    def format(self, record: logging.LogRecord) -> str:
        return str(record.msg)


class _Listener(logging.handlers.QueueListener):
    """The writer thread; at the end it writes what is queued, however full the queue."""

    def enqueue_sentinel(self) -> None:
        # the queue may be full: wait for the writer to make room (it is draining)
        self.queue.put(self._sentinel, timeout=10)  # type: ignore[attr-defined]


class JsonFileLog(logging.handlers.QueueHandler):
    """JSON lines into a rotating, bounded file, written by a thread of its own: the
    thread that logs only formats and queues (bounded: dropped and counted when full)."""

    def __init__(
        self,
        path: Path,
        *,
        context: LogContext | None = None,
        max_bytes: int = MAX_BYTES,
        backup_count: int = BACKUP_COUNT,
        capacity: int = CAPACITY,
    ) -> None:
        super().__init__(queue.Queue(capacity))
        self.stats = LogStats()
        self.path = path
        self.setFormatter(JsonFormatter(context))
        path.parent.mkdir(parents=True, exist_ok=True)
        self.file = logging.handlers.RotatingFileHandler(
            path, maxBytes=max_bytes, backupCount=backup_count, encoding="utf-8"
        )
        self.file.setFormatter(_Passthrough())
        self.listener = _Listener(self.queue, self.file)
        self.listener.start()
        self._closed = False
        self.attached: logging.Logger | None = None
        """The logger :func:`add_file_log` added it to (it leaves it when closed)."""

    def enqueue(self, record: logging.LogRecord) -> None:
        try:
            self.queue.put_nowait(record)
        except queue.Full:
            self.stats.dropped += 1
        else:
            self.stats.queued += 1

    def prepare(self, record: logging.LogRecord) -> logging.LogRecord:
        # the JSON line is made here, in the thread that logs (it holds the record's
        # exception); the writer thread only writes it
        line = self.format(record)
        out = logging.makeLogRecord({"name": record.name, "levelno": record.levelno})
        out.msg, out.args, out.exc_info, out.exc_text = line, None, None, None
        return out

    def close(self) -> None:
        """Write what is queued, stop the writer thread, close the file."""
        if self.attached is not None:
            self.attached.removeHandler(self)
            self.attached = None
        if not self._closed:
            self._closed = True
            try:
                self.listener.stop()
            except queue.Full:  # the writer is stuck (a dead disk): leave it, daemon
                log.error("log file %s: its writer is stuck; lines not written", self.path)
            self.file.close()
        super().close()


def add_file_log(
    path: Path,
    context: LogContext | None = None,
    *,
    max_bytes: int = MAX_BYTES,
    backup_count: int = BACKUP_COUNT,
    logger: logging.Logger | None = None,
) -> JsonFileLog:
    """Log to ``path`` as JSON lines (rotated at ``max_bytes``, ``backup_count`` old
    files kept) from now on, on ``logger`` (the root logger by default). ``close()`` it
    at the end (it also leaves the logger)."""
    handler = JsonFileLog(path, context=context, max_bytes=max_bytes, backup_count=backup_count)
    target = logger or logging.getLogger()
    target.addHandler(handler)
    handler.attached = target
    return handler


# -- handlers that send from the event loop ---------------------------------------------------


class _LoopHandler(logging.Handler):
    """Formats a record where it is logged and queues it (bounded) for a task on the
    event loop, which :meth:`run` is; any thread may log."""

    def __init__(self, context: LogContext | None, capacity: int) -> None:
        super().__init__()
        self.formatter_ = JsonFormatter(context)
        self.capacity = capacity
        self.stats = LogStats()
        self._queue: deque[LogRecord] = deque()
        self._loop: asyncio.AbstractEventLoop | None = None
        self._thread = 0
        self._wake: asyncio.Event | None = None
        self._woken = False

    def emit(self, record: logging.LogRecord) -> None:
        if record.name == __name__:
            return  # this module's own warnings (about these handlers) stay off them
        if _publishing.get(False):
            self.stats.recursive += 1
            return
        if len(self._queue) >= self.capacity:
            self.stats.dropped += 1
            return
        try:
            msg = self.formatter_.to_message(record)
        except Exception:  # logging's contract: a handler reports, never raises
            self.handleError(record)
            return
        self._queue.append(msg)
        self.stats.queued += 1
        self._kick()

    def _kick(self) -> None:
        loop, wake = self._loop, self._wake
        if loop is None or wake is None or self._woken:
            return
        self._woken = True
        if threading.get_ident() == self._thread:
            wake.set()
        else:
            with contextlib.suppress(RuntimeError):  # the loop has closed
                loop.call_soon_threadsafe(wake.set)

    async def run(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        """Send queued lines until cancelled."""
        self._loop = asyncio.get_running_loop()
        self._thread = threading.get_ident()
        wake = self._wake = asyncio.Event()
        _publishing.set(True)  # in this task (its context) only
        task_status.started()
        q = self._queue
        while True:
            if not q:
                self._woken = False
                wake.clear()
                if not q:
                    await wake.wait()
                    continue
            batch = [q.popleft() for _ in range(min(len(q), BATCH))]
            await self._send(batch)

    async def flush_async(self, timeout: float = 2.0) -> None:
        """Wait (at most ``timeout`` s) until the queue is empty."""
        with anyio.move_on_after(timeout):
            while self._queue and self._loop is not None:
                self._kick()
                await anyio.sleep(0.01)

    async def _send(self, batch: list[LogRecord]) -> None:
        raise NotImplementedError


class FabricLogHandler(_LoopHandler):
    """Publishes each line as a ``rap.LogRecord/1`` on ``rap/<system>/log/<node>`` (only
    while someone subscribes to it). Run :meth:`run` in a task on the fabric's loop.

    The envelopes' source is ``<node>.log``: a node's own ``Rejection`` records on the
    same key keep their sequence (receivers count gaps per source and key)."""

    def __init__(
        self,
        fabric: Fabric,
        *,
        system: str,
        node: str,
        context: LogContext | None = None,
        capacity: int = CAPACITY,
        timeout: float = 0.5,
    ) -> None:
        super().__init__(context, capacity)
        self.fabric = fabric
        self.key = keys.log(system, node)
        self.sealer = Sealer(f"{node}.log")
        self.timeout = timeout
        self._heard = (-1, False)

    async def _send(self, batch: list[LogRecord]) -> None:
        fabric, key = self.fabric, self.key
        epoch, heard = self._heard
        if epoch != fabric.epoch:
            epoch = fabric.epoch
            try:
                heard = fabric.has_subscribers(key)
            except RapError:  # the fabric has closed
                heard = False
            self._heard = (epoch, heard)
        if not heard:
            self.stats.unheard += len(batch)
            return
        for msg in batch:
            payload, _ = self.sealer.seal_message(key, msg)
            try:
                await fabric.publish(key, payload, timeout=self.timeout)
            except RapError:
                self.stats.lost += 1
            else:
                self.stats.sent += 1


class RedisStreamHandler(_LoopHandler):
    """Adds each line to a Redis stream (``XADD stream MAXLEN ~ maxlen * record
    <json>``), bounded to about ``maxlen`` entries. A Redis that cannot be reached is
    retried with a growing delay (``RETRY_FIRST`` to ``RETRY_MAX`` s); lines wait in the
    bounded queue meanwhile. Run :meth:`run` in a task."""

    def __init__(
        self,
        url: str,
        *,
        stream: str,
        maxlen: int = REDIS_MAXLEN,
        context: LogContext | None = None,
        capacity: int = CAPACITY,
        timeout: float = 2.0,
    ) -> None:
        super().__init__(context, capacity)
        self.url = url
        self.stream = stream
        self.maxlen = maxlen
        self.timeout = timeout
        self.retry = RETRY_FIRST
        self._client: Any = None
        self._throttle = Throttle(interval_ns=30_000_000_000)

    def _connect(self) -> Any:
        if self._client is None:
            import redis.asyncio

            self._client = redis.asyncio.from_url(
                self.url, socket_timeout=self.timeout, socket_connect_timeout=self.timeout
            )
        return self._client

    async def _send(self, batch: list[LogRecord]) -> None:
        import redis

        while True:
            try:
                async with self._connect().pipeline(transaction=False) as pipe:
                    for msg in batch:
                        pipe.xadd(
                            self.stream,
                            {"record": _encode(msg)},
                            maxlen=self.maxlen,
                            approximate=True,
                        )
                    await pipe.execute()
            except (redis.RedisError, OSError) as exc:
                self.stats.failures += 1
                count = self._throttle.hit("down")
                if count:
                    log.warning(
                        "log stream %s on %s: cannot add %d line(s) (%s, %d failure(s) in "
                        "all); retrying in %g s, lines wait in a queue of %d",
                        self.stream,
                        self.url,
                        len(batch),
                        exc,
                        self.stats.failures,
                        self.retry,
                        self.capacity,
                    )
                await anyio.sleep(self.retry)
                self.retry = min(self.retry * 2, RETRY_MAX)
                # lines that came meanwhile wait behind these; the queue stays bounded
                over = len(batch) + len(self._queue) - self.capacity
                if over > 0:
                    del batch[:over]
                    self.stats.dropped += over
                continue
            self.stats.sent += len(batch)
            self.retry = RETRY_FIRST
            return

    async def aclose(self) -> None:
        if self._client is not None:
            client, self._client = self._client, None
            with contextlib.suppress(OSError):
                await client.aclose()


@asynccontextmanager
async def publish_logs(
    fabric: Fabric | None,
    context: LogContext,
    *,
    node: str,
    redis_url: str | None = None,
    redis_maxlen: int = REDIS_MAXLEN,
    logger: logging.Logger | None = None,
) -> AsyncIterator[Sequence[_LoopHandler]]:
    """For the duration of the block, publish what ``logger`` (the root logger by
    default) logs on the fabric (``rap/<system>/log/<node>``) and, with ``redis_url``,
    in the Redis stream :func:`redis_stream` of the system. What is queued at the end is
    sent within a second or two."""
    target = logger or logging.getLogger()
    handlers: list[_LoopHandler] = []
    if fabric is not None:
        handlers.append(FabricLogHandler(fabric, system=context.system, node=node, context=context))
    redis_handler = None
    if redis_url is not None:
        redis_handler = RedisStreamHandler(
            redis_url, stream=redis_stream(context.system), maxlen=redis_maxlen, context=context
        )
        handlers.append(redis_handler)
    async with anyio.create_task_group() as tg:
        for h in handlers:
            await tg.start(h.run)
            target.addHandler(h)
        try:
            yield handlers
        finally:
            for h in handlers:
                target.removeHandler(h)
            with anyio.CancelScope(shield=True):
                for h in handlers:
                    await h.flush_async(1.0)
                if redis_handler is not None:
                    await redis_handler.aclose()
            tg.cancel_scope.cancel()


def open_file_log(
    path: Path | None, context: LogContext, option: str = "--log-file"
) -> JsonFileLog | None:
    """For a command line's ``--log-file PATH``: JSON lines to ``path`` from now on (None:
    not given); an :class:`~rap_sdk.entry.EntryError` line when it cannot be opened."""
    from .entry import fail

    if path is None:
        return None
    try:
        return add_file_log(path, context)
    except OSError as exc:
        raise fail(
            f"{option} {path}: cannot write it ({exc.strerror or exc}) - give a file in a "
            "folder you can write"
        ) from None


def check_redis_url(url: str | None, option: str = "--log-redis") -> str | None:
    """A command line's ``--log-redis URL`` checked (None: not given)."""
    from .entry import fail

    if url is not None and not url.startswith(("redis://", "rediss://", "unix://")):
        raise fail(f"{option} {url!r} is not a Redis URL - write e.g. redis://127.0.0.1:6379/0")
    return url

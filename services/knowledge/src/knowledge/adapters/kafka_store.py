"""The knowledge stream on Kafka: the service's SQLite store keeps knowledge, and every
record it takes is also appended to a Kafka topic, for consumers outside RAP.

Kafka is not the store here: latest values, compare-and-set, history, the key list,
models and pins are the SQLite store's (:class:`~knowledge.adapters.sqlite_store.SqliteStore`
with its outbox), so a write is acknowledged once it is in the SQLite file, whether or
not the broker is there, and a read never waits for the broker. What the topic gets:

- every record that joined the store, in the order the store committed them (a
  re-applied record or a refused compare-and-set joins nothing and is not sent; an
  older version that only joins history is sent: read ``version`` to order a key);
- at least once: the store writes each record to its outbox in the same transaction as
  the record itself, and deletes it from there only once the broker acknowledged it
  with ``acks=all``; a service killed, or a broker away, meanwhile leaves it there, and
  it is sent when both are back (a batch cut off mid-way is sent again whole, so a
  consumer may see a record twice: ``key``, ``version`` and ``writer`` identify it);
- the Kafka record key is the knowledge key (every version of a key in one partition,
  in order, and a topic with ``cleanup.policy=compact`` keeps the last one of each key);
  the value is the :class:`~rap_schemas.KbRecord` in msgpack (a map: ``key``,
  ``version``, ``ts``, ``writer``, ``value``, ``deleted`` when true); the headers
  ``rap-type`` (``rap.KbRecord/1``), ``rap-kb-version`` and ``rap-kb-writer`` (UTF-8)
  let a consumer filter without decoding.

The topic is ``rap.<system>.kb`` unless one is given; the broker creates it (or it is
created beforehand, with the retention the consumers need). The outbox has no bound of
its own: while the broker is away it grows on disk, and :attr:`KafkaStore.backlog` says
by how much (logged, rate-limited).
"""

from __future__ import annotations

import logging
import re
import time
from types import TracebackType
from typing import Any, Final
from urllib.parse import urlsplit

import anyio
import msgspec
from aiokafka import AIOKafkaProducer  # type: ignore[import-untyped]
from aiokafka.errors import (  # type: ignore[import-untyped]
    KafkaError,
    MessageSizeTooLargeError,
    RecordTooLargeError,
)
from anyio.abc import TaskGroup, TaskStatus
from rap_schemas import KbRecord

from ..errors import BadRequest, StoreUnavailable
from ..ports import Applied
from .layered import Layered
from .sqlite_store import SqliteStore

__all__ = ["DEFAULT_PORT", "DEFAULT_URL", "KafkaStore", "default_topic", "parse_url"]

log = logging.getLogger(__name__)
_TOO_LARGE = (MessageSizeTooLargeError, RecordTooLargeError)

DEFAULT_PORT: Final = 9092
DEFAULT_URL: Final = "kafka://127.0.0.1:9092"
BATCH: Final = 500
"""Outbox rows sent together (their acknowledgements awaited together)."""
RETRY_MAX_S: Final = 5.0
LOG_EVERY_S: Final = 10.0
_TOPIC = re.compile(r"[A-Za-z0-9._-]{1,249}")
_encode = msgspec.msgpack.Encoder().encode


def parse_url(url: str) -> str:
    """``kafka://HOST[:PORT]`` -> ``host:port`` (a Kafka client's bootstrap server);
    anything else is a :class:`~knowledge.errors.BadRequest` saying what to write."""
    try:
        parts = urlsplit(url)
        port = parts.port or DEFAULT_PORT
    except ValueError:
        parts, port = None, 0
    if (
        parts is None
        or parts.scheme != "kafka"
        or not parts.hostname
        or parts.path not in ("", "/")
        or parts.query
        or parts.fragment
        or parts.username is not None
    ):
        raise BadRequest(f"Kafka URL {url!r}: write kafka://HOST[:PORT], e.g. {DEFAULT_URL}")
    return f"{parts.hostname}:{port}"


def default_topic(system: str) -> str:
    return f"rap.{system}.kb"


def check_topic(topic: str) -> str:
    if topic in (".", "..") or not _TOPIC.fullmatch(topic):
        raise BadRequest(
            f"Kafka topic {topic!r}: 1 to 249 letters, digits, '.', '_' or '-', e.g. rap.demo.kb"
        )
    return topic


class KafkaStore(Layered):
    """A :class:`~knowledge.ports.Store`: ``inner`` (a SQLite store opened with
    ``outbox=True``, which this store closes with itself) keeps knowledge, and a task of
    this store sends its outbox to ``topic`` at the Kafka broker ``url``. Use it as an
    async context manager (the task runs inside it)."""

    _inner: SqliteStore

    def __init__(
        self,
        url: str,
        system: str,
        inner: SqliteStore,
        *,
        topic: str | None = None,
        timeout: float = 10.0,
    ) -> None:
        self._bootstrap = parse_url(url)
        self._url = url
        self.topic = check_topic(topic or default_topic(system))
        self._inner = inner
        self._timeout = timeout
        self._producer: Any = None
        self._wake = anyio.Event()
        self._progress = anyio.Event()
        """Set (and made anew) each time records leave the outbox."""
        self._tg: TaskGroup | None = None
        self.published = 0
        self.refused = 0
        """Records the broker refused for good (too large): in the store, not the topic."""
        """Records the broker acknowledged."""
        self.backlog = 0
        """Records in the outbox when it was last read."""
        self.connected = False
        self._logged = 0.0

    @property
    def inner(self) -> SqliteStore:
        return self._inner

    async def __aenter__(self) -> KafkaStore:
        tg = anyio.create_task_group()
        await tg.__aenter__()
        self._tg = tg
        try:
            await tg.start(self._publish)
        except BaseException as exc:
            tg.cancel_scope.cancel()
            await tg.__aexit__(type(exc), exc, exc.__traceback__)
            raise
        return self

    async def __aexit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> bool | None:
        tg, self._tg = self._tg, None
        try:
            if tg is not None:
                tg.cancel_scope.cancel()
                return await tg.__aexit__(exc_type, exc, tb)
            return None
        finally:
            with anyio.CancelScope(shield=True):
                await self._drop()
                await self._inner.aclose()

    async def aclose(self) -> None:
        """For :class:`~knowledge.ports.Store`: leaving the context closes everything."""

    # -- the stream --------------------------------------------------------------------------

    async def wait_sent(self) -> None:
        """Wait until the outbox is empty (everything so far acknowledged by the broker)."""
        while True:
            progress = self._progress
            if await self._inner.outbox_size() == 0:
                return
            await progress.wait()

    async def _publish(self, *, task_status: TaskStatus[None] = anyio.TASK_STATUS_IGNORED) -> None:
        task_status.started()
        delay = 0.1
        while True:
            wake = self._wake = anyio.Event()  # before reading: a write after it sets it
            try:
                rows = await self._inner.outbox_take(BATCH)
                if not rows:
                    self.backlog = 0
                    await wake.wait()
                    continue
                self.backlog = len(rows) if len(rows) < BATCH else await self._inner.outbox_size()
                await self._send(rows)
                await self._inner.outbox_done(rows[-1][0])
                self.published += len(rows)
                self._progress.set()
                self._progress = anyio.Event()
                delay = 0.1
            except (KafkaError, TimeoutError, OSError) as exc:
                await self._drop()
                self._warn(f"cannot send to Kafka at {self._url}: {type(exc).__name__}: {exc}")
                await anyio.sleep(delay)
                delay = min(delay * 2, RETRY_MAX_S)
            except StoreUnavailable as exc:
                self._warn(f"cannot read the outbox: {exc}")
                await anyio.sleep(delay)
                delay = min(delay * 2, RETRY_MAX_S)

    async def _send(self, rows: list[tuple[int, KbRecord]]) -> None:
        with anyio.fail_after(self._timeout * 2):
            if self._producer is None:
                producer = AIOKafkaProducer(
                    bootstrap_servers=self._bootstrap,
                    client_id="rap-knowledge",
                    acks="all",
                    request_timeout_ms=int(self._timeout * 1000),
                    max_request_size=64 << 20,
                )
                try:
                    await producer.start()
                except BaseException:
                    with anyio.CancelScope(shield=True):
                        await producer.stop()
                    raise
                self._producer = producer
                self.connected = True
                log.info("knowledge stream: connected to %s, topic %s", self._url, self.topic)
            sent = []
            for _, rec in rows:
                headers = [
                    ("rap-type", KbRecord.TYPE.encode()),
                    ("rap-kb-version", str(rec.version).encode()),
                    ("rap-kb-writer", rec.writer.encode()),
                ]
                sent.append(
                    await self._producer.send(
                        self.topic, _encode(rec), key=rec.key.encode(), headers=headers
                    )
                )
            for (_, rec), future in zip(rows, sent, strict=True):
                try:
                    await future  # acknowledged by the leader and the in-sync replicas
                except _TOO_LARGE as exc:  # refused for good: retrying would block the rest
                    self.refused += 1
                    log.error(
                        "knowledge stream: the broker refused %s version %d as too large "
                        "(%s); it stays in the store but is not in the topic %s (%d so far) "
                        "- raise the broker's message.max.bytes",
                        rec.key,
                        rec.version,
                        type(exc).__name__,
                        self.topic,
                        self.refused,
                    )

    def _warn(self, message: str) -> None:
        now = time.monotonic()
        if now - self._logged >= LOG_EVERY_S:
            self._logged = now
            log.warning(
                "knowledge stream: %s; %d record(s) wait in the outbox, retrying",
                message,
                self.backlog,
            )

    async def _drop(self) -> None:
        producer, self._producer = self._producer, None
        self.connected = False
        if producer is not None:
            with anyio.CancelScope(shield=True), anyio.move_on_after(2.0):
                try:
                    await producer.stop()
                except (KafkaError, OSError) as exc:
                    log.debug("knowledge stream: stopping the producer: %s", exc)

    # -- the store: the SQLite store's -------------------------------------------------------

    async def apply(
        self, rec: KbRecord, *, expect: int | None = None, deadline: float | None = None
    ) -> Applied:
        applied = await self._inner.apply(rec, expect=expect, deadline=deadline)
        if not applied.duplicate:
            self._wake.set()
        return applied

    async def get(self, key: str) -> KbRecord | None:
        return await self._inner.get(key)

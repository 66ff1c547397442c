"""The Kafka link (aiokafka; docs/bridges/kafka.md).

- ``out``: each message is produced to the topic ``address`` with the bridge's name as
  the record key, so that all of one bridge's messages land in one partition, in the
  order they were sent. Cycle, cause, wire type and sender go in Kafka record headers
  (``rap-cycle``, ``rap-cause``: 32 hex digits; ``rap-type``, ``rap-source``; values in
  UTF-8). At QoS >= 1 the producer asks for ``acks=all``: a message counts as sent once
  the partition's leader and all its in-sync replicas have it; a message whose
  acknowledgement was cut off by a lost connection is produced again after the
  reconnect (at least once: a consumer may see it twice). At QoS 0 (``acks=0``) a
  message counts as sent once written to the connection. QoS 2 is QoS 1 (Kafka's
  transactions are not used).
- ``in``: the bridge joins the consumer group ``group`` (default
  ``rap-bridge-<name>``) on the topic ``address``. Offsets are committed by the link,
  never automatically: after the records of a fetched batch have been handed to the
  bridge (its inbox took them), their offsets are committed, so that a bridge that is
  stopped, crashes or loses the broker before that gets them again (at least once),
  and one that comes back resumes where its group left off. A group without a
  committed offset (new, or forgotten by the broker) starts at the earliest record
  the topic keeps. Record headers ``rap-cycle``/``rap-cause``/``rap-type`` are read
  as the frame's headers; a record with a header value that is not UTF-8 is rejected
  (counted, and its offset committed with the others).
- A record larger than ``max_frame`` (+ 64 KiB for headers and framing) is not
  produced: it is rejected and counted (it would be refused by the broker each time it
  is sent again).
- No credentials and no TLS yet (the spec refuses them): the link speaks to a
  plaintext listener.

aiokafka reconnects by itself and keeps quiet about a broker that is gone; the link
notices: a send that gets no acknowledgement within ``TIMEOUT_S``, a metadata request
that no broker answers (every ``PROBE_S`` while idle) or a failed commit raise
:class:`LinkDown`, and the bridge makes the link again with its backoff.
"""

from __future__ import annotations

import asyncio
import logging
from collections.abc import Sequence
from typing import Any, Final

import anyio
from aiokafka import AIOKafkaConsumer, AIOKafkaProducer  # type: ignore[import-untyped]
from aiokafka.errors import (  # type: ignore[import-untyped]
    KafkaError,
    MessageSizeTooLargeError,
)
from aiokafka.structs import OffsetAndMetadata  # type: ignore[import-untyped]

from .core import Deliver, Frame, FrameRefused, LinkContext, LinkDown
from .spec import BridgeSpec

__all__ = ["HEADROOM", "PROBE_S", "TIMEOUT_S", "KafkaLink", "group_of"]

log = logging.getLogger(__name__)

TIMEOUT_S: Final = 10.0
"""How long a connection or an acknowledgement may take before the link counts as lost."""
PROBE_S: Final = 1.0
"""How often an idle link asks the broker for metadata, to notice it is gone."""
SESSION_TIMEOUT_MS: Final = 6000
"""An ``in`` bridge's consumer-group session: the broker hands its partitions to another
member this long after the bridge went silent (6 s: the least Kafka allows by default)."""
HEARTBEAT_MS: Final = 2000
STOP_S: Final = 2.0
"""How long a client may take to stop (leave its group, flush) before it is cut short."""
HEADROOM: Final = 64 * 1024
"""Bytes allowed beyond ``max_frame`` for a record's key, headers and framing."""
FETCH_RECORDS: Final = 500
"""Records taken per fetch; their offsets are committed together once handed over."""


def group_of(spec: BridgeSpec, name: str) -> str:
    """The consumer group of an ``in`` bridge: the spec's ``group``, else derived from the
    bridge's name."""
    return spec.group or f"rap-bridge-{name}"


def _fix(exc: BaseException, spec: BridgeSpec) -> str:
    text = f"{type(exc).__name__} {exc}".lower()
    if "authoriz" in text or "authentic" in text:
        return "the broker asks for credentials: connect to a plaintext listener without them"
    if "topic" in text and ("unknown" in text or "invalid" in text):
        return f"create topic {spec.address!r} or let the broker create topics"
    return f"is the broker running and reachable at {spec.host}:{spec.port}?"


def _why(exc: BaseException) -> str:
    text = str(exc)
    return f"{type(exc).__name__}: {text}" if text else type(exc).__name__


class KafkaLink:
    """A Kafka producer (``out``) or consumer-group member (``in``) for one bridge (see the
    module's documentation)."""

    def __init__(self, spec: BridgeSpec, ctx: LinkContext) -> None:
        self.spec = spec
        self.ctx = ctx
        self.client_id = f"rap-bridge-{ctx.name}"
        self.group = group_of(spec, ctx.name)
        self.key = ctx.name.encode()
        self.max_record = spec.max_frame + HEADROOM
        self._producer: Any = None
        self._consumer: Any = None

    @property
    def where(self) -> str:
        return self.spec.where

    def _common(self) -> dict[str, Any]:
        spec = self.spec
        return {
            "bootstrap_servers": f"{spec.host}:{spec.port}",
            "client_id": self.client_id,
            "request_timeout_ms": int(TIMEOUT_S * 1000),
            "retry_backoff_ms": 100,
        }

    async def open(self) -> None:
        await self._drop()
        spec = self.spec
        kw = self._common()
        if self.ctx.direction == "out":
            producer = AIOKafkaProducer(
                acks="all" if spec.qos > 0 else 0,
                max_request_size=self.max_record,
                linger_ms=0,
                **kw,
            )
            await self._start(producer, "cannot connect")
            self._producer = producer
            return
        consumer = AIOKafkaConsumer(
            spec.address,
            group_id=self.group,
            enable_auto_commit=False,
            auto_offset_reset="earliest",
            session_timeout_ms=SESSION_TIMEOUT_MS,
            heartbeat_interval_ms=HEARTBEAT_MS,
            max_partition_fetch_bytes=max(self.max_record, 1 << 20),
            **kw,
        )
        await self._start(consumer, f"cannot join consumer group {self.group!r}")
        self._consumer = consumer

    async def _start(self, client: Any, what: str) -> None:
        try:
            with anyio.fail_after(TIMEOUT_S * 2):  # a group join waits for the others
                await client.start()
        except (KafkaError, TimeoutError, OSError) as exc:
            await self._stop(client)
            raise LinkDown(f"{what}: {_why(exc)}", _fix(exc, self.spec)) from None
        except anyio.get_cancelled_exc_class():  # the bridge stops while it joins
            await self._stop(client)  # shielded: the client never outlives the link
            raise

    async def run(self, deliver: Deliver) -> None:
        if self._consumer is not None:
            await self._consume(self._consumer, deliver)
            return
        producer = self._producer
        if producer is None:
            raise LinkDown("not connected")
        while True:  # nothing comes in: watch that the broker is still there
            await anyio.sleep(PROBE_S)
            await self._probe(producer.client.fetch_all_metadata)

    async def _probe(self, ask: Any) -> None:
        try:
            with anyio.fail_after(TIMEOUT_S):
                await ask()
        except (KafkaError, TimeoutError, OSError) as exc:
            raise LinkDown(
                f"the broker stopped answering: {_why(exc)}", _fix(exc, self.spec)
            ) from None

    async def _consume(self, consumer: Any, deliver: Deliver) -> None:
        while True:
            try:
                batches = await consumer.getmany(
                    timeout_ms=int(PROBE_S * 1000), max_records=FETCH_RECORDS
                )
            except KafkaError as exc:
                raise LinkDown(f"fetch failed: {_why(exc)}", _fix(exc, self.spec)) from None
            if not batches:
                await self._probe(consumer.topics)  # quiet topic, or no broker?
                continue
            offsets = {}
            for tp, records in batches.items():
                for record in records:
                    frame = self._frame(record.value, record.headers)
                    if frame is not None:
                        await deliver(frame)
                offsets[tp] = OffsetAndMetadata(records[-1].offset + 1, "")
            try:
                # shielded: aiokafka runs the commit in a task of its own, which a
                # cancelled commit() would leave failing with nobody to hear it (a stop
                # waits for the commit instead, TIMEOUT_S at most)
                with anyio.CancelScope(shield=True), anyio.fail_after(TIMEOUT_S):
                    await consumer.commit(offsets)
            except (KafkaError, TimeoutError) as exc:
                raise LinkDown(
                    f"cannot commit offsets of group {self.group!r} (the records are "
                    f"delivered again after the reconnect): {_why(exc)}",
                    _fix(exc, self.spec),
                ) from None

    def _frame(self, value: bytes | None, headers: Sequence[tuple[str, bytes]]) -> Frame | None:
        found: dict[str, str] = {}
        for name, raw in headers:
            try:
                found[name] = raw.decode() if raw is not None else ""
            except UnicodeDecodeError:
                self.ctx.reject(f"record header {name!r} is not UTF-8")
                return None
        return Frame(value if value is not None else b"", found)

    async def send(self, frame: Frame) -> None:
        producer = self._producer
        if producer is None:
            raise LinkDown("not connected")
        headers = [(k, v.encode()) for k, v in frame.headers.items()]
        size = len(frame.payload) + len(self.key) + sum(len(k) + len(v) for k, v in headers)
        if size > self.max_record:
            raise FrameRefused(
                f"record of {size} bytes is over the limit of {self.max_record} (max_frame "
                f"+ {HEADROOM} for key and headers): not produced"
            )
        try:
            with anyio.fail_after(TIMEOUT_S * 2):  # metadata, then the acknowledgement
                await producer.send_and_wait(
                    self.spec.address, frame.payload, key=self.key, headers=headers
                )
        except MessageSizeTooLargeError as exc:  # the broker's own limit is lower
            raise FrameRefused(f"the broker refused the record as too large: {_why(exc)}") from None
        except (KafkaError, TimeoutError, OSError) as exc:
            raise LinkDown(f"produce failed: {_why(exc)}", _fix(exc, self.spec)) from None

    async def close(self) -> None:
        await self._drop()

    async def _drop(self) -> None:
        producer, self._producer = self._producer, None
        consumer, self._consumer = self._consumer, None
        for client in (producer, consumer):
            if client is not None:
                await self._stop(client)

    @staticmethod
    async def _stop(client: Any) -> None:
        """Stop an aiokafka client (it leaves its group, or flushes what it holds) within
        ``STOP_S``: one whose broker is gone is cut short there. aiokafka's consumer may
        let the ``CancelledError`` of a fetch it cancelled itself out of ``stop()``
        (aio-libs/aiokafka#647): that is a stopped client too, never a cancellation of
        the bridge (the scope is shielded: only its own deadline cancels it)."""
        with anyio.CancelScope(shield=True), anyio.move_on_after(STOP_S) as scope:
            try:
                await client.stop()
            except asyncio.CancelledError:
                if scope.cancel_called:
                    raise  # the deadline: move_on_after takes it
                log.debug("kafka link: %s stopped with a stray cancellation", type(client).__name__)
            except (KafkaError, OSError) as exc:  # already gone: nothing to say goodbye to
                log.debug("kafka link: stopping %s: %s", type(client).__name__, exc)
        if scope.cancelled_caught:
            log.debug("kafka link: %s did not stop within %s s", type(client).__name__, STOP_S)

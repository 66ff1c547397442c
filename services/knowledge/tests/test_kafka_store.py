"""The knowledge stream on Kafka against a real Tansu broker of the test's own, read back
with aiokafka's own consumer (a client no one here wrote): every record the store took
reaches the topic in commit order; writes are acknowledged while the broker is away and
reach it once it is back; the outbox outlives the service; the service itself runs on
the ``kafka`` backend."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from aiokafka import AIOKafkaConsumer  # type: ignore[import-untyped]
from knowledge.adapters.kafka_store import KafkaStore, check_topic, default_topic, parse_url
from knowledge.adapters.sqlite_store import SqliteStore
from knowledge.app import open_service
from knowledge.config import HistoryRule, KnowledgeConfig
from knowledge.core import Retention
from knowledge.errors import BadRequest, Conflict
from rap_schemas import KbRecord
from rap_sdk import MemoryBus, MemoryFabric
from rap_sdk.knowledge import KnowledgeClient
from rap_sdk.testing import TansuServer

pytestmark = [pytest.mark.anyio, pytest.mark.kafka]

TOPIC = default_topic("t")


@pytest.fixture
async def broker() -> AsyncIterator[TansuServer]:
    server = TansuServer()
    await server.start()
    try:
        yield server
    finally:
        await server.stop()


def rec(key: str, version: int, value: Any, *, writer: str = "w") -> KbRecord:
    return KbRecord(
        key=key,
        version=version,
        ts=time.time_ns(),
        writer=writer,
        value=msgspec.Raw(msgspec.msgpack.encode(value)),
    )


def sqlite(path: Path) -> SqliteStore:
    return SqliteStore(
        str(path / "kb.sqlite3"), Retention([HistoryRule(max_count=100)]), outbox=True
    )


async def read_topic(broker: TansuServer, n: int, topic: str = TOPIC) -> list[Any]:
    """The first ``n`` records of ``topic``, as aiokafka's consumer reads them (in the
    order of their partition: all records of one key share one)."""
    consumer = AIOKafkaConsumer(
        topic, bootstrap_servers=broker.bootstrap, group_id=None, auto_offset_reset="earliest"
    )
    await consumer.start()
    got: list[Any] = []
    try:
        with anyio.fail_after(20):
            async for record in consumer:
                got.append(record)
                if len(got) == n:
                    break
    finally:
        await consumer.stop()
    return got


def decoded(records: list[Any]) -> list[tuple[str, int, str, Any]]:
    out = []
    for r in records:
        kb = msgspec.msgpack.decode(r.value, type=KbRecord)
        assert r.key == kb.key.encode()
        out.append((kb.key, kb.version, kb.writer, msgspec.msgpack.decode(kb.value)))
    return out


async def test_every_record_the_store_took_reaches_the_topic_in_commit_order(
    broker: TansuServer, tmp_path: Path
) -> None:
    async with KafkaStore(f"kafka://{broker.bootstrap}", "t", await sqlite(tmp_path).open()) as s:
        await s.apply(rec("pose", 1, "a"))
        await s.apply(rec("pose", 3, "c"))
        await s.apply(rec("pose", 2, "b", writer="w2"))  # older: history only, still sent
        await s.apply(rec("pose", 3, "c"))  # the latest again: a no-op, not sent
        with pytest.raises(Conflict):
            await s.apply(rec("pose", 4, "lost"), expect=1)  # refused: not sent
        await s.apply(rec("pose", 4, "d"), expect=3)
        with anyio.fail_after(20):
            await s.wait_sent()
        assert s.published == 4
        records = await read_topic(broker, 4)
    assert decoded(records) == [
        ("pose", 1, "w", "a"),
        ("pose", 3, "w", "c"),
        ("pose", 2, "w2", "b"),
        ("pose", 4, "w", "d"),
    ]
    headers = dict(records[2].headers)
    assert headers == {
        "rap-type": b"rap.KbRecord/1",
        "rap-kb-version": b"2",
        "rap-kb-writer": b"w2",
    }


async def test_writes_are_acknowledged_while_the_broker_is_away_and_reach_it_after(
    broker: TansuServer, tmp_path: Path
) -> None:
    await broker.stop()
    async with KafkaStore(
        f"kafka://{broker.bootstrap}", "t", await sqlite(tmp_path).open(), timeout=1.0
    ) as s:
        with anyio.fail_after(5):  # the SQLite file acknowledges them: no waiting on Kafka
            for v in range(1, 21):
                await s.apply(rec(f"k{v % 3}", v, v))
        assert s.published == 0
        assert await s.inner.outbox_size() == 20
        assert (await s.get("k2")) is not None
        await broker.start()
        with anyio.fail_after(30):
            await s.wait_sent()
        assert s.published == 20
        records = await read_topic(broker, 20)
    by_key: dict[str, list[int]] = {}
    for key, version, _, _ in decoded(records):
        by_key.setdefault(key, []).append(version)
    assert sorted(v for vs in by_key.values() for v in vs) == list(range(1, 21))
    assert all(vs == sorted(vs) for vs in by_key.values())  # each key in commit order


async def test_the_outbox_outlives_the_service(broker: TansuServer, tmp_path: Path) -> None:
    """Records a service stored while the broker was away are sent by the next service
    on the same file."""
    await broker.stop()
    url = f"kafka://{broker.bootstrap}"
    async with KafkaStore(url, "t", await sqlite(tmp_path).open(), timeout=1.0) as s:
        for v in range(1, 6):
            await s.apply(rec("kept", v, v))
    await broker.start()
    async with KafkaStore(url, "t", await sqlite(tmp_path).open()) as again:
        with anyio.fail_after(20):
            await again.wait_sent()
        assert again.published == 5
        got = await again.get("kept")
        assert got is not None
        assert got.version == 5
        records = await read_topic(broker, 5)
    assert [version for _, version, _, _ in decoded(records)] == [1, 2, 3, 4, 5]


async def test_the_service_on_the_kafka_backend_streams_what_clients_write(
    broker: TansuServer, tmp_path: Path
) -> None:
    config = KnowledgeConfig(
        system="t",
        backend="kafka",
        sqlite_path=str(tmp_path / "kb.sqlite3"),
        kafka_url=f"kafka://{broker.bootstrap}",
        kafka_topic="ops.knowledge",
    )
    bus = MemoryBus()
    async with (
        MemoryFabric(bus=bus) as sf,
        open_service(config, fabric=sf),
        MemoryFabric(bus=bus) as cf,
        KnowledgeClient(fabric=cf, system="t", writer="robot", timeout=5.0) as kb,
    ):
        await kb.write("robot/pose", {"x": 1.5}, durable=True)
        await kb.write("robot/pose", {"x": 2.5}, durable=True)
        records = await read_topic(broker, 2, topic="ops.knowledge")
        assert await kb.read("robot/pose") == {"x": 2.5}
    got = decoded(records)
    assert [(k, w, v) for k, _, w, v in got] == [
        ("robot/pose", "robot", {"x": 1.5}),
        ("robot/pose", "robot", {"x": 2.5}),
    ]
    assert got[0][1] < got[1][1]


@pytest.mark.parametrize(
    ("url", "ok"),
    [
        ("kafka://broker", "broker:9092"),
        ("kafka://127.0.0.1:19092", "127.0.0.1:19092"),
        ("redis://x", None),
        ("kafka://u:p@broker", None),
        ("kafka://broker/topic", None),
    ],
)
def test_the_kafka_url(url: str, ok: str | None) -> None:
    if ok is not None:
        assert parse_url(url) == ok
    else:
        with pytest.raises(BadRequest, match=r"write kafka://HOST\[:PORT\]"):
            parse_url(url)


def test_the_topic_name() -> None:
    assert default_topic("demo") == "rap.demo.kb"
    assert check_topic("rap.demo.kb") == "rap.demo.kb"
    for bad in ("a/b", "..", "x" * 250, ""):
        with pytest.raises(BadRequest, match="1 to 249 letters"):
            check_topic(bad)

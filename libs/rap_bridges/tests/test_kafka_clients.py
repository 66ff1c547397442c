"""The Kafka bridge with clients no one here wrote (aiokafka's own producer, consumer and
group offsets API, used directly), against a Tansu broker of the test's own: the record
key, partition and headers an ``out`` bridge writes; an ``in`` bridge's consumer group
committing only what it took, and resuming there after the bridge itself restarts;
records and messages it cannot carry rejected and counted; what the spec accepts."""

from __future__ import annotations

import json
from collections.abc import AsyncIterator
from typing import Any

import anyio
import msgspec
import pytest
from aiokafka import AIOKafkaConsumer, AIOKafkaProducer  # type: ignore[import-untyped]
from aiokafka.structs import TopicPartition  # type: ignore[import-untyped]
from rap_bridges import Bridge, BridgeSpec, Direction
from rap_bridges.kafka import HEADROOM, group_of
from rap_sdk import MemoryFabric
from rap_sdk.testing import TansuServer

from libs.rap_bridges.tests.contract import KEY, FabricSide, Reading, fast_backoff, until
from libs.rap_bridges.tests.outside_kafka import frame_of, require_server

pytestmark = [pytest.mark.anyio]

CYCLE = bytes(range(16))
CAUSE = bytes(range(16, 32))


@pytest.fixture
async def server() -> AsyncIterator[TansuServer]:
    require_server()
    s = TansuServer()
    await s.start()
    try:
        yield s
    finally:
        await s.stop()


def spec(server: TansuServer, address: str, **kw: Any) -> BridgeSpec:
    return BridgeSpec(
        protocol="kafka", url=f"kafka://127.0.0.1:{server.port}", address=address, **kw
    )


def bridge(fabric: MemoryFabric, name: str, s: BridgeSpec, direction: Direction) -> Bridge:
    return Bridge(
        name, s, fabric, KEY, direction=direction, message=Reading, backoff=fast_backoff()
    )


async def produce(server: TansuServer, topic: str, records: list[tuple[bytes | None, Any]]) -> None:
    """aiokafka's producer, ``acks=all``, one key (one partition, in order)."""
    producer = AIOKafkaProducer(bootstrap_servers=server.bootstrap, acks="all")
    await producer.start()
    try:
        for value, headers in records:
            await producer.send_and_wait(topic, value, key=b"outside", headers=headers)
    finally:
        await producer.stop()


async def committed(server: TansuServer, group: str, topic: str) -> dict[int, int | None]:
    """The group's committed offset of each partition of ``topic``, as aiokafka reads it
    (without joining the group)."""
    consumer = AIOKafkaConsumer(bootstrap_servers=server.bootstrap, group_id=group)
    await consumer.start()
    try:
        await consumer.topics()  # fresh metadata
        parts = sorted(consumer.partitions_for_topic(topic) or ())
        return {p: await consumer.committed(TopicPartition(topic, p)) for p in parts}
    finally:
        await consumer.stop()


async def committed_reaches(server: TansuServer, group: str, topic: str, n: int) -> None:
    """Wait until the group has committed ``n`` offsets of ``topic`` in all (polled: the
    broker tells no one)."""
    total = 0
    for _ in range(200):
        total = sum(o or 0 for o in (await committed(server, group, topic)).values())
        if total >= n:
            return
        await anyio.sleep(0.05)
    raise TimeoutError(f"group {group} committed {total} offsets of {topic}, not {n}")


def json_reading(n: int) -> bytes:
    return msgspec.json.encode(Reading(n=n))


async def test_an_aiokafka_consumer_reads_the_key_partition_and_headers_of_an_out_bridge(
    server: TansuServer,
) -> None:
    consumer = AIOKafkaConsumer(
        "robot.readings",
        bootstrap_servers=server.bootstrap,
        group_id=None,
        auto_offset_reset="earliest",
    )
    await consumer.start()
    try:
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            b = bridge(fabric, "deck-out", spec(server, "robot.readings", format="json"), "out")
            await tg.start(b.run)
            with anyio.fail_after(10):
                await b.wait_connected()
            side = FabricSide(fabric)
            await side.publish(0, cycle=CYCLE, cause=CAUSE)
            for n in range(1, 50):
                await side.publish(n)
            records = []
            with anyio.fail_after(20):
                async for record in consumer:
                    records.append(record)
                    if len(records) == 50:
                        break
            await until(lambda: b.stats.sent == 50)
            tg.cancel_scope.cancel()
    finally:
        await consumer.stop()
    assert [json.loads(r.value) for r in records] == [{"n": n, "note": ""} for n in range(50)]
    assert {r.key for r in records} == {b"deck-out"}  # the bridge's name: one partition
    assert len({r.partition for r in records}) == 1
    offsets = [r.offset for r in records]
    assert offsets == list(range(offsets[0], offsets[0] + 50))  # nothing between them
    first = frame_of(records[0]).headers
    assert first["rap-cycle"] == CYCLE.hex()
    assert first["rap-cause"] == CAUSE.hex()
    assert first["rap-type"] == "test.Reading/1"
    assert first["rap-source"] == "contract-test"
    assert "rap-cycle" not in frame_of(records[1]).headers


async def test_an_in_bridge_commits_what_it_took_and_resumes_there_after_its_own_restart(
    server: TansuServer,
) -> None:
    """The group's committed offsets (read with aiokafka) follow what the bridge took; a
    bridge started again under the same group takes what was produced while it was
    away, and nothing twice."""
    topic, group = "ops.readings", "ops-readers"
    s = spec(server, topic, format="json", group=group)
    assert group_of(s, "ops-in") == group
    await produce(server, topic, [(json_reading(n), []) for n in range(10)])
    async with MemoryFabric() as fabric, anyio.create_task_group() as outer:
        side = FabricSide(fabric)
        await outer.start(side.record)
        async with anyio.create_task_group() as tg:
            first = bridge(fabric, "ops-in", s, "in")
            await tg.start(first.run)
            await side.wait_for(10)
            await committed_reaches(server, group, topic, 10)  # after they were taken
            tg.cancel_scope.cancel()  # the bridge stops (and leaves its group)
        await produce(server, topic, [(json_reading(n), []) for n in range(10, 15)])
        async with anyio.create_task_group() as tg:
            second = bridge(fabric, "ops-in", s, "in")
            await tg.start(second.run)
            await side.wait_for(15)
            await until(lambda: second.stats.published == 5)
            tg.cancel_scope.cancel()
        outer.cancel_scope.cancel()
    assert side.readings() == list(range(15))  # the first ten were not taken again
    assert (first.stats.received, second.stats.received) == (10, 5)
    await committed_reaches(server, group, topic, 15)


async def test_records_an_in_bridge_cannot_take_are_rejected_and_passed_over(
    server: TansuServer,
) -> None:
    topic = "bad.readings"
    records: list[tuple[bytes | None, Any]] = [
        (json_reading(0), []),
        (json_reading(1), [("rap-cycle", b"\xff\xfe")]),  # a header that is not UTF-8
        (None, []),  # a tombstone: no value
        (b'{"n": "one"}', []),  # not a Reading
        (json_reading(2), [("rap-type", b"rap.Pose2D/1")]),  # another message type
        (json_reading(3), [("rap-cause", CAUSE.hex().encode())]),
    ]
    await produce(server, topic, records)
    async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
        side = FabricSide(fabric)
        await tg.start(side.record)
        b = bridge(fabric, "bad-in", spec(server, topic, format="json"), "in")
        await tg.start(b.run)
        await side.wait_for(2)
        await until(lambda: b.stats.rejected == 4)
        await committed_reaches(server, group_of(b.spec, "bad-in"), topic, len(records))
        tg.cancel_scope.cancel()
    assert side.readings() == [0, 3]
    assert side.got[1].cause == CAUSE
    reasons = " | ".join(b.stats.rejections.by_reason)
    assert "is not UTF-N" in reasons  # (digits in reasons are counted as N)
    assert "expected type test.Reading/N" in reasons


async def test_a_message_over_the_record_limit_is_rejected_not_produced(
    server: TansuServer,
) -> None:
    consumer = AIOKafkaConsumer(
        "big.readings", bootstrap_servers=server.bootstrap, auto_offset_reset="earliest"
    )
    await consumer.start()
    try:
        async with MemoryFabric() as fabric, anyio.create_task_group() as tg:
            s = spec(server, "big.readings", format="json", max_frame=1000)
            b = bridge(fabric, "big-out", s, "out")
            await tg.start(b.run)
            with anyio.fail_after(10):
                await b.wait_connected()
            side = FabricSide(fabric)
            await side.publish(0)
            await fabric.publish(
                KEY, side.sealer.seal_out(KEY, Reading(n=1, note="x" * (1000 + HEADROOM)))
            )
            await side.publish(2)
            got = []
            with anyio.fail_after(20):
                async for record in consumer:
                    got.append(json.loads(record.value)["n"])
                    if len(got) == 2:
                        break
            await until(lambda: b.stats.rejected == 1)
            assert b.connected  # it never lost the connection over it
            tg.cancel_scope.cancel()
    finally:
        await consumer.stop()
    assert got == [0, 2]
    assert "over the limit" in " | ".join(b.stats.rejections.by_reason)
    assert (b.stats.disconnects, b.stats.sent) == (0, 2)  # the refused one is not "sent"


@pytest.mark.parametrize(
    ("kw", "says"),
    [
        ({"address": "robot/scan"}, "is not a Kafka topic name"),
        ({"address": ".."}, "is not a Kafka topic name"),
        ({"address": "x" * 250}, "is not a Kafka topic name"),
        ({"address": ""}, "needs an address"),
        ({"url": "kafka+ssl://127.0.0.1:9093"}, "its scheme must be kafka://"),
        ({"username": "robot"}, "takes no credentials or TLS settings"),
        ({"url": "kafka://127.0.0.1:9092", "maxlen": 10}, "maxlen applies to redis-stream only"),
    ],
)
def test_the_spec_says_what_a_kafka_bridge_needs(kw: dict[str, Any], says: str) -> None:
    fields: dict[str, Any] = {"url": "kafka://127.0.0.1:9092", "address": "robot.scan"}
    fields.update(kw)
    with pytest.raises(ValueError, match=says.replace("+", r"\+").replace(".", r"\.")):
        BridgeSpec(protocol="kafka", **fields)


def test_a_kafka_spec_takes_a_group_and_the_default_port() -> None:
    s = BridgeSpec(protocol="kafka", url="kafka://broker", address="robot.scan", group="ops")
    assert (s.host, s.port, s.group, s.where) == (
        "broker",
        9092,
        "ops",
        "kafka://broker/robot.scan",
    )
    assert group_of(BridgeSpec(protocol="kafka", url="kafka://b", address="t"), "deck") == (
        "rap-bridge-deck"
    )

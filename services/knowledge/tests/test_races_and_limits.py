"""Races and limits found by review: each test failed before its fix."""

from __future__ import annotations

import time
from contextlib import AsyncExitStack
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from knowledge.adapters.memory import MemoryStore
from knowledge.adapters.sqlite_store import SqliteStore
from knowledge.app import open_service
from knowledge.config import HistoryRule, KnowledgeConfig
from knowledge.core import Retention
from rap_schemas import (
    Envelope,
    KbPut,
    KbRecord,
    KbReply,
    LidarMask,
    Rejection,
    keys,
    pack_flags,
)
from rap_schemas.knowledge import EPOCH_MS
from rap_sdk import MemoryBus, MemoryFabric, Sealer
from rap_sdk.knowledge import HybridClock, KnowledgeClient, KnowledgeError

from services.knowledge.tests.deployment import deployment

pytestmark = pytest.mark.anyio


def record(
    key: str, version: int, value: Any, *, ts: int | None = None, writer: str = "w"
) -> KbRecord:
    return KbRecord(
        key=key,
        version=version,
        ts=time.time_ns() if ts is None else ts,
        writer=writer,
        value=msgspec.Raw(msgspec.msgpack.encode(value)),
    )


def far_future_version() -> int:
    return ((time.time_ns() // 1_000_000 - EPOCH_MS + 3_600_000) << 20) | 1


async def test_out_of_range_and_far_future_versions_are_refused() -> None:
    async with deployment("memory") as d:
        w = await d.client("w")
        key = keys.kb("t", "k")
        for rec in (
            record("k", 2**63, 1),
            record("k", far_future_version(), 1),
            record("k", 5, 1, ts=-1),
        ):
            payload, _ = w.sealer.seal_message(key, rec)
            await w.fabric.publish(key, payload)  # on the stream: rejected, counted
            (reply,) = await w.fabric.query(key, msgspec.msgpack.encode(KbPut(record=rec)))
            got = msgspec.msgpack.decode(reply.payload, type=KbReply)
            assert (got.ok, got.code) == (False, "bad-request")
        assert d.service is not None
        with anyio.fail_after(5):
            while d.service.stats.stream_rejected < 3:
                await anyio.wait_all_tasks_blocked()
        assert d.service.stats.stream_rejected == 3
        assert await w.write("k", "fine", durable=True) > 0  # still serving


@pytest.mark.parametrize("kind", ["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)])
async def test_a_replica_applies_the_services_bounds(kind: str) -> None:
    """A record the service refuses (version 2**63-1, an hour ahead, too large) was
    adopted for good by every replica: the key froze at the forged value."""
    async with deployment(kind) as d:
        reader, writer = await d.client("reader"), await d.client("writer")
        await writer.write("scan", "real 1", durable=True)
        assert await reader.read("scan") == "real 1"  # replicated now
        key = keys.kb("t", "scan")
        assert d.service is not None
        forger = Sealer("forger")
        fabric = d.service.fabric  # the reader is linked to the service's session
        for rec in (
            record("scan", 2**63 - 1, "forged"),
            record("scan", far_future_version(), "forged"),
            record("scan", writer.clock.next(), "x" * (2 << 20)),  # over the 1 MiB limit
            record("other", 7, "forged"),  # a record for another key on this stream
        ):
            payload, _ = forger.seal_message(key, rec)
            await fabric.publish(key, payload)
        with anyio.fail_after(5):
            while reader.rejections.total < 4:
                await anyio.wait_all_tasks_blocked()
        assert await reader.read("scan") == "real 1"
        v = await writer.write("scan", "real 2")
        assert await reader.read("scan", min_version=v) == "real 2"  # not frozen
        assert sum(reader.rejections.by_reason.values()) == 4


def test_a_clock_does_not_follow_a_version_from_the_far_future() -> None:
    clock = HybridClock("w")
    before = clock.next()
    clock.observe(far_future_version())
    after = clock.next()
    assert before < after < before + (10_000 << 20)  # still near now


async def test_a_moved_write_keeps_its_writer_tag() -> None:
    async with deployment("memory") as d:
        fast, slow = await d.client("fast"), await d.client("slow")
        fast.clock.observe(fast.clock.next() + (1000 << 20))  # 1 s ahead
        await fast.write("k", "fast 1", durable=True)
        moved = await slow.write("k", "slow", durable=True)  # moved past fast's version
        assert moved & 0xFF == slow.clock.tag
        await fast.write("k", "fast 2", durable=True)  # must not collide with 'slow'
        assert await slow.read("k") == "fast 2"


@pytest.mark.parametrize("backend", ["memory", "sqlite"])  # sqlite yields between calls
async def test_concurrent_durable_writes_each_become_the_latest(
    backend: str, tmp_path: Path
) -> None:
    config = KnowledgeConfig(
        system="t",
        backend=backend,  # type: ignore[arg-type]
        sqlite_path=str(tmp_path / "kb.db"),
    )
    async with deployment("memory", config) as d:
        a, b = await d.client("a"), await d.client("b")
        versions: list[int] = []

        async def writer(kb: KnowledgeClient, name: str) -> None:
            for i in range(20):
                version = await kb.write("k", f"{name}{i}", durable=True)
                versions.append(version)

        async with anyio.create_task_group() as tg:
            tg.start_soon(writer, a, "a")
            tg.start_soon(writer, b, "b")
        assert len(set(versions)) == 40  # no write was told another write's version
        hist = await a.history("k")
        assert len(hist) == 40
        assert max(versions) == (await a.read_record("k")).version  # type: ignore[union-attr]


async def test_a_resent_durable_write_is_stored_once() -> None:
    async with deployment("memory") as d:
        w = await d.client("w")
        rec = record("k", w.clock.next(), "once")
        put = msgspec.msgpack.encode(KbPut(record=rec))
        for _ in range(3):  # a client retrying after a lost reply
            (reply,) = await w.fabric.query(keys.kb("t", "k"), put)
            assert msgspec.msgpack.decode(reply.payload, type=KbReply).version == rec.version
        assert len(await w.history("k")) == 1


@pytest.mark.zenoh
async def test_concurrent_first_reads_both_see_the_value() -> None:
    async with deployment("zenoh") as d:  # a real round trip: the two reads interleave
        await (await d.client("w")).write("k", "value", durable=True)
        reader = await d.client("r")
        got: list[Any] = []

        async def read() -> None:
            got.append(await reader.read("k", default="<missing>"))

        async with anyio.create_task_group() as tg:
            tg.start_soon(read)
            tg.start_soon(read)
        assert got == ["value", "value"]


async def test_replicas_made_before_the_service_existed_catch_up() -> None:
    bus, config = MemoryBus(), KnowledgeConfig(system="t")
    store = MemoryStore(Retention(config.history))
    await store.apply(record("k", HybridClock("x").next(), "stored"))
    async with AsyncExitStack() as stack:
        rf = await stack.enter_async_context(MemoryFabric(bus=bus))
        sf = await stack.enter_async_context(MemoryFabric(bus=bus))
        reader = await stack.enter_async_context(KnowledgeClient(fabric=rf, system="t", writer="r"))
        assert await reader.read("k", default=None) is None  # no service yet
        async with open_service(config, fabric=sf, store=store):
            with anyio.fail_after(5):
                while reader.known_version("k") == 0:
                    await anyio.wait_all_tasks_blocked()
            assert await reader.read("k") == "stored"
            assert reader.catch_ups == 1


async def test_concurrent_model_puts_get_distinct_versions(tmp_path: Path) -> None:
    config = KnowledgeConfig(system="t", backend="sqlite", sqlite_path=str(tmp_path / "m.db"))
    async with deployment("memory", config) as d:  # sqlite: each call yields (thread hop)
        a, b = await d.client("a"), await d.client("b")
        metas: list[Any] = []

        async def put(kb: KnowledgeClient, data: bytes) -> None:
            metas.append(await kb.put_model("m", data))

        async with anyio.create_task_group() as tg:
            tg.start_soon(put, a, b"from a")
            tg.start_soon(put, b, b"from b")
        assert sorted(m.version for m in metas) == [1, 2]
        for m in metas:
            assert (await a.get_model("m", m.version))[0].sha256 == m.sha256


@pytest.mark.parametrize("kind", ["memory", "sqlite"])
async def test_history_keeps_the_newest_by_time_whatever_the_arrival_order(
    kind: str, tmp_path: Path
) -> None:
    retention = Retention([HistoryRule(max_count=2)])
    store: Any = (
        MemoryStore(retention)
        if kind == "memory"
        else await SqliteStore(str(tmp_path / "h.db"), retention).open()
    )
    try:
        for v, ts in ((3, 3000), (2, 2000), (1, 1000), (1, 1000)):  # late, and a repeat
            await store.apply(record("k", v, v, ts=ts))
        kept = await store.history("k", since=None, until=None, limit=10)
        assert [(r.version, r.ts) for r in kept] == [(2, 2000), (3, 3000)]
        latest = await store.get("k")
        assert latest.version == 3
    finally:
        await store.aclose()


async def test_a_request_sent_to_another_key_is_refused() -> None:
    async with deployment("memory") as d:
        w = await d.client("w")
        put = msgspec.msgpack.encode(KbPut(record=record("a", w.clock.next(), 1)))
        (reply,) = await w.fabric.query(keys.kb("t", "b"), put)
        got = msgspec.msgpack.decode(reply.payload, type=KbReply)
        assert (got.ok, got.code) == (False, "bad-request")
        assert "was sent to" in got.error
        with pytest.raises(KnowledgeError, match="has no value"):
            await w.read("a")


async def test_a_value_nested_past_the_limit_is_not_stored_and_the_refusal_is_published() -> None:
    """The service stored values nested hundreds of levels deep, which readers with a deeper stack
    could not decode; now it refuses past 32 levels, and says so on its log key."""
    async with deployment("memory") as d:
        w = await d.client("w")
        assert d.service is not None
        log_sub = w.fabric.subscribe(keys.log("t", "knowledge"))
        deep = record("k", w.clock.next(), None)
        deep = msgspec.structs.replace(deep, value=msgspec.Raw(b"\x91" * 200 + b"\xc0"))
        (reply,) = await w.fabric.query(
            keys.kb("t", "k"), msgspec.msgpack.encode(KbPut(record=deep))
        )
        got = msgspec.msgpack.decode(reply.payload, type=KbReply)
        assert (got.ok, got.code) == (False, "bad-request")
        assert "more than 32 levels" in got.error
        payload, _ = w.sealer.seal_message(keys.kb("t", "k"), deep)
        await w.fabric.publish(keys.kb("t", "k"), payload)  # on the stream
        with anyio.fail_after(5):
            rec = msgspec.msgpack.decode((await log_sub.get()).payload, type=Envelope)
        rejection = msgspec.msgpack.decode(rec.body, type=Rejection)
        assert rejection.node == "knowledge"
        assert "more than 32 levels" in rejection.reason
        assert await w.read("k", default=None) is None


@pytest.mark.parametrize("kind", ["memory", pytest.param("zenoh", marks=pytest.mark.zenoh)])
async def test_a_record_of_the_wrong_type_is_refused_by_a_replica_that_reads_the_key(
    kind: str,
) -> None:
    """make fuzz: a planned mask whose angle was out of range failed the analysis on every
    scan, and only the planner (which acts after the analysis) would have written a good
    one: the loop never closed again. A replica now refuses a value that is not what it
    reads the key as, and keeps the last good one."""
    async with deployment(kind) as d:
        reader, writer = await d.client("reader"), await d.client("writer")
        good = LidarMask(angle_min=0.0, angle_increment=0.1, occluded=pack_flags([True, False]))
        await writer.write("mask", good, durable=True)
        assert await reader.read("mask", LidarMask) == good
        assert d.service is not None
        fabric, forger = d.service.fabric, Sealer("forger")
        key = keys.kb("t", "mask")
        bad = {"angle_min": 99.0, "angle_increment": 0.1, "occluded": pack_flags([True])}
        for value in (bad, "not a mask", [1, 2, 3]):
            payload, _ = forger.seal_message(key, record("mask", writer.clock.next(), value))
            await fabric.publish(key, payload)
        with anyio.fail_after(5):
            while reader.rejections.total < 3:
                await anyio.wait_all_tasks_blocked()
        assert await reader.read("mask", LidarMask) == good
        newer = LidarMask(angle_min=0.5, angle_increment=0.1, occluded=pack_flags([False]))
        v = await writer.write("mask", newer)
        assert await reader.read("mask", LidarMask, min_version=v) == newer

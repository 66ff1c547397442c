"""One behaviour suite for every Store: memory, sqlite (a file of the test's own), redis
(a real redis-server the test starts on a free port), memcached (a real memcached the
test starts on a free port, with a memory store for history and models) and kafka (a
SQLite store with its outbox, sent to a real Tansu broker the test starts on a free port;
after each test the outbox must have drained to the broker)."""

from __future__ import annotations

import time
from collections.abc import AsyncIterator
from pathlib import Path
from typing import Any

import anyio
import msgspec
import pytest
from knowledge.adapters.kafka_store import KafkaStore
from knowledge.adapters.memcached_store import MemcachedStore
from knowledge.adapters.memory import MemoryStore
from knowledge.adapters.redis_store import RedisStore
from knowledge.adapters.sqlite_store import SqliteStore
from knowledge.config import HistoryRule
from knowledge.core import Retention, sha256
from knowledge.errors import Conflict
from rap_schemas import KbRecord, ModelMeta
from rap_sdk.testing import TansuServer

from services.knowledge.tests.servers import memcached_server, redis_server

pytestmark = pytest.mark.anyio

RULES = [
    HistoryRule(pattern="short/**", max_count=3),
    HistoryRule(pattern="aged/**", max_count=None, max_age_s=60.0),
    HistoryRule(pattern="**", max_count=100),
]
KINDS = [
    "memory",
    "sqlite",
    pytest.param("redis", marks=pytest.mark.redis),
    pytest.param("memcached", marks=pytest.mark.memcached),
    pytest.param("kafka", marks=pytest.mark.kafka),
]


async def make_store(kind: str, tmp_path: Path, stack: Any) -> Any:
    retention = Retention(RULES)
    if kind == "memory":
        return MemoryStore(retention)
    if kind == "sqlite":
        store = await SqliteStore(str(tmp_path / "kb.sqlite3"), retention).open()
    elif kind == "redis":
        server = await stack.enter_async_context(redis_server(tmp_path))
        store = await RedisStore(server.url, "t", retention).open()
    elif kind == "kafka":
        broker = TansuServer()
        await broker.start()
        stack.push_async_callback(broker.stop)
        inner = await SqliteStore(str(tmp_path / "kb.sqlite3"), retention, outbox=True).open()
        return await stack.enter_async_context(
            KafkaStore(f"kafka://{broker.bootstrap}", "t", inner)
        )
    else:
        cache = await stack.enter_async_context(memcached_server())
        store = await MemcachedStore(cache.url, "t", MemoryStore(retention)).open()
    stack.push_async_callback(store.aclose)
    return store


@pytest.fixture(params=KINDS)
async def store(request: pytest.FixtureRequest, tmp_path: Path) -> AsyncIterator[Any]:
    from contextlib import AsyncExitStack

    async with AsyncExitStack() as stack:
        store = await make_store(request.param, tmp_path, stack)
        yield store
        if isinstance(store, KafkaStore):  # every record stored reached the broker
            with anyio.fail_after(20):
                await store.wait_sent()


def rec(
    key: str,
    version: int,
    value: Any = None,
    *,
    writer: str = "w",
    ts: int = 0,
    deleted: bool = False,
) -> KbRecord:
    return KbRecord(
        key=key,
        version=version,
        ts=ts or time.time_ns(),
        writer=writer,
        value=msgspec.Raw(msgspec.msgpack.encode(value)),
        deleted=deleted,
    )


def val(r: KbRecord | None) -> Any:
    assert r is not None
    return msgspec.msgpack.decode(r.value)


async def test_the_highest_version_is_the_latest(store: Any) -> None:
    assert await store.get("a") is None
    assert (await store.apply(rec("a", 10, "x"))).latest
    applied = await store.apply(rec("a", 5, "older", writer="w2"))  # concurrent, older
    assert (applied.version, applied.latest) == (10, False)
    assert val(await store.get("a")) == "x"
    assert (await store.apply(rec("a", 20, "y"))).version == 20
    assert val(await store.get("a")) == "y"
    assert [r.version for r in await store.history("a", since=None, until=None, limit=10)] == [
        10,
        5,
        20,
    ]


async def test_reapplying_the_latest_record_is_a_no_op(store: Any) -> None:
    r = rec("a", 7, 1)
    await store.apply(r)
    again = await store.apply(r)
    assert again.duplicate
    assert len(await store.history("a", since=None, until=None, limit=10)) == 1


async def test_compare_and_set(store: Any) -> None:
    assert (await store.apply(rec("c", 3, "first"), expect=0)).version == 3
    with pytest.raises(Conflict, match="expected version 0, but the current version is 3"):
        await store.apply(rec("c", 4, "lost"), expect=0)
    with pytest.raises(Conflict) as exc:
        await store.apply(rec("c", 4, "lost"), expect=2)
    assert exc.value.current == 3
    assert (await store.apply(rec("c", 4, "won"), expect=3)).version == 4
    assert val(await store.get("c")) == "won"


async def test_deletion_is_a_versioned_tombstone(store: Any) -> None:
    await store.apply(rec("d/x", 1, "v"))
    await store.apply(rec("d/y", 1, "v"))
    await store.apply(rec("d/x", 2, None, deleted=True))
    got = await store.get("d/x")
    assert got is not None
    assert got.deleted
    assert await store.keys("d/**") == ["d/y"]
    assert (await store.apply(rec("d/x", 3, "again"), expect=0)).version == 3  # gone = 0
    assert await store.keys("d/*") == ["d/x", "d/y"]


async def test_history_by_time_and_limit(store: Any) -> None:
    base = time.time_ns()
    for i in range(10):
        await store.apply(rec("h", i + 1, i, ts=base + i * 1000))
    window = await store.history("h", since=base + 3000, until=base + 7000, limit=100)
    assert [val(r) for r in window] == [3, 4, 5, 6]
    assert [val(r) for r in await store.history("h", since=None, until=None, limit=3)] == [7, 8, 9]


async def test_history_is_bounded_by_the_first_matching_rule(store: Any) -> None:
    for i in range(10):
        await store.apply(rec("short/k", i + 1, i))
    kept = await store.history("short/k", since=None, until=None, limit=100)
    assert [val(r) for r in kept] == [7, 8, 9]
    old = time.time_ns() - 120 * 10**9  # two minutes ago, rule keeps one minute
    await store.apply(rec("aged/k", 1, "old", ts=old))
    await store.apply(rec("aged/k", 2, "new"))
    kept = await store.history("aged/k", since=None, until=None, limit=100)
    assert "new" in [val(r) for r in kept]
    if not isinstance(store, RedisStore):  # redis trims by insertion time, not by ts
        assert [val(r) for r in kept] == ["new"]


async def test_keys_by_pattern(store: Any) -> None:
    for k in ("robot/tb1/pose", "robot/tb2/pose", "robot/tb1/scan", "mask"):
        await store.apply(rec(k, 1, 0))
    assert await store.keys("robot/*/pose") == ["robot/tb1/pose", "robot/tb2/pose"]
    assert await store.keys("**") == sorted(
        ["mask", "robot/tb1/pose", "robot/tb1/scan", "robot/tb2/pose"]
    )


async def test_models_versions_and_pins(store: Any) -> None:
    for v, data in ((1, b"a" * 10), (2, b"b" * 20)):
        meta = ModelMeta(
            name="det",
            version=v,
            sha256=sha256(data),
            size=len(data),
            created=time.time_ns(),
            tags={"v": str(v)},
        )
        await store.put_model(meta, data)
    assert [m.version for m in await store.list_models("det")] == [1, 2]
    got = await store.get_model("det", 2)
    assert got is not None
    assert got[1] == b"b" * 20
    assert got[0].tags == {"v": "2"}
    assert await store.get_model("det", 3) is None
    assert await store.get_pin("det") is None
    await store.set_pin("det", 1)
    assert await store.get_pin("det") == 1
    await store.set_pin("det", None)
    assert await store.get_pin("det") is None


@pytest.mark.parametrize("kind", ["sqlite", pytest.param("redis", marks=pytest.mark.redis)])
async def test_durable_stores_keep_data_across_a_reopen(kind: str, tmp_path: Path) -> None:
    from contextlib import AsyncExitStack

    async with AsyncExitStack() as stack:
        if kind == "sqlite":
            first = await SqliteStore(str(tmp_path / "kb.sqlite3"), Retention(RULES)).open()
            await first.apply(rec("p", 1, "kept"))
            await first.aclose()
            second = await SqliteStore(str(tmp_path / "kb.sqlite3"), Retention(RULES)).open()
        else:
            server = await stack.enter_async_context(redis_server(tmp_path))
            first = await RedisStore(server.url, "t", Retention(RULES)).open()
            await first.apply(rec("p", 1, "kept"))
            await server.restart()  # the server restarts under a live client
            await first.apply(rec("p", 2, "after restart"))  # reconnects with backoff
            await first.aclose()
            second = await RedisStore(server.url, "t", Retention(RULES)).open()
        stack.push_async_callback(second.aclose)
        assert val(await second.get("p")) == ("kept" if kind == "sqlite" else "after restart")
        assert len(await second.history("p", since=None, until=None, limit=10)) == (
            1 if kind == "sqlite" else 2
        )

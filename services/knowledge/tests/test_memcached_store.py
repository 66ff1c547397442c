"""The memcached store against a real memcached of the test's own: what memcached cannot
promise (a restart or an eviction loses items, an item has a size limit, keys have a
syntax) is made up for by the inner store; racing writers never lower a version."""

from __future__ import annotations

import random
import time
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from pathlib import Path
from typing import Any

import aiomcache
import anyio
import msgspec
import pytest
from anyio.abc import SocketAttribute, SocketStream
from knowledge.adapters.memcached_store import (
    MARKER,
    RECORD,
    MemcachedStore,
    _Client,
    item_key,
    parse_url,
)
from knowledge.adapters.memory import MemoryStore
from knowledge.adapters.sqlite_store import SqliteStore
from knowledge.app import open_service
from knowledge.config import HistoryRule, KnowledgeConfig
from knowledge.core import Retention
from knowledge.errors import BadRequest, Conflict, StoreUnavailable
from rap_schemas import KbRecord
from rap_sdk import MemoryBus, MemoryFabric
from rap_sdk.knowledge import KnowledgeClient

from services.knowledge.tests.servers import MemcachedServer, memcached_server

pytestmark = [pytest.mark.anyio, pytest.mark.memcached]

PREFIX = "rap:t:kb:"


def rec(key: str, version: int, value: Any, *, writer: str = "w") -> KbRecord:
    return KbRecord(
        key=key,
        version=version,
        ts=time.time_ns(),
        writer=writer,
        value=msgspec.Raw(msgspec.msgpack.encode(value)),
    )


def val(r: KbRecord | None) -> Any:
    assert r is not None
    return msgspec.msgpack.decode(r.value)


def retention() -> Retention:
    return Retention([HistoryRule(pattern="**", max_count=100)])


@asynccontextmanager
async def raw_client(server: MemcachedServer) -> AsyncIterator[aiomcache.Client]:
    """memcached as any other client sees it."""
    client = aiomcache.Client("127.0.0.1", server.port)
    try:
        yield client
    finally:
        await client.close()


async def test_a_restarted_memcached_is_refilled_from_the_inner_store(tmp_path: Path) -> None:
    async with memcached_server() as server, raw_client(server) as mc:
        inner = await SqliteStore(str(tmp_path / "kb.sqlite3"), retention()).open()
        store = await MemcachedStore(server.url, "t", inner).open()
        try:
            await store.apply(rec("a", 1, "a1"))
            await store.apply(rec("a", 2, "a2"))
            await store.apply(rec("b", 1, "b1"))
            assert (await mc.get(item_key(PREFIX, "a")) or b"")[:1] == RECORD

            await server.restart()  # killed: every item is gone
            assert await mc.get(item_key(PREFIX, "a")) is None

            assert val(await store.get("a")) == "a2"  # from SQLite, and put back
            assert await mc.get(item_key(PREFIX, "a")) is not None
            assert val(await store.get("b")) == "b1"
            applied = await store.apply(rec("a", 3, "a3"))  # writes go on
            assert (applied.version, applied.latest) == (3, True)
            older = await store.apply(rec("a", 2, "late", writer="w2"))
            assert (older.version, older.latest) == (3, False)
            assert val(await store.get("a")) == "a3"
            history = await store.history("a", since=None, until=None, limit=10)
            assert [r.version for r in history] == [1, 2, 3, 2]
            assert await store.keys("**") == ["a", "b"]

            await server.restart()  # a write first after a restart: compare-and-set
            with pytest.raises(Conflict) as exc:  # against the version SQLite keeps
                await store.apply(rec("a", 9, "lost"), expect=2)
            assert exc.value.current == 3
            assert (await store.apply(rec("a", 4, "a4"), expect=3)).latest
            assert val(await store.get("a")) == "a4"
        finally:
            await store.aclose()


async def test_an_evicted_item_is_served_from_the_inner_store_and_put_back() -> None:
    async with memcached_server() as server, raw_client(server) as mc:
        store = await MemcachedStore(server.url, "t", MemoryStore(retention())).open()
        try:
            await store.apply(rec("k", 5, "v5"))
            assert await mc.delete(item_key(PREFIX, "k"))  # as an eviction would
            assert val(await store.get("k")) == "v5"
            raw = await mc.get(item_key(PREFIX, "k"))
            assert raw is not None
            assert raw[:1] == RECORD
            # a write that finds no item compares with the inner store's version
            assert await mc.delete(item_key(PREFIX, "k"))
            assert not (await store.apply(rec("k", 4, "older", writer="w2"))).latest
            assert val(await store.get("k")) == "v5"
        finally:
            await store.aclose()


async def test_racing_writers_never_lower_a_version() -> None:
    """Two stores (two processes, each its own inner store) and many tasks write one key
    with shuffled versions: memcached ends at the highest, as both stores read it."""
    async with memcached_server() as server:
        one = await MemcachedStore(server.url, "t", MemoryStore(retention())).open()
        two = await MemcachedStore(server.url, "t", MemoryStore(retention())).open()
        try:
            versions = list(range(1, 201))
            random.Random(7).shuffle(versions)
            latest: list[int] = []

            async def write(store: MemcachedStore, mine: list[int]) -> None:
                for v in mine:
                    applied = await store.apply(rec("race", v, v, writer=f"w{v}"))
                    if applied.latest:
                        latest.append(v)

            async with anyio.create_task_group() as tg:
                for i in range(8):
                    tg.start_soon(write, one if i % 2 else two, versions[i::8])
            assert val(await one.get("race")) == 200
            assert val(await two.get("race")) == 200
            assert 200 in latest
        finally:
            await one.aclose()
            await two.aclose()


async def test_values_larger_than_an_item_stay_in_the_inner_store() -> None:
    async with memcached_server() as server, raw_client(server) as mc:
        store = await MemcachedStore(server.url, "t", MemoryStore(retention())).open()
        try:
            assert store.item_size_max == 1 << 20
            big = "x" * (2 << 20)
            assert (await store.apply(rec("big", 2, big))).latest
            raw = await mc.get(item_key(PREFIX, "big"))
            assert raw is not None
            assert raw[:1] == MARKER  # the version only
            assert len(raw) < 200
            assert val(await store.get("big")) == big
            assert not (await store.apply(rec("big", 1, "older", writer="w2"))).latest
            assert val(await store.get("big")) == big
            assert (await store.apply(rec("big", 3, "small"))).latest
            raw = await mc.get(item_key(PREFIX, "big"))
            assert raw is not None
            assert raw[:1] == RECORD
            assert val(await store.get("big")) == "small"
        finally:
            await store.aclose()


async def test_keys_memcached_cannot_take_are_hashed() -> None:
    long_key = "/".join(["segment"] * 40)  # over 250 bytes
    odd_key = "robot/tb1/größe"  # not ASCII
    assert item_key(PREFIX, "robot/tb1/pose") == b"rap:t:kb:k:robot/tb1/pose"
    for key in (long_key, odd_key):
        mkey = item_key(PREFIX, key)
        assert mkey.startswith(b"rap:t:kb:h:")
        assert len(mkey) <= 250
    async with memcached_server() as server:
        store = await MemcachedStore(server.url, "t", MemoryStore(retention())).open()
        try:
            await store.apply(rec(long_key, 1, "long"))
            await store.apply(rec(odd_key, 1, "odd"))
            assert val(await store.get(long_key)) == "long"
            assert val(await store.get(odd_key)) == "odd"
        finally:
            await store.aclose()


async def test_a_memcached_that_is_down_is_a_clear_error() -> None:
    async with memcached_server() as server:
        store = await MemcachedStore(
            server.url, "t", MemoryStore(retention()), retry_for=0.3
        ).open()
        try:
            await store.apply(rec("k", 1, "v"))
            await server.stop()
            with pytest.raises(StoreUnavailable) as failed:
                await store.get("k")
            assert f"memcached store {server.url} unreachable" in str(failed.value)
            assert "apt-get install memcached" in str(failed.value)
            with pytest.raises(StoreUnavailable, match="not stored"):
                await store.apply(rec("k", 2, "v2"))
            # what only the inner store holds is still served
            assert [r.version for r in await store.history("k", since=None, until=None, limit=9)]
            assert await store.keys("**") == ["k"]
            await server.start()  # same port: the store reconnects by itself
            assert val(await store.get("k")) == "v"
            assert (await store.apply(rec("k", 2, "v2"))).latest
        finally:
            await store.aclose()
    with pytest.raises(StoreUnavailable, match=r"memcached store memcached://127\.0\.0\.1:"):
        await MemcachedStore(server.url, "t", MemoryStore(retention())).open(retry_for=0.2)


@pytest.mark.parametrize(
    "url",
    ["redis://127.0.0.1:6379/0", "memcached://", "memcached://h:99999", "memcached://h/0"],
)
def test_urls_other_than_memcached_host_port_are_refused(url: str) -> None:
    with pytest.raises(BadRequest, match=r"write memcached://HOST\[:PORT\]"):
        parse_url(url)
    assert parse_url("memcached://10.0.0.5") == ("10.0.0.5", 11211)
    assert parse_url("memcached://[::1]:11212") == ("::1", 11212)


async def test_the_service_on_memcached(tmp_path: Path) -> None:
    async with memcached_server() as server, raw_client(server) as mc:
        config = KnowledgeConfig(
            system="t",
            backend="memcached",
            memcached_url=server.url,
            sqlite_path=str(tmp_path / "kb.sqlite3"),
        )
        bus = MemoryBus()
        async with (
            MemoryFabric(bus=bus) as sf,
            open_service(config, fabric=sf),
            MemoryFabric(bus=bus) as cf,
            KnowledgeClient(fabric=cf, system="t", writer="w", timeout=5.0) as kb,
        ):
            await kb.write("robot/pose", {"x": 1}, durable=True)
            await kb.write("robot/pose", {"x": 2}, durable=True)
            assert await kb.read("robot/pose") == {"x": 2}
            assert await mc.get(b"rap:t:kb:k:robot/pose") is not None
            await server.restart()
            assert await kb.read("robot/pose") == {"x": 2}
            assert [v.value for v in await kb.history("robot/pose")] == [{"x": 1}, {"x": 2}]
            assert await kb.keys("robot/**") == ["robot/pose"]


async def test_writes_across_a_restart_under_load_never_hang_nor_go_back() -> None:
    """memcached is killed while writes are in flight (replies cut off midway): each
    write is stored or fails with StoreUnavailable, none hangs, and the latest value is
    the highest version stored."""
    async with memcached_server() as server:
        store = await MemcachedStore(
            server.url, "t", MemoryStore(retention()), retry_for=1.0
        ).open()
        stored: list[int] = []
        try:

            async def writer(first: int) -> None:
                for v in range(first, 400, 4):
                    try:
                        if (await store.apply(rec("load", v, v))).latest:
                            stored.append(v)
                    except StoreUnavailable:
                        pass

            with anyio.fail_after(30):
                async with anyio.create_task_group() as tg:
                    for first in range(1, 5):
                        tg.start_soon(writer, first)
                    await anyio.sleep(0.05)
                    await server.restart()
            assert stored
            assert val(await store.get("load")) == max(stored)
        finally:
            await store.aclose()


async def test_a_reply_cut_off_by_the_server_is_an_error_not_a_hang() -> None:
    """aiomcache alone would read the closed connection forever, blocking the event loop
    (aio-libs/aiomcache#502): here a server that dies after reading the command."""

    async def die(stream: SocketStream) -> None:
        await stream.receive()
        await stream.aclose()

    async with await anyio.create_tcp_listener(local_host="127.0.0.1") as listener:
        port = listener.extra(SocketAttribute.local_port)
        async with anyio.create_task_group() as tg:
            tg.start_soon(listener.serve, die)
            client = _Client("127.0.0.1", port, pool_size=1)
            try:
                with pytest.raises(ConnectionResetError, match="closed the connection"):
                    await client.add(b"k", b"v")
            finally:
                await client.close()
            tg.cancel_scope.cancel()

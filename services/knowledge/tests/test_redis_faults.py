"""Durable writes against a Redis that dies or stalls: a write reported failed is never
stored later, and a write reported stored is stored (the service retried Redis for 10 s
while its client gave up after 2 s, and then stored the write)."""

from __future__ import annotations

import time
from pathlib import Path

import anyio
import msgspec
import pytest
import redis.asyncio as aioredis
from knowledge.adapters.redis_store import RedisStore
from knowledge.app import open_service
from knowledge.config import HistoryRule, KnowledgeConfig
from knowledge.core import Retention
from knowledge.errors import OutcomeUnknown, StoreUnavailable
from rap_schemas import KbRecord
from rap_sdk import MemoryBus, MemoryFabric
from rap_sdk.knowledge import KnowledgeClient, KnowledgeError

from services.knowledge.tests.servers import redis_server

pytestmark = [pytest.mark.anyio, pytest.mark.redis]


def record(key: str, version: int, value: object) -> KbRecord:
    return KbRecord(
        key=key,
        version=version,
        ts=time.time_ns(),
        writer="w",
        value=msgspec.Raw(msgspec.msgpack.encode(value)),
    )


async def test_a_write_reported_failed_while_redis_is_down_is_never_stored(
    tmp_path: Path,
) -> None:
    async with redis_server(tmp_path) as server:
        config = KnowledgeConfig(system="t", backend="redis", redis_url=server.url)
        bus = MemoryBus()
        async with (
            MemoryFabric(bus=bus) as sf,
            open_service(config, fabric=sf),
            MemoryFabric(bus=bus) as cf,
            KnowledgeClient(fabric=cf, system="t", writer="w", timeout=1.0) as kb,
        ):
            await kb.write("k", "before", durable=True)
            await server.stop()
            with pytest.raises(KnowledgeError) as failed:
                await kb.write("k", "during", durable=True)
            assert failed.value.code == "unavailable"
            assert "not stored" in str(failed.value)
            await server.start()  # the service's old retries would now have stored it
            await anyio.sleep(2.0)  # longer than any backoff step: give a late store a chance
            kb.timeout = 5.0
            assert await kb.read("k") == "before"
            assert [v.value for v in await kb.history("k")] == ["before"]


@pytest.mark.parametrize("pause_ms", [200, 400, 600, 900])
async def test_what_a_stalled_redis_answers_agrees_with_what_it_stores(
    tmp_path: Path, pause_ms: int
) -> None:
    """Redis holds every write for ``pause_ms`` (CLIENT PAUSE): attempts time out after
    reaching it. Whatever apply() answers (stored, not stored, unknown) must be what the
    store holds once Redis runs again."""
    async with redis_server(tmp_path) as server:
        store = await RedisStore(server.url, "t", Retention([HistoryRule()])).open()
        admin = aioredis.Redis.from_url(server.url)
        try:
            await store.apply(record("k", 1 << 20, "old"))
            await admin.execute_command("CLIENT", "PAUSE", pause_ms, "WRITE")
            outcome = "stored"
            try:
                await store.apply(record("k", 2 << 20, "new"), deadline=time.monotonic() + 0.75)
            except OutcomeUnknown:
                outcome = "unknown"
            except StoreUnavailable:
                outcome = "not stored"
            await anyio.sleep(pause_ms / 1000 + 0.3)  # the pause is over, queued commands ran
            latest = await store.get("k")
            assert latest is not None
            stored = latest.version == 2 << 20
            if outcome == "stored":
                assert stored
            elif outcome == "not stored":
                assert not stored
        finally:
            await admin.aclose()
            await store.aclose()

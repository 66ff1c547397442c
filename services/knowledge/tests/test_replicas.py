"""Replicas that missed writes catch up from the service: on a gap in a writer's
sequence, and when the service comes back."""

from __future__ import annotations

import time
from contextlib import AsyncExitStack

import anyio
import msgspec
import pytest
from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from rap_schemas import KbRecord, keys
from rap_sdk import MemoryBus, MemoryFabric
from rap_sdk.envelope import Sealer
from rap_sdk.knowledge import KnowledgeClient

from services.knowledge.tests.deployment import deployment

pytestmark = pytest.mark.anyio


async def wait_for_version(kb: KnowledgeClient, key: str, version: int) -> None:
    with anyio.fail_after(5):
        await kb.read_record(key, min_version=version)


async def test_a_gap_in_the_stream_triggers_a_catch_up() -> None:
    async with deployment("memory") as d:
        reader = await d.client("reader")
        writer = await d.client("writer")
        await writer.write("k", "v1", durable=True)
        assert await reader.read("k") == "v1"  # replicated
        # v2 reaches the store only (its stream sample was lost) ...
        assert d.service is not None
        v2 = writer.clock.next()
        await d.service.store.apply(
            KbRecord(
                key="k",
                version=v2,
                ts=time.time_ns(),
                writer="lossy",
                value=msgspec.Raw(msgspec.msgpack.encode("v2")),
            )
        )
        # ... the lossy writer's seq 0 arrives, its seq 1 (v2) is lost, seq 2 arrives
        lossy, key = Sealer("lossy"), keys.kb("t", "k")
        for seq, send in ((0, True), (1, False), (2, True)):
            rec = KbRecord(
                key="k",
                version=v2 - 10 + seq,
                ts=time.time_ns(),
                writer="lossy",
                value=msgspec.Raw(msgspec.msgpack.encode(f"stale {seq}")),
            )
            payload, _ = lossy.seal_message(key, rec)
            if send:
                await writer.fabric.publish(key, payload)
        # only the gap can bring v2 in time: the read's own fallback would take 60 s
        with anyio.fail_after(5):
            await reader.read_record("k", min_version=v2, timeout=60)
        assert reader.opener.stats.missing == 1
        assert await reader.read("k") == "v2"


async def test_replicas_catch_up_when_the_service_comes_back() -> None:
    bus = MemoryBus()
    config = KnowledgeConfig(system="t")
    async with AsyncExitStack() as stack:
        rf = await stack.enter_async_context(MemoryFabric(bus=bus))
        wf = await stack.enter_async_context(MemoryFabric(bus=bus))
        store_holder = await stack.enter_async_context(MemoryFabric(bus=bus))
        from knowledge.adapters.memory import MemoryStore
        from knowledge.core import Retention

        store = MemoryStore(Retention(config.history))
        reader = await stack.enter_async_context(
            KnowledgeClient(fabric=rf, system="t", writer="reader")
        )
        writer = await stack.enter_async_context(
            KnowledgeClient(fabric=wf, system="t", writer="writer")
        )
        async with open_service(config, fabric=store_holder, store=store):
            await writer.write("k", "before", durable=True)
            assert await reader.read("k") == "before"
        # the service is down; a write reaches the store while the reader hears nothing
        import time

        import msgspec
        from rap_schemas import KbRecord as Rec

        late = Rec(
            key="k",
            version=writer.clock.next(),
            ts=time.time_ns(),
            writer="writer",
            value=msgspec.Raw(msgspec.msgpack.encode("while away")),
        )
        await store.apply(late)
        async with open_service(config, fabric=store_holder, store=store):
            await wait_for_version(reader, "k", late.version)
            assert await reader.read("k") == "while away"
            assert reader.catch_ups == 1

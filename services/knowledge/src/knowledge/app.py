"""Wiring: a store for the configured backend, and the service on a fabric."""

from __future__ import annotations

import contextlib
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio
from rap_sdk import Fabric
from rap_sdk.identity import Verifier
from rap_sdk.knowledge import SERVICE_NODE
from rap_sdk.runtime import refuse_running

from .adapters.kafka_store import KafkaStore
from .adapters.memcached_store import MemcachedStore
from .adapters.memory import MemoryStore
from .adapters.redis_store import RedisStore
from .adapters.sqlite_store import SqliteStore
from .config import KnowledgeConfig
from .core import Retention
from .ports import Store
from .service import KnowledgeService

__all__ = ["open_service", "open_store"]


@asynccontextmanager
async def open_store(config: KnowledgeConfig) -> AsyncIterator[Store]:
    retention = Retention(config.history)
    if config.backend == "kafka":  # a task of its own sends the stream: a context
        inner = SqliteStore(config.sqlite_path, retention, outbox=True)
        stream = KafkaStore(config.kafka_url, config.system, inner, topic=config.kafka_topic)
        await inner.open()  # after the URL and topic were checked
        async with stream:
            yield stream
        return
    store: Store
    if config.backend == "memory":
        store = MemoryStore(retention)
    elif config.backend == "sqlite":
        store = await SqliteStore(config.sqlite_path, retention).open()
    elif config.backend == "memcached":
        # the latest values in memcached, everything else in SQLite; memcached is checked
        # first, so that no file is made for a service that cannot start
        inner = SqliteStore(config.sqlite_path, retention)
        cached = MemcachedStore(config.memcached_url, config.system, inner)
        await cached.open(retry_for=2.0)
        try:
            await inner.open()
        except BaseException:
            await cached.aclose()
            raise
        store = cached
    else:
        store = await RedisStore(config.redis_url, config.system, retention).open(retry_for=2.0)
    try:
        yield store
    finally:
        with anyio.CancelScope(shield=True):
            await store.aclose()


@asynccontextmanager
async def open_service(
    config: KnowledgeConfig,
    *,
    fabric: Fabric,
    store: Store | None = None,
    verifier: Verifier | None = None,
) -> AsyncIterator[KnowledgeService]:
    """Run the service on ``fabric`` for the duration of the block (ready on entry). A
    store that cannot be opened raises its :class:`~knowledge.errors.KnowledgeError`
    before anything runs. ``verifier``: who may use the model store is checked with it
    (default: the CA of ``RAP_CERTS`` when it is set)."""
    # before anything runs, so that the error comes plain (not in a task group's group)
    await refuse_running(fabric=fabric, system=config.system, names=[SERVICE_NODE])
    async with contextlib.AsyncExitStack() as stack:
        if store is None:
            store = await stack.enter_async_context(open_store(config))
        async with anyio.create_task_group() as tg:
            service = KnowledgeService(config, fabric=fabric, store=store, verifier=verifier)
            await tg.start(service.run)
            try:
                yield service
            finally:
                tg.cancel_scope.cancel()

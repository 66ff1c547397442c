"""Wiring: a store for the configured backend, and the service on a fabric."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

import anyio
from rap_sdk import Fabric

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
    store: Store
    if config.backend == "memory":
        store = MemoryStore(retention)
    elif config.backend == "sqlite":
        store = await SqliteStore(config.sqlite_path, retention).open()
    else:
        store = await RedisStore(config.redis_url, config.system, retention).open()
    try:
        yield store
    finally:
        with anyio.CancelScope(shield=True):
            await store.aclose()


@asynccontextmanager
async def open_service(
    config: KnowledgeConfig, *, fabric: Fabric, store: Store | None = None
) -> AsyncIterator[KnowledgeService]:
    """Run the service on ``fabric`` for the duration of the block (ready on entry)."""
    async with anyio.create_task_group() as tg:
        if store is None:
            store = await tg.start(_hold_store, config)
        service = KnowledgeService(config, fabric=fabric, store=store)
        await tg.start(service.run)
        try:
            yield service
        finally:
            tg.cancel_scope.cancel()


async def _hold_store(config: KnowledgeConfig, *, task_status: anyio.abc.TaskStatus[Store]) -> None:
    async with open_store(config) as store:
        task_status.started(store)
        await anyio.sleep_forever()

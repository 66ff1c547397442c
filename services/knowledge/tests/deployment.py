"""A knowledge service and clients on one fabric kind, for tests."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import AsyncExitStack, asynccontextmanager
from typing import Any

from knowledge.app import open_service
from knowledge.config import KnowledgeConfig
from knowledge.service import KnowledgeService
from rap_sdk import MemoryBus, MemoryFabric, ZenohConfig, ZenohFabric
from rap_sdk.knowledge import KnowledgeClient
from rap_sdk.testing import free_port


class Deployment:
    def __init__(self, kind: str, stack: AsyncExitStack) -> None:
        self.kind = kind
        self.stack = stack
        self.bus = MemoryBus()
        self.port = free_port()
        self.service: KnowledgeService | None = None

    def fabric(self, *, first: bool = False) -> Any:
        if self.kind == "memory":
            return MemoryFabric(bus=self.bus)
        if first:
            return ZenohFabric(ZenohConfig(listen=[f"tcp/127.0.0.1:{self.port}"]))
        return ZenohFabric(ZenohConfig(connect=[f"tcp/127.0.0.1:{self.port}"]))

    async def client(self, writer: str, **kw: Any) -> KnowledgeClient:
        fabric = await self.stack.enter_async_context(self.fabric())
        if self.kind == "zenoh":
            from rap_schemas import keys

            await fabric.wait_matched(keys.kb("t", "_keys"), queryable=True, timeout=10)
        return await self.stack.enter_async_context(
            KnowledgeClient(fabric=fabric, system="t", writer=writer, **kw)
        )


@asynccontextmanager
async def deployment(
    kind: str,
    config: KnowledgeConfig | None = None,
) -> AsyncIterator[Deployment]:
    async with AsyncExitStack() as stack:
        d = Deployment(kind, stack)
        fabric = await stack.enter_async_context(d.fabric(first=True))
        d.service = await stack.enter_async_context(
            open_service(config or KnowledgeConfig(system="t"), fabric=fabric)
        )
        yield d

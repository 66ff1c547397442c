"""A store in front of an inner one: what the front does not keep itself goes to ``_inner``.

The memcached store keeps the latest values and the Kafka store appends every record to a
topic; history, the key list and the model store stay in the inner (SQLite) store for
both. :class:`Layered` is that delegation, written once.
"""

from __future__ import annotations

from rap_schemas import KbRecord, ModelMeta

from ..ports import Store

__all__ = ["Layered"]


class Layered:
    """History, keys and models from ``_inner`` (set by the subclass)."""

    _inner: Store

    async def history(
        self, key: str, *, since: int | None, until: int | None, limit: int
    ) -> list[KbRecord]:
        return await self._inner.history(key, since=since, until=until, limit=limit)

    async def keys(self, pattern: str) -> list[str]:
        return await self._inner.keys(pattern)

    async def put_model(self, meta: ModelMeta, data: bytes) -> None:
        await self._inner.put_model(meta, data)

    async def get_model(self, name: str, version: int) -> tuple[ModelMeta, bytes] | None:
        return await self._inner.get_model(name, version)

    async def list_models(self, name: str) -> list[ModelMeta]:
        return await self._inner.list_models(name)

    async def set_pin(self, name: str, version: int | None) -> None:
        await self._inner.set_pin(name, version)

    async def get_pin(self, name: str) -> int | None:
        return await self._inner.get_pin(name)

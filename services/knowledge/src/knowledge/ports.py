"""What the knowledge service needs from a backend: one protocol, one contract suite
(memory, sqlite, redis, memcached)."""

from __future__ import annotations

from dataclasses import dataclass
from typing import Protocol

from rap_schemas import KbRecord, ModelMeta

__all__ = ["Applied", "Store"]


@dataclass(frozen=True, slots=True)
class Applied:
    version: int
    """The key's latest version after the write."""
    latest: bool
    """Whether this record became the latest (a concurrent older one only joins history)."""
    duplicate: bool = False


class Store(Protocol):
    async def apply(
        self, rec: KbRecord, *, expect: int | None = None, deadline: float | None = None
    ) -> Applied:
        """Store one version. The latest value is the highest version (last writer wins
        by version); every version joins the key's bounded history; re-applying the
        latest record is a no-op. ``expect``: only if the current version equals it (0:
        the key does not exist), else :class:`~knowledge.errors.Conflict`.
        ``deadline`` (``time.monotonic()``): store by then or not at all; past it raise
        :class:`~knowledge.errors.StoreUnavailable` (nothing stored), or
        :class:`~knowledge.errors.OutcomeUnknown` when the store cannot tell."""

    async def get(self, key: str) -> KbRecord | None:
        """The latest record (a deletion included), or None."""

    async def history(
        self, key: str, *, since: int | None, until: int | None, limit: int
    ) -> list[KbRecord]:
        """Records with ``since <= ts < until``, oldest first, at most ``limit`` (the
        newest ones when more match)."""

    async def keys(self, pattern: str) -> list[str]:
        """Sorted keys matching ``pattern`` whose latest record is not a deletion."""

    async def put_model(self, meta: ModelMeta, data: bytes) -> None: ...

    async def get_model(self, name: str, version: int) -> tuple[ModelMeta, bytes] | None: ...

    async def list_models(self, name: str) -> list[ModelMeta]:
        """Versions of ``name``, oldest first."""

    async def set_pin(self, name: str, version: int | None) -> None: ...

    async def get_pin(self, name: str) -> int | None: ...

    async def aclose(self) -> None: ...

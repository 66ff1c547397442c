"""The in-memory store (the default): a dict of latest records and a bounded history."""

from __future__ import annotations

import bisect
import time

from rap_schemas import KbRecord, ModelMeta
from rap_sdk.keyexpr import intersects

from ..core import Limit, Retention, check_deadline
from ..errors import Conflict
from ..ports import Applied

__all__ = ["MemoryStore"]


def _order(r: KbRecord) -> tuple[int, int]:
    return (r.ts, r.version)


class _History:
    """One key's history: records ordered by (ts, version), each (version, writer) once,
    and the retention limit of the key."""

    __slots__ = ("ids", "limit", "records")

    def __init__(self, limit: Limit) -> None:
        self.records: list[KbRecord] = []
        self.ids: set[tuple[int, str]] = set()
        self.limit = limit


class MemoryStore:
    """Latest records in a dict; per key a history list ordered by (ts, version), holding
    each (version, writer) once, trimmed to the newest by count and age."""

    immediate = True
    """``apply`` never waits (no I/O): the service may store a record written in its own
    process in the writer's task."""

    def __init__(self, retention: Retention) -> None:
        self._retention = retention
        self._latest: dict[str, KbRecord] = {}
        self._history: dict[str, _History] = {}
        self._models: dict[str, dict[int, tuple[ModelMeta, bytes]]] = {}
        self._pins: dict[str, int] = {}

    async def apply(
        self, rec: KbRecord, *, expect: int | None = None, deadline: float | None = None
    ) -> Applied:
        return self.apply_now(rec, expect=expect, deadline=deadline)

    def apply_now(
        self, rec: KbRecord, *, expect: int | None = None, deadline: float | None = None
    ) -> Applied:
        """:meth:`apply`, in the caller's frame (it never waits)."""
        key = rec.key
        if deadline is not None:
            check_deadline(key, deadline)
        cur = self._latest.get(key)
        if cur is None:
            cur_version = 0
        else:
            cur_version = cur.version
            if cur_version == rec.version and cur.writer == rec.writer:
                return Applied(cur_version, True, duplicate=True)
        if expect is not None:
            live = cur_version if cur is not None and not cur.deleted else 0
            if live != expect:
                raise Conflict(key, expect, live)
        h = self._history.get(key)
        if h is None:
            h = self._history[key] = _History(self._retention.limit(key))
        ident = (rec.version, rec.writer)
        ids = h.ids
        if ident not in ids:
            ids.add(ident)
            hist = h.records
            if not hist or _order(hist[-1]) <= (rec.ts, rec.version):
                hist.append(rec)  # the usual case: the newest
            else:
                bisect.insort(hist, rec, key=_order)
            limit = h.limit
            if limit.max_age_ns is not None or (
                limit.max_count is not None and len(hist) > limit.max_count
            ):
                self._trim(limit, hist, ids)
        if rec.version > cur_version:
            self._latest[key] = rec
            return Applied(rec.version, True)
        return Applied(cur_version, False)

    @staticmethod
    def _trim(limit: Limit, hist: list[KbRecord], ids: set[tuple[int, str]]) -> None:
        drop = 0
        if limit.max_count is not None and len(hist) > limit.max_count:
            drop = len(hist) - limit.max_count
        if limit.max_age_ns is not None:
            oldest = time.time_ns() - limit.max_age_ns
            while drop < len(hist) and hist[drop].ts < oldest:
                drop += 1
        if drop == 1:  # the usual case: one in, one out
            old = hist.pop(0)
            ids.discard((old.version, old.writer))
            return
        for r in hist[:drop]:
            ids.discard((r.version, r.writer))
        del hist[:drop]

    async def get(self, key: str) -> KbRecord | None:
        return self._latest.get(key)

    async def history(
        self, key: str, *, since: int | None, until: int | None, limit: int
    ) -> list[KbRecord]:
        h = self._history.get(key)
        hist = h.records if h is not None else []
        out = [
            r for r in hist if (since is None or r.ts >= since) and (until is None or r.ts < until)
        ]
        return out[-limit:] if limit else []

    async def keys(self, pattern: str) -> list[str]:
        return sorted(
            k for k, r in self._latest.items() if not r.deleted and intersects(pattern, k)
        )

    async def put_model(self, meta: ModelMeta, data: bytes) -> None:
        self._models.setdefault(meta.name, {})[meta.version] = (meta, data)

    async def get_model(self, name: str, version: int) -> tuple[ModelMeta, bytes] | None:
        return self._models.get(name, {}).get(version)

    async def list_models(self, name: str) -> list[ModelMeta]:
        return [m for _, (m, _) in sorted(self._models.get(name, {}).items())]

    async def set_pin(self, name: str, version: int | None) -> None:
        if version is None:
            self._pins.pop(name, None)
        else:
            self._pins[name] = version

    async def get_pin(self, name: str) -> int | None:
        return self._pins.get(name)

    async def aclose(self) -> None:
        return None

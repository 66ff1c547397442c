"""The shared store: Redis, reachable from every compute node.

Per system: a hash of latest records and a hash of their versions, one stream per key
for history (trimmed by count with MAXLEN and by age with MINID; a stream trims by
arrival at the server, where the other stores keep the newest by ``ts``), and the model store in
hashes and strings. A write is one Lua script (atomic: compare-and-set, latest and
history together). Versions are compared as 20-digit strings, because Lua numbers are
doubles and lose 64-bit precision. Connection errors are retried with exponential
backoff; past that the operation fails with ``StoreUnavailable``.
"""

from __future__ import annotations

import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any

import anyio
import msgspec
import redis.asyncio as aioredis
from rap_schemas import KbRecord, ModelMeta
from rap_sdk.keyexpr import intersects
from redis.exceptions import ConnectionError as RedisConnectionError
from redis.exceptions import RedisError
from redis.exceptions import TimeoutError as RedisTimeoutError

from ..core import Retention, check_deadline
from ..errors import Conflict, OutcomeUnknown, StoreUnavailable
from ..ports import Applied

__all__ = ["RedisStore"]

log = logging.getLogger(__name__)

_APPLY = """
if KEYS[6] ~= nil and redis.call('GET', KEYS[6]) == 'fenced' then
  return {-2, '0'}
end
local cur = redis.call('HGET', KEYS[1], ARGV[1])
local cur_deleted = redis.call('HGET', KEYS[4], ARGV[1])
if cur == false then cur = '00000000000000000000' end
if cur == ARGV[2] and redis.call('HGET', KEYS[5], ARGV[1]) == ARGV[7] then
  return {2, cur}
end
if ARGV[4] ~= '' then
  local live = cur
  if cur_deleted == '1' then live = '00000000000000000000' end
  if live ~= ARGV[4] then return {-1, live} end
end
if ARGV[5] ~= '' then
  redis.call('XADD', KEYS[3], 'MAXLEN', '=', ARGV[5], '*', 'r', ARGV[3])
else
  redis.call('XADD', KEYS[3], '*', 'r', ARGV[3])
end
if ARGV[6] ~= '' then redis.call('XTRIM', KEYS[3], 'MINID', ARGV[6]) end
if ARGV[2] > cur then
  redis.call('HSET', KEYS[1], ARGV[1], ARGV[2])
  redis.call('HSET', KEYS[2], ARGV[1], ARGV[3])
  redis.call('HSET', KEYS[4], ARGV[1], ARGV[8])
  redis.call('HSET', KEYS[5], ARGV[1], ARGV[7])
  return {1, ARGV[2]}
end
return {0, cur}
"""
# a durable write marks its request id applied (in the same script, so atomically)
_APPLY_DURABLE = _APPLY.replace(
    "  return {1, ARGV[2]}\nend\nreturn {0, cur}",
    "  redis.call('SET', KEYS[6], 'applied', 'EX', 3600)\n  return {1, ARGV[2]}\nend\n"
    "redis.call('SET', KEYS[6], 'applied', 'EX', 3600)\nreturn {0, cur}",
)
_FENCE = """
if redis.call('GET', KEYS[1]) == 'applied' then return 1 end
redis.call('SET', KEYS[1], 'fenced', 'EX', 3600)
return 0
"""
"""Settle a durable write whose attempt may or may not have run: Redis runs one script
at a time, so either the write ran first (applied) or it will find the fence and store
nothing."""
FENCE_BUDGET = 0.3
"""Seconds kept from a durable write's budget to settle an uncertain attempt."""

_encode = msgspec.msgpack.Encoder().encode
_record = msgspec.msgpack.Decoder(KbRecord).decode
_meta = msgspec.msgpack.Decoder(ModelMeta).decode


SINCE_SLACK_MS = 60_000


def _v(version: int) -> str:
    return f"{version:020d}"


class RedisStore:
    def __init__(
        self, url: str, system: str, retention: Retention, *, retry_for: float = 10.0
    ) -> None:
        self._retention = retention
        self._p = f"rap:{system}:kb:"
        self._url = url
        self._retry_for = retry_for
        self._client = aioredis.Redis.from_url(
            url, socket_connect_timeout=2.0, socket_timeout=5.0, health_check_interval=10
        )
        self._apply_script = self._client.register_script(_APPLY)
        self._apply_durable = self._client.register_script(_APPLY_DURABLE)
        self._fence_script = self._client.register_script(_FENCE)

    async def open(self, *, retry_for: float | None = None) -> RedisStore:
        """Check that Redis answers (trying for ``retry_for`` s, default the store's)."""
        until = None if retry_for is None else time.monotonic() + retry_for
        try:
            await self._call(self._client.ping, until=until)
        except StoreUnavailable:
            await self._client.aclose()
            raise
        return self

    async def _call(
        self,
        fn: Callable[..., Awaitable[Any]],
        *args: Any,
        until: float | None = None,
        **kw: Any,
    ) -> Any:
        """Run one command, retrying connection failures with exponential backoff for up
        to ``retry_for`` seconds, or until the monotonic time ``until`` (each attempt
        then bounded by it too). Writes are safe to repeat: re-applying the latest record
        is a no-op. Raises :class:`_Failed` (a ``StoreUnavailable``) saying whether a
        failed attempt may have reached the server."""
        delay = 0.02
        deadline = time.monotonic() + self._retry_for if until is None else until
        sent = False
        while True:
            left = deadline - time.monotonic()
            try:
                if until is None:
                    return await fn(*args, **kw)
                if left <= 0:
                    raise TimeoutError
                with anyio.fail_after(left):
                    return await fn(*args, **kw)
            except (RedisConnectionError, RedisTimeoutError, TimeoutError) as exc:
                sent = sent or not _never_sent(exc)
                if time.monotonic() + delay > deadline:
                    raise _Failed(
                        f"redis store {self._url} unreachable: {exc or 'no answer in time'}",
                        sent=sent,
                    ) from None
                log.info("redis store %s: %s; retrying in %.2f s", self._url, exc, delay)
                await anyio.sleep(delay)  # backoff between reconnection attempts
                delay = min(delay * 2, 1.0)
            except RedisError as exc:
                raise _Failed(f"redis store {self._url}: {exc}", sent=True) from None

    async def aclose(self) -> None:
        await self._client.aclose()

    # -- records ---------------------------------------------------------------------------

    async def apply(
        self, rec: KbRecord, *, expect: int | None = None, deadline: float | None = None
    ) -> Applied:
        """See :class:`~knowledge.ports.Store`. With a ``deadline`` (a durable write) an
        attempt that failed after it may have reached Redis is settled with a fence
        before answering: applied (a success), fenced (it never will be: not stored), or,
        when Redis cannot be asked either, :class:`OutcomeUnknown`."""
        if deadline is None:
            return await self._apply(rec, expect, None)
        check_deadline(rec.key, deadline)
        request = f"{self._p}req:{rec.key}@{rec.version}:{rec.writer}"
        try:
            return await self._apply(rec, expect, (request, deadline - FENCE_BUDGET))
        except _Failed as exc:
            if not exc.sent:
                raise StoreUnavailable(f"{exc}; not stored") from None
            first = str(exc)
        try:
            applied = await self._call(lambda: self._fence_script(keys=[request]), until=deadline)
        except _Failed as exc:
            raise OutcomeUnknown(
                f"durable write of {rec.key!r} may or may not be stored: {first}, and Redis "
                f"could not be asked in time ({exc}); read the key to see"
            ) from None
        if applied:
            current = await self._call(self._client.hget, self._p + "ver", rec.key, until=None)
            version = int(current) if current is not None else rec.version
            return Applied(version, version == rec.version)
        raise StoreUnavailable(f"{first}; not stored (and fenced: it never will be)")

    async def _apply(
        self, rec: KbRecord, expect: int | None, durable: tuple[str, float] | None
    ) -> Applied:
        p = self._p
        limit = self._retention.limit(rec.key)
        minid = ""
        if limit.max_age_ns is not None:
            minid = str((time.time_ns() - limit.max_age_ns) // 1_000_000)
        script = self._apply_script if durable is None else self._apply_durable
        fence = [] if durable is None else [durable[0]]
        code, cur = await self._call(
            lambda: script(
                keys=[
                    p + "ver",
                    p + "latest",
                    p + "h:" + rec.key,
                    p + "deleted",
                    p + "writer",
                    *fence,
                ],
                args=[
                    rec.key,
                    _v(rec.version),
                    _encode(rec),
                    "" if expect is None else _v(expect),
                    "" if limit.max_count is None else str(limit.max_count),
                    minid,
                    rec.writer,
                    "1" if rec.deleted else "0",
                ],
            ),
            until=None if durable is None else durable[1],
        )
        current = int(cur)
        if code == -2:
            raise StoreUnavailable(f"durable write of {rec.key!r} was fenced; not stored")
        if code == -1:
            raise Conflict(rec.key, expect, current)
        if code == 2:
            return Applied(current, True, duplicate=True)
        return Applied(current, code == 1)

    async def get(self, key: str) -> KbRecord | None:
        raw = await self._call(self._client.hget, self._p + "latest", key)
        return _record(raw) if raw is not None else None

    async def history(
        self, key: str, *, since: int | None, until: int | None, limit: int
    ) -> list[KbRecord]:
        # stream ids are the server's arrival time; a record's ts is its writer's clock:
        # start SINCE_SLACK_MS early so a record that arrived before its ts is found
        lo = "-" if since is None else str(max(0, since // 1_000_000 - SINCE_SLACK_MS))
        entries = await self._call(self._client.xrange, self._p + "h:" + key, min=lo, max="+")
        seen: set[tuple[int, str]] = set()
        out = []
        for _, fields in entries:
            r = _record(fields[b"r"])
            in_window = (since is None or r.ts >= since) and (until is None or r.ts < until)
            if in_window and (r.version, r.writer) not in seen:
                seen.add((r.version, r.writer))
                out.append(r)
        out.sort(key=lambda r: (r.ts, r.version))
        return out[-limit:] if limit else []

    async def keys(self, pattern: str) -> list[str]:
        flags = await self._call(self._client.hgetall, self._p + "deleted")
        return sorted(
            k.decode() for k, d in flags.items() if d == b"0" and intersects(pattern, k.decode())
        )

    # -- models ----------------------------------------------------------------------------

    async def put_model(self, meta: ModelMeta, data: bytes) -> None:
        p = self._p

        async def put() -> None:
            async with self._client.pipeline(transaction=True) as pipe:
                pipe.set(f"{p}model:{meta.name}:{meta.version}", data)
                pipe.hset(f"{p}models:{meta.name}", str(meta.version), _encode(meta))
                await pipe.execute()

        await self._call(put)

    async def get_model(self, name: str, version: int) -> tuple[ModelMeta, bytes] | None:
        p = self._p
        meta = await self._call(self._client.hget, f"{p}models:{name}", str(version))
        if meta is None:
            return None
        data = await self._call(self._client.get, f"{p}model:{name}:{version}")
        return _meta(meta), bytes(data or b"")

    async def list_models(self, name: str) -> list[ModelMeta]:
        metas = await self._call(self._client.hvals, f"{self._p}models:{name}")
        return sorted((_meta(m) for m in metas), key=lambda m: m.version)

    async def set_pin(self, name: str, version: int | None) -> None:
        if version is None:
            await self._call(self._client.hdel, self._p + "pins", name)
        else:
            await self._call(self._client.hset, self._p + "pins", name, str(version))

    async def get_pin(self, name: str) -> int | None:
        raw = await self._call(self._client.hget, self._p + "pins", name)
        return int(raw) if raw is not None else None


class _Failed(StoreUnavailable):
    """A command failed; ``sent``: an attempt may have reached the server."""

    def __init__(self, message: str, *, sent: bool) -> None:
        super().__init__(message)
        self.sent = sent


def _never_sent(exc: BaseException) -> bool:
    """The connection was refused: the command cannot have reached the server."""
    return isinstance(exc.__context__, ConnectionRefusedError) or isinstance(
        exc.__cause__, ConnectionRefusedError
    )

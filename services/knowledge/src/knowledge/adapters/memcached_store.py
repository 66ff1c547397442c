"""Latest values in memcached; history, the key list and models in the service's own store.

memcached keeps one item per key and nothing else: it cannot list keys, keep a history
or hold a 256 MiB model, and it promises nothing about keeping an item (an item is
evicted when memory runs short, every item is gone when the server restarts). So this
store pairs it with an *inner* store (SQLite in the service: see :mod:`knowledge.app`):

- every record goes to the inner store too (history, the key list, and a copy of the
  latest value); models and pins live there only;
- the latest record of a key lives in memcached, replaced with ``gets``/``cas`` (``add``
  when the key has no item) so that a lower version never overwrites a higher one,
  whoever writes: two writers racing on one key both re-read and compare again;
- a read that finds no item (evicted, or memcached restarted) serves the inner store's
  latest record and puts it back;
- a record too large for an item (memcached's ``item_size_max``, 1 MiB by default, read
  at :meth:`MemcachedStore.open`) is kept in the inner store only: memcached holds a
  marker with its version, so versions still only go up there, and a read of the
  marker serves the inner store's record.

Each item is one byte of kind (``R``: the record, ``S``: the marker) then the record in
msgpack; its key is ``rap:<system>:kb:k:<key>`` when that is printable ASCII of at most
250 bytes, else ``rap:<system>:kb:h:<sha256 of the key>``. Items never expire.

memcached being down is an error, not a fallback: a read or a write of a latest value
retries the connection with exponential backoff (up to ``retry_for`` s, 10 by default)
and then fails with :class:`~knowledge.errors.StoreUnavailable` naming the URL. History,
key lists and models, which only the inner store holds, keep working meanwhile. A
connection that failed is closed and a new one opened for the next command, so the
store carries on by itself once memcached is back.
"""

from __future__ import annotations

import hashlib
import logging
import time
from collections.abc import Awaitable, Callable
from typing import Any, TypeVar
from urllib.parse import urlsplit

import aiomcache
import anyio
import msgspec
from aiomcache.pool import Connection
from rap_schemas import KbRecord

from ..core import check_deadline
from ..errors import BadRequest, Conflict, OutcomeUnknown, StoreUnavailable
from ..ports import Applied, Store
from .layered import Layered

__all__ = ["DEFAULT_URL", "MemcachedStore", "item_key", "parse_url"]

log = logging.getLogger(__name__)

T = TypeVar("T")

DEFAULT_URL = "memcached://127.0.0.1:11211"
DEFAULT_PORT = 11211
RECORD = b"R"
"""An item that holds the record."""
MARKER = b"S"
"""An item that holds the record without its value (too large for memcached): the
inner store has it."""
ITEM_OVERHEAD = 512
"""Bytes kept from ``item_size_max`` for memcached's item header and the key."""
CAS_ROUNDS = 64
"""Times a write re-reads a key that other writers changed under it, then gives up."""
FIX = (
    "start memcached there (Debian: apt-get install memcached) or give the URL of a "
    "running one (--memcached-url)"
)

_encode = msgspec.msgpack.Encoder().encode
_decode = msgspec.msgpack.Decoder(KbRecord).decode


def parse_url(url: str) -> tuple[str, int]:
    """``memcached://HOST[:PORT]`` -> (host, port); anything else is a
    :class:`~knowledge.errors.BadRequest` saying what to write."""
    try:
        parts = urlsplit(url)
        port = parts.port or DEFAULT_PORT
    except ValueError:
        parts, port = None, 0
    if (
        parts is None
        or parts.scheme != "memcached"
        or not parts.hostname
        or parts.path not in ("", "/")
        or parts.query
        or parts.fragment
        or parts.username is not None
    ):
        raise BadRequest(
            f"memcached URL {url!r}: write memcached://HOST[:PORT], e.g. {DEFAULT_URL}"
        )
    return parts.hostname, port


def item_key(prefix: str, key: str) -> bytes:
    """The memcached key of a knowledge key: readable when memcached allows it (printable
    ASCII, no space, at most 250 bytes), else a hash."""
    plain = f"{prefix}k:{key}".encode()
    if len(plain) <= 250 and all(0x21 <= b <= 0x7E for b in plain):
        return plain
    return f"{prefix}h:{hashlib.sha256(key.encode()).hexdigest()}".encode()


class _Client(aiomcache.Client):
    """aiomcache's client, failing on a reply the server cut off: its own loop would read
    the closed connection forever, without ever waiting (aio-libs/aiomcache#502)."""

    async def _execute_simple_command(self, conn: Connection, raw_command: bytes) -> bytes:
        conn.writer.write(raw_command)
        await conn.writer.drain()
        line = await conn.reader.readline()  # every command sent here answers one line
        if not line.endswith(b"\r\n"):
            raise ConnectionResetError("memcached closed the connection")
        return line[:-2]


class _Lost(Exception):
    """memcached could not be reached, or stopped answering; ``sent``: the command may
    have reached it."""

    def __init__(self, message: str, *, sent: bool) -> None:
        super().__init__(message)
        self.sent = sent


class _ItemTooLarge(Exception):
    """memcached refused an item as larger than its item size."""


class MemcachedStore(Layered):
    """A :class:`~knowledge.ports.Store` whose latest values live in memcached at ``url``
    and everything else in ``inner`` (which this store closes with itself)."""

    def __init__(
        self,
        url: str,
        system: str,
        inner: Store,
        *,
        connections: int = 4,
        timeout: float = 2.0,
        retry_for: float = 10.0,
    ) -> None:
        self._host, self._port = parse_url(url)
        self._url = url
        self._inner = inner
        self._prefix = f"rap:{system}:kb:"
        self._timeout = timeout
        self._retry_for = retry_for
        self._item_max = 1 << 20
        self._idle: list[_Client] = []
        """Connections ready for a command: one client of one connection each, so that a
        failed or cancelled command closes its own connection and no other."""
        self._slots = anyio.Semaphore(connections)

    @property
    def inner(self) -> Store:
        return self._inner

    async def open(self, *, retry_for: float | None = None) -> MemcachedStore:
        """Check that memcached answers (trying for ``retry_for`` s, default the store's)
        and read its item size."""
        until = time.monotonic() + (self._retry_for if retry_for is None else retry_for)
        settings = await self._retrying(until, _Client.stats, b"settings")
        size = settings.get(b"item_size_max")
        if size is not None and size.isdigit():
            self._item_max = int(size)
        return self

    async def aclose(self) -> None:
        idle, self._idle = self._idle, []
        with anyio.CancelScope(shield=True):
            for client in idle:
                await client.close()
            await self._inner.aclose()

    # -- memcached commands ----------------------------------------------------------------

    async def _once(self, until: float, op: Callable[..., Awaitable[T]], *args: Any) -> T:
        """``op(client, *args)``: one command (a method of the client) on a connection of
        its own, by the monotonic time ``until`` and within the store's timeout. A
        connection whose command failed is closed."""
        left = min(self._timeout, until - time.monotonic())
        if left <= 0:
            raise _Lost("no answer in time", sent=False)
        started = False
        try:
            with anyio.fail_after(left):
                async with self._slots:
                    client = self._idle.pop() if self._idle else self._client()
                    started = True
                    try:
                        result = await op(client, *args)
                    except BaseException:
                        with anyio.CancelScope(shield=True):
                            await client.close()
                        raise
                    self._idle.append(client)
                    return result
        except TimeoutError:
            raise _Lost("no answer in time", sent=started) from None
        except ConnectionRefusedError as exc:
            raise _Lost(str(exc) or "connection refused", sent=False) from None
        except (OSError, EOFError) as exc:  # reset, closed mid-reply, unreachable
            raise _Lost(str(exc) or type(exc).__name__, sent=True) from None
        except aiomcache.ClientException as exc:
            text = str(exc)
            if "object too large" in text:
                raise _ItemTooLarge(text) from None
            if text.endswith("b''"):  # a reply that stops short: the connection closed
                raise _Lost(f"memcached closed the connection ({text})", sent=True) from None
            raise StoreUnavailable(f"memcached store {self._url}: {text}") from None

    def _client(self) -> _Client:
        return _Client(self._host, self._port, pool_size=1)

    async def _retrying(self, until: float, op: Callable[..., Awaitable[T]], *args: Any) -> T:
        """A command that is safe to repeat (a read), retried on connection failures with
        exponential backoff until ``until``."""
        delay = 0.02
        while True:
            try:
                return await self._once(until, op, *args)
            except _Lost as exc:
                await self._backoff(exc, delay, until, "")
                delay = min(delay * 2, 1.0)

    async def _backoff(self, exc: _Lost, delay: float, until: float, unstored: str) -> None:
        """Wait ``delay`` s before another attempt, or raise
        :class:`~knowledge.errors.StoreUnavailable` when that would pass ``until``."""
        if time.monotonic() + delay > until:
            raise StoreUnavailable(
                f"memcached store {self._url} unreachable: {exc}; {FIX}{unstored}"
            )
        log.info("memcached store %s: %s; retrying in %.2f s", self._url, exc, delay)
        await anyio.sleep(delay)

    def _item(self, rec: KbRecord, mkey: bytes) -> bytes:
        item = RECORD + _encode(rec)
        if len(item) + len(mkey) + ITEM_OVERHEAD > self._item_max:
            return self._marker(rec)
        return item

    @staticmethod
    def _marker(rec: KbRecord) -> bytes:
        return MARKER + _encode(msgspec.structs.replace(rec, value=msgspec.Raw(b"\xc0")))

    def _read(self, key: str, raw: bytes) -> tuple[KbRecord, bool]:
        """The record of an item, and whether it is a marker (the value is elsewhere)."""
        kind, body = raw[:1], raw[1:]
        try:
            if kind not in (RECORD, MARKER):
                raise msgspec.DecodeError(f"unknown item kind {kind!r}")
            rec = _decode(body)
        except msgspec.DecodeError as exc:
            raise StoreUnavailable(
                f"memcached store {self._url}: the item of {key!r} is not a RAP knowledge "
                f"record ({exc}); something else writes under {self._prefix!r}: delete the item"
            ) from None
        if rec.key != key:
            raise StoreUnavailable(
                f"memcached store {self._url}: the item of {key!r} holds {rec.key!r}; "
                f"something else writes under {self._prefix!r}: delete the item"
            )
        return rec, kind == MARKER

    # -- records ---------------------------------------------------------------------------

    async def apply(
        self, rec: KbRecord, *, expect: int | None = None, deadline: float | None = None
    ) -> Applied:
        """See :class:`~knowledge.ports.Store`. memcached decides which record is the
        latest (``gets`` then ``cas``, or ``add`` for a key without an item, again on a
        race), then the record joins the inner store's history. With a ``deadline``, a
        write whose ``cas`` may have reached memcached but whose answer never came is
        :class:`~knowledge.errors.OutcomeUnknown`."""
        key = rec.key
        check_deadline(key, deadline)
        mkey = item_key(self._prefix, key)
        item = self._item(rec, mkey)
        until = deadline if deadline is not None else time.monotonic() + self._retry_for
        sent = False  # a storing command may have reached memcached
        delay = 0.02
        races = 0
        while True:
            try:
                raw, token = await self._once(until, _Client.gets, mkey)
                if raw is not None:
                    cur: KbRecord | None = self._read(key, raw)[0]
                else:  # no item (evicted, memcached restarted, never written)
                    cur = await self._inner.get(key)
                cur_version = cur.version if cur is not None else 0
                if cur is not None and (cur.version, cur.writer) == (rec.version, rec.writer):
                    if raw is None:  # the inner store's latest: put it back
                        await self._refill(key, mkey, rec)
                    return await self._stored(rec, Applied(rec.version, True, duplicate=not sent))
                if expect is not None:
                    live = cur_version if cur is not None and not cur.deleted else 0
                    if live != expect:
                        raise Conflict(key, expect, live)
                if rec.version <= cur_version:  # an older record: history only
                    if raw is None and cur is not None:
                        await self._refill(key, mkey, cur)
                    return await self._stored(rec, Applied(cur_version, False))
                try:
                    if raw is None or token is None:
                        ok = await self._once(until, _Client.add, mkey, item)
                    else:
                        ok = await self._once(until, _Client.cas, mkey, item, token)
                except _ItemTooLarge:
                    item = self._marker(rec)  # memcached's limit is lower than it said
                    continue
                except _Lost as exc:
                    sent = sent or exc.sent
                    raise
            except _Lost as exc:
                if sent and deadline is not None and time.monotonic() + delay > until:
                    raise OutcomeUnknown(
                        f"durable write of {key!r} may or may not be stored: memcached "
                        f"store {self._url} stopped answering ({exc}); read the key to see"
                    ) from None
                await self._backoff(
                    exc,
                    delay,
                    until,
                    "; the write may or may not be stored" if sent else "; not stored",
                )
                delay = min(delay * 2, 1.0)
                continue
            if ok:
                return await self._stored(rec, Applied(rec.version, True))
            races += 1  # another writer changed the item since gets: compare again
            if races >= CAS_ROUNDS:
                raise StoreUnavailable(
                    f"memcached store {self._url}: {key!r} changed under {CAS_ROUNDS} "
                    "attempts in a row to write it; not stored"
                )

    async def _stored(self, rec: KbRecord, applied: Applied) -> Applied:
        """Add ``rec`` to the inner store (history; the latest there too when it is): a
        record already there is a no-op, so this also completes an earlier attempt
        that reached memcached but not the inner store."""
        try:
            await self._inner.apply(rec)
        except StoreUnavailable as exc:
            raise OutcomeUnknown(
                f"{rec.key!r} version {rec.version} is in memcached but not in the "
                f"history of the service's own store ({exc}); write it again"
            ) from None
        return applied

    async def _refill(self, key: str, mkey: bytes, rec: KbRecord) -> None:
        """Put the inner store's latest record back into memcached (best effort: a miss
        serves the inner store again). Only ever raises the item's version."""
        until = time.monotonic() + self._timeout
        item = self._item(rec, mkey)
        try:
            for _ in range(CAS_ROUNDS):
                raw, token = await self._once(until, _Client.gets, mkey)
                if raw is not None and self._read(key, raw)[0].version >= rec.version:
                    return
                if raw is None or token is None:
                    ok = await self._once(until, _Client.add, mkey, item)
                else:
                    ok = await self._once(until, _Client.cas, mkey, item, token)
                if ok:
                    return
        except (_Lost, _ItemTooLarge, StoreUnavailable) as exc:
            log.info("memcached store %s: %r not put back: %s", self._url, key, exc)

    async def get(self, key: str) -> KbRecord | None:
        mkey = item_key(self._prefix, key)
        raw = await self._retrying(time.monotonic() + self._retry_for, _Client.get, mkey)
        if raw is not None:
            cached, marker = self._read(key, raw)
            if not marker:
                return cached
            full = await self._inner.get(key)  # too large for memcached: kept there
            if full is None:
                raise StoreUnavailable(
                    f"memcached store {self._url}: {key!r} version {cached.version} is too "
                    "large for memcached, and the service's own store does not have it"
                )
            return full
        rec = await self._inner.get(key)  # evicted, or memcached restarted: put it back
        if rec is not None:
            await self._refill(key, mkey, rec)
            again = await self._inner.get(key)  # a write that landed while refilling
            if again is not None and again.version > rec.version:
                await self._refill(key, mkey, again)
                rec = again
        return rec

    # -- the inner store: history, keys, models ---------------------------------------------

    @property
    def item_size_max(self) -> int:
        """memcached's item size (bytes), as it said at :meth:`open`."""
        return self._item_max

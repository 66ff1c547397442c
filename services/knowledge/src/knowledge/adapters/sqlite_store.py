"""The embedded durable store: SQLite in WAL mode with ``synchronous=FULL``, so a write
acknowledged to a client survives a crash of the service (kill -9) and a restart.

sqlite3 blocks, so every call runs on one worker thread (a limiter of 1 also serialises
them); the event loop never waits on the disk.

With ``outbox=True`` every record that joins the store is also written, in the same
transaction, to an ``outbox`` table numbered in commit order: what a store built on this
one (the Kafka knowledge stream, :mod:`knowledge.adapters.kafka_store`) must still pass
on, kept across a crash. It takes rows with :meth:`SqliteStore.outbox_take` and deletes
them with :meth:`SqliteStore.outbox_done` once passed on.
"""

from __future__ import annotations

import functools
import sqlite3
import time
from collections.abc import Callable
from typing import Any, TypeVar

import anyio
import msgspec
from rap_schemas import KbRecord, ModelMeta
from rap_sdk.keyexpr import intersects

from ..core import Retention, check_deadline
from ..errors import Conflict, StoreUnavailable
from ..ports import Applied

__all__ = ["SqliteStore"]

T = TypeVar("T")

_SCHEMA = """
CREATE TABLE IF NOT EXISTS records (
    key TEXT NOT NULL, version INTEGER NOT NULL, writer TEXT NOT NULL,
    ts INTEGER NOT NULL, deleted INTEGER NOT NULL, value BLOB NOT NULL,
    PRIMARY KEY (key, version, writer));
CREATE INDEX IF NOT EXISTS records_by_time ON records (key, ts);
CREATE TABLE IF NOT EXISTS latest (
    key TEXT PRIMARY KEY, version INTEGER NOT NULL, writer TEXT NOT NULL,
    ts INTEGER NOT NULL, deleted INTEGER NOT NULL, value BLOB NOT NULL);
CREATE TABLE IF NOT EXISTS models (
    name TEXT NOT NULL, version INTEGER NOT NULL, meta BLOB NOT NULL, data BLOB NOT NULL,
    PRIMARY KEY (name, version));
CREATE TABLE IF NOT EXISTS pins (name TEXT PRIMARY KEY, version INTEGER NOT NULL);
"""
_OUTBOX = """
CREATE TABLE IF NOT EXISTS outbox (
    seq INTEGER PRIMARY KEY AUTOINCREMENT, key TEXT NOT NULL, version INTEGER NOT NULL,
    writer TEXT NOT NULL, ts INTEGER NOT NULL, deleted INTEGER NOT NULL, value BLOB NOT NULL);
"""

_COLS = "key, version, writer, ts, deleted, value"


def _row(r: tuple[Any, ...]) -> KbRecord:
    return KbRecord(
        key=r[0], version=r[1], writer=r[2], ts=r[3], deleted=bool(r[4]), value=msgspec.Raw(r[5])
    )


def _vals(rec: KbRecord) -> tuple[Any, ...]:
    return (rec.key, rec.version, rec.writer, rec.ts, int(rec.deleted), bytes(rec.value))


class SqliteStore:
    def __init__(self, path: str, retention: Retention, *, outbox: bool = False) -> None:
        self._path = path
        self._retention = retention
        self._outbox = outbox
        self._limiter = anyio.CapacityLimiter(1)
        self._conn: sqlite3.Connection | None = None

    async def _run(self, fn: Callable[..., T], *args: Any) -> T:
        try:
            return await anyio.to_thread.run_sync(
                functools.partial(fn, *args), limiter=self._limiter
            )
        except sqlite3.Error as exc:  # locked, unreadable, not a database, disk full
            raise StoreUnavailable(f"sqlite store {self._path!r}: {exc}") from None

    async def open(self) -> SqliteStore:
        self._conn = await self._run(self._connect)
        return self

    def _connect(self) -> sqlite3.Connection:
        conn = sqlite3.connect(self._path, check_same_thread=False, isolation_level=None)
        conn.execute("PRAGMA journal_mode=WAL")
        conn.execute("PRAGMA synchronous=FULL")
        conn.executescript(_SCHEMA + (_OUTBOX if self._outbox else ""))
        return conn

    @property
    def _db(self) -> sqlite3.Connection:
        if self._conn is None:
            raise StoreUnavailable("sqlite store is not open")
        return self._conn

    async def aclose(self) -> None:
        if self._conn is not None:
            conn, self._conn = self._conn, None
            await self._run(conn.close)

    # -- records ---------------------------------------------------------------------------

    async def apply(
        self, rec: KbRecord, *, expect: int | None = None, deadline: float | None = None
    ) -> Applied:
        return await self._run(self._apply, rec, expect, deadline)

    def _apply(self, rec: KbRecord, expect: int | None, deadline: float | None) -> Applied:
        db = self._db
        db.execute("BEGIN IMMEDIATE")
        try:
            check_deadline(rec.key, deadline)  # under the write lock: stored in time or not
            cur = db.execute(
                "SELECT version, writer, deleted FROM latest WHERE key = ?", (rec.key,)
            ).fetchone()
            cur_version = cur[0] if cur else 0
            if cur and cur[0] == rec.version and cur[1] == rec.writer:
                db.execute("COMMIT")
                return Applied(cur_version, True, duplicate=True)
            if expect is not None:
                live = cur_version if cur and not cur[2] else 0
                if live != expect:
                    raise Conflict(rec.key, expect, live)
            added = db.execute(
                f"INSERT OR IGNORE INTO records ({_COLS}) VALUES (?,?,?,?,?,?)", _vals(rec)
            ).rowcount
            if added and self._outbox:
                db.execute(f"INSERT INTO outbox ({_COLS}) VALUES (?,?,?,?,?,?)", _vals(rec))
            self._trim(db, rec.key)
            latest = rec.version > cur_version
            if latest:
                db.execute(
                    f"INSERT OR REPLACE INTO latest ({_COLS}) VALUES (?,?,?,?,?,?)", _vals(rec)
                )
            db.execute("COMMIT")
        except BaseException:
            db.execute("ROLLBACK")
            raise
        return Applied(rec.version if latest else cur_version, latest)

    def _trim(self, db: sqlite3.Connection, key: str) -> None:
        limit = self._retention.limit(key)
        if limit.max_count is not None:
            db.execute(
                "DELETE FROM records WHERE key = ? AND rowid NOT IN (SELECT rowid FROM "
                "records WHERE key = ? ORDER BY ts DESC, version DESC LIMIT ?)",
                (key, key, limit.max_count),
            )
        if limit.max_age_ns is not None:
            db.execute(
                "DELETE FROM records WHERE key = ? AND ts < ?",
                (key, time.time_ns() - limit.max_age_ns),
            )

    async def outbox_take(self, limit: int) -> list[tuple[int, KbRecord]]:
        """The oldest ``limit`` rows of the outbox (``outbox=True``): (number, record)."""
        rows = await self._run(
            lambda: self._db.execute(
                f"SELECT seq, {_COLS} FROM outbox ORDER BY seq LIMIT ?", (limit,)
            ).fetchall()
        )
        return [(r[0], _row(r[1:])) for r in rows]

    async def outbox_done(self, upto: int) -> None:
        """Delete the outbox's rows up to number ``upto``: passed on."""

        def done() -> None:
            with self._db:
                self._db.execute("DELETE FROM outbox WHERE seq <= ?", (upto,))

        await self._run(done)

    async def outbox_size(self) -> int:
        """Rows waiting in the outbox."""
        row = await self._run(lambda: self._db.execute("SELECT count(*) FROM outbox").fetchone())
        return int(row[0])

    async def get(self, key: str) -> KbRecord | None:
        row = await self._run(
            lambda: self._db.execute(f"SELECT {_COLS} FROM latest WHERE key = ?", (key,)).fetchone()
        )
        return _row(row) if row else None

    async def history(
        self, key: str, *, since: int | None, until: int | None, limit: int
    ) -> list[KbRecord]:
        def query() -> list[tuple[Any, ...]]:
            return self._db.execute(
                f"SELECT {_COLS} FROM records WHERE key = ? AND ts >= ? AND ts < ? "
                "ORDER BY ts DESC, version DESC LIMIT ?",
                (
                    key,
                    since if since is not None else -(2**63),
                    until if until is not None else 2**63 - 1,
                    limit,
                ),
            ).fetchall()

        rows = await self._run(query)
        return [_row(r) for r in reversed(rows)]

    async def keys(self, pattern: str) -> list[str]:
        rows = await self._run(
            lambda: self._db.execute("SELECT key FROM latest WHERE deleted = 0").fetchall()
        )
        return sorted(k for (k,) in rows if intersects(pattern, k))

    # -- models ----------------------------------------------------------------------------

    async def put_model(self, meta: ModelMeta, data: bytes) -> None:
        def put() -> None:
            with self._db:
                self._db.execute(
                    "INSERT INTO models VALUES (?,?,?,?)",
                    (meta.name, meta.version, msgspec.msgpack.encode(meta), data),
                )

        await self._run(put)

    async def get_model(self, name: str, version: int) -> tuple[ModelMeta, bytes] | None:
        row = await self._run(
            lambda: self._db.execute(
                "SELECT meta, data FROM models WHERE name = ? AND version = ?", (name, version)
            ).fetchone()
        )
        if row is None:
            return None
        return msgspec.msgpack.decode(row[0], type=ModelMeta), bytes(row[1])

    async def list_models(self, name: str) -> list[ModelMeta]:
        rows = await self._run(
            lambda: self._db.execute(
                "SELECT meta FROM models WHERE name = ? ORDER BY version", (name,)
            ).fetchall()
        )
        return [msgspec.msgpack.decode(r[0], type=ModelMeta) for r in rows]

    async def set_pin(self, name: str, version: int | None) -> None:
        def pin() -> None:
            with self._db:
                if version is None:
                    self._db.execute("DELETE FROM pins WHERE name = ?", (name,))
                else:
                    self._db.execute("INSERT OR REPLACE INTO pins VALUES (?, ?)", (name, version))

        await self._run(pin)

    async def get_pin(self, name: str) -> int | None:
        row = await self._run(
            lambda: self._db.execute("SELECT version FROM pins WHERE name = ?", (name,)).fetchone()
        )
        return int(row[0]) if row else None

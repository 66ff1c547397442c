"""Configuration of the knowledge service (validated, unknown fields refused)."""

from __future__ import annotations

from typing import Literal

import msgspec

__all__ = ["HistoryRule", "KnowledgeConfig"]


class HistoryRule(msgspec.Struct, frozen=True, forbid_unknown_fields=True):
    """Bounded history for the keys matching ``pattern`` (``*``/``**`` chunks)."""

    pattern: str = "**"
    max_count: int | None = 1000
    max_age_s: float | None = None


class KnowledgeConfig(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    system: str = "rap"
    backend: Literal["memory", "sqlite", "redis", "memcached", "kafka"] = "memory"
    sqlite_path: str = "knowledge.sqlite3"
    """The SQLite file (``sqlite``; with ``memcached``: history, the key list, models;
    with ``kafka``: everything, and the outbox of the knowledge stream)."""
    redis_url: str = "redis://127.0.0.1:6379/0"
    memcached_url: str = "memcached://127.0.0.1:11211"
    """memcached (``memcached``: the latest value of each key)."""
    kafka_url: str = "kafka://127.0.0.1:9092"
    """The Kafka broker (``kafka``: every record stored is appended to ``kafka_topic``)."""
    kafka_topic: str | None = None
    """The knowledge stream's topic (None: ``rap.<system>.kb``)."""
    history: list[HistoryRule] = msgspec.field(default_factory=lambda: [HistoryRule()])
    """First matching rule wins."""
    max_value_bytes: int = 1 << 20
    max_model_bytes: int = 256 << 20
    model_grants: dict[str, dict[str, Literal["read", "write"]]] = {}
    """Identity -> model name -> ``read`` (get, list) or ``write`` (also put, pin, roll
    back): what the system model grants each process (``rap up`` derives it from the
    components' ``models:``). With identities (``RAP_CERTS``) the model store takes a
    request only signed, from an operator or from an identity granted that model;
    without, from anyone."""
    handler_timeout: float = 30.0

"""The envelope every sample on the fabric travels in (docs/architecture.md, "Envelope")."""

from __future__ import annotations

import msgspec

__all__ = ["Envelope"]


class Envelope(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    """One msgpack-encoded envelope per fabric sample.

    ``seq`` counts per sender *and key*: a receiver that follows one key sees a dense
    sequence, so a gap means a lost sample rather than a message on another key.
    ``body`` stays raw msgpack until a typed decoder for ``type`` reads it.
    """

    uid: bytes
    """128-bit id (UUIDv7 layout), unique per message."""
    ts: int
    """UTC wall clock at creation, integer nanoseconds."""
    source: str
    """Node id of the sender."""
    seq: int
    """Per-sender, per-key monotonic counter starting at 0."""
    type: str
    """Schema name with version, e.g. ``rap.LaserScan/1``."""
    body: msgspec.Raw
    """The typed message, msgpack."""
    cycle: bytes | None = None
    """Id of the loop cycle: uid of the sample that started it."""
    cause: bytes | None = None
    """uid of the envelope this one was produced in reaction to."""
    ctx: dict[str, int] = {}
    """Knowledge versions written before emitting this envelope ({key: version})."""

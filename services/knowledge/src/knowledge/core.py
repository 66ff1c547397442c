"""Pure knowledge logic: retention rules, validation, model integrity. No I/O."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass

from rap_schemas import MODELS_PREFIX, KbRecord, keys
from rap_schemas.knowledge import RecordError
from rap_schemas.knowledge import check_record as bounds
from rap_schemas.limits import MAX_DEPTH, DecodeRejected, SafeDecoder
from rap_sdk.keyexpr import KeyExprError, intersects, validate

from .config import HistoryRule
from .errors import BadRequest, IntegrityError, StoreUnavailable, TooLarge

__all__ = [
    "Retention",
    "admit_record",
    "check_deadline",
    "check_key",
    "check_model",
    "check_pattern",
    "check_time",
    "check_value",
    "sha256",
]


@dataclass(frozen=True, slots=True)
class Limit:
    max_count: int | None
    max_age_ns: int | None


class Retention:
    """Which history limit applies to a key: the first matching rule."""

    def __init__(self, rules: list[HistoryRule]) -> None:
        for r in rules:
            check_pattern(r.pattern)
            if r.max_count is not None and r.max_count < 1:
                raise BadRequest(f"history rule {r.pattern!r}: max_count must be >= 1")
        self._rules = [
            (r.pattern, Limit(r.max_count, None if r.max_age_s is None else int(r.max_age_s * 1e9)))
            for r in rules
        ]
        self._cache: dict[str, Limit] = {}

    def limit(self, key: str) -> Limit:
        hit = self._cache.get(key)
        if hit is None:
            hit = next((lim for pat, lim in self._rules if intersects(pat, key)), Limit(None, None))
            if len(self._cache) < 65536:
                self._cache[key] = hit
        return hit


_VALID_KEYS: set[str] = set()
"""Keys already checked (bounded): a key is validated once, not on every request."""


def check_key(key: str) -> str:
    if key in _VALID_KEYS:
        return key
    try:
        keys.kb("x", key)
    except keys.KeyError_ as exc:
        raise BadRequest(str(exc)) from None
    if key == MODELS_PREFIX or key.startswith(MODELS_PREFIX + "/"):
        raise BadRequest(f"knowledge key {key!r} is reserved for the model store")
    if len(_VALID_KEYS) < 65536:
        _VALID_KEYS.add(key)
    return key


def check_pattern(pattern: str) -> str:
    try:
        validate(pattern)
    except KeyExprError as exc:
        raise BadRequest(f"invalid key pattern: {exc}") from None
    return pattern


def check_time(name: str, value: int | None) -> int | None:
    if value is not None and not 0 <= value < 2**63:
        raise BadRequest(f"{name} must be UTC nanoseconds in 0 .. 2**63-1, got {value}")
    return value


def admit_record(rec: KbRecord, max_value_bytes: int, *, local: bool = False) -> KbRecord:
    """The key, then the bounds every replica applies too
    (:func:`rap_schemas.knowledge.check_record`), then the value's nesting, except for
    a record written in this process (``local``): its writer checked the value's
    nesting before encoding it (:meth:`rap_sdk.KnowledgeClient.write`)."""
    check_key(rec.key)
    try:
        bounds(rec, now_ms=time.time_ns() // 1_000_000, max_value_bytes=max_value_bytes)
    except RecordError as exc:
        raise (TooLarge if exc.code == "too-large" else BadRequest)(str(exc)) from None
    if not local:
        check_value(rec)
    return rec


_plain = SafeDecoder[object](max_depth=MAX_DEPTH, max_bytes=1 << 62, what="value")


def check_value(rec: KbRecord) -> None:
    """A stored value must decode, nested at most ``MAX_DEPTH`` levels: every reader can
    then read it, whatever its stack (the decoder's own nesting guard depends on it)."""
    try:
        _plain.decode(rec.value)
    except DecodeRejected as exc:
        raise BadRequest(f"record for {rec.key!r}: {exc.reason}") from None


def sha256(data: bytes) -> str:
    return hashlib.sha256(data).hexdigest()


def check_model(name: str, data: bytes, digest: str, max_bytes: int) -> None:
    try:
        keys.kb("x", f"{MODELS_PREFIX}/{name}")
    except keys.KeyError_ as exc:
        raise BadRequest(f"invalid model name: {exc}") from None
    if len(data) > max_bytes:
        raise TooLarge(f"model {name!r} is {len(data)} bytes, over the limit of {max_bytes}")
    if sha256(data) != digest:
        raise IntegrityError(f"model {name!r}: the data does not match the sha256 sent with it")


def check_deadline(key: str, deadline: float | None) -> None:
    """Refuse to store a durable write whose budget has run out (nothing is stored)."""
    if deadline is not None and time.monotonic() > deadline:
        raise StoreUnavailable(
            f"durable write of {key!r} not stored: its budget ran out before the store could "
            "take it (the store is slow or was unreachable); retry it"
        )

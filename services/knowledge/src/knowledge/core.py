"""Pure knowledge logic: retention rules, validation, model integrity. No I/O."""

from __future__ import annotations

import hashlib
import time
from dataclasses import dataclass

from rap_schemas import MODELS_PREFIX, KbRecord, keys
from rap_sdk.keyexpr import KeyExprError, intersects, validate
from rap_sdk.knowledge import EPOCH_MS

from .config import HistoryRule
from .errors import BadRequest, IntegrityError, TooLarge

__all__ = [
    "Retention",
    "check_key",
    "check_model",
    "check_pattern",
    "check_record",
    "check_time",
    "check_version",
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


MAX_DRIFT_MS = 60_000
"""How far ahead of this service's clock a version's time may be. A version from the far
future would win every later write and push every writer's clock past it."""


def check_version(key: str, version: int) -> int:
    if not 0 < version < 2**63:
        raise BadRequest(
            f"record for {key!r} has version {version}; versions are in "
            "1 .. 2**63-1 (hybrid-logical-clock stamps)"
        )
    if version >> 20 > time.time_ns() // 1_000_000 - EPOCH_MS + MAX_DRIFT_MS:
        raise BadRequest(
            f"record for {key!r} has a version {version} more than "
            f"{MAX_DRIFT_MS // 1000} s ahead of this service's clock; check "
            "the writer's clock"
        )
    return version


def check_time(name: str, value: int | None) -> int | None:
    if value is not None and not 0 <= value < 2**63:
        raise BadRequest(f"{name} must be UTC nanoseconds in 0 .. 2**63-1, got {value}")
    return value


def check_record(rec: KbRecord, max_value_bytes: int) -> KbRecord:
    check_key(rec.key)
    check_version(rec.key, rec.version)
    check_time("ts", rec.ts)
    if len(rec.value) > max_value_bytes:
        raise TooLarge(
            f"value for {rec.key!r} is {len(rec.value)} bytes, over the limit of "
            f"{max_value_bytes}; store large artefacts in the model store"
        )
    return rec


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

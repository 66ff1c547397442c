"""Errors of the knowledge service::

KnowledgeError            carries a machine-readable ``code`` for the reply
├── BadRequest            malformed key, value, pattern or operation (bad-request)
├── TooLarge              value or model over the configured limit (too-large)
├── Conflict              compare-and-set saw another version (conflict)
├── NotFound              no such key, model or version (not-found)
├── IntegrityError        stored bytes do not match their sha256 (integrity)
├── StoreUnavailable      the backend cannot be reached now; nothing stored (unavailable)
└── OutcomeUnknown        a durable write's outcome could not be learned (unknown)
"""

from __future__ import annotations

__all__ = [
    "BadRequest",
    "Conflict",
    "IntegrityError",
    "KnowledgeError",
    "NotFound",
    "OutcomeUnknown",
    "StoreUnavailable",
    "TooLarge",
]


class KnowledgeError(Exception):
    code = "error"


class BadRequest(KnowledgeError):
    code = "bad-request"


class TooLarge(KnowledgeError):
    code = "too-large"


class Conflict(KnowledgeError):
    code = "conflict"

    def __init__(self, key: str, expected: int | None, current: int) -> None:
        super().__init__(
            f"compare-and-set on {key!r} expected version {expected}, but the current "
            f"version is {current}: read it again and retry"
        )
        self.current = current


class NotFound(KnowledgeError):
    code = "not-found"


class IntegrityError(KnowledgeError):
    code = "integrity"


class StoreUnavailable(KnowledgeError):
    code = "unavailable"


class OutcomeUnknown(KnowledgeError):
    """A durable write may or may not have been stored: the backend failed mid-write and
    could not be asked before the request's budget ran out."""

    code = "unknown"

"""Errors of the knowledge service::

ServiceError              carries a machine-readable ``code`` for the reply
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
    "NotFound",
    "OutcomeUnknown",
    "ServiceError",
    "StoreUnavailable",
    "TooLarge",
]


class ServiceError(Exception):
    code = "error"


class BadRequest(ServiceError):
    code = "bad-request"


class TooLarge(ServiceError):
    code = "too-large"


class Conflict(ServiceError):
    code = "conflict"

    def __init__(self, key: str, expected: int | None, current: int) -> None:
        super().__init__(
            f"compare-and-set on {key!r} expected version {expected}, but the current "
            f"version is {current}: read it again and retry"
        )
        self.current = current


class NotFound(ServiceError):
    code = "not-found"


class IntegrityError(ServiceError):
    code = "integrity"


class StoreUnavailable(ServiceError):
    code = "unavailable"


class OutcomeUnknown(ServiceError):
    """A durable write may or may not have been stored: the backend failed mid-write and
    could not be asked before the request's budget ran out."""

    code = "unknown"

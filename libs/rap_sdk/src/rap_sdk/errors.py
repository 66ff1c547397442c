"""The errors of rap_sdk. The SDK's own failures are :class:`RapError`; Zenoh's errors
are wrapped into :class:`FabricError`. Arguments that are malformed raise ``ValueError``
subclasses at the call: an invalid key (``rap_schemas.keys.KeyError_``, or
``rap_sdk.keyexpr.KeyExprError`` for an expression) or an invalid ``InboxPolicy``::

    RapError
    ├── LifecycleError        an object used in the wrong state (not open, closed, running)
    ├── FabricError           the data fabric failed
    │   ├── QueryError        a query got no usable reply (timeout, remote error)
    │   └── BackpressureTimeout  a bounded inbox stayed full past the publish deadline
    ├── RejectedSample        a sample that cannot be accepted (undecodable, wrong type)
    ├── HandlerError          a handler's declaration is wrong (signature, annotation)
    └── ConfigError           a configuration value is invalid (with its ``$.path``)

Messages say what happened, the bad value, and how to fix it.
"""

from __future__ import annotations

__all__ = [
    "BackpressureTimeout",
    "ConfigError",
    "FabricError",
    "HandlerError",
    "LifecycleError",
    "QueryError",
    "RapError",
    "RejectedSample",
]


class RapError(Exception):
    """Base of every error raised by rap_sdk."""


class LifecycleError(RapError):
    """An object was used in a state that does not allow it."""


class FabricError(RapError):
    """The data fabric failed (session, transport, declaration)."""


class QueryError(FabricError):
    """A query got no usable reply."""


class BackpressureTimeout(FabricError):
    """A FIFO inbox stayed full for longer than the publisher's deadline."""


class RejectedSample(RapError):
    """A sample cannot be accepted; ``reason`` is fit for a rejection record."""

    def __init__(self, reason: str, *, source: str = "", type: str = "") -> None:
        super().__init__(reason)
        self.reason = reason
        self.source = source
        """The sender, when the envelope could be read."""
        self.type = type
        """The wire type, when the envelope could be read."""


class HandlerError(RapError):
    """A handler is declared wrongly."""


class ConfigError(RapError):
    """A configuration value is invalid."""

"""A process's log line, as it travels (``rap/<system>/log/<node>``, JSON lines files,
Redis streams).

The log key also carries :class:`~rap_schemas.Rejection` records (samples a node
refused): a reader tells the two apart by the envelope's ``type``
(``rap.LogRecord/1`` or ``rap.Rejection/1``). In a JSON lines file or a Redis stream
each line is this Struct as JSON, one object per line.
"""

from __future__ import annotations

from typing import Final

from .message import Message

__all__ = ["MAX_LOG_MESSAGE", "LogRecord"]

MAX_LOG_MESSAGE: Final = 16 * 1024
"""Characters of a log message (and of its exception text) kept; the rest is cut and
marked (a log line is never a way to ship a large payload)."""


class LogRecord(Message, frozen=True, omit_defaults=True):
    """One log line of a RAP process."""

    TYPE = "rap.LogRecord/1"

    ts: int
    """When it was logged, UTC integer nanoseconds."""
    level: str
    """``DEBUG``, ``INFO``, ``WARNING``, ``ERROR`` or ``CRITICAL``."""
    logger: str
    """The Python logger's name (``rap_sdk.runtime``, ``knowledge``, ...)."""
    message: str
    system: str = ""
    compute_node: str = ""
    process: str = ""
    """The process that logged it (``runner``, ``knowledge``, ``trust-<spec>``)."""
    component: str = ""
    """The component the line is about, when known (a component's own logger, or a
    runtime line naming the node)."""
    exc: str = ""
    """The exception's traceback text, when the line carries one."""

"""Messages of the trust checker on the fabric.

rap/<system>/trust/<stream>          TrustOutput: one output stream's value at a tick
rap/<system>/admin/<node>/swap       queryable: TrustSpecUpdate in, TrustSpecStatus out
"""

from __future__ import annotations

from typing import Any

import msgspec

from .message import Message

__all__ = ["TrustOutput", "TrustSpecStatus", "TrustSpecUpdate"]


class TrustOutput(Message, frozen=True, omit_defaults=True):
    """One output stream of a trust spec ticked (``rap/<system>/trust/<stream>``)."""

    TYPE = "rap.TrustOutput/1"

    stream: str
    tick: int
    """The checker's tick number (0-based, counted since it started)."""
    ts: int
    """The tick's wall-clock time, UTC integer nanoseconds."""
    value: Any = None
    """The value as plain data (numbers, strings, booleans, lists, maps); ``None`` for
    Unit and for ⊥ (then ``deferred`` is true)."""
    deferred: bool = False
    """The value cannot be computed yet (⊥, printed ``Deferred``)."""


class TrustSpecUpdate(Message, frozen=True, omit_defaults=True):
    """A new spec for a running checker: hot swap with stream history carried over."""

    TYPE = "rap.TrustSpecUpdate/1"

    spec: str
    """The spec text (either syntax era)."""
    path: str = "<swap>"
    """A name for the spec in error messages (``path:line:col``)."""


class TrustSpecStatus(Message, frozen=True, omit_defaults=True):
    """The answer to a spec update: swapped, or rejected with every problem."""

    TYPE = "rap.TrustSpecStatus/1"

    ok: bool
    node: str
    ts: int
    tick: int = 0
    """The checker's tick count when the new spec took over (ok) or was refused."""
    problems: list[str] = msgspec.field(default_factory=list)
    """Each problem as ``path:line:col: message`` (with the text and a hint)."""
    inputs: list[str] = msgspec.field(default_factory=list)
    """The input streams of the spec now running."""
    outputs: list[str] = msgspec.field(default_factory=list)

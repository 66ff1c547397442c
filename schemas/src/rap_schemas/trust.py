"""Messages of the trust checker on the fabric.

rap/<system>/trust/<stream>          TrustOutput: one output stream's value at a tick
rap/<system>/trust/<stream>/verdict  TrustVerdict: a Bool output turned false (with why),
                                     or a trigger fired (``<stream>`` is then
                                     ``trigger.<n>``, n its place among the spec's triggers)
rap/<system>/admin/<node>/swap       queryable: TrustSpecUpdate in, TrustSpecStatus out
"""

from __future__ import annotations

from typing import Any, Literal

import msgspec

from .message import Message

__all__ = ["TrustCause", "TrustOutput", "TrustSpecStatus", "TrustSpecUpdate", "TrustVerdict"]


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


class TrustCause(msgspec.Struct, frozen=True, kw_only=True, omit_defaults=True):
    """One reason in a :class:`TrustVerdict`: a subexpression of the spec and its value
    at the verdict's tick, or an input's held value and the tick it arrived at."""

    expr: str
    """The subexpression's source text, as written in the spec (``latency < 2.0``)."""
    value: Any = None
    """Its value as plain data (``None`` for Unit and ⊥; ``deferred`` tells ⊥ apart)."""
    deferred: bool = False
    depth: int = 0
    """0 for an operand of the verdict's expression, 1 for an operand of that, ..."""
    input: str | None = None
    """For an input's value (``latency``, ``latency[1]``): the input stream."""
    input_tick: int | None = None
    """The tick at which that input value arrived (None: it never did, the value is ⊥)."""


class TrustVerdict(Message, frozen=True, omit_defaults=True):
    """A Bool output of a trust spec turned false (true or no value before, false now),
    or a ``trigger`` fired; ``because`` names what decided it
    (``rap/<system>/trust/<stream>/verdict``)."""

    TYPE = "rap.TrustVerdict/1"

    stream: str
    """The output stream, or ``trigger.<n>`` for the spec's n-th trigger (0-based)."""
    tick: int
    ts: int | None = None
    """The tick's wall-clock time, UTC integer nanoseconds (None: a trace file's tick)."""
    value: Any = None
    """The output's value (false), or the trigger condition's (true)."""
    kind: Literal["output", "trigger"] = "output"
    expr: str = ""
    """The source text of the output's equation or of the trigger's condition."""
    because: list[TrustCause] = msgspec.field(default_factory=list)
    """The deciding subexpressions and inputs, outermost first (depth-first)."""
    truncated: bool = False
    """``because`` was cut to its size bound (or could not be given for this tick)."""
    message: str = ""
    """A trigger's message."""
    severity: Literal["info", "warning", "error", "critical"] | None = None
    """A trigger's severity."""

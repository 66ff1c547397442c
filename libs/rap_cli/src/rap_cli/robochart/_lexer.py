"""The RoboChart/RoboArch lexer: words, numbers, strings and symbols with positions.

Comments (``//`` and ``/* */``) are dropped; an unterminated comment or string and
brackets nested deeper than :data:`MAX_NESTING` raise :class:`SourceError`, which the
parser turns into one located diagnostic.
"""

from __future__ import annotations

import re
from dataclasses import dataclass
from typing import Literal

__all__ = ["CLOSERS", "MAX_NESTING", "OPENERS", "Lexeme", "SourceError", "lex"]

MAX_NESTING = 100
"""Deepest bracket nesting (``{``, ``(``, ``[`` together) the parser accepts."""
OPENERS = {"(": ")", "[": "]", "{": "}"}
CLOSERS = frozenset(OPENERS.values())

_TOKEN_RE = re.compile(
    r"""
      (?P<space>\s+)
    | (?P<comment>//[^\n]*|/\*.*?\*/)
    | (?P<open_comment>/\*)
    | (?P<string>"(?:[^"\\\n]|\\.)*")
    | (?P<open_string>")
    | (?P<number>[0-9]+(?:\.[0-9]+)?)
    | (?P<word>[A-Za-z_][A-Za-z0-9_]*)
    | (?P<symbol>::|->|=>|==|!=|<=|>=|/\\|\\/|\S)
    """,
    re.VERBOSE | re.DOTALL,
)


@dataclass(frozen=True, slots=True)
class Lexeme:
    """One token of the source: kind, text, offsets and 1-based position."""

    kind: Literal["word", "number", "string", "symbol"]
    value: str
    start: int
    end: int
    line: int
    column: int


class SourceError(Exception):
    """A located problem found while lexing or feeding; becomes one Diagnostic."""

    def __init__(self, line: int, column: int, message: str) -> None:
        super().__init__(message)
        self.line = line
        self.column = column
        self.message = message


def lex(text: str) -> list[Lexeme]:
    """The tokens of ``text``; raises :class:`SourceError` on an unterminated comment
    or string and on nesting deeper than :data:`MAX_NESTING`."""
    out: list[Lexeme] = []
    line, line_start, depth = 1, 0, 0
    for m in _TOKEN_RE.finditer(text):
        kind, value, start = m.lastgroup, m.group(), m.start()
        column = start - line_start + 1
        if kind == "open_comment":
            raise SourceError(line, column, "comment '/*' is never closed - end it with '*/'")
        if kind == "open_string":
            raise SourceError(line, column, "string is not closed on its line - end it with '\"'")
        if kind in ("word", "number", "string", "symbol"):
            out.append(Lexeme(kind, value, start, m.end(), line, column))  # type: ignore[arg-type]
            if value in OPENERS and kind == "symbol":
                depth += 1
                if depth > MAX_NESTING:
                    raise SourceError(
                        line,
                        column,
                        f"brackets nest deeper than {MAX_NESTING} levels - "
                        "flatten the states or split the expression",
                    )
            elif value in CLOSERS and kind == "symbol":
                depth = max(depth - 1, 0)
        newlines = value.count("\n")
        if newlines:
            line += newlines
            line_start = start + value.rindex("\n") + 1
    return out

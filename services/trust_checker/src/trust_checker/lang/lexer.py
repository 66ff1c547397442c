"""Tokens of the spec language (:class:`Lexeme`: a token with its place in the source).

The lexer never stops at the first bad character: it records a :class:`Problem` and goes
on, so one run reports every lexical error. Newlines are not tokens; each token knows
whether it is the first on its line (``bol``), which the parser uses to find statement
starts when it recovers from an error.

A number directly followed by letters (``500ms``, ``2.5s``, ``10Hz``) is one ``QTY``
token: a duration or a rate, read by the parser where one is allowed. After a ``.`` a
number is always a plain integer, so ``t.0.1`` is two tuple field accesses.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Final

from trust_checker.errors import Problem

__all__ = ["DURATION_UNITS", "KEYWORDS", "Lexeme", "source_line", "tokenize"]

KEYWORDS: Final = frozenset(
    {"in", "out", "aux", "var", "if", "then", "else", "true", "false", "trigger"}
)

DURATION_UNITS: Final[dict[str, int]] = {
    "ns": 1,
    "us": 1_000,
    "ms": 1_000_000,
    "s": 1_000_000_000,
    "min": 60_000_000_000,
    "h": 3_600_000_000_000,
}

# Longest first, so "<=" wins over "<".
_PUNCT: Final = (
    "++",
    "=>",
    "||",
    "&&",
    "==",
    "!=",
    "<=",
    ">=",
    "<",
    ">",
    "+",
    "-",
    "*",
    "/",
    "%",
    "!",
    "=",
    "(",
    ")",
    "[",
    "]",
    "{",
    "}",
    ",",
    ":",
    ".",
    "@",
)

_MAX_INT_DIGITS: Final = 40  # longer is out of range anyway; int() of huge text is slow

_ESCAPES: Final = {"n": "\n", "t": "\t", '"': '"', "\\": "\\"}


@dataclass(frozen=True, slots=True)
class Lexeme:
    """One token of a spec. ``kind`` is ``NAME``, ``INT``, ``FLOAT``, ``STR``, ``QTY``,
    ``EOF``, a keyword or the punctuation itself (``"("``, ``"<="``). ``value`` is the
    int, float or decoded string; for ``QTY`` it is ``(number, unit)``."""

    kind: str
    text: str
    line: int
    col: int
    bol: bool
    value: object = None
    start: int = 0
    """Offset of the token's first character in the source (``end``: one past its last)."""
    end: int = 0


def source_line(text: str, line: int) -> str:
    """Line ``line`` (1-based) of ``text``, without its end of line ("" past the end)."""
    lines = text.splitlines()
    return lines[line - 1].rstrip() if 1 <= line <= len(lines) else ""


def _is_name_start(ch: str) -> bool:
    return ch.isascii() and (ch.isalpha() or ch == "_")


def _is_name_char(ch: str) -> bool:
    return ch.isascii() and (ch.isalnum() or ch == "_")


class _Lexer:
    def __init__(self, text: str, path: str) -> None:
        self.text = text
        self.path = path
        self.i = 0
        self.line = 1
        self.col = 1
        self.tokens: list[Lexeme] = []
        self.problems: list[Problem] = []
        self.last_line = 0  # line of the last token emitted (for ``bol``)

    def problem(self, line: int, col: int, message: str, hint: str) -> None:
        self.problems.append(
            Problem(self.path, line, col, message, source_line(self.text, line), hint)
        )

    def advance(self, n: int = 1) -> None:
        for _ in range(n):
            if self.text[self.i] == "\n":
                self.line += 1
                self.col = 1
            else:
                self.col += 1
            self.i += 1

    def emit(self, kind: str, text: str, line: int, col: int, value: object = None) -> None:
        bol = line != self.last_line
        start = self.i - len(text)
        self.tokens.append(Lexeme(kind, text, line, col, bol, value, start, self.i))
        self.last_line = line

    def run(self) -> None:
        text = self.text
        while self.i < len(text):
            ch = text[self.i]
            if ch in " \t\r\n\f":
                self.advance()
            elif text.startswith("//", self.i):
                while self.i < len(text) and text[self.i] != "\n":
                    self.advance()
            elif text.startswith("(*", self.i):
                self.block_comment()
            elif ch == '"':
                self.string()
            elif "0" <= ch <= "9":
                self.number()
            elif _is_name_start(ch):
                self.name()
            else:
                self.punct()
        self.emit("EOF", "", self.line, self.col)

    def block_comment(self) -> None:
        line, col = self.line, self.col
        end = self.text.find("*)", self.i + 2)
        if end < 0:
            self.problem(line, col, "unterminated comment '(*'", "close the comment with '*)'")
            self.advance(len(self.text) - self.i)
            return
        self.advance(end + 2 - self.i)

    def string(self) -> None:
        line, col, start = self.line, self.col, self.i
        self.advance()
        out: list[str] = []
        while True:
            if self.i >= len(self.text) or self.text[self.i] == "\n":
                self.problem(
                    line,
                    col,
                    f"unterminated string {self.text[start : self.i]}",
                    'close it with " on the same line (write \\n for a line break)',
                )
                break  # still a string token, so the parser does not trip over it
            ch = self.text[self.i]
            if ch == '"':
                self.advance()
                break
            if ch == "\\":
                nxt = self.text[self.i + 1 : self.i + 2]
                if nxt in _ESCAPES:
                    out.append(_ESCAPES[nxt])
                    self.advance(2)
                    continue
                self.problem(
                    self.line,
                    self.col,
                    f"unknown escape '\\{nxt}' in a string",
                    'the escapes are \\n, \\t, \\" and \\\\ (write \\\\ for a backslash)',
                )
                self.advance(2 if nxt and nxt != "\n" else 1)
                continue
            out.append(ch)
            self.advance()
        self.emit("STR", self.text[start : self.i], line, col, "".join(out))

    def number(self) -> None:
        line, col, start = self.line, self.col, self.i
        text = self.text
        while self.i < len(text) and "0" <= text[self.i] <= "9":
            self.advance()
        after_dot = (
            bool(self.tokens)
            and self.tokens[-1].kind == "."
            and (self.tokens[-1].line == line and self.tokens[-1].col == col - 1)
        )
        if after_dot:  # t.0 : a tuple field, never a float
            digits = text[start : self.i]
            self.emit("INT", digits, line, col, int(digits) if len(digits) <= 18 else -1)
            return
        is_float = False
        if self.i + 1 < len(text) and text[self.i] == "." and "0" <= text[self.i + 1] <= "9":
            is_float = True
            self.advance()
            while self.i < len(text) and "0" <= text[self.i] <= "9":
                self.advance()
        number = text[start : self.i]
        if self.i < len(text) and _is_name_start(text[self.i]):
            ustart = self.i
            while self.i < len(text) and _is_name_char(text[self.i]):
                self.advance()
            unit = text[ustart : self.i]
            self.emit("QTY", text[start : self.i], line, col, (number, unit))
            return
        if is_float:
            self.emit("FLOAT", number, line, col, float(number))
        elif len(number) > _MAX_INT_DIGITS:
            self.problem(
                line,
                col,
                f"integer literal {number[:24]}... does not fit in 64 bits",
                "Int is 64-bit (at most 9223372036854775807); write a Float with a dot",
            )
            self.emit("INT", number, line, col, 0)
        else:
            self.emit("INT", number, line, col, int(number))

    def name(self) -> None:
        line, col, start = self.line, self.col, self.i
        while self.i < len(self.text) and _is_name_char(self.text[self.i]):
            self.advance()
        word = self.text[start : self.i]
        self.emit(word if word in KEYWORDS else "NAME", word, line, col, word)

    def punct(self) -> None:
        line, col = self.line, self.col
        for p in _PUNCT:
            if self.text.startswith(p, self.i):
                self.advance(len(p))
                self.emit(p, p, line, col)
                return
        ch = self.text[self.i]
        hint = "remove it"
        if ch == "'":
            end = self.text.find("'", self.i + 1)
            stop = self.text.find("\n", self.i)
            if end > 0 and (stop < 0 or end < stop):
                body = self.text[self.i + 1 : end]
                self.problem(
                    line,
                    col,
                    f"'{body}' is in single quotes",
                    f'strings use double quotes: "{body}"',
                )
                self.advance(end + 1 - self.i)
                self.emit("STR", self.text[self.i - len(body) - 2 : self.i], line, col, body)
                return
            hint = 'strings use double quotes: "text"'
        elif ch == "&" or ch == "|":
            hint = f"logical operators are '{ch}{ch}'"
        self.problem(line, col, f"unexpected character {ch!r}", hint)
        self.advance()


def tokenize(text: str, path: str = "<spec>") -> tuple[list[Lexeme], list[Problem]]:
    """The tokens of ``text`` (ending with ``EOF``) and the lexical problems found."""
    lx = _Lexer(text, path)
    lx.run()
    return lx.tokens, lx.problems

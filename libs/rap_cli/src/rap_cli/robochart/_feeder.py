"""Feeding lexemes to Lark's LALR parser for ``robochart.lark``.

The feeder decides per token what the grammar sees: a word is a keyword only where the
parser accepts that keyword (else a NAME), and where the grammar asks for TEXT (an action,
condition, trigger or value) it takes every token up to the first one, at bracket depth 0,
that the grammar accepts after the text, and hands the source slice over as one TEXT
token. Syntax errors become :class:`~rap_cli.robochart._lexer.SourceError` with a message
that says what was found, what was expected and how to fix it; an unknown top-level
``word ... { ... }`` is skipped and recorded in :attr:`Feeder.skipped`.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from importlib import resources
from typing import Any

from lark import Lark, Token
from lark.common import LexerConf
from lark.exceptions import UnexpectedToken
from lark.lexer import Lexer, PatternStr
from lark.parsers.lalr_parser_state import ParseConf, ParserState
from lark.tree import Tree

from ._lexer import CLOSERS, OPENERS, Lexeme, SourceError

__all__ = ["SUFFIXES", "Feeder"]

SUFFIXES = {".rct": "rct_file", ".rac": "rac_file"}
_TEXT_WHAT = {
    "entry": "an entry action",
    "during": "a during action",
    "exit": "an exit action",
    "action": "an action",
    "condition": "a condition",
    "trigger": "a trigger",
    "probability": "a probability",
    "precondition": "a precondition",
    "postcondition": "a postcondition",
    "=": "a value",
}
# Keywords after which the feeder labels the next '{' for messages ("in state 'S'").
_BLOCK_KEYWORDS = frozenset(
    "datatype record enumeration interface platform controller stm operation module "
    "state transition function layer".split()
)
# Clause keywords that never occur in an expression: a TEXT always ends before them, so
# a clause out of order is reported where it is instead of being read as text.
_TEXT_ENDERS = frozenset(
    "entry during exit trigger probability condition action precondition postcondition "
    "from state initial final junction transition".split()
)
_CLAUSE_ORDER = ("from", "to", "trigger", "probability", "condition", "action")

# ------------------------------------------------------------------------------ grammar


class _NoLexer(Lexer):
    """Placeholder for Lark: the feeder hands tokens over itself."""

    def __init__(self, conf: LexerConf) -> None:
        self.conf = conf

    def lex(self, lexer_state: Any, parser_state: Any) -> Iterator[Token]:
        raise NotImplementedError("tokens are fed by rap_cli.robochart.parse")


@dataclass(frozen=True, slots=True)
class _Grammar:
    """The compiled grammar with its keyword and symbol terminals, and a cache of which
    terminals end a TEXT in each parser state."""

    lark: Lark
    keywords: dict[str, str]
    symbols: dict[str, str]
    display: dict[str, str]
    no_callbacks: dict[str, ParseConf[Any]]
    text_stops: dict[tuple[str, int], frozenset[str]]


@cache
def _grammar() -> _Grammar:
    """Build the LALR parser once per process (the grammar is constant)."""
    source = resources.files(__package__).joinpath("robochart.lark").read_text("utf-8")
    lark = Lark(
        source,
        parser="lalr",
        lexer=_NoLexer,
        start=list(SUFFIXES.values()),
        propagate_positions=True,
        maybe_placeholders=True,
    )
    keywords: dict[str, str] = {}
    symbols: dict[str, str] = {}
    for term in lark.terminals:
        if isinstance(term.pattern, PatternStr):
            value = term.pattern.value
            (keywords if re.fullmatch(r"[A-Za-z_]\w*", value) else symbols)[value] = term.name
    display = {name: f"'{value}'" for value, name in (keywords | symbols).items()}
    display |= {
        "NAME": "a name",
        "NUMBER": "a number",
        "STRING": "a string",
        "$END": "the end of the file",
    }
    table = lark.parse_interactive(None, start="rct_file").parser_state.parse_conf.parse_table
    no_callbacks = {start: ParseConf(table, {}, start) for start in SUFFIXES.values()}
    return _Grammar(lark, keywords, symbols, display, no_callbacks, {})


def _accepts(conf: ParseConf[Any], stack: list[Any], types: Iterable[str]) -> bool:
    """Whether the parser with state ``stack`` accepts the token types in order."""
    probe: ParserState[Any] = ParserState(conf, None, list(stack), [None] * len(stack))  # type: ignore[arg-type]
    try:
        for t in types:
            probe.feed_token(Token(t, ""), t == "$END")
    except UnexpectedToken:
        return False
    return True


# ------------------------------------------------------------------------------ feeder


class Feeder:
    """Feeds one file's tokens to the parser (see the module docstring)."""

    def __init__(self, text: str, lexemes: list[Lexeme], start: str) -> None:
        self.g = _grammar()
        self.text = text
        self.lexemes = lexemes
        self.start = start
        self.conf = self.g.no_callbacks[start]
        self.state: ParserState[Any] = self.g.lark.parse_interactive(None, start).parser_state
        self.blocks: list[tuple[str, Lexeme]] = []  # open '{' with their labels
        self.block_keyword: str | None = None
        self.block_name: str | None = None
        self.last: Lexeme | None = None
        self.last_type = ""
        self.skipped: list[tuple[int, int, str, str, str]] = []  # line, column, word, extent, hint

    def run(self) -> Tree[Token]:
        """Feed every token and the end; returns the parse tree or raises SourceError."""
        i, n = 0, len(self.lexemes)
        while i < n:
            if "TEXT" in self._choices():
                end = self._text_end(i)
                if end > i:
                    first, last = self.lexemes[i], self.lexemes[end - 1]
                    self._feed(self._token("TEXT", self.text[first.start : last.end], first, last))
                    self.last = last
                    i = end
                    continue
            lx = self.lexemes[i]
            token = self._token(self._type(lx), lx.value, lx, lx)
            try:
                self.state.feed_token(token)
            except UnexpectedToken as e:
                after = self._skippable(i, e)
                if after is None:
                    raise self._syntax_error(token, e) from None
                i = after
                continue
            self._track(lx, token.type)
            self.last = lx
            i += 1
        eof = self._end_token()
        try:
            tree: Tree[Token] = self.state.feed_token(eof, True)
        except UnexpectedToken as e:
            raise self._syntax_error(eof, e) from None
        return tree

    def _choices(self) -> dict[str, Any]:
        """The terminals (and rules) the parser has an action for in its current state."""
        return self.conf.parse_table.states[self.state.position]

    def _feed(self, token: Token) -> None:
        try:
            self.state.feed_token(token)
        except UnexpectedToken as e:  # a TEXT is only fed where it is expected
            raise self._syntax_error(token, e) from None

    def _type(self, lx: Lexeme) -> str:
        """The terminal a lexeme is in the current parser state."""
        if lx.kind == "word":
            keyword = self.g.keywords.get(lx.value)
            choices = self._choices()
            if keyword and (keyword in choices or "NAME" not in choices):
                return keyword
            return "NAME"
        if lx.kind == "symbol":
            return self.g.symbols.get(lx.value, "SYMBOL")
        return lx.kind.upper()

    @staticmethod
    def _token(type_: str, value: str, first: Lexeme, last: Lexeme) -> Token:
        return Token(
            type_,
            value,
            start_pos=first.start,
            line=first.line,
            column=first.column,
            end_line=last.line,
            end_column=last.column + len(last.value),
            end_pos=last.end,
        )

    def _end_token(self) -> Token:
        if self.last is None:
            return Token("$END", "", 0, 1, 1, 1, 1, 0)
        lx = self.last
        column = lx.column + len(lx.value)
        return Token("$END", "", lx.end, lx.line, column, lx.line, column, lx.end)

    def _stops(self) -> frozenset[str]:
        """Terminals that end a TEXT starting in the current parser state."""
        key = (self.start, self.state.position)
        stops = self.g.text_stops.get(key)
        if stops is None:
            stack = self.state.state_stack
            probe: ParserState[Any] = ParserState(self.conf, None, list(stack), [None] * len(stack))  # type: ignore[arg-type]
            probe.feed_token(Token("TEXT", ""))
            states = self.conf.parse_table.states
            stops = frozenset(t for t in states[probe.position] if t.isupper())
            self.g.text_stops[key] = stops
        return stops

    def _text_end(self, i: int) -> int:
        """Index just past the TEXT starting at lexeme ``i``."""
        stops = self._stops()
        open_: list[Lexeme] = []
        j = i
        while j < len(self.lexemes):
            lx = self.lexemes[j]
            if lx.kind == "symbol" and lx.value in CLOSERS:
                if not open_:
                    break
                opener = open_.pop()
                if OPENERS[opener.value] != lx.value:
                    raise SourceError(
                        lx.line,
                        lx.column,
                        f"found '{lx.value}' but '{opener.value}' at line {opener.line} "
                        f"column {opener.column} is still open - "
                        f"close it with '{OPENERS[opener.value]}' first",
                    )
            elif lx.kind == "symbol" and lx.value in OPENERS:
                open_.append(lx)
            elif not open_ and (self._type_in(lx, stops) or self._ends_text(lx)):
                break
            j += 1
        if open_:
            opener = open_[-1]
            raise SourceError(
                opener.line,
                opener.column,
                f"'{opener.value}' is never closed - add '{OPENERS[opener.value]}' "
                f"where {self._text_what()} ends",
            )
        return j

    @staticmethod
    def _ends_text(lx: Lexeme) -> bool:
        return lx.kind == "word" and lx.value in _TEXT_ENDERS

    def _type_in(self, lx: Lexeme, types: frozenset[str]) -> bool:
        table = self.g.keywords if lx.kind == "word" else self.g.symbols
        return lx.kind in ("word", "symbol") and table.get(lx.value) in types

    def _text_what(self) -> str:
        return _TEXT_WHAT.get(self.last.value if self.last else "", "the expression")

    def _track(self, lx: Lexeme, type_: str) -> None:
        """Keep the stack of open blocks for messages ("in state 'S'"): a block is named
        by the keyword that declared it and the name after that keyword (``state S {``),
        else by the name just before its ``{`` (a RoboArch ``monitor {``)."""
        if type_ == "LBRACE":
            if self.block_keyword:
                label = f"{self.block_keyword} '{self.block_name}'"
            else:
                label = (
                    f"'{self.last.value}'" if self.last_type == "NAME" and self.last else "block"
                )
            self.blocks.append((label, lx))
            self.block_keyword = self.block_name = None
        elif type_ == "RBRACE":
            if self.blocks:
                self.blocks.pop()
            self.block_keyword = self.block_name = None
        elif lx.value in _BLOCK_KEYWORDS and type_ != "NAME":
            self.block_keyword, self.block_name = lx.value, None
        elif type_ == "NAME" and self.block_keyword and self.block_name is None:
            self.block_name = lx.value
        self.last_type = type_

    def _skippable(self, i: int, e: UnexpectedToken) -> int | None:
        """If lexeme ``i`` starts an unknown top-level ``word ... { ... }``, record it as
        skipped and return the index after it; else None."""
        first = self.lexemes[i]
        top = self.g.keywords["interface"]
        if first.kind != "word" or self.blocks or top not in e.expected:
            return None
        depth, j = 0, i
        while j < len(self.lexemes):
            lx = self.lexemes[j]
            if lx.kind == "symbol" and lx.value == "{":
                depth += 1
            elif lx.kind == "symbol" and lx.value == "}":
                depth -= 1
                if depth < 0:
                    return None
                if depth == 0:
                    break
            elif depth == 0 and lx.kind == "symbol" and lx.value == ";":
                return None
            j += 1
        else:
            return None
        j += 1
        if j < len(self.lexemes) and self.lexemes[j].value == ";":
            j += 1
        end_line = self.lexemes[j - 1].line
        extent = (
            f"line {first.line}" if end_line == first.line else f"lines {first.line}-{end_line}"
        )
        close = difflib.get_close_matches(first.value, self._top_keywords(e), n=1)
        hint = f"did you mean '{close[0]}'?" if close else "remove it if it is not needed"
        self.skipped.append((first.line, first.column, first.value, extent, hint))
        return j

    def _top_keywords(self, e: UnexpectedToken) -> list[str]:
        """The keywords that may start a declaration where ``e`` happened."""
        names = {name: value for value, name in self.g.keywords.items()}
        return [names[t] for t in e.expected if t in names]

    def _syntax_error(self, token: Token, e: UnexpectedToken) -> SourceError:
        """Word an unexpected token for a user: what was found, what was expected."""
        stack = e.state.state_stack if e.state is not None else []
        expected = sorted(
            (t for t in e.expected if _accepts(self.conf, stack, [t])),
            key=lambda t: (t != "TEXT", t not in ("NAME", "$END"), self.g.display.get(t, t)),
        )
        names = [self._text_what() if t == "TEXT" else self.g.display.get(t, t) for t in expected]
        keywords = [n[1:-1] for n in names if re.fullmatch(r"'\w+'", n)]
        shown = names if len(names) <= 10 else [*names[:9], "..."]
        wanted = " or ".join(shown) if shown else "nothing more"
        found = _describe(token)
        where = f" in {self.blocks[-1][0]}" if self.blocks else ""
        message = f"syntax error{where}: found {found} where {wanted} is expected"
        line, column = token.line or 1, token.column or 1
        close = difflib.get_close_matches(str(token), keywords, n=1)
        if token.type == "$END" and self.blocks:
            label, opener = self.blocks[-1]
            fix = f"close the {label} opened at line {opener.line} with '}}'"
        elif (
            str(token) in _CLAUSE_ORDER
            and where.startswith(" in transition")
            and not {"'from'", "'to'"} & set(names)
        ):
            fix = f"a transition's clauses go in the order {', '.join(_CLAUSE_ORDER)}, each once"
        elif token.type in ("NAME", "SYMBOL") and close:
            fix = f"did you mean '{close[0]}'?"
        elif len(names) == 1:
            fix = f"write {names[0]} here"
        else:
            fix = f"correct or remove {found}"
        return SourceError(line, column, f"{message} - {fix}")


def _describe(token: Token) -> str:
    """A token as a message names it."""
    value = str(token)
    short = value if len(value) <= 40 else value[:37] + "..."
    if token.type == "$END":
        return "the end of the file"
    if token.type == "NAME":
        return f"name '{short}'"
    if token.type == "TEXT":
        return f"text '{' '.join(short.split())}'"
    if token.type == "NUMBER":
        return f"number {short}"
    if token.type == "STRING":
        return f"string {short}"
    return f"'{short}'"

"""Parse RoboChart (``.rct``) and RoboArch (``.rac``) text into the located syntax model.

Three stages, all without recursion on the input's nesting:

1. a lexer (:func:`_lex`) splits the text into words, numbers, strings and symbols,
   dropping ``//`` and ``/* */`` comments and keeping each token's position;
2. the tokens are fed one by one to Lark's LALR parser for ``robochart.lark``. The feeder
   decides per token what the grammar sees: a word is a keyword only where the parser
   accepts that keyword (else a NAME), and where the grammar asks for TEXT (an action,
   condition, trigger or value) the feeder takes every token up to the first one, at
   bracket depth 0, that the grammar accepts after the text, and hands the source slice
   over as one TEXT token;
3. :class:`_Build` (a non-recursive Lark transformer) turns the parse tree into
   :mod:`rap_cli.robochart.syntax` nodes.

Nothing raises on bad input: a syntax error, an unreadable or oversized file, or nesting
deeper than :data:`MAX_NESTING` becomes a :class:`~rap_cli.diagnostics.Diagnostic` that
says what was found, what was expected and how to fix it. An unknown top-level
declaration with a ``{ ... }`` body is skipped with a warning and a
:class:`~rap_cli.robochart.syntax.Note`.
"""

from __future__ import annotations

import difflib
import re
from collections.abc import Iterable, Iterator
from dataclasses import dataclass
from functools import cache
from importlib import resources
from pathlib import Path
from typing import Any, Literal

from lark import Lark, Token, Transformer_NonRecursive, v_args
from lark.common import LexerConf
from lark.exceptions import UnexpectedToken
from lark.lexer import Lexer, PatternStr
from lark.parsers.lalr_parser_state import ParseConf, ParserState
from lark.tree import Meta, Tree

from rap_cli.diagnostics import Diagnostic, Severity

from . import syntax as s

__all__ = [
    "MAX_BYTES",
    "MAX_NESTING",
    "parse_roboarch",
    "parse_robochart",
    "parse_robochart_files",
]

MAX_BYTES = 2 * 1024 * 1024
"""Largest file the parser reads; larger ones get an error diagnostic."""

MAX_NESTING = 100
"""Deepest bracket nesting (``{``, ``(``, ``[`` together) the parser accepts."""

_SUFFIXES = {".rct": "rct_file", ".rac": "rac_file"}
_OPENERS = {"(": ")", "[": "]", "{": "}"}
_CLOSERS = frozenset(_OPENERS.values())
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
_MAPLEK_STAGES = frozenset({"monitor", "analyse", "plan", "legitimate", "execute", "knowledge"})

# ------------------------------------------------------------------------------ lexer

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
class _Lexeme:
    """One token of the source: kind, text, offsets and 1-based position."""

    kind: Literal["word", "number", "string", "symbol"]
    value: str
    start: int
    end: int
    line: int
    column: int


class _SourceError(Exception):
    """A located problem found while lexing or feeding; becomes one Diagnostic."""

    def __init__(self, line: int, column: int, message: str) -> None:
        super().__init__(message)
        self.line = line
        self.column = column
        self.message = message


def _lex(text: str) -> list[_Lexeme]:
    """The tokens of ``text``; raises :class:`_SourceError` on an unterminated comment
    or string and on nesting deeper than :data:`MAX_NESTING`."""
    out: list[_Lexeme] = []
    line, line_start, depth = 1, 0, 0
    for m in _TOKEN_RE.finditer(text):
        kind, value, start = m.lastgroup, m.group(), m.start()
        column = start - line_start + 1
        if kind == "open_comment":
            raise _SourceError(line, column, "comment '/*' is never closed - end it with '*/'")
        if kind == "open_string":
            raise _SourceError(line, column, "string is not closed on its line - end it with '\"'")
        if kind in ("word", "number", "string", "symbol"):
            out.append(_Lexeme(kind, value, start, m.end(), line, column))  # type: ignore[arg-type]
            if value in _OPENERS and kind == "symbol":
                depth += 1
                if depth > MAX_NESTING:
                    raise _SourceError(
                        line,
                        column,
                        f"brackets nest deeper than {MAX_NESTING} levels - "
                        "flatten the states or split the expression",
                    )
            elif value in _CLOSERS and kind == "symbol":
                depth = max(depth - 1, 0)
        newlines = value.count("\n")
        if newlines:
            line += newlines
            line_start = start + value.rindex("\n") + 1
    return out


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
        start=list(_SUFFIXES.values()),
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
    no_callbacks = {start: ParseConf(table, {}, start) for start in _SUFFIXES.values()}
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


class _Feeder:
    """Feeds one file's tokens to the parser (see the module docstring)."""

    def __init__(self, text: str, lexemes: list[_Lexeme], start: str) -> None:
        self.g = _grammar()
        self.text = text
        self.lexemes = lexemes
        self.start = start
        self.conf = self.g.no_callbacks[start]
        self.state: ParserState[Any] = self.g.lark.parse_interactive(None, start).parser_state
        self.blocks: list[tuple[str, _Lexeme]] = []  # open '{' with their labels
        self.block_keyword: str | None = None
        self.block_name: str | None = None
        self.last: _Lexeme | None = None
        self.last_type = ""
        self.skipped: list[tuple[int, int, str, str, str]] = []  # line, column, word, extent, hint

    def run(self) -> Tree[Token]:
        """Feed every token and the end; returns the parse tree or raises _SourceError."""
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

    def _type(self, lx: _Lexeme) -> str:
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
    def _token(type_: str, value: str, first: _Lexeme, last: _Lexeme) -> Token:
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
        open_: list[_Lexeme] = []
        j = i
        while j < len(self.lexemes):
            lx = self.lexemes[j]
            if lx.kind == "symbol" and lx.value in _CLOSERS:
                if not open_:
                    break
                opener = open_.pop()
                if _OPENERS[opener.value] != lx.value:
                    raise _SourceError(
                        lx.line,
                        lx.column,
                        f"found '{lx.value}' but '{opener.value}' at line {opener.line} "
                        f"column {opener.column} is still open - "
                        f"close it with '{_OPENERS[opener.value]}' first",
                    )
            elif lx.kind == "symbol" and lx.value in _OPENERS:
                open_.append(lx)
            elif not open_ and (self._type_in(lx, stops) or self._ends_text(lx)):
                break
            j += 1
        if open_:
            opener = open_[-1]
            raise _SourceError(
                opener.line,
                opener.column,
                f"'{opener.value}' is never closed - add '{_OPENERS[opener.value]}' "
                f"where {self._text_what()} ends",
            )
        return j

    @staticmethod
    def _ends_text(lx: _Lexeme) -> bool:
        return lx.kind == "word" and lx.value in _TEXT_ENDERS

    def _type_in(self, lx: _Lexeme, types: frozenset[str]) -> bool:
        table = self.g.keywords if lx.kind == "word" else self.g.symbols
        return lx.kind in ("word", "symbol") and table.get(lx.value) in types

    def _text_what(self) -> str:
        return _TEXT_WHAT.get(self.last.value if self.last else "", "the expression")

    def _track(self, lx: _Lexeme, type_: str) -> None:
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

    def _syntax_error(self, token: Token, e: UnexpectedToken) -> _SourceError:
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
        return _SourceError(line, column, f"{message} - {fix}")


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


# ------------------------------------------------------------------------------ tree -> model


@v_args(meta=True)
class _Build(Transformer_NonRecursive[Token, Any]):
    """Parse tree -> :mod:`syntax` nodes; collects diagnostics for what parses but is
    wrong or not modelled (a second ``entry``, an unknown RoboArch block)."""

    def __init__(self, source: str, skipped: Iterable[tuple[int, int, str, str, str]]) -> None:
        super().__init__()
        self._source = source
        self.diagnostics: list[Diagnostic] = []
        self._notes: list[s.Note] = []
        for line, column, word, extent, hint in skipped:
            loc = s.Loc(source, line, column)
            message = f"'{word}' does not start a declaration RAP reads; {extent} skipped"
            self._notes.append(s.Note(loc, message))
            self._report(loc, "warning", f"{message} - {hint}")

    def _loc(self, meta: Meta | Token) -> s.Loc:
        return s.Loc(self._source, getattr(meta, "line", 1) or 1, getattr(meta, "column", 1) or 1)

    def _text(self, token: Token | None) -> s.Text | None:
        return None if token is None else s.Text(str(token), self._loc(token))

    def _report(self, loc: s.Loc, severity: Severity, message: str) -> None:
        self.diagnostics.append(Diagnostic(loc.file, loc.line, loc.column, severity, message))

    def _note(self, loc: s.Loc, message: str, fix: str) -> None:
        self._notes.append(s.Note(loc, message))
        self._report(loc, "note", f"{message} - {fix}")

    # ---- files, names, types

    def rct_file(self, meta: Meta, c: list[Any]) -> s.RcFile:
        package = c[0]
        return s.RcFile(
            package=package,
            imports=tuple(x for x in c[1:] if isinstance(x, s.Import)),
            declarations=tuple(x for x in c[1:] if not isinstance(x, s.Import)),
            notes=tuple(self._notes),
            loc=s.Loc(self._source, 1, 1),
        )

    def package(self, meta: Meta, c: list[Any]) -> str:
        return str(c[0])

    def import_(self, meta: Meta, c: list[Any]) -> s.Import:
        return s.Import("::".join(c[:-1]), c[-1] is not None, self._loc(meta))

    def import_all(self, meta: Meta, c: list[Any]) -> bool:
        return True

    def qname(self, meta: Meta, c: list[Token]) -> str:
        return "::".join(c)

    def type_name(self, meta: Meta, c: list[Any]) -> s.TypeName:
        return s.TypeName(c[0], self._loc(meta))

    def seq_type(self, meta: Meta, c: list[Any]) -> s.SeqType:
        return s.SeqType(c[0], self._loc(meta))

    def set_type(self, meta: Meta, c: list[Any]) -> s.SetType:
        return s.SetType(c[0], self._loc(meta))

    def type_param(self, meta: Meta, c: list[Any]) -> s.TypeParam:
        return s.TypeParam(str(c[0]), self._loc(meta))

    def product_type(self, meta: Meta, c: list[Any]) -> s.ProductType:
        return s.ProductType(tuple(c), self._loc(meta))

    def function_type(self, meta: Meta, c: list[Any]) -> s.FunctionType:
        return s.FunctionType(c[0], c[1], self._loc(meta))

    def primitive_type(self, meta: Meta, c: list[Any]) -> s.PrimitiveType:
        return s.PrimitiveType(str(c[0]), self._loc(meta))

    def record(self, meta: Meta, c: list[Any]) -> s.Record:
        return s.Record(str(c[1]), c[0], tuple(c[2:]), self._loc(meta))

    def field(self, meta: Meta, c: list[Any]) -> s.Field:
        return s.Field(str(c[0]), c[1], self._loc(meta))

    def enumeration(self, meta: Meta, c: list[Any]) -> s.Enumeration:
        return s.Enumeration(str(c[0]), tuple(c[1:]), self._loc(meta))

    def enum_literal(self, meta: Meta, c: list[Any]) -> s.EnumLiteral:
        return s.EnumLiteral(str(c[0]), self._loc(meta))

    # ---- members

    def event_decl(self, meta: Meta, c: list[Any]) -> s.Event:
        return s.Event(str(c[0]), c[1], self._loc(meta))

    def var_decl(self, meta: Meta, c: list[Any]) -> s.Variable:
        return s.Variable(str(c[1]), c[2], c[0] == "const", self._text(c[3]), self._loc(meta))

    def clock_decl(self, meta: Meta, c: list[Any]) -> s.Clock:
        return s.Clock(str(c[0]), self._loc(meta))

    def op_sig(self, meta: Meta, c: list[Any]) -> s.OperationSig:
        return s.OperationSig(str(c[0]), c[1] or (), self._loc(meta))

    def params(self, meta: Meta, c: list[Any]) -> tuple[s.Param, ...]:
        return tuple(c)

    def param(self, meta: Meta, c: list[Any]) -> s.Param:
        return s.Param(str(c[0]), c[1], self._loc(meta))

    def interface_use(self, meta: Meta, c: list[Any]) -> s.InterfaceUse:
        return s.InterfaceUse(c[0], c[1], self._loc(meta))

    def interface(self, meta: Meta, c: list[Any]) -> s.Interface:
        items = c[1:]
        return s.Interface(
            name=str(c[0]),
            events=_only(items, s.Event),
            variables=_only(items, s.Variable),
            operations=_only(items, s.OperationSig),
            clocks=_only(items, s.Clock),
            loc=self._loc(meta),
        )

    def platform(self, meta: Meta, c: list[Any]) -> s.RoboticPlatform:
        items = c[1:]
        return s.RoboticPlatform(
            name=str(c[0]),
            **_uses(items),
            events=_only(items, s.Event),
            variables=_only(items, s.Variable),
            operations=_only(items, s.OperationSig),
            clocks=_only(items, s.Clock),
            loc=self._loc(meta),
        )

    # ---- controllers and modules

    def controller(self, meta: Meta, c: list[Any]) -> s.Controller:
        machines: list[s.MachineRef] = []
        operations: list[s.OperationRef] = []
        for x in c[1:]:
            if isinstance(x, s.MachineRef):
                machines.append(x)
            elif isinstance(x, s.OperationRef):
                operations.append(x)
            elif isinstance(x, s.StateMachine) and x.kind == "stm":
                machines.append(s.MachineRef(x.name, "stm", None, x, x.loc))
            elif isinstance(x, s.StateMachine):
                operations.append(s.OperationRef(x.name, None, x, x.loc))
        return s.Controller(
            name=str(c[0]),
            **_uses(c[1:]),
            events=_only(c[1:], s.Event),
            variables=_only(c[1:], s.Variable),
            clocks=_only(c[1:], s.Clock),
            machines=tuple(machines),
            operations=tuple(operations),
            connections=_only(c[1:], s.Connection),
            loc=self._loc(meta),
        )

    def machine_ref(self, meta: Meta, c: list[Any]) -> s.MachineRef:
        return s.MachineRef(str(c[1]), c[0], c[2], None, self._loc(meta))

    def op_ref(self, meta: Meta, c: list[Any]) -> s.OperationRef:
        return s.OperationRef(str(c[0]), c[1], None, self._loc(meta))

    def connection(self, meta: Meta, c: list[Any]) -> s.Connection:
        (a, e), (b, f), *options = c
        flags = {flag for option in options for flag in option}
        return s.Connection(a, e, b, f, "_async" in flags, "_bidirec" in flags, self._loc(meta))

    rac_connection = connection

    def endpoint(self, meta: Meta, c: list[Token]) -> tuple[str, str]:
        return str(c[0]), str(c[1])

    def connection_option(self, meta: Meta, c: list[str]) -> set[str]:
        return set(c)

    def module(self, meta: Meta, c: list[Any]) -> s.Module:
        platforms = [x for x in c[1:] if isinstance(x, s.PlatformRef | s.RoboticPlatform)]
        for extra in platforms[1:]:
            self._report(
                extra.loc,
                "error",
                f"module '{c[0]}' has a second robotic platform - keep one platform per module",
            )
        platform = platforms[0] if platforms else None
        if isinstance(platform, s.RoboticPlatform):
            platform = s.PlatformRef(platform.name, None, platform, platform.loc)
        controllers = [
            s.ControllerRef(x.name, None, x, x.loc) if isinstance(x, s.Controller) else x
            for x in c[1:]
            if isinstance(x, s.Controller | s.ControllerRef)
        ]
        return s.Module(
            name=str(c[0]),
            platform=platform,
            controllers=tuple(controllers),
            connections=_only(c[1:], s.Connection),
            loc=self._loc(meta),
        )

    def platform_ref(self, meta: Meta, c: list[Any]) -> s.PlatformRef:
        return s.PlatformRef(str(c[0]), c[1], None, self._loc(meta))

    def controller_ref(self, meta: Meta, c: list[Any]) -> s.ControllerRef:
        return s.ControllerRef(str(c[0]), c[1], None, self._loc(meta))

    # ---- state machines

    def _machine(
        self,
        meta: Meta,
        name: Token,
        kind: Literal["stm", "operation"],
        params: Any,
        items: list[Any],
    ) -> s.StateMachine:
        return s.StateMachine(
            name=str(name),
            kind=kind,
            params=params or (),
            **_uses(items),
            variables=_only(items, s.Variable),
            events=_only(items, s.Event),
            clocks=_only(items, s.Clock),
            operations=_only(items, s.OperationRef),
            nodes=_only(items, s.State, s.Initial, s.Final, s.Junction),
            transitions=_only(items, s.Transition),
            loc=self._loc(meta),
        )

    def stm(self, meta: Meta, c: list[Any]) -> s.StateMachine:
        return self._machine(meta, c[0], "stm", None, c[1:])

    def operation(self, meta: Meta, c: list[Any]) -> s.StateMachine:
        return self._machine(meta, c[0], "operation", c[1], c[2:])

    def state(self, meta: Meta, c: list[Any]) -> s.State:
        actions: dict[str, s.Text] = {}
        for kind, text in (x for x in c[1:] if isinstance(x, tuple)):
            if kind in actions:
                self._report(
                    text.loc,
                    "error",
                    f"state '{c[0]}' has a second {kind} action (the first is at line "
                    f"{actions[kind].loc.line}) - join them with ';'",
                )
            else:
                actions[kind] = text
        return s.State(
            name=str(c[0]),
            entry=actions.get("entry"),
            during=actions.get("during"),
            exit=actions.get("exit"),
            nodes=_only(c[1:], s.State, s.Initial, s.Final, s.Junction),
            transitions=_only(c[1:], s.Transition),
            loc=self._loc(meta),
        )

    def state_action(self, meta: Meta, c: list[Any]) -> tuple[str, s.Text | None]:
        return str(c[0]), self._text(c[1])

    def initial(self, meta: Meta, c: list[Any]) -> s.Initial:
        return s.Initial(str(c[0]), self._loc(meta))

    def final(self, meta: Meta, c: list[Any]) -> s.Final:
        return s.Final(str(c[0]), self._loc(meta))

    def junction(self, meta: Meta, c: list[Any]) -> s.Junction:
        return s.Junction(str(c[1]), c[0] is not None, self._loc(meta))

    def transition(self, meta: Meta, c: list[Any]) -> s.Transition:
        name, source, target, trigger, probability, guard, action = c
        return s.Transition(
            str(name), source, target, trigger, probability, guard, action, self._loc(meta)
        )

    def trigger(self, meta: Meta, c: list[Any]) -> s.Text | None:
        return self._text(c[0])

    probability = condition = action = trigger

    # ---- functions

    def function(self, meta: Meta, c: list[Any]) -> s.FunctionDecl:
        clauses: list[tuple[str, s.Text]] = c[3] or []
        return s.FunctionDecl(
            name=str(c[0]),
            params=c[1] or (),
            result=c[2],
            preconditions=tuple(t for k, t in clauses if k == "precondition"),
            postconditions=tuple(t for k, t in clauses if k == "postcondition"),
            loc=self._loc(meta),
        )

    def function_body(self, meta: Meta, c: list[Any]) -> list[Any]:
        return c

    def function_clause(self, meta: Meta, c: list[Any]) -> tuple[str, s.Text | None]:
        return str(c[0]), self._text(c[1])

    # ---- keyword alternatives kept as strings

    def _keyword(self, meta: Meta, c: list[Token]) -> str:
        return str(c[0])

    record_kind = var_kind = use_kind = machine_ref_kind = connection_flag = _keyword
    state_action_kind = function_clause_kind = probabilistic = _keyword

    # ---- RoboArch

    def rac_file(self, meta: Meta, c: list[Any]) -> s.RacFile:
        items = c[1:]
        connections = [conn for x in items if isinstance(x, list) for conn in x]
        return s.RacFile(
            system=c[0],
            declarations=tuple(x for x in items if not isinstance(x, s.Layer | list)),
            layers=_only(items, s.Layer),
            connections=tuple(connections),
            notes=tuple(self._notes),
            loc=s.Loc(self._source, 1, 1),
        )

    def system(self, meta: Meta, c: list[Any]) -> str:
        return str(c[0])

    def rac_connections(self, meta: Meta, c: list[Any]) -> list[s.Connection]:
        return list(c)

    def layer(self, meta: Meta, c: list[Any]) -> s.Layer:
        name, layer_type, items = str(c[0]), c[1], c[2:]
        props = _only(items, s.Property)
        pattern = [v for p in props if p.key == "pattern" for v in p.values]
        for extra in pattern[1:]:
            self._report(
                extra.loc,
                "error",
                f"layer '{name}' names a second pattern '{extra.name}' - keep one",
            )
        stages = _only(items, s.LayerBlock)
        for stage in stages:
            if stage.name.lower() not in _MAPLEK_STAGES:
                self._note(
                    stage.loc,
                    f"block '{stage.name}' of layer '{name}' is not a MAPLE-K stage; "
                    "it is kept as a generic block",
                    "rename it to monitor, analyse, plan, legitimate or execute if it is one",
                )
        return s.Layer(
            name=name,
            layer_type=None if layer_type is None else str(layer_type),
            **_uses(items),
            inputs=tuple(v for p in props if p.key == "inputs" for v in p.values),
            outputs=tuple(v for p in props if p.key == "outputs" for v in p.values),
            pattern=pattern[0].name if pattern else None,
            stages=stages,
            properties=tuple(p for p in props if p.key not in ("inputs", "outputs", "pattern")),
            loc=self._loc(meta),
        )

    def layer_block(self, meta: Meta, c: list[Any]) -> s.LayerBlock:
        return s.LayerBlock(
            name=str(c[0]),
            **_uses(c[1:]),
            properties=_only(c[1:], s.Property),
            blocks=_only(c[1:], s.LayerBlock),
            loc=self._loc(meta),
        )

    def layer_property(self, meta: Meta, c: list[Any]) -> s.Property:
        return s.Property(str(c[0]), tuple(c[1:]), self._loc(meta))

    def named_value(self, meta: Meta, c: list[Any]) -> s.PropertyValue:
        return s.PropertyValue(str(c[0]), c[1], self._loc(meta))

    def hyphen_value(self, meta: Meta, c: list[Token]) -> s.PropertyValue:
        return s.PropertyValue("-".join(c), None, self._loc(meta))

    def literal_value(self, meta: Meta, c: list[Token]) -> s.PropertyValue:
        return s.PropertyValue(str(c[0]), None, self._loc(meta))


def _only(items: Iterable[Any], *types: type) -> tuple[Any, ...]:
    """The items of the given types, in order."""
    return tuple(x for x in items if isinstance(x, types))


def _uses(items: Iterable[Any]) -> dict[str, tuple[s.InterfaceUse, ...]]:
    """``uses``/``provides``/``requires`` keyword arguments from a body's items."""
    found: dict[str, list[s.InterfaceUse]] = {"uses": [], "provides": [], "requires": []}
    for x in items:
        if isinstance(x, s.InterfaceUse):
            found[x.kind].append(x)
    return {k: tuple(v) for k, v in found.items()}


# ------------------------------------------------------------------------------ API


def _too_big(source: str, size: int) -> Diagnostic:
    message = (
        f"file is {size} bytes, more than the {MAX_BYTES} bytes a RoboChart or RoboArch "
        "file may have - split it into several packages"
    )
    return Diagnostic(source, 0, 0, "error", message)


def _parse(text: str, source: str, start: str) -> tuple[Any, list[Diagnostic]]:
    """Text -> (syntax model or None, diagnostics) for the given start rule."""
    size = len(text.encode("utf-8", "surrogatepass"))
    if size > MAX_BYTES:
        return None, [_too_big(source, size)]
    text = text.removeprefix("\ufeff")
    try:
        feeder = _Feeder(text, _lex(text), start)
        tree = feeder.run()
    except _SourceError as e:
        return None, [Diagnostic(source, e.line, e.column, "error", e.message)]
    build = _Build(source, feeder.skipped)
    return build.transform(tree), build.diagnostics


def parse_robochart(text: str, source: str) -> tuple[s.RcFile | None, list[Diagnostic]]:
    """Parse one ``.rct`` file's text; ``source`` names it in locations and diagnostics.
    Returns None and an error diagnostic when the text is not valid RoboChart; a file
    that parses may still come with diagnostics (warnings for skipped declarations,
    errors such as a state's second ``entry``)."""
    result, diagnostics = _parse(text, source, "rct_file")
    return (result if isinstance(result, s.RcFile) else None), diagnostics


def parse_roboarch(text: str, source: str) -> tuple[s.RacFile | None, list[Diagnostic]]:
    """Parse one ``.rac`` file's text, like :func:`parse_robochart`."""
    result, diagnostics = _parse(text, source, "rac_file")
    return (result if isinstance(result, s.RacFile) else None), diagnostics


def parse_robochart_files(
    paths: Iterable[str | Path],
) -> tuple[list[s.RcFile | s.RacFile], list[Diagnostic]]:
    """Parse ``.rct`` and ``.rac`` files (directories: every such file below them, sorted),
    picking the language by extension. Returns the files that parsed and every
    diagnostic; a file that cannot be read or parsed is left out with an error."""
    files: list[s.RcFile | s.RacFile] = []
    diagnostics: list[Diagnostic] = []
    for path in _expand(paths):
        name = str(path)
        start = _SUFFIXES.get(path.suffix.lower())
        if start is None:
            diagnostics.append(
                Diagnostic(
                    name,
                    0,
                    0,
                    "error",
                    f"'{path.suffix or path.name}' is not a RoboChart or RoboArch file - "
                    "give .rct or .rac files",
                )
            )
            continue
        try:
            size = path.stat().st_size
            if size > MAX_BYTES:
                diagnostics.append(_too_big(name, size))
                continue
            text = path.read_text(encoding="utf-8")
        except UnicodeDecodeError as e:
            message = f"file is not UTF-8 text (byte {e.start}) - save it as UTF-8"
            diagnostics.append(Diagnostic(name, 0, 0, "error", message))
            continue
        except OSError as e:
            message = f"cannot read the file: {e.strerror or e} - check the path"
            diagnostics.append(Diagnostic(name, 0, 0, "error", message))
            continue
        result, found = _parse(text, name, start)
        diagnostics.extend(found)
        if isinstance(result, s.RcFile | s.RacFile):
            files.append(result)
    return files, diagnostics


def _expand(paths: Iterable[str | Path]) -> Iterator[Path]:
    for p in map(Path, paths):
        if p.is_dir():
            yield from sorted(q for q in p.rglob("*") if q.suffix.lower() in _SUFFIXES)
        else:
            yield p

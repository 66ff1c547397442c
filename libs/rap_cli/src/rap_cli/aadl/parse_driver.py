"""The LALR parse of an AADL token list with error recovery: each syntax error becomes a
worded, located diagnostic (the token found, what the grammar accepts there, in which
declaration), and parsing resumes after it (see :mod:`rap_cli.aadl.parse`)."""

from __future__ import annotations

import functools
from collections import deque
from copy import copy
from importlib import resources
from typing import Any

from lark import Lark, Token, Tree
from lark.exceptions import UnexpectedToken
from lark.parsers.lalr_parser_state import ParserState

from rap_cli.aadl.parse_tree import _text, _words
from rap_cli.diagnostics import Diagnostic, Severity

MAX_ERRORS = 50
"""Syntax errors reported per file before giving up on it."""

# A repair (a ';' inserted, a category assumed) stands when the parser then takes this many
# tokens; a resynchronisation (tokens skipped, stack popped) wants more: on damaged copies
# of the test fixtures, 8 finds as many of the real errors as 3 does, with a sixth of the
# spurious follow-up errors.
_REPAIR_TRIAL = 4
_RESYNC_TRIAL = 8
# where parsing may resume after an error: these keywords, or any token after a ';'
_RESUME_AT = {"END", "PUBLIC", "PRIVATE", "WITH", "PACKAGE", "PROPERTY", "ANNEX", "$END"}
_RESUME_AT |= {"FEATURES", "SUBCOMPONENTS", "CONNECTIONS", "PROPERTIES", "MODES", "FLOWS"}
_RESUME_AT |= {"CALLS", "PROTOTYPES", "REQUIRES"}
_RESUME_AT |= {"ABSTRACT", "BUS", "DATA", "DEVICE", "MEMORY", "PROCESS", "PROCESSOR"}
_RESUME_AT |= {"SUBPROGRAM", "SYSTEM", "THREAD", "VIRTUAL"}

_State = ParserState[Any]

_CATEGORIES = (
    "abstract, bus, data, device, memory, process, processor, subprogram, "
    "subprogram group, system, thread, thread group, virtual bus, virtual processor"
)
# the token that opens a list of items on the parser stack -> what such an item is called
_ITEM_OF = {
    "FEATURES": "feature declaration",
    "SUBCOMPONENTS": "subcomponent declaration",
    "CONNECTIONS": "connection declaration",
    "PROPERTIES": "property association",
    "_LBRACE": "property association",
    "MODES": "mode declaration",
    "FLOWS": "flow declaration",
    "CALLS": "call sequence",
    "PROTOTYPES": "prototype declaration",
    "WITH": "'with' clause",
    "RENAMES": "renames declaration",
    "ANNEX": "annex clause",
    "IS": "property declaration",
    "END": "closing 'end'",
}
_TERMINAL_WORDS = {
    "IDENT": "a name",
    "INTEGER": "an integer",
    "REAL": "a real number",
    "STRING": "a string",
    "ANNEX_TEXT": "'{** annex text **}'",
    "$END": "the end of the file",
}


@functools.cache
def _parser() -> Lark:
    """The compiled grammar, built once on first use (about 0.1 s)."""
    grammar = resources.files(__package__).joinpath("aadl.lark").read_text(encoding="utf-8")
    return Lark(grammar, parser="lalr", lexer="basic", propagate_positions=True)


def _at(source: str, token: Token, severity: Severity, message: str) -> Diagnostic:
    """A diagnostic at ``token``."""
    return Diagnostic(source, token.line or 0, token.column or 0, severity, message)


# ---------------------------------------------------------------- parsing with recovery


class _Driver:
    """Feeds the token list to lark's LALR parser state, one token at a time, turning
    each syntax error into a worded diagnostic and resuming after it."""

    def __init__(self, tokens: list[Token], text: str, source: str) -> None:
        self.tokens = tokens
        self.source = source
        self.errors: list[Diagnostic] = []
        last = tokens[-1] if tokens else None
        line = last.end_line or 1 if last else 1
        column = last.end_column or 1 if last else 1
        self.eof = Token("$END", "", len(text), line, column, line, column, len(text))

    def token(self, index: int) -> Token:
        """Token ``index``, or the end-of-file token past the last one."""
        return self.tokens[index] if index < len(self.tokens) else self.eof

    def run(self) -> Tree[Token] | None:
        """The parse tree, or None when there were syntax errors (in :attr:`errors`)."""
        state: _State = _parser().parse_interactive().parser_state
        history: deque[tuple[int, _State]] = deque(maxlen=3)
        index = 0
        while True:
            token = self.token(index)
            history.append((index, state.copy(deepcopy_values=False)))
            try:
                result = state.feed_token(token, token.type == "$END")
            except UnexpectedToken:
                if len(self.errors) >= MAX_ERRORS:
                    message = f"more than {MAX_ERRORS} syntax errors - fix these first"
                    self.errors.append(_at(self.source, token, "error", message))
                    return None
                resumed = self.recover(index, history)
                if resumed is None:
                    return None
                index, state = resumed
                history.clear()
                continue
            if token.type == "$END":
                return None if self.errors else _as_tree(result)
            index += 1

    # -- recovery

    def recover(self, index: int, history: deque[tuple[int, _State]]) -> tuple[int, _State] | None:
        """Report the error at token ``index``; return where and in which state to go on."""
        before = dict(history)
        pre = before[index]
        for k in (index, index - 1):
            word = self.token(k)
            if k in before and word.type == "IDENT" and "ABSTRACT" in _accepts(before[k]):
                message = f"unknown component category '{word}' - use one of {_CATEGORIES}"
                self.errors.append(_at(self.source, word, "error", message))
                # read the declaration on as an abstract one, to find the errors in it
                probe = before[k].copy(deepcopy_values=False)
                probe.feed_token(Token.new_borrow_pos("ABSTRACT", "abstract", word))
                if self.progress(probe, k + 1) >= _REPAIR_TRIAL:
                    return k + 1, probe
                return self.resync(index, pre)
        for j in (index, index - 1, index - 2):
            repaired = self.insert_semicolon(j, before.get(j))
            if repaired is not None:
                return j, repaired
        self.errors.append(self.explain(index, pre))
        return self.resync(index, pre)

    def insert_semicolon(self, j: int, state: _State | None) -> _State | None:
        """When token ``j`` starts a line and a ``;`` before it lets the parse go on,
        report the missing ``;`` and return the state after it."""
        if state is None or j < 1:
            return None
        previous, current = self.tokens[j - 1], self.token(j)
        if (current.line or 0) <= (previous.end_line or 0):
            return None
        semicolon = Token.new_borrow_pos("_SEMI", ";", previous)
        probe = state.copy(deepcopy_values=False)
        try:
            probe.feed_token(semicolon)
        except UnexpectedToken:
            return None
        if self.progress(probe, j) < _REPAIR_TRIAL:
            return None
        context = _context(state.value_stack)
        line, column = previous.end_line or 0, previous.end_column or 0
        message = f"expected ';' after the {context} - add ';' at the end of this line"
        self.errors.append(Diagnostic(self.source, line, column, "error", message))
        return probe

    def progress(
        self, state: _State, start: int, limit: int = _REPAIR_TRIAL, *, repair: bool = False
    ) -> int:
        """How many tokens from ``start`` on the parser in ``state`` takes, up to
        ``limit`` (``limit`` also when it takes the rest of the file). With ``repair``, one
        missing ``;`` at the end of a line is assumed, as the main loop would."""
        probe = state.copy(deepcopy_values=False)
        for taken, k in enumerate(range(start, min(start + limit, len(self.tokens) + 1))):
            token = self.token(k)
            saved = probe.copy(deepcopy_values=False) if repair else None
            try:
                probe.feed_token(token, token.type == "$END")
            except UnexpectedToken:
                if saved is None or k < 1 or token.line == self.tokens[k - 1].end_line:
                    return taken
                probe, repair = saved, False
                try:
                    probe.feed_token(Token.new_borrow_pos("_SEMI", ";", self.tokens[k - 1]))
                    probe.feed_token(token, token.type == "$END")
                except UnexpectedToken:
                    return taken
        return limit

    def resync(self, index: int, pre: _State) -> tuple[int, _State] | None:
        """Panic mode: skip tokens from ``index`` to the next place where a declaration
        or section may start (after a ``;``, or at a keyword such as ``end``), and pop the
        stack of ``pre`` until the parser takes the next few tokens from there."""
        table = pre.parse_conf.states
        for start in range(index, len(self.tokens) + 1):
            token = self.token(start)
            after_semicolon = start > 0 and self.tokens[start - 1].type == "_SEMI"
            if not (after_semicolon or token.type in _RESUME_AT):
                continue
            for depth in range(len(pre.state_stack), 0, -1):
                if token.type not in table[pre.state_stack[depth - 1]]:
                    continue
                stack, values = pre.state_stack[:depth], pre.value_stack[: depth - 1]
                candidate: _State = ParserState(pre.parse_conf, pre.lexer, stack, values)
                if self.progress(candidate, start, _RESYNC_TRIAL, repair=True) == _RESYNC_TRIAL:
                    return start, candidate
        return None

    # -- wording

    def explain(self, index: int, pre: _State) -> Diagnostic:
        """The diagnostic for token ``index`` rejected by the parser in state ``pre``."""
        token = self.token(index)
        accepted = _accepts(pre)
        context = _context(pre.value_stack)
        found = _found(token)
        if token.type == "$END":
            outer = next(
                (o for i in range(len(pre.value_stack)) if (o := _owner(pre.value_stack, i))), ""
            )
            message = (
                f"the file ends inside {outer or 'a declaration'} - complete it "
                f"(expected {_expected(accepted)})"
            )
        elif token.type == "IDENT" and token.lower() == "for" and _after_impl_name(pre):
            following = self.token(index + 1)
            message = (
                "'for' after an implementation name is not AADL v2 - remove "
                f"'for {following}': the name 'T.impl' already says which type it implements"
            )
        elif "IDENT" in accepted and token.value.isidentifier() and token.type != "IDENT":
            message = (
                f"'{token}' is a reserved word of AADL and cannot be used as a name "
                f"- rename it (e.g. '{token}_1')"
            )
        elif "_SEMI" in accepted:
            message = (
                f"expected ';' after the {context}, found {found} "
                "- end the declaration with ';' or remove what follows"
            )
        else:
            message = f"unexpected {found} in the {context} - expected {_expected(accepted)}"
        return _at(self.source, token, "error", message)


def _as_tree(result: object) -> Tree[Token]:
    """The parse result, which the grammar's start rule makes a tree."""
    if not isinstance(result, Tree):
        raise TypeError(f"the AADL grammar produced {type(result).__name__}, not a tree")
    return result


def _accepts(state: _State) -> set[str]:
    """The terminals the parser in ``state`` can really take next (LALR tables list some
    that only reduce and then fail)."""
    conf = copy(state.parse_conf)
    conf.callbacks = {}
    accepted: set[str] = set()
    for name in state.parse_conf.states[state.position]:
        if not name.isupper():
            continue
        probe: _State = ParserState(
            conf, state.lexer, list(state.state_stack), list(state.value_stack)
        )
        try:
            probe.feed_token(Token(name, ""), name == "$END")
        except UnexpectedToken:
            continue
        accepted.add(name)
    return accepted


def _after_impl_name(state: _State) -> bool:
    """Whether the parser has just read ``implementation T.impl``."""
    values = state.value_stack[-4:]
    return (
        len(values) == 4
        and isinstance(values[0], Token)
        and values[0].type == "IMPLEMENTATION"
        and isinstance(values[2], Token)
        and values[2].type == "DOT"
    )


def _found(token: Token) -> str:
    """``token`` as the message names what was found."""
    if token.type == "$END":
        return "the end of the file"
    if token.type == "ANNEX_TEXT":
        return "annex text"
    if token.type == "STRING":
        return f"the string {token}"
    return f"'{token}'"


def _expected(terminals: set[str]) -> str:
    """The acceptable terminals, worded, ``;`` first and names last, at most 8."""

    def rank(name: str) -> tuple[int, str]:
        if name == "_SEMI":
            return 0, name
        if name in _TERMINAL_WORDS:
            return 3, name
        return (1 if name.startswith("_") or not name.isalpha() else 2), name

    words = [_terminal_word(name) for name in sorted(terminals, key=rank)]
    if not words:
        return "nothing more"
    if len(words) > 8:
        words = [*words[:8], "..."]
    return ", ".join(words)


def _terminal_word(name: str) -> str:
    """How a message names terminal ``name``: ``'features'``, ``a name``."""
    if name in _TERMINAL_WORDS:
        return _TERMINAL_WORDS[name]
    return f"'{_parser().get_terminal(name).pattern.value}'"


def _context(stack: list[Any]) -> str:
    """Where the parser is, from its value stack: 'feature declaration in process type
    'monitor''; the innermost open list of items and the innermost declaration."""
    owner_at, owner = -1, ""
    for i in range(len(stack)):
        phrase = _owner(stack, i)
        if phrase:
            owner_at, owner = i, phrase
    item = ""
    for i in range(len(stack) - 1, owner_at, -1):
        value = stack[i]
        if isinstance(value, Token) and value.type in _ITEM_OF:
            following = stack[i + 1] if i + 1 < len(stack) else None
            if value.type == "END" and isinstance(following, Token) and following.type == "TO":
                continue
            item = _ITEM_OF[value.type]
            break
    if item and owner:
        return f"{item} in {owner}"
    if owner:
        return f"declaration of {owner}"
    return item or "top level of the file"


def _owner(stack: list[Any], i: int) -> str:
    """The declaration opened at ``stack[i]``, worded, or ''."""
    value = stack[i]
    previous = stack[i - 1] if i else None
    rest = stack[i + 1 :]
    if isinstance(value, Tree) and value.data == "category":
        if isinstance(previous, Token) and previous.type in {"TO", "RENAMES"}:
            return ""
        category = _words(value)
        if rest and isinstance(rest[0], Token) and rest[0].type == "IMPLEMENTATION":
            name = "".join(v for v in rest[1:4] if isinstance(v, Token))
            return f"{category} implementation '{name}'"
        if rest and isinstance(rest[0], Token) and rest[0].type == "IDENT":
            if isinstance(previous, Token) and previous.type == "_COLON":
                return ""
            return f"{category} type '{rest[0]}'"
        return ""
    if isinstance(value, Token) and value.type == "PACKAGE" and rest:
        if isinstance(previous, Token) and previous.type == "RENAMES":
            return ""
        name = _text(rest[0]) if isinstance(rest[0], Tree) else str(rest[0])
        return f"package '{name}'"
    if isinstance(value, Token) and value.type == "SET" and len(rest) >= 1:
        return f"property set '{rest[0]}'"
    return ""

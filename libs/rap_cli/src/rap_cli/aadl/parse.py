"""Parse AADL v2 text into the located syntax model of :mod:`rap_cli.aadl.syntax`.

:func:`parse_aadl` never raises on bad input: every problem is a :class:`Diagnostic`, and
the file is returned only when there is no error among them. The pipeline:

1. guards: a file larger than :data:`MAX_FILE_BYTES`, or with brackets nested deeper than
   :data:`MAX_NESTING`, is refused with one diagnostic (the tree walk below is recursive);
2. lexing (lark's basic lexer: keywords are reserved, case-insensitive); an unknown
   character, an unclosed string or an unclosed ``{** annex **}`` stops here, located;
3. LALR parsing, token by token through lark's parser state, so that a syntax error can be
   explained (the token found, what the grammar accepts there, in which declaration) and
   recovered from: by inserting a missing ``;`` at the end of the previous line, by
   reading an unknown category as ``abstract``, or else by skipping to the next place
   where a declaration may start (after a ``;``, at ``end`` or a section keyword) and
   popping the parser stack until the parser takes the next tokens again. A broken
   declaration thus yields one error, rarely a follow-up one, and a file up to
   :data:`MAX_ERRORS`;
4. building the syntax model from the tree, with the checks the grammar does not make
   (``end`` names, section order, malformed numbers).
"""

from __future__ import annotations

import functools
import os
from collections import deque
from collections.abc import Iterable
from copy import copy
from importlib import resources
from pathlib import Path
from typing import Any

from lark import Lark, Token, Tree
from lark.exceptions import UnexpectedCharacters, UnexpectedToken
from lark.parsers.lalr_parser_state import ParserState

from rap_cli.aadl import syntax as s
from rap_cli.diagnostics import Diagnostic, Severity

__all__ = ["MAX_ERRORS", "MAX_FILE_BYTES", "MAX_NESTING", "parse_aadl", "parse_aadl_files"]

MAX_FILE_BYTES = 2_000_000
"""Larger files are refused: real AADL packages are well under 100 KB."""
MAX_NESTING = 64
"""Deepest nesting of ``( [ { -[`` accepted (the tree walk is recursive)."""
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
_MAX_EXPONENT = 308  # integer literals beyond 1e308 are refused, not computed

_State = ParserState[Any]
_Branch = Tree[Token] | Token

_CATEGORIES = (
    "abstract, bus, data, device, memory, process, processor, subprogram, "
    "subprogram group, system, thread, thread group, virtual bus, virtual processor"
)
_OPENERS = {"_LPAR", "_LSQB", "_LBRACE", "TRANSITION_OPEN"}
_CLOSERS = {"_RPAR", "_RSQB", "_RBRACE", "TRANSITION_CLOSE"}
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
_VALUE_RULES = {
    "list_value",
    "range_value",
    "number_value",
    "string_value",
    "bool_value",
    "name_value",
    "reference_value",
    "classifier_value",
    "record_value",
    "computed_value",
}
_TYPE_RULES = {
    "bool_type",
    "string_type",
    "int_type",
    "real_type",
    "enum_type",
    "units_type",
    "classifier_type",
    "reference_type",
    "range_type",
    "record_type",
    "type_ref",
}
_FEATURE_WORDS = {"EVENT", "DATA", "PORT", "PARAMETER", "BUS", "SUBPROGRAM", "GROUP"}
_FEATURE_WORDS |= {"VIRTUAL", "ACCESS", "FEATURE"}
_DIRECTIONS: dict[str, s.Direction] = {"in": "in", "out": "out", "in out": "in out"}
_TYPE_ORDER = ("prototypes", "features", "flows", "modes", "properties", "annex_subclause")
_IMPL_ORDER = (
    *("prototypes", "subcomponents", "calls", "connections"),
    *("flows", "modes", "properties", "annex_subclause"),
)


@functools.cache
def _parser() -> Lark:
    """The compiled grammar, built once on first use (about 0.1 s)."""
    grammar = resources.files(__package__).joinpath("aadl.lark").read_text(encoding="utf-8")
    return Lark(grammar, parser="lalr", lexer="basic", propagate_positions=True)


def parse_aadl(text: str, source: str) -> tuple[s.AadlFile | None, list[Diagnostic]]:
    """Parse one AADL file's ``text``; ``source`` names it in locations and diagnostics.

    Returns the syntax model and the diagnostics; the model is None exactly when there
    is an error among the diagnostics (warnings alone leave it usable)."""
    size = len(text.encode("utf-8", errors="replace"))
    if size > MAX_FILE_BYTES:
        return None, [_too_big(source, size)]
    tokens, diagnostics = _lex(text, source)
    if not diagnostics:
        diagnostics = _check_nesting(tokens, source)
    if diagnostics:
        return None, diagnostics
    driver = _Driver(tokens, text, source)
    tree = driver.run()
    if tree is None:
        return None, driver.errors
    builder = _Builder(source)
    aadl_file = builder.file(tree)
    if any(d.severity == "error" for d in builder.diagnostics):
        return None, builder.diagnostics
    return aadl_file, builder.diagnostics


def parse_aadl_files(
    paths: Iterable[str | os.PathLike[str]],
) -> tuple[list[s.AadlFile], list[Diagnostic]]:
    """Read and parse each file; a file that cannot be read or parsed is left out of the
    result and explained in the diagnostics."""
    files: list[s.AadlFile] = []
    diagnostics: list[Diagnostic] = []
    for entry in paths:
        path = Path(entry)
        source = str(path)
        try:
            size = path.stat().st_size
            if size > MAX_FILE_BYTES:
                diagnostics.append(_too_big(source, size))
                continue
            text = _decode(path.read_bytes(), source, diagnostics)
        except OSError as exc:
            message = f"cannot read the file: {exc.strerror or exc} - check the path"
            diagnostics.append(Diagnostic(source, 0, 0, "error", message))
            continue
        parsed, found = parse_aadl(text, source)
        diagnostics.extend(found)
        if parsed is not None:
            files.append(parsed)
    return files, diagnostics


def _too_big(source: str, size: int) -> Diagnostic:
    """The refusal of a file over :data:`MAX_FILE_BYTES`."""
    message = (
        f"the file is {size} bytes, more than the {MAX_FILE_BYTES} an AADL file may have "
        "- split it into several packages"
    )
    return Diagnostic(source, 0, 0, "error", message)


def _decode(data: bytes, source: str, diagnostics: list[Diagnostic]) -> str:
    """UTF-8 text (a BOM is dropped); other bytes are read as Latin-1, with a warning."""
    try:
        return data.decode("utf-8-sig")
    except UnicodeDecodeError as exc:
        line = data[: exc.start].count(b"\n") + 1
        message = "the file is not UTF-8 text; it was read as Latin-1 - save it as UTF-8"
        diagnostics.append(Diagnostic(source, line, 1, "warning", message))
        return data.decode("latin-1")


# ---------------------------------------------------------------- lexing and guards


def _at(source: str, token: Token, severity: Severity, message: str) -> Diagnostic:
    """A diagnostic at ``token``."""
    return Diagnostic(source, token.line or 0, token.column or 0, severity, message)


def _lex(text: str, source: str) -> tuple[list[Token], list[Diagnostic]]:
    """The tokens of ``text``, or the first lexical error (an unknown character, an
    unclosed string or annex), after which nothing more can be read reliably."""
    tokens: list[Token] = []
    try:
        for token in _parser().lex(text):
            if token.type == "_LBRACE" and text.startswith("{**", token.start_pos or 0):
                message = (
                    "the annex text opened here with '{**' is never closed "
                    "- end it with '**}' followed by ';'"
                )
                return tokens, [_at(source, token, "error", message)]
            tokens.append(token)
    except UnexpectedCharacters as exc:
        char = text[exc.pos_in_stream or 0]
        if char == '"':
            message = "this string is not closed on its line - add the closing '\"'"
        else:
            message = (
                f"the character {char!r} cannot appear here in AADL text - remove it "
                "(comments start with '--', free text goes in \"strings\")"
            )
        return tokens, [Diagnostic(source, exc.line, exc.column, "error", message)]
    return tokens, []


def _check_nesting(tokens: list[Token], source: str) -> list[Diagnostic]:
    """Refuse brackets nested deeper than :data:`MAX_NESTING` (unbalanced ones are
    the parser's to report)."""
    depth = 0
    for token in tokens:
        if token.type in _OPENERS:
            depth += 1
            if depth > MAX_NESTING:
                message = (
                    f"brackets are nested more than {MAX_NESTING} levels deep here "
                    "- flatten the value"
                )
                return [_at(source, token, "error", message)]
        elif token.type in _CLOSERS:
            depth = max(0, depth - 1)
    return []


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


# ---------------------------------------------------------------- tree helpers


def _text(node: _Branch) -> str:
    """The tokens under ``node`` joined as written without spaces (``a::b.impl``)."""
    if isinstance(node, Token):
        return str(node)
    return "".join(_text(child) for child in node.children)


def _words(node: Tree[Token]) -> str:
    """Keyword tokens as lower-case words (``thread group``, ``in out``)."""
    return " ".join(str(c).lower() for c in node.children if isinstance(c, Token))


def _owner_text(node: Tree[Token]) -> str:
    """An ``applies to`` owner of a property definition as written (``access
    connection``, ``pkg::T``), category words in lower case."""
    out = ""
    for child in node.children:
        word = str(child)
        glued = child.type in {"DCOLON", "DOT"} if isinstance(child, Token) else False
        out += word if glued or out.endswith((":", ".")) or not out else f" {word}"
    return out.lower() if ":" not in out else out


def _trees(node: Tree[Token], *names: str) -> list[Tree[Token]]:
    """The children of ``node`` that are subtrees of one of ``names``."""
    return [c for c in node.children if isinstance(c, Tree) and c.data in names]


def _tree(node: Tree[Token], name: str) -> Tree[Token] | None:
    """The first child subtree ``name`` of ``node``, or None."""
    found = _trees(node, name)
    return found[0] if found else None


def _toks(node: Tree[Token], *types: str) -> list[Token]:
    """The children of ``node`` that are tokens of one of ``types``."""
    return [c for c in node.children if isinstance(c, Token) and c.type in types]


def _has(node: Tree[Token], kind: str) -> bool:
    """Whether ``node`` has a token of ``kind`` among its children."""
    return bool(_toks(node, kind))


# ---------------------------------------------------------------- building the model


class _Builder:
    """Turns the parse tree into :mod:`syntax` nodes, collecting notes (what is skipped)
    and diagnostics (what the grammar cannot check)."""

    def __init__(self, source: str) -> None:
        self.source = source
        self.notes: list[s.Note] = []
        self.diagnostics: list[Diagnostic] = []

    def loc(self, node: _Branch) -> s.Loc:
        """Where ``node`` starts (its first token, keywords included)."""
        if isinstance(node, Token):
            return s.Loc(self.source, node.line or 0, node.column or 0)
        meta = node.meta
        return s.Loc(self.source, getattr(meta, "line", 0), getattr(meta, "column", 0))

    def report(self, node: _Branch, severity: Severity, message: str) -> None:
        """A diagnostic at ``node``."""
        loc = self.loc(node)
        self.diagnostics.append(Diagnostic(self.source, loc.line, loc.column, severity, message))

    def note(self, node: _Branch, message: str) -> None:
        """Record, at ``node``, something read but not modelled."""
        self.notes.append(s.Note(self.loc(node), message))

    def check_end(self, written: list[Token], end: list[Token], what: str) -> None:
        """``end X;`` must repeat the declared name (in any case)."""
        name, closing = "".join(written), "".join(end)
        if s.norm(name) != s.norm(closing):
            message = f"'end {closing};' does not close {what} '{name}' - write 'end {name};'"
            self.report(end[0], "error", message)

    # -- files, packages, classifiers

    def file(self, tree: Tree[Token]) -> s.AadlFile:
        """The whole file; notes sorted by place."""
        packages = tuple(self.package(t) for t in _trees(tree, "package"))
        sets = tuple(self.property_set(t) for t in _trees(tree, "property_set"))
        notes = tuple(sorted(self.notes, key=lambda n: (n.loc.line, n.loc.column)))
        return s.AadlFile(self.source, packages, sets, notes)

    def package(self, tree: Tree[Token]) -> s.Package:
        """A package; the withs of both sections are merged, in order."""
        start, end = _trees(tree, "pkg_name")
        name = _text(start)
        self.check_end(_toks(start, "IDENT", "DCOLON"), _toks(end, "IDENT", "DCOLON"), "package")
        withs: list[str] = []
        renames: list[s.Renames] = []
        sections: dict[str, list[s.Declaration]] = {"public_section": [], "private_section": []}
        for section in _trees(tree, "public_section", "private_section"):
            for item in _trees(section, "with_clause", "renames"):
                if item.data == "with_clause":
                    withs += [_text(n) for n in _trees(item, "pkg_name")]
                elif item.data == "renames":
                    renames.append(self.renames(item))
            for child in _trees(section, "component_type", "component_impl", "annex_library"):
                if child.data == "component_type":
                    sections[section.data].append(self.component_type(child))
                elif child.data == "component_impl":
                    sections[section.data].append(self.component_impl(child))
                else:
                    annex = _toks(child, "IDENT")[0]
                    message = (
                        f"annex library {annex} of package {name} skipped: "
                        "RAP does not read annexes"
                    )
                    self.note(child, message)
        properties = self.properties(_tree(tree, "properties"))
        return s.Package(
            self.loc(tree),
            name,
            tuple(withs),
            tuple(renames),
            tuple(sections["public_section"]),
            tuple(sections["private_section"]),
            properties,
        )

    def renames(self, tree: Tree[Token]) -> s.Renames:
        """One of the four renames forms."""
        idents = _toks(tree, "IDENT")
        if _has(tree, "ALL"):
            parts = [c for c in tree.children if isinstance(c, Token)][1:-2]
            return s.Renames(self.loc(tree), None, "all", "".join(parts))
        package = _tree(tree, "pkg_name")
        if package is not None:
            return s.Renames(self.loc(tree), str(idents[0]), "package", _text(package))
        category = _tree(tree, "category")
        kind = _words(category) if category is not None else "feature group"
        target = _tree(tree, "classifier_ref")
        return s.Renames(self.loc(tree), str(idents[0]), kind, _text(target) if target else "")

    def component_type(self, tree: Tree[Token]) -> s.ComponentType:
        """A component type and its sections."""
        category = _words(_trees(tree, "category")[0])
        idents = _toks(tree, "IDENT")
        name = str(idents[0])
        owner = f"{category} type '{name}'"
        self.check_end([idents[0]], [idents[-1]], f"the {category} type")
        extends = _tree(tree, "classifier_ref")
        self.check_order(tree, _TYPE_ORDER, owner)
        features = [
            self.feature(f) for sec in _trees(tree, "features") for f in _trees(sec, "feature")
        ]
        modes, transitions, requires = self.modes(tree)
        return s.ComponentType(
            self.loc(tree),
            category,
            name,
            _text(extends) if extends is not None else None,
            tuple(features),
            modes,
            transitions,
            requires,
            self.section_properties(tree),
            self.skipped(tree, owner),
        )

    def component_impl(self, tree: Tree[Token]) -> s.ComponentImpl:
        """A component implementation and its sections."""
        category = _words(_trees(tree, "category")[0])
        idents = _toks(tree, "IDENT")
        type_name, impl_name = str(idents[0]), str(idents[1])
        name = f"{type_name}.{impl_name}"
        owner = f"{category} implementation '{name}'"
        self.check_end(idents[:2], idents[-2:], f"the {category} implementation")
        extends = _tree(tree, "classifier_ref")
        self.check_order(tree, _IMPL_ORDER, owner)
        subcomponents = [
            self.subcomponent(c)
            for sec in _trees(tree, "subcomponents")
            for c in sec.children
            if isinstance(c, Tree)
        ]
        connections = [
            self.connection(c)
            for sec in _trees(tree, "connections")
            for c in sec.children
            if isinstance(c, Tree)
        ]
        modes, transitions, requires = self.modes(tree)
        if requires:
            message = (
                f"'requires modes' in {owner} - AADL v2 allows it in component types only; "
                "declare the modes with 'modes'"
            )
            self.report(tree, "warning", message)
        return s.ComponentImpl(
            self.loc(tree),
            category,
            name,
            type_name,
            impl_name,
            _text(extends) if extends is not None else None,
            tuple(subcomponents),
            tuple(connections),
            modes,
            transitions,
            self.section_properties(tree),
            self.skipped(tree, owner),
        )

    def check_order(self, tree: Tree[Token], order: tuple[str, ...], owner: str) -> None:
        """Warn about sections out of the standard's order, or repeated."""
        last = -1
        seen: set[str] = set()
        for section in tree.children:
            if not isinstance(section, Tree) or section.data not in order:
                continue
            rank = order.index(section.data)
            word = "annex" if section.data == "annex_subclause" else section.data
            if section.data in seen and section.data != "annex_subclause":
                message = f"a second '{word}' section in {owner} - merge it into the first"
                self.report(section, "warning", message)
            elif rank < last:
                sequence = ", ".join(o.replace("_subclause", "") for o in order)
                message = (
                    f"the '{word}' section of {owner} is out of order "
                    f"- AADL v2 orders sections as {sequence}"
                )
                self.report(section, "warning", message)
            seen.add(section.data)
            last = max(last, rank)

    def skipped(self, tree: Tree[Token], owner: str) -> int:
        """Note the sections RAP does not model (``none`` ones need no note); return the
        number of flow declarations."""
        flows = 0
        counted = {"flows": "flow", "calls": "call_sequence", "prototypes": "prototype"}
        what = {"flows": "flow declaration", "calls": "call sequence", "prototypes": "prototype"}
        for section in tree.children:
            if not isinstance(section, Tree):
                continue
            if section.data in counted:
                count = len(_trees(section, counted[section.data]))
                flows += count if section.data == "flows" else 0
                if count:
                    kind = what[section.data]
                    message = (
                        f"{count} {kind}(s) of {owner} skipped: RAP does not model {section.data}"
                    )
                    self.note(section, message)
            elif section.data == "annex_subclause" and not _has(section, "NONE"):
                annex = _toks(section, "IDENT")[0]
                self.note(section, f"annex {annex} of {owner} skipped: RAP does not read annexes")
        return flows

    # -- features, subcomponents, connections, modes

    def feature(self, tree: Tree[Token]) -> s.Feature:
        """A feature; its kind is its keywords less direction and access."""
        name = _toks(tree, "IDENT")[0]
        direction = _tree(tree, "direction")
        access = _toks(tree, "PROVIDES", "REQUIRES")
        classifier = _tree(tree, "classifier_ref")
        return s.Feature(
            self.loc(name),
            str(name),
            " ".join(str(t).lower() for t in _toks(tree, *_FEATURE_WORDS)),
            _DIRECTIONS[_words(direction)] if direction is not None else None,
            ("provides" if access[0].type == "PROVIDES" else "requires") if access else None,
            _text(classifier) if classifier is not None else None,
            self.dims(tree),
            self.block(tree),
            _has(tree, "REFINED"),
            _has(tree, "INVERSE"),
        )

    def dims(self, tree: Tree[Token]) -> tuple[str, ...]:
        """Array sizes as written, ``''`` for ``[]``."""
        dims = _tree(tree, "array_dims")
        return tuple(_text(d) for d in _trees(dims, "array_dim")) if dims is not None else ()

    def subcomponent(self, tree: Tree[Token]) -> s.Subcomponent:
        """A subcomponent."""
        name = _toks(tree, "IDENT")[0]
        classifier = _tree(tree, "classifier_ref")
        return s.Subcomponent(
            self.loc(name),
            str(name),
            _words(_trees(tree, "category")[0]),
            _text(classifier) if classifier is not None else None,
            self.dims(tree),
            self.in_modes(tree),
            self.block(tree),
            _has(tree, "REFINED"),
        )

    def connection(self, tree: Tree[Token]) -> s.Connection:
        """A connection, named or not."""
        name = _toks(tree, "IDENT")
        source, dest = _trees(tree, "element_path")
        return s.Connection(
            self.loc(tree),
            str(name[0]) if name else None,
            _words(_trees(tree, "connection_kind")[0]),
            _text(source),
            _text(dest),
            _has(tree, "BIARROW"),
            self.in_modes(tree),
            self.block(tree),
        )

    def in_modes(self, tree: Tree[Token]) -> tuple[str, ...]:
        """The modes of ``in modes (..)``; of a mapping ``m => sm`` the owner's ``m``."""
        modes = _tree(tree, "in_modes")
        if modes is None:
            return ()
        return tuple(str(_toks(ref, "IDENT")[0]) for ref in _trees(modes, "mode_ref"))

    def modes(
        self, tree: Tree[Token]
    ) -> tuple[tuple[s.Mode, ...], tuple[s.ModeTransition, ...], bool]:
        """Modes, transitions, and whether they are ``requires modes``."""
        modes: list[s.Mode] = []
        transitions: list[s.ModeTransition] = []
        requires = False
        for section in _trees(tree, "modes"):
            requires = requires or _has(section, "REQUIRES")
            for item in _trees(section, "mode"):
                name = _toks(item, "IDENT")[0]
                modes.append(
                    s.Mode(self.loc(name), str(name), _has(item, "INITIAL"), self.block(item))
                )
            transitions += [self.transition(t) for t in _trees(section, "mode_transition")]
        return tuple(modes), tuple(transitions), requires

    def transition(self, tree: Tree[Token]) -> s.ModeTransition:
        """A mode transition, named or not."""
        sources = _trees(tree, "transition_sources")[0]
        idents = _toks(tree, "IDENT")  # [name,] destination
        return s.ModeTransition(
            self.loc(tree),
            str(idents[0]) if len(idents) == 2 else None,
            tuple(str(t) for t in _toks(sources, "IDENT")),
            tuple(_text(p) for p in _trees(tree, "element_path")),
            str(idents[-1]),
            self.block(tree),
        )

    # -- property associations and values

    def section_properties(self, tree: Tree[Token]) -> tuple[s.PropertyAssociation, ...]:
        """The associations of all ``properties`` sections of a classifier."""
        found: list[s.PropertyAssociation] = []
        for section in _trees(tree, "properties"):
            found += self.properties(section)
        return tuple(found)

    def properties(self, section: Tree[Token] | None) -> tuple[s.PropertyAssociation, ...]:
        """The associations of one ``properties`` section or ``{ }`` block."""
        if section is None:
            return ()
        return tuple(self.association(a) for a in _trees(section, "property_association"))

    def block(self, tree: Tree[Token]) -> tuple[s.PropertyAssociation, ...]:
        """The inline ``{ }`` associations of an element."""
        return self.properties(_tree(tree, "prop_block"))

    def association(self, tree: Tree[Token]) -> s.PropertyAssociation:
        """One property association."""
        value = next(c for c in tree.children if isinstance(c, Tree) and c.data in _VALUE_RULES)
        applies = _tree(tree, "applies_to")
        binding = _tree(tree, "in_binding")
        return s.PropertyAssociation(
            self.loc(tree),
            _text(_trees(tree, "property_name")[0]),
            self.value(value),
            tuple(_text(p) for p in _trees(applies, "element_path")) if applies else (),
            _has(tree, "APPEND"),
            _has(tree, "CONSTANT"),
            self.in_modes(tree),
            tuple(_text(c) for c in _trees(binding, "classifier_ref")) if binding else (),
        )

    def value(self, tree: Tree[Token]) -> s.PropertyValue:
        """A property value of any kind."""
        loc = self.loc(tree)
        kind = tree.data
        if kind == "number_value":
            return self.number(tree)
        if kind == "list_value":
            return s.ListValue(loc, tuple(self.value(c) for c in _trees(tree, *_VALUE_RULES)))
        if kind == "range_value":
            bounds = [self.value(c) for c in _trees(tree, *_VALUE_RULES)]
            return s.RangeValue(loc, bounds[0], bounds[1], bounds[2] if len(bounds) > 2 else None)
        if kind == "string_value":
            return s.StringValue(loc, str(tree.children[0])[1:-1].replace('""', '"'))
        if kind == "bool_value":
            return s.BoolValue(loc, _has(tree, "TRUE"))
        if kind == "name_value":
            text = _text(tree)
            return s.NameValue(loc, text) if "::" in text else s.EnumValue(loc, text)
        if kind == "reference_value":
            return s.ReferenceValue(loc, _text(_trees(tree, "element_path")[0]))
        if kind == "classifier_value":
            return s.ClassifierValue(loc, _text(_trees(tree, "classifier_ref")[0]))
        if kind == "record_value":
            fields = []
            for field in _trees(tree, "record_field"):
                name = _toks(field, "IDENT")[0]
                inner = _trees(field, *_VALUE_RULES)[0]
                fields.append(s.RecordField(self.loc(name), str(name), self.value(inner)))
            return s.RecordValue(loc, tuple(fields))
        # computed_value: compute ( function )
        return s.ComputedValue(loc, "".join(str(t) for t in _toks(tree, "IDENT", "DCOLON")))

    def number(self, tree: Tree[Token]) -> s.IntValue | s.RealValue:
        """A signed number with the unit written after it."""
        loc = self.loc(tree)
        negative = _has(tree, "MINUS")
        unit_tokens = _toks(tree, "IDENT")
        unit = str(unit_tokens[0]) if unit_tokens else None
        reals = _toks(tree, "REAL")
        if reals:
            real = float(str(reals[0]).replace("_", ""))
            return s.RealValue(loc, -real if negative else real, unit)
        literal = _toks(tree, "INTEGER")[0]
        integer = self.integer(literal)
        return s.IntValue(loc, -integer if negative else integer, unit)

    def integer(self, token: Token) -> int:
        """An AADL integer literal: ``1_000``, ``1e3``, ``16#FF#``, ``2#1010#e2``."""
        text = str(token).replace("_", "").lower()
        if "#" in text:
            base_text, digits, tail = text.split("#")
            base, exponent = int(base_text), int(tail[1:].lstrip("+") or 0) if tail else 0
        else:
            digits, _, tail = text.partition("e")
            base, exponent = 10, int(tail.lstrip("+") or 0)
        if not 2 <= base <= 16 or exponent > _MAX_EXPONENT:
            message = (
                f"the integer {token} is out of range "
                f"- use a base from 2 to 16 and an exponent up to {_MAX_EXPONENT}"
            )
            self.report(token, "error", message)
            return 0
        scale: int = base**exponent
        try:
            return int(digits, base) * scale
        except ValueError:
            message = f"'{digits}' are not digits of base {base} - fix the literal {token}"
            self.report(token, "error", message)
            return 0

    # -- property sets

    def property_set(self, tree: Tree[Token]) -> s.PropertySet:
        """A property set: its types, definitions and constants."""
        idents = _toks(tree, "IDENT")
        self.check_end([idents[0]], [idents[-1]], "the property set")
        withs = [_text(n) for w in _trees(tree, "with_clause") for n in _trees(w, "pkg_name")]
        types = []
        for decl in _trees(tree, "property_type"):
            name = _toks(decl, "IDENT")[0]
            spec = _trees(decl, *_TYPE_RULES)[0]
            types.append(s.PropertyTypeDecl(self.loc(name), str(name), self.ptype(spec)))
        definitions = [self.definition(d) for d in _trees(tree, "property_definition")]
        constants = []
        for decl in _trees(tree, "property_constant"):
            name = _toks(decl, "IDENT")[0]
            spec = _trees(decl, *_TYPE_RULES)[0]
            value = _trees(decl, *_VALUE_RULES)[0]
            depth = len(_trees(decl, "list_of"))
            constant = s.PropertyConstant(
                self.loc(name), str(name), self.ptype(spec), self.value(value), depth
            )
            constants.append(constant)
        return s.PropertySet(
            self.loc(tree),
            str(idents[0]),
            tuple(withs),
            tuple(types),
            tuple(definitions),
            tuple(constants),
        )

    def definition(self, tree: Tree[Token]) -> s.PropertyDefinition:
        """A property definition."""
        name = _toks(tree, "IDENT")[0]
        default = _trees(tree, *_VALUE_RULES)
        return s.PropertyDefinition(
            self.loc(name),
            str(name),
            self.ptype(_trees(tree, *_TYPE_RULES)[0]),
            len(_trees(tree, "list_of")),
            _has(tree, "INHERIT"),
            self.value(default[0]) if default else None,
            tuple(_owner_text(o) for o in _trees(tree, "owner")),
        )

    def ptype(self, tree: Tree[Token]) -> s.PropertyType:
        """A property type, inline or named."""
        loc = self.loc(tree)
        kind = tree.data
        if kind == "type_ref":
            return s.PropertyType(loc, "named", name=_text(tree))
        if kind in {"int_type", "real_type"}:
            bounds = _tree(tree, "type_range")
            low = high = None
            if bounds is not None:
                low, high = (self.value(b) for b in _trees(bounds, *_VALUE_RULES))
            units_name: str | None = None
            units: tuple[s.UnitLiteral, ...] = ()
            spec = _tree(tree, "units_spec")
            if spec is not None:
                named = _tree(spec, "type_ref")
                units_name = _text(named) if named is not None else None
                units = self.units(_tree(spec, "units_list"))
            base = "aadlinteger" if kind == "int_type" else "aadlreal"
            return s.PropertyType(loc, base, units_name=units_name, units=units, low=low, high=high)
        if kind == "units_type":
            return s.PropertyType(loc, "units", units=self.units(_tree(tree, "units_list")))
        if kind == "enum_type":
            literals = tuple(str(t) for t in _toks(tree, "IDENT"))
            return s.PropertyType(loc, "enumeration", enumerators=literals)
        if kind in {"classifier_type", "reference_type"}:
            owners = tuple(_owner_text(o) for o in _trees(tree, "owner"))
            return s.PropertyType(loc, kind.removesuffix("_type"), owners=owners)
        if kind == "range_type":
            element = self.ptype(_trees(tree, *_TYPE_RULES)[0])
            return s.PropertyType(loc, "range", element=element)
        if kind == "record_type":
            fields = []
            for field in _trees(tree, "record_field_decl"):
                name = _toks(field, "IDENT")[0]
                ftype = self.ptype(_trees(field, *_TYPE_RULES)[0])
                depth = len(_trees(field, "list_of"))
                fields.append(s.RecordFieldType(self.loc(name), str(name), ftype, depth))
            return s.PropertyType(loc, "record", fields=tuple(fields))
        return s.PropertyType(loc, "aadlboolean" if kind == "bool_type" else "aadlstring")

    def units(self, tree: Tree[Token] | None) -> tuple[s.UnitLiteral, ...]:
        """The literals of ``units (..)``."""
        if tree is None:
            return ()
        literals = []
        for decl in _trees(tree, "unit_decl"):
            idents = _toks(decl, "IDENT")
            factor: int | float | None = None
            numbers = _toks(decl, "INTEGER", "REAL")
            if numbers:
                number = numbers[0]
                factor = (
                    self.integer(number)
                    if number.type == "INTEGER"
                    else float(str(number).replace("_", ""))
                )
            base = str(idents[1]) if len(idents) > 1 else None
            literals.append(s.UnitLiteral(self.loc(decl), str(idents[0]), base, factor))
        return tuple(literals)

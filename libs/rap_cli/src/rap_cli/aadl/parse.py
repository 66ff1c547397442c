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

Steps 1-2 live here, step 3 in :mod:`.parse_driver`, step 4 in :mod:`.parse_components`
(files, packages, classifiers) and :mod:`.parse_properties` (properties, property sets),
over the tree helpers of :mod:`.parse_tree`.
"""

from __future__ import annotations

import os
from collections.abc import Iterable
from pathlib import Path

from lark import Token
from lark.exceptions import UnexpectedCharacters

from rap_cli.aadl import syntax as s
from rap_cli.aadl.parse_components import _Builder
from rap_cli.aadl.parse_driver import MAX_ERRORS, _at, _Driver, _parser
from rap_cli.diagnostics import Diagnostic

__all__ = ["MAX_ERRORS", "MAX_FILE_BYTES", "MAX_NESTING", "parse_aadl", "parse_aadl_files"]

MAX_FILE_BYTES = 2_000_000
"""Larger files are refused: real AADL packages are well under 100 KB."""
MAX_NESTING = 64
"""Deepest nesting of ``( [ { -[`` accepted (the tree walk is recursive)."""

_OPENERS = {"_LPAR", "_LSQB", "_LBRACE", "TRANSITION_OPEN"}
_CLOSERS = {"_RPAR", "_RSQB", "_RBRACE", "TRANSITION_CLOSE"}


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

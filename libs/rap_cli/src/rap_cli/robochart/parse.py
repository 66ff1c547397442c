"""Parse RoboChart (``.rct``) and RoboArch (``.rac``) text into the located syntax model.

Three stages, all without recursion on the input's nesting:

1. a lexer (:func:`._lexer.lex`) splits the text into words, numbers, strings and symbols,
   dropping ``//`` and ``/* */`` comments and keeping each token's position;
2. the tokens are fed one by one to Lark's LALR parser for ``robochart.lark``. The feeder
   decides per token what the grammar sees: a word is a keyword only where the parser
   accepts that keyword (else a NAME), and where the grammar asks for TEXT (an action,
   condition, trigger or value) the feeder takes every token up to the first one, at
   bracket depth 0, that the grammar accepts after the text, and hands the source slice
   over as one TEXT token;
3. :class:`._build.Build` (a non-recursive Lark transformer) turns the parse tree into
   :mod:`rap_cli.robochart.syntax` nodes.

Nothing raises on bad input: a syntax error, an unreadable or oversized file, or nesting
deeper than :data:`MAX_NESTING` becomes a :class:`~rap_cli.diagnostics.Diagnostic` that
says what was found, what was expected and how to fix it. An unknown top-level
declaration with a ``{ ... }`` body is skipped with a warning and a
:class:`~rap_cli.robochart.syntax.Note`.
"""

from __future__ import annotations

from collections.abc import Iterable, Iterator
from pathlib import Path
from typing import Any

from rap_cli.diagnostics import Diagnostic

from . import syntax as s
from ._build import Build
from ._feeder import SUFFIXES, Feeder
from ._lexer import MAX_NESTING, SourceError, lex

__all__ = [
    "MAX_BYTES",
    "MAX_NESTING",
    "parse_roboarch",
    "parse_robochart",
    "parse_robochart_files",
]

MAX_BYTES = 2 * 1024 * 1024
"""Largest file the parser reads; larger ones get an error diagnostic."""

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
        feeder = Feeder(text, lex(text), start)
        tree = feeder.run()
    except SourceError as e:
        return None, [Diagnostic(source, e.line, e.column, "error", e.message)]
    build = Build(source, feeder.skipped)
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
        start = SUFFIXES.get(path.suffix.lower())
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
            yield from sorted(q for q in p.rglob("*") if q.suffix.lower() in SUFFIXES)
        else:
            yield p

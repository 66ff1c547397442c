"""The spec language: syntax tree, parser, static checks.

:func:`load_spec` is the entry point: parse, then check, and raise :class:`SpecError`
with every problem, or return a spec that may run.
"""

from __future__ import annotations

import os
import pathlib

from rap_schemas.yamlconf import read_text_file

from trust_checker.errors import SpecError, TextFileError
from trust_checker.lang.ast import Spec
from trust_checker.lang.check import Limits, check_spec, dependency_order, memory_bound
from trust_checker.lang.parser import parse_expr, parse_spec

__all__ = [
    "Limits",
    "check_spec",
    "dependency_order",
    "load_spec",
    "memory_bound",
    "parse_expr",
    "parse_spec",
    "read_source",
]


def read_source(path: str | os.PathLike[str], what: str = "spec") -> str:
    """The text of a spec or trace file (at most ``rap_schemas.limits.MAX_TEXT_BYTES``).
    Raises :class:`TextFileError` naming the file (and ``line:col`` of the first byte
    that is not UTF-8 text) and how to fix it."""
    try:
        return read_text_file(path, what=what, error=TextFileError)
    except TextFileError as exc:
        # "<where>: what; how" -> "<where>: what - how" (the form of every CLI error)
        message = str(exc)
        head, sep, rest = message.partition(": ")
        if ": cannot read the " in message:
            rest += " - check the path (and that the file is readable)"
        else:
            rest = rest.replace("; ", " - ", 1)
        raise TextFileError(
            head + sep + rest, source=exc.source, line=exc.line, column=exc.column
        ) from None


_DEFAULT_LIMITS = Limits()


def load_spec(
    source: str | os.PathLike[str],
    *,
    path: str | None = None,
    limits: Limits = _DEFAULT_LIMITS,
) -> Spec:
    """Parse and check a spec: ``source`` is a file (a :class:`pathlib.Path` or other
    path-like) or the spec text itself; a ``str`` is always text, never opened, so spec
    text from the network can go through here. ``path`` names it in errors (default: the
    file name, or ``<spec>``). Raises :class:`SpecError` listing every problem, and
    :class:`TextFileError` for a file that cannot be read (:func:`read_source`)."""
    if isinstance(source, os.PathLike):
        file = pathlib.Path(source)
        text = read_source(file, "spec")
        where = path if path is not None else str(file)
    else:
        text = str(source)
        where = path if path is not None else "<spec>"
    spec = parse_spec(text, where)
    problems = check_spec(spec, limits)
    if problems:
        raise SpecError(problems)
    return spec

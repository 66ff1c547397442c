"""The spec language: syntax tree, parser, static checks.

:func:`load_spec` is the entry point: parse, then check, and raise :class:`SpecError`
with every problem, or return a spec that may run.
"""

from __future__ import annotations

import os
import pathlib

from trust_checker.errors import SpecError
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
]

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
    file name, or ``<spec>``). Raises :class:`SpecError` listing every problem."""
    if isinstance(source, os.PathLike):
        file = pathlib.Path(source)
        text = file.read_text(encoding="utf-8")
        where = path if path is not None else str(file)
    else:
        text = str(source)
        where = path if path is not None else "<spec>"
    spec = parse_spec(text, where)
    problems = check_spec(spec, limits)
    if problems:
        raise SpecError(problems)
    return spec

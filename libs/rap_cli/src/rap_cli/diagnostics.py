"""Findings about a design or a model, each with where it is and how to fix it.

Every check, parser and importer of the ``rap`` command reports through
:class:`Diagnostic`; ``str(d)`` is the line a user reads::

    model.yaml:12:7: error: port monitor.scan carries 'Scan', which is not a message -
    declare it under messages: or use one of: ...
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass
from typing import Literal

Severity = Literal["error", "warning", "note"]

__all__ = ["Diagnostic", "Loc", "Note", "Severity", "errors", "sort_diagnostics"]

_RANK = {"error": 0, "warning": 1, "note": 2}


@dataclass(frozen=True, slots=True)
class Diagnostic:
    """One finding. ``line``/``column`` are 1-based; 0 when the finding has no place in
    the file (a missing file, a whole-model finding). ``message`` says what is wrong
    and, after `` - ``, how to fix it."""

    file: str
    line: int
    column: int
    severity: Severity
    message: str

    def __str__(self) -> str:
        where = self.file
        if self.line:
            where += f":{self.line}:{self.column or 1}"
        return f"{where}: {self.severity}: {self.message}"

    def to_json(self) -> dict[str, object]:
        return {
            "file": self.file,
            "line": self.line,
            "column": self.column,
            "severity": self.severity,
            "message": self.message,
        }


def errors(diagnostics: Iterable[Diagnostic]) -> list[Diagnostic]:
    """The errors among ``diagnostics``."""
    return [d for d in diagnostics if d.severity == "error"]


def sort_diagnostics(diagnostics: Iterable[Diagnostic]) -> list[Diagnostic]:
    """By file, then position, then severity (errors first)."""
    return sorted(diagnostics, key=lambda d: (d.file, d.line, d.column, _RANK[d.severity]))


@dataclass(frozen=True, slots=True)
class Loc:
    """Where a construct of a parsed design starts: the file as given to the parser,
    1-based line and column (characters)."""

    file: str
    line: int
    column: int

    def __str__(self) -> str:
        return f"{self.file}:{self.line}:{self.column}"


@dataclass(frozen=True, slots=True)
class Note:
    """Something a parser read but does not model (an annex, a flows section, an unknown
    block it skipped), so that nothing is dropped silently."""

    loc: Loc
    message: str

    def diagnostic(self) -> Diagnostic:
        """This note as a ``note`` diagnostic, for the same report as errors."""
        return Diagnostic(self.loc.file, self.loc.line, self.loc.column, "note", self.message)

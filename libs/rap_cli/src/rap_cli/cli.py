"""What every ``rap`` command shares: exit codes, one-line errors, the ``--format`` option."""

from __future__ import annotations

from typing import NoReturn

import typer

from .designs import FORMATS, Format

__all__ = ["FAILED", "OK", "USAGE", "failed", "format_option", "usage"]

OK, FAILED, USAGE = 0, 1, 2
"""0 ok; 1 the checked thing is wrong, or the run failed; 2 bad usage or unreadable input."""


def usage(message: str) -> NoReturn:
    """End the command with ``rap: error: <message>`` and exit code 2."""
    typer.echo(f"rap: error: {message}", err=True)
    raise typer.Exit(USAGE)


def failed(message: str) -> NoReturn:
    """End the command with ``rap: error: <message>`` and exit code 1."""
    typer.echo(f"rap: error: {message}", err=True)
    raise typer.Exit(FAILED)


def format_option(value: str | None) -> Format | None:
    """The design format ``--format`` names (None: from the file names)."""
    if value is None:
        return None
    for f in FORMATS:
        if f == value:
            return f
    usage(f"--format {value!r} is not one of {', '.join(FORMATS)} - use one of them")

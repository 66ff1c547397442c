"""Errors of the trust checker.

TrustError                    base of everything raised here
├── SpecError                 a spec that must not start (syntax, types, cycles,
│                             memory bound): one or more :class:`Problem` with
│                             file:line:col, the offending text and a hint
├── EvalError                 a run-time error in a tick (Int overflow, division by
│                             zero, a value of the wrong type): stream, tick, place
├── InputError                an input that cannot be taken (unknown stream, bad
│                             value, bad trace file line): what and where
└── TextFileError             a spec or trace file that cannot be read (missing, a
                              directory, too large, not UTF-8 text): path[:line:col]
"""

from __future__ import annotations

from dataclasses import dataclass

from rap_schemas.yamlconf import YamlError

__all__ = [
    "EXCERPT",
    "EvalError",
    "InputError",
    "Problem",
    "SpecError",
    "TextFileError",
    "TrustError",
]


class TrustError(Exception):
    """Base of the trust checker's errors."""


@dataclass(frozen=True, slots=True)
class Problem:
    """One thing wrong with a spec, at ``path:line:col``."""

    path: str
    line: int
    col: int
    message: str
    text: str = ""
    """The offending source line (shown with a caret under ``col``)."""
    hint: str = ""

    def __str__(self) -> str:
        out = f"{self.path}:{self.line}:{self.col}: {self.message}"
        if self.text:
            text, caret = _excerpt(self.text, max(self.col - 1, 0))
            out += f"\n    {text}\n    {' ' * caret}^"
        if self.hint:
            out += f"\n    hint: {self.hint}"
        return out


EXCERPT = 120
"""The most characters of a source line shown under a problem (a long line is cut
around the column, marked with '...'): a refused spec from the network never makes a
message, a log line or a status record as long as its own lines."""


def _excerpt(text: str, at: int) -> tuple[str, int]:
    """``text`` cut to at most ``EXCERPT`` characters around index ``at``, and where
    ``at`` is in the cut."""
    if len(text) <= EXCERPT:
        return text, at
    start = min(max(0, at - EXCERPT // 2), len(text) - EXCERPT)
    end = start + EXCERPT
    head = "..." if start > 0 else ""
    tail = "..." if end < len(text) else ""
    return f"{head}{text[start:end]}{tail}", at - start + len(head)


class SpecError(TrustError):
    """The spec has errors and will not run; ``problems`` lists them all."""

    def __init__(self, problems: list[Problem]) -> None:
        self.problems = list(problems)
        super().__init__("\n".join(str(p) for p in self.problems))


class EvalError(TrustError):
    """A tick could not be evaluated: ``stream`` at ``tick``, at ``pos`` of the spec."""

    def __init__(self, message: str, *, stream: str = "", tick: int = -1, where: str = "") -> None:
        self.stream, self.tick, self.where = stream, tick, where
        at = f" in {stream!r}" if stream else ""
        at += f" at tick {tick}" if tick >= 0 else ""
        at += f" ({where})" if where else ""
        super().__init__(f"{message}{at}")


class InputError(TrustError):
    """An input that cannot be taken: unknown stream, bad value, bad trace line."""


class TextFileError(TrustError, YamlError):
    """A spec or trace file that cannot be read: the message starts with the path (and
    ``line:col`` of the first byte that is not UTF-8) and says how to fix it; ``source``,
    ``line`` and ``column`` are attributes too (see
    :func:`rap_schemas.yamlconf.read_text_file`)."""

"""Trace files of the reference checker, and running a spec over one.

A trace is a sequence of numbered blocks, one per tick::

    // comments run to the end of the line
    0: x = 1
       y = 2
    1: x = 3
    3: y = "a"      // tick 2 is empty: nothing arrived

``N: var = value`` opens tick N; further ``var = value`` lines, indented, add to it.
Values are literals of the language (``-3``, ``1.5``, ``true``, ``"s"``, ``()``,
``[1, 2]``, ``Map("k": 1)``, ``{a: 1}``, ``(1, true)``), parsed by the checker's own parser.
Tick numbers increase; a number skipped (or a first block after 0) is an empty tick.

:func:`iter_trace` runs a spec over the ticks one at a time (a run-time error at tick n
comes after ticks 0..n-1 were given); :func:`load_trace` also gives the line each tick's
block starts on, so that an error can name its place in the file.
"""

from __future__ import annotations

import re
from collections.abc import Iterator
from typing import Final, NamedTuple

from trust_checker.engine import Output, SpecRunner
from trust_checker.errors import InputError, SpecError
from trust_checker.lang import ast
from trust_checker.lang.parser import parse_expr
from trust_checker.values import MapV, StructV, TupleV, console

__all__ = ["Trace", "iter_trace", "load_trace", "read_trace", "run_trace"]


class Trace(NamedTuple):
    """A trace file's ticks, and for each the line its block starts on (0 for a tick
    that no block gives: a number skipped)."""

    ticks: list[dict[str, object]]
    lines: list[int]

    def where(self, path: str, tick: int) -> str:
        """``path:line:1`` of ``tick``'s block (``path`` alone past the last block)."""
        line = self.lines[tick] if 0 <= tick < len(self.lines) else 0
        return f"{path}:{line}:1" if line else path


_HEAD: Final = re.compile(r"(\s*)(\d+)\s*:\s*")
_ASSIGN: Final = re.compile(r"([A-Za-z_][A-Za-z0-9_]*)\s*=(?!=)\s*")


def _strip_comment(line: str) -> str:
    """``line`` without a ``//`` comment (a ``//`` inside a string literal stays)."""
    in_str = escaped = False
    for i, ch in enumerate(line):
        if in_str:
            if escaped:
                escaped = False
            elif ch == "\\":
                escaped = True
            elif ch == '"':
                in_str = False
        elif ch == '"':
            in_str = True
        elif ch == "/" and line.startswith("//", i):
            return line[:i]
    return line


def _literal(e: ast.Expr, where: tuple[str, int, int]) -> object:
    """The value of a constant literal tree; :class:`InputError` for anything else."""
    if isinstance(e, ast.Lit):
        return e.value
    if isinstance(e, ast.Unary) and e.op == "-" and isinstance(e.operand, ast.Lit):
        v = e.operand.value
        if type(v) is int or type(v) is float:
            return -v
    if isinstance(e, ast.ListLit):
        return tuple(_literal(x, where) for x in e.items)
    if isinstance(e, ast.TupleLit):
        return TupleV(_literal(x, where) for x in e.items)
    if isinstance(e, ast.MapLit):
        return MapV((k, _literal(x, where)) for k, x in e.pairs)
    if isinstance(e, ast.StructLit):
        return StructV((k, _literal(x, where)) for k, x in e.fields)
    path, line, col0 = where
    col = col0 + e.pos.col - 1
    raise InputError(
        f"{path}:{line}:{col}: a trace value must be a literal (a number, true/false, "
        f'"text", (), [..], Map("k": ..), {{k: ..}} or (a, b)), found {type(e).__name__.lower()}'
        " expression"
    )


def read_trace(text: str, path: str = "<trace>") -> list[dict[str, object]]:
    """The ticks of a trace file: one dict per tick (empty: nothing arrived), input name
    to value. Raises :class:`InputError` at ``path:line:col`` for a malformed line."""
    return load_trace(text, path).ticks


def load_trace(text: str, path: str = "<trace>") -> Trace:
    """:func:`read_trace` with the line of every tick's block."""
    ticks: list[dict[str, object]] = []
    lines: list[int] = []
    current: dict[str, object] | None = None
    last = -1
    for lineno, raw in enumerate(text.splitlines(), start=1):
        line = _strip_comment(raw).rstrip()
        if not line.strip():
            continue
        col = 1
        head = _HEAD.match(line)
        if head is not None:
            n = int(head.group(2))
            if n <= last:
                raise InputError(
                    f"{path}:{lineno}:{len(head.group(1)) + 1}: tick {n} comes after tick "
                    f"{last} - tick numbers must increase (merge the two blocks, or renumber)"
                )
            ticks.extend({} for _ in range(n - last - 1))
            lines.extend(0 for _ in range(n - last - 1))
            current = {}
            ticks.append(current)
            lines.append(lineno)
            last = n
            col = head.end() + 1
            if col > len(line):  # "N:" alone: an empty tick
                continue
        elif current is None or not line[0].isspace():
            indent = len(line) - len(line.lstrip())
            raise InputError(
                f"{path}:{lineno}:{indent + 1}: expected 'N: name = value' to open a tick"
                + (" - lines that add to a tick are indented under it" if current else "")
            )
        else:
            col = len(line) - len(line.lstrip()) + 1
        assign = _ASSIGN.match(line, col - 1)
        if assign is None:
            raise InputError(
                f"{path}:{lineno}:{col}: expected 'name = value', found {line[col - 1 :]!r}"
                " - write one assignment per line, e.g. x = 1"
            )
        name = assign.group(1)
        if name in current:
            raise InputError(
                f"{path}:{lineno}:{col}: '{name}' is given twice in tick {last} - one value "
                "per stream and tick (put the second in a later tick)"
            )
        vcol = assign.end() + 1
        source = line[assign.end() :]
        try:
            expr = parse_expr(source, path)
        except SpecError as e:
            p = e.problems[0]
            raise InputError(
                f"{path}:{lineno}:{vcol + p.col - 1}: bad value {source.strip()!r}: {p.message}"
                + (f" - {p.hint}" if p.hint else " - write a literal of the language")
            ) from None
        current[name] = _literal(expr, (path, lineno, vcol))
    return Trace(ticks, lines)


def iter_trace(
    spec: ast.Spec | SpecRunner, ticks: list[dict[str, object]]
) -> Iterator[list[Output]]:
    """Run ``spec`` (or a fresh :class:`SpecRunner`) over ``ticks`` and the drain ticks
    after them: each tick's outputs, one list per tick, input ticks first. A run-time
    error raises :class:`trust_checker.errors.EvalError`, a bad input
    :class:`InputError`, at the tick that fails, after every earlier tick was yielded."""
    m = spec if isinstance(spec, SpecRunner) else SpecRunner(spec)
    for t in ticks:
        yield m.step(t)
    yield from m.drain()


def run_trace(spec: ast.Spec | SpecRunner, ticks: list[dict[str, object]]) -> list[str]:
    """:func:`iter_trace` in one go: the console lines ``name[tick] = Int(7)``."""
    return [
        f"{o.stream}[{o.tick}] = {console(o.value)}"
        for outs in iter_trace(spec, ticks)
        for o in outs
    ]

"""Reading an AADL-IL file (JSON) with where every member is.

Python's ``json`` module checks the text and builds the values but forgets positions; a
second pass (:func:`json_positions`) walks the same, already valid, text token by token
and records, for every path (``("_systemList", 0, "_processList", 2, "_name")``), the
line and column where that member starts: the key of an object member, the value of an
array item. The pass keeps its own stack, so deep nesting costs no recursion.
"""

from __future__ import annotations

import bisect
import json
import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from ..diagnostics import Diagnostic, Loc

__all__ = ["MAX_BYTES", "JsonDocument", "json_positions", "read_json"]

MAX_BYTES = 16 * 1024 * 1024
"""Largest AADL-IL file the importer reads; larger ones get an error diagnostic."""

JsonPath = tuple[str | int, ...]

_TOKEN = re.compile(
    r"""\s*(?:(?P<string>"(?:[^"\\]|\\.)*")|(?P<punct>[{}\[\],:])|(?P<atom>[^\s{}\[\],:"]+))""",
    re.DOTALL,
)


@dataclass(slots=True)
class JsonDocument:
    """A decoded JSON file: its value, and where each member starts (see
    :func:`json_positions`)."""

    source: str
    value: Any
    positions: dict[JsonPath, tuple[int, int]] = field(default_factory=dict)

    def loc(self, path: JsonPath) -> Loc:
        """Where the member at ``path`` (or its nearest enclosing member) starts."""
        while path not in self.positions and path:
            path = path[:-1]
        line, column = self.positions.get(path, (1, 1))
        return Loc(self.source, line, column)


class _Frame:
    """An open object or array of the position pass."""

    __slots__ = ("index", "is_object", "key", "path")

    def __init__(self, path: JsonPath, is_object: bool) -> None:
        self.path = path
        self.is_object = is_object
        self.key: str | None = None
        self.index = 0


def json_positions(text: str) -> dict[JsonPath, tuple[int, int]]:
    """For valid JSON ``text``: ``path -> (line, column)`` (1-based) of every member's
    start (an object member's key, an array item's value; the root at ``()``)."""
    starts = [0] + [m.end() for m in re.finditer("\n", text)]

    def position(offset: int) -> tuple[int, int]:
        line = bisect.bisect_right(starts, offset)
        return line, offset - starts[line - 1] + 1

    found: dict[JsonPath, tuple[int, int]] = {}
    stack: list[_Frame] = []
    expect_key = False

    def value_path() -> JsonPath | None:
        """The path of a value starting now; None when its member was recorded at its key."""
        if not stack:
            return ()
        top = stack[-1]
        return None if top.is_object else (*top.path, top.index)

    for m in _TOKEN.finditer(text):
        kind = m.lastgroup
        start = m.start(kind) if kind else m.start()
        token = m.group(kind) if kind else ""
        if kind == "string" and expect_key and stack:
            top = stack[-1]
            top.key = json.loads(token)
            found.setdefault((*top.path, top.key), position(start))
            expect_key = False
            continue
        if kind == "punct" and token in ",:":
            if token == "," and stack:
                if stack[-1].is_object:
                    expect_key = True
                else:
                    stack[-1].index += 1
            continue
        if kind == "punct" and token in "}]":
            stack.pop()
            expect_key = False
            continue
        if kind is None:
            continue
        path = value_path()
        if path is not None:
            found.setdefault(path, position(start))
        if kind == "punct":  # '{' or '['
            own: JsonPath = path if path is not None else (*stack[-1].path, stack[-1].key or "")
            stack.append(_Frame(own, token == "{"))
            expect_key = token == "{"
    return found


def read_json(path: Path) -> tuple[JsonDocument | None, list[Diagnostic]]:
    """Read and decode ``path``; on failure None and one located error (a file that
    cannot be read, is too big, is not UTF-8 or is not JSON)."""
    source = str(path)

    def error(message: str, line: int = 0, column: int = 0) -> tuple[None, list[Diagnostic]]:
        return None, [Diagnostic(source, line, column, "error", message)]

    try:
        size = path.stat().st_size
        if size > MAX_BYTES:
            return error(
                f"file is {size} bytes, more than the {MAX_BYTES} bytes an AADL-IL file may "
                "have - check that it is the design.json RPIO wrote"
            )
        text = path.read_text(encoding="utf-8")
    except UnicodeDecodeError as e:
        return error(f"file is not UTF-8 text (byte {e.start}) - save it as UTF-8")
    except OSError as e:
        return error(f"cannot read the file: {e.strerror or e} - check the path")
    text = text.removeprefix("\ufeff")
    try:
        value = json.loads(text)
    except json.JSONDecodeError as e:
        return error(
            f"not valid JSON: {e.msg} - fix the JSON at this point (an AADL-IL design is "
            "one JSON object)",
            e.lineno,
            e.colno,
        )
    except RecursionError:
        return error("JSON nests too deeply to read - flatten the design")
    return JsonDocument(source, value, json_positions(text)), []

"""Python source as ``ruff format`` and ``ruff check`` want it, for the generated modules.

The generator writes code that those leave as it is (RAP's own settings: line length 100,
double quotes, isort's sections), so that a generated package passes a project's lint:

- :func:`q`: a string literal, double-quoted unless the text holds more ``"`` than ``'``;
- :class:`Call` and :func:`lines`: a call, subscript or collection on one line when it
  fits, else one item a line with a trailing comma (which ruff keeps exploded); a string
  too long for its line becomes a parenthesized implicit concatenation;
- :func:`docstring`: a docstring wrapped within the line length;
- :func:`import_from`, :func:`sort_all`: imports and ``__all__`` as isort and RUF022 sort
  them;
- :func:`prune_imports`: a generated module without the imports it does not use (F401),
  its user regions included in what counts as use.
"""

from __future__ import annotations

import ast
import re
import textwrap
from collections.abc import Iterable
from dataclasses import dataclass

from .regions import REGION

__all__ = [
    "LINE",
    "Call",
    "Item",
    "docstring",
    "flat",
    "import_from",
    "lines",
    "prune_imports",
    "q",
    "sort_all",
    "split_string",
]

LINE = 100
"""The line length of the generated code (RAP's ruff setting)."""
_INDENT = "    "


def q(text: str) -> str:
    """``text`` as a Python string literal, quoted as ``ruff format`` quotes it."""
    quote = '"' if text.count('"') <= text.count("'") else "'"
    out = []
    for ch in text:
        if ch == "\\":
            out.append("\\\\")
        elif ch == quote:
            out.append("\\" + ch)
        elif ch.isprintable():
            out.append(ch)
        else:
            out.append(repr(ch)[1:-1])
    return quote + "".join(out) + quote


@dataclass(frozen=True, slots=True)
class Call:
    """``head(args)`` (or ``head[args]`` with ``brackets="[]"``); ``comma`` False for the
    parts of an implicit string concatenation."""

    head: str
    args: tuple[Item, ...]
    brackets: str = "()"
    comma: bool = True


Item = str | Call


def flat(item: Item) -> str:
    """``item`` on one line."""
    if isinstance(item, str):
        return item
    sep = ", " if item.comma else " "
    return f"{item.head}{item.brackets[0]}{sep.join(flat(a) for a in item.args)}{item.brackets[1]}"


def lines(item: Item, indent: str = "", suffix: str = "") -> list[str]:
    """``item`` at ``indent``, followed by ``suffix``: on one line when it fits in
    :data:`LINE`, else exploded one argument a line (recursively)."""
    one = f"{indent}{flat(item)}{suffix}"
    if len(one) <= LINE:
        return [one]
    if isinstance(item, str):
        split = split_string(item, indent)
        return [one] if split is None else lines(split, indent, suffix)
    out = [f"{indent}{item.head}{item.brackets[0]}"]
    inner = indent + _INDENT
    for arg in item.args:
        out += lines(arg, inner, "," if item.comma else "")
    out.append(f"{indent}{item.brackets[1]}{suffix}")
    return out


_KEYWORD = re.compile(r"^([A-Za-z_][A-Za-z0-9_]*=)(.*)$", re.DOTALL)


def split_string(item: str, indent: str) -> Call | None:
    """A string literal (``"..."`` or ``name="..."``) too long for its line, in
    parentheses, as an implicit concatenation of parts that fit (``ruff format`` keeps
    both); None when ``item`` is no plain string literal."""
    head = ""
    match = _KEYWORD.match(item)
    if match is not None:
        head, item = match.group(1), match.group(2)
    try:
        text = ast.literal_eval(item)
    except (ValueError, SyntaxError):
        return None
    if not isinstance(text, str) or item[:1] not in "\"'":
        return None
    width = LINE - len(indent) - len(_INDENT) - 2
    words = re.findall(r"\S+\s*|\s+", text)
    parts: list[str] = []
    current = ""
    for word in words:
        if current and len(q(current + word)) > width:
            parts.append(current)
            current = ""
        current += word
    if current:
        parts.append(current)
    if not parts:
        return None
    return Call(head, tuple(q(p) for p in parts), comma=False)


def docstring(text: str, indent: str) -> list[str]:
    """The docstring of ``text`` at ``indent``: one line when it fits, else wrapped; its
    paragraphs (blank lines) and its list items (lines starting ``- ``) are kept."""
    body = text.replace("\\", "\\\\").replace('"""', '\\"\\"\\"').strip()
    if not body:
        return []
    if body.endswith('"'):
        body = body[:-1] + '\\"'
    one = f'{indent}"""{body}"""'
    if len(one) <= LINE and "\n" not in body:
        return [one]
    width = LINE - len(indent)
    out: list[str] = []
    for para in body.split("\n"):
        if not para.strip():
            out.append("")
            continue
        bullet = para.lstrip().startswith("- ")
        wrapped = textwrap.wrap(
            para.strip(),
            width=width - 3,
            subsequent_indent="  " if bullet else "",
            break_long_words=False,
            break_on_hyphens=False,
        )
        out += wrapped or [""]
    out[0] = '"""' + out[0]
    if len(out[-1]) + len(indent) + 3 <= LINE:
        out[-1] += '"""'
    else:
        out.append('"""')
    return [f"{indent}{line}" if line else "" for line in out]


def _type_rank(name: str) -> int:
    if len(name) > 1 and name.isupper():
        return 0  # CONSTANTS
    return 1 if name[:1].isupper() else 2  # Classes, then everything else


def _natural(name: str) -> list[str | int]:
    return [int(p) if p.isdigit() else p for p in re.split(r"(\d+)", name)]


def sort_all(names: Iterable[str]) -> list[str]:
    """``names`` as RUF022 sorts ``__all__``: constants, classes, then the rest."""
    return sorted(set(names), key=lambda n: (_type_rank(n), _natural(n)))


def _import_key(name: str) -> tuple[int, str, str]:
    return (_type_rank(name), name.lower(), name)


def import_from(module: str, names: Iterable[str], indent: str = "") -> list[str]:
    """``from module import a, B`` with the names as isort orders them (constants,
    classes, the rest), wrapped one a line when it is too long."""
    ordered = sorted(set(names), key=_import_key)
    one = f"{indent}from {module} import {', '.join(ordered)}"
    if len(one) <= LINE:
        return [one]
    return [
        f"{indent}from {module} import (",
        *(f"{indent}{_INDENT}{n}," for n in ordered),
        f"{indent})",
    ]


def _regions(text: str) -> list[tuple[int, int]]:
    """Line ranges (1-based, inclusive) of the user regions of ``text``."""
    out: list[tuple[int, int]] = []
    start: int | None = None
    for n, line in enumerate(text.splitlines(), 1):
        stripped = line.strip()
        if stripped.startswith(REGION):
            start = n
        elif stripped.startswith("# endregion user:") and start is not None:
            out.append((start, n))
            start = None
    return out


def prune_imports(text: str) -> str:
    """``text`` (a generated module, its user regions filled in) without the names its
    top-level imports outside the regions bring and nothing uses. A module that does not
    parse is returned as it is."""
    try:
        tree = ast.parse(text)
    except SyntaxError:
        return text
    used = {n.id for n in ast.walk(tree) if isinstance(n, ast.Name)}
    for node in ast.walk(tree):
        if isinstance(node, ast.Assign) and any(
            isinstance(t, ast.Name) and t.id == "__all__" for t in node.targets
        ):
            used |= {
                e.value
                for e in ast.walk(node.value)
                if isinstance(e, ast.Constant) and isinstance(e.value, str)
            }
    inside = _regions(text)
    src = text.split("\n")
    edits: list[tuple[int, int, list[str]]] = []
    for stmt in tree.body:
        if not isinstance(stmt, ast.Import | ast.ImportFrom):
            continue
        if isinstance(stmt, ast.ImportFrom) and stmt.module == "__future__":
            continue
        first, last = stmt.lineno, stmt.end_lineno or stmt.lineno
        if any(a <= first <= b for a, b in inside):
            continue
        if any(alias.asname is not None or alias.name == "*" for alias in stmt.names):
            continue
        keep = [a.name for a in stmt.names if a.name.partition(".")[0] in used]
        if len(keep) == len(stmt.names):
            continue
        indent = src[first - 1][: len(src[first - 1]) - len(src[first - 1].lstrip())]
        if isinstance(stmt, ast.Import):
            edits.append((first, last, [f"{indent}import {name}" for name in keep]))
            continue
        module = "." * stmt.level + (stmt.module or "")
        edits.append((first, last, import_from(module, keep, indent) if keep else []))
    for first, last, new in reversed(edits):
        src[first - 1 : last] = new
        if not new and 1 < first <= len(src) and not src[first - 2].strip():
            if first - 1 < len(src) and not src[first - 1].strip():
                del src[first - 1]  # the section it was alone in: one blank line stays
    return "\n".join(src)

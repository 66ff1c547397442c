"""YAML files decoded into msgspec Structs, with errors that point at ``file:line:col``.

    doc = parse_yaml(text, "plan.yaml", what="deployment plan")
    plan = doc.convert(DeploymentPlan)      # YamlError: "plan.yaml:7:5: Object contains ..."
    raise doc.error(("components", "monitor", "node"), "compute node 'x' is not defined")

or both steps at once: ``load_yaml(text, DeploymentPlan, "plan.yaml")``.

A conversion error keeps msgspec's own message, with the path made concrete (msgspec
says ``$.components[...]`` inside a mapping; here the entry is named,
``$.components.monitor``), the offending scalar when there is one, and a hint taken from
the target type: the known fields of a Struct (and the closest one to a misspelling), the
values an enum or Literal allows. A key written twice in one mapping, which YAML loaders
silently collapse to the last one, is an error at the second key.

Errors: :class:`YamlError` (a ``ValueError``); callers pass their own subclass as
``error=`` to keep their package's error tree.
"""

from __future__ import annotations

import difflib
import os
import re
from collections.abc import Sequence
from pathlib import Path
from typing import Any, TypeVar

import msgspec
import msgspec.inspect as mi
import yaml

from .limits import MAX_TEXT_BYTES, MAX_YAML_BYTES, MAX_YAML_DEPTH

__all__ = [
    "Location",
    "YamlDocument",
    "YamlError",
    "load_yaml",
    "parse_location",
    "parse_yaml",
    "read_text_file",
    "render_location",
]

T = TypeVar("T")

Location = Sequence[Any]
"""A place in a document: mapping keys and list indices from the root, e.g.
``("components", "monitor", "node")`` or ``("robots", 0, "name")``."""

_MERGE = "tag:yaml.org,2002:merge"
_STEP = re.compile(r"\.([^.\[`]+)|\[(\d+)\]|(\[\.\.\.\])")
_IDENT = re.compile(r"[A-Za-z_][A-Za-z0-9_]*")
_UNKNOWN_FIELD = re.compile(r"Object contains unknown field `([^`]*)`")
_MISSING_FIELD = re.compile(r"Object missing required field `([^`]*)`")


class YamlError(ValueError):
    """A YAML file that cannot be used. The message starts with ``source:line:col``
    (``source`` alone when no position applies); the parts are attributes too."""

    def __init__(self, message: str, *, source: str = "", line: int = 0, column: int = 0) -> None:
        super().__init__(message)
        self.source = source
        self.line = line
        """1-based; 0 when unknown."""
        self.column = column


def render_location(loc: Location) -> str:
    """``$.components.monitor.node``, ``$.robots[0]``, ``$.nodes['a.b']``."""
    out = "$"
    for step in loc:
        if isinstance(step, int) and not isinstance(step, bool):
            out += f"[{step}]"
        elif isinstance(step, str) and _IDENT.fullmatch(step):
            out += f".{step}"
        else:
            out += f"[{step!r}]"
    return out


def parse_location(path: str) -> list[Any]:
    """The steps of a msgspec path: ``$.robots[0].name`` -> ``["robots", 0, "name"]``
    (a ``[...]`` step, a mapping entry msgspec does not name, ends the list)."""
    loc: list[Any] = []
    for field, index, any_key in _STEP.findall(path.removeprefix("$")):
        if any_key:
            break
        loc.append(field if field else int(index))
    return loc


class YamlDocument:
    """A parsed YAML document: the plain data and the node tree that knows positions."""

    __slots__ = ("_constructor", "_error", "data", "root", "source")

    def __init__(
        self, source: str, root: yaml.Node, data: Any, error: type[YamlError] = YamlError
    ) -> None:
        self.source = source
        self.root = root
        self.data = data
        self._error = error
        self._constructor = yaml.constructor.SafeConstructor()

    # -- positions ---------------------------------------------------------------------

    def _key_value(self, node: yaml.Node) -> Any:
        if not isinstance(node, yaml.ScalarNode):
            return None
        try:
            return self._constructor.construct_object(node)
        except yaml.YAMLError:
            return node.value

    def _child(self, node: yaml.Node, step: Any) -> tuple[yaml.Node, yaml.Node] | None:
        """(key node, value node) of ``step`` under ``node``; for a list the index node
        is the item itself. The last match wins, as it does in the loaded data."""
        if isinstance(node, yaml.MappingNode):
            found = None
            for key, value in node.value:
                if self._key_value(key) == step:
                    found = (key, value)
            return found
        if isinstance(node, yaml.SequenceNode) and isinstance(step, int):
            if 0 <= step < len(node.value):
                item: yaml.Node = node.value[step]
                return item, item
        return None

    def node_at(self, loc: Location, *, key: bool = False) -> yaml.Node:
        """The node at ``loc``, or its deepest existing ancestor; ``key=True``: the key
        node of the last step (to point at a mapping key rather than its value)."""
        node = self.root
        for i, step in enumerate(loc):
            pair = self._child(node, step)
            if pair is None:
                break
            node = pair[0] if key and i == len(loc) - 1 else pair[1]
        return node

    def position(self, loc: Location = (), *, key: bool = False) -> tuple[int, int]:
        """1-based (line, column) of :meth:`node_at`."""
        mark = self.node_at(loc, key=key).start_mark
        return mark.line + 1, mark.column + 1

    def where(self, loc: Location = (), *, key: bool = False) -> str:
        """``source:line:col`` of the node at ``loc``."""
        line, column = self.position(loc, key=key)
        return f"{self.source}:{line}:{column}"

    def error(self, loc: Location, problem: str, *, key: bool = False) -> YamlError:
        """An error (of the document's error class) at ``loc``: ``source:line:col: problem``."""
        line, column = self.position(loc, key=key)
        return self._error(
            f"{self.source}:{line}:{column}: {problem}",
            source=self.source,
            line=line,
            column=column,
        )

    # -- conversion --------------------------------------------------------------------

    def convert(self, type: type[T], *, strict: bool = True) -> T:
        """The data as ``type``; a mismatch raises the document's error class at the
        offending line. ``strict=False`` lets msgspec coerce strings to numbers etc."""
        try:
            return msgspec.convert(self.data, type=type, strict=strict)
        except msgspec.ValidationError as exc:
            raise self._explain(str(exc), type, strict) from None

    def _explain(self, message: str, target: Any, strict: bool) -> YamlError:
        what, sep, at = message.rpartition(" - at ")
        if not sep:  # at the root
            what, at = message, "`$`"
        key_error = at.startswith("`key` in ")
        raw_path = at[at.find("`$") + 2 : at.rfind("`")]
        loc: list[Any] = []
        data = self.data
        for field, index, any_key in _STEP.findall(raw_path):
            if field:
                loc.append(field)
            elif index:
                loc.append(int(index))
            elif any_key:
                found, data = self._culprit(data, loc, message, target, strict)
                if found is _NOT_FOUND:
                    break
                loc.append(found)
        unknown = _UNKNOWN_FIELD.match(what)
        if key_error:
            found, _ = self._culprit(data, loc, message, target, strict)
            if found is not _NOT_FOUND:
                text = f"{what} - at key {found!r} in `{render_location(loc)}`"
                hint = self._quote_hint(what, [*loc, found], key=True)
                return self.error([*loc, found], text + hint, key=True)
            return self.error(loc, f"{what} - at a key in `{render_location(loc)}`")
        text = f"{what} - at `{render_location(loc)}`" if loc else what
        hint = _hint(what, _type_at(mi.type_info(target), loc, self.data))
        if unknown is not None:  # point at the unknown key itself
            return self.error([*loc, unknown.group(1)], text + hint, key=True)
        node = self.node_at(loc)
        found_value = ""
        if isinstance(node, yaml.ScalarNode) and not what.startswith("Invalid"):
            found_value = f" (found {node.value!r})"
        return self.error(loc, text + found_value + hint + self._quote_hint(what, loc))

    def _quote_hint(self, what: str, loc: Location, *, key: bool = False) -> str:
        node = self.node_at(loc, key=key)
        if (
            what.startswith("Expected `str`")
            and isinstance(node, yaml.ScalarNode)
            and node.style is None
        ):
            return f"; quote the {'key' if key else 'value'} to make it a string"
        return ""

    def _culprit(
        self, data: Any, loc: list[Any], message: str, target: Any, strict: bool
    ) -> tuple[Any, Any]:
        """The key of the mapping at ``loc`` whose entry alone reproduces ``message``
        (msgspec names no mapping key in its paths), and the data narrowed to it."""
        mapping = _get(data, loc)
        if not isinstance(mapping, dict):
            return _NOT_FOUND, data
        for k, v in mapping.items():
            trial = _replace(data, loc, {k: v})
            try:
                msgspec.convert(trial, type=target, strict=strict)
            except msgspec.ValidationError as exc:
                if str(exc) == message:
                    return k, trial
        return _NOT_FOUND, data


_NOT_FOUND = object()


def _get(data: Any, loc: Sequence[Any]) -> Any:
    for step in loc:
        if isinstance(data, dict):
            data = data.get(step)
        elif isinstance(data, list) and isinstance(step, int) and 0 <= step < len(data):
            data = data[step]
        else:
            return None
    return data


def _replace(data: Any, loc: Sequence[Any], new: Any) -> Any:
    """A copy of ``data`` with the value at ``loc`` replaced (containers on the way copied)."""
    if not loc:
        return new
    head, rest = loc[0], loc[1:]
    if isinstance(data, dict):
        out = dict(data)
        out[head] = _replace(data[head], rest, new)
        return out
    if isinstance(data, list):
        items = list(data)
        items[head] = _replace(data[head], rest, new)
        return items
    return data


def _type_at(info: mi.Type, loc: Sequence[Any], data: Any) -> mi.Type | None:
    """The msgspec type of the value at ``loc`` (following the data through unions)."""
    current: mi.Type | None = info
    for step in loc:
        current = _resolve(current, data)
        if isinstance(current, mi.StructType):
            field = next((f for f in current.fields if f.encode_name == step), None)
            current = field.type if field is not None else None
        elif isinstance(current, mi.DictType):
            current = current.value_type
        elif isinstance(current, (mi.ListType, mi.SetType, mi.FrozenSetType, mi.VarTupleType)):
            current = current.item_type
        else:
            return None
        data = _get(data, [step])
    return _resolve(current, data)


def _resolve(t: mi.Type | None, data: Any) -> mi.Type | None:
    """Unwrap metadata; pick the member of a union that ``data`` is meant to be."""
    while isinstance(t, mi.Metadata):
        t = t.type
    if isinstance(t, mi.UnionType):
        members = [m for m in t.types if not isinstance(m, mi.NoneType)]
        structs = [m for m in members if isinstance(m, mi.StructType)]
        if isinstance(data, dict) and structs:
            for s in structs:
                if s.tag_field is not None and data.get(s.tag_field) == s.tag:
                    return s
            return structs[0] if len(structs) == 1 else None
        return _resolve(members[0], data) if len(members) == 1 else None
    return t


def _hint(what: str, t: mi.Type | None) -> str:
    unknown = _UNKNOWN_FIELD.match(what)
    if unknown is not None and isinstance(t, mi.StructType):
        names = [f.encode_name for f in t.fields]
        close = difflib.get_close_matches(unknown.group(1), names, n=1)
        known = f"known fields: {', '.join(names)}"
        return f"; did you mean `{close[0]}`? {known}" if close else f"; {known}"
    missing = _MISSING_FIELD.match(what)
    if missing is not None:
        return f"; add `{missing.group(1)}:` to this mapping"
    if what.startswith("Invalid enum value"):
        values: list[Any] = []
        if isinstance(t, mi.LiteralType):
            values = list(t.values)
        elif isinstance(t, mi.EnumType):
            values = [m.value for m in t.cls]
        if values:
            return f"; use one of {', '.join(str(v) for v in values)}"
    return ""


def _check_duplicate_keys(root: yaml.Node, source: str, error: type[YamlError]) -> None:
    seen: set[int] = set()
    stack = [root]
    while stack:
        node = stack.pop()
        if id(node) in seen:
            continue
        seen.add(id(node))
        if isinstance(node, yaml.MappingNode):
            first: dict[tuple[str, str], int] = {}
            for key, value in node.value:
                stack.append(value)
                if not isinstance(key, yaml.ScalarNode) or key.tag == _MERGE:
                    continue
                ident = (key.tag, key.value)
                line, column = key.start_mark.line + 1, key.start_mark.column + 1
                if ident in first:
                    raise error(
                        f"{source}:{line}:{column}: key {key.value!r} appears twice in "
                        f"this mapping (first on line {first[ident]}); YAML would keep "
                        "only the last one: remove or rename one of them",
                        source=source,
                        line=line,
                        column=column,
                    )
                first[ident] = line
        elif isinstance(node, yaml.SequenceNode):
            stack.extend(node.value)


def parse_yaml(
    text: str,
    source: str = "<yaml>",
    *,
    what: str = "file",
    error: type[YamlError] = YamlError,
) -> YamlDocument:
    """Parse one YAML document (safe loader). An empty document, invalid YAML, a
    duplicate key, or a document past the limits (:mod:`rap_schemas.limits`: size,
    nesting, aliases that expand too far) raises ``error`` at its position; ``what``
    names the file in messages."""
    if len(text) > MAX_YAML_BYTES:
        raise error(
            f"{source}: the {what} is {len(text)} characters, over the limit of "
            f"{MAX_YAML_BYTES}; split it or remove what is not needed",
            source=source,
        )
    loader = yaml.SafeLoader(text)
    try:
        _check_shape(text, source, what, error)
        root = loader.get_single_node()
        if root is None:
            raise error(f"{source}: the {what} is empty", source=source)
        _check_duplicate_keys(root, source, error)
        data = loader.construct_document(root)
    except yaml.MarkedYAMLError as exc:
        mark = exc.problem_mark or exc.context_mark
        problem = ": ".join(p for p in (exc.context, exc.problem) if p) or str(exc)
        if mark is None:
            raise error(f"{source}: not valid YAML: {problem}", source=source) from None
        line, column = mark.line + 1, mark.column + 1
        raise error(
            f"{source}:{line}:{column}: not valid YAML: {problem}",
            source=source,
            line=line,
            column=column,
        ) from None
    except yaml.YAMLError as exc:
        raise error(f"{source}: not valid YAML: {exc}", source=source) from None
    except RecursionError:  # _check_shape bounds nesting first; this is a last guard
        raise error(
            f"{source}: the {what} nests too deeply; at most {MAX_YAML_DEPTH} levels",
            source=source,
        ) from None
    finally:
        loader.dispose()
    return YamlDocument(source, root, data, error)


MAX_EXPANDED_NODES = 1_000_000
"""Nodes a document may have once its aliases are expanded (a few aliases to aliases
would otherwise make a small file expand to billions of nodes in any reader)."""


def _position(event: yaml.Event) -> tuple[int, int]:
    mark = event.start_mark
    return (mark.line + 1, mark.column + 1) if mark is not None else (0, 0)


def _check_shape(text: str, source: str, what: str, error: type[YamlError]) -> None:
    """Nesting depth and expanded size, from the parser's event stream (iterative, so
    no depth can exhaust the stack before the limit is seen)."""
    depth = 0
    sizes: dict[str, int] = {}
    open_: list[tuple[str | None, int]] = []  # (anchor, expanded nodes before it)
    total = 0
    for event in yaml.parse(text, Loader=yaml.SafeLoader):
        if isinstance(event, yaml.CollectionStartEvent):
            depth += 1
            if depth > MAX_YAML_DEPTH:
                line, column = _position(event)
                raise error(
                    f"{source}:{line}:{column}: the {what} nests lists or mappings more "
                    f"than {MAX_YAML_DEPTH} levels deep; flatten it",
                    source=source,
                    line=line,
                    column=column,
                )
            open_.append((event.anchor, total))
            total += 1
        elif isinstance(event, yaml.CollectionEndEvent):
            depth -= 1
            anchor, before = open_.pop()
            if anchor is not None:
                sizes[anchor] = total - before
        elif isinstance(event, yaml.ScalarEvent):
            total += 1
            if event.anchor is not None:
                sizes[event.anchor] = 1
        elif isinstance(event, yaml.AliasEvent):
            total += sizes.get(event.anchor or "", 1)
        if total > MAX_EXPANDED_NODES:
            line, column = _position(event)
            raise error(
                f"{source}:{line}:{column}: the {what} expands to more than "
                f"{MAX_EXPANDED_NODES} values (aliases of aliases); write it out plainly",
                source=source,
                line=line,
                column=column,
            )


def read_text_file(
    path: str | os.PathLike[str],
    *,
    what: str = "file",
    error: type[YamlError] = YamlError,
    max_bytes: int = MAX_TEXT_BYTES,
) -> str:
    """The UTF-8 text of ``path``. A file that cannot be read, is larger than
    ``max_bytes`` or is not UTF-8 text (a binary file) raises ``error`` naming the file
    (and the line and column of the first bad byte)."""
    p = Path(path)
    source = str(p)
    try:
        with p.open("rb") as f:
            data = f.read(max_bytes + 1)
    except IsADirectoryError:
        raise error(f"{source}: is a directory; give the path of a file", source=source) from None
    except OSError as exc:
        reason = exc.strerror or str(exc)
        raise error(f"{source}: cannot read the {what}: {reason}", source=source) from None
    if len(data) > max_bytes:
        raise error(
            f"{source}: the {what} is larger than {max_bytes} bytes; split it",
            source=source,
        )
    try:
        return data.decode("utf-8")
    except UnicodeDecodeError as exc:
        head = data[: exc.start]
        line = head.count(b"\n") + 1
        column = exc.start - (head.rfind(b"\n") + 1) + 1
        raise error(
            f"{source}:{line}:{column}: the {what} is not UTF-8 text (byte "
            f"0x{data[exc.start]:02x}); is it a binary file? give the {what} in text form",
            source=source,
            line=line,
            column=column,
        ) from None


def load_yaml(
    text: str,
    type: type[T],
    source: str = "<yaml>",
    *,
    what: str = "file",
    strict: bool = True,
    error: type[YamlError] = YamlError,
) -> T:
    """Parse ``text`` and convert it to ``type``; every error carries ``source:line:col``."""
    return parse_yaml(text, source, what=what, error=error).convert(type, strict=strict)

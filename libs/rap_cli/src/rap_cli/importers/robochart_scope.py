"""Name resolution across the packages of a RoboChart design, and its types as the
model's field types.

A name used in a file is looked up, in order: as written when it is qualified
(``Pkg::Name``); in the file's own package (every file of that package); in the packages
it imports (``import P::*``) and the declarations it imports one by one
(``import P::Name``); and in the file itself for a RoboArch file (no package). A name
found only elsewhere still resolves, with a warning that the import is missing.

Types (:meth:`Scope.field_type`): ``real`` -> ``float``, ``int`` -> ``int``, ``nat`` ->
``int`` with ``ge: 0``, ``boolean`` -> ``bool``, ``string`` -> ``str``, a record,
datatype, enumeration or primitive type -> the message made of it, ``Seq(T)`` and
``Set(T)`` -> ``list[T]``, ``A * B`` -> a message with fields ``item1``, ``item2``. A name
that resolves to nothing is kept as written (``::`` as ``.``): the model's own check
(``model_findings``) reports it as neither a scalar nor a message, at the field.
"""

from __future__ import annotations

from collections import defaultdict
from collections.abc import Callable
from dataclasses import dataclass
from typing import Any

from ..diagnostics import Diagnostic, Loc
from ..robochart import syntax as s

__all__ = ["PRIMITIVES", "STANDARD_PACKAGES", "FieldType", "Scope", "qualified"]

PRIMITIVES = {"real": "float", "int": "int", "nat": "int", "boolean": "bool", "string": "str"}
"""RoboChart's basic types -> scalars of the model (``nat`` also gets ``ge: 0``)."""

STANDARD_PACKAGES = frozenset(
    {"sequence_toolkit", "set_toolkit", "relation_toolkit", "function_toolkit", "core"}
)
"""RoboChart's own library packages, which a design imports without giving their files."""

File = s.RcFile | s.RacFile


@dataclass(frozen=True, slots=True)
class FieldType:
    """A RoboChart type as a field type of the model; ``ge`` is 0 for ``nat``."""

    type: str
    ge: float | None = None
    doc: str = ""


def qualified(package: str | None, name: str) -> str:
    """``Pkg::Name`` (or ``Name`` outside any package)."""
    return f"{package}::{name}" if package else name


def _package(file: File) -> str | None:
    return file.package if isinstance(file, s.RcFile) else None


class Scope:
    """The declarations of every file by package, and lookups that follow the imports.

    ``message_of`` maps a record, enumeration or primitive type to the name of its
    message (set by the importer); ``product_message`` creates the message of a product
    type on first use."""

    def __init__(self, files: list[File]) -> None:
        self.files = files
        self.packages: dict[str | None, list[tuple[Any, File]]] = defaultdict(list)
        for file in files:
            for decl in file.declarations:
                self.packages[_package(file)].append((decl, file))
        self.message_of: dict[Any, str] = {}
        self.product_message: Callable[[tuple[FieldType, ...], Loc], str] | None = None
        self.diagnostics: list[Diagnostic] = []
        self._warned: set[tuple[str, int, str]] = set()

    def qname(self, decl: Any, file: File) -> str:
        """The qualified name of a top-level declaration of ``file``."""
        return qualified(_package(file), decl.name)

    def _in(
        self, package: str | None, name: str, kinds: tuple[type, ...]
    ) -> list[tuple[Any, File]]:
        return [
            (d, f)
            for d, f in self.packages.get(package, [])
            if d.name == name and isinstance(d, kinds)
        ]

    def lookup(
        self, name: str, file: File, kinds: tuple[type, ...], at: Loc
    ) -> tuple[Any, File] | None:
        """The declaration ``name`` means in ``file`` (see the module docstring)."""
        if "::" in name:
            prefix, _, simple = name.rpartition("::")
            qualified_found = self._in(prefix, simple, kinds)
            return qualified_found[0] if qualified_found else None
        found = self._in(_package(file), name, kinds)
        if isinstance(file, s.RcFile):
            for imp in file.imports:
                if imp.wildcard:
                    found += self._in(imp.path, name, kinds)
                else:
                    prefix, _, simple = imp.path.rpartition("::")
                    if simple == name:
                        found += self._in(prefix, name, kinds)
        if found:
            return found[0]
        anywhere = [
            (d, f)
            for decls in self.packages.values()
            for d, f in decls
            if d.name == name and isinstance(d, kinds)
        ]
        if anywhere:
            decl, where = anywhere[0]
            package = _package(where)
            key = (at.file, at.line, name)
            if package and key not in self._warned:
                self._warned.add(key)
                self.diagnostics.append(
                    Diagnostic(
                        at.file,
                        at.line,
                        at.column,
                        "warning",
                        f"{name!r} is declared in package {package}, which this file does not "
                        f"import - add 'import {package}::*' (it is resolved there)",
                    )
                )
            return decl, where
        return None

    def field_type(self, t: s.TypeExpr, file: File) -> FieldType:
        """``t`` as a field type (see the module docstring)."""
        if isinstance(t, s.TypeName):
            if t.name in PRIMITIVES:
                return FieldType(PRIMITIVES[t.name], 0 if t.name == "nat" else None)
            kinds = (s.Record, s.Enumeration, s.PrimitiveType)
            found = self.lookup(t.name, file, kinds, t.loc)
            if found is not None and found[0] in self.message_of:
                return FieldType(self.message_of[found[0]])
            return FieldType(t.name.replace("::", "."))
        if isinstance(t, s.SeqType | s.SetType):
            inner = self.field_type(t.elem, file)
            doc = "a set in RoboChart" if isinstance(t, s.SetType) else inner.doc
            return FieldType(f"list[{inner.type}]", doc=doc)
        if isinstance(t, s.ProductType) and self.product_message is not None:
            items = tuple(self.field_type(x, file) for x in t.items)
            return FieldType(self.product_message(items, t.loc))
        kind = "a function type" if isinstance(t, s.FunctionType) else "a type parameter"
        return FieldType("bytes", doc=f"{kind} in RoboChart, which the model cannot type")


def render_type(t: s.TypeExpr | None) -> str:
    """A RoboChart type as written (for properties and docs)."""
    if t is None:
        return ""
    if isinstance(t, s.TypeName):
        return t.name
    if isinstance(t, s.SeqType):
        return f"Seq({render_type(t.elem)})"
    if isinstance(t, s.SetType):
        return f"Set({render_type(t.elem)})"
    if isinstance(t, s.ProductType):
        return " * ".join(render_type(x) for x in t.items)
    if isinstance(t, s.FunctionType):
        return f"{render_type(t.domain)} -> {render_type(t.codomain)}"
    return f"?{t.name}"

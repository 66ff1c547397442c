"""What a RoboChart import checks and notes beyond the parts it maps: imports of
packages none of the files declares, and the declarations the model has no place for
(functions, operations, package-level constants, machines in no controller, unused
interfaces). Functions of :class:`~rap_cli.importers.robochart._Importer`'s run."""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..robochart import syntax as s
from .robochart_scope import STANDARD_PACKAGES, render_type

if TYPE_CHECKING:
    from .robochart import _Importer

__all__ = ["check_imports", "leftovers", "unused_interfaces"]

File = s.RcFile | s.RacFile


def params(ps: tuple[s.Param, ...]) -> str:
    """Parameters as written: ``a: real, b: Seq(int)``."""
    return ", ".join(f"{p.name}: {render_type(p.type)}" for p in ps)


def check_imports(self: _Importer) -> None:
    """Every import names a package of the given files (or RoboChart's library)."""
    packages = {f.package for f in self.rct}
    for file in self.rct:
        for imp in file.imports:
            package, _, name = (imp.path, "", "") if imp.wildcard else imp.path.rpartition("::")
            root = package.split("::")[0]
            if package in packages:
                if name and not self.scope._in(package, name, (object,)):
                    self.draft.report(
                        imp.loc,
                        "error",
                        f"import {imp.path}: package {package} declares no {name!r} - "
                        f"fix the name or import {package}::*",
                    )
            elif package in STANDARD_PACKAGES or root in STANDARD_PACKAGES:
                self.draft.report(
                    imp.loc,
                    "note",
                    f"import {imp.path}: {package} is RoboChart's own library, which RAP "
                    "does not read - what the design uses of it is in expressions only",
                )
            else:
                self.draft.report(
                    imp.loc,
                    "error",
                    f"import {imp.path}: none of the given files declares package "
                    f"{package} - give its .rct file too, or remove the import",
                )


def leftovers(self: _Importer, file: File) -> None:
    """Notes (or components) for the top-level declarations nothing else maps."""
    for decl in file.declarations:
        qname = self.scope.qname(decl, file)
        if isinstance(decl, s.StateMachine) and decl.kind == "stm":
            if decl not in self.instanced:
                comp = self.machine(decl, file, qname, "stm")
                self.draft.report(
                    decl.loc,
                    "note",
                    f"state machine {qname} is in no controller: component {comp.name} "
                    "has no connections - reference it from a controller (sref)",
                )
        elif isinstance(decl, s.StateMachine):
            self.draft.report(
                decl.loc,
                "note",
                f"operation {qname} is behaviour the machines call; the model keeps "
                "behaviour as text on the machines that reference it",
            )
        elif isinstance(decl, s.FunctionDecl):
            self.draft.report(
                decl.loc,
                "note",
                f"function {qname}({params(decl.params)}): {render_type(decl.result)} "
                "is used in expressions; the model has no place for functions",
            )
        elif isinstance(decl, s.Variable):
            value = f" = {' '.join(decl.value.text.split())}" if decl.value else ""
            self.draft.report(
                decl.loc,
                "note",
                f"{'const' if decl.const else 'var'} {qname}: {render_type(decl.type)}"
                f"{value} is package-level; the model has no place for it",
            )
        elif isinstance(decl, s.RoboticPlatform) and decl not in self.platforms:
            self.platform(decl, file, qname)


def unused_interfaces(self: _Importer) -> None:
    """A note for each interface nothing uses."""
    for file in self.files:
        for decl in file.declarations:
            if isinstance(decl, s.Interface) and decl not in self.used_interfaces:
                self.draft.report(
                    decl.loc,
                    "note",
                    f"interface {self.scope.qname(decl, file)} is used by no machine, "
                    "controller or platform; it adds nothing to the model",
                )

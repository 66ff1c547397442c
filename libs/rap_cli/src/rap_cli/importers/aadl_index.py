"""The declarations of an AADL design, indexed for the importer (:mod:`.aadl`).

:class:`Index` holds every package and property set of the parsed files under its name
compared without case, checks the ``with`` clauses, and resolves classifier references
(``pkg::T.impl``, ``T``, through ``renames``) into a :class:`Classifier`, a
:class:`BaseType` (``Base_Types::Float_64``, known without a file), an :class:`Opaque`
classifier (of a library named in a ``with`` but not in the import: its features are
unknown, nothing more is said about it) or None (reported once, at the reference).

It also merges what ``extends`` inherits (features, subcomponents, connections, modes,
properties); :mod:`.aadl_units` checks the units written after numbers.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from ..aadl import syntax as s
from ..aadl.syntax import norm
from ..diagnostics import Diagnostic, Loc, Severity

__all__ = [
    "BASE_TYPES",
    "BaseType",
    "Classifier",
    "Index",
    "Opaque",
    "Resolved",
    "diagnostic",
    "find_property",
]

PREDECLARED = frozenset(
    norm(n)
    for n in (
        "Base_Types",
        "Data_Model",
        "AADL_Project",
        "Timing_Properties",
        "Deployment_Properties",
        "Thread_Properties",
        "Communication_Properties",
        "Memory_Properties",
        "Programming_Properties",
        "Modeling_Properties",
    )
)
"""Packages and property sets of the AADL standard, known without a file."""

TOOL_LIBRARIES = {
    "sei": "OSATE",
    "emv2": "OSATE",
    "arp4761": "OSATE",
    "physical": "OSATE",
    "deployment": "Ocarina",
    "ocarina_drivers": "Ocarina",
    "ocarina_buses": "Ocarina",
    "ocarina_processors_x86": "Ocarina",
    "ocarina_processors_arm": "Ocarina",
    "ocarina_config": "Ocarina",
}
"""Libraries that AADL tools ship: a ``with`` of one that the import lacks is a note,
and its classifiers are opaque."""

BASE_TYPES = {
    "boolean": "bool",
    "integer": "int",
    "integer_8": "int8",
    "integer_16": "int16",
    "integer_32": "int32",
    "integer_64": "int64",
    "unsigned_8": "uint8",
    "unsigned_16": "uint16",
    "unsigned_32": "uint32",
    "unsigned_64": "uint64",
    "natural": "uint64",
    "float": "float",
    "float_32": "float32",
    "float_64": "float64",
    "character": "str",
    "string": "str",
}
"""``Base_Types`` data types and the RAP field type each becomes."""

_CONTAINERS = {"system", "abstract"}


@dataclass(frozen=True, slots=True)
class BaseType:
    """A data type of ``Base_Types``; ``rap`` is the field type it becomes."""

    name: str
    rap: str


@dataclass(frozen=True, slots=True)
class Opaque:
    """A classifier of a library named in a ``with`` but not in the import."""

    ref: str

    @property
    def name(self) -> str:
        return self.ref.rpartition("::")[2].partition(".")[0]


@dataclass(frozen=True, slots=True)
class Classifier:
    """A component type or implementation and the package that declares it."""

    package: s.Package
    decl: s.Declaration

    @property
    def qualified(self) -> str:
        return f"{self.package.name}::{self.decl.name}"

    @property
    def type_name(self) -> str:
        """``T`` of ``T`` or ``T.impl``."""
        decl = self.decl
        return decl.type_name if isinstance(decl, s.ComponentImpl) else decl.name

    @property
    def key(self) -> tuple[str, str]:
        return norm(self.package.name), norm(self.decl.name)


Resolved = Classifier | BaseType | Opaque | None


def diagnostic(loc: Loc, severity: Severity, message: str) -> Diagnostic:
    """A diagnostic at ``loc``."""
    return Diagnostic(loc.file, loc.line, loc.column, severity, message)


def find_property(
    associations: list[s.PropertyAssociation], *names: str
) -> s.PropertyAssociation | None:
    """The last association (the one that wins) of one of ``names``: ``set::Name`` must
    match its property set too, a bare ``Name`` matches in any set."""
    found = None
    for assoc in associations:
        simple = norm(assoc.simple_name)
        owner = norm(assoc.property_set or "")
        for name in names:
            want_set, _, want = name.rpartition("::")
            if simple == norm(want) and (not want_set or owner == norm(want_set)):
                found = assoc
    return found


@dataclass
class Index:
    """The packages and property sets of the parsed files, by name without case."""

    files: list[s.AadlFile]
    diagnostics: list[Diagnostic] = field(default_factory=list)
    packages: dict[str, s.Package] = field(default_factory=dict)
    property_sets: dict[str, s.PropertySet] = field(default_factory=dict)
    missing: set[str] = field(default_factory=set)
    """Packages named in a ``with`` that the import lacks (already reported)."""
    _reported: set[tuple[str, int, int]] = field(default_factory=set)

    def __post_init__(self) -> None:
        for aadl_file in self.files:
            for package in aadl_file.packages:
                self._add(self.packages, package.name, package, package.loc, "package")
            for pset in aadl_file.property_sets:
                self._add(self.property_sets, pset.name, pset, pset.loc, "property set")
        self._check_withs()

    def _add(
        self,
        table: dict[str, s.Package] | dict[str, s.PropertySet],
        name: str,
        item: s.Package | s.PropertySet,
        loc: Loc,
        what: str,
    ) -> None:
        key = norm(name)
        other = table.get(key)
        if other is not None:
            message = (
                f"{what} {name} is declared twice (also at {other.loc}) - keep one; "
                "the first one is imported"
            )
            self.diagnostics.append(diagnostic(loc, "error", message))
            return
        table[key] = item  # type: ignore[assignment]

    # -- with clauses

    def known(self, name: str) -> bool:
        """Whether ``name`` is a package or property set of the import or predeclared."""
        key = norm(name)
        return key in self.packages or key in self.property_sets or key in PREDECLARED

    def _check_withs(self) -> None:
        owners: list[tuple[str, tuple[str, ...], tuple[Loc, ...], Loc, s.Package | None]] = [
            (p.name, p.withs, p.with_locs, p.loc, p) for p in self.packages.values()
        ]
        owners += [(p.name, p.withs, p.with_locs, p.loc, None) for p in self.property_sets.values()]
        for owner, withs, locs, loc, package in owners:
            for i, name in enumerate(withs):
                if self.known(name):
                    continue
                key = norm(name)
                self.missing.add(key)
                where = locs[i] if i < len(locs) else loc
                tool = TOOL_LIBRARIES.get(key)
                if tool is not None:
                    message = (
                        f"{owner} uses {name}, which {tool} provides and the import does not "
                        f"hold: its classifiers are read as opaque and its properties as text"
                    )
                    self.diagnostics.append(diagnostic(where, "note", message))
                    continue
                used = package is not None and _uses(package, key)
                message = (
                    f"{owner} names package {name} in its 'with', but no file of the import "
                    f"declares it - add the file that declares {name} to the import"
                )
                if not used:
                    message += ", or remove it from the 'with' (nothing here uses it)"
                self.diagnostics.append(diagnostic(where, "error" if used else "warning", message))

    # -- classifiers

    def resolve(self, ref: str, package: s.Package, loc: Loc) -> Resolved:
        """The classifier ``ref`` names from ``package``; None (reported at ``loc``) when
        it names nothing."""
        head, sep, local = ref.rpartition("::")
        if not sep:
            return self._local(ref, package, loc)
        key = norm(head)
        for ren in package.renames:
            if ren.kind == "package" and ren.alias is not None and norm(ren.alias) == key:
                key = norm(ren.target)
        if key == "base_types" and key not in self.packages:
            rap = BASE_TYPES.get(norm(local))
            if rap is not None:
                return BaseType(local, rap)
            names = ", ".join(n.title() for n in BASE_TYPES)
            self._report(loc, f"Base_Types has no type {local} - use one of {names}")
            return None
        target = self.packages.get(key)
        if target is None:
            if key in self.missing or key in TOOL_LIBRARIES or key in PREDECLARED:
                return Opaque(ref)
            self._report(
                loc,
                f"{ref} names package {head}, which no file of the import declares - "
                f"add its file to the import, or fix the name",
            )
            return None
        found = target.find(local)
        if found is None:
            self._report(
                loc, f"package {target.name} declares no classifier {local}" + _others(target)
            )
            return None
        return Classifier(target, found)

    def _local(self, ref: str, package: s.Package, loc: Loc) -> Resolved:
        found = package.find(ref)
        if found is not None:
            return Classifier(package, found)
        key = norm(ref)
        for ren in package.renames:
            if ren.alias is not None and norm(ren.alias) == key and ren.kind != "package":
                return self.resolve(ren.target, package, loc)
            if ren.kind == "all":
                other = self.packages.get(norm(ren.target))
                hit = other.find(ref) if other is not None else None
                if other is not None and hit is not None:
                    return Classifier(other, hit)
        self._report(
            loc,
            f"{ref} is not declared in package {package.name} - qualify it with its package "
            f"(pkg::{ref}) and name that package in the 'with'" + _others(package),
        )
        return None

    def _report(self, loc: Loc, message: str) -> None:
        key = (loc.file, loc.line, loc.column)
        if key not in self._reported:
            self._reported.add(key)
            self.diagnostics.append(diagnostic(loc, "error", message))

    def type_of(self, c: Classifier) -> Classifier | None:
        """The component type of ``c`` (``c`` itself for a type)."""
        if isinstance(c.decl, s.ComponentType):
            return c
        found = c.package.find(c.decl.type_name)
        if isinstance(found, s.ComponentType):
            return Classifier(c.package, found)
        self._report(
            c.decl.loc,
            f"implementation {c.decl.name} implements {c.decl.type_name}, which package "
            f"{c.package.name} does not declare - declare the type {c.decl.type_name}",
        )
        return None

    def chain(self, c: Classifier) -> list[Classifier]:
        """``c`` and what it extends, the most basic first."""
        out: list[Classifier] = []
        here: Classifier | None = c
        seen: set[tuple[str, str]] = set()
        while here is not None and here.key not in seen:
            seen.add(here.key)
            out.append(here)
            parent = here.decl.extends
            if parent is None:
                break
            found = self.resolve(parent, here.package, here.decl.loc)
            here = found if isinstance(found, Classifier) else None
        return out[::-1]

    def base_of(self, c: Classifier) -> Resolved:
        """What the most basic classifier of ``c``'s type chain extends when that is not
        a classifier of the import (a ``Base_Types`` type, an opaque one)."""
        ctype = self.type_of(c)
        if ctype is None:
            return None
        first = self.chain(ctype)[0]
        if first.decl.extends is None:
            return None
        found = self.resolve(first.decl.extends, first.package, first.decl.loc)
        return None if isinstance(found, Classifier) else found

    # -- what extends merges

    def features(self, c: Classifier) -> dict[str, s.Feature]:
        """The features of ``c``'s type, inherited ones first, refined ones replaced."""
        ctype = self.type_of(c)
        out: dict[str, s.Feature] = {}
        for link in self.chain(ctype) if ctype is not None else []:
            assert isinstance(link.decl, s.ComponentType)
            for feature in link.decl.features:
                out[norm(feature.name)] = feature
        return out

    def impl_chain(self, c: Classifier) -> list[Classifier]:
        """The implementations ``c`` extends and ``c`` (empty for a type)."""
        if not isinstance(c.decl, s.ComponentImpl):
            return []
        return self.chain(c)

    def subcomponents(self, c: Classifier) -> list[tuple[s.Subcomponent, s.Package]]:
        """The subcomponents of implementation ``c`` with extends merged, each with the
        package it is declared in (where its classifier is resolved)."""
        out: dict[str, tuple[s.Subcomponent, s.Package]] = {}
        for link in self.impl_chain(c):
            assert isinstance(link.decl, s.ComponentImpl)
            for sub in link.decl.subcomponents:
                out[norm(sub.name)] = (sub, link.package)
        return list(out.values())

    def connections(self, c: Classifier) -> list[s.Connection]:
        """The connections of implementation ``c`` with extends merged."""
        out: list[s.Connection] = []
        for link in self.impl_chain(c):
            assert isinstance(link.decl, s.ComponentImpl)
            out += link.decl.connections
        return out

    def modes(self, c: Classifier) -> tuple[list[s.Mode], list[s.ModeTransition]]:
        """Modes and transitions of ``c``'s type and implementation chains."""
        modes: dict[str, s.Mode] = {}
        transitions: list[s.ModeTransition] = []
        ctype = self.type_of(c)
        links = (self.chain(ctype) if ctype is not None else []) + self.impl_chain(c)
        for link in links:
            for mode in link.decl.modes:
                modes[norm(mode.name)] = mode
            transitions += link.decl.mode_transitions
        return list(modes.values()), transitions

    def properties(self, c: Classifier) -> list[s.PropertyAssociation]:
        """``c``'s own associations (no ``applies to``), type chain then implementation
        chain: a later one wins."""
        ctype = self.type_of(c)
        links = (self.chain(ctype) if ctype is not None else []) + self.impl_chain(c)
        return [p for link in links for p in link.decl.properties if not p.applies_to]

    def contained(self, c: Classifier) -> list[tuple[s.PropertyAssociation, s.Package]]:
        """The associations of implementation ``c`` with ``applies to``."""
        return [
            (p, link.package)
            for link in self.impl_chain(c)
            for p in link.decl.properties
            if p.applies_to
        ]


def _others(package: s.Package) -> str:
    names = [d.name for d in package.declarations][:12]
    return f" (it declares {', '.join(names)})" if names else ""


def _uses(package: s.Package, key: str) -> bool:
    """Whether anything in ``package`` names ``key::``."""
    prefix = key + "::"
    for decl in package.declarations:
        refs: list[str | None] = [decl.extends]
        refs += [p.name for p in decl.properties]
        if isinstance(decl, s.ComponentType):
            refs += [f.classifier for f in decl.features]
            refs += [p.name for f in decl.features for p in f.properties]
        else:
            refs += [sub.classifier for sub in decl.subcomponents]
            refs += [p.name for sub in decl.subcomponents for p in sub.properties]
        if any(r is not None and norm(r).startswith(prefix) for r in refs):
            return True
    return False


def is_container(category: str) -> bool:
    """Categories whose implementations are flattened through (systems, abstract)."""
    return category in _CONTAINERS

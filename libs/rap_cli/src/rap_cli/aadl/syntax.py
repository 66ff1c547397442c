"""The located syntax model of an AADL v2 file: what was written, where, nothing resolved.

:func:`rap_cli.aadl.parse_aadl` produces these nodes; the importer that builds RAP's system
model (instance tree, bindings) consumes them. Every node is a frozen dataclass with a
``loc`` (file, 1-based line and column of its first token). Names keep the case they were
written in; AADL compares them case-insensitively, so compare through :func:`norm`.
Sequences are tuples, so a whole file is immutable and hashable.

Nothing here is resolved: a classifier reference is the text ``pkg::T.impl``, a connection
end is the path ``sub.port``, a unit is the identifier written after a number (``Mbps``)
whether or not any property set declares it. What the parser skipped (annexes, flows,
call sequences, prototypes) is listed in :attr:`AadlFile.notes`, each with its location.
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

from rap_cli.diagnostics import Loc, Note

__all__ = [
    "AadlFile",
    "BoolValue",
    "ClassifierValue",
    "ComponentImpl",
    "ComponentType",
    "ComputedValue",
    "Connection",
    "Declaration",
    "Direction",
    "EnumValue",
    "Feature",
    "IntValue",
    "ListValue",
    "Loc",
    "Mode",
    "ModeTransition",
    "NameValue",
    "Note",
    "Package",
    "PropertyAssociation",
    "PropertyConstant",
    "PropertyDefinition",
    "PropertySet",
    "PropertyType",
    "PropertyTypeDecl",
    "PropertyValue",
    "RangeValue",
    "RealValue",
    "RecordField",
    "RecordFieldType",
    "RecordValue",
    "ReferenceValue",
    "Renames",
    "StringValue",
    "Subcomponent",
    "UnitLiteral",
    "norm",
]

Direction = Literal["in", "out", "in out"]


def norm(name: str) -> str:
    """The form under which AADL compares ``name``: identifiers, qualified names and
    paths are case-insensitive (``Base_Types::Float`` is ``base_types::float``)."""
    return name.lower()


# ---------------------------------------------------------------- property values


@dataclass(frozen=True, slots=True)
class IntValue:
    """An integer, with the unit written after it (``8 Bytes``, ``2000 Ms``) or None."""

    loc: Loc
    value: int
    unit: str | None = None


@dataclass(frozen=True, slots=True)
class RealValue:
    """A real, with the unit written after it (``10.0 Hz``, ``23.46 Mbps``) or None."""

    loc: Loc
    value: float
    unit: str | None = None


@dataclass(frozen=True, slots=True)
class StringValue:
    """A string literal, unquoted (``""`` inside it stands for one ``"``)."""

    loc: Loc
    value: str


@dataclass(frozen=True, slots=True)
class BoolValue:
    """``true`` or ``false``."""

    loc: Loc
    value: bool


@dataclass(frozen=True, slots=True)
class EnumValue:
    """A bare identifier: an enumeration literal (``Periodic``, ``MQTT``, ``Struct``), or
    an unqualified property constant; which one is for the importer to resolve."""

    loc: Loc
    literal: str


@dataclass(frozen=True, slots=True)
class NameValue:
    """A qualified name (``rpio::Topic``, ``ARP4761::Major``): a property constant or a
    qualified literal of a property set."""

    loc: Loc
    name: str


@dataclass(frozen=True, slots=True)
class RangeValue:
    """``low .. high [delta d]`` (``1 ms .. 2 ms``)."""

    loc: Loc
    low: PropertyValue
    high: PropertyValue
    delta: PropertyValue | None = None


@dataclass(frozen=True, slots=True)
class ListValue:
    """``(a, b, ...)``; ``(360)`` is a list of one."""

    loc: Loc
    items: tuple[PropertyValue, ...]


@dataclass(frozen=True, slots=True)
class RecordField:
    """``name => value;`` inside a record value."""

    loc: Loc
    name: str
    value: PropertyValue


@dataclass(frozen=True, slots=True)
class RecordValue:
    """``[f => v; g => w;]``."""

    loc: Loc
    fields: tuple[RecordField, ...]


@dataclass(frozen=True, slots=True)
class ReferenceValue:
    """``reference (a.b.c)`` (or the older ``reference a.b.c``): a path of subcomponents
    (and features) from the component the association belongs to."""

    loc: Loc
    path: str


@dataclass(frozen=True, slots=True)
class ClassifierValue:
    """``classifier (pkg::T.impl)``: the classifier reference as written."""

    loc: Loc
    name: str


@dataclass(frozen=True, slots=True)
class ComputedValue:
    """``compute (function)``: the value is computed by a tool function."""

    loc: Loc
    function: str


PropertyValue = (
    IntValue
    | RealValue
    | StringValue
    | BoolValue
    | EnumValue
    | NameValue
    | RangeValue
    | ListValue
    | RecordValue
    | ReferenceValue
    | ClassifierValue
    | ComputedValue
)


@dataclass(frozen=True, slots=True)
class PropertyAssociation:
    """``Name => value [in modes (..)] [applies to a.b, c] [in binding (..)];`` in a
    ``properties`` section or an inline ``{ }`` block. ``name`` is as written, qualified
    or not (``rpio::Port_Protocol``, ``Period``); ``append`` is ``+=>``."""

    loc: Loc
    name: str
    value: PropertyValue
    applies_to: tuple[str, ...] = ()
    append: bool = False
    constant: bool = False
    in_modes: tuple[str, ...] = ()
    in_binding: tuple[str, ...] = ()

    @property
    def property_set(self) -> str | None:
        """The property set the name is qualified with (``rpio``), or None."""
        head, sep, _ = self.name.rpartition("::")
        return head if sep else None

    @property
    def simple_name(self) -> str:
        """The name without its property set (``Port_Protocol``)."""
        return self.name.rpartition("::")[2]


# ---------------------------------------------------------------- component declarations


@dataclass(frozen=True, slots=True)
class Feature:
    """A feature of a component type. ``kind`` is one of ``event port``, ``data port``,
    ``event data port``, ``parameter``, ``data access``, ``bus access``, ``subprogram
    access``, ``subprogram group access``, ``virtual bus access``, ``feature group``,
    ``feature`` (abstract). ``direction`` is set for ports, parameters and abstract
    features, ``access`` (``provides``/``requires``) for accesses. ``classifier`` is None
    for an untyped feature (``in event port;``)."""

    loc: Loc
    name: str
    kind: str
    direction: Direction | None = None
    access: Literal["provides", "requires"] | None = None
    classifier: str | None = None
    dims: tuple[str, ...] = ()
    properties: tuple[PropertyAssociation, ...] = ()
    refined: bool = False
    inverse: bool = False


@dataclass(frozen=True, slots=True)
class Subcomponent:
    """``name: category [classifier] [dims] [{..}] [in modes (..)];`` of an
    implementation. ``dims`` are the array sizes as written (``"4"``, ``""`` for ``[]``)."""

    loc: Loc
    name: str
    category: str
    classifier: str | None = None
    dims: tuple[str, ...] = ()
    in_modes: tuple[str, ...] = ()
    properties: tuple[PropertyAssociation, ...] = ()
    refined: bool = False


@dataclass(frozen=True, slots=True)
class Connection:
    """A connection of an implementation; ``name`` is None for an anonymous (AADL 1
    style) one. ``kind`` is as written (``port``, ``event data port``, ``parameter``,
    ``bus access``, ``feature group``...); ``source``/``dest`` are paths (``sub.port`` or a
    feature of the implementation itself); ``bidirectional`` is ``<->``."""

    loc: Loc
    name: str | None
    kind: str
    source: str
    dest: str
    bidirectional: bool = False
    in_modes: tuple[str, ...] = ()
    properties: tuple[PropertyAssociation, ...] = ()


@dataclass(frozen=True, slots=True)
class Mode:
    """``name: [initial] mode;``."""

    loc: Loc
    name: str
    initial: bool = False
    properties: tuple[PropertyAssociation, ...] = ()


@dataclass(frozen=True, slots=True)
class ModeTransition:
    """``[name:] m1 [, m2] -[ trigger, .. ]-> m3;``; triggers are paths (``p``,
    ``sub.done``)."""

    loc: Loc
    name: str | None
    sources: tuple[str, ...]
    triggers: tuple[str, ...]
    destination: str
    properties: tuple[PropertyAssociation, ...] = ()


@dataclass(frozen=True, slots=True)
class ComponentType:
    """``category name [extends X] ... end name;``. ``category`` is one of ``system``,
    ``process``, ``thread``, ``thread group``, ``data``, ``subprogram``, ``subprogram
    group``, ``processor``, ``virtual processor``, ``memory``, ``bus``, ``virtual bus``,
    ``device``, ``abstract``. ``flows_skipped`` counts the flow declarations not modelled."""

    loc: Loc
    category: str
    name: str
    extends: str | None = None
    features: tuple[Feature, ...] = ()
    modes: tuple[Mode, ...] = ()
    mode_transitions: tuple[ModeTransition, ...] = ()
    requires_modes: bool = False
    properties: tuple[PropertyAssociation, ...] = ()
    flows_skipped: int = 0


@dataclass(frozen=True, slots=True)
class ComponentImpl:
    """``category implementation T.impl [extends X] ... end T.impl;``. ``name`` is
    ``T.impl``, ``type_name`` is ``T`` (the type it implements, in the same package)."""

    loc: Loc
    category: str
    name: str
    type_name: str
    impl_name: str
    extends: str | None = None
    subcomponents: tuple[Subcomponent, ...] = ()
    connections: tuple[Connection, ...] = ()
    modes: tuple[Mode, ...] = ()
    mode_transitions: tuple[ModeTransition, ...] = ()
    properties: tuple[PropertyAssociation, ...] = ()
    flows_skipped: int = 0


Declaration = ComponentType | ComponentImpl


@dataclass(frozen=True, slots=True)
class Renames:
    """A renames declaration: ``alias renames package a::b;`` (kind ``package``),
    ``alias renames thread a::T;`` (kind = the category), ``alias renames feature group
    a::G;`` (``feature group``), or ``renames a::b::all;`` (kind ``all``, alias None)."""

    loc: Loc
    alias: str | None
    kind: str
    target: str


@dataclass(frozen=True, slots=True)
class Package:
    """``package a::b public ... [private ...] [properties ...] end a::b;``. ``withs`` are
    the imported packages and property sets of both sections, in order; ``with_locs``
    where each of them is written (same order)."""

    loc: Loc
    name: str
    withs: tuple[str, ...] = ()
    renames: tuple[Renames, ...] = ()
    public: tuple[Declaration, ...] = ()
    private: tuple[Declaration, ...] = ()
    properties: tuple[PropertyAssociation, ...] = ()
    with_locs: tuple[Loc, ...] = ()

    @property
    def declarations(self) -> tuple[Declaration, ...]:
        """Public then private classifiers."""
        return self.public + self.private

    def find(self, name: str) -> Declaration | None:
        """The classifier named ``name`` (``T`` or ``T.impl``, any case), or None."""
        key = norm(name)
        return next((d for d in self.declarations if norm(d.name) == key), None)


# ---------------------------------------------------------------- property sets


@dataclass(frozen=True, slots=True)
class UnitLiteral:
    """One unit of a units type: ``Hz`` (the base, no factor) or ``kHz => Hz * 1000``."""

    loc: Loc
    name: str
    base: str | None = None
    factor: int | float | None = None


@dataclass(frozen=True, slots=True)
class RecordFieldType:
    """``name : type;`` inside a ``record ( .. )`` property type."""

    loc: Loc
    name: str
    type: PropertyType
    list_depth: int = 0


@dataclass(frozen=True, slots=True)
class PropertyType:
    """A property type. ``kind`` is ``aadlboolean``, ``aadlstring``, ``aadlinteger``,
    ``aadlreal``, ``enumeration``, ``units``, ``classifier``, ``reference``, ``range``,
    ``record``, or ``named`` (a reference to a declared type, in ``name``).

    Numbers carry their units either as a units type name (``units_name``, e.g.
    ``mbed::Processor_Speed_Units``) or inline (``units``); a ``units`` type lists its
    literals in ``units``. ``owners`` are the categories a classifier/reference type may
    denote; ``element`` is the type of ``range of T``."""

    loc: Loc
    kind: str
    name: str | None = None
    units_name: str | None = None
    units: tuple[UnitLiteral, ...] = ()
    enumerators: tuple[str, ...] = ()
    low: PropertyValue | None = None
    high: PropertyValue | None = None
    owners: tuple[str, ...] = ()
    element: PropertyType | None = None
    fields: tuple[RecordFieldType, ...] = ()


@dataclass(frozen=True, slots=True)
class PropertyTypeDecl:
    """``Name : type <type>;``."""

    loc: Loc
    name: str
    type: PropertyType


@dataclass(frozen=True, slots=True)
class PropertyDefinition:
    """``Name : [inherit] [list of] <type> [=> default] applies to (owners);``.
    ``applies_to`` are the owners as written (``port``, ``access connection``, ``all``)."""

    loc: Loc
    name: str
    type: PropertyType
    list_depth: int = 0
    inherit: bool = False
    default: PropertyValue | None = None
    applies_to: tuple[str, ...] = ()


@dataclass(frozen=True, slots=True)
class PropertyConstant:
    """``Name : constant [list of] <type> => value;``."""

    loc: Loc
    name: str
    type: PropertyType
    value: PropertyValue
    list_depth: int = 0


@dataclass(frozen=True, slots=True)
class PropertySet:
    """``property set Name is [with ..;] ... end Name;``; ``with_locs`` are where the
    names of ``withs`` are written."""

    loc: Loc
    name: str
    withs: tuple[str, ...] = ()
    types: tuple[PropertyTypeDecl, ...] = ()
    definitions: tuple[PropertyDefinition, ...] = ()
    constants: tuple[PropertyConstant, ...] = ()
    with_locs: tuple[Loc, ...] = ()

    def unit_literals(self) -> Iterator[UnitLiteral]:
        """Every unit this set declares, in its units types and inline ``units (..)``."""
        types = [t.type for t in self.types]
        types += [d.type for d in self.definitions] + [c.type for c in self.constants]
        for ptype in types:
            yield from _units_of(ptype)


def _units_of(ptype: PropertyType) -> Iterator[UnitLiteral]:
    yield from ptype.units
    if ptype.element is not None:
        yield from _units_of(ptype.element)
    for field in ptype.fields:
        yield from _units_of(field.type)


@dataclass(frozen=True, slots=True)
class AadlFile:
    """One parsed file: its packages and property sets in order, and the notes about what
    was skipped."""

    source: str
    packages: tuple[Package, ...] = ()
    property_sets: tuple[PropertySet, ...] = ()
    notes: tuple[Note, ...] = ()

"""The located syntax model of RoboChart (``.rct``) and RoboArch (``.rac``) files.

What :mod:`rap_cli.robochart.parse` returns: one frozen dataclass per construct, each
with its :class:`Loc` (file, 1-based line and column of its first token). Names keep their
written case; references (``sref s = M``, ``uses I``, a transition's ``from``) are kept as
written (``a::b`` for qualified names) and are not resolved here. Triggers, guards,
actions and other expressions are :class:`Text`: the source text, verbatim, with where it
starts.

Containers keep their members in source order as tuples, so the model is immutable and
hashable. Nothing here knows about RAP's system model; building it (a state machine per
component, a port per connection endpoint, a message per record) reads these nodes.
"""

from __future__ import annotations

from dataclasses import dataclass
from typing import Literal

from rap_cli.diagnostics import Loc, Note

__all__ = [
    "Clock",
    "Connection",
    "Controller",
    "ControllerRef",
    "Declaration",
    "EnumLiteral",
    "Enumeration",
    "Event",
    "Field",
    "Final",
    "FunctionDecl",
    "FunctionType",
    "Import",
    "Initial",
    "Interface",
    "InterfaceUse",
    "Junction",
    "Layer",
    "LayerBlock",
    "Loc",
    "MachineRef",
    "Module",
    "Node",
    "Note",
    "OperationRef",
    "OperationSig",
    "Param",
    "PlatformRef",
    "PrimitiveType",
    "ProductType",
    "Property",
    "PropertyValue",
    "RacFile",
    "RcFile",
    "Record",
    "RoboticPlatform",
    "SeqType",
    "SetType",
    "State",
    "StateMachine",
    "Text",
    "Transition",
    "TypeExpr",
    "TypeName",
    "TypeParam",
    "Variable",
]


@dataclass(frozen=True, slots=True)
class Text:
    """An expression, trigger, condition or action kept as written (comments inside it
    included), for a later expression parser or for display."""

    text: str
    loc: Loc


# ------------------------------------------------------------------------------ types


@dataclass(frozen=True, slots=True)
class TypeName:
    """A named type: ``real``, ``boolean``, ``LidarRange``, ``Pkg::T`` (as written)."""

    name: str
    loc: Loc


@dataclass(frozen=True, slots=True)
class SeqType:
    """``Seq(T)``: a sequence of ``elem``."""

    elem: TypeExpr
    loc: Loc


@dataclass(frozen=True, slots=True)
class SetType:
    """``Set(T)``: a set of ``elem``."""

    elem: TypeExpr
    loc: Loc


@dataclass(frozen=True, slots=True)
class ProductType:
    """``A * B * C``: a tuple of two or more ``items``."""

    items: tuple[TypeExpr, ...]
    loc: Loc


@dataclass(frozen=True, slots=True)
class FunctionType:
    """``A -> B``: a function type (in function signatures)."""

    domain: TypeExpr
    codomain: TypeExpr
    loc: Loc


@dataclass(frozen=True, slots=True)
class TypeParam:
    """``?X``: a type parameter of a generic function."""

    name: str
    loc: Loc


TypeExpr = TypeName | SeqType | SetType | ProductType | FunctionType | TypeParam


@dataclass(frozen=True, slots=True)
class PrimitiveType:
    """``type X``: a type with no structure given."""

    name: str
    loc: Loc


@dataclass(frozen=True, slots=True)
class Field:
    """``name: type`` in a record."""

    name: str
    type: TypeExpr
    loc: Loc


@dataclass(frozen=True, slots=True)
class Record:
    """``datatype R { ... }`` or ``record R { ... }`` (``kind`` says which was written)."""

    name: str
    kind: Literal["datatype", "record"]
    fields: tuple[Field, ...]
    loc: Loc


@dataclass(frozen=True, slots=True)
class EnumLiteral:
    """One literal of an enumeration."""

    name: str
    loc: Loc


@dataclass(frozen=True, slots=True)
class Enumeration:
    """``enumeration E { A B C }`` (commas between literals optional)."""

    name: str
    literals: tuple[EnumLiteral, ...]
    loc: Loc


# ------------------------------------------------------------------------------ members


@dataclass(frozen=True, slots=True)
class Event:
    """``event e: T``; ``type`` is None for an untyped event."""

    name: str
    type: TypeExpr | None
    loc: Loc


@dataclass(frozen=True, slots=True)
class Variable:
    """``var v: T`` or ``const c: T`` (``const`` is True), with its initial value if any."""

    name: str
    type: TypeExpr
    const: bool
    value: Text | None
    loc: Loc


@dataclass(frozen=True, slots=True)
class Clock:
    """``clock c``."""

    name: str
    loc: Loc


@dataclass(frozen=True, slots=True)
class Param:
    """``name: type`` in an operation or function signature."""

    name: str
    type: TypeExpr
    loc: Loc


@dataclass(frozen=True, slots=True)
class OperationSig:
    """``op(p: T, ...)``: an operation an interface or platform offers."""

    name: str
    params: tuple[Param, ...]
    loc: Loc


@dataclass(frozen=True, slots=True)
class InterfaceUse:
    """``uses I`` / ``provides I`` / ``requires I``."""

    kind: Literal["uses", "provides", "requires"]
    interface: str
    loc: Loc


@dataclass(frozen=True, slots=True)
class Connection:
    """``connection A on e to B on f (_async) (_bidirec)``; in RoboArch, one item of
    ``connections = ...``. Node names are machine, controller or platform references as
    written (or the enclosing controller's or platform's own name)."""

    from_node: str
    from_event: str
    to_node: str
    to_event: str
    asynchronous: bool
    bidirectional: bool
    loc: Loc


# ------------------------------------------------------------------------------ interfaces


@dataclass(frozen=True, slots=True)
class Interface:
    """``interface I { ... }``: events, variables (``var`` and ``const``), operations."""

    name: str
    events: tuple[Event, ...]
    variables: tuple[Variable, ...]
    operations: tuple[OperationSig, ...]
    clocks: tuple[Clock, ...]
    loc: Loc

    @property
    def consts(self) -> tuple[Variable, ...]:
        """The ``const`` members among :attr:`variables`."""
        return tuple(v for v in self.variables if v.const)


@dataclass(frozen=True, slots=True)
class RoboticPlatform:
    """``robotic platform P { ... }``."""

    name: str
    uses: tuple[InterfaceUse, ...]
    provides: tuple[InterfaceUse, ...]
    requires: tuple[InterfaceUse, ...]
    events: tuple[Event, ...]
    variables: tuple[Variable, ...]
    operations: tuple[OperationSig, ...]
    clocks: tuple[Clock, ...]
    loc: Loc


# ------------------------------------------------------------------------------ state machines


@dataclass(frozen=True, slots=True)
class Initial:
    """``initial i``."""

    name: str
    loc: Loc


@dataclass(frozen=True, slots=True)
class Final:
    """``final f``."""

    name: str
    loc: Loc


@dataclass(frozen=True, slots=True)
class Junction:
    """``junction j`` or ``probabilistic junction j``."""

    name: str
    probabilistic: bool
    loc: Loc


@dataclass(frozen=True, slots=True)
class Transition:
    """``transition t { from a to b trigger ... probability ... condition ... action ... }``.
    ``source``/``target`` are node names as written; ``guard`` is the ``condition``."""

    name: str
    source: str
    target: str
    trigger: Text | None
    probability: Text | None
    guard: Text | None
    action: Text | None
    loc: Loc


@dataclass(frozen=True, slots=True)
class State:
    """``state S { entry ... during ... exit ... <nodes> <transitions> }``."""

    name: str
    entry: Text | None
    during: Text | None
    exit: Text | None
    nodes: tuple[Node, ...]
    transitions: tuple[Transition, ...]
    loc: Loc


Node = State | Initial | Final | Junction


@dataclass(frozen=True, slots=True)
class OperationRef:
    """An operation a controller or machine has: ``opref o = O`` (``target`` set) or an
    inline ``operation O(...) { ... }`` (``definition`` set)."""

    name: str
    target: str | None
    definition: StateMachine | None
    loc: Loc


@dataclass(frozen=True, slots=True)
class StateMachine:
    """``stm M { ... }``, or ``operation O(params) { ... }`` (``kind`` "operation"), which
    has the same body. ``nodes`` are the top-level nodes; states nest further ones."""

    name: str
    kind: Literal["stm", "operation"]
    params: tuple[Param, ...]
    uses: tuple[InterfaceUse, ...]
    provides: tuple[InterfaceUse, ...]
    requires: tuple[InterfaceUse, ...]
    variables: tuple[Variable, ...]
    events: tuple[Event, ...]
    clocks: tuple[Clock, ...]
    operations: tuple[OperationRef, ...]
    nodes: tuple[Node, ...]
    transitions: tuple[Transition, ...]
    loc: Loc


# ------------------------------------------------------------------------------ controllers


@dataclass(frozen=True, slots=True)
class MachineRef:
    """A state machine of a controller: ``sref s = M`` / ``ref s = M`` / ``cref s = M``
    (``kind`` as written, ``target`` the machine's name) or an inline ``stm`` (``kind``
    "stm", ``definition`` set, ``name`` the machine's own name)."""

    name: str
    kind: Literal["sref", "ref", "cref", "stm"]
    target: str | None
    definition: StateMachine | None
    loc: Loc


@dataclass(frozen=True, slots=True)
class Controller:
    """``controller C { ... }``."""

    name: str
    uses: tuple[InterfaceUse, ...]
    provides: tuple[InterfaceUse, ...]
    requires: tuple[InterfaceUse, ...]
    events: tuple[Event, ...]
    variables: tuple[Variable, ...]
    clocks: tuple[Clock, ...]
    machines: tuple[MachineRef, ...]
    operations: tuple[OperationRef, ...]
    connections: tuple[Connection, ...]
    loc: Loc


@dataclass(frozen=True, slots=True)
class PlatformRef:
    """A module's platform: ``rref p = P`` / ``robotic platform p = P`` (``target``) or an
    inline ``robotic platform P { ... }`` (``definition``)."""

    name: str
    target: str | None
    definition: RoboticPlatform | None
    loc: Loc


@dataclass(frozen=True, slots=True)
class ControllerRef:
    """A module's controller: ``cref c = C`` (``target``) or an inline ``controller``."""

    name: str
    target: str | None
    definition: Controller | None
    loc: Loc


@dataclass(frozen=True, slots=True)
class Module:
    """``module M { ... }``: the platform, controllers and their connections."""

    name: str
    platform: PlatformRef | None
    controllers: tuple[ControllerRef, ...]
    connections: tuple[Connection, ...]
    loc: Loc


@dataclass(frozen=True, slots=True)
class FunctionDecl:
    """``function f(params): T { precondition ... postcondition ... }``: the signature,
    and the conditions as text."""

    name: str
    params: tuple[Param, ...]
    result: TypeExpr
    preconditions: tuple[Text, ...]
    postconditions: tuple[Text, ...]
    loc: Loc


@dataclass(frozen=True, slots=True)
class Import:
    """``import a::b`` (``wildcard`` False) or ``import a::*`` (``path`` "a")."""

    path: str
    wildcard: bool
    loc: Loc


Declaration = (
    PrimitiveType
    | Record
    | Enumeration
    | Interface
    | RoboticPlatform
    | Controller
    | StateMachine
    | Module
    | FunctionDecl
    | Variable
)


@dataclass(frozen=True, slots=True)
class RcFile:
    """One ``.rct`` file: its package (None when it has no ``package`` line), imports,
    top-level declarations in source order, and notes about what was skipped."""

    package: str | None
    imports: tuple[Import, ...]
    declarations: tuple[Declaration, ...]
    notes: tuple[Note, ...]
    loc: Loc


# ------------------------------------------------------------------------------ RoboArch


@dataclass(frozen=True, slots=True)
class PropertyValue:
    """One item of a RoboArch ``key = a : T, b, MAPLE-K;``: a name with an optional type,
    a hyphenated word (``MAPLE-K``), or a literal number or string (``type`` None)."""

    name: str
    type: TypeExpr | None
    loc: Loc


@dataclass(frozen=True, slots=True)
class Property:
    """``key = value, ...;`` inside a RoboArch layer or block."""

    key: str
    values: tuple[PropertyValue, ...]
    loc: Loc


@dataclass(frozen=True, slots=True)
class LayerBlock:
    """``name { ... }`` inside a layer, such as a MAPLE-K stage (``monitor { ... }``)."""

    name: str
    uses: tuple[InterfaceUse, ...]
    provides: tuple[InterfaceUse, ...]
    requires: tuple[InterfaceUse, ...]
    properties: tuple[Property, ...]
    blocks: tuple[LayerBlock, ...]
    loc: Loc

    def values(self, key: str) -> tuple[PropertyValue, ...]:
        """Every value of every ``key = ...;`` in this block, in order."""
        return tuple(v for p in self.properties if p.key == key for v in p.values)


@dataclass(frozen=True, slots=True)
class Layer:
    """``layer L : Type { ... };``. ``inputs``, ``outputs`` and ``pattern`` come from
    the properties of those names; ``properties`` keeps the others; ``stages`` are the
    nested blocks (the MAPLE-K stages for ``pattern = MAPLE-K``)."""

    name: str
    layer_type: str | None
    uses: tuple[InterfaceUse, ...]
    provides: tuple[InterfaceUse, ...]
    requires: tuple[InterfaceUse, ...]
    inputs: tuple[PropertyValue, ...]
    outputs: tuple[PropertyValue, ...]
    pattern: str | None
    stages: tuple[LayerBlock, ...]
    properties: tuple[Property, ...]
    loc: Loc


@dataclass(frozen=True, slots=True)
class RacFile:
    """One ``.rac`` file: the system's name, its type and interface declarations, layers,
    the ``connections = ...;`` between layers and platform, and notes."""

    system: str
    declarations: tuple[Declaration, ...]
    layers: tuple[Layer, ...]
    connections: tuple[Connection, ...]
    notes: tuple[Note, ...]
    loc: Loc

"""The syntax tree of a trust spec (both syntax eras parse to it).

Every node carries ``pos`` (1-based line and column in the spec source) so that type
and run-time errors can point at the text. Nodes are frozen dataclasses: a compiled
spec keeps the tree it came from, and hot swap compares trees.

Desugaring done by the parser, so the evaluator sees one form:

- D5.2 ``x[-k, c]`` is ``Call("default", (Index(x, k), c))``; ``x[-k]`` is ``Index(x, k)``.
- ``dynamic(s)`` is ``Eval(s, kind="eval")``; ``var`` declarations are ``aux``.
- ``List(a, b)`` is ``ListLit``; ``{k: e}`` and ``Struct("k": e)`` are ``StructLit``.
- ``a != b`` is ``Unary("!", Binary("==", a, b))`` (three-valued, like ``==``).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal, TypeAlias

__all__ = [
    "AGGREGATES",
    "BUILTINS",
    "Aggregate",
    "Binary",
    "Call",
    "Decl",
    "Equation",
    "Eval",
    "Expr",
    "Field",
    "If",
    "Index",
    "ListLit",
    "Lit",
    "MapLit",
    "Pos",
    "Spec",
    "StructLit",
    "TAny",
    "TList",
    "TMap",
    "TName",
    "TStruct",
    "TTuple",
    "Trigger",
    "TupleLit",
    "Type",
    "Unary",
    "Var",
]


@dataclass(frozen=True, slots=True)
class Pos:
    line: int
    col: int

    def __str__(self) -> str:
        return f"{self.line}:{self.col}"


NOWHERE = Pos(0, 0)

# -- types -------------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TName:
    """``Int`` (64-bit), ``Float``, ``Str``, ``Bool``, ``Unit`` or ``Any``."""

    name: Literal["Int", "Float", "Str", "Bool", "Unit", "Any"]

    def __str__(self) -> str:
        return self.name


TAny = TName("Any")


@dataclass(frozen=True, slots=True)
class TList:
    elem: Type

    def __str__(self) -> str:
        return f"List<{self.elem}>"


@dataclass(frozen=True, slots=True)
class TMap:
    """String keys; ``value`` is the type of the values."""

    value: Type

    def __str__(self) -> str:
        return f"Map<{self.value}>"


@dataclass(frozen=True, slots=True)
class TStruct:
    fields: tuple[tuple[str, Type], ...]

    def __str__(self) -> str:
        return "Struct<" + ", ".join(f"{k}: {t}" for k, t in self.fields) + ">"


@dataclass(frozen=True, slots=True)
class TTuple:
    items: tuple[Type, ...]

    def __str__(self) -> str:
        return "(" + ", ".join(map(str, self.items)) + ")"


Type: TypeAlias = TName | TList | TMap | TStruct | TTuple

# -- expressions -------------------------------------------------------------------------

BUILTINS: frozenset[str] = frozenset(
    {
        "default",
        "init",
        "is_defined",
        "when",
        "latch",
        "update",
        "sin",
        "cos",
        "tan",
        "abs",
        "List.get",
        "List.concat",
        "List.append",
        "List.head",
        "List.tail",
        "List.len",
        "Map.get",
        "Map.insert",
        "Map.remove",
        "Map.has_key",
        "timeout",
    }
)
"""Functions ``Call.func`` may name (``timeout(x, 2s)`` is RAP's, real time)."""

AGGREGATES: frozenset[str] = frozenset({"count", "sum", "avg", "min", "max"})


@dataclass(frozen=True, slots=True)
class Lit:
    """A literal: int, float, bool, str, or ``UNIT`` (see :mod:`trust_checker.values`)."""

    value: object
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Var:
    name: str
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Index:
    """``x[k]``: k >= 0 ticks into the past (the stream's held value k ticks ago)."""

    expr: Expr
    offset: int
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Unary:
    op: Literal["-", "!"]
    operand: Expr
    pos: Pos = field(default=NOWHERE, compare=False)


BinOp: TypeAlias = Literal[
    "++", "=>", "||", "&&", "==", "<", "<=", ">", ">=", "+", "-", "*", "/", "%"
]


@dataclass(frozen=True, slots=True)
class Binary:
    op: BinOp
    left: Expr
    right: Expr
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class If:
    cond: Expr
    then: Expr
    else_: Expr
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Call:
    """A built-in (``func`` in :data:`BUILTINS`, e.g. ``"default"``, ``"List.get"``)."""

    func: str
    args: tuple[Expr, ...]
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Eval:
    """``eval(s)`` / ``dynamic(s)`` (kind ``eval``) and ``defer(s)``: ``source`` is a Str
    stream holding an expression; optional ascription ``eval(s: Int)`` and scope
    ``eval(s, {x, y})`` (None: every stream of the spec)."""

    source: Expr
    kind: Literal["eval", "defer"]
    ascription: Type | None = None
    scope: tuple[str, ...] | None = None
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class ListLit:
    items: tuple[Expr, ...]
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class MapLit:
    pairs: tuple[tuple[str, Expr], ...]
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class StructLit:
    fields: tuple[tuple[str, Expr], ...]
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class TupleLit:
    items: tuple[Expr, ...]
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Field:
    """``s.f`` on a struct, ``t.0`` on a tuple (``name`` is then the digits)."""

    expr: Expr
    name: str
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Aggregate:
    """RAP's real time: ``x.aggregate(over: 5s, using: count)``: the values x took in the
    last ``window_ns`` of tick time, folded with ``using``."""

    expr: Expr
    window_ns: int
    using: Literal["count", "sum", "avg", "min", "max"]
    pos: Pos = field(default=NOWHERE, compare=False)


Expr: TypeAlias = (
    Lit
    | Var
    | Index
    | Unary
    | Binary
    | If
    | Call
    | Eval
    | ListLit
    | MapLit
    | StructLit
    | TupleLit
    | Field
    | Aggregate
)

# -- the spec ----------------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Decl:
    kind: Literal["in", "out", "aux"]
    name: str
    type: Type | None = None
    period_ns: int | None = None
    """RAP's real time: ``out y @ 10Hz`` also ticks every period (None: only on input)."""
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Equation:
    name: str
    expr: Expr
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Trigger:
    """RAP's ``trigger COND "message" [info|warning|error|critical]``: a verdict whenever
    COND is true (default severity ``warning``)."""

    cond: Expr
    message: str
    severity: Literal["info", "warning", "error", "critical"] = "warning"
    pos: Pos = field(default=NOWHERE, compare=False)


@dataclass(frozen=True, slots=True)
class Spec:
    decls: tuple[Decl, ...]
    equations: tuple[Equation, ...]
    triggers: tuple[Trigger, ...] = ()
    order: tuple[str, ...] = ()
    """Every stream name in order of first appearance in the source (console order)."""
    source: str = field(default="", compare=False)
    path: str = field(default="<spec>", compare=False)

    def decl(self, name: str) -> Decl | None:
        return next((d for d in self.decls if d.name == name), None)

    @property
    def inputs(self) -> tuple[str, ...]:
        return tuple(d.name for d in self.decls if d.kind == "in")

    @property
    def outputs(self) -> tuple[str, ...]:
        """Output names in console order."""
        outs = {d.name for d in self.decls if d.kind == "out"}
        return tuple(n for n in self.order if n in outs)

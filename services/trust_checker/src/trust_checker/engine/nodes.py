"""The compiled form of a spec's expressions: stream slots and expression nodes.

Each AST node compiles (:mod:`.compiler`) to an :class:`ExprNode`: its AST node, its
operand nodes and three closures:

- ``held()``: the node's held value at the current tick (its latest value that was not
  NoVal; NoVal until it has had one). Operators call their operands' ``held`` - that is
  how "operators hold their operands" is implemented.
- ``cur()``: the value at this tick, NoVal where the node did not tick. It differs from
  ``held`` only for the nodes that pass NoVal through: a bare reference, ``latch``,
  ``init`` once its operand has had a value, and ``eval``.
- ``started``: ``None`` if the node always has a value, else a closure telling whether it
  has had one yet, without computing it (so a lazy ``if`` can tell that its untaken
  branch has a value without evaluating it).

A pure lifted node (:mod:`.lifted`) is a function of its operands' held values, so it
needs no state and, once it has a value, ticks on every tick (``cur is held``). The nodes
with state (:mod:`.stateful`, :mod:`.dynamic`) are :class:`StatefulNode`: the runner calls
their ``update()`` once per tick before the stream that contains them is computed.

Streams are :class:`Stream` slots (``cur``, ``held`` and a bounded history of held values);
the runner (:mod:`.runner`) orders them and steps them. Nodes can be inspected between
ticks: ``node.value()`` is the node's held value at the last tick.
"""

from __future__ import annotations

from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, Final, Protocol, cast

from trust_checker.lang import ast
from trust_checker.operators import Fault
from trust_checker.values import NOVAL, MapV

__all__ = [
    "INF",
    "PY_TYPES",
    "ConstNode",
    "ExprNode",
    "Fused",
    "Holder",
    "Source",
    "StatefulNode",
    "Stream",
    "Thunk",
    "TickTime",
    "VarNode",
    "all_started",
    "const",
    "located",
    "type_hint",
    "value_hint",
]

INF: Final = 1 << 62
"""An unbounded number of drain ticks (a literal's ``extra``)."""

Thunk = Callable[[], object]


class TickTime:
    """The current tick's timestamp (ns), shared by the real-time nodes."""

    __slots__ = ("ts",)

    def __init__(self) -> None:
        self.ts: int | None = None


class Stream:
    """One stream's state: value at this tick, held value, history of held values
    (``hist[-k]`` is the held value k ticks ago; NoVal there: none yet)."""

    __slots__ = ("cur", "decl", "extra", "held", "hidden", "hist", "kind", "name", "next")

    def __init__(self, name: str, kind: str, decl: ast.Decl | None, *, hidden: bool = False):
        self.name = name
        self.kind = kind
        self.decl = decl
        self.hidden = hidden
        self.cur: object = NOVAL
        self.held: object = NOVAL
        self.hist: deque[object] | None = None
        self.extra = 0
        self.next: object = NOVAL
        """An input's value for the tick being taken (checked, not yet in force)."""

    def __repr__(self) -> str:
        return f"Stream({self.name!r}, cur={self.cur!r}, held={self.held!r})"


class Source(Protocol):
    held: object


Fused = tuple[Callable[..., Any], Source, Source, type | None, type | None]


PY_TYPES: Final[dict[str, type]] = {"Int": int, "Float": float, "Str": str, "Bool": bool}


def type_hint(decl: ast.Decl | None) -> type | None:
    """The Python type of a declared stream's data values (None: not one type)."""
    t = decl.type if decl is not None else None
    if isinstance(t, ast.TName):
        return PY_TYPES.get(t.name)
    if isinstance(t, ast.TMap):
        return MapV
    if isinstance(t, ast.TList):
        return tuple
    return None


class ExprNode:
    """A compiled expression node (see the module docstring)."""

    __slots__ = ("ast", "children", "cur", "fused", "held", "hint", "src", "started")

    def __init__(
        self,
        node: ast.Expr,
        children: Sequence[ExprNode],
        held: Thunk,
        cur: Thunk | None = None,
        started: Callable[[], bool] | None = None,
        hint: type | None = None,
    ) -> None:
        self.ast = node
        self.children = tuple(children)
        self.held = held
        self.cur = held if cur is None else cur
        self.started = started
        self.hint = hint
        """The Python type the node's data values are expected to have (None: unknown);
        operators use it to choose a fast path, guarded by the actual type."""
        self.src: Source | None = None
        """For a stream reference or a constant: where operators read the held value
        (``src.held``) without a call."""
        self.fused: Fused | None
        self.fused = None
        """For ``a op b`` on two references or constants with a fast path: the operator,
        both sources and their expected types, so that a parent (``if``) can compute it
        in place, calling this node only off the fast path."""

    def value(self) -> object:
        """The held value at the last tick (recomputed; call between ticks)."""
        return self.held()


class VarNode(ExprNode):
    """A bare stream reference (operators read ``stream.held`` directly)."""

    __slots__ = ("stream",)

    def __init__(self, node: ast.Var, stream: Stream) -> None:
        def held() -> object:
            return stream.held

        def cur() -> object:
            return stream.cur

        def started() -> bool:
            return stream.held is not NOVAL

        super().__init__(node, (), held, cur, started, type_hint(stream.decl))
        self.stream = stream
        self.src = stream


class StatefulNode(ExprNode):
    """A node with state, updated once per tick by the runner (``update``)."""

    __slots__ = ("cur_v", "held_v")

    def __init__(self, node: ast.Expr, children: Sequence[ExprNode], *, always: bool) -> None:
        self.cur_v: object = NOVAL
        self.held_v: object = NOVAL
        me = self

        def held() -> object:
            return me.held_v

        def cur() -> object:
            return me.cur_v

        def started() -> bool:
            return me.held_v is not NOVAL

        super().__init__(node, children, held, cur, None if always else started)

    def update(self) -> None:
        raise NotImplementedError

    def _set(self, v: object) -> None:
        self.cur_v = v
        if v is not NOVAL:
            self.held_v = v

    def export(self) -> object:
        """The state to carry over a hot swap (see :meth:`restore`)."""
        return (self.cur_v, self.held_v)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v = state  # type: ignore[misc]


def located(f: Fault, where: str) -> Fault:
    if not f.where:
        f.where = where
    return f


def all_started(kids: Sequence[ExprNode]) -> Callable[[], bool] | None:
    checks = [k.started for k in kids if k.started is not None]
    if not checks:
        return None
    done = False

    def started() -> bool:
        nonlocal done
        if done:
            return True
        for c in checks:
            if not c():
                return False
        done = True
        return True

    return started


def value_hint(k: ExprNode) -> type | None:
    """The type of the values in the map (or list) ``k``, when one is known."""
    if isinstance(k, ConstNode) and type(k.const) in (MapV, tuple):
        c = k.const
        vals = c.values() if type(c) is MapV else cast(tuple[object, ...], c)
        types = {type(v) for v in vals}
        return types.pop() if len(types) == 1 else None
    if isinstance(k, VarNode) and k.stream.decl is not None:
        t = k.stream.decl.type
        if isinstance(t, ast.TMap | ast.TList):
            inner = t.value if isinstance(t, ast.TMap) else t.elem
            return PY_TYPES.get(inner.name) if isinstance(inner, ast.TName) else None
    return None


class Holder:
    """A constant operand, read like a stream (``.held``)."""

    __slots__ = ("held",)

    def __init__(self, v: object) -> None:
        self.held = v


class ConstNode(ExprNode):
    """A literal, or a pure operator over constants folded when compiled: the same value
    on every tick."""

    __slots__ = ("const",)

    def __init__(self, node: ast.Expr, children: Sequence[ExprNode], v: object) -> None:
        def held() -> object:
            return v

        super().__init__(node, children, held)
        self.const = v
        self.src = Holder(v)
        self.hint = type(v)


def const(node: ast.Expr, v: object) -> ExprNode:
    return ConstNode(node, (), v)

"""Compiling expressions into closures (no Python source, no ``compile``/``exec``).

Each AST node becomes a :class:`Node`: its AST node, its operand nodes and three closures:

- ``held()``: the node's held value at the current tick (its latest value that was not
  NoVal; NoVal until it has had one). Operators call their operands' ``held`` - that is
  how "operators hold their operands" is implemented.
- ``cur()``: the value at this tick, NoVal where the node did not tick. It differs from
  ``held`` only for the nodes that pass NoVal through: a bare reference, ``latch``,
  ``init`` once its operand has had a value, and ``eval``.
- ``started``: ``None`` if the node always has a value, else a closure telling whether it
  has had one yet, without computing it (so a lazy ``if`` can tell that its untaken
  branch has a value without evaluating it).

A pure lifted node's value is a function of its operands' held values, so it needs no
state and, once it has a value, ticks on every tick (``cur is held``). The nodes with
state (``when``, ``latch``, ``update``, ``timeout``, aggregates, ``eval``) are
:class:`StatefulNode`: the monitor calls their ``update()`` once per tick before the
stream that contains them is computed.

Streams are :class:`Stream` slots (``cur``, ``held`` and a bounded history of held values);
the monitor (:mod:`trust_checker.monitor`) orders them and steps them. Nodes can be
inspected between ticks: ``node.value()`` is the node's held value at the last tick.

Speed (measured in bench/trust), with the semantics unchanged:

- a pure operator over constants is folded into a :class:`ConstNode` when compiled
  (``Map("a": 1)`` is built once, not on every tick);
- an operator reads an operand that is a stream reference or a constant in place
  (``node.src.held``), and is one closure per shape of its operands, so it costs one
  Python call;
- where the operands' types are known from the spec, the operation is first tried on
  exactly those types with Python's own operator (``type(a) is int and type(b) is int``:
  ``a + b``, range-checked), every other case taking the general path of
  :mod:`trust_checker.operators`; an ``if`` computes a comparison condition in place.
"""

from __future__ import annotations

import math
import operator as _pyop
from collections import deque
from collections.abc import Callable, Sequence
from typing import Any, Final, Protocol, cast

from trust_checker import operators as op
from trust_checker.errors import SpecError
from trust_checker.lang import ast
from trust_checker.lang.parser import parse_expr
from trust_checker.operators import Fault, Mismatch
from trust_checker.values import BOTTOM, INT_MAX, INT_MIN, NOVAL, MapV, StructV, TupleV, console

__all__ = [
    "INF",
    "Clock",
    "Compiler",
    "ConstNode",
    "EvalNode",
    "Node",
    "StatefulNode",
    "Stream",
    "VarNode",
    "type_hint",
]

INF: Final = 1 << 62
"""An unbounded number of drain ticks (a literal's ``extra``)."""

Thunk = Callable[[], object]


class Clock:
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


class _Source(Protocol):
    held: object


_Fused = tuple[Callable[..., Any], _Source, _Source, type | None, type | None]


_PY_TYPES: Final[dict[str, type]] = {"Int": int, "Float": float, "Str": str, "Bool": bool}


def type_hint(decl: ast.Decl | None) -> type | None:
    """The Python type of a declared stream's data values (None: not one type)."""
    t = decl.type if decl is not None else None
    if isinstance(t, ast.TName):
        return _PY_TYPES.get(t.name)
    if isinstance(t, ast.TMap):
        return MapV
    if isinstance(t, ast.TList):
        return tuple
    return None


class Node:
    """A compiled expression node (see the module docstring)."""

    __slots__ = ("ast", "children", "cur", "fused", "held", "hint", "src", "started")

    def __init__(
        self,
        node: ast.Expr,
        children: Sequence[Node],
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
        self.src: _Source | None = None
        """For a stream reference or a constant: where operators read the held value
        (``src.held``) without a call."""
        self.fused: _Fused | None
        self.fused = None
        """For ``a op b`` on two references or constants with a fast path: the operator,
        both sources and their expected types, so that a parent (``if``) can compute it
        in place, calling this node only off the fast path."""

    def value(self) -> object:
        """The held value at the last tick (recomputed; call between ticks)."""
        return self.held()


class VarNode(Node):
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


class StatefulNode(Node):
    """A node with state, updated once per tick by the monitor (``update``)."""

    __slots__ = ("cur_v", "held_v")

    def __init__(self, node: ast.Expr, children: Sequence[Node], *, always: bool) -> None:
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


def _located(f: Fault, where: str) -> Fault:
    if not f.where:
        f.where = where
    return f


# -- pure lifted nodes ----------------------------------------------------------------------
#
# Operators read an operand in one of two ways: a stream reference or a constant through
# its ``src`` (an object whose ``held`` attribute is the value: the stream itself, or a
# :class:`_Holder`), anything else by calling its ``held()``. Each operator node is one
# closure for its operands' shape (``src``/call on each side), so the common cases cost
# one Python call per operator. Where the operands' types are known from the spec (a
# declared stream type, a literal, another operator's result), the closure first tries
# the operation on exactly those types with the plain Python operator, which for those
# types computes what :mod:`trust_checker.operators` does; any other value (NoVal, ⊥, a
# value of another type, an Int result outside 64 bits) takes the general path. The hints
# only choose the fast path: a wrong hint costs speed, never a different value.


def _all_started(kids: Sequence[Node]) -> Callable[[], bool] | None:
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


Fast = tuple[Callable[..., Any], bool, type | None]
"""A fast path: the Python operator, whether an Int result needs the 64-bit range
check, and the result's type (a hint for the node's parent)."""

_NUM: Final = (int, float)
_FAST2: Final[dict[tuple[str, type, type], Fast]] = {}
for _t in (int, float, str, bool):
    _FAST2["==", _t, _t] = (_pyop.eq, False, bool)
for _a in _NUM:
    for _b in _NUM:
        if _a is not _b:  # Int == Float compares the numbers, as Python does
            _FAST2["==", _a, _b] = (_pyop.eq, False, bool)
for _name, _fn in (("<", _pyop.lt), ("<=", _pyop.le), (">", _pyop.gt), (">=", _pyop.ge)):
    _FAST2[_name, str, str] = (_fn, False, bool)
    for _a in _NUM:
        for _b in _NUM:
            _FAST2[_name, _a, _b] = (_fn, False, bool)
for _name, _fn in (("+", _pyop.add), ("-", _pyop.sub), ("*", _pyop.mul)):
    _FAST2[_name, int, int] = (_fn, True, int)
    # Int with Float: Python converts the Int with float(), as the operators do
    for _a, _b in ((float, float), (int, float), (float, int)):
        _FAST2[_name, _a, _b] = (_fn, False, float)
_FAST2["&&", bool, bool] = (_pyop.and_, False, bool)
_FAST2["||", bool, bool] = (_pyop.or_, False, bool)
_FAST2["=>", bool, bool] = (_pyop.le, False, bool)  # on Bools, a => b is a <= b
_FAST2["++", str, str] = (_pyop.add, False, str)


def _map_get(m: MapV, k: str) -> object:
    return m.get(k, BOTTOM)


def _map_remove(m: MapV, k: str) -> object:
    out = MapV(m)
    out.pop(k, None)
    return out


_FAST_CALL2: Final[dict[tuple[str, type, type], Fast]] = {
    ("Map.get", MapV, str): (_map_get, False, None),
    ("Map.has_key", MapV, str): (_pyop.contains, False, bool),
    ("Map.remove", MapV, str): (_map_remove, False, MapV),
}


def _list_append(items: tuple[object, ...], x: object) -> object:
    return items + (x,)  # noqa: RUF005 (a tuple concatenation copies in one step)


for _t in (int, float, str, bool):
    _FAST_CALL2["List.append", tuple, _t] = (_list_append, False, tuple)


def _list_head(items: tuple[object, ...]) -> object:
    return items[0] if items else BOTTOM


_FAST_CALL1: Final[dict[tuple[str, type], Fast]] = {
    ("List.head", tuple): (_list_head, False, None),
    ("List.len", tuple): (len, False, int),
    ("List.tail", tuple): (_pyop.itemgetter(slice(1, None)), False, tuple),
}
_FAST1: Final[dict[tuple[str, type], Fast]] = {
    ("-", float): (_pyop.neg, False, float),
    ("!", bool): (_pyop.not_, False, bool),
}


def _slow2(
    fn: Callable[[object, object], object], where: str
) -> Callable[[object, object], object]:
    """The general path of a lifted binary node: NoVal, then ⊥, then ``fn``."""

    def slow(a: object, b: object) -> object:
        if a is NOVAL or b is NOVAL:
            return NOVAL
        if a is BOTTOM or b is BOTTOM:
            return BOTTOM
        try:
            return fn(a, b)
        except Fault as e:
            raise _located(e, where) from None

    return slow


def _lift1(
    node: ast.Expr, kid: Node, fn: Callable[[object], object], where: str, fast: Fast | None = None
) -> Node:
    fa, sa = kid.held, kid.src

    def slow(a: object) -> object:
        if a is NOVAL or a is BOTTOM:
            return a
        try:
            return fn(a)
        except Fault as e:
            raise _located(e, where) from None

    held: Thunk
    if fast is not None:
        pyop, _, hint = fast
        ta = kid.hint
        if sa is not None:

            def held() -> object:
                a = sa.held
                if type(a) is ta:
                    return pyop(a)
                return slow(a)

        else:

            def held() -> object:
                a = fa()
                if type(a) is ta:
                    return pyop(a)
                return slow(a)

        return Node(node, (kid,), held, None, kid.started, hint)
    if sa is not None:

        def held() -> object:
            a = sa.held
            if a is NOVAL or a is BOTTOM:
                return a
            try:
                return fn(a)
            except Fault as e:
                raise _located(e, where) from None

    else:

        def held() -> object:
            a = fa()
            if a is NOVAL or a is BOTTOM:
                return a
            try:
                return fn(a)
            except Fault as e:
                raise _located(e, where) from None

    return Node(node, (kid,), held, None, kid.started)


def _lift2(
    node: ast.Expr,
    ka: Node,
    kb: Node,
    fn: Callable[[object, object], object],
    where: str,
    fast: Fast | None = None,
) -> Node:
    """A lifted binary node (see the section comment for ``fast`` and the shapes)."""
    kids = (ka, kb)
    started = _all_started(kids)
    if fast is None:
        return _lift2_general(node, ka, kb, fn, where, started)
    pyop, checked, hint = fast
    slow = _slow2(fn, where)
    if not checked and (ka.fused is not None or kb.fused is not None):
        return _lift2_fused(node, ka, kb, pyop, slow, started, hint)
    sa, sb, fa, fb = ka.src, kb.src, ka.held, kb.held
    ta, tb = ka.hint, kb.hint
    lo, hi = INT_MIN, INT_MAX
    held: Thunk
    if checked:
        if sa is not None and sb is not None:

            def held() -> object:
                a = sa.held
                b = sb.held
                if type(a) is ta and type(b) is tb:
                    r = pyop(a, b)
                    if lo <= r <= hi:
                        return r
                return slow(a, b)

        elif sa is not None:

            def held() -> object:
                a = sa.held
                b = fb()
                if type(a) is ta and type(b) is tb:
                    r = pyop(a, b)
                    if lo <= r <= hi:
                        return r
                return slow(a, b)

        elif sb is not None:

            def held() -> object:
                a = fa()
                b = sb.held
                if type(a) is ta and type(b) is tb:
                    r = pyop(a, b)
                    if lo <= r <= hi:
                        return r
                return slow(a, b)

        else:

            def held() -> object:
                a = fa()
                b = fb()
                if type(a) is ta and type(b) is tb:
                    r = pyop(a, b)
                    if lo <= r <= hi:
                        return r
                return slow(a, b)

    elif sa is not None and sb is not None:

        def held() -> object:
            a = sa.held
            b = sb.held
            if type(a) is ta and type(b) is tb:
                return pyop(a, b)
            return slow(a, b)

        n = Node(node, kids, held, None, started, hint)
        n.fused = (pyop, sa, sb, ta, tb)
        return n

    elif sa is not None:

        def held() -> object:
            a = sa.held
            b = fb()
            if type(a) is ta and type(b) is tb:
                return pyop(a, b)
            return slow(a, b)

    elif sb is not None:

        def held() -> object:
            a = fa()
            b = sb.held
            if type(a) is ta and type(b) is tb:
                return pyop(a, b)
            return slow(a, b)

    else:

        def held() -> object:
            a = fa()
            b = fb()
            if type(a) is ta and type(b) is tb:
                return pyop(a, b)
            return slow(a, b)

    return Node(node, kids, held, None, started, hint)


_UNFUSED: Final = cast(_Fused, (None, None, None, None, None))
"""Stands for an operand that is not fused (its parts are never read)."""


def _lift2_fused(
    node: ast.Expr,
    ka: Node,
    kb: Node,
    pyop: Callable[..., Any],
    slow: Callable[[object, object], object],
    started: Callable[[], bool] | None,
    hint: type | None,
) -> Node:
    """A fast binary node over a comparison (``a == 1 && b < c``): an operand that is
    itself a fast operator on two references or constants is computed in place (its
    node is called only off its fast path)."""
    ta, tb, fa, fb, sa, sb = ka.hint, kb.hint, ka.held, kb.held, ka.src, kb.src
    ma = 2 if ka.fused is not None else 1 if sa is not None else 0
    mb = 2 if kb.fused is not None else 1 if sb is not None else 0
    pa, xa, ya, txa, tya = ka.fused or _UNFUSED
    pb, xb, yb, txb, tyb = kb.fused or _UNFUSED

    def held() -> object:
        if ma == 2:
            x = xa.held
            y = ya.held
            a = pa(x, y) if type(x) is txa and type(y) is tya else fa()
        elif ma == 1:
            a = sa.held  # type: ignore[union-attr]
        else:
            a = fa()
        if mb == 2:
            x = xb.held
            y = yb.held
            b = pb(x, y) if type(x) is txb and type(y) is tyb else fb()
        elif mb == 1:
            b = sb.held  # type: ignore[union-attr]
        else:
            b = fb()
        if type(a) is ta and type(b) is tb:
            return pyop(a, b)
        return slow(a, b)

    return Node(node, (ka, kb), held, None, started, hint)


def _lift2_general(
    node: ast.Expr,
    ka: Node,
    kb: Node,
    fn: Callable[[object, object], object],
    where: str,
    started: Callable[[], bool] | None,
) -> Node:
    sa, sb, fa, fb = ka.src, kb.src, ka.held, kb.held
    held: Thunk
    if sa is not None and sb is not None:

        def held() -> object:
            a = sa.held
            b = sb.held
            if a is NOVAL or b is NOVAL:
                return NOVAL
            if a is BOTTOM or b is BOTTOM:
                return BOTTOM
            try:
                return fn(a, b)
            except Fault as e:
                raise _located(e, where) from None

    elif sa is not None:

        def held() -> object:
            a = sa.held
            b = fb()
            if a is NOVAL or b is NOVAL:
                return NOVAL
            if a is BOTTOM or b is BOTTOM:
                return BOTTOM
            try:
                return fn(a, b)
            except Fault as e:
                raise _located(e, where) from None

    elif sb is not None:

        def held() -> object:
            a = fa()
            b = sb.held
            if a is NOVAL or b is NOVAL:
                return NOVAL
            if a is BOTTOM or b is BOTTOM:
                return BOTTOM
            try:
                return fn(a, b)
            except Fault as e:
                raise _located(e, where) from None

    else:

        def held() -> object:
            a = fa()
            b = fb()
            if a is NOVAL or b is NOVAL:
                return NOVAL
            if a is BOTTOM or b is BOTTOM:
                return BOTTOM
            try:
                return fn(a, b)
            except Fault as e:
                raise _located(e, where) from None

    return Node(node, (ka, kb), held, None, started)


def _liftn(node: ast.Expr, kids: Sequence[Node], fn: Callable[..., object], where: str) -> Node:
    if len(kids) == 3:
        return _lift3(node, kids[0], kids[1], kids[2], fn, where)
    fs = [k.held for k in kids]

    def held() -> object:
        vals = [f() for f in fs]
        for v in vals:  # identity first: the markers define no __eq__
            if v is NOVAL:
                return NOVAL
        for v in vals:
            if v is BOTTOM:
                return BOTTOM
        try:
            return fn(*vals)
        except Fault as e:
            raise _located(e, where) from None

    return Node(node, kids, held, None, _all_started(kids))


def _lift3(
    node: ast.Expr, ka: Node, kb: Node, kc: Node, fn: Callable[..., object], where: str
) -> Node:
    sa, sb, sc = ka.src, kb.src, kc.src
    fa, fb, fc = ka.held, kb.held, kc.held

    insert = fn is op.map_insert

    def held() -> object:
        a = fa() if sa is None else sa.held
        b = fb() if sb is None else sb.held
        c = fc() if sc is None else sc.held
        if insert and type(a) is MapV and type(b) is str and c is not NOVAL and c is not BOTTOM:
            out = MapV(a)
            out[b] = c
            return out
        if a is NOVAL or b is NOVAL or c is NOVAL:
            return NOVAL
        if a is BOTTOM or b is BOTTOM or c is BOTTOM:
            return BOTTOM
        try:
            return fn(a, b, c)
        except Fault as e:
            raise _located(e, where) from None

    hint = MapV if insert else None
    return Node(node, (ka, kb, kc), held, None, _all_started((ka, kb, kc)), hint)


def _map_get_ss(node: ast.Expr, km: Node, kk: Node, where: str) -> Node:
    """``Map.get(m, k)`` on two references or constants, the lookup done in place."""
    sm, sk = km.src, kk.src
    assert sm is not None
    assert sk is not None
    slow = _slow2(op.map_get, where)

    def held() -> object:
        m = sm.held
        k = sk.held
        if type(m) is MapV and type(k) is str:
            return m.get(k, BOTTOM)
        return slow(m, k)

    return Node(node, (km, kk), held, None, _all_started((km, kk)), _value_hint(km))


def _value_hint(k: Node) -> type | None:
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
            return _PY_TYPES.get(inner.name) if isinstance(inner, ast.TName) else None
    return None


class _Holder:
    """A constant operand, read like a stream (``.held``)."""

    __slots__ = ("held",)

    def __init__(self, v: object) -> None:
        self.held = v


class ConstNode(Node):
    """A literal, or a pure operator over constants folded when compiled: the same value
    on every tick."""

    __slots__ = ("const",)

    def __init__(self, node: ast.Expr, children: Sequence[Node], v: object) -> None:
        def held() -> object:
            return v

        super().__init__(node, children, held)
        self.const = v
        self.src = _Holder(v)
        self.hint = type(v)


def _const(node: ast.Expr, v: object) -> Node:
    return ConstNode(node, (), v)


# -- stateful built-ins ---------------------------------------------------------------------


class _When(StatefulNode):
    __slots__ = ("_fe",)

    def __init__(self, node: ast.Expr, e: Node) -> None:
        super().__init__(node, (e,), always=True)
        self._fe = e.held
        self.cur_v = self.held_v = False

    def update(self) -> None:
        if self.held_v is False:
            v = self._fe()
            if v is not NOVAL and v is not BOTTOM:
                self.cur_v = self.held_v = True


class _Latch(StatefulNode):
    __slots__ = ("_fx", "_fy")

    def __init__(self, node: ast.Expr, x: Node, y: Node) -> None:
        super().__init__(node, (x, y), always=False)
        self._fx, self._fy = x.held, y.cur

    def update(self) -> None:
        if self._fy() is NOVAL:
            self.cur_v = NOVAL
        else:
            self._set(self._fx())


class _Update(StatefulNode):
    __slots__ = ("_fa", "_fb", "_switched")

    def __init__(self, node: ast.Expr, a: Node, b: Node) -> None:
        super().__init__(node, (a, b), always=False)
        self._fa, self._fb = a.held, b.held
        self._switched = False

    def update(self) -> None:
        if not self._switched:
            v = self._fb()
            if v is not NOVAL and v is not BOTTOM:
                self._switched = True
        self._set(self._fb() if self._switched else self._fa())

    def export(self) -> object:
        return (self.cur_v, self.held_v, self._switched)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, self._switched = state  # type: ignore[misc]


class _Timeout(StatefulNode):
    __slots__ = ("_clock", "_fx", "_limit", "_since", "_where")

    def __init__(self, node: ast.Expr, x: Node, limit_ns: int, clock: Clock, where: str):
        super().__init__(node, (x,), always=True)
        self._fx, self._limit, self._clock, self._where = x.cur, limit_ns, clock, where
        self._since: int | None = None

    def update(self) -> None:
        now = self._clock.ts
        if now is None:
            raise Fault(
                "timeout(...) needs tick timestamps, and this tick has none "
                "(pass ts_ns to Monitor.step)",
                self._where,
            )
        v = self._fx()
        if self._since is None or (v is not NOVAL and v is not BOTTOM):
            self._since = now
        self.cur_v = self.held_v = now - self._since > self._limit

    def export(self) -> object:
        return (self.cur_v, self.held_v, self._since)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, self._since = state  # type: ignore[misc]


class _Aggregate(StatefulNode):
    """``x.aggregate(over: W, using: f)`` over the data values x took at ticks whose
    timestamp is within ``(now - W, now]``; bounded by ``cap`` samples."""

    __slots__ = (
        "_cap",
        "_clock",
        "_floats",
        "_fx",
        "_isum",
        "_mono",
        "_q",
        "_using",
        "_where",
        "_window",
    )

    def __init__(self, node: ast.Aggregate, x: Node, clock: Clock, cap: int, where: str) -> None:
        super().__init__(node, (x,), always=True)
        self._fx, self._clock, self._cap, self._where = x.cur, clock, cap, where
        self._window, self._using = node.window_ns, node.using
        self._q: deque[tuple[int, object]] = deque()
        self._mono: deque[tuple[int, object]] = deque()
        self._isum = 0
        self._floats = 0

    def update(self) -> None:
        now = self._clock.ts
        if now is None:
            raise Fault(
                f"x.aggregate(using: {self._using}) needs tick timestamps, and this tick "
                "has none (pass ts_ns to Monitor.step)",
                self._where,
            )
        v = self._fx()
        using = self._using
        if v is not NOVAL and v is not BOTTOM:
            if using != "count" and (type(v) is not int and type(v) is not float):
                raise Fault(f"aggregate {using} needs numbers, got {console(v)}", self._where)
            if len(self._q) >= self._cap:
                raise Fault(
                    f"aggregate window holds more than {self._cap} samples "
                    "(raise Limits.window_samples or shorten the window)",
                    self._where,
                )
            self._q.append((now, v))
            if type(v) is int:
                self._isum += v
            else:
                self._floats += 1
            if using in ("min", "max"):
                mono = self._mono
                if using == "min":
                    while mono and mono[-1][1] >= v:  # type: ignore[operator]
                        mono.pop()
                else:
                    while mono and mono[-1][1] <= v:  # type: ignore[operator]
                        mono.pop()
                mono.append((now, v))
        edge = now - self._window
        q = self._q
        while q and q[0][0] <= edge:
            _, old = q.popleft()
            if type(old) is int:
                self._isum -= old
            else:
                self._floats -= 1
        while self._mono and self._mono[0][0] <= edge:
            self._mono.popleft()
        self.cur_v = self.held_v = self._fold()

    def _fold(self) -> object:
        n = len(self._q)
        if self._using == "count":
            return n
        if self._using in ("min", "max"):
            return self._mono[0][1] if self._mono else BOTTOM
        if self._floats:
            total: object = math.fsum(v for _, v in self._q)  # type: ignore[misc]
        else:
            if not INT_MIN <= self._isum <= INT_MAX:
                raise Fault(
                    f"Int overflow: the window's sum {self._isum} does not fit in 64 bits",
                    self._where,
                )
            total = self._isum
        if self._using == "sum":
            return total
        return total / n if n else BOTTOM  # type: ignore[operator]

    def export(self) -> object:
        return (self.cur_v, self.held_v, list(self._q), list(self._mono))

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, q, mono = cast(
            tuple[object, object, list[tuple[int, object]], list[tuple[int, object]]], state
        )
        self._q.clear()
        self._mono.clear()
        self._isum = self._floats = 0
        for t, v in q:
            self._q.append((t, v))
            if type(v) is int:
                self._isum += v
            else:
                self._floats += 1
        self._mono.extend(mono)


# -- the compiler ---------------------------------------------------------------------------


def _switch(e: ast.If) -> tuple[str, type, dict[object, object], object] | None:
    """A chain ``if x == k1 then r1 else if x == k2 then r2 ... else r`` on one stream
    ``x``, with literal keys of one type (Str or Int) and literal results, as a table:
    for a value of the keys' type the chain's value is the first ki's ri, else r (x's
    other values, NoVal and ⊥ take the chain itself)."""
    name: str | None = None
    kt: type | None = None
    cases: dict[object, object] = {}
    x: ast.Expr = e
    while isinstance(x, ast.If):
        c = x.cond
        if not (isinstance(c, ast.Binary) and c.op == "==" and isinstance(x.then, ast.Lit)):
            return None
        var, key = (c.left, c.right) if isinstance(c.left, ast.Var) else (c.right, c.left)
        if not isinstance(var, ast.Var) or not isinstance(key, ast.Lit):
            return None
        if name is None:
            name, kt = var.name, type(key.value)
        if var.name != name or type(key.value) is not kt or kt not in (str, int):
            return None
        cases.setdefault(key.value, x.then.value)
        x = x.else_
    if not isinstance(x, ast.Lit) or name is None or kt is None or len(cases) < 2:
        return None
    return name, kt, cases, x.value


_FOLDABLE: Final = (
    ast.Binary,
    ast.Unary,
    ast.If,
    ast.Call,
    ast.Field,
    ast.ListLit,
    ast.TupleLit,
    ast.MapLit,
    ast.StructLit,
)
"""Pure lifted operators: over constant operands, a constant."""
_PURE_CALLS: Final = frozenset(op.CALLS) | {"default", "is_defined"}


class Compiler:
    """Compiles expressions against a set of streams.

    ``lookup(name)`` gives the stream a name refers to (raising :class:`Fault` for a name
    that cannot be used there); ``hidden(index)`` the stream standing for a non-variable
    operand of ``x[k]``. Stateful nodes are appended to ``stateful`` in post-order, the
    order the monitor updates them in.
    """

    def __init__(
        self,
        *,
        path: str,
        clock: Clock,
        lookup: Callable[[str, ast.Expr, int], Stream],
        hidden: Callable[[ast.Index], Stream],
        make_eval: Callable[[ast.Eval, Node, Compiler], StatefulNode],
        window_samples: int,
    ) -> None:
        self.path = path
        self.clock = clock
        self.lookup = lookup
        self.hidden = hidden
        self.make_eval = make_eval
        self.window_samples = window_samples
        self.stateful: list[StatefulNode] = []

    def where(self, e: ast.Expr) -> str:
        return f"{self.path}:{e.pos}"

    def compile(self, e: ast.Expr) -> Node:
        n = self._compile(e)
        if (
            n.children
            and isinstance(e, _FOLDABLE)
            and all(isinstance(k, ConstNode) for k in n.children)
            and not (isinstance(e, ast.Call) and e.func not in _PURE_CALLS)
        ):
            # a pure operator over constants: the same value on every tick, computed
            # once here (a run-time error stays one, raised at its tick with its stream)
            try:
                return ConstNode(e, n.children, n.held())
            except (Fault, TypeError, ValueError, ArithmeticError):
                return n
        return n

    def _compile(self, e: ast.Expr) -> Node:
        if isinstance(e, ast.Lit):
            return _const(e, e.value)
        if isinstance(e, ast.Var):
            return self._var(e)
        if isinstance(e, ast.Index):
            return self._index(e)
        if isinstance(e, ast.Binary):
            ka, kb = self.compile(e.left), self.compile(e.right)
            fast = _FAST2.get((e.op, ka.hint, kb.hint))  # type: ignore[arg-type]
            return _lift2(e, ka, kb, op.BINARY[e.op], self.where(e), fast)
        if isinstance(e, ast.Unary):
            fn = op.negate if e.op == "-" else op.logical_not
            k = self.compile(e.operand)
            fast1 = _FAST1.get((e.op, k.hint))  # type: ignore[arg-type]
            return _lift1(e, k, fn, self.where(e), fast1)
        if isinstance(e, ast.If):
            return self._if(e)
        if isinstance(e, ast.Call):
            return self._call(e)
        if isinstance(e, ast.Field):
            name = e.name
            return _lift1(e, self.compile(e.expr), lambda v: op.field(v, name), self.where(e))
        if isinstance(e, ast.ListLit):
            return self._container(e, e.items, tuple)
        if isinstance(e, ast.TupleLit):
            return self._container(e, e.items, TupleV)
        if isinstance(e, ast.MapLit | ast.StructLit):
            pairs = e.pairs if isinstance(e, ast.MapLit) else e.fields
            keys = [k for k, _ in pairs]
            cls = MapV if isinstance(e, ast.MapLit) else StructV
            return self._container(
                e, [x for _, x in pairs], lambda vals: cls(zip(keys, vals, strict=True))
            )
        if isinstance(e, ast.Aggregate):
            x = self.compile(e.expr)
            return self._stateful(_Aggregate(e, x, self.clock, self.window_samples, self.where(e)))
        if isinstance(e, ast.Eval):
            source = self.compile(e.source)
            return self._stateful(self.make_eval(e, source, self))
        raise Fault(f"cannot evaluate {type(e).__name__} nodes", self.where(e))

    def _stateful(self, n: StatefulNode) -> StatefulNode:
        self.stateful.append(n)
        return n

    def _var(self, e: ast.Var) -> Node:
        return VarNode(e, self.lookup(e.name, e, 0))

    def _index(self, e: ast.Index) -> Node:
        if isinstance(e.expr, ast.Var):
            s = self.lookup(e.expr.name, e, e.offset)
            kid = self._var(e.expr) if e.offset == 0 else _const(e.expr, NOVAL)
        else:
            s = self.hidden(e)
            kid = _const(e.expr, NOVAL)
        k = e.offset
        hint = type_hint(s.decl)
        if k == 0:

            def held0() -> object:
                v = s.held
                return BOTTOM if v is NOVAL else v

            return Node(e, (kid,), held0, None, None, hint)
        hist = s.hist
        if hist is None or (hist.maxlen or 0) < k:
            raise Fault(
                f"{s.name}[{k}] reaches further back than the {hist.maxlen if hist else 0} "
                "ticks of history kept (raise Limits.dynamic_history)",
                self.where(e),
            )
        neg = -k

        def held() -> object:
            v = hist[neg]
            return BOTTOM if v is NOVAL else v

        return Node(e, (kid,), held, None, None, hint)

    def _container(
        self, e: ast.Expr, items: Sequence[ast.Expr], build: Callable[[list[object]], object]
    ) -> Node:
        kids = [self.compile(x) for x in items]
        if not kids:
            return _const(e, build([]))
        return _liftn(e, kids, lambda *vals: build(list(vals)), self.where(e))

    def _if(self, e: ast.If) -> Node:
        kc, ka, kb = self.compile(e.cond), self.compile(e.then), self.compile(e.else_)
        fc, fa, fb = kc.held, ka.held, kb.held
        sc, sa, sb = kc.src, ka.src, kb.src
        started = _all_started((kc, ka, kb))
        where = self.where(e)
        ok = started is None

        def bad(c: object) -> object:
            if c is BOTTOM:
                return BOTTOM
            raise Fault(f"the condition of 'if' must be a Bool, got {console(c)}", where)

        held: Thunk
        if kc.fused is not None:
            pyop, sx, sy, tx, ty = kc.fused

            def held() -> object:
                nonlocal ok
                if not ok:
                    if not started():  # type: ignore[misc]
                        return NOVAL
                    ok = True
                x = sx.held
                y = sy.held
                c = pyop(x, y) if type(x) is tx and type(y) is ty else fc()
                if c is True:
                    return fa() if sa is None else sa.held
                if c is False:
                    return fb() if sb is None else sb.held
                return bad(c)

        elif sc is not None:

            def held() -> object:
                nonlocal ok
                if not ok:
                    if not started():  # type: ignore[misc]
                        return NOVAL
                    ok = True
                c = sc.held
                if c is True:
                    return fa() if sa is None else sa.held
                if c is False:
                    return fb() if sb is None else sb.held
                return bad(c)

        else:

            def held() -> object:
                nonlocal ok
                if not ok:
                    if not started():  # type: ignore[misc]
                        return NOVAL
                    ok = True
                c = fc()
                if c is True:
                    return fa() if sa is None else sa.held
                if c is False:
                    return fb() if sb is None else sb.held
                return bad(c)

        hint = ka.hint if ka.hint is kb.hint else None
        table = _switch(e)
        if table is not None:  # if x == "a" then 1 else if x == "b" then 2 else 0
            name, kt, cases, other = table
            sx = self.lookup(name, e, 0)
            general = held

            def held() -> object:
                v = sx.held
                if type(v) is kt:
                    return cases.get(v, other)
                return general()

        return Node(e, (kc, ka, kb), held, None, started, hint)

    def _call(self, e: ast.Call) -> Node:
        f = e.func
        where = self.where(e)
        if f in op.CALLS:
            arity, fn = op.CALLS[f]
            self._arity(e, arity)
            kids = [self.compile(a) for a in e.args]
            if arity == 1:
                fast1 = _FAST_CALL1.get((f, kids[0].hint))  # type: ignore[arg-type]
                if fast1 is not None and f == "List.head":
                    fast1 = (fast1[0], False, _value_hint(kids[0]))
                return _lift1(e, kids[0], fn, where, fast1)
            if arity == 2:
                fast = _FAST_CALL2.get((f, kids[0].hint, kids[1].hint))  # type: ignore[arg-type]
                if fast is not None and f == "Map.get":
                    if kids[0].src is not None and kids[1].src is not None:
                        return _map_get_ss(e, kids[0], kids[1], where)
                    fast = (fast[0], False, _value_hint(kids[0]))
                return _lift2(e, kids[0], kids[1], fn, where, fast)
            return _liftn(e, kids, fn, where)
        if f == "timeout":
            self._arity(e, 2)
            limit = e.args[1]
            if not isinstance(limit, ast.Lit) or type(limit.value) is not int:
                raise Fault("timeout(x, d) needs a duration literal for d, e.g. 2s", where)
            x = self.compile(e.args[0])
            return self._stateful(_Timeout(e, x, limit.value, self.clock, where))
        if f not in ("default", "init", "is_defined", "when", "latch", "update"):
            raise Fault(f"unknown function '{f}'", where)
        self._arity(e, 1 if f in ("is_defined", "when") else 2)
        kids = [self.compile(a) for a in e.args]
        if f == "when":
            return self._stateful(_When(e, kids[0]))
        if f == "latch":
            return self._stateful(_Latch(e, kids[0], kids[1]))
        if f == "update":
            return self._stateful(_Update(e, kids[0], kids[1]))
        if f == "is_defined":
            fe = kids[0].held

            def held_def() -> object:
                v = fe()
                return NOVAL if v is NOVAL else v is not BOTTOM

            return Node(e, kids, held_def, None, kids[0].started, bool)
        if f == "default":
            past = e.args[0]
            if (
                isinstance(past, ast.Index)
                and isinstance(past.expr, ast.Var)
                and past.offset > 0
                and isinstance(kids[1], ConstNode)
            ):  # x[k] with a constant default (D5.2's x[-k, c]): read the history here
                return self._default_past(e, kids[0], kids[1], past, past.expr.name)
            return self._default(e, kids[0], kids[1])
        return self._init(e, kids[0], kids[1])

    def _default_past(
        self, e: ast.Call, ke: Node, kd: ConstNode, past: ast.Index, name: str
    ) -> Node:
        hist = self.lookup(name, past, past.offset).hist
        assert hist is not None  # the index node compiled: it has this much history
        neg, d = -past.offset, kd.const

        def held() -> object:
            v = hist[neg]
            if v is NOVAL or v is BOTTOM:
                return d
            return v

        hint = ke.hint if ke.hint is kd.hint else None
        return Node(e, (ke, kd), held, None, None, hint)

    def _arity(self, e: ast.Call, n: int) -> None:
        if len(e.args) != n:
            raise Fault(
                f"{e.func} takes {n} argument{'s' if n != 1 else ''}, got {len(e.args)}",
                self.where(e),
            )

    @staticmethod
    def _default(e: ast.Call, ke: Node, kd: Node) -> Node:
        fe, fd, sd = ke.held, kd.held, kd.started
        src_d = kd.src
        held: Thunk
        if sd is None and src_d is not None:  # the common default(x[k], literal)

            def held() -> object:
                v = fe()
                if v is BOTTOM:
                    return src_d.held
                return v

        else:

            def held() -> object:
                v = fe()
                if v is NOVAL:
                    return NOVAL
                if v is BOTTOM:
                    return fd()
                if sd is not None and not sd():
                    return NOVAL
                return v

        hint = ke.hint if ke.hint is kd.hint else None
        return Node(e, (ke, kd), held, None, _all_started((ke, kd)), hint)

    @staticmethod
    def _init(e: ast.Call, ke: Node, kd: Node) -> Node:
        eh, ec, dh = ke.held, ke.cur, kd.held

        def held() -> object:
            v = eh()
            return dh() if v is NOVAL else v

        if ec is eh:
            cur = held
        else:

            def cur() -> object:
                return dh() if eh() is NOVAL else ec()

        se, sd = ke.started, kd.started
        if se is None or sd is None:
            started = None
        else:

            def started() -> bool:
                return se() or sd()

        return Node(e, (ke, kd), held, cur, started)


# -- eval / dynamic / defer ------------------------------------------------------------------


class EvalNode(StatefulNode):
    """``eval(s)`` / ``dynamic(s)`` and ``defer(s)``: the expression held in the Str stream
    ``s``, parsed with the checker's own parser and compiled by ``compiler()`` (whose
    ``lookup`` enforces the scope). ``eval`` re-parses whenever the text changes; ``defer``
    keeps the first expression that parses."""

    __slots__ = ("_compiler", "_conform", "_expr", "_fixed", "_src", "_text", "_updates", "_where")

    def __init__(
        self,
        node: ast.Eval,
        source: Node,
        compiler: Callable[[], Compiler],
        where: str,
    ) -> None:
        super().__init__(node, (source,), always=False)
        self._src = source.held
        self._compiler = compiler
        self._where = where
        self._conform = None if node.ascription is None else op.conformer(node.ascription)
        self._text: str | None = None
        self._expr: Node | None = None
        self._updates: list[StatefulNode] = []
        self._fixed = False

    @property
    def kind(self) -> str:
        return self.ast.kind  # type: ignore[union-attr]

    def update(self) -> None:
        s = self._src()
        if s is NOVAL:
            self.cur_v = NOVAL
            return
        if not self._fixed:
            if s is BOTTOM:
                self._set(BOTTOM)
                return
            if type(s) is not str:
                raise Fault(
                    f"{self.kind}(s) needs a Str holding an expression, got {console(s)}",
                    self._where,
                )
            if s != self._text:
                self._load(s)
        if self._expr is None:
            self._set(BOTTOM)
            return
        for u in self._updates:
            u.update()
        v = self._expr.cur()
        if self._conform is not None and v is not NOVAL:
            try:
                v = self._conform(v)
            except Mismatch as m:
                raise Fault(
                    f"{self.kind} of {self._text!r} gave a value of the wrong type: {m} "
                    "(fix the expression or the ascription)",
                    self._where,
                ) from None
        self._set(v)

    def _load(self, text: str) -> None:
        self._text = text
        self._expr = None
        self._updates = []
        try:
            tree = parse_expr(text, f"<{self.kind} at {self._where}>")
            c = self._compiler()
            expr = c.compile(tree)
        except SpecError as e:
            raise Fault(
                f"cannot parse the {self.kind} expression {text!r}: {e}", self._where
            ) from None
        except Fault as f:
            raise Fault(
                f"cannot use the {self.kind} expression {text!r}: {f.message}"
                + (f" ({f.where})" if f.where else ""),
                self._where,
            ) from None
        self._expr, self._updates = expr, c.stateful
        self._fixed = self.kind == "defer"

    def export(self) -> object:
        inner = [u.export() for u in self._updates]
        return (self.cur_v, self.held_v, self._text, self._fixed, inner)

    def restore(self, state: object) -> None:
        self.cur_v, self.held_v, text, fixed, inner = cast(
            tuple[object, object, str | None, bool, list[object]], state
        )
        if text is None:
            return
        try:
            self._load(text)
        except Fault:
            return
        self._fixed = fixed
        if len(inner) == len(self._updates):
            for u, st in zip(self._updates, inner, strict=True):
                u.restore(st)

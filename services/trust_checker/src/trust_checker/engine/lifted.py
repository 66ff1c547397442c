"""The pure lifted operators (arithmetic, comparisons, logic, calls, containers) as
compiled nodes: a lifted node's value is a function of its operands' held values (NoVal
until every operand has had one, ⊥ if one is ⊥), so it needs no state.

Speed (measured in bench/trust), with the semantics unchanged:

- an operator reads an operand that is a stream reference or a constant in place
  (``node.src.held``), and is one closure per shape of its operands, so it costs one
  Python call;
- where the operands' types are known from the spec, the operation is first tried on
  exactly those types with Python's own operator (``type(a) is int and type(b) is int``:
  ``a + b``, range-checked), every other case taking the general path of
  :mod:`trust_checker.operators` (the tables :data:`FAST2`, :data:`FAST1`,
  :data:`FAST_CALL1`, :data:`FAST_CALL2`).
"""

from __future__ import annotations

import operator as _pyop
from collections.abc import Callable, Sequence
from typing import Any, Final, cast

from trust_checker import operators as op
from trust_checker.engine.nodes import (
    ExprNode,
    Fused,
    Thunk,
    all_started,
    located,
    value_hint,
)
from trust_checker.lang import ast
from trust_checker.operators import Fault
from trust_checker.values import BOTTOM, INT_MAX, INT_MIN, NOVAL, MapV

__all__ = [
    "FAST1",
    "FAST2",
    "FAST_CALL1",
    "FAST_CALL2",
    "Fast",
    "lift1",
    "lift2",
    "liftn",
    "map_get_ss",
]

# -- pure lifted nodes ----------------------------------------------------------------------
#
# Operators read an operand in one of two ways: a stream reference or a constant through
# its ``src`` (an object whose ``held`` attribute is the value: the stream itself, or a
# :class:`Holder`), anything else by calling its ``held()``. Each operator node is one
# closure for its operands' shape (``src``/call on each side), so the common cases cost
# one Python call per operator. Where the operands' types are known from the spec (a
# declared stream type, a literal, another operator's result), the closure first tries
# the operation on exactly those types with the plain Python operator, which for those
# types computes what :mod:`trust_checker.operators` does; any other value (NoVal, ⊥, a
# value of another type, an Int result outside 64 bits) takes the general path. The hints
# only choose the fast path: a wrong hint costs speed, never a different value.

Fast = tuple[Callable[..., Any], bool, type | None]
"""A fast path: the Python operator, whether an Int result needs the 64-bit range
check, and the result's type (a hint for the node's parent)."""

_NUM: Final = (int, float)
FAST2: Final[dict[tuple[str, type, type], Fast]] = {}
for _t in (int, float, str, bool):
    FAST2["==", _t, _t] = (_pyop.eq, False, bool)
for _a in _NUM:
    for _b in _NUM:
        if _a is not _b:  # Int == Float compares the numbers, as Python does
            FAST2["==", _a, _b] = (_pyop.eq, False, bool)
for _name, _fn in (("<", _pyop.lt), ("<=", _pyop.le), (">", _pyop.gt), (">=", _pyop.ge)):
    FAST2[_name, str, str] = (_fn, False, bool)
    for _a in _NUM:
        for _b in _NUM:
            FAST2[_name, _a, _b] = (_fn, False, bool)
for _name, _fn in (("+", _pyop.add), ("-", _pyop.sub), ("*", _pyop.mul)):
    FAST2[_name, int, int] = (_fn, True, int)
    # Int with Float: Python converts the Int with float(), as the operators do
    for _a, _b in ((float, float), (int, float), (float, int)):
        FAST2[_name, _a, _b] = (_fn, False, float)
FAST2["&&", bool, bool] = (_pyop.and_, False, bool)
FAST2["||", bool, bool] = (_pyop.or_, False, bool)
FAST2["=>", bool, bool] = (_pyop.le, False, bool)  # on Bools, a => b is a <= b
FAST2["++", str, str] = (_pyop.add, False, str)


def _map_get(m: MapV, k: str) -> object:
    return m.get(k, BOTTOM)


def _map_remove(m: MapV, k: str) -> object:
    out = MapV(m)
    out.pop(k, None)
    return out


FAST_CALL2: Final[dict[tuple[str, type, type], Fast]] = {
    ("Map.get", MapV, str): (_map_get, False, None),
    ("Map.has_key", MapV, str): (_pyop.contains, False, bool),
    ("Map.remove", MapV, str): (_map_remove, False, MapV),
}


def _list_append(items: tuple[object, ...], x: object) -> object:
    return items + (x,)  # noqa: RUF005 (a tuple concatenation copies in one step)


for _t in (int, float, str, bool):
    FAST_CALL2["List.append", tuple, _t] = (_list_append, False, tuple)


def _list_head(items: tuple[object, ...]) -> object:
    return items[0] if items else BOTTOM


FAST_CALL1: Final[dict[tuple[str, type], Fast]] = {
    ("List.head", tuple): (_list_head, False, None),
    ("List.len", tuple): (len, False, int),
    ("List.tail", tuple): (_pyop.itemgetter(slice(1, None)), False, tuple),
}
FAST1: Final[dict[tuple[str, type], Fast]] = {
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
            raise located(e, where) from None

    return slow


def lift1(
    node: ast.Expr,
    kid: ExprNode,
    fn: Callable[[object], object],
    where: str,
    fast: Fast | None = None,
) -> ExprNode:
    fa, sa = kid.held, kid.src

    def slow(a: object) -> object:
        if a is NOVAL or a is BOTTOM:
            return a
        try:
            return fn(a)
        except Fault as e:
            raise located(e, where) from None

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

        return ExprNode(node, (kid,), held, None, kid.started, hint)
    if sa is not None:

        def held() -> object:
            a = sa.held
            if a is NOVAL or a is BOTTOM:
                return a
            try:
                return fn(a)
            except Fault as e:
                raise located(e, where) from None

    else:

        def held() -> object:
            a = fa()
            if a is NOVAL or a is BOTTOM:
                return a
            try:
                return fn(a)
            except Fault as e:
                raise located(e, where) from None

    return ExprNode(node, (kid,), held, None, kid.started)


def lift2(
    node: ast.Expr,
    ka: ExprNode,
    kb: ExprNode,
    fn: Callable[[object, object], object],
    where: str,
    fast: Fast | None = None,
) -> ExprNode:
    """A lifted binary node (see the section comment for ``fast`` and the shapes)."""
    kids = (ka, kb)
    started = all_started(kids)
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

        n = ExprNode(node, kids, held, None, started, hint)
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

    return ExprNode(node, kids, held, None, started, hint)


_UNFUSED: Final = cast(Fused, (None, None, None, None, None))
"""Stands for an operand that is not fused (its parts are never read)."""


def _lift2_fused(
    node: ast.Expr,
    ka: ExprNode,
    kb: ExprNode,
    pyop: Callable[..., Any],
    slow: Callable[[object, object], object],
    started: Callable[[], bool] | None,
    hint: type | None,
) -> ExprNode:
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

    return ExprNode(node, (ka, kb), held, None, started, hint)


def _lift2_general(
    node: ast.Expr,
    ka: ExprNode,
    kb: ExprNode,
    fn: Callable[[object, object], object],
    where: str,
    started: Callable[[], bool] | None,
) -> ExprNode:
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
                raise located(e, where) from None

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
                raise located(e, where) from None

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
                raise located(e, where) from None

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
                raise located(e, where) from None

    return ExprNode(node, (ka, kb), held, None, started)


def liftn(
    node: ast.Expr, kids: Sequence[ExprNode], fn: Callable[..., object], where: str
) -> ExprNode:
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
            raise located(e, where) from None

    return ExprNode(node, kids, held, None, all_started(kids))


def _lift3(
    node: ast.Expr, ka: ExprNode, kb: ExprNode, kc: ExprNode, fn: Callable[..., object], where: str
) -> ExprNode:
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
            if len(out) > op.MAX_ENTRIES:
                op.grown("Map.insert", len(out))
            return out
        if a is NOVAL or b is NOVAL or c is NOVAL:
            return NOVAL
        if a is BOTTOM or b is BOTTOM or c is BOTTOM:
            return BOTTOM
        try:
            return fn(a, b, c)
        except Fault as e:
            raise located(e, where) from None

    hint = MapV if insert else None
    return ExprNode(node, (ka, kb, kc), held, None, all_started((ka, kb, kc)), hint)


def map_get_ss(node: ast.Expr, km: ExprNode, kk: ExprNode, where: str) -> ExprNode:
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

    return ExprNode(node, (km, kk), held, None, all_started((km, kk)), value_hint(km))

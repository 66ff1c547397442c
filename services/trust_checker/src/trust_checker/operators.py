"""What the operators and built-ins do to data values (no NoVal, no ⊥: the compiled nodes in
:mod:`trust_checker.engine.lifted` handle holding and ⊥ before calling in here).

Every function raises :class:`Fault` for a run-time error (Int overflow, division by zero,
a value of the wrong type); the node that called it adds where in the spec, and the
runner adds the stream and the tick (:class:`trust_checker.errors.EvalError`).
Type conformance of inputs and ``eval`` ascriptions is :func:`conformer`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Final

from trust_checker.lang import ast
from trust_checker.values import (
    BOTTOM,
    INT_MAX,
    INT_MIN,
    UNIT,
    MapV,
    StructV,
    TupleV,
    console,
    type_name,
)

__all__ = [
    "BINARY",
    "CALLS",
    "MAX_ENTRIES",
    "Fault",
    "Mismatch",
    "conformer",
    "equal",
    "field",
    "grown",
    "logical_not",
    "negate",
]


MAX_ENTRIES: Final = 10_000
"""The most entries a List or Map may grow to. A spec whose collections grow with its
input (a map of every knowledge key seen, say) would otherwise grow without bound on a
flood of made-up keys, copying the whole collection at every tick: past this, the
growing operation fails the tick (an evaluation error), the collection keeps its size."""


def grown(fn: str, n: int) -> None:
    if n > MAX_ENTRIES:
        raise Fault(
            f"{fn} would make a collection of {n} entries, over the limit of {MAX_ENTRIES}; "
            "a spec's Lists and Maps must stay bounded: remove entries as they stop mattering"
        )


class Fault(Exception):
    """A run-time error in an operator; ``where`` is filled in by the node (``path:l:c``)."""

    def __init__(self, message: str, where: str = "") -> None:
        super().__init__(message)
        self.message = message
        self.where = where


class Mismatch(Exception):
    """A value does not conform to a declared type (the message says how)."""


def _show(v: object) -> str:
    return console(v)


def _overflow(op: str, a: object, b: object) -> Fault:
    return Fault(
        f"Int overflow: {a} {op} {b} does not fit in 64 bits "
        "(use Float for values this large, or bound the inputs)"
    )


def _is_num(t: type) -> bool:
    return t is int or t is float


def _need_numbers(op: str, a: object, b: object) -> Fault:
    return Fault(
        f"'{op}' needs two numbers (Int or Float), got {_show(a)} and {_show(b)} "
        "(check the declared types of the streams involved)"
    )


# -- arithmetic ---------------------------------------------------------------------------


def add(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ta is int and tb is int:
        r: int = a + b  # type: ignore[operator]
        if INT_MIN <= r <= INT_MAX:
            return r
        raise _overflow("+", a, b)
    if _is_num(ta) and _is_num(tb):
        return float(a) + float(b)  # type: ignore[arg-type]
    raise _need_numbers("+", a, b)


def sub(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ta is int and tb is int:
        r: int = a - b  # type: ignore[operator]
        if INT_MIN <= r <= INT_MAX:
            return r
        raise _overflow("-", a, b)
    if _is_num(ta) and _is_num(tb):
        return float(a) - float(b)  # type: ignore[arg-type]
    raise _need_numbers("-", a, b)


def mul(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ta is int and tb is int:
        r: int = a * b  # type: ignore[operator]
        if INT_MIN <= r <= INT_MAX:
            return r
        raise _overflow("*", a, b)
    if _is_num(ta) and _is_num(tb):
        return float(a) * float(b)  # type: ignore[arg-type]
    raise _need_numbers("*", a, b)


def _float_div(x: float, y: float) -> float:
    if y != 0.0:
        return x / y
    if x == 0.0 or math.isnan(x):
        return math.nan
    return math.copysign(math.inf, x) * math.copysign(1.0, y)


def div(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ta is int and tb is int:
        x: int = a  # type: ignore[assignment]
        y: int = b  # type: ignore[assignment]
        if y == 0:
            raise Fault(
                f"Int division by zero: {x} / 0 "
                "(guard the divisor, e.g. if d == 0 then ... else n / d)"
            )
        q = abs(x) // abs(y)
        if (x < 0) != (y < 0):
            q = -q
        if q > INT_MAX:
            raise _overflow("/", x, y)
        return q
    if _is_num(ta) and _is_num(tb):
        return _float_div(float(a), float(b))  # type: ignore[arg-type]
    raise _need_numbers("/", a, b)


def mod(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ta is int and tb is int:
        x: int = a  # type: ignore[assignment]
        y: int = b  # type: ignore[assignment]
        if y == 0:
            raise Fault(
                f"Int division by zero: {x} % 0 "
                "(guard the divisor, e.g. if d == 0 then ... else n % d)"
            )
        r = abs(x) % abs(y)
        return -r if x < 0 else r
    if _is_num(ta) and _is_num(tb):
        fx, fy = float(a), float(b)  # type: ignore[arg-type]
        if fy == 0.0 or math.isinf(fx) or math.isnan(fx) or math.isnan(fy):
            return math.nan
        return math.fmod(fx, fy)
    raise _need_numbers("%", a, b)


def negate(a: object) -> object:
    t = type(a)
    if t is int:
        if a == INT_MIN:
            raise Fault(f"Int overflow: -({a}) does not fit in 64 bits (use Float)")
        return -a  # type: ignore[operator]
    if t is float:
        return -a  # type: ignore[operator]
    raise Fault(f"unary '-' needs a number (Int or Float), got {_show(a)}")


def logical_not(a: object) -> object:
    if type(a) is bool:
        return not a
    raise Fault(f"'!' needs a Bool, got {_show(a)}")


# -- comparisons and logic ----------------------------------------------------------------


def equal(a: object, b: object) -> bool:
    """Structural equality; Int and Float compare as numbers, other types never equal."""
    ta, tb = type(a), type(b)
    if ta is not tb:
        return _is_num(ta) and _is_num(tb) and a == b
    if ta is tuple or ta is TupleV:
        xs: tuple[object, ...] = a  # type: ignore[assignment]
        ys: tuple[object, ...] = b  # type: ignore[assignment]
        return len(xs) == len(ys) and all(equal(x, y) for x, y in zip(xs, ys, strict=True))
    if ta is MapV or ta is StructV:
        mx: dict[str, object] = a  # type: ignore[assignment]
        my: dict[str, object] = b  # type: ignore[assignment]
        return mx.keys() == my.keys() and all(equal(v, my[k]) for k, v in mx.items())
    return a == b


def _eq(a: object, b: object) -> object:
    return equal(a, b)


def _unordered(op: str, a: object, b: object) -> Fault:
    return Fault(
        f"'{op}' compares two numbers or two strings, got {_show(a)} and {_show(b)} "
        "(check the declared types of the streams involved)"
    )


def lt(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ((ta is int or ta is float) and (tb is int or tb is float)) or (ta is str and tb is str):
        return a < b  # type: ignore[operator]
    raise _unordered("<", a, b)


def le(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ((ta is int or ta is float) and (tb is int or tb is float)) or (ta is str and tb is str):
        return a <= b  # type: ignore[operator]
    raise _unordered("<=", a, b)


def gt(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ((ta is int or ta is float) and (tb is int or tb is float)) or (ta is str and tb is str):
        return a > b  # type: ignore[operator]
    raise _unordered(">", a, b)


def ge(a: object, b: object) -> object:
    ta, tb = type(a), type(b)
    if ((ta is int or ta is float) and (tb is int or tb is float)) or (ta is str and tb is str):
        return a >= b  # type: ignore[operator]
    raise _unordered(">=", a, b)


def _not_bools(op: str, a: object, b: object) -> Fault:
    return Fault(f"'{op}' needs two Bools, got {_show(a)} and {_show(b)}")


def and_(a: object, b: object) -> object:
    if type(a) is bool and type(b) is bool:
        return a and b
    raise _not_bools("&&", a, b)


def or_(a: object, b: object) -> object:
    if type(a) is bool and type(b) is bool:
        return a or b
    raise _not_bools("||", a, b)


def implies(a: object, b: object) -> object:
    if type(a) is bool and type(b) is bool:
        return (not a) or b
    raise _not_bools("=>", a, b)


def concat(a: object, b: object) -> object:
    if type(a) is str and type(b) is str:
        return a + b
    raise Fault(
        f"'++' concatenates two Str, got {_show(a)} and {_show(b)} "
        "(for lists use List.concat(a, b))"
    )


BINARY: Final[dict[str, Callable[[object, object], object]]] = {
    "+": add,
    "-": sub,
    "*": mul,
    "/": div,
    "%": mod,
    "==": _eq,
    "<": lt,
    "<=": le,
    ">": gt,
    ">=": ge,
    "&&": and_,
    "||": or_,
    "=>": implies,
    "++": concat,
}
"""Binary operators on data values (⊥ and NoVal handled by the caller)."""


# -- fields, lists, maps, maths -----------------------------------------------------------


def field(v: object, name: str) -> object:
    t = type(v)
    if t is StructV:
        s: dict[str, object] = v  # type: ignore[assignment]
        if name in s:
            return s[name]
        raise Fault(
            f"struct {_show(v)} has no field '{name}' (its fields: {', '.join(s) or 'none'})"
        )
    if t is TupleV and name.isdigit():
        items: tuple[object, ...] = v  # type: ignore[assignment]
        i = int(name)
        if i < len(items):
            return items[i]
        raise Fault(f"tuple {_show(v)} has no item .{name} (it has {len(items)} items)")
    raise Fault(
        f"'.{name}' needs a struct (or a tuple, with .0, .1, ...), got {_show(v)}"
        + (" (for maps use Map.get(m, key))" if t is MapV else "")
    )


def _list(fn: str, v: object) -> tuple[object, ...]:
    if type(v) is tuple:
        return v
    raise Fault(f"{fn} needs a List as its first argument, got {_show(v)}")


def _int(fn: str, v: object) -> int:
    if type(v) is int:
        return v
    raise Fault(f"{fn} needs an Int index, got {_show(v)}")


def _map(fn: str, v: object) -> MapV:
    if type(v) is MapV:
        return v
    raise Fault(f"{fn} needs a Map as its first argument, got {_show(v)}")


def _key(fn: str, v: object) -> str:
    if type(v) is str:
        return v
    raise Fault(f"{fn} needs a Str key, got {_show(v)}")


def list_get(lst: object, i: object) -> object:
    items, k = _list("List.get", lst), _int("List.get", i)
    return items[k] if 0 <= k < len(items) else BOTTOM


def list_concat(a: object, b: object) -> object:
    left, right = _list("List.concat", a), _list("List.concat (second argument)", b)
    grown("List.concat", len(left) + len(right))
    return left + right


def list_append(lst: object, x: object) -> object:
    items = _list("List.append", lst)
    grown("List.append", len(items) + 1)
    return (*items, x)


def list_head(lst: object) -> object:
    items = _list("List.head", lst)
    return items[0] if items else BOTTOM


def list_tail(lst: object) -> object:
    return _list("List.tail", lst)[1:]


def list_len(lst: object) -> object:
    return len(_list("List.len", lst))


def map_get(m: object, k: object) -> object:
    return _map("Map.get", m).get(_key("Map.get", k), BOTTOM)


def map_insert(m: object, k: object, v: object) -> object:
    out = MapV(_map("Map.insert", m))
    out[_key("Map.insert", k)] = v
    grown("Map.insert", len(out))
    return out


def map_remove(m: object, k: object) -> object:
    out = MapV(_map("Map.remove", m))
    out.pop(_key("Map.remove", k), None)
    return out


def map_has_key(m: object, k: object) -> object:
    return _key("Map.has_key", k) in _map("Map.has_key", m)


def _trig(fn: str, f: Callable[[float], float]) -> Callable[[object], object]:
    def apply(x: object) -> object:
        if not _is_num(type(x)):
            raise Fault(f"{fn} needs a number (Int or Float), got {_show(x)}")
        v = float(x)  # type: ignore[arg-type]
        return math.nan if math.isinf(v) else f(v)

    return apply


def abs_(x: object) -> object:
    t = type(x)
    if t is int:
        if x == INT_MIN:
            raise Fault(f"Int overflow: abs({x}) does not fit in 64 bits (use Float)")
        return abs(x)  # type: ignore[arg-type]
    if t is float:
        return abs(x)  # type: ignore[arg-type]
    raise Fault(f"abs needs a number (Int or Float), got {_show(x)}")


CALLS: Final[dict[str, tuple[int, Callable[..., object]]]] = {
    "sin": (1, _trig("sin", math.sin)),
    "cos": (1, _trig("cos", math.cos)),
    "tan": (1, _trig("tan", math.tan)),
    "abs": (1, abs_),
    "List.get": (2, list_get),
    "List.concat": (2, list_concat),
    "List.append": (2, list_append),
    "List.head": (1, list_head),
    "List.tail": (1, list_tail),
    "List.len": (1, list_len),
    "Map.get": (2, map_get),
    "Map.insert": (3, map_insert),
    "Map.remove": (2, map_remove),
    "Map.has_key": (2, map_has_key),
}
"""Lifted built-ins on data values: name -> (arity, function)."""


# -- type conformance ---------------------------------------------------------------------


def _any_value(v: object) -> object:
    t = type(v)
    if t is int:
        if INT_MIN <= v <= INT_MAX:  # type: ignore[operator]
            return v
        raise Mismatch(f"integer {v} does not fit in 64 bits")
    if t in (bool, float, str) or v is UNIT or v is BOTTOM:
        return v
    if t is tuple or t is TupleV:
        items: tuple[object, ...] = v  # type: ignore[assignment]
        for x in items:
            _any_value(x)
        return v
    if t is MapV or t is StructV:
        d: dict[object, object] = v  # type: ignore[assignment]
        for k, x in d.items():
            if type(k) is not str:
                raise Mismatch(f"{type_name(v)} key {k!r} is not a string")
            _any_value(x)
        return v
    raise Mismatch(f"{v!r} ({type(v).__name__}) is not a value of the language")


def conformer(t: ast.Type | None) -> Callable[[object], object]:
    """A function that returns ``v`` as a value of type ``t`` (Int widened to Float) or
    raises :class:`Mismatch`; ⊥ conforms to every type. ``None`` and ``Any`` accept any
    value of the language."""
    if t is None or t == ast.TAny:
        return _any_value
    if isinstance(t, ast.TName):
        return _simple(t.name)
    if isinstance(t, ast.TList):
        elem = conformer(t.elem)

        def conform_list(v: object) -> object:
            if v is BOTTOM:
                return v
            if type(v) is not tuple:
                raise Mismatch(f"expected {t}, got {type_name(v)} {_show_safe(v)}")
            items: tuple[object, ...] = v
            return tuple(elem(x) for x in items)

        return conform_list
    if isinstance(t, ast.TMap):
        val = conformer(t.value)

        def conform_map(v: object) -> object:
            if v is BOTTOM:
                return v
            if not isinstance(v, dict) or type(v) is StructV:
                raise Mismatch(f"expected {t}, got {type_name(v)} {_show_safe(v)}")
            out = MapV()
            for k, x in v.items():
                if type(k) is not str:
                    raise Mismatch(f"{t} key {k!r} is not a string")
                out[k] = val(x)
            return out

        return conform_map
    if isinstance(t, ast.TStruct):
        fields = [(k, conformer(ft)) for k, ft in t.fields]

        def conform_struct(v: object) -> object:
            if v is BOTTOM:
                return v
            if not isinstance(v, dict) or set(v) != {k for k, _ in fields}:
                raise Mismatch(f"expected {t}, got {type_name(v)} {_show_safe(v)}")
            return StructV((k, f(v[k])) for k, f in fields)

        return conform_struct
    items_c = [conformer(it) for it in t.items]

    def conform_tuple(v: object) -> object:
        if v is BOTTOM:
            return v
        if not isinstance(v, tuple) or len(v) != len(items_c):
            raise Mismatch(f"expected {t}, got {type_name(v)} {_show_safe(v)}")
        return TupleV(f(x) for f, x in zip(items_c, v, strict=True))

    return conform_tuple


def _show_safe(v: object) -> str:
    try:
        return console(v)
    except TypeError:
        return repr(v)


def _simple(name: str) -> Callable[[object], object]:
    if name == "Any":
        return _any_value
    if name == "Int":

        def conform_int(v: object) -> object:
            if type(v) is int and INT_MIN <= v <= INT_MAX:
                return v
            if v is BOTTOM:
                return v
            if type(v) is int:
                raise Mismatch(f"integer {v} does not fit in 64 bits")
            raise Mismatch(f"expected Int, got {type_name(v)} {_show_safe(v)}")

        return conform_int
    if name == "Float":

        def conform_float(v: object) -> object:
            t = type(v)
            if t is float or v is BOTTOM:
                return v
            if t is int:
                return float(v)  # type: ignore[arg-type]
            raise Mismatch(f"expected Float, got {type_name(v)} {_show_safe(v)}")

        return conform_float
    want: object = {"Bool": bool, "Str": str, "Unit": type(UNIT)}[name]

    def conform(v: object) -> object:
        if type(v) is want or v is BOTTOM:
            return v
        raise Mismatch(f"expected {name}, got {type_name(v)} {_show_safe(v)}")

    return conform

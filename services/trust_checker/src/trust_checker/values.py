"""Values of the stream language, and how they are written.

Data values are plain Python objects, chosen so evaluation needs no wrapping:

============  ==========================================================
``Int``       ``int`` (never ``bool``: test with ``type(v) is int``), 64-bit checked
``Float``     ``float``
``Bool``      ``bool``
``Str``       ``str``
``Unit``      :data:`UNIT`
``List<T>``   ``tuple`` of values (immutable: operators build new ones)
``Map<T>``    :class:`MapV` (a dict with string keys, never mutated once built)
``Struct``    :class:`StructV` (field name -> value, in declaration order)
tuple         :class:`TupleV`
============  ==========================================================

Two markers are not data: :data:`BOTTOM` (⊥, "cannot be computed yet", printed
``Deferred``) and :data:`NOVAL` ("this stream did not tick here").

Formats: :func:`console` (the reference checker's ``Int(7)``), :func:`to_tagged` /
:func:`from_tagged` (D5.2's externally tagged JSON), :func:`to_plain` /
:func:`from_plain` (plain JSON).
"""

from __future__ import annotations

import math
from typing import Any, Final

__all__ = [
    "BOTTOM",
    "INT_MAX",
    "INT_MIN",
    "NOVAL",
    "UNIT",
    "MapV",
    "StructV",
    "TupleV",
    "ValueError_",
    "console",
    "from_plain",
    "from_tagged",
    "is_data",
    "to_plain",
    "to_tagged",
    "type_name",
]

INT_MIN: Final = -(2**63)
INT_MAX: Final = 2**63 - 1


class _Marker:
    __slots__ = ("_name",)

    def __init__(self, name: str) -> None:
        self._name = name

    def __repr__(self) -> str:
        return self._name

    def __reduce__(self) -> str:  # singletons survive copy.deepcopy
        return self._name


BOTTOM: Final = _Marker("BOTTOM")
NOVAL: Final = _Marker("NOVAL")


class _Unit:
    __slots__ = ()

    def __repr__(self) -> str:
        return "UNIT"

    def __reduce__(self) -> str:
        return "UNIT"


UNIT: Final = _Unit()


class MapV(dict[str, Any]):
    """A map value (string keys). Treat as immutable: operators copy."""

    __slots__ = ()


class StructV(dict[str, Any]):
    """A struct value: field name -> value, in order."""

    __slots__ = ()


class TupleV(tuple[Any, ...]):
    """A tuple value ``(a, b)`` (lists are plain tuples)."""

    __slots__ = ()


class ValueError_(Exception):
    """A value cannot be read from its wire form (with the reason)."""


def is_data(v: object) -> bool:
    return v is not BOTTOM and v is not NOVAL


def type_name(v: object) -> str:
    """The language's name for ``v``'s type (``Int``, ``List``, ...)."""
    t = type(v)
    if t is bool:
        return "Bool"
    if t is int:
        return "Int"
    if t is float:
        return "Float"
    if t is str:
        return "Str"
    if v is UNIT:
        return "Unit"
    if t is tuple:
        return "List"
    if t is MapV:
        return "Map"
    if t is StructV:
        return "Struct"
    if t is TupleV:
        return "Tuple"
    if v is BOTTOM:
        return "Deferred"
    if v is NOVAL:
        return "NoVal"
    return t.__name__


# -- console (the reference checker's Debug-like form) -------------------------------------


def _float_text(f: float) -> str:
    if math.isnan(f):
        return "NaN"
    if math.isinf(f):
        return "inf" if f > 0 else "-inf"
    text = repr(f)
    if "e" in text:  # Rust prints 1e-7 and 1e20, Python 1e-07 and 1e+20
        mant, exp = text.split("e")
        return f"{mant}e{int(exp)}"
    return text


def _str_text(s: str) -> str:
    out = ['"']
    for ch in s:
        if ch == '"':
            out.append('\\"')
        elif ch == "\\":
            out.append("\\\\")
        elif ch == "\n":
            out.append("\\n")
        elif ch == "\t":
            out.append("\\t")
        elif ch == "\r":
            out.append("\\r")
        else:
            out.append(ch)
    out.append('"')
    return "".join(out)


def console(v: object) -> str:
    """``Int(7)``, ``Float(2.0)``, ``Bool(true)``, ``Str("a")``, ``Unit``, ``Deferred``,
    ``List([Int(1)])``, ``Map({"k": Int(1)})``, ``Struct({"a": Int(1)})``,
    ``Tuple([Int(1), Bool(true)])``."""
    t = type(v)
    if t is bool:
        return "Bool(true)" if v else "Bool(false)"
    if t is int:
        return f"Int({v})"
    if t is float:
        return f"Float({_float_text(v)})"  # type: ignore[arg-type]
    if t is str:
        return f"Str({_str_text(v)})"  # type: ignore[arg-type]
    if v is UNIT:
        return "Unit"
    if v is BOTTOM:
        return "Deferred"
    if v is NOVAL:
        return "NoVal"
    if t is tuple:
        return "List([" + ", ".join(console(x) for x in v) + "])"  # type: ignore[attr-defined]
    if t is TupleV:
        return "Tuple([" + ", ".join(console(x) for x in v) + "])"  # type: ignore[attr-defined]
    if t is MapV or t is StructV:
        items = ", ".join(f"{_str_text(k)}: {console(x)}" for k, x in v.items())  # type: ignore[attr-defined]
        return f"{'Map' if t is MapV else 'Struct'}({{{items}}})"
    raise TypeError(f"not a stream value: {v!r}")


# -- JSON forms ---------------------------------------------------------------------------


def to_tagged(v: object) -> Any:
    """D5.2's externally tagged JSON: ``{"Int": 42}``, ``"Unit"``, ``"Unknown"`` (⊥)."""
    t = type(v)
    if t is bool:
        return {"Bool": v}
    if t is int:
        return {"Int": v}
    if t is float:
        return {"Float": v}
    if t is str:
        return {"Str": v}
    if v is UNIT:
        return "Unit"
    if v is BOTTOM:
        return "Unknown"
    if t is tuple:
        return {"List": [to_tagged(x) for x in v]}  # type: ignore[attr-defined]
    if t is TupleV:
        return {"Tuple": [to_tagged(x) for x in v]}  # type: ignore[attr-defined]
    if t is MapV:
        return {"Map": {k: to_tagged(x) for k, x in v.items()}}  # type: ignore[attr-defined]
    if t is StructV:
        return {"Struct": {k: to_tagged(x) for k, x in v.items()}}  # type: ignore[attr-defined]
    raise TypeError(f"not a stream value: {v!r}")


def from_tagged(j: Any) -> Any:
    """The inverse of :func:`to_tagged`; raises :class:`ValueError_` naming the bad part."""
    if j == "Unit":
        return UNIT
    if j == "Unknown" or j == "Deferred":
        return BOTTOM
    if isinstance(j, dict) and len(j) == 1:
        ((tag, x),) = j.items()
        if tag == "Int" and type(x) is int:
            return check_int(x)
        if tag == "Float" and type(x) in (int, float):
            return float(x)
        if tag == "Bool" and type(x) is bool:
            return x
        if tag == "Str" and type(x) is str:
            return x
        if tag in ("List", "Tuple") and isinstance(x, list):
            items = tuple(from_tagged(e) for e in x)
            return items if tag == "List" else TupleV(items)
        if tag in ("Map", "Struct") and isinstance(x, dict):
            cls = MapV if tag == "Map" else StructV
            return cls({str(k): from_tagged(e) for k, e in x.items()})
    raise ValueError_(
        f'not a tagged value: {_clip(j)} - write e.g. {{"Int": 42}}, {{"Str": "a"}}, '
        '"Unit" or "Unknown"'
    )


def to_plain(v: object) -> Any:
    """Plain JSON: numbers, strings, booleans, lists, objects; Unit and ⊥ are null."""
    t = type(v)
    if t in (bool, int, float, str):
        return v
    if v is UNIT or v is BOTTOM:
        return None
    if t is tuple or t is TupleV:
        return [to_plain(x) for x in v]  # type: ignore[attr-defined]
    if t is MapV or t is StructV:
        return {k: to_plain(x) for k, x in v.items()}  # type: ignore[attr-defined]
    raise TypeError(f"not a stream value: {v!r}")


def from_plain(j: Any) -> Any:
    """Plain JSON to a value: objects become maps, arrays lists, null Unit."""
    if j is None:
        return UNIT
    t = type(j)
    if t is bool or t is str:
        return j
    if t is int:
        return check_int(j)
    if t is float:
        return j
    if t is list:
        return tuple(from_plain(x) for x in j)
    if t is dict:
        return MapV({str(k): from_plain(x) for k, x in j.items()})
    raise ValueError_(f"not a JSON value: {_clip(j)} - send numbers, strings, lists or objects")


def check_int(i: int) -> int:
    if INT_MIN <= i <= INT_MAX:
        return i
    raise ValueError_(f"integer {_clip(i)} does not fit in 64 bits - send a Float")


def _clip(v: object, n: int = 80) -> str:
    """``repr(v)`` cut to ``n`` characters (a reason must not echo a whole payload)."""
    if type(v) is int and v.bit_length() > 256:
        return f"of {v.bit_length()} bits"  # repr() of a huge int is slow, or refused
    text = repr(v)
    return text if len(text) <= n else text[: n - 3] + "..."

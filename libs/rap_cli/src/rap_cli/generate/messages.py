"""The messages module of a generated package: msgspec Structs from the model's messages,
with their constraints and docs, registered for decoding by wire name; and a samples
module with one valid example of each (the generated tests send them)."""

from __future__ import annotations

import math
import re
from dataclasses import dataclass

from rap_schemas import DeploymentPlan
from rap_schemas.catalog import MESSAGES
from rap_schemas.model import TypeExpr, TypeSyntaxError, parse_type
from rap_schemas.plan import FieldSpec, MessageSpec

from .names import class_name, unique
from .pyfmt import Call, Item, docstring, flat, lines, q, sort_all

__all__ = ["MessageNames", "messages_module", "samples_module"]

_INT_RANGE = {
    "int8": (-(2**7), 2**7 - 1),
    "int16": (-(2**15), 2**15 - 1),
    "int32": (-(2**31), 2**31 - 1),
    "int64": (-(2**63), 2**63 - 1),
    "uint8": (0, 2**8 - 1),
    "uint16": (0, 2**16 - 1),
    "uint32": (0, 2**32 - 1),
    "uint64": (0, 2**64 - 1),
}
_SCALARS = {"bool": "bool", "int": "int", "str": "str", "bytes": "bytes"}
_FLOATS = {"float", "float32", "float64", "double"}


@dataclass(frozen=True, slots=True)
class MessageNames:
    """Python class names of the model's messages and of RAP's wire types in use."""

    classes: dict[str, str]
    """model message name -> class name in the messages module."""
    package: str

    @classmethod
    def of(cls, plan: DeploymentPlan, package: str) -> MessageNames:
        return cls(unique({n: class_name(n) for n in plan.messages}), package)

    def wire(self, type_name: str | None) -> str | None:
        """The class for a port type: a model message, or RAP's own wire type."""
        if type_name is None:
            return None
        if type_name in self.classes:
            return self.classes[type_name]
        for m in MESSAGES:
            if m.TYPE == type_name:
                return m.__name__
        return None

    def is_rap(self, type_name: str | None) -> bool:
        return (
            type_name is not None and type_name not in self.classes and bool(self.wire(type_name))
        )


def _field_name(name: str) -> tuple[str, str | None]:
    """A Python attribute for a field, and its wire name when they differ."""
    if name.isidentifier() and not name.startswith("_") and name != "TYPE":
        import keyword

        if not keyword.iskeyword(name):
            return name, None
    safe = re.sub(r"\W+", "_", name).strip("_") or "field"
    if safe[0].isdigit() or safe.startswith("_"):
        safe = f"f_{safe.lstrip('_')}"
    return f"{safe}_", name


def _annotation(t: TypeExpr, names: MessageNames, metas: list[str]) -> str:
    """The Python annotation of a field type; constraints of the type itself go to
    ``metas``."""
    if t.name == "list":
        assert t.item is not None
        item = _annotation(t.item, names, [])
        if t.length is not None:
            metas.append(f"min_length={t.length}, max_length={t.length}")
        return f"list[{item}]"
    if t.name == "optional":
        assert t.item is not None
        return f"{_annotation(t.item, names, metas)} | None"
    if t.name in _SCALARS:
        return _SCALARS[t.name]
    if t.name in _INT_RANGE:
        lo, hi = _INT_RANGE[t.name]
        # msgspec checks bounds within int64: uint64's upper bound goes unchecked
        metas.append(f"ge={lo}, le={hi}" if hi < 2**63 else f"ge={lo}")
        return "int"
    if t.name in _FLOATS:
        return "float"
    cls = names.wire(t.name)
    return cls if cls is not None else "msgspec.Raw"


def _merge(metas: list[str], spec: FieldSpec, *, integer: bool = False) -> list[str]:
    """One Meta from the type's bounds and the field's constraints (the tighter wins).
    Bounds are written as the model has them (``1`` stays ``1``, ``0.0`` stays ``0.0``);
    an integer field's bounds are integers (msgspec wants them so): ``ge: 0.5`` is
    ``ge=1``."""
    bounds: dict[str, float | int] = {}
    for m in metas:
        for part in m.split(", "):
            name, text = part.split("=")
            bounds[name] = int(text)
    for k in ("ge", "gt", "le", "lt", "min_length", "max_length"):
        v: float | int | None = getattr(spec, k)
        if v is None:
            continue
        if k.endswith("length"):
            v = int(v)
        elif integer and isinstance(v, float):
            v = math.ceil(v) if k in ("ge", "lt") else math.floor(v)
        if k in bounds:  # the tighter wins, written as it is (1 stays 1, 0.0 stays 0.0)
            v = max(bounds[k], v) if k in ("ge", "gt", "min_length") else min(bounds[k], v)
        bounds[k] = v
    # msgspec takes one lower and one upper bound: keep the tighter of ge/gt, le/lt
    for inclusive, strict, stricter in (("ge", "gt", float.__ge__), ("le", "lt", float.__le__)):
        if inclusive in bounds and strict in bounds:
            tight = stricter(float(bounds[strict]), float(bounds[inclusive]))
            del bounds[inclusive if tight else strict]
    parts = [f"{k}={v!r}" for k, v in bounds.items()]
    if spec.pattern is not None:
        parts.append(f"pattern={q(spec.pattern)}")
    if spec.doc:
        parts.append(f"description={q(spec.doc)}")
    return parts


def messages_module(plan: DeploymentPlan, names: MessageNames, source: str) -> str:
    """The text of ``<package>/messages.py``."""
    out = [
        *docstring(
            f"The messages of system {plan.system!r}, generated by ``rap generate`` from "
            f"{source}.\n\nDo not edit: regenerating rewrites this file. Change the messages "
            "in the model.",
            "",
        ),
        "",
        "from __future__ import annotations",
        "",
        "import enum",
        "from typing import Annotated",
        "",
        "import msgspec",
        "from rap_schemas import Message",
        "from rap_schemas.catalog import register",
        "",
    ]
    exports = sort_all(["MESSAGES", "json_schemas", *names.classes.values()])
    out += ["__all__ = [", *(f"    {q(e)}," for e in exports), "]", ""]
    structs: list[str] = []
    for name, spec in plan.messages.items():
        cls = names.classes[name]
        out += ["", *_message(name, cls, spec, names), ""]
        if spec.enum is None:
            structs.append(cls)
    head = "MESSAGES: tuple[type[Message], ...] = "
    if len(structs) == 1:
        listed = [f"{head}({structs[0]},)"]
    else:
        listed = lines(Call(head, tuple(structs)))
    out += [
        "",
        *listed,
        '"""Every message of the model (registered: decoders find them by wire name)."""',
        "register(*MESSAGES)",
        "",
        "",
        "def json_schemas() -> dict[str, object]:",
        '    """The JSON Schema of each message, by wire name."""',
        "    return {m.TYPE: msgspec.json.schema(m) for m in MESSAGES}",
        "",
    ]
    return "\n".join(out)


def _message(name: str, cls: str, spec: MessageSpec, names: MessageNames) -> list[str]:
    if spec.enum is not None:
        out = [f"class {cls}(enum.Enum):", *docstring(spec.doc or name, "    "), ""]
        used: set[str] = set()
        for lit in spec.enum:
            attr, _ = _field_name(lit)
            attr = attr.upper() if attr.isidentifier() else attr
            while attr in used:
                attr += "_"
            used.add(attr)
            out.append(f"    {attr} = {q(lit)}")
        return out
    out = [
        f"class {cls}(Message, frozen=True, kw_only=True):",
        *docstring(spec.doc or f"{name} (a message of the model).", "    "),
        "",
        f"    TYPE = {q(f'{names.package}.{cls}/1')}",
    ]
    for fname, fspec in spec.fields.items():
        attr, wire_name = _field_name(fname)
        metas: list[str] = []
        try:
            t = parse_type(fspec.type)
        except TypeSyntaxError:
            t = TypeExpr("bytes")
        ann: Item = _annotation(t, names, metas)
        inner = t
        while inner.name == "optional" and inner.item is not None:
            inner = inner.item
        meta = _merge(metas, fspec, integer=inner.name == "int" or inner.name in _INT_RANGE)
        if meta:
            ann = Call("Annotated", (ann, Call("msgspec.Meta", tuple(meta))), brackets="[]")
        default = ""
        if t.name == "optional":
            default = " = None" if wire_name is None else ""
        if wire_name is not None:
            extra = ", default=None" if t.name == "optional" else ""
            default = f" = msgspec.field(name={q(wire_name)}{extra})"
        if isinstance(ann, Call):
            ann = Call(f"{attr}: {ann.head}", ann.args, ann.brackets)
        else:
            ann = f"{attr}: {ann}"
        out += lines(ann, "    ", default)
        out += docstring(fspec.doc, "    ")
    return out


# -- samples ---------------------------------------------------------------------------


def _number(spec: FieldSpec | None, lo: float | None, hi: float | None, integer: bool) -> str:
    ge = [x for x in (lo, spec.ge if spec else None) if x is not None]
    le = [x for x in (hi, spec.le if spec else None) if x is not None]
    low = max(ge) if ge else None
    high = min(le) if le else None
    step = 1 if integer else 0.5
    if spec is not None and spec.gt is not None:
        low = max(low, spec.gt + step) if low is not None else spec.gt + step
    if spec is not None and spec.lt is not None:
        high = min(high, spec.lt - step) if high is not None else spec.lt - step
    value: float = 0
    if low is not None and high is not None:
        value = (low + high) / 2
    elif low is not None:
        value = max(low, 0)
    elif high is not None:
        value = min(high, 0)
    if integer:
        return str(int(value))
    return repr(float(value))


def _text(spec: FieldSpec | None, unit: str) -> str:
    n = spec.min_length if spec is not None and spec.min_length else 1
    if spec is not None and spec.max_length is not None:
        n = min(n, spec.max_length)
    if spec is not None and spec.pattern is not None:
        rx = re.compile(spec.pattern)
        for candidate in ("", "a", "0", "a" * n, "0" * n, "A" * n, "a0"):
            if rx.search(candidate):
                return q(candidate)
    return q(unit * n)


def _sample(t: TypeExpr, spec: FieldSpec | None, names: MessageNames, plan: DeploymentPlan) -> Item:
    if t.name == "optional":
        return "None"
    if t.name == "list":
        assert t.item is not None
        n = t.length or (spec.min_length if spec is not None and spec.min_length else 0)
        if not n:
            return "[]"
        item = flat(_sample(t.item, None, names, plan))
        return f"[{item}] * {n}"
    if t.name == "bool":
        return "True"
    if t.name == "int":
        return _number(spec, None, None, True)
    if t.name in _INT_RANGE:
        return _number(spec, *_INT_RANGE[t.name], True)
    if t.name in _FLOATS:
        return _number(spec, None, None, False)
    if t.name == "str":
        return _text(spec, "x")
    if t.name == "bytes":
        return "b" + _text(spec, "\0")
    if t.name in plan.messages:
        return sample_expr(t.name, names, plan)
    return 'msgspec.Raw(b"null")'


def sample_expr(name: str, names: MessageNames, plan: DeploymentPlan) -> Item:
    """A Python expression of a valid example of message ``name`` (a model message)."""
    spec = plan.messages[name]
    cls = f"messages.{names.classes[name]}"
    if spec.enum is not None:
        return f"next(iter({cls}))"
    args: list[Item] = []
    for fname, fspec in spec.fields.items():
        attr, _ = _field_name(fname)
        try:
            t = parse_type(fspec.type)
        except TypeSyntaxError:
            t = TypeExpr("bytes")
        value = _sample(t, fspec, names, plan)
        if isinstance(value, Call):
            args.append(Call(f"{attr}={value.head}", value.args, value.brackets))
        else:
            args.append(f"{attr}={value}")
    return Call(cls, tuple(args))


def samples_module(plan: DeploymentPlan, names: MessageNames) -> str:
    """The text of ``<package>/samples.py``: ``sample(ClassName)`` gives a valid example."""
    out = [
        '"""A valid example of each message (the generated tests send them). Generated by',
        '``rap generate``; regenerating rewrites it."""',
        "",
        "from __future__ import annotations",
        "",
        "from typing import Any",
        "",
        "import msgspec",
        "",
        "from . import messages",
        "",
        '__all__ = ["sample"]',
        "",
        "",
        "def _examples() -> dict[type[Any], Any]:",
    ]
    examples: list[Item] = []
    for name, spec in plan.messages.items():
        if spec.enum is not None:
            continue
        value = sample_expr(name, names, plan)
        key = f"messages.{names.classes[name]}: "
        examples.append(
            Call(key + value.head, value.args) if isinstance(value, Call) else key + value
        )
    if examples:
        out += ["    return {", *(x for e in examples for x in lines(e, "        ", ",")), "    }"]
    else:
        out.append("    return {}")
    out += [
        "",
        "",
        "def sample(cls: type[Any]) -> Any:",
        '    """A valid example of message class ``cls`` (RAP\'s own types: their defaults)."""',
        "    examples = _examples()",
        "    if cls in examples:",
        "        return examples[cls]",
        "    return msgspec.convert({}, cls)",
        "",
    ]
    return "\n".join(out)

"""The messages package of ``rap export aadl`` (:mod:`.aadl`): messages as data types
with the Data_Model annex's properties, RAP wire types as data types with
``RAP::Wire_Type``, and the array types lists need. A field type AADL cannot say
(``optional[float]``, ``bytes``) is ``Base_Types::String`` with ``RAP::Field_Type``;
field constraints are ``RAP::Constraints`` (``ge=0.0; pattern="^a"``, values in JSON).
"""

from __future__ import annotations

import json
from dataclasses import dataclass, field

from rap_schemas import DeploymentPlan
from rap_schemas.model import TypeSyntaxError, parse_type
from rap_schemas.plan import FieldSpec

from .aadl_names import Names, aadl_string, common, props_block, strings

__all__ = ["Types", "messages_section"]

_SCALARS = {
    "bool": "Base_Types::Boolean",
    "int": "Base_Types::Integer",
    "int8": "Base_Types::Integer_8",
    "int16": "Base_Types::Integer_16",
    "int32": "Base_Types::Integer_32",
    "int64": "Base_Types::Integer_64",
    "uint8": "Base_Types::Unsigned_8",
    "uint16": "Base_Types::Unsigned_16",
    "uint32": "Base_Types::Unsigned_32",
    "uint64": "Base_Types::Unsigned_64",
    "float": "Base_Types::Float",
    "float32": "Base_Types::Float_32",
    "float64": "Base_Types::Float_64",
    "str": "Base_Types::String",
}


@dataclass
class Types:
    """The data types of the messages package: messages, enumerations, RAP wire types
    and the array types lists need."""

    pkg: str
    names: Names = field(default_factory=Names)
    extra: list[str] = field(default_factory=list)
    _arrays: dict[str, str] = field(default_factory=dict)
    _wire: dict[str, str] = field(default_factory=dict)

    def wire(self, type_name: str) -> str:
        """The data type standing for RAP wire type ``type_name`` (``rap.LaserScan/2``)."""
        if type_name not in self._wire:
            local = self.names(f"wire {type_name}")
            self._wire[type_name] = local
            self.extra += [
                f"  data {local}",
                "  properties",
                f"    RAP::Wire_Type => {aadl_string(type_name)};",
                f"  end {local};",
                "",
            ]
        return f"{self.pkg}::{self._wire[type_name]}"

    def field_type(self, text: str) -> tuple[str, bool]:
        """The AADL classifier of field type ``text``, and whether it says the type
        exactly (False: the field also needs ``RAP::Field_Type``)."""
        try:
            parsed = parse_type(text)
        except TypeSyntaxError:
            return "Base_Types::String", False
        return self._classifier(str(parsed))

    def _classifier(self, text: str) -> tuple[str, bool]:
        if text in _SCALARS:
            return _SCALARS[text], True
        if text.startswith("list[") and text.endswith("]"):
            inner, size = _split_list(text[5:-1])
            elem, exact = self._classifier(inner)
            key = f"{elem}[{size}]"
            if key not in self._arrays:
                local = self.names(f"{elem.rsplit('::', 1)[-1]} array {size or ''}".strip())
                self._arrays[key] = local
                props = [
                    "Data_Model::Data_Representation => Array",
                    f"Data_Model::Base_Type => (classifier ({elem}))",
                ]
                if size:
                    props.append(f"Data_Model::Dimension => ({size})")
                self.extra += [f"  data {local}", *props_block(props, "  "), f"  end {local};", ""]
            return f"{self.pkg}::{self._arrays[key]}", exact
        if text.startswith(("optional[", "bytes")) or text == "bytes":
            return "Base_Types::String", False
        return f"{self.pkg}::{self.names(text)}", True


def _split_list(inner: str) -> tuple[str, str]:
    depth = 0
    for i, ch in enumerate(inner):
        depth += ch == "["
        depth -= ch == "]"
        if ch == "," and depth == 0:
            return inner[:i].strip(), inner[i + 1 :].strip()
    return inner.strip(), ""


def _constraints(spec: FieldSpec) -> str:
    parts = [
        f"{name}={json.dumps(getattr(spec, name))}"
        for name in ("ge", "le", "gt", "lt", "min_length", "max_length", "pattern")
        if getattr(spec, name) is not None
    ]
    return "; ".join(parts)


def messages_section(plan: DeploymentPlan, types: Types) -> list[str]:
    out: list[str] = []
    for name in plan.messages:
        types.names(name)
    for name, msg in plan.messages.items():
        local = types.names(name)
        shared = common(name, local, msg.doc, {})
        if msg.enum is not None:
            props = [
                "Data_Model::Data_Representation => Enum",
                f"Data_Model::Enumerators => {strings(msg.enum)}",
                *shared,
            ]
            out += [f"  data {local}", *props_block(props, "  "), f"  end {local};", ""]
            continue
        out += [f"  data {local}", *props_block(shared, "  "), f"  end {local};", ""]
        fields = Names()
        subs: list[str] = []
        for fname, spec in msg.fields.items():
            classifier, exact = types.field_type(spec.type)
            fid = fields(fname)
            extra = common(fname, fid, spec.doc, {})
            if not exact:
                extra.append(f"RAP::Field_Type => {aadl_string(spec.type)}")
            cons = _constraints(spec)
            if cons:
                extra.append(f"RAP::Constraints => {aadl_string(cons)}")
            block = " {" + " ".join(f"{p};" for p in extra) + "}" if extra else ""
            subs.append(f"    {fid}: data {classifier}{block};")
        body = ["  subcomponents", *subs] if subs else []
        out += [
            f"  data implementation {local}.impl",
            *body,
            "  properties",
            "    Data_Model::Data_Representation => Struct;",
            f"  end {local}.impl;",
            "",
        ]
    return out

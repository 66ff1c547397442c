"""Data classifiers to the messages of RAP's model, with the Data_Model annex.

What a data classifier becomes (``Data_Model::Data_Representation``, or what it has):

- ``Struct``, or fields without a representation: a message; its fields are the data
  implementation's subcomponents, or ``Element_Names`` with ``Base_Type``, or the type's
  ``provides data access`` features (RPIO writes messages that way);
- ``Union``: a message whose fields are all ``optional[T]`` (one of them is set);
- ``Enum``: an enumeration (``Enumerators``);
- ``Array``: a type, not a message: ``list[T, N]`` with ``Dimension => (N)`` (nested
  lists for several dimensions), ``list[T]`` without; T is ``Base_Type`` (``bytes``,
  with a warning, when it is missing);
- a ``Base_Types`` type, or a data type that extends one, or ``Integer``/``Float``/
  ``Boolean``/``Character``/``String``/``Fixed``: a scalar (``Fixed`` as ``float``);
- anything else (no representation, no fields: an opaque C or ASN.1 type): a message
  with no fields, its doc saying so.

A port must carry a message: a port typed by an array or a scalar carries a *wrapper*
message named after the data classifier (``FloatArray``, ``Float_64``) with one field
``value`` of that type.

A field's ``Data_Model::Measurement_Unit`` (its own, else its data type's) ends its doc:
``"North position (unit: m)"``, ``"unit: s"`` without a doc.

A data type with ``RAP::Wire_Type`` is that RAP wire type (no message); ``RAP::Name``,
``RAP::Field_Type`` and ``RAP::Constraints`` name a message or field, override a
field's type and give its constraints (:mod:`.aadl_rap`).

Message names are the classifier's type name (``shipPose``, ``T`` of ``T.impl``); when
two different classifiers would share a name (compared without case), the later ones
take their qualified name with ``.`` for ``::`` (``pkg.T``, then ``pkg.T.impl``), which
is a valid model name and field type.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rap_schemas.plan import FieldSpec, MessageSpec

from ..aadl import syntax as s
from ..aadl.syntax import norm
from ..diagnostics import Diagnostic, Loc
from .aadl_index import BaseType, Classifier, Index, Opaque, Resolved, diagnostic, find_property
from .aadl_rap import constraints, rap_string

__all__ = ["Messages"]

_SCALAR_REPRESENTATIONS = {
    "integer": "int",
    "float": "float",
    "fixed": "float",
    "boolean": "bool",
    "character": "str",
    "string": "str",
}
_MAX_NESTING = 32

Key = tuple[str, ...]


@dataclass
class Messages:
    """The messages of the model, built on demand from the classifiers ports use."""

    index: Index
    diagnostics: list[Diagnostic]
    rap: bool = False
    """A RAP design (:mod:`.aadl_rap`): every message is imported, docs are its own."""
    specs: dict[str, MessageSpec] = field(default_factory=dict)
    where: dict[tuple[object, ...], Loc] = field(default_factory=dict)
    _names: dict[Key, str] = field(default_factory=dict)
    _taken: dict[str, Key] = field(default_factory=dict)
    _warned: set[Key] = field(default_factory=set)

    # -- entry points

    def port_type(self, resolved: Resolved, loc: Loc) -> str | None:
        """The message a port of classifier ``resolved`` carries (None: untyped or not
        resolved)."""
        if resolved is None:
            return None
        if isinstance(resolved, BaseType):
            return self._wrapper(
                ("base", norm(resolved.name)),
                resolved.name,
                resolved.rap,
                f"Base_Types::{resolved.name}",
                loc,
            )
        if isinstance(resolved, Opaque):
            return self._opaque(resolved, loc)
        wire = rap_string(self._props(resolved), "Wire_Type")
        if wire:
            return wire
        inline = self._inline(resolved, 0)
        if inline is None:
            return self.message(resolved, 0)
        return self._wrapper(
            _key(resolved), resolved.type_name, inline, resolved.qualified, resolved.decl.loc
        )

    def field_type(self, resolved: Resolved, loc: Loc, depth: int = 0) -> str:
        """The field type of a field of classifier ``resolved``."""
        if isinstance(resolved, BaseType):
            return resolved.rap
        if isinstance(resolved, Opaque):
            return self._opaque(resolved, loc)
        if resolved is None:
            return "bytes"
        inline = self._inline(resolved, depth)
        return inline if inline is not None else self.message(resolved, depth)

    # -- naming

    def every_message(self) -> None:
        """Import every struct and enumeration data classifier of the design, used by a
        port or not (a RAP design's messages)."""
        for package in self.index.packages.values():
            for decl in package.declarations:
                c = Classifier(package, decl)
                if decl.category != "data" or rap_string(self._props(c), "Wire_Type"):
                    continue
                if self._representation(c) in ("struct", "enum"):
                    self.message(c, 0)

    def _name(self, key: Key, short: str, qualified: str, named: str | None = None) -> str:
        """The message name of ``key`` (see the module's docstring); ``named`` (its
        ``RAP::Name``) wins."""
        found = self._names.get(key)
        if found is not None:
            return found
        if named is not None:
            self._taken[norm(named)] = key
            self._names[key] = named
            return named
        for candidate in (short, qualified.replace("::", "."), f"{qualified.replace('::', '.')}_"):
            if norm(candidate) not in self._taken:
                self._taken[norm(candidate)] = key
                self._names[key] = candidate
                return candidate
        raise AssertionError(f"no free name for {qualified}")  # pragma: no cover

    # -- kinds

    def _wrapper(self, key: Key, short: str, inner: str, qualified: str, loc: Loc) -> str:
        name = self._name(key, short, qualified)
        if name not in self.specs:
            self.specs[name] = MessageSpec(
                fields={"value": FieldSpec(type=inner)},
                origin=f"aadl data {qualified}",
                doc=f"wraps {qualified} ({inner}): a port carries a message",
            )
            self.where[("messages", name)] = loc
        return name

    def _opaque(self, resolved: Opaque, loc: Loc) -> str:
        name = self._name(("opaque", norm(resolved.ref)), resolved.name, resolved.ref)
        if name not in self.specs:
            self.specs[name] = MessageSpec(
                origin=f"aadl data {resolved.ref}",
                doc=f"opaque: {resolved.ref} is in a library the import does not hold",
            )
            self.where[("messages", name)] = loc
        return name

    def _props(self, c: Classifier) -> list[s.PropertyAssociation]:
        return self.index.properties(c)

    def _representation(self, c: Classifier) -> str | None:
        found = find_property(self._props(c), "Data_Model::Data_Representation")
        if found is None:
            return None
        if isinstance(found.value, s.EnumValue):
            return norm(found.value.literal)
        self._warn(
            c,
            found.loc,
            f"Data_Representation of {c.qualified} is not a literal "
            "such as Struct, Array or Enum - it is ignored",
        )
        return None

    def _inline(self, c: Classifier, depth: int) -> str | None:
        """The field type of ``c`` when it is not a message: an array or a scalar."""
        rep = self._representation(c)
        if rep == "array":
            return self._array(c, depth)
        if rep in _SCALAR_REPRESENTATIONS:
            return _SCALAR_REPRESENTATIONS[rep]
        if rep is None and not self._has_fields(c):
            base = self.index.base_of(c)
            if isinstance(base, BaseType):
                return base.rap
        return None

    def _array(self, c: Classifier, depth: int) -> str:
        props = self._props(c)
        bases = _classifiers(find_property(props, "Data_Model::Base_Type"))
        if bases:
            value, package = bases[0]
            element = (
                self.field_type(
                    self.index.resolve(value.name, package or c.package, value.loc),
                    value.loc,
                    depth + 1,
                )
                if depth < _MAX_NESTING
                else "bytes"
            )
        else:
            element = "bytes"
            self._warn(
                c,
                c.decl.loc,
                f"the array {c.qualified} has no Data_Model::Base_Type: "
                "its elements are read as bytes - add Data_Model::Base_Type => "
                "(classifier (Base_Types::...))",
            )
        dims = find_property(props, "Data_Model::Dimension")
        sizes: list[int] = []
        if dims is not None:
            items = dims.value.items if isinstance(dims.value, s.ListValue) else (dims.value,)
            for item in items:
                if isinstance(item, s.IntValue) and item.value > 0:
                    sizes.append(item.value)
                else:
                    self._warn(
                        c,
                        dims.loc,
                        f"Dimension of {c.qualified} is not a list of "
                        "positive integers - the array is read without a length",
                    )
                    sizes = []
                    break
        if not sizes:
            return f"list[{element}]"
        out = element
        for size in reversed(sizes):
            out = f"list[{out}, {size}]"
        return out

    def _has_fields(self, c: Classifier) -> bool:
        if self.index.subcomponents(c):
            return True
        if find_property(self._props(c), "Data_Model::Element_Names") is not None:
            return True
        return any(f.kind == "data access" for f in self.index.features(c).values())

    def canonical(self, c: Classifier) -> Classifier:
        """A data type with exactly one implementation in its package stands for that
        implementation (AADL matches a type with its implementations), so that both
        become one message."""
        impls = [
            d
            for d in c.package.declarations
            if isinstance(d, s.ComponentImpl) and norm(d.type_name) == norm(c.type_name)
        ]
        return Classifier(c.package, impls[0]) if len(impls) == 1 else c

    def message(self, c: Classifier, depth: int) -> str:
        """The message (or enumeration) classifier ``c`` becomes."""
        c = self.canonical(c)
        named = rap_string(self._props(c), "Name")
        name = self._name(_key(c), c.type_name, c.qualified, named)
        if name in self.specs:
            return name
        own_doc = rap_string(self._props(c), "Doc")
        origin = f"aadl data {c.qualified}"
        self.specs[name] = MessageSpec(origin=origin)  # placeholder against recursion
        self.where[("messages", name)] = c.decl.loc
        rep = self._representation(c)
        if rep == "enum":
            self.specs[name] = self._enum(c, origin, own_doc or "")
            return name
        fields = self._fields(c, name, depth, optional=rep == "union")
        doc = ""
        if rep == "union":
            doc = f"the union {c.qualified}: exactly one field is set"
        elif not fields:
            doc = f"opaque: {c.qualified} gives no fields nor Data_Model representation"
            if rep not in (None, "struct"):
                doc = f"{c.qualified}: Data_Representation {rep} has no RAP equivalent"
        if own_doc is not None or self.rap:
            doc = own_doc or ""
        self.specs[name] = MessageSpec(fields=fields, origin=origin, doc=doc)
        return name

    def _enum(self, c: Classifier, origin: str, doc: str) -> MessageSpec:
        found = find_property(self._props(c), "Data_Model::Enumerators")
        literals: list[str] = []
        if found is not None:
            items = found.value.items if isinstance(found.value, s.ListValue) else (found.value,)
            for item in items:
                if isinstance(item, s.StringValue):
                    literals.append(item.value)
                elif isinstance(item, s.EnumValue):
                    literals.append(item.literal)
        if not literals:
            self._warn(
                c,
                c.decl.loc,
                f"the enumeration {c.qualified} lists no "
                'Data_Model::Enumerators - add Enumerators => ("a", "b")',
            )
        return MessageSpec(enum=literals, origin=origin, doc=doc)

    def _fields(
        self, c: Classifier, name: str, depth: int, *, optional: bool
    ) -> dict[str, FieldSpec]:
        out: dict[str, FieldSpec] = {}
        entries: list[tuple[str, Resolved, Loc]] = []
        own: dict[str, tuple[s.PropertyAssociation, ...]] = {}
        subs = self.index.subcomponents(c)
        if subs:
            for sub, package in subs:
                resolved = (
                    self.index.resolve(sub.classifier, package, sub.loc)
                    if sub.classifier is not None
                    else None
                )
                entries.append((sub.name, resolved, sub.loc))
                own[sub.name] = sub.properties
        elif (names := find_property(self._props(c), "Data_Model::Element_Names")) is not None:
            entries = self._elements(c, names)
        else:
            ctype = self.index.type_of(c)
            for feature in self.index.features(c).values():
                if feature.kind != "data access" or feature.classifier is None:
                    continue
                package = ctype.package if ctype is not None else c.package
                resolved = self.index.resolve(feature.classifier, package, feature.loc)
                entries.append((feature.name, resolved, feature.loc))
        for fname, resolved, loc in entries:
            props = own.get(fname, ())
            ftype = rap_string(props, "Field_Type")
            if ftype is None:
                ftype = (
                    self.field_type(resolved, loc, depth + 1) if depth < _MAX_NESTING else "bytes"
                )
                ftype = f"optional[{ftype}]" if optional else ftype
            called = rap_string(props, "Name") or fname
            doc = rap_string(props, "Doc") or ""
            unit = self._unit(list(props), resolved)
            if unit:
                doc = f"{doc} (unit: {unit})" if doc else f"unit: {unit}"
            out[called] = FieldSpec(type=ftype, doc=doc, **constraints(props))
            self.where[("messages", name, "fields", called)] = loc
        return out

    def _unit(self, own: list[s.PropertyAssociation], resolved: Resolved) -> str | None:
        """``Data_Model::Measurement_Unit`` of a field: its own, else its data type's."""
        found = find_property(own, "Data_Model::Measurement_Unit")
        if found is None and isinstance(resolved, Classifier):
            found = find_property(self._props(resolved), "Data_Model::Measurement_Unit")
        value = found.value if found is not None else None
        if isinstance(value, s.StringValue):
            return value.value or None
        return value.literal if isinstance(value, s.EnumValue) else None

    def _elements(
        self, c: Classifier, names: s.PropertyAssociation
    ) -> list[tuple[str, Resolved, Loc]]:
        labels = [i.value for i in _items(names.value) if isinstance(i, s.StringValue)]
        bases = _classifiers(find_property(self._props(c), "Data_Model::Base_Type"))
        if len(bases) != len(labels):
            self._warn(
                c,
                names.loc,
                f"{c.qualified} names {len(labels)} elements but gives "
                f"{len(bases)} Base_Type classifiers - give one classifier per name",
            )
        out: list[tuple[str, Resolved, Loc]] = []
        for label, (value, package) in zip(labels, bases, strict=False):
            out.append(
                (label, self.index.resolve(value.name, package or c.package, value.loc), value.loc)
            )
        return out

    def _warn(self, c: Classifier, loc: Loc, message: str) -> None:
        key = (*_key(c), message)
        if key not in self._warned:
            self._warned.add(key)
            self.diagnostics.append(diagnostic(loc, "warning", message))


def _key(c: Classifier) -> Key:
    """Messages are keyed by type; a type's several implementations by their own names."""
    if isinstance(c.decl, s.ComponentImpl):
        impls = [
            d
            for d in c.package.declarations
            if isinstance(d, s.ComponentImpl) and norm(d.type_name) == norm(c.type_name)
        ]
        if len(impls) == 1:
            return ("data", norm(c.package.name), norm(c.type_name))
    return ("data", *c.key)


def _items(value: s.PropertyValue) -> tuple[s.PropertyValue, ...]:
    return value.items if isinstance(value, s.ListValue) else (value,)


def _classifiers(
    assoc: s.PropertyAssociation | None,
) -> list[tuple[s.ClassifierValue, s.Package | None]]:
    if assoc is None:
        return []
    return [(i, None) for i in _items(assoc.value) if isinstance(i, s.ClassifierValue)]

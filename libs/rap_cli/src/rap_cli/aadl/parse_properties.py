"""Building the syntax model of property associations, property values and property
sets (types, definitions, constants, units) from lark's parse tree."""

from __future__ import annotations

from lark import Token, Tree

from rap_cli.aadl import syntax as s
from rap_cli.aadl.parse_tree import (
    _TYPE_RULES,
    _VALUE_RULES,
    _BuilderBase,
    _has,
    _owner_text,
    _text,
    _toks,
    _tree,
    _trees,
)

_MAX_EXPONENT = 308  # integer literals beyond 1e308 are refused, not computed


class _PropertyBuilder(_BuilderBase):
    """Property associations, values and property sets."""

    def section_properties(self, tree: Tree[Token]) -> tuple[s.PropertyAssociation, ...]:
        """The associations of all ``properties`` sections of a classifier."""
        found: list[s.PropertyAssociation] = []
        for section in _trees(tree, "properties"):
            found += self.properties(section)
        return tuple(found)

    def properties(self, section: Tree[Token] | None) -> tuple[s.PropertyAssociation, ...]:
        """The associations of one ``properties`` section or ``{ }`` block."""
        if section is None:
            return ()
        return tuple(self.association(a) for a in _trees(section, "property_association"))

    def block(self, tree: Tree[Token]) -> tuple[s.PropertyAssociation, ...]:
        """The inline ``{ }`` associations of an element."""
        return self.properties(_tree(tree, "prop_block"))

    def association(self, tree: Tree[Token]) -> s.PropertyAssociation:
        """One property association."""
        value = next(c for c in tree.children if isinstance(c, Tree) and c.data in _VALUE_RULES)
        applies = _tree(tree, "applies_to")
        binding = _tree(tree, "in_binding")
        return s.PropertyAssociation(
            self.loc(tree),
            _text(_trees(tree, "property_name")[0]),
            self.value(value),
            tuple(_text(p) for p in _trees(applies, "element_path")) if applies else (),
            _has(tree, "APPEND"),
            _has(tree, "CONSTANT"),
            self.in_modes(tree),
            tuple(_text(c) for c in _trees(binding, "classifier_ref")) if binding else (),
        )

    def value(self, tree: Tree[Token]) -> s.PropertyValue:
        """A property value of any kind."""
        loc = self.loc(tree)
        kind = tree.data
        if kind == "number_value":
            return self.number(tree)
        if kind == "list_value":
            return s.ListValue(loc, tuple(self.value(c) for c in _trees(tree, *_VALUE_RULES)))
        if kind == "range_value":
            bounds = [self.value(c) for c in _trees(tree, *_VALUE_RULES)]
            return s.RangeValue(loc, bounds[0], bounds[1], bounds[2] if len(bounds) > 2 else None)
        if kind == "string_value":
            return s.StringValue(loc, str(tree.children[0])[1:-1].replace('""', '"'))
        if kind == "bool_value":
            return s.BoolValue(loc, _has(tree, "TRUE"))
        if kind == "name_value":
            text = _text(tree)
            return s.NameValue(loc, text) if "::" in text else s.EnumValue(loc, text)
        if kind == "reference_value":
            return s.ReferenceValue(loc, _text(_trees(tree, "element_path")[0]))
        if kind == "classifier_value":
            return s.ClassifierValue(loc, _text(_trees(tree, "classifier_ref")[0]))
        if kind == "record_value":
            fields = []
            for field in _trees(tree, "record_field"):
                name = _toks(field, "IDENT")[0]
                inner = _trees(field, *_VALUE_RULES)[0]
                fields.append(s.RecordField(self.loc(name), str(name), self.value(inner)))
            return s.RecordValue(loc, tuple(fields))
        # computed_value: compute ( function )
        return s.ComputedValue(loc, "".join(str(t) for t in _toks(tree, "IDENT", "DCOLON")))

    def number(self, tree: Tree[Token]) -> s.IntValue | s.RealValue:
        """A signed number with the unit written after it."""
        loc = self.loc(tree)
        negative = _has(tree, "MINUS")
        unit_tokens = _toks(tree, "IDENT")
        unit = str(unit_tokens[0]) if unit_tokens else None
        reals = _toks(tree, "REAL")
        if reals:
            real = float(str(reals[0]).replace("_", ""))
            return s.RealValue(loc, -real if negative else real, unit)
        literal = _toks(tree, "INTEGER")[0]
        integer = self.integer(literal)
        return s.IntValue(loc, -integer if negative else integer, unit)

    def integer(self, token: Token) -> int:
        """An AADL integer literal: ``1_000``, ``1e3``, ``16#FF#``, ``2#1010#e2``."""
        text = str(token).replace("_", "").lower()
        if "#" in text:
            base_text, digits, tail = text.split("#")
            base, exponent = int(base_text), int(tail[1:].lstrip("+") or 0) if tail else 0
        else:
            digits, _, tail = text.partition("e")
            base, exponent = 10, int(tail.lstrip("+") or 0)
        if not 2 <= base <= 16 or exponent > _MAX_EXPONENT:
            message = (
                f"the integer {token} is out of range "
                f"- use a base from 2 to 16 and an exponent up to {_MAX_EXPONENT}"
            )
            self.report(token, "error", message)
            return 0
        scale: int = base**exponent
        try:
            return int(digits, base) * scale
        except ValueError:
            message = f"'{digits}' are not digits of base {base} - fix the literal {token}"
            self.report(token, "error", message)
            return 0

    # -- property sets

    def property_set(self, tree: Tree[Token]) -> s.PropertySet:
        """A property set: its types, definitions and constants."""
        idents = _toks(tree, "IDENT")
        self.check_end([idents[0]], [idents[-1]], "the property set")
        names = [n for w in _trees(tree, "with_clause") for n in _trees(w, "pkg_name")]
        withs = [_text(n) for n in names]
        types = []
        for decl in _trees(tree, "property_type"):
            name = _toks(decl, "IDENT")[0]
            spec = _trees(decl, *_TYPE_RULES)[0]
            types.append(s.PropertyTypeDecl(self.loc(name), str(name), self.ptype(spec)))
        definitions = [self.definition(d) for d in _trees(tree, "property_definition")]
        constants = []
        for decl in _trees(tree, "property_constant"):
            name = _toks(decl, "IDENT")[0]
            spec = _trees(decl, *_TYPE_RULES)[0]
            value = _trees(decl, *_VALUE_RULES)[0]
            depth = len(_trees(decl, "list_of"))
            constant = s.PropertyConstant(
                self.loc(name), str(name), self.ptype(spec), self.value(value), depth
            )
            constants.append(constant)
        return s.PropertySet(
            self.loc(tree),
            str(idents[0]),
            tuple(withs),
            tuple(types),
            tuple(definitions),
            tuple(constants),
            tuple(self.loc(n) for n in names),
        )

    def definition(self, tree: Tree[Token]) -> s.PropertyDefinition:
        """A property definition."""
        name = _toks(tree, "IDENT")[0]
        default = _trees(tree, *_VALUE_RULES)
        return s.PropertyDefinition(
            self.loc(name),
            str(name),
            self.ptype(_trees(tree, *_TYPE_RULES)[0]),
            len(_trees(tree, "list_of")),
            _has(tree, "INHERIT"),
            self.value(default[0]) if default else None,
            tuple(_owner_text(o) for o in _trees(tree, "owner")),
        )

    def ptype(self, tree: Tree[Token]) -> s.PropertyType:
        """A property type, inline or named."""
        loc = self.loc(tree)
        kind = tree.data
        if kind == "type_ref":
            return s.PropertyType(loc, "named", name=_text(tree))
        if kind in {"int_type", "real_type"}:
            bounds = _tree(tree, "type_range")
            low = high = None
            if bounds is not None:
                low, high = (self.value(b) for b in _trees(bounds, *_VALUE_RULES))
            units_name: str | None = None
            units: tuple[s.UnitLiteral, ...] = ()
            spec = _tree(tree, "units_spec")
            if spec is not None:
                named = _tree(spec, "type_ref")
                units_name = _text(named) if named is not None else None
                units = self.units(_tree(spec, "units_list"))
            base = "aadlinteger" if kind == "int_type" else "aadlreal"
            return s.PropertyType(loc, base, units_name=units_name, units=units, low=low, high=high)
        if kind == "units_type":
            return s.PropertyType(loc, "units", units=self.units(_tree(tree, "units_list")))
        if kind == "enum_type":
            literals = tuple(str(t) for t in _toks(tree, "IDENT"))
            return s.PropertyType(loc, "enumeration", enumerators=literals)
        if kind in {"classifier_type", "reference_type"}:
            owners = tuple(_owner_text(o) for o in _trees(tree, "owner"))
            return s.PropertyType(loc, kind.removesuffix("_type"), owners=owners)
        if kind == "range_type":
            element = self.ptype(_trees(tree, *_TYPE_RULES)[0])
            return s.PropertyType(loc, "range", element=element)
        if kind == "record_type":
            fields = []
            for field in _trees(tree, "record_field_decl"):
                name = _toks(field, "IDENT")[0]
                ftype = self.ptype(_trees(field, *_TYPE_RULES)[0])
                depth = len(_trees(field, "list_of"))
                fields.append(s.RecordFieldType(self.loc(name), str(name), ftype, depth))
            return s.PropertyType(loc, "record", fields=tuple(fields))
        return s.PropertyType(loc, "aadlboolean" if kind == "bool_type" else "aadlstring")

    def units(self, tree: Tree[Token] | None) -> tuple[s.UnitLiteral, ...]:
        """The literals of ``units (..)``."""
        if tree is None:
            return ()
        literals = []
        for decl in _trees(tree, "unit_decl"):
            idents = _toks(decl, "IDENT")
            factor: int | float | None = None
            numbers = _toks(decl, "INTEGER", "REAL")
            if numbers:
                number = numbers[0]
                factor = (
                    self.integer(number)
                    if number.type == "INTEGER"
                    else float(str(number).replace("_", ""))
                )
            base = str(idents[1]) if len(idents) > 1 else None
            literals.append(s.UnitLiteral(self.loc(decl), str(idents[0]), base, factor))
        return tuple(literals)

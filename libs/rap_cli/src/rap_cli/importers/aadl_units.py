"""Units written after numbers in an AADL design, checked against the units declared by
the property sets of the import and the predeclared ``AADL_Project`` (and OSATE ``SEI``)
units types: an undeclared one (``23.46 Mbps``) is an error at the number, naming the
units the property's type accepts."""

from __future__ import annotations

from collections.abc import Iterator

from ..aadl import syntax as s
from ..aadl.syntax import norm
from .aadl_index import Index, diagnostic

__all__ = ["AADL_PROJECT_UNITS", "check_units", "declared_units"]

AADL_PROJECT_UNITS = {
    "time_units": ("ps", "ns", "us", "ms", "sec", "min", "hr"),
    "size_units": ("bits", "Bytes", "KByte", "MByte", "GByte", "TByte"),
    "data_rate_units": ("bitsps", "Bytesps", "KBytesps", "MBytesps", "GBytesps"),
    "processor_speed_units": ("KIPS", "MIPS", "GIPS"),
    "frequency_units": ("Hz", "KHz", "MHz", "GHz"),
    "power_units": ("mW", "W", "KW"),
    "voltage_units": ("mV", "V", "KV"),
    "energy_units": ("mJ", "J", "KJ"),
    "current_units": ("mA", "A"),
    "weight_units": ("g", "kg"),
    "instructions_units": ("ipd", "kipd", "mipd"),
}
"""Units types of ``AADL_Project`` (and OSATE's ``SEI``), known without a file."""


def declared_units(index: Index) -> set[str]:
    units = {norm(u) for names in AADL_PROJECT_UNITS.values() for u in names}
    for pset in index.property_sets.values():
        units |= {norm(u.name) for u in pset.unit_literals()}
    return units


def check_units(index: Index) -> None:
    """Every unit written after a number must be declared somewhere."""
    declared = declared_units(index)
    for assoc in _associations(index):
        for value in _numbers(assoc.value):
            if value.unit is None or norm(value.unit) in declared:
                continue
            allowed = _units_of(index, assoc.name)
            fix = f"use one of {', '.join(allowed)}" if allowed else "use a declared unit"
            message = (
                f"the unit {value.unit} of {assoc.name} is declared by no property set "
                f"of the import nor AADL_Project - {fix}, or declare {value.unit} in "
                "the property's units type"
            )
            index.diagnostics.append(diagnostic(value.loc, "error", message))


def _units_of(index: Index, name: str) -> list[str]:
    head, _, simple = name.rpartition("::")
    sets = [index.property_sets[norm(head)]] if norm(head) in index.property_sets else []
    sets = sets or list(index.property_sets.values())
    for pset in sets:
        for definition in pset.definitions:
            if norm(definition.name) == norm(simple):
                return _units_of_type(index, definition.type)
    return []


def _units_of_type(index: Index, ptype: s.PropertyType) -> list[str]:
    if ptype.units:
        return [u.name for u in ptype.units]
    if ptype.element is not None:
        return _units_of_type(index, ptype.element)
    if ptype.units_name is None:
        return []
    head, _, simple = ptype.units_name.rpartition("::")
    if norm(simple) in AADL_PROJECT_UNITS:
        return list(AADL_PROJECT_UNITS[norm(simple)])
    for pset in index.property_sets.values():
        if head and norm(pset.name) != norm(head):
            continue
        for decl in pset.types:
            if norm(decl.name) == norm(simple):
                return [u.name for u in decl.type.units]
    return []


def _associations(index: Index) -> Iterator[s.PropertyAssociation]:
    for package in index.packages.values():
        yield from package.properties
        for decl in package.declarations:
            yield from decl.properties
            for mode in decl.modes:
                yield from mode.properties
            if isinstance(decl, s.ComponentType):
                for feature in decl.features:
                    yield from feature.properties
            else:
                for sub in decl.subcomponents:
                    yield from sub.properties
                for conn in decl.connections:
                    yield from conn.properties


def _numbers(value: s.PropertyValue) -> Iterator[s.IntValue | s.RealValue]:
    if isinstance(value, s.IntValue | s.RealValue):
        yield value
    elif isinstance(value, s.RangeValue):
        yield from _numbers(value.low)
        yield from _numbers(value.high)
        if value.delta is not None:
            yield from _numbers(value.delta)
    elif isinstance(value, s.ListValue):
        for item in value.items:
            yield from _numbers(item)
    elif isinstance(value, s.RecordValue):
        for fld in value.fields:
            yield from _numbers(fld.value)

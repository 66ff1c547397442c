"""AADL-IL processors -> compute nodes, and their bindings of processes.

Part of :mod:`.aadl_il`'s import: a processor's ``_IP`` is the node's address; its
``rap_backbone``, ``_propertyList`` (value and unit) and own features (network
interfaces) become properties; each ``_bindingList`` entry (a copy of a process) binds the
process of that name to it - a name no process has, or a second binding, is an error.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import msgspec
from rap_schemas.plan import ComponentSpec, ComputeNode

from .aadl_il_json import JsonPath
from .aadl_il_names import clean_name, description

if TYPE_CHECKING:
    from .aadl_il import _Importer

__all__ = ["processor", "scalar_text"]


def processor(self: _Importer, proc: dict[str, Any], at: JsonPath, system: str) -> None:
    """A processor -> a compute node, and the processes its ``_bindingList`` binds to it."""
    name = self._name(proc, at, "processor")
    if name is None:
        return
    nname = clean_name(name)
    if nname in self.nodes:
        self._report(
            at,
            "error",
            f"processor {name!r} is declared again - rename one; the second is left out",
        )
        return
    properties: dict[str, str] = {}
    if "rap_backbone" in proc:
        properties["rap_backbone"] = scalar_text(proc["rap_backbone"])
    for path, prop in self._items(proc, "_propertyList", at):
        pname = self._name(prop, path, "property")
        if pname is not None:
            unit = prop.get("_dataType")
            value = scalar_text(prop.get("_value"))
            properties[pname] = f"{value} {unit}" if isinstance(unit, str) and unit else value
    interfaces = [
        f"{f.get('_name')} ({f.get('_featureType')}, {f.get('_type')})"
        for _, f in self._items(proc, "_featureList", at)
    ]
    if interfaces:
        properties["features"] = "; ".join(interfaces)
    address = proc.get("_IP")
    self.nodes[nname] = ComputeNode(
        address=address if isinstance(address, str) and address else None,
        origin=f"aadl-il processor {system}.{name}",
        properties=properties,
        doc=description(proc),
    )
    self._where(("compute_nodes", nname), (*at, "_name"))
    self._where(("compute_nodes", nname, "address"), (*at, "_IP"))
    for path, binding in self._items(proc, "_bindingList", at):
        _bind(self, binding, path, nname)


def _bind(self: _Importer, binding: dict[str, Any], at: JsonPath, node: str) -> None:
    name = self._name(binding, at, "binding")
    if name is None:
        return
    cname = clean_name(name)
    comp = self.components.get(cname)
    if comp is None or comp.external:
        listed = ", ".join(c for c, s in self.components.items() if not s.external)
        self._report(
            (*at, "_name"),
            "error",
            f"processor {node!r} binds process {name!r}, "
            f"which the design does not declare - use one of {listed or '(none)'}",
        )
        return
    if cname in self.bound:
        first = self.doc.loc(self.bound[cname])
        self._report(
            (*at, "_name"),
            "error",
            f"process {name!r} is bound a second time "
            f"(first at line {first.line}, to {comp.node}) - bind it to one "
            "processor; the first binding is kept",
        )
        return
    self.bound[cname] = (*at, "_name")
    self.components[cname] = _replace(comp, node=node)
    self._where(("components", cname, "node"), (*at, "_name"))


def _replace(comp: ComponentSpec, **changes: Any) -> ComponentSpec:
    return msgspec.structs.replace(comp, **changes)


def scalar_text(value: object) -> str:
    """A JSON scalar as a property value (``true``/``false`` as JSON writes them)."""
    if isinstance(value, bool):
        return "true" if value else "false"
    return "" if value is None else str(value)

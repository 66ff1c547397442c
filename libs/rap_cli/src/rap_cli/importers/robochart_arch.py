"""The RoboArch (``.rac``) part of a RoboChart import.

A RoboArch file describes the same system one level up: layers with their inputs and
outputs (a MAPLE-K layer with stage blocks), the platform, datatypes and interfaces, and
the connections between layers and platform. Given with the RoboChart files it
describes, it mostly repeats them, so:

- a layer named like a RoboChart controller *is* that controller: its type, pattern,
  inputs, outputs and other properties become ``roboarch.*`` properties of the
  controller's component, and each stage block's properties go to the controller's machine
  of that stage (a note when there is none);
- any other layer becomes a component with role ``layer``: its inputs are ``in`` ports,
  its outputs ``out`` ports (typed like events); its stage blocks become components
  ``<layer>.<block>`` with that stage and the block's properties; other blocks become
  ``roboarch.<block>.<key>`` properties of the layer;
- a datatype or enumeration named like a RoboChart one is that message (a note; a
  warning when the fields differ); the platform likewise; otherwise they are added;
- a connection a module already makes is noted as a repeat; others are added.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

from ..robochart import syntax as s
from .aadl_il_names import stage_or_role
from .robochart_model import CompDraft, EventRef
from .robochart_notes import leftovers
from .robochart_scope import render_type

if TYPE_CHECKING:
    from .robochart import _Importer

__all__ = ["import_roboarch"]


def _values(values: tuple[s.PropertyValue, ...]) -> str:
    return ", ".join(f"{v.name}: {render_type(v.type)}" if v.type else v.name for v in values)


def _block_properties(block: s.LayerBlock, prefix: str) -> dict[str, str]:
    """A block's properties (``key = values;``) and nested blocks' as text."""
    props: dict[str, str] = {}
    todo = [(block, prefix)]
    while todo:
        b, at = todo.pop()
        for p in b.properties:
            key = f"{at}{p.key}"
            text = _values(p.values)
            props[key] = f"{props[key]}; {text}" if key in props else text
        for use in (*b.uses, *b.provides, *b.requires):
            props[f"{at}{use.kind}"] = use.interface
        todo += [(inner, f"{at}{inner.name}.") for inner in b.blocks]
    return props


def import_roboarch(imp: _Importer, rac: s.RacFile) -> None:
    """Add what ``rac`` says to the import (see the module docstring)."""
    draft = imp.draft
    for decl in rac.declarations:
        if isinstance(decl, s.Record | s.Enumeration | s.PrimitiveType):
            _message(imp, decl, rac)
        elif isinstance(decl, s.RoboticPlatform):
            known = imp.by_design_name.get(decl.name)
            if known is not None and known.role == "platform":
                imp.platforms[decl] = known
                imp.events((), (*decl.uses, *decl.provides, *decl.requires), rac, decl.name)
                draft.report(
                    decl.loc,
                    "note",
                    f"robotic platform {decl.name} is the RoboChart platform at {known.loc} - "
                    "one component",
                )
            else:
                imp.platform(decl, rac, decl.name)
    leftovers(imp, rac)
    for layer in rac.layers:
        known = imp.by_design_name.get(layer.name)
        if known is not None and known.role == "controller":
            _controller_layer(imp, layer, known, rac)
        else:
            _layer(imp, layer, rac)
    for conn in rac.connections:
        imp.connection(conn, imp.by_design_name, f"system {rac.system}", repeat_ok=True)


def _message(
    imp: _Importer, decl: s.Record | s.Enumeration | s.PrimitiveType, rac: s.RacFile
) -> None:
    draft = imp.draft
    imp.scope.message_of[decl] = decl.name
    known = draft.messages.get(decl.name)
    if known is None:
        imp.add_message(decl, rac, "roboarch datatype")
        return
    at = imp.out.where.get(("messages", decl.name))
    same = (
        known.enum == [lit.name for lit in decl.literals]
        if isinstance(decl, s.Enumeration)
        else not isinstance(decl, s.Record) or imp.fields(decl, rac, decl.name) == known.fields
    )
    if same:
        draft.report(
            decl.loc, "note", f"{decl.name} repeats the RoboChart type at {at} - one message"
        )
    else:
        draft.report(
            decl.loc,
            "warning",
            f"{decl.name} differs from the RoboChart type of that name at {at} - make them "
            "agree; the RoboChart one is used",
        )


def _controller_layer(imp: _Importer, layer: s.Layer, comp: CompDraft, rac: s.RacFile) -> None:
    uses = (*layer.uses, *layer.provides, *layer.requires)
    imp.events((), uses, rac, layer.name)  # resolves (and marks used) its interfaces
    props = comp.properties
    if uses:
        props["roboarch.interfaces"] = "; ".join(f"{u.kind} {u.interface}" for u in uses)
    if layer.layer_type:
        props["roboarch.layer"] = layer.layer_type
    if layer.pattern:
        props["roboarch.pattern"] = layer.pattern
    if layer.inputs:
        props["roboarch.inputs"] = _values(layer.inputs)
    if layer.outputs:
        props["roboarch.outputs"] = _values(layer.outputs)
    for p in layer.properties:
        props[f"roboarch.{p.key}"] = _values(p.values)
    imp.draft.report(
        layer.loc,
        "note",
        f"layer {layer.name} is the RoboChart controller at {comp.loc}: its RoboArch "
        "properties are kept on that component",
    )
    machines = imp.machines_of.get(comp.name, [])
    for block in layer.stages:
        stage, role = stage_or_role(block.name)
        match = [m for m in machines if (stage and m.stage is stage) or (role and m.role == role)]
        if not match:
            imp.draft.report(
                block.loc,
                "note",
                f"block {block.name} of layer {layer.name}: controller {comp.name} has no "
                "machine of that stage; its properties are kept on the controller",
            )
            props.update(_block_properties(block, f"roboarch.{block.name}."))
            continue
        match[0].properties.update(_block_properties(block, "roboarch."))


def _layer(imp: _Importer, layer: s.Layer, rac: s.RacFile) -> None:
    draft = imp.draft
    comp = CompDraft(
        name=draft.unique(layer.name, "layer"),
        loc=layer.loc,
        origin=f"roboarch layer {rac.system}::{layer.name}",
        role="layer",
        doc=f"A RoboArch {layer.layer_type or 'layer'}.",
    )
    uses = (*layer.uses, *layer.provides, *layer.requires)
    comp.events = imp.events((), uses, rac, f"{rac.system}::{layer.name}")
    draft.add_component(comp)
    imp.by_design_name.setdefault(layer.name, comp)
    for values, output in ((layer.inputs, False), (layer.outputs, True)):
        for v in values:
            ref = EventRef(s.Event(v.name, v.type, v.loc), f"{rac.system}::{layer.name}", rac)
            comp.events[v.name] = ref
            port = draft.port(comp, v.name, sends=output, takes=not output, at=v.loc)
            port.origin = f"roboarch {'output' if output else 'input'} {layer.name}.{v.name}"
            port.type = imp.event_type(ref)
            if v.type is not None:
                draft.where(("components", comp.name, "ports", v.name, "type"), v.type.loc)
    comp.properties = {"roboarch.layer": layer.layer_type or ""}
    if layer.pattern:
        comp.properties["roboarch.pattern"] = layer.pattern
    if uses:
        comp.properties["interfaces"] = "; ".join(f"{u.kind} {u.interface}" for u in uses)
    for p in layer.properties:
        comp.properties[f"roboarch.{p.key}"] = _values(p.values)
    for block in layer.stages:
        stage, role = stage_or_role(block.name)
        if stage is None and role is None:
            comp.properties.update(_block_properties(block, f"roboarch.{block.name}."))
            continue
        draft.add_component(
            CompDraft(
                name=draft.unique(f"{layer.name}.{block.name}", "layer"),
                loc=block.loc,
                origin=f"roboarch stage {rac.system}::{layer.name}.{block.name}",
                stage=stage,
                role=role,
                properties=_block_properties(block, "roboarch."),
            )
        )

"""Import a RoboChart design (``.rct`` files, with its RoboArch ``.rac`` if given) into
RAP's system model.

Mapping (each part's place in the design goes to :attr:`Imported.where`):

- a record or datatype -> a message with its fields (types as
  :mod:`.robochart_scope` says: ``Seq(T)`` -> ``list[T]``, ``real`` -> ``float``, ``nat``
  -> ``int`` with ``ge: 0`` ...); an enumeration -> a message with ``enum`` literals; a
  primitive type (``type X``) -> a message without fields. A name declared in two
  packages is qualified in the model (``Pkg.Name``);
- a state machine referenced by a controller (``sref``/``ref``/``cref``, or inline) -> a
  component (``module`` none: to generate), origin ``robochart stm <qualified name>``; its
  stage from its name (Monitor, Analyse/Analysis, Plan, Legitimate, Execute, also as the
  last ``_`` part: ``Adaptation_Monitor``), Knowledge -> role ``knowledge``. Its
  interfaces, events, variables, consts, clocks, operations, states and transitions are
  kept as text properties (the model has no fields for behaviour);
- a controller -> an external component with role ``controller``: its own events are the
  boundary its machines talk to the outside through (``connection Adaptation on
  lidarData to stm_ref0 on lidarData``), so they become its ports; its machines are listed
  in its properties. External: RAP never runs it, it is the seam to the platform;
- a robotic platform -> an external component with role ``platform`` (its operations,
  variables and events as properties; ports where connections name its events);
- each connection (of a controller, a module, or RoboArch's ``connections =``) -> a
  connection of the model; each of its ends -> a port of that component named after the
  event (direction: see :mod:`.robochart_model`; kind ``event-data`` for a typed event,
  ``event`` otherwise; ``_async`` kept in the connection's origin);
- a port carries a message, so an event typed by a record or enumeration carries that
  message, and an event typed by anything else (``real``, ``Seq(LidarRange)``) carries a
  *wrapper* message named after the type (``FloatValue``, ``LidarRangeList``) whose one
  field ``value`` has that type - the same wrapper for the same type everywhere, so both
  ends of a connection agree;
- RoboArch (:mod:`.robochart_arch`): a layer that is a controller adds its properties
  to that component (its stage blocks to the machine of that stage); any other layer is a
  component with role ``layer`` whose inputs and outputs are ports; datatypes, interfaces
  and the platform it repeats from the RoboChart files are one part of the model, with a
  note; a connection a module already makes is noted, not repeated.

Diagnostics the design alone gives: a reference that resolves to nothing (a machine,
controller, platform or interface), a connection end that names no machine or no event,
an import of a package none of the files declares (RoboChart's own library packages get a
note), a name used without its import (a warning). Notes: functions, package-level
constants, unused interfaces, operations and anything else read that has no place in the
model. RoboChart has no compute nodes, so the plan has none; ``plan_findings`` says so.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

from rap_schemas.model import SCALARS, parse_type
from rap_schemas.plan import FieldSpec, MessageSpec

from ..robochart import parse_robochart_files
from ..robochart import syntax as s
from . import Imported
from .aadl_il_names import clean_name, stage_or_role
from .robochart_arch import import_roboarch
from .robochart_model import CompDraft, EventRef, ModelDraft, behaviour_properties
from .robochart_notes import check_imports, leftovers, params, unused_interfaces
from .robochart_scope import FieldType, Scope, render_type

__all__ = ["import_robochart"]

File = s.RcFile | s.RacFile
_USES = ("uses", "provides", "requires")


def import_robochart(paths: Sequence[Path]) -> Imported:
    """Import the ``.rct``/``.rac`` files (or folders of them) in ``paths`` (see the module
    docstring). Never raises; ``readable`` is False when no file could be parsed."""
    files, diagnostics = parse_robochart_files(paths)
    sources = sorted({f.loc.file for f in files} | {d.file for d in diagnostics})
    out = Imported(None, diagnostics=list(diagnostics), sources=sources)
    if not files:
        out.readable = False
        return out
    _Importer(files, out).run()
    return out


def _uses(x: Any) -> tuple[s.InterfaceUse, ...]:
    return tuple(u for kind in _USES for u in getattr(x, kind))


class _Importer:
    """The parsed files -> ``out.plan`` (see the module docstring)."""

    def __init__(self, files: list[File], out: Imported) -> None:
        self.files = files
        self.rct = [f for f in files if isinstance(f, s.RcFile)]
        self.rac = [f for f in files if isinstance(f, s.RacFile)]
        self.out = out
        self.scope = Scope(files)
        self.scope.product_message = self._product_message
        self.draft = ModelDraft(out)
        self.used_interfaces: set[s.Interface] = set()
        self.instanced: set[s.StateMachine] = set()
        self.controllers: dict[s.Controller, CompDraft] = {}
        self.platforms: dict[s.RoboticPlatform, CompDraft] = {}
        self.machines_of: dict[str, list[CompDraft]] = {}
        self.by_design_name: dict[str, CompDraft] = {}

    def run(self) -> None:
        check_imports(self)
        self._messages()
        for file in self.rct:
            for decl in file.declarations:
                if isinstance(decl, s.Controller):
                    self.controller(decl, file, self.scope.qname(decl, file))
        for file in self.rct:
            for decl in file.declarations:
                if isinstance(decl, s.Module):
                    self._module(decl, file, self.scope.qname(decl, file))
        for file in self.rct:
            leftovers(self, file)
        for rac in self.rac:
            import_roboarch(self, rac)
        unused_interfaces(self)
        self.out.diagnostics += self.scope.diagnostics
        self.out.plan = self.draft.freeze(self._system_name(), "")
        self.out.where.setdefault(("system",), self.files[0].loc)
        self.out.where.setdefault((), self.files[0].loc)

    # ---- messages

    def _messages(self) -> None:
        """Name every record, enumeration and primitive type first (fields refer to
        each other), then build them. RoboArch's repeat the RoboChart ones of the same
        name (see :mod:`.robochart_arch`)."""
        kinds = (s.Record, s.Enumeration, s.PrimitiveType)
        decls = [(d, f) for f in self.rct for d in f.declarations if isinstance(d, kinds)]
        count: dict[str, int] = {}
        for d, _ in decls:
            count[d.name] = count.get(d.name, 0) + 1
        for d, f in decls:
            qname = self.scope.qname(d, f)
            self.scope.message_of[d] = (
                d.name if count[d.name] == 1 else clean_name(qname.replace("::", "."))
            )
        for d, f in decls:
            self.add_message(d, f, f"robochart {d.kind if isinstance(d, s.Record) else 'type'}")

    def add_message(self, decl: Any, file: File, what: str) -> None:
        name = self.scope.message_of[decl]
        origin = f"{what} {self.scope.qname(decl, file)}"
        if isinstance(decl, s.Enumeration):
            spec = MessageSpec(enum=[lit.name for lit in decl.literals], origin=origin)
            for i, lit in enumerate(decl.literals):
                self.draft.where(("messages", name, "enum", i), lit.loc)
        elif isinstance(decl, s.Record):
            spec = MessageSpec(fields=self.fields(decl, file, name), origin=origin)
        else:
            spec = MessageSpec(
                origin=origin, doc="A RoboChart primitive type: the design gives it no structure."
            )
        self.draft.add_message(name, spec, decl.loc)

    def fields(self, decl: s.Record, file: File, message: str) -> dict[str, FieldSpec]:
        fields: dict[str, FieldSpec] = {}
        for fd in decl.fields:
            ft = self.scope.field_type(fd.type, file)
            fields[fd.name] = FieldSpec(type=ft.type, ge=ft.ge, doc=ft.doc)
            self.draft.where(("messages", message, "fields", fd.name), fd.loc)
            self.draft.where(("messages", message, "fields", fd.name, "type"), fd.type.loc)
        return fields

    def _product_message(self, items: tuple[FieldType, ...], loc: s.Loc) -> str:
        name = clean_name("Tuple_" + "_".join(_mangle(i.type) for i in items))
        if name not in self.draft.messages:
            fields = {
                f"item{n}": FieldSpec(type=i.type, ge=i.ge, doc=i.doc)
                for n, i in enumerate(items, 1)
            }
            doc = "A RoboChart product type (A * B ...): its items in order."
            self.draft.add_message(
                name, MessageSpec(fields=fields, origin="robochart product type", doc=doc), loc
            )
        return name

    def event_type(self, ref: EventRef) -> str | None:
        """The message a port for this event carries (see the module docstring)."""
        t = ref.event.type
        if t is None:
            return None
        ft = self.scope.field_type(t, ref.file)
        if ft.type in self.draft.messages:
            return ft.type
        base = _mangle(ft.type)
        name = clean_name(base if ft.type.startswith("list[") else base + "Value")
        wrapper = MessageSpec(
            fields={"value": FieldSpec(type=ft.type, ge=ft.ge, doc=ft.doc)},
            origin=f"robochart type {render_type(t)}",
            doc=f"The RoboChart type {render_type(t)} as a message (a port carries a "
            "message): its one field 'value'.",
        )
        while name in self.draft.messages and self.draft.messages[name] != wrapper:
            name += "Event"
        if name not in self.draft.messages:
            self.draft.add_message(name, wrapper, t.loc)
            self.draft.where(("messages", name, "fields", "value"), t.loc)
        return name

    # ---- components

    def events(
        self, own: tuple[s.Event, ...], uses: tuple[s.InterfaceUse, ...], file: File, owner: str
    ) -> dict[str, EventRef]:
        """The events a component may name: its own, then those of its interfaces."""
        events = {e.name: EventRef(e, owner, file) for e in own}
        for use in uses:
            found = self.scope.lookup(use.interface, file, (s.Interface,), use.loc)
            if found is None:
                self.draft.report(
                    use.loc,
                    "error",
                    f"{use.kind} {use.interface}: the design declares no interface "
                    f"{use.interface!r} - give the file that declares it, or fix the name",
                )
                continue
            iface, ifile = found
            self.used_interfaces.add(iface)
            for e in iface.events:
                events.setdefault(e.name, EventRef(e, self.scope.qname(iface, ifile), ifile))
        return events

    def machine(self, stm: s.StateMachine, file: File, qname: str, qualifier: str) -> CompDraft:
        stage, role = stage_or_role(stm.name)
        comp = CompDraft(
            name=self.draft.unique(clean_name(stm.name), qualifier),
            loc=stm.loc,
            origin=f"robochart stm {qname}",
            stage=stage,
            role=role,
        )
        comp.events = self.events(stm.events, _uses(stm), file, qname)
        ops = tuple(f"{o.name} = {o.target}" if o.target else o.name for o in stm.operations)
        comp.properties = behaviour_properties(
            uses=_uses(stm),
            variables=stm.variables,
            events=comp.events,
            clocks=stm.clocks,
            operations=ops,
            nodes=stm.nodes,
            transitions=stm.transitions,
        )
        self.instanced.add(stm)
        return self.draft.add_component(comp)

    def controller(self, ctrl: s.Controller, file: File, qname: str) -> CompDraft:
        comp = CompDraft(
            name=self.draft.unique(clean_name(ctrl.name), "controller"),
            loc=ctrl.loc,
            origin=f"robochart controller {qname}",
            role="controller",
            external=True,
            doc="A RoboChart controller: its ports are the events its machines exchange "
            "with the outside.",
        )
        comp.events = self.events(ctrl.events, _uses(ctrl), file, qname)
        self.draft.add_component(comp)
        self.controllers[ctrl] = comp
        self.by_design_name.setdefault(ctrl.name, comp)
        nodes = {ctrl.name: comp}
        listed: list[str] = []
        machines = self.machines_of.setdefault(comp.name, [])
        for ref in ctrl.machines:
            if ref.definition is not None:
                stm, sfile, sq = ref.definition, file, f"{qname}::{ref.definition.name}"
            else:
                target = ref.target or ref.name
                found = self.scope.lookup(target, file, (s.StateMachine,), ref.loc)
                if found is None:
                    self.draft.report(
                        ref.loc,
                        "error",
                        f"{ref.kind} {ref.name} = {target}: the design declares no state "
                        f"machine {target!r} - give the file that declares it, or fix the name",
                    )
                    continue
                stm, sfile = found
                sq = self.scope.qname(stm, sfile)
            mc = self.machine(stm, sfile, sq, comp.name)
            machines.append(mc)
            nodes[ref.name] = mc
            listed.append(f"{ref.name} = {mc.name}")
        ops = tuple(f"{o.name} = {o.target}" if o.target else o.name for o in ctrl.operations)
        comp.properties = behaviour_properties(
            uses=_uses(ctrl),
            variables=ctrl.variables,
            events=comp.events,
            clocks=ctrl.clocks,
            operations=ops,
        )
        if listed:
            comp.properties["machines"] = ", ".join(listed)
        for conn in ctrl.connections:
            self.connection(conn, nodes, f"controller {ctrl.name}")
        return comp

    def platform(self, plat: s.RoboticPlatform, file: File, qname: str) -> CompDraft:
        known = self.platforms.get(plat)
        if known is not None:
            return known
        comp = CompDraft(
            name=self.draft.unique(clean_name(plat.name), "platform"),
            loc=plat.loc,
            origin=f"robochart platform {qname}",
            role="platform",
            external=True,
            doc="A RoboChart robotic platform: the robot the controllers drive.",
        )
        comp.events = self.events(plat.events, _uses(plat), file, qname)
        ops = [o for u in _uses(plat) for o in self._interface_ops(u, file)]
        ops += [f"{o.name}({params(o.params)})" for o in plat.operations]
        comp.properties = behaviour_properties(
            uses=_uses(plat),
            variables=plat.variables,
            events=comp.events,
            clocks=plat.clocks,
            operations=tuple(ops),
        )
        self.platforms[plat] = comp
        self.by_design_name.setdefault(plat.name, comp)
        return self.draft.add_component(comp)

    def _interface_ops(self, use: s.InterfaceUse, file: File) -> list[str]:
        found = self.scope.lookup(use.interface, file, (s.Interface,), use.loc)
        if found is None:
            return []
        return [f"{o.name}({params(o.params)})" for o in found[0].operations]

    def _module(self, mod: s.Module, file: File, qname: str) -> None:
        nodes: dict[str, CompDraft] = {}
        pref = mod.platform
        if pref is not None:
            plat: tuple[s.RoboticPlatform, File] | None
            if pref.definition is not None:
                plat = pref.definition, file
                pq = f"{qname}::{pref.definition.name}"
            else:
                plat = self.scope.lookup(
                    pref.target or pref.name, file, (s.RoboticPlatform,), pref.loc
                )
                pq = self.scope.qname(plat[0], plat[1]) if plat else ""
            if plat is None:
                self.draft.report(
                    pref.loc,
                    "error",
                    f"module {mod.name}: the design declares no robotic platform "
                    f"{pref.target!r} - give the file that declares it, or fix the name",
                )
            else:
                nodes[pref.name] = nodes[plat[0].name] = self.platform(plat[0], plat[1], pq)
        for cref in mod.controllers:
            if cref.definition is not None:
                comp = self.controller(cref.definition, file, f"{qname}::{cref.definition.name}")
            else:
                found = self.scope.lookup(cref.target or cref.name, file, (s.Controller,), cref.loc)
                if found is None or found[0] not in self.controllers:
                    self.draft.report(
                        cref.loc,
                        "error",
                        f"cref {cref.name} = {cref.target}: the design declares no controller "
                        f"{cref.target!r} - give the file that declares it, or fix the name",
                    )
                    continue
                comp = self.controllers[found[0]]
            nodes[cref.name] = comp
        for conn in mod.connections:
            self.connection(conn, nodes, f"module {mod.name}")

    def connection(
        self,
        conn: s.Connection,
        nodes: dict[str, CompDraft],
        where: str,
        *,
        repeat_ok: bool = False,
    ) -> None:
        """One connection between the parts ``nodes`` names (see the module docstring)."""
        ends: list[tuple[CompDraft, str]] = []
        for node, event in ((conn.from_node, conn.from_event), (conn.to_node, conn.to_event)):
            comp = nodes.get(node)
            if comp is None:
                self.draft.report(
                    conn.loc,
                    "error",
                    f"connection {conn.from_node} on {conn.from_event} to {conn.to_node} on "
                    f"{conn.to_event}: {node!r} is none of the parts of {where} - use one of "
                    f"{', '.join(nodes) or '(none)'}; the connection is left out",
                )
                return
            if event not in comp.events:
                self.draft.report(
                    conn.loc,
                    "error",
                    f"connection end {node} on {event}: {comp.name} has no event {event!r} - "
                    f"its events are {', '.join(comp.events) or '(none)'}; the port is made "
                    "without a type",
                )
            ends.append((comp, event))
        (a, e), (b, f) = ends
        if repeat_ok:
            first = self.draft.find_link((a.name, e, b.name, f))
            if first is not None:
                self.draft.report(
                    conn.loc,
                    "note",
                    f"connection {conn.from_node} on {e} to {conn.to_node} on {f} repeats the "
                    f"one at {first} - one connection in the model",
                )
                return
        flags = " (_async)" if conn.asynchronous else ""
        flags += " (_bidirec)" if conn.bidirectional else ""
        origin = (
            f"robochart {where}: connection {conn.from_node} on {e} to {conn.to_node} on {f}{flags}"
        )
        ports = self.draft.connect(
            (a, e), (b, f), bidirectional=conn.bidirectional, origin=origin, loc=conn.loc
        )
        for (comp, event), port in zip(ends, ports, strict=True):
            ref = comp.events.get(event)
            if ref is not None and port.origin == "":
                port.origin = f"robochart event {ref.owner}.{event}"
                port.type = self.event_type(ref)
                if ref.event.type is not None:
                    self.draft.where(
                        ("components", comp.name, "ports", event, "type"), ref.event.type.loc
                    )

    def _system_name(self) -> str:
        modules = [d.name for f in self.rct for d in f.declarations if isinstance(d, s.Module)]
        controllers = [c.name for c in self.controllers]
        for names in ([r.system for r in self.rac], modules, controllers):
            if len(names) == 1:
                return clean_name(names[0])
        packages = [f.package for f in self.rct if f.package]
        return clean_name(packages[0] if packages else Path(self.files[0].loc.file).stem)


def _mangle(type_text: str) -> str:
    """A field type as part of a message name: ``list[LidarRange]`` ->
    ``LidarRangeList``, ``float`` -> ``Float``."""
    try:
        expr = parse_type(type_text)
    except ValueError:
        return clean_name(type_text)
    suffix = ""
    while expr.item is not None:
        suffix = ("List" if expr.name == "list" else "Option") + suffix
        expr = expr.item
    head = expr.name.replace(".", "_")
    if expr.name in SCALARS:
        head = head.capitalize()
    return head + suffix

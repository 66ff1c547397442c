"""The physical side of an AADL instance tree: compute nodes, bindings, buses and the
knowledge backend.

- Compute nodes are the processor and virtual processor instances, named by their dotted
  instance path from the root (``platform.controller.MissionProcessor1``); by their
  ``RAP::Name``, or in a RAP design their subcomponent's name (:mod:`.aadl_rap`), when
  they have one. One exception keeps a machine's name: a system that carries a network
  address and holds exactly one processor is that machine, and the node takes the
  system's path (``companion`` for ``companion.cpu`` when ``companion`` has
  ``mbed::IP_Address``).
- The address is the nearest ``IP_Address``, ``Deployment::location``, ``Address`` or
  ``Host`` string on the processor or a system above it.
- ``Actual_Processor_Binding`` in any implementation on the path (``applies to`` paths and
  references relative to that implementation; on a subcomponent's ``{ }`` block, to the
  one holding it) binds a component, or a system and so all it holds; the outermost
  association wins, as in AADL. A binding to a system that holds exactly one processor
  binds to that processor.
- Buses are the bus and virtual bus instances, named as nodes are; their nodes are the
  processors that reach them through bus access connections, directly or through a
  device bound to them. A bus's kind is its ``RAP::Bus_Kind``, else its type's name
  (``ethernet`` in a RAP design).
- A system with RPIO backend properties (``rpio::Redis_port``, ``Redis_Database``) is the
  knowledge backend: ``knowledge: {backend: redis, url: redis://<address>:<port>/<db>,
  node: <its binding>}``; its other properties go to that node's ``properties``.
"""

from __future__ import annotations

from collections.abc import Mapping
from dataclasses import dataclass, field

import msgspec
from rap_schemas.plan import BusSpec, ComputeNode, KnowledgeSpec, Resources

from ..aadl import syntax as s
from ..aadl.syntax import norm
from ..diagnostics import Diagnostic, Loc
from .aadl_index import Index, diagnostic, find_property
from .aadl_instance import Instance, value_text
from .aadl_rap import rap_number, rap_string, rap_strings, texts
from .aadl_wiring import Flow, Wiring

__all__ = ["Deployment"]

_PROCESSORS = frozenset({"processor", "virtual processor"})
_BUSES = frozenset({"bus", "virtual bus"})
_ADDRESS = ("IP_Address", "Deployment::location", "Address", "Host", "Hostname")
_BACKEND = ("rpio::Redis_port", "rpio::Redis_Database")
_BINDING = "Actual_Processor_Binding"


@dataclass
class Deployment:
    """Compute nodes, bindings, buses and knowledge of the tree under ``root``."""

    index: Index
    root: Instance
    wiring: Wiring
    diagnostics: list[Diagnostic]
    rap: bool = False
    """A RAP design (:mod:`.aadl_rap`): nodes and buses are named by their subcomponent."""
    nodes: dict[str, ComputeNode] = field(default_factory=dict)
    buses: dict[str, BusSpec] = field(default_factory=dict)
    knowledge: KnowledgeSpec = field(default_factory=KnowledgeSpec)
    where: dict[tuple[object, ...], Loc] = field(default_factory=dict)
    node_of: dict[int, str] = field(default_factory=dict)
    bus_of: dict[int, str] = field(default_factory=dict)
    bound: dict[int, Instance] = field(default_factory=dict)

    def __post_init__(self) -> None:
        self._nodes()
        self._bindings()
        self._buses()
        self._knowledge()

    # -- compute nodes

    def _nodes(self) -> None:
        machines: dict[int, Instance] = {}
        for inst in self.root.walk()[1:]:
            if inst.category != "system" or _own_address(inst) is None:
                continue
            procs = [i for i in inst.walk() if i.category in _PROCESSORS]
            if len(procs) == 1 and id(procs[0]) not in machines:
                machines[id(procs[0])] = inst
        for proc in self.root.walk():
            if proc.category not in _PROCESSORS:
                continue
            machine = machines.get(id(proc))
            name = self._name(proc, (machine or proc).dotted, self.nodes)
            own = proc.properties()
            props = texts(own)
            origin = f"aadl {proc.category} {proc.dotted} ({proc.classifier_text})"
            if machine is not None:
                props.update(texts(machine.properties()))
                origin += f" in system {machine.dotted} ({machine.classifier_text})"
            address = _address(proc)
            for key in [k for k in props if _is_address(k)]:
                del props[key]
            memory = rap_number(own, "Memory_MB")
            self.nodes[name] = ComputeNode(
                address=address,
                architecture=rap_string(own, "Architecture"),
                resources=Resources(
                    cpus=rap_number(own, "CPUs"), memory_mb=int(memory) if memory else None
                ),
                listen=rap_strings(own, "Listen") or [],
                connect=rap_strings(own, "Connect") or [],
                origin=origin,
                properties=props,
                doc=rap_string(own, "Doc") or "",
            )
            self.where[("compute_nodes", name)] = (machine or proc).loc
            self.node_of[id(proc)] = name

    def _name(self, inst: Instance, dotted: str, taken: Mapping[str, object]) -> str:
        """A node's or bus's name: its ``RAP::Name``; in a RAP design its subcomponent's
        name when free; else its dotted path (see the module's docstring)."""
        named = rap_string(inst.properties(), "Name")
        if named is not None:
            return named
        if self.rap and inst.name not in taken:
            return inst.name
        return dotted

    # -- bindings

    def _bindings(self) -> None:
        for holder in sorted(self.root.walk(), key=lambda i: i.depth):
            if holder.sub is not None and holder.parent is not None:
                for assoc in holder.sub.properties:
                    if _is_binding(assoc) and not assoc.applies_to:
                        self._bind([holder], assoc, holder.parent)
            impl = holder.impl
            if impl is None:
                continue
            for assoc, _ in self.index.contained(impl):
                if _is_binding(assoc):
                    targets = [t for p in assoc.applies_to for t in holder.resolve(p)]
                    self._bind(targets, assoc, holder)

    def _bind(self, targets: list[Instance], assoc: s.PropertyAssociation, base: Instance) -> None:
        refs = _references(assoc.value)
        if not refs:
            message = (
                f"{assoc.name} must be a reference (reference (path.to.processor)), "
                f"not {value_text(assoc.value)} - write the processor's path"
            )
            self.diagnostics.append(diagnostic(assoc.loc, "error", message))
            return
        processor = self._processor(refs[0], base)
        if processor is None:
            return
        if len(refs) > 1:
            message = (
                f"{assoc.name} lists {len(refs)} processors (any of them may run it): RAP "
                f"maps it to the first, {refs[0].path} - keep one to say which"
            )
            self.diagnostics.append(diagnostic(assoc.loc, "note", message))
        for target in targets:
            self.bound.setdefault(id(target), processor)

    def _processor(self, ref: s.ReferenceValue, base: Instance) -> Instance | None:
        found = base.resolve(ref.path)
        where = base.classifier_text
        if not found:
            parts = ref.path.split(".")
            here, known = base, []
            for part in parts:
                nxt = here.resolve(part)
                if not nxt:
                    break
                known.append(part)
                here = nxt[0]
            names = ", ".join(c.name for c in here.children.values()) or "(none)"
            at = ".".join(known) or where
            message = (
                f"the binding refers to {ref.path}, but {at} has no subcomponent "
                f"{parts[len(known)]} - use one of {names} (the path is relative to {where})"
            )
            self.diagnostics.append(diagnostic(ref.loc, "error", message))
            return None
        target = found[0]
        if target.category in _PROCESSORS:
            return target
        procs = [i for i in target.walk() if i.category in _PROCESSORS]
        if target.category in {"system", "abstract"} and len(procs) == 1:
            return procs[0]
        if target.category in {"system", "abstract"} and procs:
            names = ", ".join(p.dotted for p in procs)
            problem = f"holds {len(procs)} processors ({names})"
            fix = "name one of them"
        else:
            problem = f"is a {target.category} with no processor"
            fix = "bind to a processor"
        message = f"the binding refers to {ref.path}, which {problem} - {fix}"
        self.diagnostics.append(diagnostic(ref.loc, "error", message))
        return None

    def node_for(self, inst: Instance) -> str | None:
        """The compute node that runs ``inst`` (its binding, or an enclosing one's)."""
        here: Instance | None = inst
        while here is not None:
            proc = self.bound.get(id(here))
            if proc is not None:
                return self.node_of.get(id(proc))
            here = here.parent
        return None

    # -- buses

    def _buses(self) -> None:
        for bus in self.root.walk():
            if bus.category not in _BUSES:
                continue
            nodes: list[str] = []
            for inst in self.wiring.accessors(bus):
                node = self.node_of.get(id(inst)) or (
                    self.node_for(inst) if inst.category == "device" else None
                )
                if node is not None and node not in nodes:
                    nodes.append(node)
            kind = bus.classifier.type_name if bus.classifier is not None else "bus"
            if bus.classifier is None and bus.sub is not None and bus.sub.classifier:
                kind = bus.sub.classifier.rpartition("::")[2].partition(".")[0]
            props = bus.properties()
            kind = rap_string(props, "Bus_Kind") or ("ethernet" if self.rap else kind)
            origin = f"aadl {bus.category} {bus.dotted} ({bus.classifier_text})"
            name = self._name(bus, bus.dotted, self.buses)
            doc = rap_string(props, "Doc") or ""
            self.buses[name] = BusSpec(kind=kind, nodes=nodes, origin=origin, doc=doc)
            self.where[("buses", name)] = bus.loc
            self.bus_of[id(bus)] = name

    def bus_for(self, flow: Flow) -> str | None:
        """The bus a flattened connection is bound to (its first bound hop's)."""
        for hop in flow.hops:
            found = self.wiring.bus_binding(hop)
            if found is None:
                continue
            assoc, base = found
            refs = _references(assoc.value)
            targets = base.resolve(refs[0].path) if refs else []
            if targets and targets[0].category in _BUSES:
                return self.bus_of.get(id(targets[0]))
            message = (
                f"{assoc.name} of connection {hop.conn.name or hop.conn.source} must refer "
                f"to a bus of {base.classifier_text} - use one of "
                f"{', '.join(self.buses) or '(none)'}"
            )
            self.diagnostics.append(diagnostic(assoc.loc, "error", message))
            return None
        return None

    # -- knowledge

    def _knowledge(self) -> None:
        for inst in self.root.walk():
            props = inst.properties()
            port = find_property(props, "rpio::Redis_port")
            if find_property(props, *_BACKEND) is None:
                continue
            node = self.node_for(inst)
            db = find_property(props, "rpio::Redis_Database")
            host = (self.nodes[node].address if node is not None else None) or "localhost"
            url = f"redis://{host}:{_int(port, 6379)}/{_int(db, 0)}"
            self.knowledge = KnowledgeSpec(backend="redis", node=node, url=url)
            self.where[("knowledge",)] = inst.loc
            if node is not None:
                spec = self.nodes[node]
                extra = {
                    f"{inst.dotted}.{a.name}": value_text(a.value)
                    for a in props
                    if not _is_binding(a)
                }
                merged = {**spec.properties, **extra}
                self.nodes[node] = msgspec.structs.replace(
                    spec,
                    properties=merged,
                    doc=f"runs the knowledge backend {inst.dotted} ({inst.classifier_text})",
                )
            return


def _int(assoc: s.PropertyAssociation | None, default: int) -> int:
    if assoc is not None and isinstance(assoc.value, s.IntValue):
        return assoc.value.value
    return default


def _is_binding(assoc: s.PropertyAssociation) -> bool:
    return norm(assoc.simple_name) == norm(_BINDING)


def _references(value: s.PropertyValue) -> list[s.ReferenceValue]:
    if isinstance(value, s.ReferenceValue):
        return [value]
    if isinstance(value, s.ListValue):
        return [v for v in value.items if isinstance(v, s.ReferenceValue)]
    return []


def _is_address(name: str) -> bool:
    simple = norm(name.rpartition("::")[2])
    return any(simple == norm(a.rpartition("::")[2]) for a in _ADDRESS)


def _own_address(inst: Instance) -> str | None:
    found = find_property(inst.properties(), *_ADDRESS)
    if found is not None and isinstance(found.value, s.StringValue):
        return found.value.value
    return None


def _address(inst: Instance) -> str | None:
    here: Instance | None = inst
    while here is not None:
        found = _own_address(here)
        if found is not None:
            return found
        here = here.parent
    return None

"""``rap export aadl``: a RAP model written as AADL v2 that ``rap import aadl`` reads
back to the same model.

Five files, one package each (``S`` is the system's identifier):

- ``RAP.aadl``: the ``RAP`` property set, for what AADL has no property of (a
  component's MAPLE-K stage, its Node module, knowledge keys, topics, RAP's own wire
  types, the knowledge backend);
- ``S_messages.aadl`` (:mod:`.aadl_types`): the messages as data types with the
  Data_Model annex's properties
  (a message is a ``Struct`` data implementation whose subcomponents are its fields, an
  enumeration an ``Enum`` with ``Enumerators``, a list an ``Array`` with ``Base_Type``
  and, for a fixed length, ``Dimension``);
- ``S_logical.aadl``: each component a process (ports as features, threads as thread
  subcomponents in their modes, modes and mode transitions), and the system
  ``Software`` holding them all with the model's connections;
- ``S_physical.aadl``: each compute node a processor, each bus a bus, in the system
  ``Platform`` with the bus access connections;
- ``S.aadl``: the root system ``S.impl`` (software and platform), the bindings
  (``Actual_Processor_Binding``, ``Actual_Connection_Binding``) and where knowledge,
  trust and the fabric are.

What AADL cannot carry is said with a ``RAP::`` property. Docs lose their line breaks.
The root says ``RAP::Infer => false``: the importer infers nothing (no stage from a
name, no component dispatch from its threads) where the model has none.
"""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

from rap_schemas import DeploymentPlan
from rap_schemas.plan import ComponentSpec, ComputeNode, PortSpec

from .aadl_names import Names, aadl_string, common, ident, props_block, real, strings
from .aadl_types import Types, messages_section

__all__ = ["PROPERTY_SET", "export_aadl", "write_aadl"]

PROPERTY_SET = """\
-- RAP's properties: what a RAP system model says that AADL has no property for.
-- Written by `rap export aadl`; `rap import aadl` reads them back.
property set RAP is
  Name: aadlstring applies to (all);
  Doc: aadlstring applies to (all);
  Stage: enumeration (monitor, analyse, plan, legitimate, execute) applies to (process);
  Role: aadlstring applies to (process, device);
  Module: aadlstring applies to (process);
  External: aadlboolean applies to (process, device);
  Run: list of aadlstring applies to (process, device);
  Config: aadlstring applies to (process);
  Config_Type: aadlstring applies to (process);
  Mode_Transitions: aadlstring applies to (process);
  Reads: list of aadlstring applies to (process);
  Writes: list of aadlstring applies to (process);
  Models: list of aadlstring applies to (process);
  Dispatch: enumeration (periodic, sporadic) applies to (process);
  Rate_Hz: aadlreal applies to (process, thread);
  Topic: aadlstring applies to (port);
  Wire_Type: aadlstring applies to (data);
  Field_Type: aadlstring applies to (data, port);
  Constraints: aadlstring applies to (data);
  Address: aadlstring applies to (processor);
  Architecture: aadlstring applies to (processor);
  CPUs: aadlreal applies to (processor);
  Memory_MB: aadlinteger applies to (processor);
  Listen: list of aadlstring applies to (processor);
  Connect: list of aadlstring applies to (processor);
  Bus_Kind: aadlstring applies to (bus);
  Design_Properties: list of aadlstring applies to (all);
  Knowledge_Backend: aadlstring applies to (system);
  Knowledge_Node: aadlstring applies to (system);
  Knowledge_Path: aadlstring applies to (system);
  Knowledge_URL: aadlstring applies to (system);
  Trust_Node: aadlstring applies to (system);
  Trust_Specs: list of aadlstring applies to (system);
  Fabric_Mode: enumeration (peer, client, router) applies to (system);
  Fabric_Routers: list of aadlstring applies to (system);
  Infer: aadlboolean applies to (system);
end RAP;
"""

_KINDS = {"event": "event port", "data": "data port", "event-data": "event data port"}
_DIRS = {"in": "in", "out": "out", "in-out": "in out"}


def _port(pid: str, pname: str, port: PortSpec, types: Types) -> str:
    kind = _KINDS[port.kind]
    classifier = ""
    if port.type is not None:
        if port.type.startswith("rap."):
            classifier = " " + types.wire(port.type)
        else:
            classifier = " " + f"{types.pkg}::{types.names(port.type)}"
    if port.kind == "event":
        classifier = ""  # an event port carries no data in AADL; kept as RAP::Field_Type
    extra = common(pname, pid, port.doc, port.properties)
    if port.topic is not None:
        extra.append(f"RAP::Topic => {aadl_string(port.topic)}")
    if port.kind == "event" and port.type is not None:
        extra.append(f"RAP::Field_Type => {aadl_string(port.type)}")
    block = " {" + " ".join(f"{p};" for p in extra) + "}" if extra else ""
    return f"    {pid}: {_DIRS[port.direction]} {kind}{classifier}{block};"


def _process(name: str, pid: str, comp: ComponentSpec, types: Types) -> Iterator[str]:
    ports = Names(("RAP",))
    features = [_port(ports(p), p, spec, types) for p, spec in comp.ports.items()]
    props = common(name, pid, comp.doc, comp.properties)
    if comp.stage is not None:
        props.append(f"RAP::Stage => {comp.stage.value}")
    for attr, prop in (("role", "Role"), ("module", "Module"), ("config_type", "Config_Type")):
        value = getattr(comp, attr)
        if value is not None:
            props.append(f"RAP::{prop} => {aadl_string(value)}")
    if comp.external:
        props.append("RAP::External => true")
    if comp.run:
        props.append(f"RAP::Run => {strings(comp.run)}")
    if comp.config:
        props.append(f"RAP::Config => {aadl_string(json.dumps(comp.config, sort_keys=True))}")
    if comp.reads:
        props.append(f"RAP::Reads => {strings(comp.reads)}")
    if comp.writes:
        props.append(f"RAP::Writes => {strings(comp.writes)}")
    if comp.models:  # "name:read", "name:write"
        models = [f"{name}:{access}" for name, access in comp.models.items()]
        props.append(f"RAP::Models => {strings(models)}")
    if any(not tr.triggers for tr in comp.mode_transitions):
        # AADL cannot write a transition without a trigger: all of them, in order, as JSON
        moves = [[tr.from_, tr.to, tr.triggers] for tr in comp.mode_transitions]
        props.append(f"RAP::Mode_Transitions => {aadl_string(json.dumps(moves))}")
    if comp.dispatch is not None:
        props.append(f"RAP::Dispatch => {comp.dispatch.kind}")
        if comp.dispatch.rate_hz is not None:
            props.append(f"RAP::Rate_Hz => {real(comp.dispatch.rate_hz)}")
    yield f"  process {pid}"
    if features:
        yield "  features"
        yield from features
    yield from props_block(props, "  ")
    yield f"  end {pid};"
    yield ""
    yield f"  process implementation {pid}.impl"
    modes = Names()
    threads = Names()
    if comp.threads:
        yield "  subcomponents"
        for tname, thread in comp.threads.items():
            tid = threads(tname)
            tprops = common(tname, tid, thread.doc, thread.properties)
            if thread.dispatch is not None:
                tprops.append(f"Dispatch_Protocol => {thread.dispatch.kind.capitalize()}")
                if thread.dispatch.rate_hz is not None:
                    tprops.append(f"RAP::Rate_Hz => {real(thread.dispatch.rate_hz)}")
            block = " {" + " ".join(f"{p};" for p in tprops) + "}" if tprops else ""
            in_modes = (
                " in modes (" + ", ".join(modes(m) for m in thread.in_modes) + ")"
                if thread.in_modes
                else ""
            )
            yield f"    {tid}: thread Worker{block}{in_modes};"
    if comp.modes:
        yield "  modes"
        for i, mode in enumerate(comp.modes):
            named = f" {{RAP::Name => {aadl_string(mode)};}}" if modes(mode) != mode else ""
            yield f"    {modes(mode)}: {'initial ' if i == 0 else ''}mode{named};"
        for tr in comp.mode_transitions:
            if not tr.triggers:
                continue  # in RAP::Mode_Transitions
            trig = ", ".join(ports(t) for t in tr.triggers)
            yield f"    {modes(tr.from_)} -[{trig}]-> {modes(tr.to)};"
    yield f"  end {pid}.impl;"
    yield ""


def _nodeprops_block(name: str, nid: str, node: ComputeNode) -> list[str]:
    props = common(name, nid, node.doc, node.properties)
    for attr, prop in (("address", "Address"), ("architecture", "Architecture")):
        value = getattr(node, attr)
        if value is not None:
            props.append(f"RAP::{prop} => {aadl_string(value)}")
    if node.resources.cpus is not None:
        props.append(f"RAP::CPUs => {real(node.resources.cpus)}")
    if node.resources.memory_mb is not None:
        props.append(f"RAP::Memory_MB => {node.resources.memory_mb}")
    if node.listen:
        props.append(f"RAP::Listen => {strings(node.listen)}")
    if node.connect:
        props.append(f"RAP::Connect => {strings(node.connect)}")
    return props


@dataclass
class _Exported:
    files: dict[str, str]
    """File name -> AADL text."""
    root: str
    """The root system implementation, for ``rap import aadl --root``."""


def export_aadl(plan: DeploymentPlan) -> _Exported:
    """The AADL files of ``plan`` (see the module's docstring)."""
    s = Names(("RAP", "Base_Types", "Data_Model"))(plan.system)
    pkg = {k: f"{s}_{k.capitalize()}" for k in ("messages", "logical", "physical")}
    types = Types(pkg["messages"])
    messages = messages_section(plan, types)
    comps = Names(("Software", "Worker"))
    logical: list[str] = []
    for name, comp in plan.components.items():
        logical += _process(name, comps(name), comp, types)
    logical += ["  thread Worker", "  end Worker;", ""]
    conns = Names()
    subs = [f"    {comps(n)}: process {comps(n)}.impl;" for n in plan.components]
    lines = []
    for i, c in enumerate(plan.connections):
        cid = conns(c.name or f"c{i + 1}")
        ends = []
        for end in (c.from_, c.to):
            cname, port = _split_end(plan, end)
            if cname is None:
                ends.append(ident(end))
            else:
                ports = Names(("RAP",))
                for p in plan.components[cname].ports:
                    ports(p)
                ends.append(f"{comps(cname)}.{ports(port)}")
        arrow = "<->" if c.bidirectional else "->"
        # an empty RAP::Name: the connection has no name in the model (AADL needs one)
        extra = [f"RAP::Name => {aadl_string(c.name or '')}"] if cid != c.name else []
        block = " {" + " ".join(f"{p};" for p in extra) + "}" if extra else ""
        lines.append(f"    {cid}: port {ends[0]} {arrow} {ends[1]}{block};")
    logical += ["  system Software", "  end Software;", "", "  system implementation Software.impl"]
    if subs:
        logical += ["  subcomponents", *subs]
    if lines:
        logical += ["  connections", *lines]
    logical += ["  end Software.impl;", ""]

    nodes = Names(("Platform", "Link"))
    buses = nodes
    physical: list[str] = []
    access: dict[str, list[str]] = {n: [] for n in plan.compute_nodes}
    for bname, bus in plan.buses.items():
        for n in bus.nodes:
            if n in access:
                access[n].append(bname)
    for name in plan.compute_nodes:
        nid = nodes(name)
        feats = [f"    {buses(b)}_access: requires bus access Link;" for b in access[name]]
        physical += [f"  processor {nid}_cpu"]
        if feats:
            physical += ["  features", *feats]
        physical += [f"  end {nid}_cpu;", ""]
    physical += ["  bus Link", "  end Link;", ""]
    psubs: list[str] = []
    for name, node in plan.compute_nodes.items():
        nid = nodes(name)
        props = _nodeprops_block(name, nid, node)
        block = " {" + " ".join(f"{p};" for p in props) + "}" if props else ""
        psubs.append(f"    {nid}: processor {nid}_cpu{block};")
    pconns: list[str] = []
    for bname, bus in plan.buses.items():
        bid = buses(bname)
        props = common(bname, bid, bus.doc, {})
        if bus.kind != "ethernet":
            props.append(f"RAP::Bus_Kind => {aadl_string(bus.kind)}")
        block = " {" + " ".join(f"{p};" for p in props) + "}" if props else ""
        psubs.append(f"    {bid}: bus Link{block};")
        pconns += [
            f"    bus access {bid} -> {nodes(n)}.{bid}_access;"
            for n in bus.nodes
            if n in plan.compute_nodes
        ]
    physical += [
        "  system Platform",
        "  end Platform;",
        "",
        "  system implementation Platform.impl",
    ]
    if psubs:
        physical += ["  subcomponents", *psubs]
    if pconns:
        physical += ["  connections", *pconns]
    physical += ["  end Platform.impl;", ""]

    root_props = common(plan.system, s, plan.doc, {})
    for name, comp in plan.components.items():
        if comp.node is not None and comp.node in plan.compute_nodes:
            root_props.append(
                f"Actual_Processor_Binding => (reference (platform.{nodes(comp.node)})) "
                f"applies to software.{comps(name)}"
            )
    for i, c in enumerate(plan.connections):
        if c.bus is not None and c.bus in plan.buses:
            cid = conns(c.name or f"c{i + 1}")
            root_props.append(
                f"Actual_Connection_Binding => (reference (platform.{buses(c.bus)})) "
                f"applies to software.{cid}"
            )
    kb = plan.knowledge
    root_props.append(f"RAP::Knowledge_Backend => {aadl_string(kb.backend)}")
    for attr, prop in (("node", "Node"), ("path", "Path"), ("url", "URL")):
        value = getattr(kb, attr)
        if value is not None:
            root_props.append(f"RAP::Knowledge_{prop} => {aadl_string(value)}")
    if plan.trust.node is not None:
        root_props.append(f"RAP::Trust_Node => {aadl_string(plan.trust.node)}")
    if plan.trust.specs:
        root_props.append(f"RAP::Trust_Specs => {strings(plan.trust.specs)}")
    root_props.append(f"RAP::Fabric_Mode => {plan.fabric.mode}")
    # the export says everything: nothing is to be inferred from names or threads
    root_props.append("RAP::Infer => false")
    if plan.fabric.routers:
        root_props.append(f"RAP::Fabric_Routers => {strings(plan.fabric.routers)}")
    root = [
        f"  system {s}",
        f"  end {s};",
        "",
        f"  system implementation {s}.impl",
        "  subcomponents",
        f"    software: system {pkg['logical']}::Software.impl;",
        f"    platform: system {pkg['physical']}::Platform.impl;",
        *props_block(root_props, "  "),
        f"  end {s}.impl;",
    ]
    header = "-- Written by `rap export aadl` from the RAP system model of system {}.\n"
    files = {
        "RAP.aadl": PROPERTY_SET,
        f"{s}_messages.aadl": _package(
            pkg["messages"], ["Base_Types", "Data_Model", "RAP"], messages + types.extra
        ),
        f"{s}_logical.aadl": _package(
            pkg["logical"], [pkg["messages"], "Base_Types", "RAP"], logical
        ),
        f"{s}_physical.aadl": _package(pkg["physical"], ["RAP"], physical),
        f"{s}.aadl": _package(s, [pkg["logical"], pkg["physical"], "RAP"], root),
    }
    head = header.format(plan.system)
    return _Exported({k: v if k == "RAP.aadl" else head + v for k, v in files.items()}, f"{s}.impl")


def _split_end(plan: DeploymentPlan, text: str) -> tuple[str | None, str]:
    at = text.find(".")
    while at != -1:
        comp = plan.components.get(text[:at])
        if comp is not None and text[at + 1 :] in comp.ports:
            return text[:at], text[at + 1 :]
        at = text.find(".", at + 1)
    return None, text


def _package(name: str, withs: list[str], body: list[str]) -> str:
    return "\n".join(
        [f"package {name}", "public", f"  with {', '.join(withs)};", "", *body, f"end {name};", ""]
    )


def write_aadl(plan: DeploymentPlan, directory: Path) -> list[Path]:
    """Write the AADL of ``plan`` into ``directory``; the files written."""
    directory.mkdir(parents=True, exist_ok=True)
    written = []
    for name, text in export_aadl(plan).files.items():
        path = directory / name
        path.write_text(text, encoding="utf-8")
        written.append(path)
    return written

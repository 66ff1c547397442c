"""The AADL importer: an AADL v2 design (one or more files) to RAP's system model.

:func:`import_aadl` parses the files (:func:`rap_cli.aadl.parse_aadl_files`), indexes
their packages and property sets (:mod:`.aadl_index`), picks the root system
implementation, instantiates the tree under it (:mod:`.aadl_instance`), checks and
flattens its connections (:mod:`.aadl_wiring`), and builds the model: compute nodes,
bindings, buses and knowledge (:mod:`.aadl_deploy`), messages (:mod:`.aadl_messages`),
components (:mod:`.aadl_components`) and their connections.

The root is the system implementation that no other implementation contains as a
subcomponent nor extends; ``root=`` picks one by name (``pkg::T.impl`` or ``T.impl``).
With several candidates and no ``root=``, the one with the largest instance tree is
taken and a note names the others. The system name is the root's type name, with any
character a model name cannot hold replaced by ``_``.

Model connections are named after the declared connections they cross, joined with
``/`` in the direction of the flow (``c1/K2``: ``c1`` of the root, then ``K2`` inside
the managing system); unnamed ones are left out of the name, and a connection crossing
only unnamed ones has none.

A design that uses RAP's property set (``rap export aadl`` writes one) is read with it:
see :mod:`.aadl_rap` (names, stages, wire types, knowledge, trust and fabric from
``RAP::`` properties; in such a design every declared connection, in declaration order).
The importer knows that property set itself: a design that says ``with RAP;`` needs no
``RAP.aadl`` among its files (one given among them is used instead).

What the model's own checks find (an unbound component, an input nobody produces, a type
mismatch...) is left to them: ``where`` locates every component, port, thread, mode
transition, message, field, compute node, bus and connection in the design.
"""

from __future__ import annotations

import re
from collections.abc import Sequence
from pathlib import Path

from rap_schemas.plan import ConnectionSpec, DeploymentPlan, FabricSpec, TrustSpec

from ..aadl import parse_aadl_files
from ..aadl import syntax as s
from ..aadl.syntax import norm
from ..diagnostics import Diagnostic, Loc, sort_diagnostics
from . import Imported
from .aadl_components import Components
from .aadl_deploy import Deployment
from .aadl_index import Classifier, Index
from .aadl_instance import build_tree
from .aadl_messages import Messages
from .aadl_rap import (
    builtin_property_sets,
    infers,
    is_rap_design,
    knowledge,
    rap_string,
    trust_and_fabric,
)
from .aadl_units import check_units
from .aadl_wiring import Wiring

__all__ = ["import_aadl"]

_INVALID = re.compile(r"[^A-Za-z0-9_.\-~+:@=%,]")


def import_aadl(paths: Sequence[Path], *, root: str | None = None) -> Imported:
    """Import the AADL design made of the files ``paths``; never raises on a bad design
    (see the module's docstring)."""
    sources = [str(p) for p in paths]
    files, diagnostics = parse_aadl_files(paths)
    files += builtin_property_sets(files)
    diagnostics += [n.diagnostic() for f in files for n in f.notes]
    if any(d.severity == "error" for d in diagnostics):
        return Imported(None, sort_diagnostics(diagnostics), sources=sources, readable=False)
    index = Index(files, diagnostics)  # reports into the same list
    check_units(index)
    if root is None and not _systems(index):
        return _data_only(index, diagnostics, sources)
    chosen = _root(index, root, diagnostics, sources)
    if chosen is None:
        return Imported(None, sort_diagnostics(diagnostics), sources=sources, readable=False)
    tree = build_tree(index, chosen, diagnostics)
    rap = is_rap_design(tree.own)
    wiring = Wiring(index, tree, diagnostics)
    deployment = Deployment(index, tree, wiring, diagnostics, rap=rap)
    messages = Messages(index, diagnostics, rap=rap)
    components = Components(
        index, tree, wiring, deployment, messages, rap=rap, infer=infers(tree.own)
    )
    if rap:
        messages.every_message()
    where: dict[tuple[object, ...], Loc] = {}
    connections = _connections(wiring, components, deployment, where, rap=rap)
    where[()] = chosen.decl.loc
    where.update(deployment.where)
    where.update(messages.where)
    where.update(components.where)
    system = (rap_string(tree.own, "Name") if rap else None) or chosen.type_name
    trust, fabric = trust_and_fabric(tree.own)
    plan = DeploymentPlan(
        system=_INVALID.sub("_", system) or "system",
        compute_nodes=deployment.nodes,
        knowledge=(knowledge(tree.own) if rap else None) or deployment.knowledge,
        components=components.specs,
        messages=dict(sorted(messages.specs.items())),
        connections=connections,
        buses=deployment.buses,
        trust=trust if rap else TrustSpec(),
        fabric=fabric if rap else FabricSpec(),
        doc=rap_string(tree.own, "Doc")
        or ("" if rap else f"imported from AADL {chosen.qualified}"),
    )
    return Imported(plan, sort_diagnostics(_unique(diagnostics)), where, sources)


def _connections(
    wiring: Wiring,
    components: Components,
    deployment: Deployment,
    where: dict[tuple[object, ...], Loc],
    *,
    rap: bool,
) -> list[ConnectionSpec]:
    """The model's connections: the flattened ones between components (see the module's
    docstring; in a RAP design, every declared one in declaration order)."""
    connections: list[ConnectionSpec] = []
    names: set[str] = set()
    flows = wiring.flows(every=rap)
    if rap:
        order = {id(c): i for i, c in enumerate(wiring.declared())}
        flows.sort(key=lambda f: [order.get(id(h.conn), 0) for h in f.hops])
    for flow in flows:
        src = components.name_of.get(id(flow.src))
        dst = components.name_of.get(id(flow.dst))
        if src is None or dst is None:
            continue  # a device without known ports: platform hardware, not a component
        named = [_conn_name(h.conn) for h in flow.hops]
        name = "/".join(n for n in named if n) or None
        if name is not None:
            base, n = name, 2
            while name in names:
                name, n = f"{base}_{n}", n + 1
            names.add(name)
        origin = ", ".join(
            f"{h.conn.name or h.conn.source + ' -> ' + h.conn.dest} of {h.holder.classifier_text}"
            for h in flow.hops
        )
        where[("connections", len(connections))] = flow.hops[0].conn.loc
        src_port = components.port_name(flow.src, flow.src_port)
        dst_port = components.port_name(flow.dst, flow.dst_port)
        connections.append(
            ConnectionSpec(
                from_=f"{src}.{src_port}",
                to=f"{dst}.{dst_port}",
                name=name,
                bus=deployment.bus_for(flow),
                bidirectional=flow.bidirectional,
                origin=f"aadl connection {origin}",
            )
        )
    return connections


def _conn_name(conn: s.Connection) -> str | None:
    """A declared connection's name: its ``RAP::Name`` (empty: none), or as declared."""
    named = rap_string(conn.properties, "Name")
    return conn.name if named is None else named or None


def _systems(index: Index) -> list[Classifier]:
    return [
        Classifier(p, d)
        for p in index.packages.values()
        for d in p.declarations
        if isinstance(d, s.ComponentImpl) and d.category == "system"
    ]


def _data_only(index: Index, diagnostics: list[Diagnostic], sources: list[str]) -> Imported:
    """A design without a system implementation (a library of data types): every data
    classifier becomes what a port of it would carry (a message, an enumeration, or a
    wrapper of an array or scalar), and nothing else is imported."""
    messages = Messages(index, diagnostics)
    first: Loc | None = None
    for package in index.packages.values():
        for decl in package.declarations:
            if decl.category != "data":
                continue
            first = first or decl.loc
            messages.port_type(Classifier(package, decl), decl.loc)
    if first is None:
        message = (
            "the design has no system implementation and no data types to import - "
            "declare a system implementation that holds the processes and processors"
        )
        source = sources[0] if sources else "<aadl>"
        diagnostics.append(Diagnostic(source, 0, 0, "error", message))
        return Imported(None, sort_diagnostics(diagnostics), sources=sources, readable=False)
    message = (
        "the design has no system implementation: only its data types are imported "
        "(as messages) - add a system implementation to import components and nodes"
    )
    diagnostics.append(Diagnostic(first.file, first.line, first.column, "note", message))
    name = next(iter(index.packages.values())).name
    plan = DeploymentPlan(
        system=_INVALID.sub("_", name.replace("::", ".")),
        compute_nodes={},
        messages=dict(sorted(messages.specs.items())),
        doc="imported from AADL data types",
    )
    where = {(): first, **messages.where}
    return Imported(plan, sort_diagnostics(_unique(diagnostics)), where, sources)


def _root(
    index: Index, wanted: str | None, diagnostics: list[Diagnostic], sources: list[str]
) -> Classifier | None:
    systems = _systems(index)
    used: set[tuple[str, str]] = set()
    for c in systems:
        if c.decl.extends is not None:
            found = index.resolve(c.decl.extends, c.package, c.decl.loc)
            if isinstance(found, Classifier):
                used.add(found.key)
        for sub, package in index.subcomponents(c):
            if sub.classifier is not None and sub.category == "system":
                found = index.resolve(sub.classifier, package, sub.loc)
                if isinstance(found, Classifier):
                    used.add(found.key)
    candidates = [c for c in systems if c.key not in used]
    listed = ", ".join(c.qualified for c in candidates) or "(none)"
    where = sources[0] if sources else "<aadl>"
    if wanted is not None:
        key = norm(wanted)
        hits = [c for c in systems if key in (norm(c.qualified), norm(c.decl.name))]
        if len(hits) == 1:
            return hits[0]
        problem = "names no system implementation" if not hits else "is ambiguous"
        message = f"--root {wanted} {problem} of the design - use one of {listed}"
        diagnostics.append(Diagnostic(where, 0, 0, "error", message))
        return None
    if not candidates:
        message = (
            "the design has no system implementation to import - declare a system "
            "implementation that holds the processes and processors"
        )
        diagnostics.append(Diagnostic(where, 0, 0, "error", message))
        return None
    sizes = {c.key: _size(index, c, set()) for c in candidates}
    best = max(candidates, key=lambda c: sizes[c.key])
    if len(candidates) > 1:
        others = ", ".join(c.qualified for c in candidates if c is not best)
        message = (
            f"the design has {len(candidates)} root systems: {best.qualified} (the largest) "
            f"is imported; the others are {others} - pick one with --root"
        )
        loc = best.decl.loc
        diagnostics.append(Diagnostic(loc.file, loc.line, loc.column, "note", message))
    return best


def _size(index: Index, c: Classifier, seen: set[tuple[str, str]]) -> int:
    """How many instances the tree under ``c`` has (for picking the root)."""
    if c.key in seen or len(seen) > 32:
        return 0
    total = 0
    for sub, package in index.subcomponents(c):
        total += 1
        if sub.classifier is None:
            continue
        found = index.resolve(sub.classifier, package, sub.loc)
        if isinstance(found, Classifier):
            total += _size(index, found, seen | {c.key})
    return total


def _unique(diagnostics: list[Diagnostic]) -> list[Diagnostic]:
    return list(dict.fromkeys(diagnostics))

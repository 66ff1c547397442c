"""The connections of an AADL instance tree, checked and flattened.

Every connection of every instantiated implementation is checked: each end must name
a subcomponent the implementation has and a feature that subcomponent (or the
implementation itself) has; otherwise an error at the connection, naming what exists.
Ends in a component whose classifier did not resolve are not checked (its features are
unknown), nor are parameter connections (they link subprogram calls).

Port connections declared in systems (and abstract components) are then flattened into
semantic connections between processes and devices, the components of RAP's model: from
every output (or ``in out``) port of a process or device, across system features, up
and down, to the process or device ports they reach. A connection of a process's own
implementation links it to its threads and is no connection of the model.

A system feature that is connected outside but to nothing inside (the flattened
connection dies there), or whose output nothing inside produces, is a warning at the
feature. Bus access connections give the buses their compute nodes (:meth:`accessors`).
"""

from __future__ import annotations

from collections.abc import Iterator
from dataclasses import dataclass, field

from ..aadl import syntax as s
from ..aadl.syntax import norm
from ..diagnostics import Diagnostic
from .aadl_index import Index, diagnostic, find_property, is_container
from .aadl_instance import Instance

__all__ = ["LEAVES", "Flow", "Hop", "Wiring"]

LEAVES = frozenset({"process", "device"})
"""The categories that become components of the model."""
_PORT_KINDS = frozenset(
    {"port", "event port", "data port", "event data port", "feature", "feature group"}
)
_ACCESS_KINDS = frozenset({"bus access", "virtual bus access"})
_PROCESSORS = frozenset({"processor", "virtual processor"})
_MAX_HOPS = 64

EndKey = tuple[int, str]


@dataclass(frozen=True, eq=False)
class Hop:
    """One declared connection on the way of a flattened one, and where it is declared."""

    conn: s.Connection
    holder: Instance


@dataclass
class Flow:
    """A semantic connection from ``src.src_port`` to ``dst.dst_port``."""

    src: Instance
    src_port: str
    dst: Instance
    dst_port: str
    hops: list[Hop]

    @property
    def bidirectional(self) -> bool:
        return any(h.conn.bidirectional for h in self.hops)


@dataclass
class Wiring:
    """The checked connections of the tree under ``root``."""

    index: Index
    root: Instance
    diagnostics: list[Diagnostic]
    ends: dict[EndKey, tuple[Instance, str | None]] = field(default_factory=dict)
    forward: dict[EndKey, list[tuple[EndKey, Hop]]] = field(default_factory=dict)
    around: dict[EndKey, list[tuple[EndKey, Hop, bool]]] = field(default_factory=dict)
    """Both ends of every port connection: the other end, the hop, and whether this end
    is the hop's source."""
    access: dict[EndKey, list[EndKey]] = field(default_factory=dict)
    hops: list[tuple[EndKey, EndKey, Hop]] = field(default_factory=list)

    def __post_init__(self) -> None:
        for inst in self.root.walk():
            impl = inst.impl
            if impl is None:
                continue
            for conn in self.index.connections(impl):
                self._add(inst, conn)
        self._check_boundaries()

    # -- building

    def _key(self, inst: Instance, feature: str | None) -> EndKey:
        key = (id(inst), norm(feature) if feature is not None else "")
        self.ends.setdefault(key, (inst, feature))
        return key

    def _add(self, holder: Instance, conn: s.Connection) -> None:
        kind = conn.kind
        if kind == "parameter" or "subprogram" in kind:
            return
        sources = self._end(holder, conn, conn.source)
        dests = self._end(holder, conn, conn.dest)
        hop = Hop(conn, holder)
        for a in sources:
            for b in dests:
                ka, kb = self._key(*a), self._key(*b)
                if kind in _ACCESS_KINDS:
                    self.access.setdefault(ka, []).append(kb)
                    self.access.setdefault(kb, []).append(ka)
                    continue
                if kind not in _PORT_KINDS:
                    continue
                self.around.setdefault(ka, []).append((kb, hop, True))
                self.around.setdefault(kb, []).append((ka, hop, False))
                if holder.category in LEAVES or not is_container(holder.category):
                    continue
                self.hops.append((ka, kb, hop))
                self.forward.setdefault(ka, []).append((kb, hop))
                if conn.bidirectional:
                    self.forward.setdefault(kb, []).append((ka, hop))

    def _end(
        self, holder: Instance, conn: s.Connection, path: str
    ) -> list[tuple[Instance, str | None]]:
        """What ``path`` names in ``holder``'s implementation; [] (reported) when it
        names nothing."""
        parts = path.split(".")
        label = conn.name or f"{conn.source} -> {conn.dest}"
        what = f"{holder.classifier_text}"
        if len(parts) == 1:
            key = norm(parts[0])
            if key in holder.features:
                return [(holder, parts[0])]
            if key in holder.children or key in holder.arrays:
                return [(c, None) for c in holder.resolve(parts[0])]
            if key in holder.subnames:
                return []
            message = (
                f"connection {label} names {path}, which {what} has neither as a feature "
                f"nor as a subcomponent - its features are {_names(holder.features)}"
            )
            self.diagnostics.append(diagnostic(conn.loc, "error", message))
            return []
        sub, feat = parts[0], parts[1]
        targets = holder.resolve(sub)
        if not targets:
            if norm(sub) not in holder.subnames:
                subs = ", ".join(holder.subnames.values()) or "(none)"
                message = (
                    f"connection {label} names {path}, but {what} has no subcomponent "
                    f"{sub} - its subcomponents are {subs}"
                )
                self.diagnostics.append(diagnostic(conn.loc, "error", message))
            return []
        out: list[tuple[Instance, str | None]] = []
        for target in targets:
            declared = target.features.get(norm(feat))
            if declared is not None:
                out.append((target, declared.name))
            elif target.opaque:
                out.append((target, feat))
            else:
                message = (
                    f"connection {label} names {path}, but {sub} ({target.category} "
                    f"{target.classifier_text}) has no feature {feat} - its features are "
                    f"{_names(target.features)}"
                )
                self.diagnostics.append(diagnostic(conn.loc, "error", message))
                return []
        return out

    # -- system boundaries

    def _check_boundaries(self) -> None:
        seen: set[tuple[EndKey, str]] = set()
        for ka, kb, hop in self.hops:
            ends = [(kb, "in"), (ka, "out")]
            if hop.conn.bidirectional:
                ends = [(kb, "in"), (ka, "in")]
            for key, way in ends:
                inst, feature = self.ends[key]
                if feature is None or inst is hop.holder or not is_container(inst.category):
                    continue
                if inst.opaque or (key, way) in seen:
                    continue
                seen.add((key, way))
                inside = [
                    (is_source or h.conn.bidirectional)
                    if way == "in"
                    else (not is_source or h.conn.bidirectional)
                    for _, h, is_source in self.around.get(key, [])
                    if h.holder is inst
                ]
                if any(inside):
                    continue
                self._dead_end(inst, feature, hop, way)

    def _dead_end(self, inst: Instance, feature: str, hop: Hop, way: str) -> None:
        declared = inst.features.get(norm(feature))
        loc = declared.loc if declared is not None else inst.loc
        conn = hop.conn
        label = conn.name or f"{conn.source} -> {conn.dest}"
        impl = inst.impl.decl.name if inst.impl is not None else None
        hint = self._candidates(inst, declared, way)
        if impl is None:
            where = f"{inst.classifier_text} has no implementation, so nothing inside it"
        else:
            where = f"nothing inside {impl}"
        if way == "in":
            problem = f"{where} takes it: what arrives there goes nowhere"
            fix = "connect it inside to a port of a subcomponent"
        else:
            problem = f"{where} produces it: the connection starts from nothing"
            fix = "connect a port of a subcomponent to it inside"
        message = (
            f"port {feature} of {inst.dotted} is connected by {label} "
            f"({hop.holder.classifier_text}, line {conn.loc.line}), but {problem} - {fix}"
            + (f" (e.g. {hint})" if hint else "")
        )
        self.diagnostics.append(diagnostic(loc, "warning", message))

    def _candidates(self, inst: Instance, declared: s.Feature | None, way: str) -> str:
        if declared is None:
            return ""
        want = {"in", "in out"} if way == "in" else {"out", "in out"}
        found: list[str] = []
        for leaf in inst.walk()[1:]:
            if leaf.category not in LEAVES:
                continue
            for f in leaf.features.values():
                same = _simple(f.classifier) == _simple(declared.classifier)
                if same and f.kind == declared.kind and f.direction in want:
                    found.append(".".join(leaf.path[len(inst.path) :]) + f".{f.name}")
        return ", ".join(found[:3])

    # -- flattening

    def flows(self, *, every: bool = False) -> list[Flow]:
        """Every semantic connection between processes and devices, in tree order: one
        per pair of ports, or with ``every`` one per path of declared connections (a
        port connected to itself included)."""
        out: list[Flow] = []
        seen: set[tuple[object, ...]] = set()
        for inst in self.root.walk():
            if inst.category not in LEAVES:
                continue
            for feature in inst.features.values():
                if feature.direction is None or "port" not in feature.kind:
                    continue
                start = (id(inst), norm(feature.name))
                if start not in self.forward:
                    continue
                visited = set() if every else {start}
                for end, hops in self._trace(start, [], visited):
                    via = tuple(id(h.conn) for h in hops) if every else ()
                    pair = (start, end, *via)
                    bidirectional = any(h.conn.bidirectional for h in hops)
                    if pair in seen or (bidirectional and (end, start, *via[::-1]) in seen):
                        continue
                    seen.add(pair)
                    dst, dst_port = self.ends[end]
                    assert dst_port is not None
                    out.append(Flow(inst, feature.name, dst, dst_port, hops))
        return out

    def declared(self) -> list[s.Connection]:
        """The declared connections of the tree, in tree and declaration order."""
        return [hop.conn for _, _, hop in self.hops]

    def _trace(
        self, here: EndKey, hops: list[Hop], visited: set[EndKey]
    ) -> Iterator[tuple[EndKey, list[Hop]]]:
        if len(hops) >= _MAX_HOPS:
            return
        for nxt, hop in self.forward.get(here, []):
            if nxt in visited or any(h.conn is hop.conn for h in hops):
                continue  # a flattened connection crosses each declared one once
            inst, feature = self.ends[nxt]
            if feature is None:
                continue
            if inst.category in LEAVES:
                yield nxt, [*hops, hop]
            elif is_container(inst.category):
                yield from self._trace(nxt, [*hops, hop], visited | {nxt})

    def inner_ports(self, system: Instance, feature: str) -> list[tuple[Instance, str]]:
        """The process and device ports inside ``system`` that its ``feature`` is
        connected to (through nested systems)."""
        start = (id(system), norm(feature))
        out: list[tuple[Instance, str]] = []
        todo, seen = [start], {start}
        prefix = system.path
        while todo:
            here = todo.pop()
            for nxt, hop, _ in self.around.get(here, []):
                holder = hop.holder
                if holder.path[: len(prefix)] != prefix or nxt in seen:
                    continue
                if holder.category in LEAVES:
                    continue
                seen.add(nxt)
                inst, name = self.ends[nxt]
                if name is None or inst is system:
                    continue
                if inst.category in LEAVES:
                    out.append((inst, name))
                elif is_container(inst.category):
                    todo.append(nxt)
        return out

    # -- buses

    def accessors(self, bus: Instance) -> list[Instance]:
        """The processors and devices that access ``bus`` through bus access
        connections (a system whose access feature leads nowhere inside: every
        processor in it)."""
        start = self._key(bus, None)
        found: list[Instance] = []
        todo, seen = [start], {start}
        while todo:
            here = todo.pop()
            nexts = self.access.get(here, [])
            for nxt in nexts:
                if nxt in seen:
                    continue
                seen.add(nxt)
                inst, _ = self.ends[nxt]
                if inst.category in _PROCESSORS or inst.category == "device":
                    found.append(inst)
                elif is_container(inst.category):
                    if self.access.get(nxt) and len(self.access[nxt]) > 1:
                        todo.append(nxt)
                    else:
                        found += [i for i in inst.walk() if i.category in _PROCESSORS]
        return list(dict.fromkeys(found))

    def bus_binding(self, hop: Hop) -> tuple[s.PropertyAssociation, Instance] | None:
        """The ``Actual_Connection_Binding`` of a declared connection and the instance
        its reference is relative to: on the connection, or in an implementation
        above it (``applies to`` the connection's path)."""
        found = find_property(list(hop.conn.properties), "Actual_Connection_Binding")
        if found is not None:
            return found, hop.holder
        if hop.conn.name is None:
            return None
        rel = [hop.conn.name]
        result: tuple[s.PropertyAssociation, Instance] | None = None
        here: Instance | None = hop.holder
        while here is not None:
            impl = here.impl
            if impl is not None:
                path = norm(".".join(rel))
                for assoc, _ in self.index.contained(impl):
                    named = any(norm(p) == path for p in assoc.applies_to)
                    if named and norm(assoc.simple_name) == "actual_connection_binding":
                        result = (assoc, here)  # the outermost one wins
            rel.insert(0, here.name)
            here = here.parent
        return result


def _simple(classifier: str | None) -> str | None:
    return norm(classifier).rpartition("::")[2] if classifier is not None else None


def _names(features: dict[str, s.Feature]) -> str:
    return ", ".join(f.name for f in features.values()) or "(none)"

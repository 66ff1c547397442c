"""The system model's cross-checks and its field type language.

:func:`model_findings` checks what a model says beyond what running it needs
(:func:`rap_schemas.plan.plan_findings`): every input has a producer, every output a
consumer (a warning), the types on both ends of a connection agree, every port, message
and field type names something that exists, no two names differ only in case, every
knowledge key read is written somewhere, and no plan reaches an execute stage except
through a legitimate stage, and every bridge carries one direction of a typed port.
``rap check`` reports both kinds with their lines.

Field types (:func:`parse_type`): ``bool``, ``int``, ``int8`` .. ``int64``, ``uint8`` ..
``uint64``, ``float``, ``float32``, ``float64``, ``str``, ``bytes``, a message or
enumeration of the model, ``list[T]``, ``list[T, N]`` (exactly ``N`` items) and
``optional[T]``.
"""

from __future__ import annotations

import re
from collections import defaultdict
from collections.abc import Iterator
from dataclasses import dataclass
from typing import Literal

from .catalog import MESSAGES
from .maplek import Stage
from .plan import ComponentSpec, DeploymentPlan, PortSpec
from .yamlconf import Location

__all__ = [
    "SCALARS",
    "Connection",
    "ModelFinding",
    "TypeExpr",
    "TypeSyntaxError",
    "connections",
    "model_findings",
    "parse_type",
    "wire_types",
]

SCALARS = frozenset(
    {
        "bool",
        "int",
        "int8",
        "int16",
        "int32",
        "int64",
        "uint8",
        "uint16",
        "uint32",
        "uint64",
        "float",
        "float32",
        "float64",
        "str",
        "bytes",
    }
)

Severity = Literal["error", "warning", "note"]


@dataclass(frozen=True, slots=True)
class ModelFinding:
    loc: Location
    severity: Severity
    message: str
    """What is wrong, then `` - `` and how to fix it."""
    key: bool = False
    """``loc`` points at a mapping key rather than its value."""


# -- field types ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class TypeExpr:
    """A parsed field type: ``name`` is a scalar, a message or enumeration, ``list`` or
    ``optional`` (then ``item`` is set; ``length`` for a fixed-length list)."""

    name: str
    item: TypeExpr | None = None
    length: int | None = None

    def __str__(self) -> str:
        if self.name == "list":
            n = f", {self.length}" if self.length is not None else ""
            return f"list[{self.item}{n}]"
        if self.name == "optional":
            return f"optional[{self.item}]"
        return self.name

    def names(self) -> Iterator[str]:
        """The scalar, message and enumeration names it uses."""
        if self.item is not None:
            yield from self.item.names()
        else:
            yield self.name


class TypeSyntaxError(ValueError):
    """A field type that does not parse; the message says what was expected."""


_TOKEN = re.compile(r"\s*(?:([A-Za-z_][A-Za-z0-9_.]*)|(\d+)|([\[\],]))")
MAX_TYPE_DEPTH = 16


def parse_type(text: str) -> TypeExpr:
    """Parse a field type (see the module's docstring)."""
    tokens: list[str] = []
    pos = 0
    text = text.strip()
    while pos < len(text):
        m = _TOKEN.match(text, pos)
        if m is None or m.end() == pos:
            raise TypeSyntaxError(f"unexpected {text[pos:].strip()[:10]!r} at column {pos + 1}")
        tokens.append(m.group(1) or m.group(2) or m.group(3))
        pos = m.end()
    if not tokens:
        raise TypeSyntaxError("empty type")
    expr, rest = _parse(tokens, 0)
    if rest != len(tokens):
        raise TypeSyntaxError(f"unexpected {tokens[rest]!r} after {expr}")
    return expr


def _parse(tokens: list[str], i: int, depth: int = 0) -> tuple[TypeExpr, int]:
    if depth > MAX_TYPE_DEPTH:
        raise TypeSyntaxError(f"types nest at most {MAX_TYPE_DEPTH} levels")
    if i >= len(tokens):
        raise TypeSyntaxError("a type name is missing at the end")
    name = tokens[i]
    if not (name[0].isalpha() or name[0] == "_"):
        raise TypeSyntaxError(f"expected a type name, found {name!r}")
    i += 1
    if name not in ("list", "optional"):
        return TypeExpr(name), i
    if i >= len(tokens) or tokens[i] != "[":
        raise TypeSyntaxError(f"expected '[' after {name}, e.g. {name}[float]")
    item, i = _parse(tokens, i + 1, depth + 1)
    length = None
    if name == "list" and i < len(tokens) and tokens[i] == ",":
        if i + 1 >= len(tokens) or not tokens[i + 1].isdigit():
            raise TypeSyntaxError("expected a length after ',' in list[T, N]")
        length = int(tokens[i + 1])
        i += 2
    if i >= len(tokens) or tokens[i] != "]":
        raise TypeSyntaxError(f"expected ']' to close {name}[")
    return TypeExpr(name, item, length), i + 1


def wire_types() -> frozenset[str]:
    """RAP's own message types a port may name (``rap.LaserScan/1`` ...)."""
    return frozenset(m.TYPE for m in MESSAGES)


# -- connections ---------------------------------------------------------------------


@dataclass(frozen=True, slots=True)
class Connection:
    """A resolved connection: ``source``/``target`` are ``(component, port)``;
    ``index`` is its place in ``connections:`` (None: implied by a shared topic)."""

    source: tuple[str, str]
    target: tuple[str, str]
    index: int | None


def _sends(port: PortSpec) -> bool:
    return port.direction in ("out", "in-out")


def _takes(port: PortSpec) -> bool:
    return port.direction in ("in", "in-out")


def _family(port: PortSpec) -> str:
    return "data" if port.kind == "data" else "event"


def connections(plan: DeploymentPlan) -> list[Connection]:
    """The connections of ``connections:`` whose ends resolve (in order), then those a
    shared topic implies (an output and an input of the same kind family on the same
    topic, in different components)."""
    out: list[Connection] = []
    for i, c in enumerate(plan.connections):
        src, dst = _endpoint(plan, c.from_), _endpoint(plan, c.to)
        if src is not None and dst is not None:
            out.append(Connection(src, dst, i))
    by_topic: dict[tuple[str, str], list[tuple[str, str, PortSpec]]] = defaultdict(list)
    for cname, comp in plan.components.items():
        for pname, port in comp.ports.items():
            if port.topic is not None:
                by_topic[(_family(port), port.topic)].append((cname, pname, port))
    explicit = {(c.source, c.target) for c in out}
    for ends in by_topic.values():
        for sc, sp, sport in ends:
            for tc, tp, tport in ends:
                pair = ((sc, sp), (tc, tp))
                if sc != tc and _sends(sport) and _takes(tport) and pair not in explicit:
                    out.append(Connection(*pair, None))
    return out


def _endpoint(plan: DeploymentPlan, text: str) -> tuple[str, str] | None:
    """``component.port``; names may hold dots themselves (``managing.m.scan``): the
    split is the one whose component and port both exist."""
    at = text.find(".")
    while at != -1:
        comp, port = text[:at], text[at + 1 :]
        spec = plan.components.get(comp)
        if spec is not None and port in spec.ports:
            return comp, port
        at = text.find(".", at + 1)
    return None


# -- the checks ----------------------------------------------------------------------


def model_findings(plan: DeploymentPlan) -> list[ModelFinding]:
    """Every cross-check finding of ``plan`` (see the module's docstring)."""
    found: list[ModelFinding] = []
    found += _type_findings(plan)
    found += _connection_findings(plan)
    found += _case_findings(plan)
    found += _knowledge_findings(plan)
    found += _gate_findings(plan)
    found += _mode_findings(plan)
    found += _bridge_findings(plan)
    return found


def _bridge_findings(plan: DeploymentPlan) -> Iterator[ModelFinding]:
    """A bridge carries one direction of a port that says what it carries."""
    for cname, comp in plan.components.items():
        for pname, port in comp.ports.items():
            spec = port.bridge
            if spec is None:
                continue
            loc = ("components", cname, "ports", pname, "bridge")
            if port.direction == "in-out":
                yield ModelFinding(
                    loc,
                    "error",
                    f"port {cname}.{pname} is in-out, and a bridge carries one direction "
                    "- split it into an 'in' and an 'out' port, each with its bridge",
                    key=True,
                )
            # which way it carries: a port of an external component RAP does not start
            # lives on the protocol (docs/bridges.md)
            outside = comp.external and not comp.run
            incoming = (port.direction == "in") != outside
            if spec.protocol == "redis" and incoming and spec.qos > 0:
                yield ModelFinding(
                    (*loc, "qos"),
                    "error",
                    f"port {cname}.{pname}: Redis pub/sub brings messages in at most once "
                    "(what is published while the bridge reconnects is lost) - write qos: 0, "
                    "or use protocol: redis-stream for at least once",
                )
            if spec.protocol == "mqtt" and not incoming and any(c in spec.address for c in "+#"):
                yield ModelFinding(
                    (*loc, "address"),
                    "error",
                    f"port {cname}.{pname}: its messages are published on one MQTT topic, "
                    f"and {spec.address!r} has a wildcard - name one topic",
                )
            if spec.format != "envelope" and port.type is None:
                yield ModelFinding(
                    (*loc, "format"),
                    "error",
                    f"port {cname}.{pname}: format {spec.format} needs the message the port "
                    "carries - give the port a type, or use format: envelope",
                )


def _mode_findings(plan: DeploymentPlan) -> Iterator[ModelFinding]:
    """Threads and mode transitions name modes the component has."""
    for cname, comp in plan.components.items():
        modes = set(comp.modes)
        listed = ", ".join(comp.modes) or "(none: add them under modes:)"
        for tname, thread in comp.threads.items():
            for i, mode in enumerate(thread.in_modes):
                if mode not in modes:
                    yield ModelFinding(
                        ("components", cname, "threads", tname, "in_modes", i),
                        "error",
                        f"thread {cname}.{tname} exists in mode {mode!r}, which {cname} "
                        f"does not have - use one of {listed}",
                    )
        for i, tr in enumerate(comp.mode_transitions):
            for field, mode in (("from", tr.from_), ("to", tr.to)):
                if mode not in modes:
                    yield ModelFinding(
                        ("components", cname, "mode_transitions", i, field),
                        "error",
                        f"a mode transition of {cname} names mode {mode!r}, which it does "
                        f"not have - use one of {listed}",
                    )
            for j, trig in enumerate(tr.triggers):
                if trig not in comp.ports:
                    yield ModelFinding(
                        ("components", cname, "mode_transitions", i, "triggers", j),
                        "error",
                        f"a mode transition of {cname} is triggered by {trig!r}, which is "
                        f"not one of its ports - use one of {', '.join(comp.ports) or '(none)'}",
                    )


def _known_types(plan: DeploymentPlan) -> set[str]:
    return set(plan.messages) | set(wire_types())


def _type_findings(plan: DeploymentPlan) -> Iterator[ModelFinding]:
    known = _known_types(plan)
    messages = ", ".join(sorted(plan.messages)) or "(none declared)"
    for mname, msg in plan.messages.items():
        if msg.enum is not None and msg.fields:
            yield ModelFinding(
                ("messages", mname),
                "error",
                f"message {mname!r} has both fields and enum - an enumeration has only "
                "'enum: [literals]'; a message only 'fields:'",
                key=True,
            )
        if msg.enum is not None and len(set(msg.enum)) != len(msg.enum):
            dup = sorted({x for x in msg.enum if msg.enum.count(x) > 1})
            yield ModelFinding(
                ("messages", mname, "enum"),
                "error",
                f"enumeration {mname!r} lists {', '.join(dup)} more than once - keep one of each",
            )
        for fname, field in msg.fields.items():
            loc = ("messages", mname, "fields", fname, "type")
            try:
                expr = parse_type(field.type)
            except TypeSyntaxError as exc:
                yield ModelFinding(
                    loc,
                    "error",
                    f"field {mname}.{fname}: type {field.type!r} does not parse: {exc} - "
                    "write a scalar, a message name, list[T], list[T, N] or optional[T]",
                )
                continue
            for name in expr.names():
                if name not in SCALARS and name not in plan.messages:
                    yield ModelFinding(
                        loc,
                        "error",
                        f"field {mname}.{fname}: type {name!r} is neither a scalar nor a "
                        f"message of the model - use one of {', '.join(sorted(SCALARS))} "
                        f"or a message: {messages}",
                    )
    for cname, comp in plan.components.items():
        if comp.config_type is not None and comp.config_type not in plan.messages:
            yield ModelFinding(
                ("components", cname, "config_type"),
                "error",
                f"component {cname!r}: config_type {comp.config_type!r} is not a message "
                f"of the model - declare it under messages: ({messages})",
            )
        for pname, port in comp.ports.items():
            if port.type is not None and port.type not in known:
                options = (
                    f"RAP's own types are: {', '.join(sorted(wire_types()))}"
                    if port.type.startswith("rap.")
                    else f"declare it under messages: or use one of: {messages}"
                )
                yield ModelFinding(
                    ("components", cname, "ports", pname, "type"),
                    "error",
                    f"port {cname}.{pname} carries {port.type!r}, which is not a message - "
                    + options,
                )


def _split(plan: DeploymentPlan, text: str) -> tuple[str, str, str]:
    """``component.port`` split at the dot after the longest component name it starts
    with (names may hold dots), or at the first dot when none matches."""
    best = text.partition(".")
    at = text.find(".")
    while at != -1:
        if text[:at] in plan.components:
            best = (text[:at], ".", text[at + 1 :])
        at = text.find(".", at + 1)
    return best


def _connection_findings(plan: DeploymentPlan) -> Iterator[ModelFinding]:
    names: dict[str, int] = {}
    for i, c in enumerate(plan.connections):
        for field, text, want in (("from", c.from_, _sends), ("to", c.to, _takes)):
            cref, sep, pref = _split(plan, text)
            spec = plan.components.get(cref)
            loc = ("connections", i, field)
            if not sep:
                yield ModelFinding(
                    loc, "error", f"{text!r} is not 'component.port' - name both, with a dot"
                )
            elif spec is None:
                yield ModelFinding(
                    loc,
                    "error",
                    f"connection {c.name or i}: there is no component {cref!r} - use one of "
                    f"{', '.join(plan.components) or '(none)'}",
                )
            elif pref not in spec.ports:
                yield ModelFinding(
                    loc,
                    "error",
                    f"connection {c.name or i}: component {cref!r} has no port {pref!r} - "
                    f"its ports are {', '.join(spec.ports) or '(none)'}",
                )
            elif not want(spec.ports[pref]):
                role = "source" if field == "from" else "destination"
                yield ModelFinding(
                    loc,
                    "error",
                    f"connection {c.name or i}: port {text} is "
                    f"'{spec.ports[pref].direction}', it cannot be the {role} - swap "
                    "from and to, or fix the port's direction",
                )
        if c.bus is not None and c.bus not in plan.buses:
            yield ModelFinding(
                ("connections", i, "bus"),
                "error",
                f"connection {c.name or i} travels over bus {c.bus!r}, which the model "
                f"does not define - use one of {', '.join(plan.buses) or '(none)'}",
            )
        elif c.bus is not None:
            yield from _bus_reach(plan, i, c.bus)
        if c.name is not None:
            if c.name in names:
                yield ModelFinding(
                    ("connections", i, "name"),
                    "error",
                    f"two connections are named {c.name!r} (the other is entry "
                    f"{names[c.name]}) - rename one",
                )
            names.setdefault(c.name, i)
    resolved = connections(plan)
    fed = {c.target for c in resolved}
    used = {c.source for c in resolved}
    for conn in resolved:
        src = plan.components[conn.source[0]].ports[conn.source[1]]
        dst = plan.components[conn.target[0]].ports[conn.target[1]]
        if src.type is not None and dst.type is not None and src.type != dst.type:
            at: Location = (
                ("connections", conn.index)
                if conn.index is not None
                else ("components", conn.target[0], "ports", conn.target[1], "type")
            )
            yield ModelFinding(
                at,
                "error",
                f"{'.'.join(conn.source)} sends {src.type} but {'.'.join(conn.target)} takes "
                f"{dst.type} - make the two ports carry the same message",
            )
    for cname, cspec in plan.components.items():
        for pname, port in cspec.ports.items():
            at = ("components", cname, "ports", pname)
            if port.direction == "in" and (cname, pname) not in fed:
                yield ModelFinding(
                    at,
                    "error",
                    f"input {cname}.{pname} is connected to nothing: no component produces "
                    "it - connect an output to it, or remove the port",
                    key=True,
                )
            elif port.direction == "out" and (cname, pname) not in used and not cspec.external:
                # an external component's (the managed system's) outputs are its own
                # data: operators' tools read them; the loop need not
                yield ModelFinding(
                    at,
                    "warning",
                    f"output {cname}.{pname} is connected to nothing: no component consumes "
                    "it - connect it, or remove the port if nothing will",
                    key=True,
                )


def _bus_reach(plan: DeploymentPlan, index: int, bus: str) -> Iterator[ModelFinding]:
    """Connection ``index`` bound to ``bus``: a warning for each end whose component runs
    on a compute node the bus does not join (AADL's Actual_Connection_Binding to a bus
    that does not reach the processors the two ends are bound to)."""
    c = plan.connections[index]
    joined = plan.buses[bus].nodes
    for text in dict.fromkeys((c.from_, c.to)):
        spec = plan.components.get(_split(plan, text)[0])
        node = spec.node if spec is not None else None
        if node is None or node not in plan.compute_nodes or node in joined:
            continue
        yield ModelFinding(
            ("connections", index, "bus"),
            "warning",
            f"connection {c.name or index} travels over bus {bus!r}, but {text} runs on "
            f"compute node {node!r}, which the bus does not join (it joins "
            f"{', '.join(joined) or 'no node'}) - bind the connection to a bus that joins "
            f"both ends' nodes, or join {node!r} to {bus!r}",
        )


def _case_findings(plan: DeploymentPlan) -> Iterator[ModelFinding]:
    for section in ("components", "messages", "compute_nodes", "buses"):
        seen: dict[str, str] = {}
        for name in getattr(plan, section):
            other = seen.get(name.lower())
            if other is not None:
                yield ModelFinding(
                    (section, name),
                    "error",
                    f"{section}: {name!r} and {other!r} differ only in case; names are "
                    "compared without case by AADL tools and on some file systems - "
                    "rename one",
                    key=True,
                )
            seen.setdefault(name.lower(), name)


def _knowledge_findings(plan: DeploymentPlan) -> Iterator[ModelFinding]:
    written = {k for c in plan.components.values() for k in c.writes}
    for cname, comp in plan.components.items():
        for i, key in enumerate(comp.reads):
            if key not in written:
                yield ModelFinding(
                    ("components", cname, "reads", i),
                    "error",
                    f"component {cname!r} reads knowledge key {key!r}, which no component "
                    "writes - add it to the writes: of the component that stores it, or "
                    "fix the key",
                )


def _stage(comp: ComponentSpec) -> Stage | None:
    return comp.stage


def _gate_findings(plan: DeploymentPlan) -> Iterator[ModelFinding]:
    """An execute stage must be reached from a plan stage only through a legitimate
    stage, and must take something from a legitimate stage."""
    edges: dict[str, list[tuple[str, Connection]]] = defaultdict(list)
    resolved = connections(plan)
    for c in resolved:
        edges[c.source[0]].append((c.target[0], c))
    comps = plan.components
    if not resolved:
        return  # a plan without a logical architecture: nothing to check
    for cname, comp in comps.items():
        if _stage(comp) is Stage.EXECUTE:
            feeders = {c.source[0] for c in resolved if c.target[0] == cname}
            if not any(_stage(comps[f]) is Stage.LEGITIMATE for f in feeders):
                yield ModelFinding(
                    ("components", cname),
                    "error",
                    f"execute stage {cname!r} takes nothing from a legitimate stage: it "
                    "could act on a plan nobody checked - connect it to a legitimate "
                    "stage's verdict output",
                    key=True,
                )
    for start, comp in comps.items():
        if _stage(comp) is not Stage.PLAN:
            continue
        seen = {start}
        todo = [start]
        while todo:
            here = todo.pop()
            for nxt, c in edges[here]:
                if nxt in seen or _stage(comps[nxt]) is Stage.LEGITIMATE:
                    continue
                seen.add(nxt)
                if _stage(comps[nxt]) is Stage.EXECUTE:
                    loc: Location = (
                        ("connections", c.index)
                        if c.index is not None
                        else ("components", c.target[0], "ports", c.target[1])
                    )
                    yield ModelFinding(
                        loc,
                        "error",
                        f"plan stage {start!r} reaches execute stage {nxt!r} through "
                        f"{'.'.join(c.source)} -> {'.'.join(c.target)} without a "
                        "legitimate stage - route plans through a legitimate stage "
                        "(Legitimate checks a plan before it runs)",
                        key=c.index is None,
                    )
                else:
                    todo.append(nxt)

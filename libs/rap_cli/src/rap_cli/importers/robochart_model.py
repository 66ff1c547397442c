"""The model a RoboChart import is building: components whose ports grow with each
connection, messages, connections, where each part came from, and the diagnostics.

A port is made the first time a connection names its event; its direction is what the
connections make of it: only ever a source -> ``out``, only ever a destination -> ``in``,
both (or a ``_bidirec`` connection) -> ``in-out`` (a controller's event that a module
feeds and the controller passes on to a machine is both). :meth:`ModelDraft.freeze`
turns the draft into a :class:`~rap_schemas.DeploymentPlan`.
"""

from __future__ import annotations

from dataclasses import dataclass, field

from rap_schemas.maplek import Stage
from rap_schemas.plan import (
    ComponentSpec,
    ConnectionSpec,
    DeploymentPlan,
    MessageSpec,
    PortDirection,
    PortSpec,
)

from ..diagnostics import Diagnostic, Loc, Severity
from ..robochart import syntax as s
from . import Imported
from .robochart_scope import render_type

__all__ = ["CompDraft", "EventRef", "ModelDraft", "PortDraft", "behaviour_properties"]


@dataclass(frozen=True, slots=True)
class EventRef:
    """An event a component can name in a connection: its declaration, the qualified
    name of what declares it (the machine or an interface it uses) and that file."""

    event: s.Event
    owner: str
    file: s.RcFile | s.RacFile


@dataclass(slots=True)
class PortDraft:
    """A port while connections are still being read."""

    sends: bool = False
    takes: bool = False
    type: str | None = None
    origin: str = ""
    loc: Loc | None = None
    type_loc: Loc | None = None

    def spec(self) -> PortSpec:
        direction: PortDirection = (
            "in-out" if self.sends and self.takes else "out" if self.sends else "in"
        )
        return PortSpec(
            direction=direction,
            kind="event" if self.type is None else "event-data",
            type=self.type,
            origin=self.origin or None,
        )


@dataclass(slots=True)
class CompDraft:
    """A component being built: what it came from, the events a connection may name
    (event name -> its declaration and the qualified name of what declares it), and the
    ports made so far."""

    name: str
    loc: Loc
    origin: str
    stage: Stage | None = None
    role: str | None = None
    external: bool = False
    doc: str = ""
    events: dict[str, EventRef] = field(default_factory=dict)
    properties: dict[str, str] = field(default_factory=dict)
    ports: dict[str, PortDraft] = field(default_factory=dict)

    def spec(self) -> ComponentSpec:
        return ComponentSpec(
            stage=self.stage,
            role=self.role,
            external=self.external,
            ports={name: port.spec() for name, port in self.ports.items()},
            origin=self.origin,
            properties=self.properties,
            doc=self.doc,
        )


@dataclass(slots=True)
class _Link:
    spec: ConnectionSpec
    loc: Loc
    ends: tuple[str, str, str, str]


class ModelDraft:
    """Components, messages and connections of the import, with ``where`` and the
    diagnostics (see the module docstring)."""

    def __init__(self, out: Imported) -> None:
        self.out = out
        self.components: dict[str, CompDraft] = {}
        self.messages: dict[str, MessageSpec] = {}
        self.links: list[_Link] = []

    # ---- diagnostics and places

    def report(self, loc: Loc, severity: Severity, message: str) -> None:
        self.out.diagnostics.append(Diagnostic(loc.file, loc.line, loc.column, severity, message))

    def where(self, path: tuple[object, ...], loc: Loc) -> None:
        self.out.where.setdefault(path, loc)

    # ---- parts

    def unique(self, name: str, qualifier: str) -> str:
        """``name`` if no component has it yet, else ``qualifier.name`` (then numbered)."""
        if name not in self.components:
            return name
        candidate = f"{qualifier}.{name}"
        n = 2
        while candidate in self.components:
            candidate = f"{qualifier}.{name}.{n}"
            n += 1
        return candidate

    def add_component(self, draft: CompDraft) -> CompDraft:
        self.components[draft.name] = draft
        self.where(("components", draft.name), draft.loc)
        return draft

    def add_message(self, name: str, spec: MessageSpec, loc: Loc) -> None:
        self.messages[name] = spec
        self.where(("messages", name), loc)

    def port(self, comp: CompDraft, event: str, *, sends: bool, takes: bool, at: Loc) -> PortDraft:
        """The port of ``comp`` for ``event`` (made on first use), marked as a source
        and/or a destination."""
        port = comp.ports.get(event)
        if port is None:
            port = comp.ports[event] = PortDraft(loc=at)
            self.where(("components", comp.name, "ports", event), at)
        port.sends |= sends
        port.takes |= takes
        return port

    def find_link(self, ends: tuple[str, str, str, str]) -> Loc | None:
        """Where a connection with these ends (component, event, component, event) was
        made, if one was."""
        for link in self.links:
            if link.ends == ends:
                return link.loc
        return None

    def connect(
        self,
        source: tuple[CompDraft, str],
        target: tuple[CompDraft, str],
        *,
        bidirectional: bool,
        origin: str,
        loc: Loc,
    ) -> tuple[PortDraft, PortDraft]:
        """A connection from ``source`` to ``target`` (component, event); returns the two
        ports, made or marked (their place: the event's declaration, else ``loc``)."""
        (a, e), (b, f) = source, target
        ports = (
            self.port(a, e, sends=True, takes=bidirectional, at=_event_loc(a, e, loc)),
            self.port(b, f, sends=bidirectional, takes=True, at=_event_loc(b, f, loc)),
        )
        index = len(self.links)
        spec = ConnectionSpec(
            from_=f"{a.name}.{e}", to=f"{b.name}.{f}", bidirectional=bidirectional, origin=origin
        )
        self.links.append(_Link(spec, loc, (a.name, e, b.name, f)))
        self.where(("connections", index), loc)
        return ports

    def freeze(self, system: str, doc: str) -> DeploymentPlan:
        return DeploymentPlan(
            system=system,
            compute_nodes={},
            components={name: c.spec() for name, c in self.components.items()},
            messages=self.messages,
            connections=[link.spec for link in self.links],
            doc=doc,
        )


def _event_loc(comp: CompDraft, event: str, default: Loc) -> Loc:
    ref = comp.events.get(event)
    return ref.event.loc if ref is not None else default


# ------------------------------------------------------------------------------ behaviour


def _oneline(text: s.Text | None) -> str:
    return " ".join(text.text.split()) if text is not None else ""


def _nodes(nodes: tuple[s.Node, ...], prefix: str = "") -> tuple[list[str], list[s.Transition]]:
    """Node names (nested states as ``S.sub``) and every transition below, depth first."""
    names: list[str] = []
    transitions: list[s.Transition] = []
    todo: list[tuple[s.Node, str]] = [(n, prefix) for n in reversed(nodes)]
    while todo:
        node, at = todo.pop()
        label = f"{at}{node.name}"
        if isinstance(node, s.State):
            names.append(label)
            transitions += node.transitions
            todo += [(n, f"{label}.") for n in reversed(node.nodes)]
        elif isinstance(node, s.Junction):
            names.append(f"{label} ({'probabilistic ' if node.probabilistic else ''}junction)")
        else:
            names.append(f"{label} ({'initial' if isinstance(node, s.Initial) else 'final'})")
    return names, transitions


def _transition(t: s.Transition) -> str:
    parts = [f"{t.name}: {t.source} -> {t.target}"]
    for word, text in (
        ("trigger", t.trigger),
        ("probability", t.probability),
        ("condition", t.guard),
        ("action", t.action),
    ):
        if text is not None:
            parts.append(f"{word} {_oneline(text)}")
    return " ".join(parts)


def _members(variables: tuple[s.Variable, ...], *, const: bool) -> str:
    out = []
    for v in variables:
        if v.const == const:
            value = f" = {_oneline(v.value)}" if v.value is not None else ""
            out.append(f"{v.name}: {render_type(v.type)}{value}")
    return "; ".join(out)


def behaviour_properties(
    *,
    uses: tuple[s.InterfaceUse, ...],
    variables: tuple[s.Variable, ...],
    events: dict[str, EventRef],
    clocks: tuple[s.Clock, ...] = (),
    operations: tuple[str, ...] = (),
    nodes: tuple[s.Node, ...] = (),
    transitions: tuple[s.Transition, ...] = (),
) -> dict[str, str]:
    """What a machine, controller or platform says that the model has no field for, as
    text properties: interfaces, events, variables, consts, clocks, operations, states
    and transitions (each as written, on one line)."""
    names, inner = _nodes(nodes)
    props = {
        "interfaces": "; ".join(f"{u.kind} {u.interface}" for u in uses),
        "events": "; ".join(
            f"{name}: {render_type(e.event.type)}" if e.event.type is not None else name
            for name, e in events.items()
        ),
        "variables": _members(variables, const=False),
        "consts": _members(variables, const=True),
        "clocks": ", ".join(c.name for c in clocks),
        "operations": ", ".join(operations),
        "states": ", ".join(names),
        "transitions": "; ".join(_transition(t) for t in (*transitions, *inner)),
    }
    return {k: v for k, v in props.items() if v}

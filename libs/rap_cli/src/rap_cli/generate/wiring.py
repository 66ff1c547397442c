"""How the generated components talk: a fabric key per port, and the Legitimate gate.

Ports joined by connections (the model's, and those a shared topic implies) share one
channel: a data topic when any of them is a ``data`` port, an event otherwise. Its name
is the topic one of them declares; else, when the channel passes through a component of
``role: knowledge`` (RPIO's designs route everything through one), that port's name,
which is also the knowledge key the producers write; else the producing port's name
(qualified ``component.port`` where two channels would share it).

The gate: the plan stage's outputs on a channel that a legitimate stage takes are
proposed (``rap_sdk.gate.propose``), that legitimate stage judges them
(``@legitimate``), and the execute stage's inputs on that channel become one handler of
approved plans (``ApprovalGate.on_approved``), so that execute acts only on plans the
legitimate stage approved.
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from typing import Literal

from rap_schemas import ComponentSpec, DeploymentPlan
from rap_schemas.catalog import MESSAGES
from rap_schemas.model import connections
from rap_schemas.plan import PortSpec

__all__ = [
    "Channel",
    "ComponentWiring",
    "PortWiring",
    "Wiring",
    "channels",
    "clean_key",
    "generated",
    "wire",
]

Family = Literal["data", "event"]
Role = Literal["input", "output", "proposal", "judged", "approved"]
End = tuple[str, str]


@dataclass(frozen=True, slots=True)
class Channel:
    family: Family
    key: str
    """The data topic or event name."""
    knowledge: str | None = None
    """The knowledge key of the channel, when it passes through a knowledge component."""


@dataclass(frozen=True, slots=True)
class PortWiring:
    component: str
    port: str
    spec: PortSpec
    channel: Channel
    type: str | None
    """The model's type name (a message of the model, or a RAP wire type); None: none."""
    role: Role


@dataclass(slots=True)
class ComponentWiring:
    name: str
    spec: ComponentSpec
    inputs: list[PortWiring] = field(default_factory=list)
    outputs: list[PortWiring] = field(default_factory=list)
    writes: list[str] = field(default_factory=list)
    reads: list[str] = field(default_factory=list)
    plan_type: str | None = None
    """Legitimate and execute stages in the gate, and plan stages that propose: the plan."""
    legitimators: list[str] = field(default_factory=list)
    """Execute stages: the legitimate stages whose approvals they take."""

    @property
    def stage(self) -> str | None:
        return self.spec.stage.value if self.spec.stage is not None else None

    @property
    def handlers(self) -> list[PortWiring]:
        return [p for p in self.inputs if p.role == "input"]


@dataclass(slots=True)
class Wiring:
    components: dict[str, ComponentWiring]
    """The components to generate, in model order."""
    sources: list[PortWiring]
    """Inputs of generated components that no generated component feeds: what a test
    (or the managed system) publishes."""
    warnings: list[str]


def generated(plan: DeploymentPlan, package: str) -> dict[str, ComponentSpec]:
    """The components ``rap generate`` writes a node for: run by the runner (neither
    external, nor a command, nor a knowledge store) with no module yet, or a module of
    the package being generated."""
    out = {}
    for name, c in plan.components.items():
        if c.external or c.run or _is_store(c):
            continue
        if c.module is None or c.module.startswith(f"{package}.nodes."):
            out[name] = c
    return out


def _is_store(c: ComponentSpec) -> bool:
    """A knowledge store of the design (``role: knowledge``): RAP's knowledge service
    plays its part; its ports relay."""
    return c.stage is None and c.role == "knowledge"


class _Groups:
    def __init__(self) -> None:
        self.parent: dict[End, End] = {}

    def find(self, e: End) -> End:
        self.parent.setdefault(e, e)
        while self.parent[e] != e:
            self.parent[e] = self.parent[self.parent[e]]
            e = self.parent[e]
        return e

    def join(self, a: End, b: End) -> None:
        ra, rb = self.find(a), self.find(b)
        if ra != rb:
            self.parent[rb] = ra


def channels(plan: DeploymentPlan) -> dict[End, Channel]:
    """The channel of every port of ``plan``, by ``(component, port)`` (see the module
    doc): what the generated code and the access-control rules both go by."""
    groups = _Groups()
    for cname, comp in plan.components.items():
        for pname in comp.ports:
            groups.find((cname, pname))
    for conn in connections(plan):
        groups.join(conn.source, conn.target)
    members: dict[End, list[End]] = {}
    for end in groups.parent:
        members.setdefault(groups.find(end), []).append(end)
    names: dict[End, tuple[Family, str, str | None, str]] = {}
    for root, ends in members.items():
        ports = [(e, plan.components[e[0]].ports[e[1]]) for e in ends]
        family: Family = "data" if any(p.kind == "data" for _, p in ports) else "event"
        topic = next((p.topic for _, p in ports if p.topic), None)
        store = next((e[1] for e, _ in ports if _is_store(plan.components[e[0]])), None)
        producer = next((e for e, p in ports if p.direction in ("out", "in-out")), min(ends))
        base = clean_key(topic or store or producer[1])
        names[root] = (family, base, store, f"{producer[0]}.{producer[1]}")
    taken: dict[tuple[Family, str], int] = {}
    for family, base, _, _ in names.values():
        taken[(family, base)] = taken.get((family, base), 0) + 1
    out: dict[End, Channel] = {}
    for end in groups.parent:
        family, base, store, qualified = names[groups.find(end)]
        qualified = clean_key(qualified)
        explicit = plan.components[end[0]].ports[end[1]].topic
        key = base if explicit or taken[(family, base)] == 1 else qualified
        out[end] = Channel(family, key, store)
    return out


_BAD = re.compile(r"[^0-9A-Za-z_.\-~+:@=%,]+")


def clean_key(text: str) -> str:
    """A fabric key path for a design's topic: no empty chunks (RPIO writes
    ``/weather_condition`` and ``//spin_config``), no characters keys refuse."""
    chunks = [_BAD.sub("_", c) for c in text.split("/") if c.strip()]
    return "/".join(c for c in chunks if c) or "topic"


def wire(plan: DeploymentPlan, package: str) -> Wiring:
    """The wiring of the components that ``rap generate`` writes (see the module doc)."""
    chans = channels(plan)
    todo = generated(plan, package)
    warnings: list[str] = []
    comps = {name: ComponentWiring(name, spec) for name, spec in todo.items()}

    def stage_of(name: str) -> str | None:
        s = plan.components[name].stage
        return s.value if s is not None else None

    # the gate: channels a plan stage produces and a legitimate stage takes
    plan_channels: dict[Channel, str | None] = {}
    for name, spec in plan.components.items():
        if stage_of(name) != "legitimate":
            continue
        for pname, port in spec.ports.items():
            if port.direction not in ("in", "in-out"):
                continue
            ch = chans[(name, pname)]
            fed_by_plan = any(
                stage_of(c) == "plan" and p.direction in ("out", "in-out")
                for (c, pn), other in chans.items()
                if other == ch
                for p in [plan.components[c].ports[pn]]
            )
            if fed_by_plan:
                plan_channels[ch] = port.type
    legitimators = [
        n
        for n, s in plan.components.items()
        if stage_of(n) == "legitimate" and any(chans[(n, p)] in plan_channels for p in s.ports)
    ]
    # RAP's style: the legitimate stage's verdict output feeds the execute stage
    verdicts: dict[Channel, list[str]] = {}
    for name, spec in plan.components.items():
        if stage_of(name) != "legitimate":
            continue
        for pname, port in spec.ports.items():
            ch = chans[(name, pname)]
            if port.direction in ("out", "in-out") and any(
                stage_of(c) == "execute" and plan.components[c].ports[pn].direction != "out"
                for (c, pn), other in chans.items()
                if other == ch
            ):
                verdicts.setdefault(ch, []).append(name)
    for name, cw in comps.items():
        stage = cw.stage
        for pname, port in cw.spec.ports.items():
            ch = chans[(name, pname)]
            in_gate = ch in plan_channels
            takes = port.direction in ("in", "in-out")
            sends = port.direction in ("out", "in-out")
            if sends and stage == "legitimate" and ch in verdicts:
                sends = False  # the gate's verdict, which @legitimate sends
            if sends:
                role: Role = "proposal" if stage == "plan" and in_gate else "output"
                cw.outputs.append(PortWiring(name, pname, port, ch, port.type, role))
                if role == "proposal":
                    cw.plan_type = port.type
                if ch.knowledge and ch.knowledge not in cw.writes:
                    cw.writes.append(ch.knowledge)
            if takes:
                role = "input"
                if stage == "legitimate" and in_gate:
                    role = "judged"
                    cw.plan_type = port.type
                elif stage == "execute" and (in_gate or ch in verdicts):
                    role = "approved"
                    if port.type not in (None, "rap.Verdict/1"):
                        cw.plan_type = port.type
                    cw.legitimators = sorted(verdicts.get(ch, legitimators))
                cw.inputs.append(PortWiring(name, pname, port, ch, port.type, role))
        for key in cw.spec.writes:
            if key not in cw.writes:
                cw.writes.append(key)
        cw.reads = list(cw.spec.reads)
        if not cw.inputs:
            warnings.append(
                f"component {name!r} has no input port: nothing triggers it; its node "
                "only offers its outputs (connect an input to it and regenerate)"
            )
    # what the generated components do not feed themselves
    fed: set[Channel] = {p.channel for cw in comps.values() for p in cw.outputs}
    sources = [
        p for cw in comps.values() for p in cw.inputs if p.channel not in fed and p.role == "input"
    ]
    return Wiring(comps, sources, warnings)


def wire_class(type_name: str | None) -> tuple[str, str] | None:
    """For a RAP wire type (``rap.LaserScan/2``): (module, class) to import it from."""
    if type_name is None:
        return None
    for m in MESSAGES:
        if m.TYPE == type_name:
            return ("rap_schemas", m.__name__)
    return None

"""Process and device instances to the components of RAP's model.

- Name: its ``RAP::Name``; else the subcomponent's name when no other process or device
  has it (compared without case), else its dotted instance path from the root
  (``managing.m``). A component with ``RAP::`` properties (or in a RAP design) takes
  stage, role, module and the rest from them (:mod:`.aadl_rap`); without ``RAP::Stage``
  nor ``RAP::Role``, its stage still comes from its name (below), unless the root says
  ``RAP::Infer => false``; ports, threads and modes take their ``RAP::Name`` too.
- Stage: from the subcomponent's name or its type's, when obvious: ``monitor``,
  ``analysis``/``analyse``/``analyze``, ``plan``, ``legitimate``, ``execute``, or the
  RoboSAPIENS one-letter ``m a p l e`` (the subcomponent's name only); ``knowledge`` or
  ``k`` is role ``knowledge``; a process under a system whose name (or type's) says
  ``managed`` (not ``managing``) has role ``managed``; a device is ``external`` with
  role ``device``.
- Ports: the port features of its type: ``in out`` -> ``in-out``; ``event data`` ->
  ``event-data``; ``type`` from :class:`~.aadl_messages.Messages`; ``topic`` and the
  port's properties (rpio ``Port_*``) from the port, or from the system feature it is
  connected to at a system boundary.
- Threads (dotted path inside the process) with their ``in modes`` and dispatch; modes
  (initial first) and transitions of the process. A transition triggered by a thread's
  port becomes a trigger on the process port that thread port is connected to, if any;
  otherwise the trigger is kept in the transition's ``origin`` only (the model's
  triggers name ports of the component).
- Dispatch: ``RAP::Dispatch`` (and ``RAP::Rate_Hz``) of the process; else its
  ``Dispatch_Protocol``/``Period``; else of its threads when they agree (periodic at the
  highest rate); else rpio ``Port_Dispatch_Protocol``/``Port_Frequency`` of its ports
  (periodic at the highest rate wins over sporadic). Each thread keeps its own.
"""

from __future__ import annotations

from collections import Counter
from dataclasses import dataclass, field

from rap_schemas.maplek import Stage
from rap_schemas.plan import ComponentSpec, Dispatch, ModeTransitionSpec, PortSpec, ThreadSpec

from ..aadl import syntax as s
from ..aadl.syntax import norm
from ..diagnostics import Loc
from .aadl_deploy import Deployment
from .aadl_il_names import STAGE_WORDS
from .aadl_index import Index, find_property, is_container
from .aadl_instance import Instance
from .aadl_messages import Messages
from .aadl_rap import is_rap, rap_component, rap_rate, rap_string, texts
from .aadl_wiring import LEAVES, Wiring

__all__ = ["Components"]

_STAGE_LETTERS = {
    "m": Stage.MONITOR,
    "a": Stage.ANALYSE,
    "p": Stage.PLAN,
    "l": Stage.LEGITIMATE,
    "e": Stage.EXECUTE,
}
_DIRECTIONS = {"in": "in", "out": "out", "in out": "in-out"}
_KINDS = {"event port": "event", "data port": "data", "event data port": "event-data"}
_SECONDS = {"ps": 1e-12, "ns": 1e-9, "us": 1e-6, "ms": 1e-3, "sec": 1.0, "min": 60.0, "hr": 3600.0}
_HERTZ = {"hz": 1.0, "khz": 1e3, "mhz": 1e6, "ghz": 1e9}
_CONSUMED = frozenset({"actual_processor_binding", "dispatch_protocol", "period"})
_TOPICS = ("Port_MQTT_Topic", "Topic")


@dataclass
class Components:
    """The components of the tree, with their names for connections."""

    index: Index
    root: Instance
    wiring: Wiring
    deployment: Deployment
    messages: Messages
    rap: bool = False
    """A RAP design (:mod:`.aadl_rap`): a process's ``RAP::`` properties decide."""
    infer: bool = True
    """Infer a stage from a name, a dispatch from threads or ports, where the ``RAP::``
    properties say none (False: the root says ``RAP::Infer => false``)."""
    specs: dict[str, ComponentSpec] = field(default_factory=dict)
    where: dict[tuple[object, ...], Loc] = field(default_factory=dict)
    name_of: dict[int, str] = field(default_factory=dict)
    _boundary: dict[tuple[int, str], list[s.PropertyAssociation]] = field(default_factory=dict)
    _ports_of: dict[tuple[int, str], str] = field(default_factory=dict)

    def __post_init__(self) -> None:
        leaves = [i for i in self.root.walk() if _is_component(i)]
        counts = Counter(norm(i.name) for i in leaves)
        for inst in leaves:
            named = rap_string(inst.properties(), "Name")
            unique = inst.name if counts[norm(inst.name)] == 1 else inst.dotted
            self.name_of[id(inst)] = named if named is not None else unique
        self._collect_boundary()
        for inst in leaves:
            name = self.name_of[id(inst)]
            self.specs[name] = self._component(inst, name)
            self.where[("components", name)] = inst.loc

    def _collect_boundary(self) -> None:
        """Properties of system features, handed to the ports inside they lead to."""
        for inst in self.root.walk():
            if not is_container(inst.category):
                continue
            for feature in inst.features.values():
                props = inst.port_properties(feature.name)
                if not props:
                    continue
                for leaf, port in self.wiring.inner_ports(inst, feature.name):
                    self._boundary.setdefault((id(leaf), norm(port)), []).extend(props)

    # -- one component

    def port_name(self, inst: Instance, feature: str) -> str:
        """The model's name of port ``feature`` of component ``inst``."""
        return self._ports_of.get((id(inst), norm(feature)), feature)

    def _component(self, inst: Instance, name: str) -> ComponentSpec:
        props = inst.properties()
        ports = self._ports(inst, name)
        modes, transitions, mode_names = self._modes(inst, name)
        threads = self._threads(inst, name, mode_names)
        device = inst.category == "device"
        origin = f"aadl {inst.category} {inst.classifier_text} at {inst.dotted}"
        dispatch = _dispatch(props)
        if dispatch is None and self.infer:
            dispatch = _agree([t.dispatch for t in threads.values() if t.dispatch])
        if dispatch is None and self.infer:
            dispatch = self._port_dispatch(inst)
        if self.rap or any(is_rap(a) for a in props):
            return rap_component(
                props,
                node=self.deployment.node_for(inst),
                ports=ports,
                threads=threads,
                modes=modes,
                mode_transitions=transitions,
                origin=origin,
                device=device,
                dispatch=dispatch,
                properties=texts(props, skip=_CONSUMED),
                inferred=None if device or not self.infer else _stage(inst),
            )
        return ComponentSpec(
            stage=None if device else _stage(inst),
            role="device" if device else _role(inst),
            external=device,
            node=self.deployment.node_for(inst),
            ports=ports,
            dispatch=dispatch,
            threads=threads,
            modes=modes,
            mode_transitions=transitions,
            origin=origin,
            properties=texts(props, skip=_CONSUMED),
        )

    def _port_props(self, inst: Instance, port: str) -> list[s.PropertyAssociation]:
        return self._boundary.get((id(inst), norm(port)), []) + inst.port_properties(port)

    def _ports(self, inst: Instance, cname: str) -> dict[str, PortSpec]:
        out: dict[str, PortSpec] = {}
        ctype = self.index.type_of(inst.classifier) if inst.classifier else None
        for feature in inst.features.values():
            kind = _KINDS.get(feature.kind)
            if kind is None or feature.direction is None:
                continue
            resolved = None
            if feature.classifier is not None and ctype is not None:
                resolved = self.index.resolve(feature.classifier, ctype.package, feature.loc)
            props = self._port_props(inst, feature.name)
            topic = find_property(props, *_TOPICS)
            pname = rap_string(props, "Name") or feature.name
            self._ports_of[(id(inst), norm(feature.name))] = pname
            ptype = rap_string(props, "Field_Type")
            out[pname] = PortSpec(
                direction=_DIRECTIONS[feature.direction],  # type: ignore[arg-type]
                kind=kind,  # type: ignore[arg-type]
                type=ptype or self.messages.port_type(resolved, feature.loc),
                topic=topic.value.value
                if topic and isinstance(topic.value, s.StringValue)
                else None,
                origin=f"aadl {feature.direction} {feature.kind} {feature.name}",
                properties=texts(props),
                doc=rap_string(props, "Doc") or "",
            )
            self.where[("components", cname, "ports", pname)] = feature.loc
        return out

    def _port_dispatch(self, inst: Instance) -> Dispatch | None:
        found: list[Dispatch] = []
        for feature in inst.features.values():
            props = self._port_props(inst, feature.name)
            protocol = find_property(props, "rpio::Port_Dispatch_Protocol")
            if protocol is None or not isinstance(protocol.value, s.EnumValue):
                continue
            kind = norm(protocol.value.literal)
            freq = find_property(props, "rpio::Port_Frequency")
            rate = _hertz(freq.value) if freq is not None else None
            if kind in ("periodic", "sporadic"):
                found.append(Dispatch(kind=kind, rate_hz=rate))  # type: ignore[arg-type]
        periodic = [d for d in found if d.kind == "periodic"]
        if periodic:
            rates = [d.rate_hz for d in periodic if d.rate_hz]
            return Dispatch(kind="periodic", rate_hz=max(rates) if rates else None)
        return found[0] if found else None

    def _threads(
        self, inst: Instance, cname: str, mode_names: dict[str, str]
    ) -> dict[str, ThreadSpec]:
        out: dict[str, ThreadSpec] = {}
        for thread in inst.walk()[1:]:
            if thread.category != "thread":
                continue
            props = thread.properties()
            tname = rap_string(props, "Name") or ".".join(thread.path[len(inst.path) :])
            in_modes = list(thread.sub.in_modes) if thread.sub else []
            out[tname] = ThreadSpec(
                dispatch=rap_rate(_dispatch(props), props),
                in_modes=[mode_names.get(norm(m), m) for m in in_modes],
                origin=f"aadl thread {thread.classifier_text} at {thread.dotted}",
                properties=texts(props, skip=_CONSUMED),
                doc=rap_string(props, "Doc") or "",
            )
            self.where[("components", cname, "threads", tname)] = thread.loc
        return out

    def _modes(
        self, inst: Instance, cname: str
    ) -> tuple[list[str], list[ModeTransitionSpec], dict[str, str]]:
        """The modes (initial first), the transitions, and mode identifier -> name."""
        if inst.classifier is None:
            return [], [], {}
        modes, transitions = self.index.modes(inst.classifier)
        called = {norm(m.name): rap_string(m.properties, "Name") or m.name for m in modes}
        ordered = [m for m in modes if m.initial] + [m for m in modes if not m.initial]
        names = [called[norm(m.name)] for m in ordered]
        if names:
            self.where[("components", cname, "modes")] = modes[0].loc
        out: list[ModeTransitionSpec] = []
        links = self._internal_links(inst)
        for tr in transitions:
            triggers: list[str] = []
            inner: list[str] = []
            for trig in tr.triggers:
                if norm(trig) in inst.features:
                    triggers.append(self.port_name(inst, trig))
                elif norm(trig) in links:
                    triggers.append(self.port_name(inst, links[norm(trig)]))
                else:
                    inner.append(trig)
            written = f"{', '.join(tr.sources)} -[{', '.join(tr.triggers)}]-> {tr.destination}"
            origin = f"aadl mode transition {tr.name + ': ' if tr.name else ''}{written}"
            if inner:
                origin += f" (triggered inside by {', '.join(inner)})"
            for src in tr.sources:
                self.where[("components", cname, "mode_transitions", len(out))] = tr.loc
                out.append(
                    ModeTransitionSpec(
                        from_=called.get(norm(src), src),
                        to=called.get(norm(tr.destination), tr.destination),
                        triggers=triggers,
                        origin=origin,
                    )
                )
        return names, out, called

    def _internal_links(self, inst: Instance) -> dict[str, str]:
        """Thread port path -> the process port it is connected to inside the process."""
        impl = inst.impl
        if impl is None:
            return {}
        out: dict[str, str] = {}
        for conn in self.index.connections(impl):
            for inner, outer in ((conn.source, conn.dest), (conn.dest, conn.source)):
                if "." in inner and "." not in outer and norm(outer) in inst.features:
                    out.setdefault(norm(inner), inst.features[norm(outer)].name)
        return out


def _is_component(inst: Instance) -> bool:
    """Processes, and devices that have ports (a device without is platform hardware,
    such as a GPU or a network driver, described by its node)."""
    if inst.category == "device":
        return any(f.kind in _KINDS for f in inst.features.values())
    return inst.category in LEAVES


def _stage(inst: Instance) -> Stage | None:
    name = norm(inst.name)
    if name in STAGE_WORDS:
        return STAGE_WORDS[name]
    if inst.classifier is not None and norm(inst.classifier.type_name) in STAGE_WORDS:
        return STAGE_WORDS[norm(inst.classifier.type_name)]
    return _STAGE_LETTERS.get(name)


def _role(inst: Instance) -> str | None:
    type_name = norm(inst.classifier.type_name) if inst.classifier is not None else ""
    if norm(inst.name) in ("knowledge", "k") or type_name == "knowledge":
        return "knowledge"
    here = inst.parent
    while here is not None:
        words = [norm(here.name)]
        if here.classifier is not None:
            words.append(norm(here.classifier.type_name))
        if any("managed" in w and "managing" not in w for w in words):
            return "managed"
        here = here.parent
    return None


def _seconds(value: s.PropertyValue) -> float | None:
    if isinstance(value, s.IntValue | s.RealValue) and value.unit is not None:
        factor = _SECONDS.get(norm(value.unit))
        if factor is not None and value.value > 0:
            return float(value.value) * factor
    return None


def _hertz(value: s.PropertyValue) -> float | None:
    if isinstance(value, s.IntValue | s.RealValue) and value.value > 0:
        return float(value.value) * _HERTZ.get(norm(value.unit or "hz"), 1.0)
    return None


def _dispatch(props: list[s.PropertyAssociation]) -> Dispatch | None:
    protocol = find_property(props, "Dispatch_Protocol")
    if protocol is None or not isinstance(protocol.value, s.EnumValue):
        return None
    period = find_property(props, "Period")
    seconds = _seconds(period.value) if period is not None else None
    rate = 1.0 / seconds if seconds else None
    kind = "periodic" if norm(protocol.value.literal) == "periodic" else "sporadic"
    if norm(protocol.value.literal) in ("aperiodic", "background"):
        rate = None
    return Dispatch(kind=kind, rate_hz=rate)  # type: ignore[arg-type]


def _agree(found: list[Dispatch]) -> Dispatch | None:
    if not found or len({d.kind for d in found}) != 1:
        return None
    rates = [d.rate_hz for d in found if d.rate_hz]
    return Dispatch(kind=found[0].kind, rate_hz=max(rates) if rates else None)

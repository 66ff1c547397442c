"""The ``RAP`` property set (:data:`rap_cli.exporters.aadl.PROPERTY_SET`) read back.

``rap export aadl`` says with ``RAP::`` properties what AADL has no property for; where a
design uses them, they decide over the importer's inferences:

- ``RAP::Name`` is the model's name of whatever carries it (the identifier otherwise);
  an empty one on a connection says it has no name in the model;
- ``RAP::Doc`` is its doc; ``RAP::Design_Properties`` (``"Name => value"`` strings) are
  its ``properties``; no ``RAP::`` property is ever copied into ``properties``;
- ``RAP::Stage``/``Role``/``Module``/``External``/``Run``/``Config`` (JSON)/``Config_Type``/
  ``Reads``/``Writes``/``Dispatch``/``Rate_Hz`` are the component's fields, and
  ``RAP::Mode_Transitions`` (JSON ``[[from, to, [trigger, ..]], ..]``) all its mode
  transitions when AADL cannot write one (a transition without a trigger);
- ``RAP::Wire_Type`` on a data type makes a port of it carry that RAP wire type,
  ``RAP::Field_Type`` overrides a field's or port's type, ``RAP::Constraints``
  (``"ge=0.0; le=1.0"``, values in JSON) gives a field's constraints;
- the root system's ``RAP::Knowledge_*``, ``Trust_*`` and ``Fabric_*`` give where
  knowledge, trust and the fabric are.

A design whose root system carries a ``RAP::`` property was written by the export
(:func:`is_rap_design`): there, names come from the design only (no stage inferred from
a name, compute nodes and buses named by their subcomponent), every message is imported
used or not, and connections keep their declared order.
"""

from __future__ import annotations

import json
from typing import Any

from rap_schemas.maplek import Stage
from rap_schemas.plan import (
    ComponentSpec,
    Dispatch,
    FabricSpec,
    KnowledgeSpec,
    ModeTransitionSpec,
    PortSpec,
    ThreadSpec,
    TrustSpec,
)

from ..aadl import syntax as s
from ..aadl.syntax import norm
from .aadl_index import find_property
from .aadl_instance import value_text

__all__ = [
    "CONSTRAINTS",
    "constraints",
    "design_properties",
    "is_rap",
    "is_rap_design",
    "knowledge",
    "rap_bool",
    "rap_component",
    "rap_enum",
    "rap_json",
    "rap_number",
    "rap_rate",
    "rap_string",
    "rap_strings",
    "texts",
    "trust_and_fabric",
    "without_rap",
]

CONSTRAINTS = ("ge", "le", "gt", "lt", "min_length", "max_length", "pattern")
"""The field constraints ``RAP::Constraints`` may give."""

_STAGES = frozenset(x.value for x in Stage)
Props = list[s.PropertyAssociation] | tuple[s.PropertyAssociation, ...]


def is_rap(assoc: s.PropertyAssociation) -> bool:
    """Whether ``assoc`` is a property of the ``RAP`` set."""
    return norm(assoc.property_set or "") == "rap"


def is_rap_design(root_props: Props) -> bool:
    """Whether the root system carries ``RAP::`` properties (the export wrote it)."""
    return any(is_rap(a) for a in root_props)


def without_rap(props: Props) -> list[s.PropertyAssociation]:
    """``props`` but the ``RAP::`` ones."""
    return [a for a in props if not is_rap(a)]


def _value(props: Props, name: str) -> s.PropertyValue | None:
    found = find_property(list(props), f"RAP::{name}")
    return found.value if found is not None else None


def rap_string(props: Props, name: str) -> str | None:
    """The string ``RAP::<name>`` (None when absent or not a string)."""
    value = _value(props, name)
    return value.value if isinstance(value, s.StringValue) else None


def rap_enum(props: Props, name: str) -> str | None:
    """The enumeration literal (or string) ``RAP::<name>``."""
    value = _value(props, name)
    if isinstance(value, s.EnumValue):
        return value.literal
    return value.value if isinstance(value, s.StringValue) else None


def rap_strings(props: Props, name: str) -> list[str] | None:
    """The list of strings ``RAP::<name>`` (one string counts as a list of one)."""
    value = _value(props, name)
    if value is None:
        return None
    items = value.items if isinstance(value, s.ListValue) else (value,)
    return [i.value for i in items if isinstance(i, s.StringValue)]


def rap_number(props: Props, name: str) -> float | None:
    """The number ``RAP::<name>``."""
    value = _value(props, name)
    return float(value.value) if isinstance(value, s.IntValue | s.RealValue) else None


def rap_bool(props: Props, name: str) -> bool | None:
    """The boolean ``RAP::<name>``."""
    value = _value(props, name)
    return value.value if isinstance(value, s.BoolValue) else None


def rap_json(props: Props, name: str) -> Any:
    """The JSON text ``RAP::<name>`` decoded (None when absent or not JSON)."""
    text = rap_string(props, name)
    if text is None:
        return None
    try:
        return json.loads(text)
    except ValueError:
        return None


def design_properties(props: Props) -> dict[str, str]:
    """``RAP::Design_Properties``: the ``"Name => value"`` strings as a dict."""
    out: dict[str, str] = {}
    for item in rap_strings(props, "Design_Properties") or []:
        key, sep, value = item.partition(" => ")
        if sep:
            out[key] = value
    return out


def texts(props: Props, *, skip: frozenset[str] = frozenset()) -> dict[str, str]:
    """A part's ``properties``: its associations as written, but the ``RAP::`` ones
    and the simple names in ``skip``, then its design properties."""
    out = {
        a.name: value_text(a.value)
        for a in props
        if not is_rap(a) and norm(a.simple_name) not in skip
    }
    out.update(design_properties(props))
    return out


def constraints(props: Props) -> dict[str, Any]:
    """``RAP::Constraints`` (``"ge=0.0; pattern=\\"^a\\""``) as FieldSpec arguments."""
    text = rap_string(props, "Constraints")
    out: dict[str, Any] = {}
    if not text:
        return out
    decoder = json.JSONDecoder()
    at = 0
    while at < len(text):
        name, sep, _ = text[at:].partition("=")
        name = name.strip(" ;")
        if not sep or name not in CONSTRAINTS:
            break
        try:
            value, end = decoder.raw_decode(text, at + text[at:].index("=") + 1)
        except ValueError:
            break
        out[name] = value
        at = end
    return out


def knowledge(props: Props) -> KnowledgeSpec | None:
    """The root's ``RAP::Knowledge_*`` (None without ``RAP::Knowledge_Backend``)."""
    backend = rap_string(props, "Knowledge_Backend")
    if backend not in ("memory", "sqlite", "redis", "memcached"):
        return None
    return KnowledgeSpec(
        backend=backend,  # type: ignore[arg-type]
        node=rap_string(props, "Knowledge_Node"),
        path=rap_string(props, "Knowledge_Path"),
        url=rap_string(props, "Knowledge_URL"),
    )


def trust_and_fabric(props: Props) -> tuple[TrustSpec, FabricSpec]:
    """The root's ``RAP::Trust_*`` and ``RAP::Fabric_*``."""
    trust = TrustSpec(
        node=rap_string(props, "Trust_Node"), specs=rap_strings(props, "Trust_Specs") or []
    )
    mode = rap_enum(props, "Fabric_Mode")
    fabric = FabricSpec(
        mode=mode if mode in ("peer", "client", "router") else "peer",  # type: ignore[arg-type]
        routers=rap_strings(props, "Fabric_Routers") or [],
    )
    return trust, fabric


def rap_rate(dispatch: Dispatch | None, props: Props) -> Dispatch | None:
    """``dispatch`` at the rate ``RAP::Rate_Hz`` says, when it says one."""
    rate = rap_number(props, "Rate_Hz")
    if dispatch is None or rate is None or rate <= 0:
        return dispatch
    return Dispatch(kind=dispatch.kind, rate_hz=rate)


def rap_component(
    props: Props,
    *,
    node: str | None,
    ports: dict[str, PortSpec],
    threads: dict[str, ThreadSpec],
    modes: list[str],
    mode_transitions: list[ModeTransitionSpec],
    origin: str,
    device: bool,
    dispatch: Dispatch | None,
    properties: dict[str, str],
) -> ComponentSpec:
    """A component whose ``RAP::`` properties say what it is: nothing is inferred from
    its name; ``dispatch`` (from AADL's properties) counts when ``RAP::Dispatch`` is
    absent."""
    stage = rap_enum(props, "Stage")
    kind = rap_enum(props, "Dispatch")
    kind = kind.lower() if kind else None
    if kind in ("periodic", "sporadic"):
        rate = rap_number(props, "Rate_Hz")
        dispatch = Dispatch(kind=kind, rate_hz=rate if rate and rate > 0 else None)  # type: ignore[arg-type]
    config = rap_json(props, "Config")
    moves = rap_json(props, "Mode_Transitions")
    if isinstance(moves, list):
        mode_transitions = [
            ModeTransitionSpec(from_=m[0], to=m[1], triggers=m[2], origin=origin)
            for m in moves
            if isinstance(m, list) and len(m) == 3
        ]
    external = rap_bool(props, "External")
    return ComponentSpec(
        module=rap_string(props, "Module"),
        stage=Stage(stage.lower()) if stage and stage.lower() in _STAGES else None,
        role=rap_string(props, "Role") or ("device" if device else None),
        external=device if external is None else external,
        node=node,
        config=config if isinstance(config, dict) else {},
        config_type=rap_string(props, "Config_Type"),
        ports=ports,
        run=rap_strings(props, "Run") or [],
        reads=rap_strings(props, "Reads") or [],
        writes=rap_strings(props, "Writes") or [],
        dispatch=dispatch,
        threads=threads,
        modes=modes,
        mode_transitions=mode_transitions,
        origin=origin,
        properties=properties,
        doc=rap_string(props, "Doc") or "",
    )

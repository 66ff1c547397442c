"""The ``RAP`` property set (:data:`rap_cli.exporters.aadl.PROPERTY_SET`) read back.

``rap export aadl`` says with ``RAP::`` properties what AADL has no property for; where a
design uses them, they decide over the importer's inferences:

- ``RAP::Name`` is the model's name of whatever carries it (the identifier otherwise);
  an empty one on a connection says it has no name in the model;
- ``RAP::Doc`` is its doc; ``RAP::Design_Properties`` (``"Name => value"`` strings) are
  its ``properties``; no ``RAP::`` property is ever copied into ``properties``;
- ``RAP::Stage``/``Role``/``Module``/``External``/``Run``/``Config`` (JSON)/``Config_Type``/
  ``Reads``/``Writes``/``Dispatch``/``Rate_Hz`` are the component's fields, ``RAP::Models``
  (``"name:read"``, ``"name:write"`` strings) its ``models``, and
  ``RAP::Mode_Transitions`` (JSON ``[[from, to, [trigger, ..]], ..]``) all its mode
  transitions when AADL cannot write one (a transition without a trigger);
- ``RAP::Wire_Type`` on a data type makes a port of it carry that RAP wire type,
  ``RAP::Field_Type`` overrides a field's or port's type, ``RAP::Constraints``
  (``"ge=0.0; le=1.0"``, values in JSON) gives a field's constraints;
- the root system's ``RAP::Knowledge_*``, ``Trust_*`` and ``Fabric_*`` give where
  knowledge, trust and the fabric are.

A design whose root system carries a ``RAP::`` property is a RAP design
(:func:`is_rap_design`, as the export writes): there, compute nodes and buses are named
by their subcomponent, every message is imported used or not, and connections keep
their declared order. A process without ``RAP::Stage`` (nor ``RAP::Role``) still gets
its stage from its name, and one without ``RAP::Dispatch`` its dispatch from AADL's
properties (its own, else its threads' when they agree), unless the root says
``RAP::Infer => false`` (:func:`infers`; the export says it: its designs say
everything).

The importer knows the property set itself (:func:`builtin_property_sets`): a design
that names ``RAP`` in a ``with`` needs no ``RAP.aadl`` among its files; one given there
is used instead.
"""

from __future__ import annotations

import json
from collections.abc import Sequence
from functools import cache
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

from ..aadl import parse_aadl
from ..aadl import syntax as s
from ..aadl.syntax import norm
from ..exporters.aadl import PROPERTY_SET
from .aadl_index import find_property
from .aadl_instance import value_text

__all__ = [
    "BUILTIN_SOURCE",
    "CONSTRAINTS",
    "builtin_property_sets",
    "constraints",
    "design_properties",
    "infers",
    "is_rap",
    "is_rap_design",
    "knowledge",
    "rap_bool",
    "rap_component",
    "rap_enum",
    "rap_json",
    "rap_models",
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


BUILTIN_SOURCE = "RAP.aadl (built in)"
"""Where diagnostics place the built-in property set."""


@cache
def _builtin() -> s.AadlFile:
    parsed, found = parse_aadl(PROPERTY_SET, BUILTIN_SOURCE)
    assert parsed is not None, [str(d) for d in found]  # the export's own text parses
    return parsed


def builtin_property_sets(files: Sequence[s.AadlFile]) -> list[s.AadlFile]:
    """RAP's property set (the text ``rap export aadl`` writes,
    :data:`rap_cli.exporters.aadl.PROPERTY_SET`) when a package or property set of
    ``files`` names ``RAP`` in its ``with`` and no file declares it; else nothing."""
    declared = {norm(p.name) for f in files for p in f.property_sets}
    declared |= {norm(p.name) for f in files for p in f.packages}
    if "rap" in declared:
        return []
    withs = [w for f in files for p in f.packages for w in p.withs]
    withs += [w for f in files for p in f.property_sets for w in p.withs]
    return [_builtin()] if any(norm(w) == "rap" for w in withs) else []


def is_rap(assoc: s.PropertyAssociation) -> bool:
    """Whether ``assoc`` is a property of the ``RAP`` set."""
    return norm(assoc.property_set or "") == "rap"


def is_rap_design(root_props: Props) -> bool:
    """Whether the root system carries ``RAP::`` properties (the export wrote it)."""
    return any(is_rap(a) for a in root_props)


def infers(root_props: Props) -> bool:
    """Whether the importer may infer what the design leaves out (a stage from a name, a
    process's dispatch from its threads): not when the root system says
    ``RAP::Infer => false`` (as the export does)."""
    return rap_bool(root_props, "Infer") is not False


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


def rap_models(props: Props) -> dict[str, str]:
    """``RAP::Models``: ``"name:access"`` strings as ``{name: access}`` (split at the last
    colon: a model name may hold one). An access that is not ``read`` or ``write``, or
    none, is kept as written, for the model's checks to report."""
    out: dict[str, str] = {}
    for item in rap_strings(props, "Models") or []:
        name, sep, access = item.rpartition(":")
        out[name if sep else item] = access if sep else ""
    return out


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
    inferred: Stage | None = None,
) -> ComponentSpec:
    """A component whose ``RAP::`` properties say what it is: ``inferred`` (the stage its
    name says) counts when neither ``RAP::Stage`` nor ``RAP::Role`` is given, ``dispatch``
    (from AADL's properties) when ``RAP::Dispatch`` is absent (at ``RAP::Rate_Hz`` when
    that is given)."""
    stage = rap_enum(props, "Stage")
    kind = rap_enum(props, "Dispatch")
    kind = kind.lower() if kind else None
    if kind in ("periodic", "sporadic"):
        rate = rap_number(props, "Rate_Hz")
        dispatch = Dispatch(kind=kind, rate_hz=rate if rate and rate > 0 else None)  # type: ignore[arg-type]
    else:
        dispatch = rap_rate(dispatch, props)
    named = Stage(stage.lower()) if stage and stage.lower() in _STAGES else None
    if stage is None and rap_string(props, "Role") is None:
        named = inferred
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
        stage=named,
        role=rap_string(props, "Role") or ("device" if device else None),
        external=device if external is None else external,
        node=node,
        config=config if isinstance(config, dict) else {},
        config_type=rap_string(props, "Config_Type"),
        ports=ports,
        run=rap_strings(props, "Run") or [],
        reads=rap_strings(props, "Reads") or [],
        writes=rap_strings(props, "Writes") or [],
        models=rap_models(props),
        dispatch=dispatch,
        threads=threads,
        modes=modes,
        mode_transitions=mode_transitions,
        origin=origin,
        properties=properties,
        doc=rap_string(props, "Doc") or "",
    )

"""The deployment plan: which MAPLE-K components run on which compute node.

    system: demo
    compute_nodes:
      laptop:
        listen: ["tcp/127.0.0.1:7447"]
    knowledge:
      backend: memory
      node: laptop
    components:
      monitor:
        module: lidar_occlusion.nodes:monitor
        stage: monitor
        node: laptop
        config: {}

This is the first slice of RAP's system model (physical architecture, mapping,
knowledge backend); it grows by adding defaulted fields only, so
that every plan written today stays valid. Its JSON Schema is exported with the wire
messages (``schemas/json/rap.DeploymentPlan.schema.json``).

:func:`parse_plan` and :func:`load_plan` check the plan beyond its types (names, the
mapping to compute nodes, module specs, endpoints) and raise :class:`PlanError` with
``file:line:col``; the returned :class:`PlanDocument` keeps the positions, so that later
errors (an import that fails on one compute node) can point at the plan's line too.
"""

from __future__ import annotations

import os
import re
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec

from . import keys
from .limits import MAX_YAML_BYTES
from .maplek import Stage
from .yamlconf import (
    Location,
    YamlDocument,
    YamlError,
    parse_yaml,
    read_text_file,
    render_location,
)

__all__ = [
    "ENDPOINT",
    "MODULE_SPEC",
    "ComponentSpec",
    "ComputeNode",
    "DeploymentPlan",
    "KnowledgeSpec",
    "PlanDocument",
    "PlanError",
    "load_plan",
    "parse_plan",
]

MODULE_SPEC = re.compile(
    r"[A-Za-z_][A-Za-z0-9_]*(\.[A-Za-z_][A-Za-z0-9_]*)*:[A-Za-z_][A-Za-z0-9_]*"
)
"""``package.module:attribute``."""
ENDPOINT = re.compile(r"[a-z][a-z0-9+\-]*/\S+")
"""A Zenoh locator: ``<protocol>/<address>``, e.g. ``tcp/127.0.0.1:7447``."""

Name = Annotated[
    str,
    msgspec.Meta(
        description="One key chunk: letters, digits and '_.-~+:@=%,'.",
        extra_json_schema={"pattern": f"^{keys._CHUNK.pattern}$"},
    ),
]
ModuleSpec = Annotated[
    str,
    msgspec.Meta(
        description="'package.module:attribute' naming a rap_sdk.Node.",
        examples=["lidar_occlusion.nodes:monitor"],
        extra_json_schema={"pattern": f"^{MODULE_SPEC.pattern}$"},
    ),
]
Endpoint = Annotated[
    str,
    msgspec.Meta(
        description="A Zenoh endpoint '<protocol>/<address>'.",
        examples=["tcp/127.0.0.1:7447"],
        extra_json_schema={"pattern": f"^{ENDPOINT.pattern}$"},
    ),
]


class _Plan(msgspec.Struct, frozen=True, forbid_unknown_fields=True, kw_only=True):
    pass


class ComputeNode(_Plan, frozen=True, kw_only=True):
    """A machine (or container) that runs a share of the system."""

    listen: list[Endpoint] = []
    """Zenoh endpoints to listen on; empty: the fabric's default (loopback, free port)."""
    connect: list[Endpoint] = []
    """Zenoh endpoints to connect to."""


class KnowledgeSpec(_Plan, frozen=True, kw_only=True):
    """Where knowledge lives and how it is stored."""

    backend: Literal["memory", "sqlite", "redis"] = "memory"
    node: Name | None = None
    """The compute node that hosts the knowledge service."""
    path: str | None = None
    """The SQLite file (``backend: sqlite``)."""
    url: str | None = None
    """The Redis URL (``backend: redis``)."""


class ComponentSpec(_Plan, frozen=True, kw_only=True):
    """One MAPLE-K component: the Node to import, its stage, where it runs, its config."""

    module: ModuleSpec
    stage: Stage
    """Must match the stage the Node declares."""
    node: Name
    """The compute node that runs it."""
    config: dict[str, Any] = {}
    """Applied with ``Node.configure`` (validated against the Node's config Struct)."""


class DeploymentPlan(_Plan, frozen=True, kw_only=True):
    """A RAP deployment: compute nodes, knowledge and the components mapped onto them.

    Component names are the names of their Nodes on the fabric."""

    system: Name
    """The system name: the ``<system>`` of every key, ``rap/<system>/...``."""
    compute_nodes: Annotated[
        dict[Name, ComputeNode], msgspec.Meta(extra_json_schema={"minProperties": 1})
    ]
    knowledge: KnowledgeSpec = KnowledgeSpec()
    components: dict[Name, ComponentSpec] = {}

    def components_on(self, node: str) -> dict[str, ComponentSpec]:
        """The components mapped to compute node ``node``, in plan order."""
        return {name: c for name, c in self.components.items() if c.node == node}


class PlanError(YamlError):
    """A deployment plan that cannot be used; the message starts with ``file:line:col``."""


class PlanDocument:
    """A checked plan and where its parts are in the file it came from."""

    __slots__ = ("document", "plan", "source")

    def __init__(
        self, plan: DeploymentPlan, *, source: str = "<plan>", document: YamlDocument | None = None
    ) -> None:
        self.plan = plan
        self.source = source
        self.document = document

    @classmethod
    def from_plan(cls, plan: DeploymentPlan, source: str = "<plan>") -> PlanDocument:
        """A plan built in code, checked like a file (errors name ``$.paths``)."""
        doc = cls(plan, source=source)
        _check(doc)
        return doc

    def where(self, loc: Location = (), *, key: bool = False) -> str:
        """``file:line:col`` of a part of the plan (``file: at $.path`` without a file)."""
        if self.document is None:
            return f"{self.source}: at `{render_location(loc)}`"
        return self.document.where(loc, key=key)

    def error(self, loc: Location, problem: str, *, key: bool = False) -> PlanError:
        if self.document is None:
            return PlanError(f"{self.where(loc)}: {problem}", source=self.source)
        line, column = self.document.position(loc, key=key)
        return PlanError(
            f"{self.source}:{line}:{column}: {problem}",
            source=self.source,
            line=line,
            column=column,
        )


def parse_plan(text: str, source: str = "<plan>") -> PlanDocument:
    """Validate a plan; errors read ``source:line:col: what is wrong; how to fix it``."""
    document = parse_yaml(text, source, what="deployment plan", error=PlanError)
    doc = PlanDocument(document.convert(DeploymentPlan), source=source, document=document)
    _check(doc)
    return doc


def load_plan(path: str | os.PathLike[str]) -> PlanDocument:
    """Read and validate a plan file (see :func:`parse_plan`)."""
    text = read_text_file(path, what="deployment plan", error=PlanError, max_bytes=MAX_YAML_BYTES)
    return parse_plan(text, str(Path(path)))


def _check(doc: PlanDocument) -> None:
    """What the types cannot say: names, references, module specs, endpoints."""
    plan = doc.plan
    try:
        keys.system_pattern(plan.system)
    except keys.KeyError_ as exc:
        raise doc.error(("system",), f"{exc}; this name is part of every key") from None
    nodes = list(plan.compute_nodes)
    if not nodes:
        raise doc.error(
            ("compute_nodes",),
            "the plan defines no compute nodes; add one, e.g. 'compute_nodes: {laptop: {}}'",
        )
    for name, compute in plan.compute_nodes.items():
        _check_name(doc, ("compute_nodes", name), "compute node", name)
        for field in ("listen", "connect"):
            for i, endpoint in enumerate(getattr(compute, field)):
                if not ENDPOINT.fullmatch(endpoint):
                    raise doc.error(
                        ("compute_nodes", name, field, i),
                        f"compute node {name!r}: {endpoint!r} is not a Zenoh endpoint; "
                        "write '<protocol>/<address>', e.g. 'tcp/127.0.0.1:7447'",
                    )
    kb = plan.knowledge
    if kb.node is not None and kb.node not in plan.compute_nodes:
        raise doc.error(
            ("knowledge", "node"),
            f"knowledge is placed on compute node {kb.node!r}, which the plan does not "
            f"define; use one of {', '.join(nodes)} or add it under compute_nodes",
        )
    for field, backend in (("path", "sqlite"), ("url", "redis")):
        if getattr(kb, field) is not None and kb.backend != backend:
            raise doc.error(
                ("knowledge", field),
                f"knowledge.{field} is for the {backend} backend, but the backend is "
                f"{kb.backend!r}; set backend: {backend} or remove {field}",
            )
    modules: dict[str, str] = {}
    for name, comp in plan.components.items():
        _check_name(doc, ("components", name), "component", name)
        if not MODULE_SPEC.fullmatch(comp.module):
            raise doc.error(
                ("components", name, "module"),
                f"component {name!r}: module {comp.module!r} is not a "
                "'package.module:attribute' spec; write the module's dotted path, a colon, "
                "then the name of the Node in it, e.g. 'lidar_occlusion.nodes:monitor'",
            )
        if comp.module in modules:
            raise doc.error(
                ("components", name, "module"),
                f"component {name!r} names the same Node as component "
                f"{modules[comp.module]!r} ({comp.module}); a Node runs once: declare "
                "another Node for the second component",
            )
        modules[comp.module] = name
        if comp.node not in plan.compute_nodes:
            raise doc.error(
                ("components", name, "node"),
                f"component {name!r} is mapped to compute node {comp.node!r}, which the "
                f"plan does not define; use one of {', '.join(nodes)} or add it under "
                "compute_nodes",
            )


def _check_name(doc: PlanDocument, loc: Location, what: str, name: str) -> None:
    try:
        keys.alive("x", name)
    except keys.KeyError_:
        raise doc.error(
            loc,
            f"invalid {what} name {name!r}: use one non-empty chunk of letters, digits "
            "and '_.-~+:@=%,' (no '/', no wildcards '*', '$', '#', '?')",
            key=True,
        ) from None

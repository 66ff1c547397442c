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
from collections.abc import Iterator
from pathlib import Path
from typing import Annotated, Any, Literal

import msgspec

from . import keys
from .bridge import BridgeSpec
from .knowledge import MODELS_PREFIX
from .limits import MAX_MESSAGE_BYTES, MAX_YAML_BYTES
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
    "MODEL_ACCESS",
    "MODULE_SPEC",
    "BusSpec",
    "ComponentSpec",
    "ComputeNode",
    "ConnectionSpec",
    "DeploymentPlan",
    "Dispatch",
    "FabricSpec",
    "FieldSpec",
    "Finding",
    "KnowledgeSpec",
    "MessageSpec",
    "ModeTransitionSpec",
    "ModelAccess",
    "ModelName",
    "PlanDocument",
    "PlanError",
    "PortDirection",
    "PortKind",
    "PortSpec",
    "Resources",
    "ThreadSpec",
    "TrustSpec",
    "load_plan",
    "parse_plan",
    "plan_findings",
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
_MIN_SAMPLE_LIMIT = 64 << 10
"""The least ``fabric.max_sample_bytes``: a message that fits one Zenoh batch (64 KiB) is
never reassembled, so no link limit applies to it."""
_MAX_SAMPLE_LIMIT = 1 << 30
"""The greatest ``fabric.max_sample_bytes``: Zenoh's own default link limit (1 GiB)."""
_SampleLimit = Annotated[
    int,
    msgspec.Meta(
        description="A size in bytes, from 65536 (64 KiB) to 1073741824 (1 GiB).",
        extra_json_schema={"minimum": _MIN_SAMPLE_LIMIT, "maximum": _MAX_SAMPLE_LIMIT},
    ),
]
ModelName = Annotated[
    str,
    msgspec.Meta(
        description="A model of the model store: key chunks of letters, digits and "
        "'_.-~+:@=%,', separated by single '/'.",
        examples=["occlusion", "detector/yolo"],
        extra_json_schema={"pattern": f"^{keys._CHUNK.pattern}(/{keys._CHUNK.pattern})*$"},
    ),
]
ModelAccess = Annotated[
    str,
    msgspec.Meta(
        description="`read` (get and list its versions) or `write` (also put new versions, "
        "pin and roll back).",
        extra_json_schema={"enum": ["read", "write"]},
    ),
]
MODEL_ACCESS = ("read", "write")
"""What a component may do with a model of the model store (``ComponentSpec.models``)."""
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


class Resources(_Plan, frozen=True, kw_only=True):
    """What a compute node offers (informative; the generator sizes containers from it)."""

    cpus: Annotated[float, msgspec.Meta(gt=0)] | None = None
    """CPU cores it offers."""
    memory_mb: Annotated[int, msgspec.Meta(gt=0)] | None = None
    """Memory it offers, in MiB."""


class ComputeNode(_Plan, frozen=True, kw_only=True):
    """A machine (or container) that runs a share of the system."""

    listen: list[Endpoint] = []
    """Zenoh endpoints to listen on; empty: the fabric's default (loopback, free port)."""
    connect: list[Endpoint] = []
    """Zenoh endpoints to connect to."""
    address: str | None = None
    """Its host name or IP address on the network that links the compute nodes."""
    architecture: str | None = None
    """CPU architecture, e.g. ``x86_64``, ``aarch64``."""
    resources: Resources = Resources()
    origin: str | None = None
    """What it was imported from (e.g. ``aadl processor platform.robot.RPI``)."""
    properties: dict[str, str] = {}
    """Properties of the design it came from that the model has no field for, as written
    there (e.g. AADL ``Clock_Period``)."""
    doc: str = ""
    """Its documentation."""


class BusSpec(_Plan, frozen=True, kw_only=True):
    """A link between compute nodes (physical architecture)."""

    kind: str = "ethernet"
    """What the link is: `ethernet`, `wifi`, `can`, ..."""
    nodes: list[Name] = []
    """The compute nodes it connects."""
    origin: str | None = None
    """What it was imported from (the construct of a design)."""
    doc: str = ""
    """Its documentation."""


PortDirection = Literal["in", "out", "in-out"]
PortKind = Literal["event", "data", "event-data"]


class PortSpec(_Plan, frozen=True, kw_only=True):
    """A port of a component (logical architecture)."""

    direction: PortDirection
    """`in`, `out` or `in-out`."""
    kind: PortKind = "event-data"
    """``event``: a signal, maybe with a message; ``data``: a sampled value (the latest
    counts); ``event-data``: a queued message."""
    type: str | None = None
    """The message it carries: a name under ``messages:`` or a RAP wire type such as
    ``rap.LaserScan/1``; none for a bare event."""
    topic: str | None = None
    """The fabric name it uses (an event name or a data topic); ports of the same kind
    family on the same topic are connected without a ``connections:`` entry."""
    bridge: BridgeSpec | None = None
    """Binds the port to a protocol outside the fabric (MQTT, TCP, Redis, AMQP,
    WebSocket, NATS, Kafka, DDS for ROS 2): ``rap up`` runs the bridge on the
    component's compute node. A port of a component RAP runs is mirrored out (``out``)
    or fed from outside (``in``); a port of an ``external`` component with no ``run:``
    lives on the protocol, so its ``out`` messages come in. Not for ``in-out`` ports.
    See docs/bridges.md."""
    origin: str | None = None
    """What it was imported from (the construct of a design)."""
    properties: dict[str, str] = {}
    """Properties of the design it came from that the model has no field for, as written there."""
    doc: str = ""
    """Its documentation."""


class Dispatch(_Plan, frozen=True, kw_only=True):
    """When a component runs: on a period, or when an input arrives."""

    kind: Literal["periodic", "sporadic"]
    """`periodic`: on a period; `sporadic`: when an input arrives."""
    rate_hz: Annotated[float, msgspec.Meta(gt=0)] | None = None
    """Periodic: how often; sporadic: the highest rate it must keep up with."""


class ThreadSpec(_Plan, frozen=True, kw_only=True):
    """A thread of a component (an AADL thread): its own dispatch, and the modes it
    exists in (all of them when empty)."""

    dispatch: Dispatch | None = None
    """When the thread runs."""
    in_modes: list[Name] = []
    """The modes of its component it exists in; empty: all."""
    origin: str | None = None
    """What it was imported from (the construct of a design)."""
    properties: dict[str, str] = {}
    """Properties of the design it came from that the model has no field for, as written there."""
    doc: str = ""
    """Its documentation."""


class ModeTransitionSpec(_Plan, frozen=True, kw_only=True):
    """A change of mode of a component, and the ports whose events trigger it."""

    from_: Name = msgspec.field(name="from")
    """The mode it leaves."""
    to: Name
    """The mode it enters."""
    triggers: list[str] = []
    """The ports of the component whose events trigger it."""
    origin: str | None = None
    """What it was imported from (the construct of a design)."""


class ConnectionSpec(_Plan, frozen=True, kw_only=True):
    """A connection from an output port to an input port: ``component.port``."""

    from_: str = msgspec.field(name="from")
    """The output: `component.port`."""
    to: str
    """The input: `component.port`."""
    name: str | None = None
    """Its name in the design (AADL connection name), for findings."""
    bus: Name | None = None
    """The bus it travels over, when the components are on different compute nodes."""
    bidirectional: bool = False
    """Both ways (AADL `<->`, a bidirectional RoboChart connection)."""
    origin: str | None = None
    """What it was imported from (the construct of a design)."""


class FieldSpec(_Plan, frozen=True, kw_only=True):
    """A field of a message. ``type``: ``bool``, ``int``, ``int8`` .. ``uint64``,
    ``float``, ``float32``, ``str``, ``bytes``, a message or enumeration name,
    ``list[T]``, ``list[T, N]`` (exactly N items) or ``optional[T]``. A bound keeps
    the type it is written with (``ge: 1`` stays an int, ``ge: 0.0`` a float)."""

    type: str
    """Its type (see above)."""
    doc: str = ""
    """Its documentation."""
    ge: int | float | None = None
    """Least value allowed (numbers)."""
    le: int | float | None = None
    """Greatest value allowed (numbers)."""
    gt: int | float | None = None
    """Values must be above this (numbers)."""
    lt: int | float | None = None
    """Values must be below this (numbers)."""
    min_length: Annotated[int, msgspec.Meta(ge=0)] | None = None
    """Least length (strings, bytes, lists)."""
    max_length: Annotated[int, msgspec.Meta(ge=0)] | None = None
    """Greatest length (strings, bytes, lists)."""
    pattern: str | None = None
    """A regular expression strings must match."""


class MessageSpec(_Plan, frozen=True, kw_only=True):
    """A message (``fields``) or an enumeration (``enum``) of the model."""

    fields: dict[str, FieldSpec] = {}
    """Its fields, in order."""
    enum: list[str] | None = None
    """The literals of an enumeration (then ``fields`` stays empty)."""
    origin: str | None = None
    """What it was imported from (the construct of a design)."""
    doc: str = ""
    """Its documentation."""


class FabricSpec(_Plan, frozen=True, kw_only=True):
    """How the compute nodes' fabric sessions find each other (Zenoh)."""

    mode: Literal["peer", "client", "router"] = "peer"
    """The Zenoh session mode of every process."""
    routers: list[Endpoint] = []
    """Zenoh routers every session connects to."""
    tls: bool = False
    """Zenoh links use TLS with mutual authentication; `rap certs` makes the certificates."""
    operators: list[Name] = []
    """Operator identities that get a certificate (`rap certs`), to reach the fabric with."""
    acl: bool = True
    """With `tls`: every router enforces access control derived from the model (each
    process may publish, subscribe, read and write only what the model declares for the
    components it runs; only operators may call admin verbs). `false` leaves any holder of
    a certificate free to do anything."""
    max_sample_bytes: _SampleLimit = MAX_MESSAGE_BYTES
    """The largest sample, query or reply payload (in bytes) the system's links must take.
    The routers and processes `rap up` and `rap generate` configure drop a message over
    this plus 64 KiB (room for its key, attachment and headers: Zenoh's
    `transport.link.rx.max_message_size`) before reassembling it, silently: the sender is
    not told, the receiver logs nothing (Zenoh traces the drop at its `trace` level only)
    and the link stays up. From 65536 to 1073741824 (Zenoh's own default); by default
    257 MiB, which the knowledge service's model store needs (256 MiB models). Lower it
    (e.g. to 4194304, the 4 MiB RAP's subscribers take) when no model is that big: it
    bounds what one peer can make a router hold while reassembling."""
    shared_memory: bool = False
    """Whether processes of one machine may pass samples through Zenoh's shared memory
    (by reference, for samples over about 3 KiB). Off by default: such a sample escapes
    `max_sample_bytes`, and a router keeps the shared-memory pool of every peer that
    sent it one mapped after that peer is gone (about 17 MiB per peer, measured by
    `make faults`, scenario `memory`). `true` suits large payloads (camera images, point
    clouds) between trusted processes of one machine: a 1 MiB sample then crosses a
    router in a fraction of the time, at that memory cost."""


class TrustSpec(_Plan, frozen=True, kw_only=True):
    """The runtime trust checker: where it runs and the specs it watches."""

    node: Name | None = None
    """The compute node that runs the trust checker."""
    specs: list[str] = []
    """Spec files (``.dsrv``), relative to the model file."""


class KnowledgeSpec(_Plan, frozen=True, kw_only=True):
    """Where knowledge lives and how it is stored."""

    backend: Literal["memory", "sqlite", "redis", "memcached", "kafka"] = "memory"
    """`memory` (lost on restart), `sqlite` (a file), `redis`, `memcached` (the
    latest values in memcached; history, the key list and models in the SQLite file), or
    `kafka` (everything in the SQLite file, and every record stored appended to a Kafka
    topic: the knowledge stream)."""
    node: Name | None = None
    """The compute node that hosts the knowledge service."""
    path: str | None = None
    """The SQLite file (``backend: sqlite`` and ``kafka``, and ``backend: memcached`` for
    history and models)."""
    url: str | None = None
    """The Redis URL (``backend: redis``, e.g. ``redis://127.0.0.1:6379/0``) or the
    memcached URL (``backend: memcached``, ``memcached://HOST[:PORT]``, by default
    ``memcached://127.0.0.1:11211``) or the Kafka broker (``backend: kafka``,
    ``kafka://HOST[:PORT]``, by default ``kafka://127.0.0.1:9092``)."""


class ComponentSpec(_Plan, frozen=True, kw_only=True):
    """A component: the Node to import (or none yet: to generate), its MAPLE-K stage or
    role, where it runs, its config, and what the model says of its ports and knowledge."""

    module: ModuleSpec | None = None
    """The Node it runs; none: to generate (``rap generate``), or run elsewhere
    (``external``)."""
    stage: Stage | None = None
    """Its MAPLE-K stage; must match the stage the Node declares."""
    role: str | None = None
    """What it is when it is no stage, e.g. ``managed`` (the managed system)."""
    external: bool = False
    """It runs outside RAP's runners (a simulator, a robot's drivers): described for the
    checks, never started by RAP."""
    node: Name | None = None
    """The compute node that runs it."""
    config: dict[str, Any] = {}
    """Applied with ``Node.configure`` (validated against the Node's config Struct)."""
    config_type: str | None = None
    """The message of the model that describes its config."""
    ports: dict[Name, PortSpec] = {}
    """Its ports (logical architecture)."""
    reads: list[str] = []
    """Knowledge keys it reads."""
    writes: list[str] = []
    """Knowledge keys it writes."""
    models: dict[ModelName, ModelAccess] = {}
    """Models of the knowledge service's model store it uses, each ``read`` (get and list
    its versions) or ``write`` (also put new versions, pin and roll back), e.g.
    ``{occlusion: read}``. With ``fabric.tls`` the access control lets it use these and
    no other (operators may use every model)."""
    dispatch: Dispatch | None = None
    """When it runs."""
    run: list[str] = []
    """A command ``rap up`` starts and supervises for it on its compute node (a simulator,
    a bridge, the robot's drivers), as argv: ``{python}`` stands for the Python that runs
    RAP, ``{system}`` for the system name, ``{model_dir}`` for the model's folder. The
    process reaches the fabric through its compute node's router (``RAP_ZENOH_CONFIG``)."""
    threads: dict[Name, ThreadSpec] = {}
    """Its threads, when the design says how it is split (AADL threads)."""
    modes: list[Name] = []
    """Its operating modes, the initial one first."""
    mode_transitions: list[ModeTransitionSpec] = []
    """How it changes mode."""
    origin: str | None = None
    """What it was imported from (e.g. ``aadl process m``, ``robochart stm Monitor``)."""
    properties: dict[str, str] = {}
    """Properties of the design it came from that the model has no field for."""
    doc: str = ""
    """Its documentation."""


class DeploymentPlan(_Plan, frozen=True, kw_only=True):
    """RAP's system model: the components and their ports, messages and connections
    (logical), compute nodes and buses (physical), the components mapped onto the
    nodes, the fabric, knowledge and trust. A deployment plan is a model that gives
    only what running it needs (nodes, mapping, modules).

    Component names are the names of their Nodes on the fabric."""

    system: Name
    """The system name: the ``<system>`` of every key, ``rap/<system>/...``."""
    compute_nodes: dict[Name, ComputeNode]
    knowledge: KnowledgeSpec = KnowledgeSpec()
    """Where knowledge lives."""
    components: dict[Name, ComponentSpec] = {}
    """The components (logical architecture) and where each runs (mapping)."""
    messages: dict[Name, MessageSpec] = {}
    """The messages and enumerations ports and fields use."""
    connections: list[ConnectionSpec] = []
    """Connections between ports (more are implied by shared topics)."""
    buses: dict[Name, BusSpec] = {}
    """Links between compute nodes (physical architecture)."""
    fabric: FabricSpec = FabricSpec()
    """How the fabric sessions connect."""
    trust: TrustSpec = TrustSpec()
    """The runtime trust checker."""
    doc: str = ""
    """What the system is."""

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
    """Raise the first of :func:`plan_findings` (what running the plan needs)."""
    for loc, problem, key in plan_findings(doc.plan):
        raise doc.error(loc, problem, key=key)


Finding = tuple[Location, str, bool]
"""Where (a path in the document), what is wrong and how to fix it, and whether the
path points at a mapping key rather than its value."""


def plan_findings(plan: DeploymentPlan) -> Iterator[Finding]:
    """What the types cannot say and running the plan needs: names, references, module
    specs, endpoints, every component on a compute node. All of them, in file order."""
    try:
        keys.system_pattern(plan.system)
    except keys.KeyError_ as exc:
        yield ("system",), f"{exc}; this name is part of every key", False
    nodes = list(plan.compute_nodes)
    listed = ", ".join(nodes)
    if not nodes:
        yield (
            ("compute_nodes",),
            "the plan defines no compute nodes; add one, e.g. 'compute_nodes: {laptop: {}}'",
            False,
        )
    for name, compute in plan.compute_nodes.items():
        yield from _name_findings(("compute_nodes", name), "compute node", name)
        for field in ("listen", "connect"):
            for i, endpoint in enumerate(getattr(compute, field)):
                if not ENDPOINT.fullmatch(endpoint):
                    yield (
                        ("compute_nodes", name, field, i),
                        f"compute node {name!r}: {endpoint!r} is not a Zenoh endpoint; "
                        "write '<protocol>/<address>', e.g. 'tcp/127.0.0.1:7447'",
                        False,
                    )
    kb = plan.knowledge
    if kb.node is not None and kb.node not in plan.compute_nodes:
        yield (
            ("knowledge", "node"),
            f"knowledge is placed on compute node {kb.node!r}, which the plan does not "
            f"define; use one of {listed} or add it under compute_nodes",
            False,
        )
    for field, backends in (
        ("path", ("sqlite", "memcached", "kafka")),
        ("url", ("redis", "memcached", "kafka")),
    ):
        if getattr(kb, field) is not None and kb.backend not in backends:
            yield (
                ("knowledge", field),
                f"knowledge.{field} is for the {backends[0]} backend (and "
                f"{', '.join(backends[1:])}), but the backend is {kb.backend!r}; set "
                f"backend: {backends[0]} or remove {field}",
                False,
            )
    for backend, port in (("memcached", 11211), ("kafka", 9092)):
        if kb.backend == backend and kb.url is not None and not kb.url.startswith(f"{backend}://"):
            yield (
                ("knowledge", "url"),
                f"knowledge.url {kb.url!r} is not a {backend} URL; write "
                f"{backend}://HOST[:PORT], e.g. {backend}://127.0.0.1:{port}",
                False,
            )
    limit = plan.fabric.max_sample_bytes
    if not _MIN_SAMPLE_LIMIT <= limit <= _MAX_SAMPLE_LIMIT:
        low = limit < _MIN_SAMPLE_LIMIT
        yield (
            ("fabric", "max_sample_bytes"),
            f"fabric.max_sample_bytes is {limit}: "
            + (
                f"under {_MIN_SAMPLE_LIMIT} (64 KiB) it would not hold (a message that fits "
                "one 64 KiB Zenoh batch is never reassembled, so no limit applies to it); "
                f"give at least {_MIN_SAMPLE_LIMIT}"
                if low
                else f"over {_MAX_SAMPLE_LIMIT} (1 GiB, Zenoh's own default) it would be "
                f"looser than no limit at all; give at most {_MAX_SAMPLE_LIMIT}"
            )
            + f", or leave it out for the default {MAX_MESSAGE_BYTES} (257 MiB)",
            False,
        )
    if plan.trust.node is not None and plan.trust.node not in plan.compute_nodes:
        yield (
            ("trust", "node"),
            f"the trust checker is placed on compute node {plan.trust.node!r}, which the "
            f"plan does not define; use one of {listed} or add it under compute_nodes",
            False,
        )
    for name, bus in plan.buses.items():
        for i, node in enumerate(bus.nodes):
            if node not in plan.compute_nodes:
                yield (
                    ("buses", name, "nodes", i),
                    f"bus {name!r} connects compute node {node!r}, which the plan does not "
                    f"define; use one of {listed} or add it under compute_nodes",
                    False,
                )
    modules: dict[str, str] = {}
    for name, comp in plan.components.items():
        yield from _name_findings(("components", name), "component", name)
        if comp.module is not None:
            if not MODULE_SPEC.fullmatch(comp.module):
                yield (
                    ("components", name, "module"),
                    f"component {name!r}: module {comp.module!r} is not a "
                    "'package.module:attribute' spec; write the module's dotted path, a "
                    "colon, then the name of the Node in it, e.g. "
                    "'lidar_occlusion.nodes:monitor'",
                    False,
                )
            elif comp.module in modules:
                yield (
                    ("components", name, "module"),
                    f"component {name!r} names the same Node as component "
                    f"{modules[comp.module]!r} ({comp.module}); a Node runs once: declare "
                    "another Node for the second component",
                    False,
                )
            else:
                modules[comp.module] = name
        if comp.node is None and not comp.external:
            yield (
                ("components", name),
                f"component {name!r} is bound to no compute node; add 'node: <name>' "
                f"with one of: {listed or '(none yet: add compute_nodes)'}",
                True,
            )
        elif comp.node not in plan.compute_nodes:
            yield (
                ("components", name, "node"),
                f"component {name!r} is mapped to compute node {comp.node!r}, which the "
                f"plan does not define; use one of {listed} or add it under "
                "compute_nodes",
                False,
            )
        if comp.run:
            if comp.module is not None:
                yield (
                    ("components", name, "run"),
                    f"component {name!r} has both module: (a Node the runner imports) and "
                    "run: (a command rap up starts); keep the one that says how it runs",
                    False,
                )
            elif comp.node is None:
                yield (
                    ("components", name, "run"),
                    f"component {name!r} has a command to run but no compute node to run "
                    f"it on; add 'node: <name>' with one of: {listed or '(none yet)'}",
                    False,
                )
            if not comp.run[0].strip():
                yield (
                    ("components", name, "run", 0),
                    f"component {name!r}: run: starts with an empty program name; give "
                    "the command as a list, e.g. ['{python}', '-m', 'sim_world']",
                    False,
                )
        yield from _model_findings(name, comp)


def _model_findings(name: str, comp: ComponentSpec) -> Iterator[Finding]:
    """A component's ``models:``: store names, each ``read`` or ``write``."""
    for model, access in comp.models.items():
        loc = ("components", name, "models", model)
        try:
            keys.kb("x", f"{MODELS_PREFIX}/{model}")
        except keys.KeyError_:
            yield (
                loc,
                f"component {name!r}: {model!r} is not a model name; use key chunks of "
                "letters, digits and '_.-~+:@=%,' separated by single '/' (no wildcards "
                "'*', '$', '#', '?'), e.g. 'occlusion' or 'detector/yolo'",
                True,
            )
        if access not in MODEL_ACCESS:
            yield (
                loc,
                f"component {name!r}: model {model!r} has access {access!r}; write read "
                "(get and list its versions) or write (also put, pin and roll back)",
                False,
            )


def _name_findings(loc: Location, what: str, name: str) -> Iterator[Finding]:
    try:
        keys.alive("x", name)
    except keys.KeyError_:
        yield (
            loc,
            f"invalid {what} name {name!r}: use one non-empty chunk of letters, digits "
            "and '_.-~+:@=%,' (no '/', no wildcards '*', '$', '#', '?')",
            True,
        )

"""What runs on each compute node of a model, for ``rap up`` and the generated compose files.

    doc = load_plan("model.yaml")
    paths = Paths.local(Path("model.yaml"), Path(".rap/demo"), "robot")
    for p in node_processes(doc, "robot", paths=paths, addresses={"edge": "10.0.0.2"}):
        p.command(sys.executable)   # argv with PYTHON replaced by the interpreter

Each compute node runs one Zenoh router (``rap_cli.router``); every other process of the
node is a Zenoh client of it (``RAP_ZENOH_CONFIG`` names the client config), so the
processes of a node reach each other and every other node through the routers, whatever
the number of processes and hosts. The router listens on the node's ``listen`` endpoints
(and on a local endpoint for its clients) and connects to the node's ``connect``
endpoints and to ``fabric.routers``.

An endpoint whose host is the name of a compute node (``tcp/edge:7447``) is resolved to
that node's address: the one given with ``--address edge=HOST``, else the model's
``address:``, else the name itself (left to DNS, as on a compose network).

With ``fabric: {tls: true}`` the model's endpoints (``listen``, ``connect``,
``fabric.routers``) go over TLS (``tcp/`` becomes ``tls/``) with mutual authentication:
each router presents its compute node's certificate (``rap certs``) and accepts only
peers whose certificate the model's CA signed. A node's own clients reach its router on
a loopback ``tcp/`` endpoint (that link never leaves the machine).

Every link of a config written here drops a message over the model's
``fabric.max_sample_bytes`` (plus ``rap_schemas.limits.MESSAGE_HEADROOM``) before
reassembling it, and uses no Zenoh shared memory unless ``fabric.shared_memory`` (through
which a message would escape that limit, and which a router keeps mapped for peers that
are gone).

Knowledge runs on ``knowledge.node`` (the first compute node when none is named), the
trust checker on ``trust.node`` (one process per spec), the runner on every node that has
components with a ``module:``, and each component with ``run:`` as its own process.
"""

from __future__ import annotations

import hashlib
import json
import re
from collections.abc import Callable, Mapping, Sequence
from dataclasses import dataclass, field, replace
from pathlib import Path, PurePosixPath
from typing import Any, Literal

from rap_schemas import DeploymentPlan, PlanDocument
from rap_schemas.limits import MAX_MESSAGE_BYTES, MESSAGE_HEADROOM

__all__ = [
    "CONFIG_ENV",
    "PYTHON",
    "Paths",
    "ProcessSpec",
    "Role",
    "TlsFiles",
    "client_config",
    "knowledge_node",
    "node_processes",
    "process_identity",
    "resolve_endpoint",
    "resolve_url",
    "router_config",
    "router_id",
    "tls_endpoint",
    "tls_link",
]

PYTHON = "{python}"
"""Stands for the Python interpreter in :attr:`ProcessSpec.argv`."""
CONFIG_ENV = "RAP_ZENOH_CONFIG"
"""The environment variable a RAP process reads its Zenoh client config from
(``rap_sdk.fabric.CONFIG_ENV``)."""
NODE_ENV = "RAP_COMPUTE_NODE"
CERTS_ENV = "RAP_CERTS"
"""The certificates' folder (``rap certs``), with ``fabric.tls``."""
AS_ENV = "RAP_AS"
"""A process's identity (its certificate's common name): ``<node>.<process>``."""
"""The compute node a process runs on (``rap_sdk.runtime.NODE_ENV``)."""

Role = Literal["router", "knowledge", "manager", "runner", "trust", "bridges", "component"]

_HOST = re.compile(r"^(?P<proto>[a-z][a-z0-9+\-]*)/(?P<host>\[[^\]]*\]|[^:/\[]+)(?P<rest>.*)$")


@dataclass(frozen=True, slots=True)
class ProcessSpec:
    """One supervised process of a compute node's share."""

    name: str
    """Unique on the node: ``router``, ``knowledge``, ``runner``, ``trust-<spec>``, or the
    component's name."""
    role: Role
    argv: tuple[str, ...]
    """The command; :data:`PYTHON` stands for the interpreter."""
    env: Mapping[str, str] = field(default_factory=dict)
    """Environment variables it needs on top of the inherited ones."""
    doc: str = ""
    metrics: str = ""
    """``HOST:PORT`` where it serves Prometheus metrics (``--metrics``); "" for none."""

    def command(self, python: str) -> list[str]:
        """The argv with the interpreter filled in."""
        return [python if a == PYTHON else a for a in self.argv]


@dataclass(frozen=True, slots=True)
class Paths:
    """How the processes name files: the model, its folder, the node's Zenoh configs, and
    where stateful services keep their data. ``rap up`` uses absolute paths on this
    machine; compose files use the paths inside the image."""

    model: str
    model_dir: str
    router_config: str
    client_config: str
    data_dir: str
    certs: str = ""
    """The folder of the certificates (``rap certs``), with ``fabric.tls``; "" for none."""

    @classmethod
    def local(cls, model: Path, run_dir: Path, node: str, certs: Path | None = None) -> Paths:
        model = model.resolve()
        node_dir = run_dir.resolve() / node
        return cls(
            model=str(model),
            model_dir=str(model.parent),
            router_config=str(node_dir / "zenoh-router.json5"),
            client_config=str(node_dir / "zenoh-client.json5"),
            data_dir=str(node_dir / "data"),
            certs=str(certs.resolve()) if certs is not None else "",
        )


def knowledge_node(plan: DeploymentPlan) -> str | None:
    """The compute node that hosts knowledge: ``knowledge.node``, else the first one."""
    if plan.knowledge.node is not None:
        return plan.knowledge.node
    return next(iter(plan.compute_nodes), None)


def resolve_endpoint(
    endpoint: str, plan: DeploymentPlan, addresses: Mapping[str, str] | None = None
) -> str:
    """``endpoint`` with a compute node's name as its host replaced by that node's address
    (``addresses`` first, then the model's ``address:``)."""
    m = _HOST.match(endpoint)
    if m is None:
        return endpoint
    host = m["host"]
    if host not in plan.compute_nodes:
        return endpoint
    address = (addresses or {}).get(host) or plan.compute_nodes[host].address
    if not address:
        return endpoint
    if ":" in address and not address.startswith("["):
        address = f"[{address}]"  # an IPv6 address in a locator
    return f"{m['proto']}/{address}{m['rest']}"


def resolve_url(url: str, plan: DeploymentPlan, addresses: Mapping[str, str] | None = None) -> str:
    """A service URL (``redis://companion:6379/0``) whose host is a compute node's name, or
    the address the model gives it, pointed at the address in ``addresses`` (or the
    model's, for a name)."""
    scheme, sep, rest = url.partition("://")
    if not sep:
        return url
    hostport, slash, tail = rest.partition("/")
    auth, at, hostport = hostport.rpartition("@")
    host, colon, port = hostport.partition(":")
    for name, spec in plan.compute_nodes.items():
        if host in (name, spec.address):
            address = (addresses or {}).get(name) or spec.address or host
            return f"{scheme}://{auth}{at}{address}{colon}{port}{slash}{tail}"
    return url


@dataclass(frozen=True, slots=True)
class TlsFiles:
    """The files of one identity's TLS links (``rap certs`` writes them)."""

    ca: str
    """The CA certificate every peer's certificate must be signed by (``ca.pem``)."""
    certificate: str
    """This identity's certificate (``<name>.pem``)."""
    private_key: str
    """Its private key (``<name>.key``)."""

    @classmethod
    def of(cls, folder: str | Path, name: str) -> TlsFiles:
        """Identity ``name``'s files in ``folder`` (as ``rap certs`` names them)."""
        base = PurePosixPath(folder) if isinstance(folder, str) else folder
        return cls(
            ca=str(base / "ca.pem"),
            certificate=str(base / f"{name}.pem"),
            private_key=str(base / f"{name}.key"),
        )

    def missing(self) -> list[str]:
        """The files that are not there (on this machine)."""
        return [f for f in (self.ca, self.certificate, self.private_key) if not Path(f).is_file()]


def tls_endpoint(endpoint: str) -> str:
    """``endpoint`` over TLS: ``tcp/HOST:PORT`` becomes ``tls/HOST:PORT``; others stay."""
    return "tls/" + endpoint[4:] if endpoint.startswith("tcp/") else endpoint


def tls_link(files: TlsFiles) -> dict[str, Any]:
    """Zenoh's ``transport.link.tls`` for mutual TLS with ``files``: the same certificate
    presented when listening and when connecting, peers' certificates checked against
    the CA both ways, the server's name checked against its certificate's
    subjectAltNames, and a link closed when a certificate expires."""
    return {
        "root_ca_certificate": files.ca,
        "listen_certificate": files.certificate,
        "listen_private_key": files.private_key,
        "connect_certificate": files.certificate,
        "connect_private_key": files.private_key,
        "enable_mtls": True,
        "verify_name_on_connect": True,
        "close_link_on_expiration": True,
    }


def _zenoh_base(
    mode: str,
    tls: TlsFiles | None = None,
    max_sample_bytes: int = MAX_MESSAGE_BYTES,
    shared_memory: bool = False,
) -> dict[str, Any]:
    """What every config RAP writes says: no scouting, a 3 s lease, a message over
    ``max_sample_bytes`` plus ``MESSAGE_HEADROOM`` dropped by the link that receives it,
    and no shared memory unless ``shared_memory`` (the model's ``fabric.shared_memory``):
    a message Zenoh passes through shared memory escapes that limit, and a router keeps
    the pool of every peer that sent it one mapped after the peer is gone
    (bench/faults/memory.py measures it)."""
    link: dict[str, Any] = {
        "tx": {"lease": 3000, "keep_alive": 4},
        "rx": {"max_message_size": max_sample_bytes + MESSAGE_HEADROOM},
    }
    if tls is not None:
        link["tls"] = tls_link(tls)
    return {
        "mode": mode,
        "scouting": {"multicast": {"enabled": False}, "gossip": {"enabled": False}},
        "transport": {"link": link, "shared_memory": {"enabled": shared_memory}},
    }


def process_identity(node: str, process: str) -> str:
    """The identity (certificate common name) of process ``process`` of compute node
    ``node``: ``<node>.<process>`` (``rap certs`` refuses a model where that is also a
    node's or an operator's name)."""
    return f"{node}.{process}"


def router_id(system: str, node: str) -> str:
    """The Zenoh id of compute node ``node``'s router: the same at every start, so that a
    router restarted is known again (its neighbours log the link as restored)."""
    return hashlib.sha256(f"rap/{system}/{node}".encode()).hexdigest()[:32]


def router_config(
    plan: DeploymentPlan,
    node: str,
    *,
    local: Sequence[str],
    addresses: Mapping[str, str] | None = None,
    listen: Sequence[str] | None = None,
    tls: TlsFiles | None = None,
    manager: bool = True,
) -> dict[str, Any]:
    """The Zenoh config of ``node``'s router, with a fixed id (:func:`router_id`): it
    listens on ``local`` (where the node's clients connect) and the node's ``listen``
    endpoints, and connects to its ``connect`` endpoints and the model's
    ``fabric.routers`` (its own listen endpoints excepted). Endpoints naming a compute
    node are resolved (:func:`resolve_endpoint`). ``listen``: the node's listen
    endpoints as the router binds them, when that differs from the model's resolved
    ones (inside a container: every interface).

    ``tls``: the node's certificate files, required when the model says ``fabric.tls``
    (``ValueError`` without them): the model's ``tcp/`` endpoints (and ``listen``) become
    ``tls/`` ones, with mutual TLS, and ``local`` too (every process presents its own
    certificate); unless ``fabric.acl`` is false, the router enforces the access
    control :func:`rap_cli.acl.access_control` derives from the model.
    ``manager``: an adaptation manager runs beside knowledge (its identity is allowed).
    Its links drop a message over the model's ``fabric.max_sample_bytes`` (plus
    ``MESSAGE_HEADROOM``) and use shared memory only if ``fabric.shared_memory``."""
    if plan.fabric.tls and tls is None:
        raise ValueError(
            f"compute node {node}: the model says fabric.tls - its router needs its "
            "certificate files (rap certs MODEL)"
        )

    def secure(e: str) -> str:
        return tls_endpoint(e) if plan.fabric.tls else e

    spec = plan.compute_nodes[node]
    mine = [secure(resolve_endpoint(e, plan, addresses)) for e in spec.listen]
    given = mine if listen is None else [secure(e) for e in listen]
    binds = list(dict.fromkeys([*(secure(e) for e in local), *given]))
    own = set(binds) | set(mine)
    connect: list[str] = []
    for e in [*spec.connect, *plan.fabric.routers]:
        r = secure(resolve_endpoint(e, plan, addresses))
        if r not in own and r not in connect and e not in spec.listen:
            connect.append(r)
    fabric = plan.fabric
    conf = _zenoh_base(
        "router", tls if fabric.tls else None, fabric.max_sample_bytes, fabric.shared_memory
    )
    conf["id"] = router_id(plan.system, node)
    if plan.fabric.tls and plan.fabric.acl:
        from .acl import access_control

        conf["access_control"] = access_control(plan, manager=manager)
    conf["listen"] = {"endpoints": binds}
    # a router keeps trying the routers it connects to: a link cut and restored heals
    conf["connect"] = {
        "endpoints": connect,
        "timeout_ms": -1,
        "exit_on_failure": False,
        "retry": {"period_init_ms": 250, "period_max_ms": 2000, "period_increase_factor": 2},
    }
    return conf


def client_config(
    router: str,
    tls: TlsFiles | None = None,
    *,
    secure: bool = False,
    max_sample_bytes: int = MAX_MESSAGE_BYTES,
    shared_memory: bool = False,
) -> dict[str, Any]:
    """The Zenoh config of the node's other processes: clients of its router (with
    ``tls``: presenting that certificate, for a ``tls/`` router endpoint). ``secure``
    (a node of a model with ``fabric.tls``): the router is reached over mutual TLS and
    each process presents its own certificate, named by its environment (``RAP_AS``,
    ``RAP_CERTS``: :func:`rap_sdk.fabric.node_overlay` fills them in).
    ``max_sample_bytes``: the model's ``fabric.max_sample_bytes`` (a message from the
    router over it plus ``MESSAGE_HEADROOM`` is dropped); ``shared_memory``: the model's
    ``fabric.shared_memory``."""
    conf = _zenoh_base("client", tls, max_sample_bytes, shared_memory)
    if secure and tls is None:
        link = {k: v for k, v in tls_link(TlsFiles("", "", "")).items() if not _is_file(k)}
        conf["transport"]["link"]["tls"] = link
        router = tls_endpoint(router)
    conf["listen"] = {"endpoints": []}
    conf["connect"] = {"endpoints": [router]}
    return conf


def _is_file(option: str) -> bool:
    return option.endswith(("_certificate", "_private_key"))


def render_zenoh(conf: Mapping[str, Any], *, title: str) -> str:
    """A Zenoh config as JSON5 text: JSON with whole-line ``//`` comments (Zenoh reads
    JSON5; :func:`rap_sdk.fabric.node_overlay` skips such comments)."""
    import json

    lines = [
        f"// {title}",
        "// Generated by rap from the system model; regenerate rather than edit.",
        "// TLS and mutual authentication: transport.link.tls; access control: access_control",
        "// (when the model says fabric: {tls: true}; rap certs makes the certificates).",
        json.dumps(conf, indent=2),
    ]
    return "\n".join(lines) + "\n"


def _has_runner(plan: DeploymentPlan, node: str) -> bool:
    return any(c.module is not None and not c.external for c in plan.components_on(node).values())


def _rel(base: str, path: str) -> str:
    """``path`` (from the model) against folder ``base``, unless it is absolute."""
    return path if path.startswith("/") else str(PurePosixPath(base) / path)


def node_processes(
    doc: PlanDocument,
    node: str,
    *,
    paths: Paths,
    system: str | None = None,
    log_level: str = "INFO",
    addresses: Mapping[str, str] | None = None,
    metrics: Callable[[str], str] | None = None,
    log_dir: str | None = None,
    manager_http: str | None = None,
) -> list[ProcessSpec]:
    """What compute node ``node`` runs, in start order (the router first). ``system``
    overrides the model's system name; ``addresses`` as for :func:`resolve_endpoint`
    (a Redis URL whose host is a compute node's name or address is resolved too).
    ``metrics``: the ``HOST:PORT`` each RAP service (knowledge, runner, trust checkers)
    serves its metrics on, by process name; ``log_dir``: each writes its JSON lines
    log to ``<log_dir>/<name>.jsonl`` (``rap up`` gives both; none by default).
    ``manager_http``: the node that hosts knowledge also runs the system's adaptation
    manager, its dashboard on this ``HOST:PORT`` (``rap up`` gives one; none by default)."""

    def observed(name: str, argv: list[str]) -> str:
        address = metrics(name) if metrics is not None else ""
        if address:
            argv += ["--metrics", address]
        if log_dir is not None:
            argv += ["--log-file", str(PurePosixPath(log_dir) / f"{name}.jsonl")]
        return address

    plan = doc.plan
    if node not in plan.compute_nodes:
        raise KeyError(
            f"{doc.source}: compute node {node!r} is not in the model; its compute nodes "
            f"are: {', '.join(plan.compute_nodes)}"
        )
    sys_name = system or plan.system
    # RAP_COMPUTE_NODE: each runtime names its compute node in its status replies
    client = {CONFIG_ENV: paths.client_config, NODE_ENV: node}
    if plan.fabric.tls and paths.certs:
        client[CERTS_ENV] = paths.certs
    out = [
        ProcessSpec(
            "router",
            "router",
            (PYTHON, "-m", "rap_cli.router", "--config", paths.router_config),
            doc=f"the Zenoh router of compute node {node}",
        )
    ]
    if knowledge_node(plan) == node:
        kb = plan.knowledge
        argv = [PYTHON, "-m", "knowledge", "--system", sys_name, "--backend", kb.backend]
        if kb.backend in ("sqlite", "memcached", "kafka"):  # memcached: history and models
            argv += ["--sqlite-path", _rel(paths.data_dir, kb.path or "knowledge.sqlite3")]
        if kb.backend == "redis":
            argv += [
                "--redis-url",
                resolve_url(kb.url or "redis://127.0.0.1:6379/0", plan, addresses),
            ]
        elif kb.backend == "memcached":
            argv += [
                "--memcached-url",
                resolve_url(kb.url or "memcached://127.0.0.1:11211", plan, addresses),
            ]
        elif kb.backend == "kafka":
            argv += [
                "--kafka-url",
                resolve_url(kb.url or "kafka://127.0.0.1:9092", plan, addresses),
            ]
        if plan.fabric.tls:  # who may use which model (the service checks identities)
            from .acl import model_grants

            grants = model_grants(plan)
            if grants:
                argv += ["--model-grants", json.dumps(grants, sort_keys=True)]
        argv += ["--log-level", log_level]
        at = observed("knowledge", argv)
        out.append(ProcessSpec("knowledge", "knowledge", tuple(argv), client, "knowledge", at))
        if manager_http is not None:
            argv = [PYTHON, "-m", "adaptation_manager", "--system", sys_name]
            argv += ["--http", manager_http, "--log-level", log_level]
            about = f"the adaptation manager, its dashboard on http://{manager_http}/"
            out.append(ProcessSpec("manager", "manager", tuple(argv), client, about))
    if _has_runner(plan, node):
        argv = [PYTHON, "-m", "maplek_runner", paths.model, "--node", node]
        argv += ["--system", sys_name, "--log-level", log_level]
        names = ", ".join(n for n, c in plan.components_on(node).items() if c.module)
        at = observed("runner", argv)
        out.append(ProcessSpec("runner", "runner", tuple(argv), client, names, at))
    if plan.trust.node == node:
        for spec in plan.trust.specs:
            stem = PurePosixPath(spec).stem
            argv = [PYTHON, "-m", "trust_checker", _rel(paths.model_dir, spec)]
            argv += ["--fabric", sys_name, "--node", f"trust-{stem}", "--log-level", log_level]
            at = observed(f"trust-{stem}", argv)
            out.append(ProcessSpec(f"trust-{stem}", "trust", tuple(argv), client, spec, at))
    if any(
        p.bridge is not None and p.direction != "in-out"
        for c in plan.components_on(node).values()
        for p in c.ports.values()
    ):
        argv = [PYTHON, "-m", "rap_cli.bridges", paths.model, "--node", node]
        argv += ["--system", sys_name, "--log-level", log_level]
        at = observed("bridges", argv)
        about = "the bridges of its components' ports (docs/bridges.md)"
        out.append(ProcessSpec("bridges", "bridges", tuple(argv), client, about, at))
    for name, comp in plan.components_on(node).items():
        if not comp.run:
            continue
        subst = {"{system}": sys_name, "{model_dir}": paths.model_dir}
        argv = []
        for a in comp.run:
            if a == PYTHON:
                argv.append(PYTHON)
                continue
            for k, v in subst.items():
                a = a.replace(k, v)
            argv.append(a)
        out.append(ProcessSpec(name, "component", tuple(argv), client, comp.doc))
    if plan.fabric.tls:  # each process presents its own certificate: <node>.<process>
        out = [
            p
            if p.role == "router"
            else replace(p, env={**p.env, AS_ENV: process_identity(node, p.name)})
            for p in out
        ]
    return out

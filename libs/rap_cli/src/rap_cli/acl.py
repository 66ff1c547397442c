"""Identities and Zenoh access control, derived from the system model.

    grants = process_grants(plan)          # what each RAP process may do on the fabric
    conf["access_control"] = access_control(plan)   # a router's Zenoh ACL block

With ``fabric: {tls: true}`` every RAP process reaches its node's router over mutual TLS
and presents its own certificate (``rap certs``), whose common name is its identity:

- ``<node>.<process>`` for each process ``rap up`` runs on a compute node (``edge.runner``,
  ``edge.knowledge``, ``edge.manager``, ``robot.trust-lidar``, ``robot.robot`` for a
  component with ``run:``);
- ``<node>`` for the node's router (routers trust each other: each enforces the rules on
  its own clients);
- each name of ``fabric.operators`` (people and their tools: every verb, every key).

Every router carries the same rules for every identity, denies what no rule allows, and
refuses a link from a peer without a certificate signed by the model's CA. A process
may (ingress, at its router):

- **components** (the runner of a node acts for the components it hosts): publish on
  their declared outputs, their ``trace/<c>`` and ``log/<c>`` keys; subscribe to their
  declared inputs; read and write (the write stream, catch-up and durable queries) only
  their declared ``reads`` and ``writes`` knowledge keys and their snapshot
  (``admin/snapshot/<c>``); query the model store on the keys of their declared
  ``models`` (``kb/_models/<name>``: a query whether it reads or writes, so the knowledge
  service tells the two apart, from the signed caller and :func:`model_grants`); serve
  their ``admin/<c>/*`` verbs; declare the liveliness token ``alive/<c>``. A verdict
  key is the Legitimate stage's output, so only the identity that hosts it may publish
  one.
- **knowledge**: the whole ``kb/**`` space (it is the store), its log and token.
- **the adaptation manager**: subscribe to the whole system (it observes), query the
  ``status`` verb of every component, serve its ``trace`` verb.
- **a trust checker**: subscribe to the whole system, publish on ``trust/**``, serve its
  ``swap`` verb (which also checks that the caller is an operator).
- **a node's bridges** (``<node>.bridges``): publish on the keys of the ports whose
  messages come in from outside, subscribe to those whose messages go out, nothing else.
- everyone: watch and query liveliness.

Only operators may call admin verbs (other than the manager's status polls) or use
reserved knowledge keys (``_...``) other than the models granted to components. Routers
log every message they refuse with the identity that sent it (``rap_cli.router``).
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass, field
from typing import Any

from rap_schemas import MODELS_PREFIX, DeploymentPlan, keys
from rap_schemas.admin import snapshot_key

from .deploy import knowledge_node, process_identity

__all__ = [
    "ALL_MESSAGES",
    "Grant",
    "access_control",
    "model_grants",
    "process_grants",
    "process_identity",
]

ALL_MESSAGES = (
    "put",
    "delete",
    "declare_subscriber",
    "query",
    "reply",
    "declare_queryable",
    "liveliness_token",
    "declare_liveliness_subscriber",
    "liveliness_query",
)
"""Every message kind Zenoh's access control filters."""

MANAGER = "manager"
"""The adaptation manager's node name on the fabric (``adaptation_manager``)."""
KNOWLEDGE = "knowledge"
"""The knowledge service's node name on the fabric."""
RESERVED = "_"
"""Knowledge keys that start with it (the model store, ``_models/...``) are operators'
only, whatever a component's ``reads`` and ``writes`` say (its ``models`` grant it
models)."""


@dataclass(slots=True)
class Grant:
    """What one identity may send to its router, by message kind: key expressions."""

    identity: str
    kind: str
    """``router``, ``operator``, ``knowledge``, ``manager``, ``runner``, ``trust``,
    ``bridges`` or ``component``."""
    node: str = ""
    components: tuple[str, ...] = ()
    """The components it acts for."""
    may: dict[str, list[str]] = field(default_factory=dict)

    def allow(self, messages: Iterable[str], *key_exprs: str) -> None:
        for m in messages:
            have = self.may.setdefault(m, [])
            for k in key_exprs:
                if k not in have:
                    have.append(k)


def _runner_components(plan: DeploymentPlan, node: str) -> list[str]:
    return [
        n
        for n, c in plan.components_on(node).items()
        if c.module is not None and not c.external and not c.run
    ]


def _component_keys(plan: DeploymentPlan, grant: Grant, name: str) -> None:
    """Allow ``grant`` what component ``name`` of ``plan`` needs."""
    from .generate.wiring import channels

    s = plan.system
    comp = plan.components[name]
    chans = channels(plan)
    for port_name, port in comp.ports.items():
        ch = chans.get((name, port_name))
        if ch is None:
            continue
        key = keys.data(s, ch.key) if ch.family == "data" else keys.event(s, ch.key)
        if port.direction in ("out", "in-out"):
            grant.allow(["put"], key)
            if ch.knowledge:
                grant.allow(["put", "query"], keys.kb(s, ch.knowledge))
        if port.direction in ("in", "in-out"):
            grant.allow(["declare_subscriber"], key)
            if ch.knowledge:
                grant.allow(["declare_subscriber", "query"], keys.kb(s, ch.knowledge))
    for k in comp.reads:
        if not k.startswith(RESERVED):
            grant.allow(["declare_subscriber", "query"], keys.kb(s, k))
    for k in comp.writes:
        if not k.startswith(RESERVED):
            grant.allow(["put", "declare_subscriber", "query"], keys.kb(s, k))
    for model in comp.models:  # read or write: a query (the service tells them apart)
        grant.allow(["query"], keys.kb(s, f"{MODELS_PREFIX}/{model}"))
    grant.allow(["put", "declare_subscriber", "query"], keys.kb(s, snapshot_key(name)))
    grant.allow(["put"], keys.trace(s, name), keys.log(s, name))
    grant.allow(["declare_queryable", "reply"], keys.pattern(s, keys.Kind.ADMIN, f"{name}/*"))
    grant.allow(["liveliness_token"], keys.alive(s, name))


def _everyone(plan: DeploymentPlan, grant: Grant) -> None:
    alive = keys.pattern(plan.system, keys.Kind.ALIVE, "*")
    grant.allow(["declare_liveliness_subscriber", "liveliness_query"], alive)


def process_grants(plan: DeploymentPlan, *, manager: bool = True) -> dict[str, Grant]:
    """Every identity of ``plan`` and what it may send: the routers, each RAP process of
    each compute node (as ``rap up`` runs them; ``manager``: with the adaptation
    manager beside knowledge) and the operators."""
    from .bridges import PROCESS, bridges_on

    s = plan.system
    everything = keys.system_pattern(s)
    out: dict[str, Grant] = {}
    for node in plan.compute_nodes:
        out[node] = Grant(node, "router", node, may={m: ["**"] for m in ALL_MESSAGES})
    kb_node = knowledge_node(plan)
    for node in plan.compute_nodes:
        if kb_node == node:
            g = Grant(process_identity(node, "knowledge"), "knowledge", node)
            kb_all = keys.pattern(s, keys.Kind.KB)
            g.allow(["put", "declare_subscriber", "declare_queryable", "reply", "query"], kb_all)
            g.allow(["put"], keys.log(s, KNOWLEDGE))
            g.allow(["liveliness_token"], keys.alive(s, KNOWLEDGE))
            out[g.identity] = g
            if manager:
                g = Grant(process_identity(node, "manager"), "manager", node)
                g.allow(["declare_subscriber"], everything)
                g.allow(["query"], keys.pattern(s, keys.Kind.ADMIN, "*/status"))
                g.allow(
                    ["declare_queryable", "reply"], keys.pattern(s, keys.Kind.ADMIN, f"{MANAGER}/*")
                )
                g.allow(["put"], keys.log(s, MANAGER))
                g.allow(["liveliness_token"], keys.alive(s, MANAGER))
                out[g.identity] = g
        hosted = _runner_components(plan, node)
        if hosted:
            g = Grant(process_identity(node, "runner"), "runner", node, tuple(hosted))
            for c in hosted:
                _component_keys(plan, g, c)
            g.allow(["put"], keys.log(s, f"runner-{node}"))  # the runner's own log lines
            out[g.identity] = g
        if plan.trust.node == node:
            from pathlib import PurePosixPath

            for spec in plan.trust.specs:
                name = f"trust-{PurePosixPath(spec).stem}"
                g = Grant(process_identity(node, name), "trust", node)
                g.allow(["declare_subscriber"], everything)
                g.allow(["put"], keys.pattern(s, keys.Kind.TRUST), keys.log(s, name))
                g.allow(
                    ["declare_queryable", "reply"], keys.pattern(s, keys.Kind.ADMIN, f"{name}/*")
                )
                g.allow(["liveliness_token"], keys.alive(s, name))
                out[g.identity] = g
        bridged = bridges_on(plan, node)
        if bridged:
            g = Grant(process_identity(node, PROCESS), "bridges", node)
            for b in bridged:  # in: it publishes what comes from outside; out: it listens
                g.allow(["put"] if b.direction == "in" else ["declare_subscriber"], b.key)
            g.allow(["put"], keys.log(s, f"{PROCESS}-{node}"))
            out[g.identity] = g
        for name, comp in plan.components_on(node).items():
            if comp.run:
                g = Grant(process_identity(node, name), "component", node, (name,))
                _component_keys(plan, g, name)
                out[g.identity] = g
    for name in plan.fabric.operators:
        out[name] = Grant(name, "operator", may={m: [everything] for m in ALL_MESSAGES})
    for g in out.values():
        if g.kind not in ("router", "operator"):
            _everyone(plan, g)
    return out


def model_grants(plan: DeploymentPlan) -> dict[str, dict[str, str]]:
    """Identity -> model name -> ``read`` or ``write``: the models of the model store
    each process may use, from its components' ``models`` (a runner's: those of every
    component it hosts, ``write`` winning). The knowledge service takes a model request
    from these identities and the operators only (``--model-grants``)."""
    out: dict[str, dict[str, str]] = {}
    for g in process_grants(plan, manager=False).values():
        for name in g.components:
            for model, access in plan.components[name].models.items():
                have = out.setdefault(g.identity, {})
                if have.get(model) != "write":
                    have[model] = access
    return out


def access_control(plan: DeploymentPlan, *, manager: bool = True) -> dict[str, Any]:
    """The ``access_control`` block of a router's Zenoh config for ``plan``: deny by
    default; each identity (matched by its certificate's common name) may send what
    :func:`process_grants` says; anything may go out to an authenticated peer (what it
    receives is bounded by what it may subscribe to and query)."""
    rules: list[dict[str, Any]] = [
        {
            "id": "out",
            "messages": list(ALL_MESSAGES),
            "flows": ["egress"],
            "permission": "allow",
            "key_exprs": ["**"],
        }
    ]
    subjects: list[dict[str, Any]] = []
    policies: list[dict[str, Any]] = []
    for i, g in enumerate(process_grants(plan, manager=manager).values()):
        subject = f"s{i}"
        subjects.append({"id": subject, "cert_common_names": [g.identity]})
        ids = ["out"]
        # one rule per set of key expressions (Zenoh's rules give messages x keys)
        by_keys: dict[tuple[str, ...], list[str]] = {}
        for message, allowed in g.may.items():
            by_keys.setdefault(tuple(allowed), []).append(message)
        for j, (exprs, messages) in enumerate(by_keys.items()):
            rid = f"r{i}.{j}"
            rules.append(
                {
                    "id": rid,
                    "messages": messages,
                    "flows": ["ingress"],
                    "permission": "allow",
                    "key_exprs": list(exprs),
                }
            )
            ids.append(rid)
        policies.append({"id": f"p{i}", "rules": ids, "subjects": [subject]})
    return {
        "enabled": True,
        "default_permission": "deny",
        "rules": rules,
        "subjects": subjects,
        "policies": policies,
    }

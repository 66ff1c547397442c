"""What the fuzzer aims at: every subscriber and queryable of the running loop.

Targets are derived from the loop's Nodes (``Node.routes``: each data, event and trust
route key, checked against ``rap_sdk.cycles.Topology``), from what the nodes did in a
warm-up cycle (the knowledge keys they read and wrote, from their ``KnowledgeAccess``
trace records), and from the services the run starts: the knowledge service (the write
stream of every key, its queryable on ``rap/<system>/kb/**``) and each trust checker
(the system's trace records and events, its ``admin/<node>/swap`` queryable).
"""

from __future__ import annotations

from collections import Counter, deque
from collections.abc import Iterable, Sequence
from dataclasses import dataclass, field
from typing import Any, Literal

from rap_schemas import KbRecord, KnowledgeAccess, StageTrace, TrustSpecUpdate, keys
from rap_sdk import Node
from rap_sdk.cycles import Topology

__all__ = ["EXTRA_KB_KEYS", "RECENT", "REQUEST", "Target", "derive", "kb_keys_of"]

RECENT = 32
"""Samples remembered per target (for the report of a crash)."""
EXTRA_KB_KEYS = ("fuzz/other", "_models/fuzz")
"""Knowledge keys no node uses: the write stream of a key nobody replicates, and one in
the model store's reserved space."""
REQUEST = "rap.KbRequest"
"""The wire type of a knowledge query (plain msgpack, no envelope)."""


@dataclass
class Target:
    name: str
    kind: Literal["put", "query"]
    keys: list[str]
    """Concrete keys the samples go to, in turn."""
    wire_type: str
    """The type of a valid sample (``rap.KbRequest``: a plain knowledge request)."""
    subscribers: list[str]
    """Who reads it: ``node`` or ``process`` names, with the key expression they use."""
    sealed: bool = True
    alt_types: list[str] = field(default_factory=list)
    """Other wire types a valid sample may have (trace records: knowledge accesses)."""
    sent: int = 0
    bytes: int = 0
    by_mutation: Counter[str] = field(default_factory=Counter)
    replies: Counter[str] = field(default_factory=Counter)
    reply_details: Counter[str] = field(default_factory=Counter)
    """Queries: the reasons of the refusals and error replies."""
    """Queries: how they were answered (``ok``, ``error-reply``, ``timeout``, ...)."""
    recent: deque[tuple[float, str, str, bytes]] = field(
        default_factory=lambda: deque(maxlen=RECENT)
    )
    """(wall time, mutation, key, payload head) of the last samples sent."""

    oddities: list[dict[str, Any]] = field(default_factory=list)
    """Queries whose answer was not what the protocol says (the first few of each kind):
    the request and the reply, in hex."""

    def oddity(self, what: str, key: str, request: bytes, reply: bytes) -> None:
        if sum(o["what"] == what for o in self.oddities) < 3:
            self.oddities.append(
                {
                    "what": what,
                    "key": key,
                    "request_len": len(request),
                    "request_hex": request[:8192].hex(),
                    "reply_len": len(reply),
                    "reply_head_hex": bytes(reply[:512]).hex(),
                }
            )

    def remember(self, t: float, mutation: str, key: str, payload: bytes) -> None:
        self.recent.append((t, mutation, key, payload[:65536]))

    def summary(self) -> dict[str, Any]:
        out: dict[str, Any] = {
            "kind": self.kind,
            "keys": self.keys,
            "wire_type": self.wire_type,
            "subscribers": self.subscribers,
            "sent": self.sent,
            "mib": round(self.bytes / 2**20, 1),
            "by_mutation": dict(sorted(self.by_mutation.items())),
        }
        if self.kind == "query":
            out["replies"] = dict(sorted(self.replies.items()))
            out["refusals"] = dict(self.reply_details.most_common(30))
            out["oddities"] = self.oddities
        return out


def derive(
    *,
    system: str,
    nodes: Sequence[Node],
    hosts: dict[str, str],
    kb_access: Iterable[KnowledgeAccess],
    checkers: Sequence[str],
    knowledge: str = "knowledge",
) -> list[Target]:
    """The targets of a loop of ``nodes`` (``hosts``: node -> process name) with the
    knowledge service process ``knowledge`` and trust checker nodes ``checkers`` (each
    reads ``rap/<system>/**``). ``kb_access``: the nodes' knowledge access records."""
    every = [f"{c} (rap/{system}/**)" for c in checkers]
    targets: dict[str, Target] = {}
    for node in nodes:
        for route in node.routes:
            key = route.key(system)
            t = targets.get(key)
            if t is None:
                name = key.removeprefix(f"rap/{system}/")
                t = targets[key] = Target(name, "put", [key], route.msg_type.TYPE, [*every])
            elif t.wire_type != route.msg_type.TYPE:
                t.wire_type = route.msg_type.TYPE  # two routes, two types: either is tested
            t.subscribers.insert(0, f"{node.name}@{hosts.get(node.name, '?')} ({route.kind})")
    topo = Topology.of(nodes, system=system)
    missing = set(topo.subscribers) - set(targets)
    if missing:  # Topology is derived from the same routes: a mismatch is a bug here
        raise RuntimeError(f"topology keys without a target: {sorted(missing)}")

    readers: dict[str, set[str]] = {}
    for acc in kb_access:
        readers.setdefault(acc.key, set())
        if acc.op == "read":
            readers[acc.key].add(acc.node)
    kb_keys = sorted(readers)
    for k in [*kb_keys, *EXTRA_KB_KEYS]:
        subs = [f"{knowledge} (rap/{system}/kb/**)"]
        subs += [f"{n}@{hosts.get(n, '?')} replica" for n in sorted(readers.get(k, ()))]
        key = keys.kb(system, k)
        targets[key] = Target(f"kb/{k}", "put", [key], KbRecord.TYPE, subs + every)

    node_names = [n.name for n in nodes]
    trace_keys = [keys.trace(system, n) for n in node_names]
    targets["trace"] = Target(
        "trace/*", "put", trace_keys, StageTrace.TYPE, [*every], alt_types=[KnowledgeAccess.TYPE]
    )

    query_keys = [keys.kb(system, k) for k in [*kb_keys, "_keys", *EXTRA_KB_KEYS]]
    targets["kb?"] = Target(
        "kb/** (queries)",
        "query",
        query_keys,
        REQUEST,
        [f"{knowledge} (queryable rap/{system}/kb/**)"],
        sealed=False,
    )
    for c in checkers:
        key = keys.admin(system, c, "swap")
        targets[key] = Target(
            f"admin/{c}/swap (queries)", "query", [key], TrustSpecUpdate.TYPE, [f"{c} (queryable)"]
        )
    return list(targets.values())


def kb_keys_of(targets: Sequence[Target]) -> list[str]:
    """The knowledge keys the loop uses (the kb targets, without the extra ones)."""
    out = []
    for t in targets:
        if t.kind == "put" and t.wire_type == KbRecord.TYPE:
            k = t.name.removeprefix("kb/")
            if k not in EXTRA_KB_KEYS:
                out.append(k)
    return out

"""The Prometheus collectors read what runtimes, gates, the knowledge service and the
trust checker count, and say it in the text format a scraper reads: real handler calls
on a fabric, the registry's output parsed back."""

from __future__ import annotations

import urllib.request
from dataclasses import dataclass
from typing import Any

import anyio
import pytest
from prometheus_client import CollectorRegistry, generate_latest
from prometheus_client.parser import text_string_to_metric_families
from rap_schemas import Message, PlanProposal, keys
from rap_sdk import Context, Node
from rap_sdk.gate import ApprovalGate, legitimate, propose
from rap_sdk.metrics import (
    METRICS,
    KnowledgeServiceCollector,
    RuntimeCollector,
    TrustCollector,
    VerdictCounts,
    parse_address,
    serve_metrics,
    start_metrics,
)
from rap_sdk.testing import Harness

pytestmark = pytest.mark.anyio

S = "met"


class Go(Message, frozen=True):
    TYPE = "test.Go/1"

    n: int


class Dock(Message, frozen=True):
    TYPE = "test.Dock/1"

    speed: float


def samples(registry: CollectorRegistry) -> dict[tuple[str, frozenset[tuple[str, str]]], float]:
    """Every sample of the registry's text output: (name, labels) -> value."""
    text = generate_latest(registry).decode()
    out = {}
    for family in text_string_to_metric_families(text):
        for s in family.samples:
            out[(s.name, frozenset(s.labels.items()))] = s.value
    return out


def value(found: dict[Any, float], name: str, **labels: str) -> float:
    want = set(labels.items())
    hits = [v for (n, ls), v in found.items() if n == name and want <= ls]
    assert len(hits) == 1, (
        f"{name}{labels}: {len(hits)} samples; names: {sorted({n for n, _ in found})}"
    )
    return hits[0]


def registry_of(*collectors: Any) -> CollectorRegistry:
    reg = CollectorRegistry(auto_describe=False)
    for c in collectors:
        reg.register(c)
    return reg


async def test_component_counters_latency_and_inbox_at_scrape_time() -> None:
    mon = Node("mon", stage="monitor")
    ana = Node("ana", stage="analyse")

    @mon.on_event("go")
    async def go(ctx: Context, msg: Go) -> None:
        await ctx.kb.write("last", msg.n)
        if msg.n % 4 == 3:
            raise RuntimeError("every fourth call fails")
        await ctx.emit("next")

    @ana.on_event("next")
    async def nxt(ctx: Context) -> None:
        assert await ctx.kb.read("last", int) >= 0  # the version its trigger carries

    async with Harness(system=S) as h:
        group = await h.start(mon, ana)
        reg = registry_of(RuntimeCollector(lambda: group.runtimes, system=S, compute_node="cn1"))
        before = samples(reg)
        assert value(before, "rap_handled_total", component="mon") == 0
        for i in range(8):
            await h.emit("go", Go(n=i))
        await h.publish_raw(keys.event(S, "go"), b"\x00not an envelope")
        await h.wait_for(lambda r: len([t for t in h.traces("ana") if t.ended]) == 6)
        await h.wait_for(lambda r: len(h.rejections("mon")) == 1)
        found = samples(reg)
    mine = {"system": S, "compute_node": "cn1", "component": "mon", "stage": "monitor"}
    assert value(found, "rap_received_total", **mine) == 9  # the refused one too
    assert value(found, "rap_handled_total", **mine) == 6
    assert value(found, "rap_failed_total", **mine) == 2
    assert value(found, "rap_rejected_total", **mine) == 1
    assert value(found, "rap_sent_total", **mine) == 6
    assert value(found, "rap_handled_total", component="ana", stage="analyse") == 6
    # the rejection by kind of reason (the reason's specifics stripped)
    reasons = [ls for (n, ls), v in found.items() if n == "rap_rejections_total" and v == 1]
    assert len(reasons) == 1
    assert ("component", "mon") in reasons[0]
    # the histogram: every call in some bucket, +Inf holds them all, a sum of seconds
    assert value(found, "rap_handler_latency_seconds_count", **mine) == 8
    assert value(found, "rap_handler_latency_seconds_bucket", le="+Inf", **mine) == 8
    assert 0 < value(found, "rap_handler_latency_seconds_sum", **mine) < 8
    assert value(found, "rap_inbox_depth", **mine) == 0
    assert value(found, "rap_last_call_failed", **mine) == 1  # n=7 failed, last
    assert value(found, "rap_last_call_timestamp_seconds", **mine) > 1.6e9
    # cycles per stage: the calls of that stage's components, returned or raised
    assert value(found, "rap_cycles_total", stage="monitor") == 8
    assert value(found, "rap_cycles_total", stage="analyse") == 6
    # knowledge accesses of its handlers
    assert value(found, "rap_kb_writes_total", **mine) == 8
    assert value(found, "rap_kb_reads_total", **mine) == 0
    assert value(found, "rap_kb_reads_total", component="ana", stage="analyse") == 6
    # the knowledge client of each running component is there
    assert value(found, "rap_knowledge_waits_total", **mine) == 0


async def test_plan_outcomes_of_the_gate() -> None:
    planner = Node("planner", stage="plan")
    judge = Node("legitimate", stage="legitimate")
    executor = Node("executor", stage="execute")
    gate = ApprovalGate(legitimators={"legitimate"}, max_age=5.0)

    @planner.on_event("want")
    async def plan(ctx: Context, want: Dock) -> None:
        await propose(ctx, want)

    @legitimate(judge)
    async def check(ctx: Context, proposal: PlanProposal[Dock]) -> str | None:
        return None if proposal.plan.speed <= 0.2 else "too fast"

    @gate.on_approved(executor)
    async def act(ctx: Context, proposal: PlanProposal[Dock]) -> None:
        await ctx.publish("base/cmd", proposal.plan)

    async with Harness(system=S) as h:
        group = await h.start(planner, judge, executor)
        reg = registry_of(RuntimeCollector(group.runtimes, system=S))
        for speed in (0.1, 0.5, 0.2):
            await h.emit("want", Dock(speed=speed))
        await h.wait_for(lambda r: gate.stats.approved + gate.stats.not_approved == 3)
        found = samples(reg)
    ex = {"component": "executor", "stage": "execute"}
    assert value(found, "rap_plans_executed_total", **ex) == 2
    assert value(found, "rap_plans_rejected_total", **ex) == 1
    assert value(found, "rap_plans_refused_total", reason="stale", **ex) == 0
    # no gate, no plan metrics for the others
    assert not [
        k for k in found if k[0] == "rap_plans_executed_total" and ("component", "planner") in k[1]
    ]


@dataclass
class _ServiceStats:
    stream_applied: int = 5
    stream_rejected: int = 2
    stream_failed: int = 1
    queries: int = 9
    query_errors: int = 3


@dataclass
class _Rejections:
    by_reason: dict[str, int]


@dataclass
class _Service:
    stats: _ServiceStats
    rejections: _Rejections


def test_knowledge_service_counters() -> None:
    svc = _Service(_ServiceStats(), _Rejections({"record for X arrived on Y": 2}))
    found = samples(registry_of(KnowledgeServiceCollector(svc, system=S, compute_node="edge")))
    assert value(found, "rap_knowledge_writes_total", result="stored", compute_node="edge") == 5
    assert value(found, "rap_knowledge_writes_total", result="refused") == 2
    assert value(found, "rap_knowledge_writes_total", result="failed") == 1
    assert value(found, "rap_knowledge_requests_total") == 9
    assert value(found, "rap_knowledge_request_errors_total") == 3
    assert value(found, "rap_knowledge_service_rejections_total") == 2


@dataclass
class _Out:
    stream: str
    value: object


async def test_trust_verdicts_per_stream_true_and_false() -> None:
    counts = VerdictCounts()
    await counts.outputs([_Out("safe", True), _Out("speed", 3), _Out("safe", False)])
    await counts.outputs([_Out("safe", True), _Out("near", False)])
    found = samples(registry_of(TrustCollector(counts, lambda: None, system=S, node="tc")))
    assert value(found, "rap_trust_verdicts_total", stream="safe", value="true") == 2
    assert value(found, "rap_trust_verdicts_total", stream="safe", value="false") == 1
    assert value(found, "rap_trust_verdicts_total", stream="near", value="false") == 1
    assert not [k for k in found if ("stream", "speed") in k[1]]  # not a Bool: not a verdict


def test_every_metric_has_help_and_the_rap_prefix() -> None:
    for name, text in METRICS.items():
        assert name.startswith("rap_"), name
        assert len(text) > 20, name


def test_parse_address() -> None:
    assert parse_address("127.0.0.1:9464") == ("127.0.0.1", 9464)
    assert parse_address("[::1]:0") == ("::1", 0)
    for bad in ("9464", "host:", ":9464", "h:70000", "h:x"):
        with pytest.raises(ValueError, match="HOST:PORT"):
            parse_address(bad)


async def test_served_over_http_and_a_taken_port_is_not_fatal() -> None:
    counts = VerdictCounts()
    await counts.outputs([_Out("safe", True)])
    reg = registry_of(TrustCollector(counts, lambda: None, system=S, node="tc"))
    with serve_metrics(reg, "127.0.0.1", 0) as server:

        def get() -> str:
            with urllib.request.urlopen(server.url, timeout=5) as resp:
                return str(resp.read().decode())

        text = await anyio.to_thread.run_sync(get)
        assert 'rap_trust_verdicts_total{checker="tc",compute_node="",stream="safe",' in text
        # a second server on the same port: logged, no metrics, the service goes on
        taken = start_metrics(f"127.0.0.1:{server.port}", [], what="test")
        assert taken is None

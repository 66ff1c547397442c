"""Prometheus metrics of RAP processes, read from the counters they keep anyway.

    registry = CollectorRegistry()                       # never the global default one
    registry.register(RuntimeCollector(lambda: group.runtimes, system="demo",
                                       compute_node="robot"))
    with serve_metrics(registry, "127.0.0.1", 9464):     # GET /metrics
        ...

Every collector here reads at scrape time what the runtime, the gate, the knowledge
client and service, or the trust checker already count (``NodeStats``, rejections by
reason, the latency histogram, ...): a handler call pays nothing more for being
observed. Scrapes run on the HTTP server's thread; they only read (copies of) counters
that the event loop's thread writes.

Every metric is named ``rap_...`` and labelled with ``system``, ``compute_node`` (""
when not known), and for a component ``component`` and ``stage`` (its MAPLE-K stage, ""
for none). :data:`METRICS` lists them with their help text.
"""

from __future__ import annotations

import contextlib
import logging
from collections.abc import Callable, Iterable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

from prometheus_client.core import (
    CounterMetricFamily,
    GaugeMetricFamily,
    HistogramMetricFamily,
    Metric,
)
from prometheus_client.registry import Collector, CollectorRegistry

from .errors import LifecycleError
from .gate import ApprovalGate

if TYPE_CHECKING:
    from .runtime import NodeRuntime

__all__ = [
    "METRICS",
    "KnowledgeServiceCollector",
    "MetricsServer",
    "RuntimeCollector",
    "TrustCollector",
    "VerdictCounts",
    "check_metrics_option",
    "gates_of",
    "parse_address",
    "serve_metrics",
    "start_metrics",
]

log = logging.getLogger(__name__)

_COMPONENT = ("system", "compute_node", "component", "stage")

METRICS: Mapping[str, str] = {
    # components (RuntimeCollector)
    "rap_received_total": "Samples a component took from its inboxes or by direct dispatch.",
    "rap_handled_total": "Handler calls of a component that returned normally.",
    "rap_failed_total": "Handler calls of a component that raised (logged, the node goes on).",
    "rap_rejected_total": "Samples a component refused (undecodable, wrong type, over a limit).",
    "rap_rejections_total": "Samples a component refused, by kind of reason.",
    "rap_sent_total": "Samples a component emitted or published.",
    "rap_dropped_total": "Samples a component's full inboxes dropped (it is slower than its "
    "input).",
    "rap_send_timeouts_total": "Sends of a component that a local node's full inbox did not "
    "take in time.",
    "rap_records_lost_total": "Trace or rejection records of a component that could not be "
    "published.",
    "rap_kb_reads_total": "Knowledge reads of a component's handlers.",
    "rap_kb_writes_total": "Knowledge writes and deletes of a component's handlers.",
    "rap_ticks_total": "Calls of a component's periodic handlers (@node.every).",
    "rap_ticks_skipped_total": "Ticks of a component's periodic handlers skipped because "
    "a call overran its period.",
    "rap_inbox_depth": "Samples queued in a component's inboxes now (all routes).",
    "rap_handler_latency_seconds": "Seconds a component's handler calls took.",
    "rap_last_call_timestamp_seconds": "When a component's last handler call ended (UTC, "
    "seconds; 0: none yet).",
    "rap_last_call_failed": "1 when a component's last handler call raised, else 0.",
    "rap_cycles_total": "Handler calls (returned or raised) of the components of one MAPLE-K "
    "stage in this process: each is one pass of that stage in a loop cycle.",
    "rap_knowledge_waits_total": "Knowledge reads of a component that waited for the version "
    "their trigger promised.",
    "rap_knowledge_catch_ups_total": "Times a component's knowledge replicas all caught up "
    "because the knowledge service came back.",
    "rap_knowledge_refused_total": "Knowledge write records a component's replicas refused.",
    "rap_plans_executed_total": "Approved plans an execute component's gate handed to its handler.",
    "rap_plans_rejected_total": "Plans a legitimator rejected, as seen by an execute "
    "component's gate.",
    "rap_plans_refused_total": "Approved plans an execute component's gate refused, by reason "
    "(stale, future, replayed, superseded, vetoed, malformed, unknown_legitimator).",
    "rap_trust_guard_verdicts_total": "Trust-checker verdicts an execute component's trust "
    "guard took.",
    "rap_trust_guard_closed_total": "Times an execute component's trust guard closed on a "
    "false verdict.",
    # the knowledge service (KnowledgeServiceCollector)
    "rap_knowledge_writes_total": "Write records the knowledge service took from the write "
    "stream, by result (stored, refused, failed: the store failed).",
    "rap_knowledge_requests_total": "Requests (reads, durable writes, history, models) the "
    "knowledge service answered.",
    "rap_knowledge_request_errors_total": "Requests the knowledge service answered with an error.",
    "rap_knowledge_service_rejections_total": "Records and requests the knowledge service "
    "refused, by kind of reason.",
    # the trust checker (TrustCollector)
    "rap_trust_verdicts_total": "Boolean outputs of a trust checker, by stream and value "
    "(true, false).",
    "rap_trust_ticks_total": "Ticks a trust checker took.",
    "rap_trust_input_errors_total": "Inputs a trust checker's spec refused.",
    "rap_trust_eval_errors_total": "Ticks a trust checker could not compute.",
    "rap_trust_rejected_total": "Payloads a trust checker's transports refused.",
}
"""Every metric RAP exports, with its help text."""


def _counter(name: str, labels: Sequence[str]) -> CounterMetricFamily:
    # prometheus_client adds the _total suffix itself
    return CounterMetricFamily(name.removesuffix("_total"), METRICS[name], labels=labels)


def _gauge(name: str, labels: Sequence[str]) -> GaugeMetricFamily:
    return GaugeMetricFamily(name, METRICS[name], labels=labels)


def _copy(counts: Mapping[str, int]) -> dict[str, int]:
    """A copy of a dict the event loop's thread may be growing (a scrape's thread reads)."""
    for _ in range(8):
        with contextlib.suppress(RuntimeError):  # "changed size during iteration"
            return dict(counts)
    return {}


_REFUSED = (
    "unknown_legitimator",
    "malformed",
    "stale",
    "future",
    "replayed",
    "superseded",
    "vetoed",
)


def gates_of(rt: NodeRuntime) -> list[ApprovalGate]:
    """The :class:`~rap_sdk.gate.ApprovalGate` objects whose execution handlers a node
    runs (found in the closures of its routes: ``gate.on_approved(node)`` registers a
    handler that refers to its gate)."""
    found: list[ApprovalGate] = []
    for route in rt.node.routes:
        for cell in getattr(route.fn, "__closure__", None) or ():
            with contextlib.suppress(ValueError):  # an empty cell
                value = cell.cell_contents
                if isinstance(value, ApprovalGate) and value not in found:
                    found.append(value)
    return found


Runtimes = Callable[[], Iterable["NodeRuntime"]] | Iterable["NodeRuntime"]


class RuntimeCollector(Collector):
    """The metrics of a group of node runtimes (a runner's components), read at scrape
    time. ``runtimes``: the runtimes, or a function returning the current ones (a swap
    may replace them). ``compute_node``: the label when a runtime does not say its own."""

    def __init__(self, runtimes: Runtimes, *, system: str, compute_node: str = "") -> None:
        self._runtimes = runtimes
        self.system = system
        self.compute_node = compute_node
        self._gates: dict[int, tuple[tuple[Any, ...], list[ApprovalGate]]] = {}
        """id(runtime) -> (its route functions, its gates), found once per set of routes."""

    def _current(self) -> list[NodeRuntime]:
        rts = self._runtimes() if callable(self._runtimes) else self._runtimes
        return list(rts)

    def _gates_of(self, rt: NodeRuntime) -> list[ApprovalGate]:
        fns = tuple(r.fn for r in rt.node.routes)
        cached = self._gates.get(id(rt))
        if cached is None or cached[0] != fns:
            cached = (fns, gates_of(rt))
            self._gates[id(rt)] = cached
        return cached[1]

    def describe(self) -> Iterable[Metric]:
        return []  # collected at scrape time only (no work at registration)

    def collect(self) -> Iterator[Metric]:
        counters = {
            name: _counter(f"rap_{name}_total", _COMPONENT)
            for name in (
                "received",
                "handled",
                "failed",
                "rejected",
                "sent",
                "dropped",
                "send_timeouts",
                "records_lost",
                "kb_reads",
                "kb_writes",
                "ticks",
                "ticks_skipped",
            )
        }
        reasons = _counter("rap_rejections_total", (*_COMPONENT, "reason"))
        depth = _gauge("rap_inbox_depth", _COMPONENT)
        latency = HistogramMetricFamily(
            "rap_handler_latency_seconds",
            METRICS["rap_handler_latency_seconds"],
            labels=_COMPONENT,
        )
        last_call = _gauge("rap_last_call_timestamp_seconds", _COMPONENT)
        last_failed = _gauge("rap_last_call_failed", _COMPONENT)
        cycles = _counter("rap_cycles_total", ("system", "compute_node", "stage"))
        kb_waits = _counter("rap_knowledge_waits_total", _COMPONENT)
        kb_catch_ups = _counter("rap_knowledge_catch_ups_total", _COMPONENT)
        kb_refused = _counter("rap_knowledge_refused_total", _COMPONENT)
        executed = _counter("rap_plans_executed_total", _COMPONENT)
        rejected = _counter("rap_plans_rejected_total", _COMPONENT)
        refused = _counter("rap_plans_refused_total", (*_COMPONENT, "reason"))
        guard_verdicts = _counter("rap_trust_guard_verdicts_total", _COMPONENT)
        guard_closed = _counter("rap_trust_guard_closed_total", _COMPONENT)
        per_stage: dict[tuple[str, str], int] = {}
        for rt in self._current():
            node = rt.node
            stage = node.stage.value if node.stage is not None else ""
            cn = getattr(rt, "compute_node", "") or self.compute_node
            labels = [self.system, cn, node.name, stage]
            s = rt.stats
            for name, family in counters.items():
                family.add_metric(labels, getattr(s, name))
            for reason, n in sorted(_copy(rt.rejections.by_reason).items()):
                reasons.add_metric([*labels, reason], n)
            depth.add_metric(labels, rt.inbox_depth)
            lat = rt.latency
            buckets = lat.cumulative()
            latency.add_metric(labels, buckets, lat.sum)
            last_call.add_metric(labels, rt.last_call / 1e9)
            last_failed.add_metric(labels, 1.0 if rt.last_failed else 0.0)
            key = (cn, stage)
            per_stage[key] = per_stage.get(key, 0) + s.handled + s.failed
            try:
                kb = rt.knowledge
            except LifecycleError:  # not running (yet, or any more)
                kb = None
            if kb is not None:
                kb_waits.add_metric(labels, kb.waits)
                kb_catch_ups.add_metric(labels, kb.catch_ups)
                kb_refused.add_metric(labels, kb.rejections.total)
            for gate in self._gates_of(rt):
                g = gate.stats
                executed.add_metric(labels, g.approved)
                rejected.add_metric(labels, g.not_approved)
                for reason in _REFUSED:
                    refused.add_metric([*labels, reason], getattr(g, reason))
                if gate.guard is not None:
                    guard_verdicts.add_metric(labels, gate.guard.stats.verdicts)
                    guard_closed.add_metric(labels, gate.guard.stats.closed)
        for (cn, stage), n in sorted(per_stage.items()):
            cycles.add_metric([self.system, cn, stage], n)
        yield from counters.values()
        yield from (reasons, depth, latency, last_call, last_failed, cycles)
        yield from (kb_waits, kb_catch_ups, kb_refused)
        yield from (executed, rejected, refused, guard_verdicts, guard_closed)


class KnowledgeServiceCollector(Collector):
    """The knowledge service's counters (``knowledge.KnowledgeService``: its ``stats``
    and ``rejections``), read at scrape time."""

    def __init__(self, service: Any, *, system: str, compute_node: str = "") -> None:
        self._service = service
        self._labels = [system, compute_node]

    def describe(self) -> Iterable[Metric]:
        return []

    def collect(self) -> Iterator[Metric]:
        labels = ("system", "compute_node")
        s = self._service.stats
        writes = _counter("rap_knowledge_writes_total", (*labels, "result"))
        writes.add_metric([*self._labels, "stored"], s.stream_applied)
        writes.add_metric([*self._labels, "refused"], s.stream_rejected)
        writes.add_metric([*self._labels, "failed"], s.stream_failed)
        requests = _counter("rap_knowledge_requests_total", labels)
        requests.add_metric(self._labels, s.queries)
        errors = _counter("rap_knowledge_request_errors_total", labels)
        errors.add_metric(self._labels, s.query_errors)
        reasons = _counter("rap_knowledge_service_rejections_total", (*labels, "reason"))
        for reason, n in sorted(_copy(self._service.rejections.by_reason).items()):
            reasons.add_metric([*self._labels, reason], n)
        yield from (writes, requests, errors, reasons)


@dataclass(slots=True)
class VerdictCounts:
    """A trust checker's sink that counts its Boolean outputs per stream, true and
    false (give it to the checker's session among its sinks)."""

    true: dict[str, int] = field(default_factory=dict)
    false: dict[str, int] = field(default_factory=dict)

    async def outputs(self, outs: Sequence[Any]) -> None:
        for out in outs:
            value = out.value
            if value is True:
                self.true[out.stream] = self.true.get(out.stream, 0) + 1
            elif value is False:
                self.false[out.stream] = self.false.get(out.stream, 0) + 1

    async def status(self, status: Any) -> None:
        """Spec swaps are not counted here (the session counts them)."""


class TrustCollector(Collector):
    """A trust checker's verdicts per stream (:class:`VerdictCounts`) and its session's
    counters. ``service``: a function returning the running
    ``trust_checker.service.TrustService`` (its ``session.stats`` and ``rejected``), or
    None while there is none."""

    def __init__(
        self,
        counts: VerdictCounts,
        service: Callable[[], Any],
        *,
        system: str,
        node: str,
        compute_node: str = "",
    ) -> None:
        self.counts = counts
        self._service = service
        self._labels = [system, compute_node, node]

    def describe(self) -> Iterable[Metric]:
        return []

    def collect(self) -> Iterator[Metric]:
        labels = ("system", "compute_node", "checker")
        verdicts = _counter("rap_trust_verdicts_total", (*labels, "stream", "value"))
        for value, counts in (("true", self.counts.true), ("false", self.counts.false)):
            for stream, n in sorted(_copy(counts).items()):
                verdicts.add_metric([*self._labels, stream, value], n)
        yield verdicts
        service = self._service()
        if service is None:
            return
        s = service.session.stats
        for name, value in (
            ("rap_trust_ticks_total", s.ticks),
            ("rap_trust_input_errors_total", s.input_errors),
            ("rap_trust_eval_errors_total", s.eval_errors),
            ("rap_trust_rejected_total", service.rejected),
        ):
            family = _counter(name, labels)
            family.add_metric(self._labels, value)
            yield family


# -- serving ---------------------------------------------------------------------------------


class MetricsServer:
    """A running metrics endpoint (``GET /metrics``); :meth:`close` stops it."""

    def __init__(self, server: Any, thread: Any) -> None:
        self._server = server
        self._thread = thread
        self.host: str = server.server_address[0]
        self.port: int = server.server_address[1]

    @property
    def url(self) -> str:
        return f"http://{self.host}:{self.port}/metrics"

    def close(self) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._thread.join(timeout=5)

    def __enter__(self) -> MetricsServer:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


def serve_metrics(registry: CollectorRegistry, host: str, port: int) -> MetricsServer:
    """Serve ``registry`` on ``http://host:port/metrics`` (port 0: a free one, see
    ``.port``), from a thread of its own. Raises ``OSError`` when the address cannot be
    bound."""
    from prometheus_client import start_http_server

    server, thread = start_http_server(port, addr=host, registry=registry)
    return MetricsServer(server, thread)


def parse_address(text: str) -> tuple[str, int]:
    """``HOST:PORT`` (``[::1]:9464`` for IPv6) as (host, port); ``ValueError`` saying
    what to write otherwise."""
    host, sep, port = text.rpartition(":")
    host = host.removeprefix("[").removesuffix("]")
    if not sep or not host or not port.isdigit() or not 0 <= int(port) < 65536:
        raise ValueError(f"{text!r} is not HOST:PORT - write e.g. 127.0.0.1:9464")
    return host, int(port)


def start_metrics(
    address: str | None, collectors: Iterable[Collector], *, what: str
) -> MetricsServer | None:
    """For a service's ``--metrics HOST:PORT``: a registry of ``collectors`` served
    there. An address that cannot be bound is logged as an error and the service goes on
    without metrics (its loop matters more than its metrics)."""
    if address is None:
        return None
    host, port = parse_address(address)
    registry = CollectorRegistry(auto_describe=False)
    for c in collectors:
        registry.register(c)
    try:
        server = serve_metrics(registry, host, port)
    except OSError as exc:
        log.error(
            "%s: metrics not served: cannot listen on %s (%s) - give another --metrics address",
            what,
            address,
            exc.strerror or exc,
        )
        return None
    log.info("%s: metrics on %s", what, server.url)
    return server


def check_metrics_option(text: str | None, option: str = "--metrics") -> str | None:
    """A command line's ``--metrics HOST:PORT`` checked (None: metrics off); an
    :class:`~rap_sdk.entry.EntryError` line otherwise."""
    from .entry import fail

    if text is None:
        return None
    try:
        parse_address(text)
    except ValueError as exc:
        raise fail(f"{option} {exc}") from None
    return text

"""Prometheus metrics of bridges, read at scrape time from their :class:`BridgeStats`.

    registry = CollectorRegistry(auto_describe=False)
    registry.register(BridgeCollector(lambda: bridges, system="demo"))
    with rap_sdk.metrics.serve_metrics(registry, "127.0.0.1", 9464):   # GET /metrics
        ...

or ``rap_sdk.metrics.start_metrics("127.0.0.1:9464", [BridgeCollector(...)], what=...)``.
Every metric is labelled with ``system``, ``compute_node``, ``bridge`` (its name),
``protocol`` and ``direction`` (in, out); :data:`METRICS` lists them.
"""

from __future__ import annotations

import contextlib
from collections.abc import Callable, Iterable, Iterator, Mapping

from prometheus_client.core import CounterMetricFamily, GaugeMetricFamily, Metric
from prometheus_client.registry import Collector

from .core import Bridge

__all__ = ["METRICS", "BridgeCollector"]

_LABELS = ("system", "compute_node", "bridge", "protocol", "direction")

METRICS: Mapping[str, str] = {
    "rap_bridge_sent_total": "Messages a bridge sent out of the fabric (confirmed by the "
    "other side at QoS >= 1).",
    "rap_bridge_received_total": "Frames a bridge received from outside, before any check.",
    "rap_bridge_published_total": "Messages a bridge published on the fabric.",
    "rap_bridge_rejected_total": "Messages a bridge refused (undecodable, wrong type, "
    "oversize, bad headers), by kind of reason.",
    "rap_bridge_dropped_total": "Messages the overflow policy dropped from a bridge's full buffer.",
    "rap_bridge_duplicates_total": "Messages a bridge saw twice (a resend) and passed over.",
    "rap_bridge_reconnects_total": "Connections a bridge made again after one was lost or refused.",
    "rap_bridge_disconnects_total": "Connections a bridge lost.",
    "rap_bridge_connect_failures_total": "Attempts to connect that failed.",
    "rap_bridge_fabric_failures_total": "Messages from outside the fabric refused to take.",
    "rap_bridge_connected": "1 while a bridge's link is up (a TCP server: listening).",
    "rap_bridge_buffered": "Messages waiting in a bridge's buffer.",
}
"""Every metric of the bridges, with its help text."""

_COUNTERS = {
    "rap_bridge_sent_total": "sent",
    "rap_bridge_received_total": "received",
    "rap_bridge_published_total": "published",
    "rap_bridge_dropped_total": "dropped",
    "rap_bridge_duplicates_total": "duplicates",
    "rap_bridge_reconnects_total": "reconnects",
    "rap_bridge_disconnects_total": "disconnects",
    "rap_bridge_connect_failures_total": "connect_failures",
    "rap_bridge_fabric_failures_total": "fabric_failures",
}


def _counter(name: str, labels: Iterable[str]) -> CounterMetricFamily:
    # prometheus_client adds the _total suffix itself
    return CounterMetricFamily(name.removesuffix("_total"), METRICS[name], labels=list(labels))


def _copy(counts: Mapping[str, int]) -> dict[str, int]:
    """A copy of a dict the event loop's thread may be growing (a scrape's thread reads)."""
    for _ in range(8):
        with contextlib.suppress(RuntimeError):  # "changed size during iteration"
            return dict(counts)
    return {}


class BridgeCollector(Collector):
    """The metrics of some bridges. ``bridges``: the bridges, or a function returning
    the current ones."""

    def __init__(
        self,
        bridges: Callable[[], Iterable[Bridge]] | Iterable[Bridge],
        *,
        system: str,
        compute_node: str = "",
    ) -> None:
        self._bridges = bridges
        self.system = system
        self.compute_node = compute_node

    def describe(self) -> Iterable[Metric]:
        return []  # collected at scrape time only

    def collect(self) -> Iterator[Metric]:
        counters = {name: _counter(name, _LABELS) for name in _COUNTERS}
        rejected = _counter("rap_bridge_rejected_total", (*_LABELS, "reason"))
        connected = GaugeMetricFamily(
            "rap_bridge_connected", METRICS["rap_bridge_connected"], labels=list(_LABELS)
        )
        buffered = GaugeMetricFamily(
            "rap_bridge_buffered", METRICS["rap_bridge_buffered"], labels=list(_LABELS)
        )
        bridges = self._bridges() if callable(self._bridges) else self._bridges
        for b in list(bridges):
            labels = [self.system, self.compute_node, b.name, b.spec.protocol, b.direction]
            st = b.stats
            for name, attr in _COUNTERS.items():
                value = getattr(st, attr)
                if attr == "duplicates":  # and the resends a link passed over itself
                    value += getattr(b.link, "duplicates", 0)
                counters[name].add_metric(labels, value)
            for reason, n in sorted(_copy(st.rejections.by_reason).items()):
                rejected.add_metric([*labels, reason], n)
            connected.add_metric(labels, 1.0 if st.connected else 0.0)
            buffered.add_metric(labels, st.buffered())
        yield from counters.values()
        yield from (rejected, connected, buffered)

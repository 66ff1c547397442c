"""Handler latency of one component: a cumulative histogram (for Prometheus) and the
recent calls (for p50/p99 in ``rap status``), kept at the cost of one bisect and two
list stores a call."""

from __future__ import annotations

from bisect import bisect_left
from typing import Final

__all__ = ["BUCKETS", "RECENT", "Latency"]

BUCKETS: Final = (
    0.000_05,
    0.000_1,
    0.000_25,
    0.000_5,
    0.001,
    0.002_5,
    0.005,
    0.01,
    0.025,
    0.05,
    0.1,
    0.25,
    0.5,
    1.0,
    2.5,
    5.0,
    10.0,
)
"""Upper bounds (s) of the histogram's buckets; one more bucket holds the rest (+Inf)."""
RECENT: Final = 1024
"""How many recent calls the percentiles are taken over (a power of two)."""
_MASK: Final = RECENT - 1


class Latency:
    """Seconds handler calls took. The runtime stores into it inline (one bisect, three
    stores: no method call on the handler's path); :meth:`observe` does the same."""

    __slots__ = ("counts", "n", "recent", "sum")

    def __init__(self) -> None:
        self.counts = [0] * (len(BUCKETS) + 1)
        """Calls per bucket (not cumulative); the last one is +Inf."""
        self.sum = 0.0
        self.recent = [0.0] * RECENT
        """The last calls, a ring indexed by ``n % RECENT``."""
        self.n = 0
        """Calls observed."""

    def observe(self, seconds: float) -> None:
        self.counts[bisect_left(BUCKETS, seconds)] += 1
        self.sum += seconds
        self.recent[self.n & _MASK] = seconds
        self.n += 1

    @property
    def count(self) -> int:
        return self.n

    def cumulative(self) -> list[tuple[str, int]]:
        """``(le, count)`` pairs as Prometheus histograms give them, ``+Inf`` last."""
        out: list[tuple[str, int]] = []
        total = 0
        for bound, n in zip((*map(str, BUCKETS), "+Inf"), self.counts, strict=True):
            total += n
            out.append((bound, total))
        return out

    def percentile(self, q: float) -> float:
        """The ``q`` quantile (0..1) of the recent calls, in seconds (0.0: no call yet)."""
        recent = sorted(self.recent[: min(self.n, RECENT)])
        if not recent:
            return 0.0
        return recent[min(len(recent) - 1, int(q * len(recent)))]

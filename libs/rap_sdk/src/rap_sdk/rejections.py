"""Counting what is refused, and saying so without flooding the logs.

Every reader of outside input (a node, the knowledge service and its replicas, the trust
checker) counts each rejection by reason and logs it rate-limited: the first on a key at
once, then at most one line per interval with how many came since.

    rejections = Rejections("analysis", log)
    rec = rejections.reject(key, "invalid rap.LaserScan/2 body: ...", source="x")
    if rec is not None:                       # due: publish it on rap/<system>/log/<node>
        await publish(rec)
    rejections.by_reason                      # Counter: reason kind -> count

:class:`Throttle` is the rate limit alone, for other repeated warnings (inbox drops,
lost liveliness).
"""

from __future__ import annotations

import logging
import re
import time
from collections import Counter
from collections.abc import Callable
from typing import Final

from rap_schemas import Rejection

__all__ = ["INTERVAL_NS", "Rejections", "Throttle", "reason_kind"]

INTERVAL_NS: Final = 1_000_000_000
"""One log line (and one rejection record) per key per second at most."""
MAX_KEYS: Final = 4096
"""Keys remembered for rate limiting; past it the oldest are forgotten."""
_NUMBER = re.compile(r"\d+")


def reason_kind(reason: str) -> str:
    """A reason without its specifics (where, which values): what ``by_reason`` counts.
    ``invalid rap.X/1 body: Expected `int`, got `str` - at `$.a[3]``` counts as
    ``invalid rap.X/N body: Expected `int`, got `str```."""
    head = reason.split(" - at ", 1)[0].split(" (", 1)[0]
    return _NUMBER.sub("N", head)[:160]


class Throttle:
    """Per key: the first event at once, then at most one per ``interval_ns`` carrying
    how many happened since."""

    __slots__ = ("_keys", "_now", "interval_ns")

    def __init__(
        self, interval_ns: int = INTERVAL_NS, now_ns: Callable[[], int] | None = None
    ) -> None:
        self.interval_ns = interval_ns
        self._now = now_ns or time.monotonic_ns
        self._keys: dict[str, list[int]] = {}  # key -> [last emitted, pending count]

    def hit(self, key: str) -> int:
        """Count one event on ``key``; returns how many to report now (0: not yet)."""
        st = self._keys.get(key)
        now = self._now()
        if st is None:
            if len(self._keys) >= MAX_KEYS:
                del self._keys[next(iter(self._keys))]
            self._keys[key] = [now, 0]
            return 1
        st[1] += 1
        if now - st[0] < self.interval_ns:
            return 0
        count, st[0], st[1] = st[1], now, 0
        return count

    def pending(self) -> dict[str, int]:
        """Counts not yet reported, per key; they are cleared (to report at shutdown)."""
        out = {k: st[1] for k, st in self._keys.items() if st[1]}
        for st in self._keys.values():
            st[1] = 0
        return out


class Rejections:
    """Rejection counting and rate-limited reporting for one reader (``who``)."""

    __slots__ = ("_clock", "_log", "_throttle", "by_reason", "total", "who")

    def __init__(
        self,
        who: str,
        log: logging.Logger,
        *,
        clock: Callable[[], int] | None = None,
        interval_ns: int = INTERVAL_NS,
    ) -> None:
        self.who = who
        self._log = log
        self._clock = clock or time.time_ns
        self._throttle = Throttle(interval_ns, self._clock)
        self.total = 0
        self.by_reason: Counter[str] = Counter()

    def reject(
        self, key: str, reason: str, *, source: str = "", type: str = ""
    ) -> Rejection | None:
        """Count one rejection; when a report is due, log it and return the record to
        publish (``count`` is how many since the last report on ``key``)."""
        self.total += 1
        self.by_reason[reason_kind(reason)] += 1
        count = self._throttle.hit(key)
        if not count:
            return None
        self._log.warning(
            "%s rejected %d sample(s) on %s: %s%s",
            self.who,
            count,
            key,
            reason,
            f" (from {source!r})" if source else "",
        )
        return Rejection(
            node=self.who,
            key=key,
            reason=reason,
            ts=self._clock(),
            count=count,
            source=source,
            type=type,
        )

    def flush(self) -> list[Rejection]:
        """Records for what was counted but not reported yet (at shutdown)."""
        out = []
        for key, count in self._throttle.pending().items():
            self._log.warning(
                "%s rejected %d more sample(s) on %s (see the earlier reason)",
                self.who,
                count,
                key,
            )
            out.append(
                Rejection(
                    node=self.who,
                    key=key,
                    reason="further samples rejected (see the earlier reason)",
                    ts=self._clock(),
                    count=count,
                )
            )
        return out

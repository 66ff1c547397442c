"""µs per tick of the SpecRunner against the same spec written by hand
(bench/trust/by_hand.py), in one process, on one generated trace.

Both run the whole trace in batches of ticks, interleaved round by round (a fresh
monitor and a fresh hand-written one each round, first round discarded as warm-up); a
sample is one batch's time divided by its ticks. The ratio is the median over rounds of
the two p50s measured back to back. Before timing, both must give identical outputs on
the whole trace (same streams, ticks, value types and values), or the bench fails.
"""

from __future__ import annotations

import gc
import statistics
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any, Protocol

from trust_checker.engine import Output, SpecRunner
from trust_checker.lang import load_spec

from ..report import pct


class Stepper(Protocol):
    def step(self, inputs: dict[str, Any], ts_ns: int | None = None) -> list[Output]: ...


def _rows(outs: Sequence[Output]) -> list[tuple[str, int, type, object]]:
    return [(o.stream, o.tick, type(o.value), o.value) for o in outs]


def check_same(
    spec: Path,
    by_hand: Callable[[], Stepper],
    trace: Sequence[dict[str, Any]],
    contender: Callable[[], Stepper] | None = None,
) -> int:
    """Both monitors (``contender``, by default the SpecRunner on ``spec``, and ``by_hand``)
    on the whole trace: AssertionError at the first tick they differ. Returns the number
    of outputs compared."""
    mon: Stepper = contender() if contender else SpecRunner(load_spec(spec))
    ref = by_hand()
    n = 0
    for i, rec in enumerate(trace):
        a, b = _rows(mon.step(rec)), _rows(ref.step(rec))
        if a != b:
            raise AssertionError(
                f"{spec.name}: the monitor and the hand-written one differ at tick {i} "
                f"(inputs {rec}): {a} != {b}"
            )
        n += len(a)
    return n


def _batches(obj: Stepper, trace: Sequence[dict[str, Any]], batch: int) -> list[float]:
    """ns per tick of each batch."""
    out: list[float] = []
    step = obj.step
    clock = time.perf_counter_ns
    for start in range(0, len(trace) - batch + 1, batch):
        chunk = trace[start : start + batch]
        t0 = clock()
        for rec in chunk:
            step(rec)
        out.append((clock() - t0) / batch)
    return out


def measure(
    spec: Path,
    by_hand: Callable[[], Stepper],
    trace: Sequence[dict[str, Any]],
    *,
    rounds: int,
    batch: int,
    contender: Callable[[], Stepper] | None = None,
) -> dict[str, Any]:
    """``contender`` (default: a fresh SpecRunner on ``spec``) against ``by_hand``; the
    contender's figures are under "monitor"."""
    outputs = check_same(spec, by_hand, trace, contender)
    parsed = load_spec(spec)
    fresh: Callable[[], Stepper] = contender or (lambda: SpecRunner(parsed))
    samples: dict[str, list[float]] = {"monitor": [], "by_hand": []}
    ratios: list[float] = []
    for r in range(rounds + 1):
        p50: dict[str, float] = {}
        order = ("monitor", "by_hand") if r % 2 else ("by_hand", "monitor")
        for name in order:
            obj: Stepper = fresh() if name == "monitor" else by_hand()
            gc.collect()
            got = _batches(obj, trace, batch)
            p50[name] = pct(got, 0.5)
            if r:  # round 0 warms up
                samples[name] += got
        if r:
            ratios.append(p50["monitor"] / p50["by_hand"])
    out: dict[str, Any] = {
        "spec": spec.name,
        "ticks": len(trace),
        "outputs_compared": outputs,
        "rounds": rounds,
        "batch_ticks": batch,
        "ratio_p50": round(statistics.median(ratios), 2),
        "ratios_per_round": [round(x, 2) for x in ratios],
    }
    for name, ns in samples.items():
        out[name] = {
            "p50_us": round(pct(ns, 0.5) / 1000, 3),
            "p99_us": round(pct(ns, 0.99) / 1000, 3),
            "ticks_per_s": round(1e9 / pct(ns, 0.5)),
            "n": len(ns),
        }
    return out

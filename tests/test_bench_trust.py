"""bench/trust's hand-written monitors and yardsticks compute what the SpecRunner does on
the specs they stand for (the bench checks this again on its full traces before timing)."""

from __future__ import annotations

from typing import Any

import pytest
from trust_checker.engine import Output

from bench.trust import ticks
from bench.trust.__main__ import FLOOR, STAGE_ORDER, STREAMS20, _Floor
from bench.trust.by_hand import (
    StageOrderAsSpecified,
    StageOrderByHand,
    StageOrderPersistent,
    Streams20ByHand,
    stage_trace,
    streams20_trace,
)


@pytest.mark.parametrize(
    ("spec", "by_hand", "contender"),
    [
        (STAGE_ORDER, StageOrderByHand, None),
        (STAGE_ORDER, StageOrderByHand, StageOrderAsSpecified),
        (STAGE_ORDER, StageOrderByHand, StageOrderPersistent),
        (STREAMS20, Streams20ByHand, None),
        (FLOOR, _Floor, None),
    ],
    ids=["stage_order", "straight_line", "persistent", "streams20", "floor"],
)
def test_same_outputs_as_the_monitor(spec: Any, by_hand: Any, contender: Any) -> None:
    # 300 cycles: past the spec's 256-cycle memory, so eviction is compared too
    trace = streams20_trace(3000) if spec == STREAMS20 else stage_trace(300)
    assert ticks.check_same(spec, by_hand, trace, contender) > 0.9 * len(trace)


def test_a_wrong_yardstick_is_caught() -> None:
    class OffByOne(StageOrderAsSpecified):
        def step(self, inputs: dict[str, Any], ts_ns: int | None = None) -> list[Output]:
            return [
                o._replace(value=not o.value) if o.tick == 40 else o
                for o in super().step(inputs, ts_ns)
            ]

    with pytest.raises(AssertionError, match="differ at tick 40"):
        ticks.check_same(STAGE_ORDER, StageOrderByHand, stage_trace(20), OffByOne)
